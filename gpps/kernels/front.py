"""DGMC's solved front on the device (seed 4.16-4.18): one ring's solve mask, start normals and merge.

Device math only; the stage :class:`gpps.pipeline.front.DeviceFront` owns the buffers and launches these per ring
around :meth:`gpps.pipeline.solver.PixelSolver.step`.  The rings and each ring pixel's source come from the
host, once (:func:`gpps.host.dgmc.front_rings`); per ring only the starts depend on the earlier rings' results:

* :func:`label_mask_kernel`: the solver's mask is ring ``k`` of the ring map (:meth:`PixelSolver.select_mask`);
* :func:`front_start_kernel`: each ring pixel starts from its source's current normal;
* :func:`front_merge_kernel`: the ring's solve replaces the current solution where it ranks better, the rule of
  :func:`gpps.host.merge.ranks_better` (a lower residual on a pixel without ``FLAG_FEW_OBSERVATIONS``), or
  everywhere on the ring without ``keep_better``.  Unlike :func:`gpps.kernels.merge.merge_saved_kernel` (the same
  comparison) it writes into the front's own buffers, records the front solve's own evaluations (not the sum of
  both solves') and which pixels it won, and leaves the solver's outputs alone.
"""

import warp as wp

__all__ = ["label_mask_kernel", "front_start_kernel", "front_merge_kernel"]


@wp.kernel(enable_backward=False)
def label_mask_kernel(labels: wp.array2d(dtype=wp.int32), value: int, mask: wp.array2d(dtype=wp.uint8)):
    """``mask = (labels == value)`` (dim (H, W)).

    Args:
        labels: (H, W) int32 label map (e.g. the front's rings).
        value: the label to select.
        mask: (H, W) out: 1 where ``labels == value``, 0 elsewhere.
    """
    i, j = wp.tid()
    if labels[i, j] == value:
        mask[i, j] = wp.uint8(1)
    else:
        mask[i, j] = wp.uint8(0)


@wp.kernel(enable_backward=False)
def front_start_kernel(
    ring: wp.array2d(dtype=wp.int32),
    k: int,
    source: wp.array3d(dtype=wp.int32),
    current: wp.array2d(dtype=wp.vec3),
    start: wp.array2d(dtype=wp.vec3),
):
    """Start normals of ring ``k``: ``start[p] = current[source[p]]`` where ``ring[p] == k`` (dim (H, W)).

    Args:
        ring: (H, W) ring of each pixel (:func:`gpps.host.dgmc.front_rings`).
        k: the ring to start.
        source: (H, W, 2) ``(row, column)`` of each ring pixel's source (solved in an earlier ring or outside
            the highlights).
        current: (H, W) the current (merged) normals.
        start: (H, W) out, on ring ``k``: the start normals (the solver's ``normals`` buffer); untouched elsewhere.
    """
    i, j = wp.tid()
    if ring[i, j] != k:
        return
    start[i, j] = current[source[i, j, 0], source[i, j, 1]]


@wp.kernel(enable_backward=False)
def front_merge_kernel(
    ring: wp.array2d(dtype=wp.int32),
    k: int,
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
    """Merge ring ``k``'s solve into the current solution (dim (H, W); pixels off ring ``k`` untouched).

    On ring ``k``: ``front_iterations`` = the solve's evaluations; the solve replaces the current normal,
    albedo, residual and flags (and ``won`` is set) where ``keep_better`` is 0, or where its residual is lower
    and ``flags & few == 0`` (:func:`gpps.host.merge.ranks_better`).

    Args:
        ring: (H, W) ring of each pixel.
        k: the ring just solved.
        keep_better: 1: keep the better of the two; 0: always the ring's solve.
        few: the FLAG_FEW_OBSERVATIONS bit.
        normals .. flags: (H, W) the solver's outputs of ring ``k``'s solve.
        cur_normals .. cur_flags: (H, W) in/out: the current solution.
        front_iterations: (H, W) out on ring ``k``: the solve's cost evaluations.
        won: (H, W) out on ring ``k``: 1 where the solve was kept.
    """
    i, j = wp.tid()
    if ring[i, j] != k:
        return
    front_iterations[i, j] = iterations[i, j]
    if keep_better != 0:
        if not (residual[i, j] < cur_residual[i, j] and (flags[i, j] & few) == 0):
            return
    cur_normals[i, j] = normals[i, j]
    cur_albedo[i, j] = albedo[i, j]
    cur_residual[i, j] = residual[i, j]
    cur_flags[i, j] = flags[i, j]
    won[i, j] = wp.uint8(1)
