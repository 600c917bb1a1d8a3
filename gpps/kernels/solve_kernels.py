"""The solver's kernels, built per specialisation: the per-pixel solve, the neighbour pass and the smoothing sweep.

Device math only (buffers and launches: :mod:`gpps.pipeline.solver`).
:func:`make_kernels` builds the three kernels of one ``(method, brdf, robust)``
in a Warp module of their own from the functions of
:func:`gpps.kernels.solve_methods.solver_funcs` (see :mod:`gpps.kernels.solve`,
whose :func:`gpps.kernels.solve.get_solve_kernels` caches them).
"""

import warp as wp

from gpps import names

from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams, light_dir, light_radiance
from gpps.kernels.solve_common import (
    FLAG_ALBEDO_FROM_NEIGHBOURS,
    FLAG_FEW_OBSERVATIONS,
    FLAG_ILL_CONDITIONED,
    FLAG_WOODHAM_FALLBACK,
    NONE,
    Pixel,
    SolverParams,
    cond_frobenius,
    grey,
    grey_max,
    in_fit,
    lanes_sum,
    lanes_sum19,
    light_gram,
    light_gram_range,
    make_pixel,
    store_least_squares,
    store_checked,
    store_checked_lanes,
    store_solution,
    vec19,
)
from gpps.kernels.solve_methods import solver_funcs
from gpps.kernels.solve_neighbours import held_pixel, neighbour_prior, neighbour_stats, prior_start


@wp.func
def observation_weights_range(
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    noise: wp.array(dtype=wp.float32),
    prm: SolverParams,
    i: int,
    j: int,
    k0: int,
    dk: int,
    nl_: int,
    gmax: float,
    weights: wp.array3d(dtype=wp.float32),
):
    """Write the observation weights ``weights[k, i, j]`` of the lights ``k0, k0 + dk, ...`` and count the
    lit ones among them.

    Weight 0: dropped (shadow below ``prm.shadow_threshold * gmax``, saturated,
    or not ``valid``); -1: dark (grey value within ``prm.lit_sigmas`` noise
    levels of 0, a one-sided term); 1 otherwise.  Lit: above
    ``prm.lit_threshold * gmax`` and clear of the noise.  (The solve itself may later set an observation
    aside: :data:`gpps.names.ASIDE_WEIGHT`, ``SolverConfig.shadow_relative``.)

    Returns:
        The number of lit observations among those lights.
    """
    ninfo = int(0)
    for k in range(k0, nl_, dk):
        o = images[k, i, j]
        ok = valid[k, i, j] != wp.uint8(0)
        if grey(o) < prm.shadow_threshold * gmax:
            ok = False
        if prm.saturation > 0.0 and wp.max(o[0], wp.max(o[1], o[2])) >= prm.saturation:
            ok = False
        w = float(0.0)
        if ok:
            w = 1.0
            # lit: a clear fraction of the brightest and clear of the image noise
            if grey(o) > prm.lit_threshold * gmax and grey(o) > prm.lit_sigmas * noise[k]:
                ninfo += 1
            if grey(o) <= prm.lit_sigmas * noise[k]:
                # dark (attached or cast shadow, within the noise of 0): a one-sided term
                w = -1.0
        weights[k, i, j] = w
    return ninfo


@wp.func
def observation_weights(
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    noise: wp.array(dtype=wp.float32),
    prm: SolverParams,
    i: int,
    j: int,
    nl_: int,
    gmax: float,
    weights: wp.array3d(dtype=wp.float32),
):
    """Write the pixel's observation weights ``weights[:, i, j]`` (:func:`observation_weights_range`, all
    lights) and return the number of its lit observations."""
    return observation_weights_range(images, valid, noise, prm, i, j, 0, 1, nl_, gmax, weights)


