"""gpps: generalized perspective photometric stereo.

Normals, albedo, roughness and depth of an object from a few images taken by a
fixed camera under different lights, with non-Lambertian reflectance,
perspective cameras and near lights, on CPU or GPU (NVIDIA Warp + Taichi).

The coordinate frame is described once, in :mod:`gpps.camera`.
"""

from gpps._check import GppsWarning
from gpps._version import __version__  # noqa: F401  (gpps.__version__)
from gpps.camera import Orthographic, Perspective, camera_from_K
from gpps.lights import DirectionalLights, PointLights
from gpps.material import BRDF_NAMES, Material

_LAZY = {
    "reconstruct": "gpps.flows.reconstruction",
    "Reconstruction": "gpps.flows.reconstruction",
    "RONConfig": "gpps.flows.ron",
    "SolverConfig": "gpps.pipeline.solver",
    "Stream": "gpps.pipeline.stream",
    "StreamConfig": "gpps.pipeline.stream",
}


def __getattr__(name):
    """Lazy exports: ``gpps.reconstruct`` and ``gpps.Stream`` load the pipeline (scipy, Warp) on first use."""
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'gpps' has no attribute {name!r}")


__all__ = [
    "GppsWarning",
    "Orthographic",
    "Perspective",
    "camera_from_K",
    "DirectionalLights",
    "PointLights",
    "Material",
    "BRDF_NAMES",
    *_LAZY,
]
