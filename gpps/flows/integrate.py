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

import dataclasses

import numpy as np

from gpps._check import check_choice
from gpps.host.creases import crease_edges, crease_pieces, separating_cuts
from gpps.names import SLITS_NAMES
from gpps.pipeline.integration import (
    IntegrationResult,
    Integrator,
    IntegratorConfig,
    Progress,
)

__all__ = ["integrate_normals", "integrate_normals_creases", "IntegrationResult", "Integrator", "IntegratorConfig"]


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
    fields = {f.name for f in dataclasses.fields(IntegratorConfig)}
    unknown = sorted(set(options) - fields)
    if unknown:
        raise TypeError(f"{unknown[0]}: not an option of integrate_normals; expected IntegratorConfig's fields "
                        f"{sorted(fields)}")
    cfg = IntegratorConfig(solver=solver, tol=tol, max_iter=max_iter, bilateral=bilateral, weighting=weighting,
                           **options)
    integ = Integrator(mask, camera=camera, config=cfg, device=device)
    try:
        return integ.run(normals, warm_start=warm_start, reference_depth=reference_depth, progress=progress)
    finally:
        integ.close()


def integrate_normals_creases(
    normals,
    mask,
    *,
    camera=None,
    floor_deg: float = 2.0,
    z: float = 4.0,
    threshold_deg: float | None = None,
    slits: str = "keep",
    reference_depth: float | None = None,
    warm_start=None,
    device: str = "auto",
    progress: Progress | None = None,
    **options,
):
    """BiNI with the normal map's crease edges cut, the pieces stitched back (an opt-in alternative to
    ``integrate_normals(bilateral=True)``, not a default).

    1. :func:`gpps.host.creases.crease_edges`: edges where the normals' second difference spikes
       (``max(floor_deg, z sigma)``, peak edge only, the normal changing across the edge);
    2. device BiNI (:class:`gpps.pipeline.integration_bini.BilateralIntegrator`) with those edges as missing
       neighbours, so each piece is integrated on its own and BiNI's weights still cut the jumps inside it;
    3. the pieces' constants (depth offsets, orthographic; log-depth offsets, perspective) from the cut edges
       (:func:`gpps.host.creases.stitch_cut_pieces`): least squares with mid-normal targets (``cut_stitch="mid"``,
       the default) or BiNI's bilateral energy of the cut edges (``cut_stitch="bini"``).

    Without a crease the result is ``integrate_normals(bilateral=True)``'s, bitwise.  A cut edge whose two sides
    stay in one piece (a crease line that ends inside the surface) is a slit: the stitch does not see it and
    BiNI loses the coupling across it (``slits="drop"`` keeps only the separating cuts).

    Measured (perf/results/integration_creases_bini_cut_cpu.json): the ray-cast discontinuity suite within 1e-3
    of the depth range per piece at 128 px (both cameras), not at 48 px on the spheres (BiNI's own one-sided
    discretisation, 2e-3 to 1.4e-2); on the DiLiGenT maps NOT within 1.1x of BiNI's published errors (buddha
    1.18x, cow 2.15x, goblet 1.13x), hence not a default.  The options do not fix that
    (perf/results/integration_creases_stitch_cpu.json): ``slits="drop"`` with ``cut_stitch="bini"`` gives
    bear 1.18x (its 775 slits had given 0.29x), buddha 0.87x, cow 1.00x, goblet 0.99x, pot1 0.99x, pot2 1.00x,
    and loses the suite's 1e-3 at 128 px on the overlapping spheres (6.3e-3 perspective): slits along occluding
    rims were helping.

    Args:
        normals, mask, camera, reference_depth, warm_start, device, progress: as :func:`integrate_normals`.
        floor_deg, z, threshold_deg: the crease test (:func:`gpps.host.creases.crease_edges`).
        slits: ``"keep"`` every crease cut, or ``"drop"`` the slits first
            (:func:`gpps.host.creases.separating_cuts`: only cuts between different pieces reach BiNI; the
            pieces are the same).
        **options: further :class:`IntegratorConfig` fields (BiNI's ``bilateral_k`` ..., ``min_nz``,
            ``cut_stitch``).

    Returns:
        ``(result, creases)``: the :class:`IntegrationResult` and a dict with ``cut_x``, ``cut_y`` ((H, W) bool
        cut edges), ``pieces`` ((H, W) int labels, 0 outside the result's mask), ``n_pieces``, ``cut_edges``,
        ``threshold_deg``, ``sigma_deg``, ``slits`` (the cut edges dropped as slits).

    Raises:
        ValueError: bad shapes or values, naming the argument.
    """
    check_choice("slits", slits, SLITS_NAMES)
    cfg = IntegratorConfig(bilateral=True, weighting="normal", **options)
    integ = Integrator(mask, camera=camera, config=cfg, device=device)
    try:
        cut_x, cut_y, info = crease_edges(normals, integ.mask, floor_deg=floor_deg, z=z, threshold_deg=threshold_deg)
        n_cut = int(cut_x.sum() + cut_y.sum())
        if slits == "drop":
            # the pixels BiNI integrates (the mask less invalid / back-facing normals): separation in its graph
            cut_x, cut_y, _, _ = separating_cuts(integ._check_normals(normals)[1], cut_x, cut_y)
        res = integ.run(normals, warm_start=warm_start, reference_depth=reference_depth, progress=progress,
                        cuts=(cut_x, cut_y))
    finally:
        integ.close()
    v = res.mask
    kx = np.zeros_like(v)
    ky = np.zeros_like(v)
    kx[:, :-1] = v[:, :-1] & v[:, 1:] & ~cut_x[:, :-1]
    ky[:-1] = v[:-1] & v[1:] & ~cut_y[:-1]
    pieces, npc = crease_pieces(v, kx, ky)
    n_kept = int(cut_x.sum() + cut_y.sum())
    return res, dict(cut_x=cut_x, cut_y=cut_y, pieces=pieces, n_pieces=npc, cut_edges=n_kept, slits=n_cut - n_kept,
                     **info)