@wp.func
def least_squares_sums(
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    lights: LightParams,
    use_all: int,
    warm_ok: int,
):
    """The normal equations of Woodham's least squares over the lane's lights ``px.lane, px.lane + px.lanes,
    ...`` (all of them on one lane), packed as a :data:`vec19`: ``A = sum l l^T`` (row-major, 0..8) and
    ``b_c = sum (I_c / E_c) l`` for the channels c (9..17).  ``use_all``, ``warm_ok``: as
    :func:`least_squares_start`."""
    t = vec19()
    for k in range(px.lane, lights.count, px.lanes):
        if warm_ok == 0 and (use_all != 0 or in_fit(weights[k, px.i, px.j])):
            l = light_dir(lights, k, px.p)
            e = light_radiance(lights, k, px.p)
            o = images[k, px.i, px.j]
            y = wp.vec3(0.0)
            for c in range(3):
                if e[c] > 0.0:
                    y[c] = o[c] / e[c]
            for r in range(3):
                for c in range(3):
                    t[3 * r + c] += l[r] * l[c]
                t[9 + r] += y[0] * l[r]
                t[12 + r] += y[1] * l[r]
                t[15 + r] += y[2] * l[r]
    return t


@wp.func
def least_squares_solution(t: vec19, px: Pixel):
    """``(normal, albedo)`` from the normal equations of :func:`least_squares_sums`: the unit normal (the
    view direction when the system is singular) and the RGB albedo (0 then)."""
    a = wp.mat33(t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8])
    bc0 = wp.vec3(t[9], t[10], t[11])
    bc1 = wp.vec3(t[12], t[13], t[14])
    bc2 = wp.vec3(t[15], t[16], t[17])
    bg = bc0 + bc1 + bc2
    ninit = px.v
    kdw = wp.vec3(0.0)
    det = wp.determinant(a)
    fa = wp.sqrt(wp.ddot(a, a))
    if wp.abs(det) > 1.0e-12 * fa * fa * fa and fa > 0.0:
        ai = wp.inverse(a)
        gvec = ai * bg
        if wp.length(gvec) > 0.0:
            ninit = wp.normalize(gvec)
            kdw = wp.vec3(wp.dot(ai * bc0, ninit), wp.dot(ai * bc1, ninit), wp.dot(ai * bc2, ninit))
    return ninit, kdw


@wp.func
def least_squares_start(
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    lights: LightParams,
    use_all: int,
    warm_ok: int,
):
    """Woodham's Lambertian least squares ``I / E = kd (l . n)`` on the valid observations.

    ``use_all`` 1: on every observation (the valid ones' lights are degenerate);
    ``warm_ok`` 1: skipped (a valid warm start replaces it).

    Returns:
        ``(normal, albedo)``: the unit normal (the view direction when the
        system is singular) and the RGB albedo (0 then).
    """
    return least_squares_solution(least_squares_sums(images, weights, px, lights, use_all, warm_ok), px)


# ---------------------------------------------------------------- lights-parallel forms (one block a pixel)
# The same per-light rules as above over the lane's lights ``px.lane, px.lane + px.lanes, ...`` (a lane writes
# and reads only its own lights' weights), the sums reduced over the block (gpps.kernels.solve_common).


@wp.func
def observation_weights_lanes(images: wp.array3d(dtype=wp.vec3), valid: wp.array3d(dtype=wp.uint8),
                              noise: wp.array(dtype=wp.float32), prm: SolverParams, px: Pixel, nl_: int, gmax: float,
                              weights: wp.array3d(dtype=wp.float32)):
    """:func:`observation_weights` over the lanes: each lane writes its lights' weights; the lit count of all."""
    n = observation_weights_range(images, valid, noise, prm, px.i, px.j, px.lane, px.lanes, nl_, gmax, weights)
    return int(lanes_sum(float(n)) + 0.5)


@wp.func
def light_gram_lanes(weights: wp.array3d(dtype=wp.float32), px: Pixel, lights: LightParams):
    """:func:`gpps.kernels.solve_common.light_gram` over the lanes (the block's total)."""
    a = light_gram_range(weights, px.i, px.j, px.p, lights, px.lane, px.lanes)
    t = vec19()
    for r in range(3):
        for c in range(3):
            t[3 * r + c] = a[r, c]
    t = lanes_sum19(t)
    return wp.mat33(t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7], t[8])


@wp.func
def least_squares_start_lanes(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel,
                              lights: LightParams, use_all: int, warm_ok: int):
    """:func:`least_squares_start` over the lanes: the normal equations summed over the block, then solved
    by every lane alike."""
    t = lanes_sum19(least_squares_sums(images, weights, px, lights, use_all, warm_ok))
    return least_squares_solution(t, px)


