"""gpps: generalized perspective photometric stereo.

Normals, albedo, roughness and depth of an object from a few images taken by a
fixed camera under different lights, with non-Lambertian reflectance,
perspective cameras and near lights, on CPU or GPU (NVIDIA Warp + Taichi).

The coordinate frame is described once, in :mod:`gpps.camera`.

The public face is this module's ``__all__`` (value types at once, the flows, configs and stages lazily)
and the :mod:`gpps.io` package (readers, writers, output-folder rules).  The other subpackages are the
layers behind them (:mod:`gpps.kernels`, :mod:`gpps.host`, :mod:`gpps.pipeline`, :mod:`gpps.flows`,
:mod:`gpps.nn`): internal, their module paths may change; names with a leading underscore are private.
"""

import importlib

from gpps._check import GppsWarning
from gpps._version import __version__  # noqa: F401  (gpps.__version__)
from gpps.camera import Orthographic, Perspective, camera_from_K
from gpps.lights import DirectionalLights, PointLights
from gpps.material import BRDF_NAMES, Material

_LAZY = {
    # whole reconstructions (gpps.flows)
    "reconstruct": "gpps.flows.reconstruction",
    "Reconstruction": "gpps.flows.reconstruction",
    "Reconstructor": "gpps.flows.reconstruction",
    "RONConfig": "gpps.flows.ron",
    "solve_normals": "gpps.flows.photometric",
    "integrate_normals": "gpps.flows.integrate",
    "solve_uncalibrated": "gpps.flows.uncalibrated",
    "UncalibratedConfig": "gpps.flows.uncalibrated",
    "reconstruct_single": "gpps.flows.single",
    "SingleConfig": "gpps.flows.single",
    "SingleNet": "gpps.nn.model",
    "reconstruct_folder": "gpps.flows.folder",
    "FolderConfig": "gpps.flows.folder",
    "FolderResult": "gpps.flows.folder",
    "reconstruct_many": "gpps.batch",
    "calibrate_lights": "gpps.flows.calibration",
    "LightCalibration": "gpps.flows.calibration",
    "run_demo": "gpps.flows.demo",
    # synthetic captures
    "render": "gpps.flows.synthetic",
    "render_dataset": "gpps.flows.synthetic",
    "default_lights": "gpps.flows.synthetic",
    "make_scene": "gpps.host.scenes",
    "SCENE_NAMES": "gpps.host.scenes",
    # errors against ground truth
    "angular_error": "gpps.host.metrics",
    "normal_errors": "gpps.host.metrics",
    # stages and their settings (gpps.pipeline)
    "depth_error": "gpps.host.metrics",
    "SolverConfig": "gpps.pipeline.solver",
    "PixelSolver": "gpps.pipeline.solver",
    "Renderer": "gpps.pipeline.render",
    "Integrator": "gpps.pipeline.integration",
    "IntegratorConfig": "gpps.pipeline.integration",
    "CuckooConfig": "gpps.pipeline.cuckoo",
    "Stream": "gpps.pipeline.stream",
    "StreamConfig": "gpps.pipeline.stream",
}


def __getattr__(name):
    """Lazy exports: ``gpps.reconstruct`` and ``gpps.Stream`` load the pipeline (scipy, Warp) on first use,
    so ``import gpps`` (and ``gpps --help``) costs numpy and the value types only."""
    if name in _LAZY:
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
