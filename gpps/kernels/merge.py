"""Device merge of two solves of the same pixels: keep the lower residual, where it can rank.

Device math only; the buffers live in :class:`gpps.pipeline.solver.PixelSolver` (``save`` /
``merge_saved``).  The rule is :func:`gpps.host.merge.ranks_better`: a new solution replaces the saved one
where its residual is lower and the pixel has 3 lit observations (an under-determined pixel fits a family of
normals, so its residual cannot rank starts).
"""

import warp as wp

__all__ = ["merge_saved_kernel"]


@wp.kernel(enable_backward=False)
def merge_saved_kernel(
    sel: wp.array2d(dtype=wp.uint8),
    few: int,
    normals0: wp.array2d(dtype=wp.vec3),
    albedo0: wp.array2d(dtype=wp.vec3),
    residual0: wp.array2d(dtype=wp.float32),
    iterations0: wp.array2d(dtype=wp.int32),
    flags0: wp.array2d(dtype=wp.int32),
    cond0: wp.array2d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
    cond: wp.array2d(dtype=wp.float32),
):
    """Merge the current outputs (a solve of the pixels where ``sel`` is set) into the saved ``*0`` ones (dim (H, W)).

    Where ``sel`` is set and the current solution ranks better (lower residual, ``flags & few == 0``) it
    stays; elsewhere the saved solution is restored.  ``iterations`` becomes the sum of both solves' where
    ``sel`` is set (the work spent on the pixel), the saved count elsewhere.

    Args:
        sel: (H, W) 1 where the current solve ran.
        few: the FLAG_FEW_OBSERVATIONS bit.
        normals0 .. cond0: (H, W) the saved solve's outputs.
        normals .. cond: (H, W) in: the current solve's outputs; out: the merge.
    """
    i, j = wp.tid()
    if sel[i, j] != wp.uint8(0):
        it = iterations[i, j] + iterations0[i, j]
        iterations[i, j] = it
        if residual[i, j] < residual0[i, j] and (flags[i, j] & few) == 0:
            return
    else:
        iterations[i, j] = iterations0[i, j]
    normals[i, j] = normals0[i, j]
    albedo[i, j] = albedo0[i, j]
    residual[i, j] = residual0[i, j]
    flags[i, j] = flags0[i, j]
    cond[i, j] = cond0[i, j]
