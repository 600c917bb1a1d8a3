"""Calibrated photometric stereo on arrays: normals and albedo from N >= 3 images.

Thin API over :class:`gpps.pipeline.solver.PixelSolver`::

    res = solve_normals(images, mask, lights, camera=cam, material=mat, solver="lm")
    res.normals  # (H, W, 3) unit normals in the gpps frame, 0 outside the mask

Methods (seed chapters 3-4):

* ``solver="none"``: Woodham's Lambertian least squares (the baseline).
* ``solver="lm" | "dogleg" | "bfgs"``: per-pixel nonlinear least squares on
  ``f_h = I_h - model`` (4.2) for the material's reflectance model
  (Lambertian, Phong, Blinn-Phong, Cook-Torrance, Ashikhmin-Shirley) with
  analytic Jacobians, started from the least-squares normal and several
  other starts.  The albedo is eliminated by variable projection (faster and
  better conditioned than solving for it jointly).

For a perspective camera the normal is the same unknown; the perspective
log-depth gradient the integrator needs is :func:`gpps.perspective.normals_to_gradient`
(PPN, 3.2-3.3).  Near point lights need a depth estimate (2.30-2.31).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from gpps._check import as_array, as_mask
from gpps.camera import Orthographic, Perspective
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.solver import PixelSolver, SolverConfig

__all__ = ["PSResult", "solve_normals", "reproject", "SolverConfig"]


@dataclass
class PSResult:
    """Output of :func:`solve_normals`.

    Attributes:
        normals: (H, W, 3) float32 unit normals (gpps frame), zeros outside the mask.
        albedo: (H, W, 3) float32 RGB albedo kd.
        residual: (H, W) float32 RMS weighted residual per observation and channel.
        iterations: (H, W) int32 cost evaluations spent (all starts and rounds).
        flags: (H, W) int32 bits ``gpps.pipeline.solver.FLAG_*`` (ill-conditioned
            lights, fewer than 3 lit observations, not converged, ...).
        cond: (H, W) float32 condition number of the valid light directions (3.13).
        weights: (N, H, W) float32 final observation weights (0: dropped; -1: dark, a one-sided
            attached-shadow term that only penalises a model brighter than the observation).
        mask: (H, W) bool.
        timings: seconds: ``setup``, ``solve`` (device), ``total``.
        config: the solver settings used.
        material: the reflectance model used.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    flags: np.ndarray
    cond: np.ndarray
    weights: np.ndarray
    mask: np.ndarray
    timings: dict = field(default_factory=dict)
    config: SolverConfig | None = None
    material: Material | None = None


def check_inputs(images, mask, lights, camera=None):
    """Check the arguments shared by :func:`solve_normals` and :func:`gpps.reconstruct`.

    Returns:
        ``(images, mask, lights, camera)``: images as an array of shape
        (N, H, W, 3) or (N, H, W), the (H, W) bool mask, the lights, and the
        camera (orthographic when None).
    """
    img = as_array("images", images)
    if img.ndim not in (3, 4) or (img.ndim == 4 and img.shape[-1] not in (1, 3)):
        raise ValueError(f"images: expected shape (N, H, W, 3) or (N, H, W), got {img.shape}")
    n, h, w = img.shape[:3]
    m = as_mask("mask", mask, (h, w))
    if not isinstance(lights, (DirectionalLights, PointLights)):
        raise TypeError(f"lights: expected gpps.lights.DirectionalLights or PointLights, got {type(lights).__name__}")
    if len(lights) != n:
        raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
    camera = Orthographic() if camera is None else camera
    if not isinstance(camera, (Orthographic, Perspective)):
        raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
    return img, m, lights, camera


