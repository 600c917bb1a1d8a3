"""DGMC's solved front on the device (seed 4.16-4.18): the sources, and one ring's solve mask, starts and merge.

Device math only; the stage :class:`gpps.pipeline.front.DeviceFront` owns the buffers and launches these around
:meth:`gpps.pipeline.solver.PixelSolver.step`.  The rings come from the host, once
(:func:`gpps.host.dgmc.front_rings`), as a list of flat pixel indices ``y * W + x`` sorted by ring (``pixels``)
and a level map (the ring of each ring pixel, 0 on the solved pixels outside the highlights, more than any ring
elsewhere); ring ``k`` is the slice ``[start, start + count)`` of the list, and every kernel here runs one thread
per listed pixel (the work of a ring is its size, not the image's):

* :func:`front_source_kernel` (once, every ring pixel): the source of each ring pixel, the seed's rule
  (4.17-4.18) among its 8 neighbours solved before its ring;
* :func:`scatter_mask_kernel`: the solver's (cleared) mask is set on a ring (:meth:`PixelSolver.select_pixels`);
* :func:`front_start_kernel`: each ring pixel starts from its source's current normal;
* :func:`front_write_back_kernel` (after the last ring, one thread a pixel): the merged solution back into the
  solver's outputs (RON's device rounds read them there), the front's evaluations added to the solver's;
* :func:`front_source_normals_kernel` (every ring pixel): the merged normal of each ring pixel's source;
* :func:`front_merge_kernel`: the ring's solve replaces the current solution where it ranks better, the rule of
  :func:`gpps.host.merge.ranks_better` (a lower residual on a pixel without ``FLAG_FEW_OBSERVATIONS``), or
  everywhere on the ring without ``keep_better``.  Unlike :func:`gpps.kernels.merge.merge_saved_kernel` (the same
  comparison) it writes into the front's own buffers, records the front solve's own evaluations (not the sum of
  both solves') and which pixels it won, and leaves the solver's outputs alone.

Only the starts depend on the earlier rings' results, so the sources are chosen for all rings at once; the
choice is the former host loop's (:func:`gpps.host.dgmc.select_sources` on each ring pixel's solved neighbours,
edge ones first): the same candidates in the same order, the same float64 tests with the tolerance multiplied
step by step in the same order, the first candidate when none qualifies; tests/test_front.py compares them.
"""

import warp as wp

__all__ = ["front_source_kernel", "scatter_mask_kernel", "front_start_kernel", "front_merge_kernel",
           "front_write_back_kernel", "front_source_normals_kernel", "curvature_in_kernel"]


@wp.kernel(enable_backward=False)
def curvature_in_kernel(src: wp.array2d(dtype=wp.float64), out: wp.array2d(dtype=wp.float64)):
    """out = src rounded to float32 (and back): a curvature map taken on the device holds the values the host's
    float32 maps (:class:`gpps.pipeline.dgmc.DGMCStart`) would give."""
    i, j = wp.tid()
    out[i, j] = wp.float64(wp.float32(src[i, j]))


@wp.func
def edge_first_offset(r: int) -> wp.vec2i:
    """The ``r``-th 8-neighbour offset ``(di, dj)``, edge neighbours first: (-1, 0), (0, -1), (0, 1), (1, 0), then
    the corners (-1, -1), (-1, 1), (1, -1), (1, 1) (the host's order)."""
    di = int(0)
    dj = int(0)
    if r == 0:
        di = -1
    elif r == 1:
        dj = -1
    elif r == 2:
        dj = 1
    elif r == 3:
        di = 1
    else:
        di = -1
        dj = -1
        if r >= 6:
            di = 1
        if r % 2 == 1:
            dj = 1
    return wp.vec2i(di, dj)


