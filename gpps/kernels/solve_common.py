"""Shared pieces of the per-pixel solver (:mod:`gpps.kernels.solve`): tags, structs and small device helpers.

Device math only.  The structs carry a pixel's settings and intermediate
results between the functions that :mod:`gpps.kernels.solve_methods` defines
per specialisation; the ``@wp.func`` here do not depend on the solver, the
reflectance model or the robust loss, so every specialised module shares them
(Warp emits into a module only the functions its kernels reach).
"""

import warp as wp

from gpps import names

from gpps.kernels.brdf import CameraParams, LightParams, light_dir, light_radiance, pixel_point, view_dir
from gpps.kernels.jacobians import mat32, tangent_basis_t1

# solver, robust-loss tags and flag bits: the integers of gpps.names (the public code uses its strings)
NONE = wp.constant(names.SOLVER_TAG["none"])
LM = wp.constant(names.SOLVER_TAG["lm"])
DOGLEG = wp.constant(names.SOLVER_TAG["dogleg"])
BFGS = wp.constant(names.SOLVER_TAG["bfgs"])

ROBUST_NONE = wp.constant(names.ROBUST_TAG["none"])
ROBUST_HUBER = wp.constant(names.ROBUST_TAG["huber"])
ROBUST_CAUCHY = wp.constant(names.ROBUST_TAG["cauchy"])

FLAG_ILL_CONDITIONED = wp.constant(names.FLAG_ILL_CONDITIONED)
FLAG_FEW_OBSERVATIONS = wp.constant(names.FLAG_FEW_OBSERVATIONS)
FLAG_NOT_CONVERGED = wp.constant(names.FLAG_NOT_CONVERGED)
FLAG_WOODHAM_FALLBACK = wp.constant(names.FLAG_WOODHAM_FALLBACK)
FLAG_ALBEDO_FROM_NEIGHBOURS = wp.constant(names.FLAG_ALBEDO_FROM_NEIGHBOURS)
FLAG_UNFOUNDED = wp.constant(names.FLAG_UNFOUNDED)
UNFOUNDED_SHADING = wp.constant(names.UNFOUNDED_SHADING)
ASIDE = wp.constant(names.ASIDE_WEIGHT)
CAST_CONFLICT = wp.constant(names.CAST_CONFLICT)


@wp.struct
class SolverParams:
    """Per-solve settings (see :class:`gpps.pipeline.solver.PixelSolver.Config`)."""

    method: wp.int32
    max_iters: wp.int32
    starts: wp.int32
    start_angle: wp.float32
    tol_step: wp.float32
    tol_grad: wp.float32
    robust: wp.int32
    robust_scale: wp.float32
    irls_rounds: wp.int32
    shadow_threshold: wp.float32
    shadow_relative: wp.float32
    saturation: wp.float32
    warm_start: wp.int32
    warm_albedo: wp.int32  # 1: a warm-started pixel with fewer than 3 lit observations holds its albedo buffer's value
    held_dark: wp.int32  # 1: the neighbour pass chooses between an attached and a cast shadow (held_dark_refit)
    grey_albedo: wp.int32
    cond_threshold: wp.float32
    early_exit: wp.int32
    lm_tau: wp.float32
    dogleg_radius: wp.float32
    lit_threshold: wp.float32
    lit_sigmas: wp.float32
    keep_unmasked: wp.int32  # 1: pixels outside the mask keep their outputs (a re-solve of a subset)
    row0: wp.int32  # first image row of the launch (a CPU launch split by rows across threads); 0: the whole image


