"""Normal integration: normal map to depth map (4.20), orthographic or perspective.

A thin functional wrapper of :class:`gpps.pipeline.integration.Integrator`;
use the class directly to integrate many normal maps over one mask (fields
are allocated once, the previous depth can warm-start the next solve).

Example::

    from gpps.camera import Perspective
    from gpps.flows.integrate import integrate_normals
    res = integrate_normals(normals, mask, camera=Perspective(K), reference_depth=1500.0)
    res.depth   # (H, W) float32, 0 outside res.mask
"""

from __future__ import annotations

from gpps.pipeline.integration import (
    IntegrationResult,
    Integrator,
    IntegratorConfig,
    Progress,
)

__all__ = ["integrate_normals", "IntegrationResult", "Integrator", "IntegratorConfig"]


def integrate_normals(
    normals,
    mask,
    *,
    camera=None,
    solver: str = "multigrid",
    tol: float = 1e-5,
    max_iter: int | None = None,
    bilateral: bool = False,
    weighting: str | None = None,
    reference_depth: float | None = None,
    warm_start=None,
    device: str = "auto",
    progress: Progress | None = None,
    **options,
) -> IntegrationResult:
    """Integrate a normal map into a depth map over a mask.

    Minimises (4.20) ``||grad u - g||^2`` over the mask with natural boundary
    conditions (``Laplace(u) = div(g)``, Neumann on the mask border); each
    connected component gets its own constant.  Orthographic: ``u`` is the
    depth, ``g = (p, q)`` from the normals.  Perspective: ``u = log(depth)``
    with the PPN gradient field (3.2)-(3.3), ``depth = exp(u)`` up to one scale.

    Args:
        normals: (H, W, 3) normals, gpps frame (x right, y up, z toward the
            camera; visible normals face the camera).  NaN, zero-length and
            back-facing normals are dropped (``result.n_invalid``).
        mask: (H, W) bool pixels to integrate.
        camera: :class:`gpps.camera.Orthographic` (default, pixel size 1) or
            :class:`gpps.camera.Perspective`.
        solver: ``"multigrid"`` (Taichi, MG-preconditioned CG), ``"jacobi"``
            (Taichi), ``"direct"`` (scipy sparse LU) or ``"dct"`` (scipy,
            full rectangles only).
        tol: relative residual of the normal equations to reach.
        max_iter: iteration cap (``None``: solver default).
        bilateral: bilateral normal integration (BiNI, Cao et al. ECCV 2022) on
            the device instead of the Poisson solve: keeps depth
            discontinuities (occluding rims, overlapping objects); BiNI's
            parameters (``bilateral_k=2``, energy tolerance ``1e-4``, inner CG
            tolerance ``1e-3``, see :class:`IntegratorConfig`).  The mode for
            measured normal maps (``gpps integrate``'s default); ``solver``,
            ``tol``, ``max_iter`` and ``weighting`` then do not apply.
        weighting: Poisson: ``"uniform"`` or ``"normal"`` (BiNI N_z^2 confidence);
            ``None`` = ``"normal"`` when ``bilateral`` else ``"uniform"``.
        reference_depth: mean depth per component (scene units); ``None``
            leaves orthographic depth with mean 0 and perspective depth with
            mean log-depth 0 (the caller fixes the scale).
        warm_start: (H, W) depth to start from.
        device: ``"auto"``, ``"cpu"`` or ``"cuda:0"`` (Taichi solvers).
        progress: optional ``progress(done, total, message)`` callback.
        **options: further :class:`IntegratorConfig` fields (Poisson:
            ``robust`` ``"curl"`` or ``"cauchy"``, ``min_nz``, ``dtype`` ...;
            BiNI: ``bilateral_k``, ``bilateral_tol`` ...).

    Returns:
        :class:`IntegrationResult`; ``depth`` is (H, W) float32 with 0 outside
        ``result.mask`` (not NaN), ``result.mask`` the pixels integrated.

    Raises:
        ValueError: bad shapes or values, naming the argument.
    """
    if weighting is None:
        weighting = "normal" if bilateral else "uniform"
    cfg = IntegratorConfig(solver=solver, tol=tol, max_iter=max_iter, bilateral=bilateral, weighting=weighting,
                           **options)
    integ = Integrator(mask, camera=camera, config=cfg, device=device)
    try:
        return integ.run(normals, warm_start=warm_start, reference_depth=reference_depth, progress=progress)
    finally:
        integ.close()