@wp.kernel(enable_backward=False)
def front_source_kernel(
    pixels: wp.array(dtype=wp.int32),
    level: wp.array2d(dtype=wp.int32),
    gc: wp.array2d(dtype=wp.float64),
    mc: wp.array2d(dtype=wp.float64),
    curvatures: int,
    tolerance: wp.float64,
    widen_factor: wp.float64,
    widen_steps: int,
    sources: wp.array(dtype=wp.int32),
):
    """Source of each ring pixel ``p`` (dim P): among its 8 neighbours ``q`` solved before its ring
    (``level[q] < level[p]``), edge ones first, the first with ``|GC_q - GC_p| <= t |GC_p|`` and
    ``|MC_q - MC_p| <= t |MC_p|`` (4.17-4.18) at ``t = tolerance``, then ``t`` times ``widen_factor`` up to
    ``widen_steps`` times; else (or with ``curvatures`` 0) the first of them.

    Args:
        pixels: (P,) flat indices of the ring pixels.
        level: (H, W) the ring of each ring pixel; 0 on solved pixels; more than any ring elsewhere.
        gc, mc: (H, W) Gaussian and mean curvature (4.16), read when ``curvatures`` is 1.
        curvatures: 1: the test of 4.17-4.18; 0: the nearest solved neighbour.
        tolerance, widen_factor, widen_steps: as :class:`gpps.host.dgmc.DGMCConfig`.
        sources: (P,) out: the flat index of each pixel's source (-1 with no solved neighbour: never for a ring
            pixel).
    """
    t = wp.tid()
    h = level.shape[0]
    w = level.shape[1]
    p = pixels[t]
    i = p // w
    j = p % w
    k = level[i, j]
    gp = gc[i, j]
    mp = mc[i, j]
    first = int(-1)
    found = int(-1)
    tt = tolerance
    for stp in range(widen_steps + 1):
        if found < 0:
            for r in range(8):
                off = edge_first_offset(r)
                a = i + off[0]
                b = j + off[1]
                if found < 0 and a >= 0 and a < h and b >= 0 and b < w:
                    if level[a, b] < k:
                        if first < 0:
                            first = a * w + b
                        if curvatures != 0:
                            if wp.abs(gc[a, b] - gp) <= tt * wp.abs(gp) and wp.abs(mc[a, b] - mp) <= tt * wp.abs(mp):
                                found = a * w + b
            tt = tt * widen_factor
    if found < 0:
        found = first
    sources[t] = found