def prelude_for(module, sfx: str, lanes: bool = False):
    """``pixel_prelude``: what a pixel's solve does before its nonlinear starts (shared by ``solve_kernel`` and
    the starts-parallel kernels of :mod:`gpps.kernels.solve_split`): its :class:`Pixel`, the observation weights
    (written to ``weights``), the flags, the lights' condition number (written to ``cond`` by lane 0) and
    Woodham's least-squares start (or the warm start).  Returns ``(px, ninit, kdw, flag, use_all, gmax)``."""

    @wp.func(name="pixel_prelude" + sfx, module=module)
    def pixel_prelude(
        images: wp.array3d(dtype=wp.vec3),
        valid: wp.array3d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        noise: wp.array(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        prm: SolverParams,
        i: int,
        j: int,
        lane: int,
        nb: int,
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        cond: wp.array2d(dtype=wp.float32),
    ):
        nl_ = lights.count
        px = make_pixel(cam, depth, i, j, prm)
        px.lane = lane
        px.lanes = nb
        # ---- observation validity (shadows, saturation, caller's mask)
        gmax = grey_max(images, i, j, nl_)
        ninfo = int(0)
        if wp.static(lanes):
            ninfo = observation_weights_lanes(images, valid, noise, prm, px, nl_, gmax, weights)
        else:
            ninfo = observation_weights(images, valid, noise, prm, i, j, nl_, gmax, weights)
        flag = int(0)
        if ninfo < 3:
            # fewer than 3 lit observations: normal and albedo are not determined together
            flag = flag | FLAG_FEW_OBSERVATIONS
        # ---- lighting sensitivity (3.13): conditioning of the valid light directions
        gram = wp.mat33(0.0)
        if wp.static(lanes):
            gram = light_gram_lanes(weights, px, lights)
        else:
            gram = light_gram(weights, i, j, px.p, lights)
        cnd = cond_frobenius(gram)
        if lane == 0:
            cond[i, j] = cnd
        if cnd > prm.cond_threshold:
            flag = flag | FLAG_ILL_CONDITIONED
        # ---- Woodham least squares on the valid observations (I / E = kd (l . n))
        use_all = int(0)
        if cnd >= 1.0e29:
            use_all = 1
            flag = flag | FLAG_WOODHAM_FALLBACK
        # a valid warm start skips the least-squares start (a stream's per-frame path)
        warm_ok = int(0)
        nw = wp.vec3(0.0)
        if prm.warm_start != 0 and prm.method != NONE:
            nw = normals[i, j]
            if wp.length(nw) > 0.5:
                warm_ok = 1
        ninit = wp.vec3(0.0)
        kdw = wp.vec3(0.0)
        if wp.static(lanes):
            ninit, kdw = least_squares_start_lanes(images, weights, px, lights, use_all, warm_ok)
        else:
            ninit, kdw = least_squares_start(images, weights, px, lights, use_all, warm_ok)
        if warm_ok != 0:
            ninit = wp.normalize(nw)
            if prm.warm_albedo != 0 and (flag & FLAG_FEW_OBSERVATIONS) != 0:
                # fewer than 3 lit observations leave the albedo free along a curve of exact fits: a warm
                # start (a stream's frame) holds the albedo it had, which the neighbour pass of a cold solve
                # gave it (or its own fit while it had 3 observations); read before this pixel's store
                kd0 = albedo[i, j]
                if wp.length(kd0) > 0.0:  # (zeros: no albedo yet; one channel may be 0, e.g. a pure red)
                    px.fix_kd = 1
                    px.kd = kd0
                    flag = flag | FLAG_ALBEDO_FROM_NEIGHBOURS
        return px, ninit, kdw, flag, use_all, gmax

    return pixel_prelude


def solve_kernel_for(method, solve_pixel, module, sfx: str, lanes: bool = False):
    """``solve_kernel``: the whole image's per-pixel solve, one thread a pixel.

    Args:
        method: ``"none"`` (least squares only), ``"lm"``, ``"dogleg"``, ``"bfgs"`` or None (run-time ``prm.method``).
        solve_pixel: the nonlinear solve (:func:`gpps.kernels.solve_methods.solve_pixel_for`).
        module: Warp module of the kernel.
        sfx: key suffix of the kernel.
        lanes: the lights-parallel build (a nonlinear ``method``; ``solve_pixel`` its lanes build, see
            :func:`gpps.kernels.solve_methods.solver_funcs`): one block of lanes a pixel, launched tiled
            over ``(rows, W, lanes)``; every per-light loop takes the lane's lights and its sums are
            reduced over the block (the same sums in another order: equal up to float rounding).
    """
    if lanes and method in ("none", None):
        raise ValueError(f"lanes: expected a nonlinear method, got {method!r}")
    prelude = prelude_for(module, sfx + ("_lanes" if lanes else ""), lanes)

    @wp.kernel(name="solve_kernel" + ("_lanes" if lanes else "") + sfx, module=module, enable_backward=False)
    def solve_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        valid: wp.array3d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        noise: wp.array(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        residual: wp.array2d(dtype=wp.float32),
        iterations: wp.array2d(dtype=wp.int32),
        flags: wp.array2d(dtype=wp.int32),
        cond: wp.array2d(dtype=wp.float32),
    ):
        """Solve one pixel: observation weights, Lambertian least squares (Woodham) start,
        multi-start nonlinear least squares, IRLS rounds; one launch for the whole image.

        Args:
            images: (N, H, W) RGB observations (already divided by light intensities
                when the lights carry unit intensity).
            mask: (H, W) 1 inside the object.
            valid: (N, H, W) 1 where the caller keeps the observation.
            depth: (H, W) depth estimate > 0 (used for point lights and the view ray).
            noise: (N,) noise standard deviation of each image's grey values (0: unknown);
                an observation counts as lit only above ``prm.lit_sigmas`` times it.
            weights: (N, H, W) scratch: observation weights (output, for inspection).
            normals: (H, W) in: warm start when ``prm.warm_start``; out: unit normals (0 outside).
            albedo: (H, W) RGB albedo kd.
            residual: (H, W) RMS weighted residual per valid observation and channel.
            iterations: (H, W) cost evaluations used (all starts and rounds).
            flags: (H, W) FLAG_* bits.
            cond: (H, W) Frobenius condition number of the valid lights' Gram matrix.
        """
        lane = int(0)
        nb = int(1)
        if wp.static(lanes):
            t, j, lane = wp.tid()
            nb = wp.block_dim()
        else:
            t, j = wp.tid()
        i = t + prm.row0
        nl_ = lights.count
        if mask[i, j] == wp.uint8(0):
            if prm.keep_unmasked != 0:
                return
            if lane == 0:
                normals[i, j] = wp.vec3(0.0)
                albedo[i, j] = wp.vec3(0.0)
                residual[i, j] = 0.0
                iterations[i, j] = 0
                flags[i, j] = 0
                cond[i, j] = 0.0
            for k in range(lane, nl_, nb):
                weights[k, i, j] = 0.0
            return
        px, ninit, kdw, flag, use_all, gmax = prelude(images, valid, depth, noise, cam, lights, prm, i, j, lane, nb,
                                                      weights, normals, albedo, cond)
        if wp.static(method == "none"):
            store_least_squares(ninit, kdw, flag, use_all, images, weights, px, lights, normals, albedo, residual, iterations, flags)
        else:
            if wp.static(method is None):
                # generic build: run-time switch
                if prm.method == NONE:
                    store_least_squares(ninit, kdw, flag, use_all, images, weights, px, lights, normals, albedo, residual, iterations, flags)
                    return
            sol = solve_pixel(ninit, gmax, images, weights, px, lights, mat, prm)
            if wp.static(lanes):
                store_checked_lanes(sol, flag, images, weights, px, lights, normals, albedo, residual, iterations,
                                    flags)
            else:
                store_checked(sol, flag, images, weights, px, lights, normals, albedo, residual, iterations, flags)

    return solve_kernel


def underdetermined_kernel_for(solve_pixel, held_dark_refit, module, sfx: str):
    """``underdetermined_kernel``: the neighbour pass for pixels with fewer than 3 lit observations.

    Args:
        solve_pixel: the nonlinear solve (:func:`gpps.kernels.solve_methods.solve_pixel_for`).
        held_dark_refit: the attached / cast shadow choice (``held_dark_refit`` of
            :func:`gpps.kernels.solve_methods.solve_pixel_for`).
        module: Warp module of the kernel.
        sfx: key suffix of the kernel.
    """

    @wp.kernel(name="underdetermined_kernel" + sfx, module=module, enable_backward=False)
    def underdetermined_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        solve_mask: wp.array2d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        radius: int,
        min_count: int,
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        residual: wp.array2d(dtype=wp.float32),
        iterations: wp.array2d(dtype=wp.int32),
        flags: wp.array2d(dtype=wp.int32),
    ):
        """Second pass for pixels with fewer than 3 lit observations (attached shadows).

        Two observations cannot fix a normal (2 dof) and an albedo together, so the
        albedo is held at the geometric median of the albedos of the nearest
        well-determined pixels (:func:`neighbour_stats`: at least ``min_count`` of
        them within ``radius``; albedo varies slowly) and the normal is re-solved
        with all starts.  The dark observations stay in the fit: the model's
        ``max(n.l, 0)`` penalises a solution that would light them.  A weak prior
        (weight 1e-3 of the data's scale) toward the first-order extrapolation of
        those pixels' normals (or their geometric median when that fit is singular
        or faces away) breaks the remaining ties (the two mirror solutions of 2
        observations, the cone of solutions of 1).  Only flagged pixels are
        written and only unflagged ones are read, so threads do not race.

        ``mask`` is the object (the neighbours are read inside it); ``solve_mask`` the pixels solved
        (``mask`` itself for a whole frame; a subset re-solved inside a frame, e.g. a stream's cold re-solve
        of jumped pixels, reads its neighbours from the whole object, not from the subset).
        """
        i, j = wp.tid()
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
        px = held_pixel(px, nb.kd, prior)
        ninit = prior_start(prior, normals[i, j])
        sol = solve_pixel(ninit, gmax, images, weights, px, lights, mat, prm)
        sol = held_dark_refit(sol, ninit, gmax, images, weights, px, lights, mat, prm)
        sol.total = sol.total + iterations[i, j]
        store_solution(sol, f | FLAG_ALBEDO_FROM_NEIGHBOURS, weights, px, lights.count, normals, albedo, residual, iterations, flags)

    return underdetermined_kernel