def solve_normals(
    images,
    mask,
    lights,
    *,
    camera=None,
    material: Material | None = None,
    solver: str = "lm",
    depth=None,
    robust: str | None = None,
    valid=None,
    init_normals=None,
    config: SolverConfig | None = None,
    device=None,
    progress=None,
    **options,
) -> PSResult:
    """Per-pixel calibrated photometric stereo.

    Args:
        images: (N, H, W, 3) RGB or (N, H, W) grey images >= 0, N >= 3, already
            divided by the light intensities when ``lights`` has unit intensities
            (the model uses ``lights.intensities`` as the radiance).
        mask: (H, W) bool, pixels to solve.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N).
        camera: :class:`Orthographic` (default) or :class:`Perspective`.
        material: reflectance model and per-scene parameters (default Lambertian).
        solver: ``"lm"``, ``"dogleg"``, ``"bfgs"`` or ``"none"`` (Woodham least squares).
        depth: (H, W) depth estimate (scene units, > 0): required for point lights.
        robust: None / ``"none"``, ``"huber"`` or ``"cauchy"`` (IRLS).
        valid: optional (N, H, W) bool of observations to use (e.g. not saturated).
        init_normals: (H, W, 3) warm start (with ``warm_start=True``).
        config: a full :class:`SolverConfig` (then ``solver``, ``robust`` and
            ``options`` must be left at their defaults).
        device: Warp device (None: CUDA if present).
        progress: optional ``progress(done, total, message)`` callback.
        **options: further :class:`SolverConfig` fields (``starts``, ``max_iters``,
            ``shadow_threshold``, ``saturation``, ...).

    Returns:
        :class:`PSResult`.

    Raises:
        ValueError: wrong shapes, non-finite values, fewer than 3 lights or
            collinear/coplanar light directions (before any solve).
    """
    t0 = time.perf_counter()
    if config is None:
        config = SolverConfig(solver=solver, robust=robust or "none", **options)
    elif not isinstance(config, SolverConfig):
        raise TypeError(f"config: expected SolverConfig, got {type(config).__name__}")
    elif options or solver != "lm" or robust is not None:
        raise ValueError("config: pass either config or solver/robust/options, not both")
    img, m, lights, camera = check_inputs(images, mask, lights, camera)
    n, h, w = img.shape[:3]
    material = Material("lambertian", ks=0.0) if material is None else material
    if not isinstance(material, Material):
        raise TypeError(f"material: expected gpps.material.Material, got {type(material).__name__}")
    if progress:
        progress(0, 3, "setup")
    ps = PixelSolver((n, h, w), camera, lights, material, config, device=device)
    ps.upload(img, m, depth=depth, valid=valid, init_normals=init_normals)
    t1 = time.perf_counter()
    if progress:
        progress(1, 3, "solve")
    ps.launch()
    from gpps._runtime import warp

    warp().synchronize_device(ps.device)
    t2 = time.perf_counter()
    out = ps.fetch()
    if progress:
        progress(3, 3, "done")
    t3 = time.perf_counter()
    return PSResult(
        normals=out["normals"],
        albedo=out["albedo"],
        residual=out["residual"],
        iterations=out["iterations"],
        flags=out["flags"],
        cond=out["cond"],
        weights=out["weights"],
        mask=m,
        timings={"setup": t1 - t0, "solve": t2 - t1, "total": t3 - t0},
        config=config,
        material=material,
    )


def reproject(result: PSResult, lights, *, camera=None, depth=None, device=None) -> np.ndarray:
    """Re-render the images (N, H, W, 3) from a result's normals and albedo with its material.

    Args:
        result: a :class:`PSResult`.
        lights: the lights used to solve.
        camera: the camera used (default orthographic).
        depth: (H, W) depth (needed for point lights; default ones).
    """
    from gpps.pipeline.render import Renderer

    h, w = result.mask.shape
    camera = Orthographic() if camera is None else camera
    dep = np.ones((h, w), np.float32) if depth is None else as_array("depth", depth, shape=(h, w))
    r = Renderer((h, w), camera, lights, result.material, device=device)
    nrm = result.normals.copy()
    bad = result.mask & (np.linalg.norm(nrm, axis=-1) < 0.5)
    nrm[bad] = (0.0, 0.0, 1.0)
    return r.render(np.where(result.mask, dep, 1.0), result.mask, np.maximum(result.albedo, 0.0), normals=nrm).numpy()
