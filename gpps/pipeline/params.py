"""Host-side builders of the per-scene Warp structs (camera, lights, material)."""

from __future__ import annotations

import numpy as np

from gpps._runtime import warp
from gpps.camera import Orthographic, Perspective
from gpps.kernels.brdf import (
    DIRECTIONAL,
    POINT,
    CameraParams,
    LightParams,
    MaterialParams,
)
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.names import LIGHTS_PARALLEL_MIN, LIGHTS_PARALLEL_PAIRS_PER_IMAGE


def camera_params(camera, shape: tuple[int, int]):
    """A :class:`gpps.kernels.brdf.CameraParams` for ``camera`` and image ``shape = (H, W)``."""
    wp = warp()

    c = CameraParams()
    if isinstance(camera, Perspective):
        c.perspective = 1
        c.fx, c.fy = camera.fx, camera.fy
        c.cx, c.cy = camera.principal_point()
        c.pixel_size = 1.0
    elif isinstance(camera, Orthographic):
        c.perspective = 0
        c.fx = c.fy = 1.0
        c.cx, c.cy = camera.principal_point(shape)
        c.pixel_size = camera.pixel_size
    else:
        raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
    del wp
    return c


def material_params(material: Material):
    if not isinstance(material, Material):
        raise TypeError(f"material: expected gpps.Material, got {type(material).__name__}")
    m = MaterialParams()
    m.model = material.device_tag
    m.ks = material.ks
    m.shininess = material.shininess
    m.roughness = material.roughness
    m.f0 = material.f0
    m.eta_u = material.eta_u
    m.eta_v = material.eta_v
    return m


def light_params(lights, device: str):
    """A :class:`gpps.kernels.brdf.LightParams` with its arrays on ``device``.

    The returned struct references device arrays; keep it alive while kernels use it.
    """
    wp = warp()

    lp = LightParams()
    n = len(lights)
    if isinstance(lights, DirectionalLights):
        lp.kind = int(DIRECTIONAL)
        vec = lights.directions
        axes = np.tile([0.0, 0.0, -1.0], (n, 1))
        mu = np.zeros(n)
    elif isinstance(lights, PointLights):
        lp.kind = int(POINT)
        vec, axes, mu = lights.positions, lights.axes, lights.mu
    else:
        raise TypeError(f"lights: expected DirectionalLights or PointLights, got {type(lights).__name__}")
    lp.count = n
    lp.vec = wp.array(np.asarray(vec, np.float32), dtype=wp.vec3, device=device)
    lp.intensity = wp.array(np.asarray(lights.intensities, np.float32), dtype=wp.vec3, device=device)
    lp.axis = wp.array(np.asarray(axes, np.float32), dtype=wp.vec3, device=device)
    lp.mu = wp.array(np.asarray(mu, np.float32), dtype=wp.float32, device=device)
    return lp


def resolve_parallel(parallel: str, device: str, images: int) -> str:
    """The build(s) a batched solve needs (:data:`gpps.names.ParallelName`): ``"auto"`` stays ``"auto"`` (chosen
    per launch by :func:`uses_lanes`) only on CUDA with :data:`gpps.names.LIGHTS_PARALLEL_MIN` images or more,
    else it is ``"pixels"``; ``"pixels"`` and ``"lights"`` as asked."""
    if parallel == "auto" and not (str(device).startswith("cuda") and images >= LIGHTS_PARALLEL_MIN):
        return "pixels"
    return parallel


def uses_lanes(parallel: str, images: int, pairs: int) -> bool:
    """Whether a launch of ``pairs`` solves (pixels, or candidate x pixel pairs) over ``images`` lights runs the
    lights-parallel build, for a :func:`resolve_parallel` choice: ``"auto"`` from at most
    ``LIGHTS_PARALLEL_PAIRS_PER_IMAGE x images`` pairs (a latency-bound launch; measured in :mod:`gpps.names`)."""
    if parallel != "auto":
        return parallel == "lights"
    return pairs <= LIGHTS_PARALLEL_PAIRS_PER_IMAGE * images