def smooth_kernel_for(run_method, module, sfx: str):
    """``smooth_kernel``: one red-black half-sweep of the smoothness-regularised fit.

    Args:
        run_method: the solver from one start (:func:`gpps.kernels.solve_methods.run_method_for`).
        module: Warp module of the kernel.
        sfx: key suffix of the kernel.
    """

    @wp.kernel(name="smooth_kernel" + sfx, module=module, enable_backward=False)
    def smooth_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
        depth: wp.array2d(dtype=wp.float32),
        cam: CameraParams,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
        strength: float,
        parity: int,
        flags: wp.array2d(dtype=wp.int32),
        weights: wp.array3d(dtype=wp.float32),
        normals: wp.array2d(dtype=wp.vec3),
        albedo: wp.array2d(dtype=wp.vec3),
        residual: wp.array2d(dtype=wp.float32),
        iterations: wp.array2d(dtype=wp.int32),
    ):
        """One red-black Gauss-Seidel half-sweep of the smoothness-regularised fit.

        Minimises, over the whole normal field (seed 4.2 plus a first-order
        smoothness term),

            E = sum_p 1/2 sum_k w_k |I_k(p) - model(n_p)|^2 + strength/2 sum_(p~q) |n_p - n_q|^2

        over 4-neighbour pairs inside the mask.  With the neighbours held fixed,
        the terms of pixel p are its data cost plus ``strength * m / 2 |n_p - nbar|^2``
        (``m`` neighbours, ``nbar`` their mean, not normalised): exactly the
        solver's prior with ``prior_w = strength * m``.  Pixels with
        ``(i + j) % 2 == parity`` are updated in place from a warm start (one
        start, the observation weights of the main solve); they only read
        pixels of the other colour, so threads do not race.  Pixels whose
        albedo came from their neighbours (``FLAG_ALBEDO_FROM_NEIGHBOURS``)
        keep it: fewer than 3 lit observations cannot fix it.
        """
        i, j = wp.tid()
        if (i + j) % 2 != parity:
            return
        if mask[i, j] == wp.uint8(0):
            return
        h = mask.shape[0]
        w = mask.shape[1]
        acc = wp.vec3(0.0)
        cnt = float(0.0)
        if i > 0:
            if mask[i - 1, j] != wp.uint8(0):
                acc += normals[i - 1, j]
                cnt += 1.0
        if i + 1 < h:
            if mask[i + 1, j] != wp.uint8(0):
                acc += normals[i + 1, j]
                cnt += 1.0
        if j > 0:
            if mask[i, j - 1] != wp.uint8(0):
                acc += normals[i, j - 1]
                cnt += 1.0
        if j + 1 < w:
            if mask[i, j + 1] != wp.uint8(0):
                acc += normals[i, j + 1]
                cnt += 1.0
        if cnt == 0.0:
            return
        px = make_pixel(cam, depth, i, j, prm)
        px.prior_n = acc / cnt
        px.prior_w = strength * cnt
        if (flags[i, j] & FLAG_ALBEDO_FROM_NEIGHBOURS) != 0:
            # under-determined pixel: keep the albedo the neighbour pass gave it
            px.fix_kd = 1
            px.kd = albedo[i, j]
        n0 = normals[i, j]
        if wp.length(n0) < 0.5:
            n0 = px.v
        res = run_method(wp.normalize(n0), images, weights, px, lights, mat, prm)
        if wp.dot(res.n, px.v) > 0.0:
            normals[i, j] = res.n
            albedo[i, j] = res.kd
            wsum = float(0.0)
            for k in range(lights.count):
                wsum += wp.abs(weights[k, i, j])
            if wsum > 0.0:
                # data part of the RMS residual (the prior's share removed)
                dp = res.n - px.prior_n
                c = wp.max(res.cost - 0.5 * px.prior_w * wp.dot(dp, dp), 0.0)
                residual[i, j] = wp.sqrt(2.0 * c / (3.0 * wsum))
        iterations[i, j] = iterations[i, j] + res.iters

    return smooth_kernel


