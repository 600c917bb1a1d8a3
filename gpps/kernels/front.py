"""DGMC's solved front on the device (seed 4.16-4.18): one ring's solve mask, start normals and merge.

Device math only; the stage :class:`gpps.pipeline.front.DeviceFront` owns the buffers and launches these per ring
around :meth:`gpps.pipeline.solver.PixelSolver.step`.  The rings and each ring pixel's source come from the
host, once (:func:`gpps.host.dgmc.front_rings`), as a list of flat pixel indices ``y * W + x`` sorted by ring
(``pixels``) and their sources' indices (``sources``); ring ``k`` is the slice ``[start, start + count)``, and
every kernel here runs one thread per pixel of that slice (the work of a ring is its size, not the image's).
Per ring only the starts depend on the earlier rings' results:

* :func:`scatter_mask_kernel`: the solver's (cleared) mask is set on the slice (:meth:`PixelSolver.select_pixels`);
* :func:`front_start_kernel`: each ring pixel starts from its source's current normal;
* :func:`front_merge_kernel`: the ring's solve replaces the current solution where it ranks better, the rule of
  :func:`gpps.host.merge.ranks_better` (a lower residual on a pixel without ``FLAG_FEW_OBSERVATIONS``), or
  everywhere on the ring without ``keep_better``.  Unlike :func:`gpps.kernels.merge.merge_saved_kernel` (the same
  comparison) it writes into the front's own buffers, records the front solve's own evaluations (not the sum of
  both solves') and which pixels it won, and leaves the solver's outputs alone.
"""

import warp as wp

__all__ = ["scatter_mask_kernel", "front_start_kernel", "front_merge_kernel"]


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