@wp.struct
class Pixel:
    """What a solve needs to know about its pixel.

    Attributes:
        i, j: row and column.
        p: surface point at the given depth (gpps frame).
        v: unit view direction.
        fix_kd: 1 to hold the albedo at ``kd`` instead of eliminating it.
        kd: the fixed albedo.
        grey_albedo: 1 for one albedo value shared by the channels.
        prior_w: weight of a weak prior ``1/2 prior_w |n - prior_n|^2`` added to
            the cost (0: none); it only breaks ties of under-determined pixels.
        prior_n: the prior normal.
        lane, lanes: the thread's lane and the lanes sharing this pixel's solve (the
            lights-parallel builds: lane ``l`` takes lights ``l, l + lanes, ...`` and the
            sums are reduced over the block); 0 and 1 in the one-thread-a-pixel builds.
        visible_only: 1 to make the solvers reject a step that turns the normal away from the camera
            (``n.v <= 0``); 0 (the starts, IRLS rounds) leaves their steps free, as the pick of starts already
            refuses a normal facing away.  The run after every start ended facing away sets it.
    """

    i: wp.int32
    j: wp.int32
    p: wp.vec3
    v: wp.vec3
    fix_kd: wp.int32
    kd: wp.vec3
    grey_albedo: wp.int32
    prior_w: wp.float32
    prior_n: wp.vec3
    lane: wp.int32
    lanes: wp.int32
    visible_only: wp.int32

# the pass-1 sums of the lights-parallel evaluation (6 vec3 and the weight sum) and the pass-2 sums
# (cost, J^T r, the 3 distinct entries of J^T J), reduced over a block as one vector each
vec19 = wp.types.vector(length=19, dtype=wp.float32)
vec6 = wp.types.vector(length=6, dtype=wp.float32)


@wp.struct
class Eval:
    """Reduced cost, its gradient ``J^T W r`` and Gauss-Newton matrix ``J^T W J`` at one normal."""

    cost: wp.float32
    jtj: wp.mat22
    jtr: wp.vec2
    kd: wp.vec3
    wsum: wp.float32


@wp.func
def grey(c: wp.vec3):
    """Grey value of an RGB colour: the mean of its channels."""
    return (c[0] + c[1] + c[2]) / 3.0


@wp.func
def dot2(a: wp.vec2, b: wp.vec2):
    """Dot product of two 2-vectors."""
    return a[0] * b[0] + a[1] * b[1]


@wp.func
def solve22(a: wp.mat22, b: wp.vec2):
    """``a^-1 b`` for a symmetric positive (semi)definite 2x2; zero when singular (checked determinant)."""
    det = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    scale = wp.abs(a[0, 0]) + wp.abs(a[1, 1])
    if wp.abs(det) <= 1.0e-12 * scale * scale or scale <= 0.0:
        return wp.vec2(0.0)
    return wp.vec2(a[1, 1] * b[0] - a[0, 1] * b[1], a[0, 0] * b[1] - a[1, 0] * b[0]) / det


@wp.func
def transport(ev: Eval, dn_old: mat32, t1: wp.vec3, t2: wp.vec3):
    """Express an evaluation made in an old chart (at a point with Jacobian ``dn_old``)
    in the new chart centred there with tangent basis ``(t1, t2)``: with
    ``dn_old M = [t1 t2]``, ``M = (dn_old^T dn_old)^-1 dn_old^T [t1 t2]``,
    ``J_new = J_old M``; cost and albedo are unchanged."""
    c0 = wp.vec3(dn_old[0, 0], dn_old[1, 0], dn_old[2, 0])
    c1 = wp.vec3(dn_old[0, 1], dn_old[1, 1], dn_old[2, 1])
    gm = wp.mat22(wp.dot(c0, c0), wp.dot(c0, c1), wp.dot(c0, c1), wp.dot(c1, c1))
    m0 = solve22(gm, wp.vec2(wp.dot(c0, t1), wp.dot(c1, t1)))
    m1 = solve22(gm, wp.vec2(wp.dot(c0, t2), wp.dot(c1, t2)))
    m = wp.mat22(m0[0], m1[0], m0[1], m1[1])
    out = Eval()
    out.cost = ev.cost
    out.kd = ev.kd
    out.wsum = ev.wsum
    out.jtr = wp.transpose(m) * ev.jtr
    out.jtj = wp.transpose(m) * ev.jtj * m
    return out


@wp.struct
class StartResult:
    """Outcome of one solver run: normal, albedo, reduced cost, cost evaluations used, converged (1) or not."""

    n: wp.vec3
    kd: wp.vec3
    cost: wp.float32
    iters: wp.int32
    converged: wp.int32