def make_lanes_kernel(method, brdf, robust, module_name: str, sfx: str):
    """The lights-parallel solve kernel (:func:`solve_kernel_for` with ``lanes``) of one specialisation (a nonlinear
    ``method``) in the Warp module ``module_name``."""
    module = wp.get_module(module_name)
    funcs = solver_funcs(method, brdf, robust, module, sfx, lanes=True)
    return solve_kernel_for(method, funcs.solve_pixel, module, sfx, lanes=True)


def make_kernels(method, brdf, robust, module_name: str, sfx: str, cache: int = names.SOLVE_TERM_CACHE,
                 with_batched: bool = False):
    """``(solve_kernel, underdetermined_kernel, smooth_kernel, batched_kernel)`` of one specialisation in the Warp
    module ``module_name``.

    Args:
        method, brdf, robust: the normalised key (:func:`gpps.kernels.solve.specialisation_key`).
        module_name: name of the Warp module (:func:`gpps.kernels.solve.module_name`).
        sfx: key suffix of the functions and kernels.
        cache: the lights the evaluation keeps between its passes (:func:`gpps.kernels.solve.term_cache_size`).
        with_batched: also build the material scorer's batched kernel
            (:func:`gpps.kernels.solve_batched.batched_kernel_for`, one thread a (candidate, pixel) pair) in this
            module, from the same device functions (:func:`gpps.kernels.solve.batched_in_solve_module`).

    Returns:
        The four kernels; the last three are None for ``method="none"``, the last one without ``with_batched``.
    """
    module = wp.get_module(module_name)
    funcs = solver_funcs(method, brdf, robust, module, sfx, cache=cache)
    solve_kernel = solve_kernel_for(method, funcs.solve_pixel, module, sfx)
    if method == "none":
        return solve_kernel, None, None, None
    underdetermined_kernel = underdetermined_kernel_for(funcs.solve_pixel, funcs.held_dark_refit, module, sfx)
    smooth_kernel = smooth_kernel_for(funcs.run_method, module, sfx)
    batched_kernel = None
    if with_batched:
        from gpps.kernels.solve_batched import batched_kernel_for  # (it imports this module's package entry)

        batched_kernel = batched_kernel_for(robust, funcs.solve_pixel, module, sfx)
    return solve_kernel, underdetermined_kernel, smooth_kernel, batched_kernel