@wp.kernel(enable_backward=False)
def scatter_mask_kernel(pixels: wp.array(dtype=wp.int32), start: int, width: int, mask: wp.array2d(dtype=wp.uint8)):
    """``mask = 1`` on the flat pixel indices ``pixels[start : start + count]`` (dim ``count``).

    Args:
        pixels: (P,) flat pixel indices ``y * W + x``.
        start: first entry of the slice.
        width: W.
        mask: (H, W) out: 1 on the slice (the caller cleared it before).
    """
    t = wp.tid()
    p = pixels[start + t]
    mask[p // width, p % width] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def front_start_kernel(
    pixels: wp.array(dtype=wp.int32),
    sources: wp.array(dtype=wp.int32),
    start: int,
    width: int,
    current: wp.array2d(dtype=wp.vec3),
    normals: wp.array2d(dtype=wp.vec3),
):
    """Start normals of one ring: ``normals[p] = current[q]`` for each pixel ``p`` of the slice and its source ``q``
    (dim ``count``).

    Args:
        pixels: (P,) flat indices of the ring pixels, sorted by ring.
        sources: (P,) flat index of each one's source (solved in an earlier ring or outside the highlights).
        start: first entry of the ring's slice.
        width: W.
        current: (H, W) the current (merged) normals.
        normals: (H, W) out on the ring: its start normals (the solver's ``normals`` buffer).
    """
    t = wp.tid()
    p = pixels[start + t]
    q = sources[start + t]
    normals[p // width, p % width] = current[q // width, q % width]


@wp.kernel(enable_backward=False)
def front_merge_kernel(
    pixels: wp.array(dtype=wp.int32),
    start: int,
    width: int,
    keep_better: int,
    few: int,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
    cur_normals: wp.array2d(dtype=wp.vec3),
    cur_albedo: wp.array2d(dtype=wp.vec3),
    cur_residual: wp.array2d(dtype=wp.float32),
    cur_flags: wp.array2d(dtype=wp.int32),
    front_iterations: wp.array2d(dtype=wp.int32),
    won: wp.array2d(dtype=wp.uint8),
):
    """Merge one ring's solve into the current solution (dim ``count``; pixels off the ring untouched).

    On each pixel of the slice: ``front_iterations`` = the solve's evaluations; the solve replaces the current
    normal, albedo, residual and flags (and ``won`` is set) where ``keep_better`` is 0, or where its residual is
    lower and ``flags & few == 0`` (:func:`gpps.host.merge.ranks_better`).

    Args:
        pixels: (P,) flat indices of the ring pixels, sorted by ring.
        start: first entry of the ring's slice.
        width: W.
        keep_better: 1: keep the better of the two; 0: always the ring's solve.
        few: the FLAG_FEW_OBSERVATIONS bit.
        normals .. flags: (H, W) the solver's outputs of the ring's solve.
        cur_normals .. cur_flags: (H, W) in/out: the current solution.
        front_iterations: (H, W) out on the ring: the solve's cost evaluations.
        won: (H, W) out on the ring: 1 where the solve was kept.
    """
    t = wp.tid()
    p = pixels[start + t]
    i = p // width
    j = p % width
    front_iterations[i, j] = iterations[i, j]
    if keep_better != 0:
        if not (residual[i, j] < cur_residual[i, j] and (flags[i, j] & few) == 0):
            return
    cur_normals[i, j] = normals[i, j]
    cur_albedo[i, j] = albedo[i, j]
    cur_residual[i, j] = residual[i, j]
    cur_flags[i, j] = flags[i, j]
    won[i, j] = wp.uint8(1)


@wp.kernel(enable_backward=False)
def front_write_back_kernel(
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    flags: wp.array2d(dtype=wp.int32),
    solve_iterations: wp.array2d(dtype=wp.int32),
    front_iterations: wp.array2d(dtype=wp.int32),
    out_normals: wp.array2d(dtype=wp.vec3),
    out_albedo: wp.array2d(dtype=wp.vec3),
    out_residual: wp.array2d(dtype=wp.float32),
    out_flags: wp.array2d(dtype=wp.int32),
    out_iterations: wp.array2d(dtype=wp.int32),
):
    """The front's merged solution into the solver's outputs (dim (H, W)): what the host path builds from the
    fetched :class:`gpps.host.dgmc.FrontResult` (``normals``, ``albedo``, ``residual``, ``flags`` replaced, the
    front's evaluations added to the solve's: ``iterations + front iterations``), left on the device.

    Args:
        normals .. flags: (H, W) the front's merged solution.
        solve_iterations: (H, W) the solution's evaluations (before the rings' solves overwrote the solver's).
        front_iterations: (H, W) the front solves' evaluations (0 off the rings).
        out_normals .. out_iterations: (H, W) out: the solver's outputs.
    """
    i, j = wp.tid()
    out_normals[i, j] = normals[i, j]
    out_albedo[i, j] = albedo[i, j]
    out_residual[i, j] = residual[i, j]
    out_flags[i, j] = flags[i, j]
    out_iterations[i, j] = solve_iterations[i, j] + front_iterations[i, j]


@wp.kernel(enable_backward=False)
def front_source_normals_kernel(
    pixels: wp.array(dtype=wp.int32),
    sources: wp.array(dtype=wp.int32),
    width: int,
    normals: wp.array2d(dtype=wp.vec3),
    out: wp.array(dtype=wp.vec3),
):
    """The merged normal of each ring pixel's source (dim: ring pixels), for RON's start normals (the host path
    reads them from the fetched :class:`gpps.host.dgmc.FrontResult`); a pixel without a source (-1) gets zero.

    Args:
        pixels: (P,) flat ring pixels; sources: (P,) their sources' flat indices (-1: none).
        width: W.
        normals: (H, W) the front's merged normals.
        out: (P,) out.
    """
    t = wp.tid()
    q = sources[t]
    if q < 0:
        out[t] = wp.vec3(0.0, 0.0, 0.0)
    else:
        out[t] = normals[q // width, q % width]
