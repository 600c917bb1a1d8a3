"""gpps: generalized perspective photometric stereo.

Normals, albedo, roughness and depth of an object from a few images taken by a
fixed camera under different lights, with non-Lambertian reflectance,
perspective cameras and near lights, on CPU or GPU (NVIDIA Warp + Taichi).

The coordinate frame is described once, in :mod:`gpps.camera`.
"""

from gpps.camera import Orthographic, Perspective, camera_from_K
from gpps.lights import DirectionalLights, PointLights
from gpps.material import BRDF_NAMES, Material

__version__ = "0.1.0"

__all__ = [
    "Orthographic",
    "Perspective",
    "camera_from_K",
    "DirectionalLights",
    "PointLights",
    "Material",
    "BRDF_NAMES",
]