@wp.func
def pick_start(start_n: wp.array3d(dtype=wp.vec3), start_kd: wp.array3d(dtype=wp.vec3),
               start_cost: wp.array3d(dtype=wp.float32), start_iters: wp.array3d(dtype=wp.int32),
               start_conv: wp.array3d(dtype=wp.int32), a: int, b: int, nstarts: int, ninit: wp.vec3, v: wp.vec3):
    """The best of the starts a starts-parallel solve kept in scratch at ``[a, b, s]``, by the multi-start loop's
    rule (:func:`gpps.kernels.solve_methods.solve_pixel_for`): in start order, the first strictly lower cost of
    a start that ended facing the camera (cost 1e30 and ``ninit`` if none did).  Returns ``(best, evaluations
    of all starts)``."""
    best = StartResult()
    best.cost = 1.0e30
    best.n = ninit
    total = int(0)
    for st in range(nstarts):
        res = StartResult()
        res.n = start_n[a, b, st]
        res.kd = start_kd[a, b, st]
        res.cost = start_cost[a, b, st]
        res.iters = start_iters[a, b, st]
        res.converged = start_conv[a, b, st]
        total += res.iters
        if res.cost < best.cost and wp.dot(res.n, v) > 0.0:
            best = res
    return best, total


@wp.func
def start_result(n: wp.vec3, ev: Eval, iters: int, converged: int):
    """The :class:`StartResult` of a run that ended at ``n`` with evaluation ``ev``."""
    res = StartResult()
    res.n = n
    res.kd = ev.kd
    res.cost = ev.cost
    res.iters = iters
    res.converged = converged
    return res


@wp.func
def start_normal(s: int, ninit: wp.vec3, v: wp.vec3, hbright: wp.vec3, prm: SolverParams):
    """Start ``s`` of the multi-start: 0 the initial normal, 1 the view direction,
    2 the half vector of the brightest observation (the centre of a highlight),
    3 halfway between that and the initial normal, then the initial normal tilted toward evenly spread azimuths, alternately by
    ``start_angle`` and twice that."""
    if s == 0:
        if wp.dot(ninit, v) <= 0.0:
            # a start facing away from the camera (a warm start, or least squares on a shadowed pixel)
            return toward_camera(ninit, v)
        return ninit
    if s == 1:
        return v
    if s == 2:
        return hbright
    if s == 3:
        return wp.normalize(hbright + ninit)
    # two rings: odd extra starts at start_angle, even ones at twice that, azimuths interleaved
    m = prm.starts - 4
    q = s - 4
    phi = 6.283185307179586 * float(q) / float(m)
    ang = prm.start_angle
    if q % 2 == 1 and m >= 4:
        ang = 2.0 * prm.start_angle
    t1 = tangent_basis_t1(ninit)
    t2 = wp.cross(ninit, t1)
    n = wp.cos(ang) * ninit + wp.sin(ang) * (wp.cos(phi) * t1 + wp.sin(phi) * t2)
    if wp.dot(n, v) <= 0.05:
        # keep the start visible
        n = toward_camera(n, v)
    return wp.normalize(n)


@wp.func
def toward_camera(n: wp.vec3, v: wp.vec3):
    """``n`` pulled toward the view direction ``v`` until ``n.v`` is 0.1 before normalising: a start on the
    visible side."""
    return wp.normalize(n + (0.1 - wp.dot(n, v)) * v)


@wp.func
def counts_for_level(o: wp.vec3, prm: SolverParams, gmax: float):
    """Whether observation ``o`` enters the lit level: not saturated and not below ``shadow_threshold``."""
    ok = grey(o) >= prm.shadow_threshold * gmax
    if prm.saturation > 0.0 and wp.max(o[0], wp.max(o[1], o[2])) >= prm.saturation:
        ok = False
    return ok


