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
from gpps.kernels.solve_common import (
    FLAG_ALBEDO_FROM_NEIGHBOURS,
    FLAG_FEW_OBSERVATIONS,
    NONE,
    SolverParams,
    grey_max,
    make_pixel,
    pick_start,
    store_checked,
    store_solution,
)
from gpps.kernels.solve_neighbours import held_pixel, neighbour_prior, neighbour_stats, prior_start

__all__ = ["split_kernels_for", "split_under_kernels_for"]


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
        store_checked(sol, flag_buf[i, j], images, weights, px, lights, normals, albedo, residual, iterations, flags)

    return split_prelude_kernel, split_starts_kernel, split_finish_kernel


def split_under_kernels_for(one_start, finish_pixel, held_dark_refit, module, sfx: str):
    """``(under_prelude_kernel, under_starts_kernel, under_finish_kernel)``: the starts-parallel form of
    ``underdetermined_kernel`` (:func:`gpps.kernels.solve_kernels.underdetermined_kernel_for`), the solver's
    neighbour pass for pixels with fewer than 3 lit observations.

    That kernel's thread runs, for one such pixel, the neighbours' robust statistics
    (:func:`gpps.kernels.solve_neighbours.neighbour_stats`) and then every start of the multi-start solve one
    after another; the launch costs its slowest thread (the 256^2 x 3-image synthetic call on an H200: about
    5 ms a launch, a quarter of the call's GPU time).  Here:

    * ``under_prelude_kernel`` (dim (H, W)): the early outs and the statistics; for a pixel the pass solves, its
      held albedo ``kd_buf``, prior normal and weight, start normal, ``gmax`` and flags; ``flag_buf`` -1 for a
      pixel it leaves alone;
    * ``under_starts_kernel`` (dim (H, W, S)): start ``s`` of such a pixel in a thread of its own, with the
      prelude's albedo held and its prior (``one_start``); a warm config runs start 0 only, as the loop does;
    * ``under_finish_kernel`` (dim (H, W)): the best start by the loop's rule (``pick_start``), ``finish_pixel``
      (the IRLS rounds), the attached / cast shadow choice (``held_dark_refit``) and the store, flagged
      ``FLAG_ALBEDO_FROM_NEIGHBOURS``.

    The prelude reads only pixels the pass does not write (well-determined ones), and the writes wait for the
    last launch, so the statistics see what the one-kernel pass's threads see; the same device functions on
    the same inputs give its results bit for bit on the CPU (tests/test_solve_split.py).
    """

    @wp.kernel(name="under_prelude_kernel" + sfx, module=module, enable_backward=False)
    def under_prelude_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        solve_mask: wp.array2d(dtype=wp.uint8),
        lights: LightParams,
        prm: SolverParams,
        radius: int,
        min_count: int,
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        flags: wp.array2d(dtype=wp.int32),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        ninit_buf: wp.array2d(dtype=wp.vec3),
        gmax_buf: wp.array2d(dtype=wp.float32),
        flag_buf: wp.array2d(dtype=wp.int32),
        kd_buf: wp.array2d(dtype=wp.vec3),
        prior_buf: wp.array2d(dtype=wp.vec4),
    ):
        i, j = wp.tid()
        flag_buf[i, j] = -1
        if solve_mask[i, j] == wp.uint8(0) or mask[i, j] == wp.uint8(0) or prm.method == NONE:
            return
        f = flags[i, j]
        if (f & FLAG_FEW_OBSERVATIONS) == 0:
            return
        nb = neighbour_stats(i, j, radius, min_count, mask, flags, normals, albedo)
        if nb.count == 0.0:
            return
        px = make_pixel(cam, depth, i, j, prm)
        gmax = grey_max(images, i, j, lights.count)
        prior = neighbour_prior(nb, px.v, gmax)
        ninit = prior_start(prior, normals[i, j])
        ninit_buf[i, j] = ninit
        gmax_buf[i, j] = gmax
        kd_buf[i, j] = nb.kd
        prior_buf[i, j] = prior
        flag_buf[i, j] = f

    @wp.kernel(name="under_starts_kernel" + sfx, module=module, enable_backward=False)
    def under_starts_kernel(
        images: wp.array3d(dtype=wp.vec3),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        weights: wp.array3d(dtype=wp.float32),
        ninit_buf: wp.array2d(dtype=wp.vec3),
        flag_buf: wp.array2d(dtype=wp.int32),
        kd_buf: wp.array2d(dtype=wp.vec3),
        prior_buf: wp.array2d(dtype=wp.vec4),
        start_n: wp.array3d(dtype=wp.vec3),
        start_kd: wp.array3d(dtype=wp.vec3),
        start_cost: wp.array3d(dtype=wp.float32),
        start_iters: wp.array3d(dtype=wp.int32),
        start_conv: wp.array3d(dtype=wp.int32),
    ):
        i, j, st = wp.tid()
        if flag_buf[i, j] < 0 or (prm.warm_start != 0 and st > 0):
            return
        px = held_pixel(make_pixel(cam, depth, i, j, prm), kd_buf[i, j], prior_buf[i, j])
        res = one_start(st, ninit_buf[i, j], images, weights, px, lights, mat, prm)
        start_n[i, j, st] = res.n
        start_kd[i, j, st] = res.kd
        start_cost[i, j, st] = res.cost
        start_iters[i, j, st] = res.iters
        start_conv[i, j, st] = res.converged

    @wp.kernel(name="under_finish_kernel" + sfx, module=module, enable_backward=False)
    def under_finish_kernel(
        images: wp.array3d(dtype=wp.vec3),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        ninit_buf: wp.array2d(dtype=wp.vec3),
        gmax_buf: wp.array2d(dtype=wp.float32),
        flag_buf: wp.array2d(dtype=wp.int32),
        kd_buf: wp.array2d(dtype=wp.vec3),
        prior_buf: wp.array2d(dtype=wp.vec4),
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
        i, j = wp.tid()
        f = flag_buf[i, j]
        if f < 0:
            return
        px = held_pixel(make_pixel(cam, depth, i, j, prm), kd_buf[i, j], prior_buf[i, j])
        ninit = ninit_buf[i, j]
        nstarts = wp.max(prm.starts, 1)
        if prm.warm_start != 0:
            nstarts = 1
        best, total = pick_start(start_n, start_kd, start_cost, start_iters, start_conv, i, j, nstarts, ninit, px.v)
        sol = finish_pixel(best, total, ninit, gmax_buf[i, j], images, weights, px, lights, mat, prm)
        sol = held_dark_refit(sol, ninit, gmax_buf[i, j], images, weights, px, lights, mat, prm)
        sol.total = sol.total + iterations[i, j]
        store_solution(sol, f | FLAG_ALBEDO_FROM_NEIGHBOURS, weights, px, lights.count, normals, albedo, residual,
                       iterations, flags)

    return under_prelude_kernel, under_starts_kernel, under_finish_kernel
