"""The starts-parallel form of ``solve_kernel`` (cold whole-image solves on CUDA).

A GPU launch costs its slowest thread, and ``solve_kernel`` runs a pixel's ``prm.starts`` starts one after
another in its thread.  Here the same work takes three launches over the same pixels:

* ``split_prelude_kernel`` (dim (rows, W)): :func:`gpps.kernels.solve_kernels.prelude_for`'s
  ``pixel_prelude`` (observation weights, flags, condition number, Woodham's start), its start normal,
  ``gmax`` and flags kept in (H, W) scratch; pixels outside the mask get ``solve_kernel``'s zeros;
* ``split_starts_kernel`` (dim (rows, W, S)): start ``s`` of a pixel in a thread of its own
  (:func:`gpps.kernels.solve_methods.solve_pixel_for`'s ``one_start``), its :class:`StartResult` to
  (H, W, S) scratch;
* ``split_finish_kernel`` (dim (rows, W)): the best start (:func:`gpps.kernels.solve_common.pick_start`, the
  multi-start loop's rule, as the material scorer's starts-parallel build), the evaluations summed, then ``finish_pixel`` (the
  least-squares fallback, the IRLS rounds) and the store.

The same device functions on the same inputs (the starts read the weights the prelude wrote, as the loop does
before any IRLS round), so on the CPU the results equal ``solve_kernel``'s bit for bit; on CUDA another module
may round differently.  Only cold solves of one thread a pixel (no warm start, no lanes, a nonlinear method).
On CUDA the module is compiled with a register cap (:data:`gpps.names.SPLIT_SOLVE_MAX_REGISTERS`: more threads
resident for these throughput-bound launches; measured by perf/register_cap.py, same normals bit for bit).
"""

import warp as wp

from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams
from gpps.kernels.solve_common import SolverParams, make_pixel, pick_start, store_solution

__all__ = ["split_kernels_for"]


def split_kernels_for(prelude, one_start, finish_pixel, module, sfx: str):
    """``(split_prelude_kernel, split_starts_kernel, split_finish_kernel)`` of one specialisation (module docstring)."""

    @wp.kernel(name="split_prelude_kernel" + sfx, module=module, enable_backward=False)
    def split_prelude_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        valid: wp.array3d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        noise: wp.array(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        prm: SolverParams,
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        residual: wp.array2d(dtype=wp.float32),
        iterations: wp.array2d(dtype=wp.int32),
        flags: wp.array2d(dtype=wp.int32),
        cond: wp.array2d(dtype=wp.float32),
        ninit_buf: wp.array2d(dtype=wp.vec3),
        gmax_buf: wp.array2d(dtype=wp.float32),
        flag_buf: wp.array2d(dtype=wp.int32),
    ):
        t, j = wp.tid()
        i = t + prm.row0
        if mask[i, j] == wp.uint8(0):
            if prm.keep_unmasked != 0:
                return
            normals[i, j] = wp.vec3(0.0)
            albedo[i, j] = wp.vec3(0.0)
            residual[i, j] = 0.0
            iterations[i, j] = 0
            flags[i, j] = 0
            cond[i, j] = 0.0
            for k in range(lights.count):
                weights[k, i, j] = 0.0
            return
        px, ninit, kdw, flag, use_all, gmax = prelude(images, valid, depth, noise, cam, lights, prm, i, j, 0, 1,
                                                      weights, normals, albedo, cond)
        ninit_buf[i, j] = ninit
        gmax_buf[i, j] = gmax
        flag_buf[i, j] = flag

    @wp.kernel(name="split_starts_kernel" + sfx, module=module, enable_backward=False)
    def split_starts_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        weights: wp.array3d(dtype=wp.float32),
        ninit_buf: wp.array2d(dtype=wp.vec3),
        start_n: wp.array3d(dtype=wp.vec3),
        start_kd: wp.array3d(dtype=wp.vec3),
        start_cost: wp.array3d(dtype=wp.float32),
        start_iters: wp.array3d(dtype=wp.int32),
        start_conv: wp.array3d(dtype=wp.int32),
    ):
        t, j, st = wp.tid()
        i = t + prm.row0
        if mask[i, j] == wp.uint8(0):
            return
        px = make_pixel(cam, depth, i, j, prm)
        res = one_start(st, ninit_buf[i, j], images, weights, px, lights, mat, prm)
        start_n[i, j, st] = res.n
        start_kd[i, j, st] = res.kd
        start_cost[i, j, st] = res.cost
        start_iters[i, j, st] = res.iters
        start_conv[i, j, st] = res.converged

    @wp.kernel(name="split_finish_kernel" + sfx, module=module, enable_backward=False)
    def split_finish_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        ninit_buf: wp.array2d(dtype=wp.vec3),
        gmax_buf: wp.array2d(dtype=wp.float32),
        flag_buf: wp.array2d(dtype=wp.int32),
        start_n: wp.array3d(dtype=wp.vec3),
        start_kd: wp.array3d(dtype=wp.vec3),
        start_cost: wp.array3d(dtype=wp.float32),
        start_iters: wp.array3d(dtype=wp.int32),
        start_conv: wp.array3d(dtype=wp.int32),
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        residual: wp.array2d(dtype=wp.float32),
        iterations: wp.array2d(dtype=wp.int32),
        flags: wp.array2d(dtype=wp.int32),
    ):
        t, j = wp.tid()
        i = t + prm.row0
        if mask[i, j] == wp.uint8(0):
            return
        px = make_pixel(cam, depth, i, j, prm)
        ninit = ninit_buf[i, j]
        best, total = pick_start(start_n, start_kd, start_cost, start_iters, start_conv, i, j, wp.max(prm.starts, 1),
                                 ninit, px.v)
        sol = finish_pixel(best, total, ninit, gmax_buf[i, j], images, weights, px, lights, mat, prm)
        store_solution(sol, flag_buf[i, j], weights, px, lights.count, normals, albedo, residual, iterations, flags)

    return split_prelude_kernel, split_starts_kernel, split_finish_kernel