@wp.func
def grey_lit_level(images: wp.array3d(dtype=wp.vec3), prm: SolverParams, i: int, j: int, nl_: int, gmax: float):
    """The pixel's lit level: the largest grey value that at least a quarter (rounded up) of its observations
    reach, among those neither saturated nor below ``prm.shadow_threshold * gmax`` (the caller's ``valid`` is not
    consulted: a scale, not a data term, computed in the solve, where that buffer is not passed).  With up to 4 such
    observations it is the brightest.  Unlike the brightest it does not follow one highlight, and unlike the
    median it stays on the lit observations of a pixel shadowed for half of its lights.  ``O(N^2)`` comparisons,
    no scratch memory (each value's rank is counted); 0 when no observation counts."""
    n = int(0)
    for k in range(nl_):
        if counts_for_level(images[k, i, j], prm, gmax):
            n += 1
    need = (n + 3) // 4
    level = float(0.0)
    for k in range(nl_):
        o = images[k, i, j]
        g = grey(o)
        if g > level and counts_for_level(o, prm, gmax):
            above = int(0)
            for m in range(nl_):
                om = images[m, i, j]
                if grey(om) >= g and counts_for_level(om, prm, gmax):
                    above += 1
            if above >= need:
                level = g
    return level


@wp.func
def in_fit(w: float):
    """Whether an observation of weight ``w`` enters the fit (kept or dark; not dropped, not set aside)."""
    return w != 0.0 and w != ASIDE


@wp.func
def light_gram_range(weights: wp.array3d(dtype=wp.float32), i: int, j: int, p: wp.vec3, lights: LightParams,
                     k0: int, dk: int):
    """``sum_k [w_k != 0] l_k l_k^T`` over the valid lights ``k0, k0 + dk, ...`` (dark ones included)."""
    a = wp.mat33(0.0)
    for k in range(k0, lights.count, dk):
        if in_fit(weights[k, i, j]):
            l = light_dir(lights, k, p)
            a += wp.outer(l, l)
    return a


@wp.func
def light_gram(weights: wp.array3d(dtype=wp.float32), i: int, j: int, p: wp.vec3, lights: LightParams):
    """``sum_k [w_k != 0] l_k l_k^T`` over the pixel's valid lights (dark ones included)."""
    return light_gram_range(weights, i, j, p, lights, 0, 1)


@wp.func
def cond_frobenius(a: wp.mat33):
    """Frobenius condition number ``|A|_F |A^-1|_F`` of a symmetric 3x3 (inf when singular; determinant checked)."""
    det = wp.determinant(a)
    fa = wp.sqrt(wp.ddot(a, a))
    if wp.abs(det) <= 1.0e-12 * fa * fa * fa or fa == 0.0:
        return 1.0e30
    ai = wp.inverse(a)
    return fa * wp.sqrt(wp.ddot(ai, ai))


@wp.func
def grey_max(images: wp.array3d(dtype=wp.vec3), i: int, j: int, nl_: int):
    """Brightest grey value of the pixel's ``nl_`` observations (0 when none is brighter)."""
    gmax = float(0.0)
    for k in range(nl_):
        gmax = wp.max(gmax, grey(images[k, i, j]))
    return gmax


@wp.struct
class PixelSolution:
    """Best solution of a pixel and the total number of cost evaluations spent."""

    best: StartResult
    total: wp.int32


@wp.func
def brightest_light(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel,
                    lights: LightParams):
    """``(grey value, light)`` of the first brightest valid observation among the lane's lights
    ``px.lane, px.lane + px.lanes, ...`` (all of them on one lane); ``(-1, lights.count)`` when none."""
    kb = int(lights.count)
    gb = float(-1.0)
    for k in range(px.lane, lights.count, px.lanes):
        if in_fit(weights[k, px.i, px.j]):
            gk = grey(images[k, px.i, px.j])
            if gk > gb:
                gb = gk
                kb = k
    return gb, kb


@wp.func
def half_vector_of(kb: int, px: Pixel, lights: LightParams):
    """Half vector ``normalize(l + v)`` of light ``kb`` (light 0 when ``kb`` is ``lights.count``: none valid)."""
    k = kb
    if k >= lights.count:
        k = 0
    return wp.normalize(light_dir(lights, k, px.p) + px.v)


@wp.func
def brightest_half_vector(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel, lights: LightParams):
    """Half vector ``normalize(l + v)`` of the brightest valid observation: where a highlight peaks."""
    gb, kb = brightest_light(images, weights, px, lights)
    return half_vector_of(kb, px, lights)


@wp.func
def weight_sum(weights: wp.array3d(dtype=wp.float32), px: Pixel, nl_: int):
    """``sum |w_k|`` over the lane's lights ``px.lane, px.lane + px.lanes, ...`` (all of them on one lane)."""
    wsum = float(0.0)
    for k in range(px.lane, nl_, px.lanes):
        wsum += wp.abs(weights[k, px.i, px.j])
    return wsum


@wp.func
def store_solution_sum(
    sol: PixelSolution,
    flag: int,
    wsum: float,
    px: Pixel,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """Write a pixel's solution (lane 0 of its lanes); ``wsum``: the sum of its |weights| (all lights)."""
    if px.lane == 0:
        i = px.i
        j = px.j
        f = flag
        if sol.best.converged == 0:
            f = f | FLAG_NOT_CONVERGED
        normals[i, j] = sol.best.n
        albedo[i, j] = sol.best.kd
        if wsum > 0.0:
            residual[i, j] = wp.sqrt(2.0 * sol.best.cost / (3.0 * wsum))
        else:
            residual[i, j] = 0.0
        iterations[i, j] = sol.total
        flags[i, j] = f


@wp.func
def store_solution(
    sol: PixelSolution,
    flag: int,
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    nl_: int,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """Write a pixel's solution (one thread a pixel)."""
    store_solution_sum(sol, flag, weight_sum(weights, px, nl_), px, normals, albedo, residual, iterations, flags)


@wp.func
def pixel_at(i: int, j: int, point: wp.vec3, view: wp.vec3, prm: SolverParams):
    """The :class:`Pixel` with array indices (i, j), surface point and view direction (no prior, albedo free)."""
    px = Pixel()
    px.i = i
    px.j = j
    px.p = point
    px.v = view
    px.fix_kd = 0
    px.kd = wp.vec3(0.0)
    px.grey_albedo = prm.grey_albedo
    px.prior_w = 0.0
    px.prior_n = wp.vec3(0.0)
    px.lane = 0
    px.lanes = 1
    px.visible_only = 0
    return px


@wp.func
def make_pixel(cam: CameraParams, depth: wp.array2d(dtype=wp.float32), i: int, j: int, prm: SolverParams):
    """The :class:`Pixel` of image pixel (i, j) at its depth."""
    point = pixel_point(cam, i, j, depth[i, j])
    return pixel_at(i, j, point, view_dir(cam, point), prm)


@wp.func
def store_least_squares(
    ninit: wp.vec3,
    kdw: wp.vec3,
    flag: int,
    use_all: int,
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    lights: LightParams,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """Store the Lambertian least-squares (Woodham) solution of solver ``"none"``."""
    i = px.i
    j = px.j
    p = px.p
    nl_ = lights.count
    normals[i, j] = ninit
    albedo[i, j] = wp.vec3(wp.max(kdw[0], 0.0), wp.max(kdw[1], 0.0), wp.max(kdw[2], 0.0))
    # residual of the Lambertian fit (no shadows in the model: plain least squares)
    rs = float(0.0)
    ws = float(0.0)
    for k in range(nl_):
        if use_all != 0 or in_fit(weights[k, i, j]):
            l = light_dir(lights, k, p)
            e = light_radiance(lights, k, p)
            o = images[k, i, j]
            for c in range(3):
                r = o[c] - e[c] * kdw[c] * wp.dot(ninit, l)
                rs += r * r
            ws += 3.0
    if ws > 0.0:
        residual[i, j] = wp.sqrt(rs / ws)
    else:
        residual[i, j] = 0.0
    iterations[i, j] = 0
    flags[i, j] = flag


@wp.func
def albedo_floor(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel,
                 lights: LightParams):
    """``max_k grey(I_k) / grey(E_k(p))`` over the lane's observations in the fit (:func:`in_fit`), 0 when none.

    With the image model ``I_k = E_k (kd t_d,k + ks t_s,k)`` (``t_s >= 0``) every kept observation has
    ``grey(kd) t_d,k <= grey(I_k) / grey(E_k)``, so an albedo above ``floor / s`` puts every one of them at a
    diffuse shading ``t_d,k`` below ``s`` (:func:`unfounded_flag`)."""
    f = float(0.0)
    for k in range(px.lane, lights.count, px.lanes):
        if in_fit(weights[k, px.i, px.j]):
            e = grey(light_radiance(lights, k, px.p))
            if e > 0.0:
                f = wp.max(f, grey(images[k, px.i, px.j]) / e)
    return f


@wp.func
def unfounded_flag(kd: wp.vec3, floor: float):
    """``FLAG_UNFOUNDED | FLAG_FEW_OBSERVATIONS`` when the fitted albedo ``kd`` exceeds ``floor`` (the pixel's
    :func:`albedo_floor`) over :data:`gpps.names.UNFOUNDED_SHADING`, else 0: the fit explains every observation
    it kept with a diffuse shading below that level, so the data do not fix the albedo (nor, through it, the
    normal).  The FEW bit sends the pixel to the neighbour pass (its neighbours' albedo held) and keeps it out of
    other pixels' neighbour statistics."""
    if grey(kd) * UNFOUNDED_SHADING > floor:
        return FLAG_UNFOUNDED | FLAG_FEW_OBSERVATIONS
    return int(0)


@wp.func
def store_checked(
    sol: PixelSolution,
    flag: int,
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    lights: LightParams,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """:func:`store_solution` of a free-albedo fit, flagged by :func:`unfounded_flag` (one thread a pixel)."""
    f = flag | unfounded_flag(sol.best.kd, albedo_floor(images, weights, px, lights))
    store_solution(sol, f, weights, px, lights.count, normals, albedo, residual, iterations, flags)


# ---------------------------------------------------------------- lights-parallel pieces
# Used only by the lights-parallel builds (``lanes=True`` in :func:`gpps.kernels.solve_methods.solver_funcs`),
# launched with ``wp.launch_tiled`` so that one block of ``lanes`` threads solves one pixel: every lane runs
# the same (uniform) solver steps and takes a strided share of the light loops; the sums are reduced over
# the block (``wp.tile_sum``) and every lane reads the same total, so the lanes' control flow stays uniform.
# A lane reads and writes only the weights of its own lights: no lane waits for another's memory writes.


@wp.func
def lanes_sum(x: float):
    """Sum of a scalar over the block's lanes (every lane gets it)."""
    return wp.tile_sum(wp.tile(x))[0]


@wp.func
def lanes_sum19(x: vec19):
    """Sum of a :data:`vec19` over the block's lanes (every lane gets it)."""
    return wp.tile_sum(wp.tile(x, preserve_type=True))[0]


@wp.func
def lanes_sum6(x: vec6):
    """Sum of a :data:`vec6` over the block's lanes (every lane gets it)."""
    return wp.tile_sum(wp.tile(x, preserve_type=True))[0]


@wp.func
def brightest_half_vector_lanes(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel,
                                lights: LightParams):
    """:func:`brightest_half_vector` over the lanes: the same light (the first of the brightest valid ones)."""
    gb, kb = brightest_light(images, weights, px, lights)
    gm = wp.tile_max(wp.tile(gb))[0]
    if gb != gm:
        kb = lights.count
    kb = wp.tile_min(wp.tile(kb))[0]
    return half_vector_of(kb, px, lights)


@wp.func
def store_solution_lanes(
    sol: PixelSolution,
    flag: int,
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    nl_: int,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """:func:`store_solution` over the lanes: the weight sum reduced over the block, lane 0 writes."""
    wsum = lanes_sum(weight_sum(weights, px, nl_))
    store_solution_sum(sol, flag, wsum, px, normals, albedo, residual, iterations, flags)


@wp.func
def store_checked_lanes(
    sol: PixelSolution,
    flag: int,
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    px: Pixel,
    lights: LightParams,
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
    residual: wp.array2d(dtype=wp.float32),
    iterations: wp.array2d(dtype=wp.int32),
    flags: wp.array2d(dtype=wp.int32),
):
    """:func:`store_checked` over the lanes: the albedo floor's maximum reduced over the block."""
    floor = wp.tile_max(wp.tile(albedo_floor(images, weights, px, lights)))[0]
    f = flag | unfounded_flag(sol.best.kd, floor)
    store_solution_lanes(sol, f, weights, px, lights.count, normals, albedo, residual, iterations, flags)
