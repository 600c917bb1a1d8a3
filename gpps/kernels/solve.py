"""Per-pixel calibrated photometric stereo: one thread solves one pixel.

Device math only; buffers and launches live in :mod:`gpps.pipeline.solver`.

Image model per light k and channel c (seed 4.1-4.2, 2.30-2.31)::

    I_kc = E_kc(p) * ( kd_c * max(n.l_k, 0) + ks * s(n, l_k, v) )

with ``l_k``, ``E_kc`` from :func:`gpps.kernels.brdf.light_dir` and
:func:`gpps.kernels.brdf.light_radiance` at the surface point ``p`` that the
pixel sees at the given depth (per-pixel direction and 1/r^2 fall-off for
point lights), ``v`` the view direction.

Unknowns: the normal, 2 degrees of freedom through the chart of
:mod:`gpps.kernels.jacobians` (re-centred on the current normal, so no
singularity anywhere on the visible hemisphere), and the albedo (1 or 3
channels).  The albedo enters linearly and is eliminated by *variable
projection*: for a given normal ``kd_c = sum_k w a y / sum_k w a^2`` with
``a_kc = E_kc max(n.l_k, 0)``, ``y_kc = I_kc - E_kc ks s_k``; the solvers then
minimise the reduced cost ``F(x) = 1/2 sum_kc w_k (y_kc - kd_c(x) a_kc)^2`` over
the 2 chart coordinates only, with its exact Jacobian (including
``d kd / dx``).  Each evaluation makes two passes over the N lights (N is a
runtime size; nothing is stored per light except the weight buffer).

Observation weights ``w_k`` (the (N, H, W) buffer) are 0 for dropped
observations (shadow: grey value below ``shadow_threshold`` times the pixel's
brightest; saturated: a channel >= ``saturation``; or masked out by the
caller's ``valid``) and otherwise 1, times the robust (IRLS) weight of the
Huber or Cauchy loss after each reweighting round.  A *dark* observation
(grey value within ``lit_sigmas`` noise levels of 0: attached or cast shadow,
or as good as) gets ``w_k = -1``: a one-sided term ``1/2 min(0, y - kd a)^2``
that only penalises a model brighter than the observation, i.e. the
inequality ``n.l <= ~0`` of an attached shadow, without letting the clipped
positive noise of a shadowed pixel pull the normal toward the terminator.
It does not enter the albedo's elimination (the albedo is that of the lit
observations, so the reduced cost and its exact Jacobian stay as above).

Specialisation: Warp emits every ``@wp.func`` a kernel reaches, and a kernel
that switched at run time between the solvers, the five reflectance models and
the robust losses carried all of them (NVRTC then inlines them at every call
site).  :func:`get_solve_kernels` instead builds, once per
``(method, brdf, robust)``, the two kernels in a Warp module of their own from
the functions that :func:`_solver_funcs` defines with ``wp.static``
conditions: the branches of the other solvers, models and losses are dropped
at code generation, so each module holds only the code its launch runs.  The
other settings (iterations, tolerances, starts, thresholds, ...) stay run-time
fields of :class:`SolverParams`.  The kernels are forward-only
(``enable_backward=False``): nothing differentiates through the solver.
"""

from types import SimpleNamespace

import warp as wp

from gpps import names

from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams, light_dir, light_radiance, pixel_point, view_dir
from gpps.kernels.jacobians import (
    ashikhmin_shirley_value_grad,
    blinn_phong_value_grad,
    chart_normal,
    chart_normal_jacobian,
    cook_torrance_value_grad,
    diffuse_value_grad,
    mat32,
    phong_value_grad,
    specular_value_grad,
    tangent_basis_t1,
)

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

NEIGHBOUR_MIN_COUNT = 16  # well-determined pixels the neighbour pass gathers (before its 2 extra rings)
WEISZFELD_ITERS = wp.constant(8)  # iterations of the neighbours' geometric median
LINEAR_ITERS = wp.constant(5)  # IRLS rounds of the neighbours' first-order normal model



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
    saturation: wp.float32
    warm_start: wp.int32
    grey_albedo: wp.int32
    cond_threshold: wp.float32
    early_exit: wp.int32
    lm_tau: wp.float32
    dogleg_radius: wp.float32
    lit_threshold: wp.float32
    lit_sigmas: wp.float32
    keep_unmasked: wp.int32  # 1: pixels outside the mask keep their outputs (a re-solve of a subset)


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
    return (c[0] + c[1] + c[2]) / 3.0


@wp.func
def _dot2(a: wp.vec2, b: wp.vec2):
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
    n: wp.vec3
    kd: wp.vec3
    cost: wp.float32
    iters: wp.int32
    converged: wp.int32


@wp.func
def _result(n: wp.vec3, ev: Eval, iters: int, converged: int):
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
        # keep the start visible: pull it toward the camera
        n = wp.normalize(n + (0.1 - wp.dot(n, v)) * v)
    return wp.normalize(n)


@wp.func
def light_gram(weights: wp.array3d(dtype=wp.float32), i: int, j: int, p: wp.vec3, lights: LightParams):
    """``sum_k [w_k != 0] l_k l_k^T`` over the pixel's valid lights (dark ones included)."""
    a = wp.mat33(0.0)
    for k in range(lights.count):
        if weights[k, i, j] != 0.0:
            l = light_dir(lights, k, p)
            a += wp.outer(l, l)
    return a


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
def ring_offset(r: int, t: int):
    """Offset ``(di, dj)`` of the ``t``-th pixel (``0 <= t < 8 r``) of the square ring of radius ``r``."""
    side = t / (2 * r)
    o = t % (2 * r)
    if side == 0:
        return -r, -r + o
    if side == 1:
        return -r + o, r
    if side == 2:
        return r, r - o
    return r - o, -r


@wp.func
def is_determined(mask: wp.array2d(dtype=wp.uint8), flags: wp.array2d(dtype=wp.int32), ii: int, jj: int):
    """True for a pixel inside the image and the mask with at least 3 lit observations."""
    if ii < 0 or ii >= mask.shape[0] or jj < 0 or jj >= mask.shape[1]:
        return False
    if mask[ii, jj] == wp.uint8(0):
        return False
    return (flags[ii, jj] & FLAG_FEW_OBSERVATIONS) == 0


@wp.struct
class NeighbourStats:
    """Robust albedo and normal of the well-determined pixels around an under-determined one."""

    kd: wp.vec3
    n: wp.vec3
    n_lin: wp.vec3
    lin_ok: wp.int32
    count: wp.float32
    reach: wp.int32


@wp.func
def neighbour_stats(
    i: int,
    j: int,
    radius: int,
    min_count: int,
    mask: wp.array2d(dtype=wp.uint8),
    flags: wp.array2d(dtype=wp.int32),
    normals: wp.array2d(dtype=wp.vec3),
    albedo: wp.array2d(dtype=wp.vec3),
):
    """Geometric medians of the albedo and the normal of the nearest well-determined pixels.

    Square rings around ``(i, j)`` are searched until ``min_count`` well-determined
    pixels are found (or ``radius``), then 2 rings more.  The location is the
    geometric (spatial) median ``argmin_m sum_q |x_q - m|`` by Weiszfeld's
    iteration ``m <- sum_q x_q / |x_q - m| / sum_q 1 / |x_q - m|`` from the mean
    (Weiszfeld 1937; breakdown point 1/2): a few grazing pixels whose shadowed
    observation noise made them look lit, with a wrong albedo, cannot pull it.
    ``n_lin``: the first-order (affine) model ``n(q) = c + g_i di + g_j dj`` of
    the same pixels' normals fitted by least absolute deviations (IRLS with
    weights ``1 / |residual|``, ``LINEAR_ITERS`` rounds from least squares),
    evaluated at the pixel (``c``): on a rim the neighbours lie on one side and
    the normal keeps turning, so their median lags where the extrapolation does
    not.  ``lin_ok`` 0: the fit was singular (neighbours on a line).
    ``count`` 0: none found.
    """
    out = NeighbourStats()
    acc = wp.vec3(0.0)
    nacc = wp.vec3(0.0)
    cnt = float(0.0)
    r_stop = radius
    reach = int(0)
    for r in range(1, radius + 1):
        if r > r_stop:
            break
        reach = r
        for t in range(8 * r):
            di, dj = ring_offset(r, t)
            if is_determined(mask, flags, i + di, j + dj):
                acc += albedo[i + di, j + dj]
                nacc += normals[i + di, j + dj]
                cnt += 1.0
        if cnt >= float(min_count) and r_stop == radius:
            r_stop = wp.min(r + 2, radius)
    out.count = cnt
    out.reach = reach
    if cnt == 0.0:
        out.kd = wp.vec3(0.0)
        out.n = wp.vec3(0.0)
        return out
    mk = acc / cnt
    mn = nacc / cnt
    for it in range(WEISZFELD_ITERS):
        ak = wp.vec3(0.0)
        an = wp.vec3(0.0)
        wk = float(0.0)
        wn = float(0.0)
        ek = 1.0e-4 * wp.length(mk) + 1.0e-12
        for r in range(1, reach + 1):
            for t in range(8 * r):
                di, dj = ring_offset(r, t)
                if is_determined(mask, flags, i + di, j + dj):
                    a = albedo[i + di, j + dj]
                    q = normals[i + di, j + dj]
                    u = 1.0 / wp.max(wp.length(a - mk), ek)
                    z = 1.0 / wp.max(wp.length(q - mn), 1.0e-4)
                    ak += u * a
                    wk += u
                    an += z * q
                    wn += z
        mk = ak / wk
        mn = an / wn
    out.kd = mk
    out.n = mn
    # first-order model n(q) = c + g_i di + g_j dj of the neighbours' normals, least absolute
    # deviations by IRLS (weights 1 / |residual|); c extrapolates the field to the pixel
    lin = wp.vec3(mn)
    gi = wp.vec3(0.0)
    gj = wp.vec3(0.0)
    ok = int(0)
    for it in range(LINEAR_ITERS):
        am = wp.mat33(0.0)
        b0 = wp.vec3(0.0)
        b1 = wp.vec3(0.0)
        b2 = wp.vec3(0.0)
        for r in range(1, reach + 1):
            for t in range(8 * r):
                di, dj = ring_offset(r, t)
                if is_determined(mask, flags, i + di, j + dj):
                    q = normals[i + di, j + dj]
                    x = wp.vec3(1.0, float(di), float(dj))
                    wgt = float(1.0)
                    if it > 0:
                        wgt = 1.0 / wp.max(wp.length(q - lin - float(di) * gi - float(dj) * gj), 1.0e-3)
                    am += wgt * wp.outer(x, x)
                    b0 += wgt * q[0] * x
                    b1 += wgt * q[1] * x
                    b2 += wgt * q[2] * x
        fa = wp.sqrt(wp.ddot(am, am))
        if wp.abs(wp.determinant(am)) <= 1.0e-6 * fa * fa * fa:
            ok = 0
            break
        ai = wp.inverse(am)
        c0 = ai * b0
        c1 = ai * b1
        c2 = ai * b2
        lin = wp.vec3(c0[0], c1[0], c2[0])
        gi = wp.vec3(c0[1], c1[1], c2[1])
        gj = wp.vec3(c0[2], c1[2], c2[2])
        ok = 1
    out.n_lin = lin
    out.lin_ok = ok
    return out


@wp.struct
class PixelSolution:
    """Best solution of a pixel and the total number of cost evaluations spent."""

    best: StartResult
    total: wp.int32


@wp.func
def brightest_half_vector(images: wp.array3d(dtype=wp.vec3), weights: wp.array3d(dtype=wp.float32), px: Pixel, lights: LightParams):
    """Half vector ``normalize(l + v)`` of the brightest valid observation: where a highlight peaks."""
    kb = int(0)
    gb = float(-1.0)
    for k in range(lights.count):
        if weights[k, px.i, px.j] != 0.0:
            gk = grey(images[k, px.i, px.j])
            if gk > gb:
                gb = gk
                kb = k
    return wp.normalize(light_dir(lights, kb, px.p) + px.v)


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
    i = px.i
    j = px.j
    wsum = float(0.0)
    for k in range(nl_):
        wsum += wp.abs(weights[k, i, j])
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
def make_pixel(cam: CameraParams, depth: wp.array2d(dtype=wp.float32), i: int, j: int, prm: SolverParams):
    px = Pixel()
    px.i = i
    px.j = j
    px.p = pixel_point(cam, i, j, depth[i, j])
    px.v = view_dir(cam, px.p)
    px.fix_kd = 0
    px.kd = wp.vec3(0.0)
    px.grey_albedo = prm.grey_albedo
    px.prior_w = 0.0
    px.prior_n = wp.vec3(0.0)
    return px


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
        if use_all != 0 or weights[k, i, j] != 0.0:
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


# --------------------------------------------------------------------------- specialisation

METHODS = names.SOLVER_NAMES
BRDFS = names.BRDF_NAMES
ROBUST = names.ROBUST_NAMES


def _specular_value_grad_for(brdf, module, sfx: str):
    """:func:`gpps.kernels.jacobians.specular_value_grad` with the model fixed at code generation.

    Same gating and lobes as the run-time dispatcher (``mat.model`` is not
    read); ``brdf=None`` returns the run-time dispatcher itself.
    """
    if brdf is None:
        return specular_value_grad

    @wp.func(name="specular_value_grad" + sfx, module=module)
    def spec_vg(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
        if wp.static(brdf == "lambertian"):
            return wp.vec4(0.0)
        else:
            if wp.dot(n, l) <= 0.0 or wp.dot(n, v) <= 0.0:
                return wp.vec4(0.0)
            if wp.static(brdf == "phong"):
                return phong_value_grad(n, l, v, mat.shininess)
            elif wp.static(brdf == "blinn-phong"):
                return blinn_phong_value_grad(n, l, v, mat.shininess)
            elif wp.static(brdf == "cook-torrance"):
                return cook_torrance_value_grad(n, l, v, mat.roughness, mat.f0)
            else:
                return ashikhmin_shirley_value_grad(n, l, v, mat.eta_u, mat.eta_v, mat.f0)

    return spec_vg


def _solver_funcs(method, brdf, robust, module=None, sfx: str = ""):
    """Define the solver functions for one ``(method, brdf, robust)``.

    ``None`` for any of them keeps that choice a run-time switch on
    ``prm.method`` / ``mat.model`` / ``prm.robust`` (the generic build).  The
    ``wp.static`` conditions are evaluated at code generation, so only the
    chosen branches are emitted.  ``module`` / ``sfx``: Warp module and key
    suffix of the functions (distinct per specialisation).
    """
    spec_vg = _specular_value_grad_for(brdf, module, sfx)

    @wp.func(name="light_terms" + sfx, module=module)
    def light_terms(
        images: wp.array3d(dtype=wp.vec3),
        lights: LightParams,
        mat: MaterialParams,
        k: int,
        i: int,
        j: int,
        p: wp.vec3,
        n: wp.vec3,
        v: wp.vec3,
        dn0: wp.vec3,
        dn1: wp.vec3,
    ):
        """Light k at the pixel: radiance, observation, diffuse and specular values and their chart derivatives."""
        l = light_dir(lights, k, p)
        dg = diffuse_value_grad(n, l)
        sg = spec_vg(mat, n, l, v)
        gd = wp.vec3(dg[1], dg[2], dg[3])
        gs = wp.vec3(sg[1], sg[2], sg[3])
        return (
            light_radiance(lights, k, p),
            images[k, i, j],
            dg[0],
            sg[0],
            wp.dot(gd, dn0),
            wp.dot(gd, dn1),
            wp.dot(gs, dn0),
            wp.dot(gs, dn1),
        )

    @wp.func(name="evaluate" + sfx, module=module)
    def evaluate(
        n0: wp.vec3,
        t1: wp.vec3,
        t2: wp.vec3,
        x: wp.vec2,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
    ):
        """Variable-projection evaluation of the reduced cost at ``n(x)`` (4.2 with kd eliminated).

        Two passes over the lights: the albedo's normal equations (and their
        derivatives) must be complete before the residuals can be formed, so
        ``light_terms`` is evaluated twice per light; caching it would need
        per-light scratch memory (N is a run-time size).
        """
        i = px.i
        j = px.j
        p = px.p
        v = px.v
        grey_albedo = px.grey_albedo
        n = chart_normal(n0, t1, t2, x)
        dn = chart_normal_jacobian(n0, t1, t2, x)
        dn0 = wp.vec3(dn[0, 0], dn[1, 0], dn[2, 0])
        dn1 = wp.vec3(dn[0, 1], dn[1, 1], dn[2, 1])
        ks = mat.ks
        # pass 1: normal equations of the albedo and their derivatives
        saa = wp.vec3(0.0)
        say = wp.vec3(0.0)
        dsaa0 = wp.vec3(0.0)
        dsaa1 = wp.vec3(0.0)
        dsay0 = wp.vec3(0.0)
        dsay1 = wp.vec3(0.0)
        wsum = float(0.0)
        for k in range(lights.count):
            w = weights[k, i, j]
            if w > 0.0:
                e, obs, dval, sval, da0, da1, ds0, ds1 = light_terms(images, lights, mat, k, i, j, p, n, v, dn0, dn1)
                wsum += w
                for c in range(3):
                    a = e[c] * dval
                    y = obs[c] - e[c] * ks * sval
                    a0 = e[c] * da0
                    a1 = e[c] * da1
                    y0 = -e[c] * ks * ds0
                    y1 = -e[c] * ks * ds1
                    saa[c] += w * a * a
                    say[c] += w * a * y
                    dsaa0[c] += w * 2.0 * a * a0
                    dsaa1[c] += w * 2.0 * a * a1
                    dsay0[c] += w * (a0 * y + a * y0)
                    dsay1[c] += w * (a1 * y + a * y1)
        if grey_albedo != 0:
            saa = wp.vec3(saa[0] + saa[1] + saa[2])
            say = wp.vec3(say[0] + say[1] + say[2])
            dsaa0 = wp.vec3(dsaa0[0] + dsaa0[1] + dsaa0[2])
            dsaa1 = wp.vec3(dsaa1[0] + dsaa1[1] + dsaa1[2])
            dsay0 = wp.vec3(dsay0[0] + dsay0[1] + dsay0[2])
            dsay1 = wp.vec3(dsay1[0] + dsay1[1] + dsay1[2])
        kd = wp.vec3(0.0)
        dkd0 = wp.vec3(0.0)
        dkd1 = wp.vec3(0.0)
        if px.fix_kd != 0:
            kd = px.kd
        for c in range(3):
            if px.fix_kd == 0 and saa[c] > 1.0e-20:
                kc = say[c] / saa[c]
                if kc > 0.0:
                    kd[c] = kc
                    dkd0[c] = (dsay0[c] - kc * dsaa0[c]) / saa[c]
                    dkd1[c] = (dsay1[c] - kc * dsaa1[c]) / saa[c]
        # pass 2: residuals r = y - kd a and their exact derivatives
        cost = float(0.0)
        jtj = wp.mat22(0.0)
        jtr = wp.vec2(0.0)
        for k in range(lights.count):
            w = weights[k, i, j]
            if w != 0.0:
                e, obs, dval, sval, da0, da1, ds0, ds1 = light_terms(images, lights, mat, k, i, j, p, n, v, dn0, dn1)
                for c in range(3):
                    a = e[c] * dval
                    r = obs[c] - e[c] * ks * sval - kd[c] * a
                    # a dark observation (w < 0) only bounds the model from above: n.l <= about 0
                    if w > 0.0 or r < 0.0:
                        wa = wp.abs(w)
                        j0 = -e[c] * ks * ds0 - dkd0[c] * a - kd[c] * e[c] * da0
                        j1 = -e[c] * ks * ds1 - dkd1[c] * a - kd[c] * e[c] * da1
                        cost += 0.5 * wa * r * r
                        jtr += wa * r * wp.vec2(j0, j1)
                        jtj += wa * wp.mat22(j0 * j0, j0 * j1, j0 * j1, j1 * j1)
        if px.prior_w > 0.0:
            dp = n - px.prior_n
            cost += 0.5 * px.prior_w * wp.dot(dp, dp)
            jtr += px.prior_w * wp.vec2(wp.dot(dn0, dp), wp.dot(dn1, dp))
            jtj += px.prior_w * wp.mat22(wp.dot(dn0, dn0), wp.dot(dn0, dn1), wp.dot(dn0, dn1), wp.dot(dn1, dn1))
        ev = Eval()
        ev.cost = cost
        ev.jtj = jtj
        ev.jtr = jtr
        ev.kd = kd
        ev.wsum = wsum
        return ev

    @wp.func(name="run_lm" + sfx, module=module)
    def run_lm(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Levenberg-Marquardt (Algorithm 4; Madsen-Nielsen damping update), chart re-centred at each accepted step.

        ``d = -(J^T J + lambda I)^-1 J^T r``; gain ratio
        ``rho = (F(x) - F(x + d)) / (1/2 d^T (lambda d - J^T r))`` (Algorithm 4's
        denominator is ``L(0) - L(d)`` of the Gauss-Newton model); accepted steps
        shrink lambda by ``max(1/3, 1 - (2 rho - 1)^3)``, rejected ones grow it by
        ``nu`` and double ``nu``.  Stops on ``|J^T r|_inf <= tol_grad``, a step
        ``<= tol_step`` (radians), or ``max_iters`` evaluations.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        zero = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, zero, images, weights, px, lights, mat)
        lam = prm.lm_tau * wp.max(wp.max(ev.jtj[0, 0], ev.jtj[1, 1]), 1.0e-20)
        nu = float(2.0)
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad:
                converged = 1
                if prm.early_exit != 0:
                    break
            a = ev.jtj + wp.mat22(lam, 0.0, 0.0, lam)
            d = -solve22(a, g)
            k += 1
            if wp.length(d) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            trial = evaluate(n0, t1, t2, d, images, weights, px, lights, mat)
            pred = 0.5 * (lam * _dot2(d, d) - _dot2(d, g))
            rho = float(-1.0)
            if pred > 0.0:
                rho = (ev.cost - trial.cost) / pred
            if rho > 0.0:
                # re-centre the chart on the accepted normal, reusing the trial's Jacobian
                dn_old = chart_normal_jacobian(n0, t1, t2, d)
                n0 = chart_normal(n0, t1, t2, d)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                ev = transport(trial, dn_old, t1, t2)
                t = 2.0 * rho - 1.0
                lam = lam * wp.max(1.0 / 3.0, 1.0 - t * t * t)
                nu = 2.0
            else:
                lam = lam * nu
                nu = 2.0 * nu
                if lam > 1.0e16:
                    converged = 1
                    if prm.early_exit != 0:
                        break
        return _result(n0, ev, k, converged)


    @wp.func(name="run_dogleg" + sfx, module=module)
    def run_dogleg(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Powell's dog leg (Algorithm 5, 4.10-4.15) on the reduced problem.

        ``h_sd = -g`` with ``g = J^T r`` and Cauchy step length
        ``alpha = |g|^2 / |J g|^2`` (4.15); ``h_gn = -(J^T J)^-1 g`` (the
        least-squares form of 4.10 for N > 2 residuals); the dog-leg step is
        (4.12-4.14) with beta chosen so that ``|h_dl| = Delta``.

        Algorithm 5's ``L(0) - L(h_dl)`` is garbled in the text; the correct gain
        ratio denominator is the decrease of the Gauss-Newton model
        ``L(0) - L(h) = -h^T g - 1/2 h^T J^T J h``, which reduces to Madsen et al.'s
        cases: ``F(x)`` for the Gauss-Newton step (when J is square), ``Delta (2
        |alpha g| - Delta) / (2 alpha)`` for the clipped steepest-descent step and
        ``1/2 alpha (1 - beta)^2 |g|^2 + beta (2 - beta) F(x)`` otherwise.  We
        evaluate the general expression.  Radius: ``rho > 0.75`` ->
        ``Delta = max(Delta, 3 |h|)``, ``rho < 0.25`` -> ``Delta / 2``.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        zero = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, zero, images, weights, px, lights, mat)
        delta = prm.dogleg_radius
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad or delta <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            a = ev.jtj
            gag = _dot2(g, a * g)
            gg = _dot2(g, g)
            alpha = float(0.0)
            if gag > 0.0:
                alpha = gg / gag
            hgn = -solve22(a, g)
            if _dot2(hgn, hgn) == 0.0:
                # singular J^T J: a tiny damping keeps the Gauss-Newton leg defined
                tr = a[0, 0] + a[1, 1]
                hgn = -solve22(a + wp.mat22(1.0e-6 * tr + 1.0e-20, 0.0, 0.0, 1.0e-6 * tr + 1.0e-20), g)
            h = wp.vec2(0.0)
            lg = wp.sqrt(gg)
            if wp.length(hgn) <= delta:
                h = hgn
            elif alpha * lg >= delta or alpha == 0.0:
                if lg > 0.0:
                    h = -(delta / lg) * g
            else:
                sa = -alpha * g
                bma = hgn - sa
                c = _dot2(sa, bma)
                b2 = _dot2(bma, bma)
                disc = wp.max(c * c + b2 * (delta * delta - _dot2(sa, sa)), 0.0)
                beta = float(0.0)
                if b2 > 0.0:
                    beta = (-c + wp.sqrt(disc)) / b2
                h = sa + beta * bma
            k += 1
            if wp.length(h) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            trial = evaluate(n0, t1, t2, h, images, weights, px, lights, mat)
            pred = -_dot2(h, g) - 0.5 * _dot2(h, a * h)
            rho = float(-1.0)
            if pred > 0.0:
                rho = (ev.cost - trial.cost) / pred
            if rho > 0.0:
                dn_old = chart_normal_jacobian(n0, t1, t2, h)
                n0 = chart_normal(n0, t1, t2, h)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                ev = transport(trial, dn_old, t1, t2)
            if rho > 0.75:
                delta = wp.max(delta, 3.0 * wp.length(h))
            elif rho < 0.25:
                delta = 0.5 * delta
        return _result(n0, ev, k, converged)


    @wp.func(name="run_bfgs" + sfx, module=module)
    def run_bfgs(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Quasi-Newton with BFGS updates (Algorithm 3, 4.4-4.8) and a backtracking Armijo line search.

        The chart is kept fixed (so the secant pairs live in one coordinate system)
        and re-centred, with B reset, only when ``|x| > 0.5``.  ``B0`` is the
        Gauss-Newton matrix ``J^T J`` (plus a tiny ridge), a standard choice for
        least squares.  B is updated only when ``Theta^T Y > sqrt(eps) |Theta| |Y|``
        (Algorithm 3).  Stops on ``|grad| <= tol_grad``, a step ``<= tol_step`` or
        ``max_iters`` line-search evaluations.
        """
        n0 = nstart
        t1 = tangent_basis_t1(n0)
        t2 = wp.cross(n0, t1)
        x = wp.vec2(0.0)
        ev = evaluate(n0, t1, t2, x, images, weights, px, lights, mat)
        tr = ev.jtj[0, 0] + ev.jtj[1, 1]
        ridge = 1.0e-6 * tr + 1.0e-20
        b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
        k = int(0)
        converged = int(0)
        while k < prm.max_iters:
            g = ev.jtr
            if wp.max(wp.abs(g[0]), wp.abs(g[1])) <= prm.tol_grad:
                converged = 1
                if prm.early_exit != 0:
                    break
            d = -solve22(b, g)
            gd = _dot2(g, d)
            if gd >= 0.0:
                d = -g
                gd = -_dot2(g, g)
                b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
            # keep steps in the chart's useful range (about 0.5 rad)
            ld = wp.length(d)
            if ld > 0.5:
                d = d * (0.5 / ld)
                gd = gd * (0.5 / ld)
            step = float(1.0)
            accepted = int(0)
            trial = ev
            while k < prm.max_iters:
                k += 1
                trial = evaluate(n0, t1, t2, x + step * d, images, weights, px, lights, mat)
                if trial.cost <= ev.cost + 1.0e-4 * step * gd:
                    accepted = 1
                    break
                step = 0.5 * step
                if step * ld <= prm.tol_step:
                    break
            if accepted == 0:
                converged = 1
                break
            theta = step * d
            yv = trial.jtr - g
            x = x + theta
            ev = trial
            ty = _dot2(theta, yv)
            if ty > 3.45e-4 * wp.length(theta) * wp.length(yv):  # sqrt(float32 eps)
                u = b * theta
                tu = _dot2(theta, u)
                if tu > 0.0:
                    b = b + wp.outer(yv, yv) / ty - wp.outer(u, u) / tu
            if wp.length(theta) <= prm.tol_step:
                converged = 1
                if prm.early_exit != 0:
                    break
            if wp.length(x) > 0.5:
                n0 = chart_normal(n0, t1, t2, x)
                t1 = tangent_basis_t1(n0)
                t2 = wp.cross(n0, t1)
                x = wp.vec2(0.0)
                ev = evaluate(n0, t1, t2, x, images, weights, px, lights, mat)
                tr = ev.jtj[0, 0] + ev.jtj[1, 1]
                ridge = 1.0e-6 * tr + 1.0e-20
                b = ev.jtj + wp.mat22(ridge, 0.0, 0.0, ridge)
        return _result(chart_normal(n0, t1, t2, x), ev, k, converged)

    @wp.func(name="run_method" + sfx, module=module)
    def run_method(
        nstart: wp.vec3,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        if wp.static(method == "lm"):
            return run_lm(nstart, images, weights, px, lights, mat, prm)
        elif wp.static(method == "dogleg"):
            return run_dogleg(nstart, images, weights, px, lights, mat, prm)
        elif wp.static(method == "bfgs"):
            return run_bfgs(nstart, images, weights, px, lights, mat, prm)
        else:
            # generic build: run-time switch
            if prm.method == DOGLEG:
                return run_dogleg(nstart, images, weights, px, lights, mat, prm)
            if prm.method == BFGS:
                return run_bfgs(nstart, images, weights, px, lights, mat, prm)
            return run_lm(nstart, images, weights, px, lights, mat, prm)

    @wp.func(name="solve_pixel" + sfx, module=module)
    def solve_pixel(
        ninit: wp.vec3,
        gmax: float,
        images: wp.array3d(dtype=wp.vec3),
        weights: wp.array3d(dtype=wp.float32),
        px: Pixel,
        lights: LightParams,
        mat: MaterialParams,
        prm: SolverParams,
    ):
        """Multi-start nonlinear least squares, then IRLS rounds from the best start."""
        i = px.i
        j = px.j
        v = px.v
        best = StartResult()
        best.cost = 1.0e30
        best.n = ninit
        total = int(0)
        nstarts = wp.max(prm.starts, 1)
        if prm.warm_start != 0:
            nstarts = 1
        hbright = brightest_half_vector(images, weights, px, lights)
        for s in range(nstarts):
            res = run_method(start_normal(s, ninit, v, hbright, prm), images, weights, px, lights, mat, prm)
            total += res.iters
            if res.cost < best.cost and wp.dot(res.n, v) > 0.0:
                best = res
        if best.cost >= 1.0e30:
            # every start ended facing away from the camera: keep the least-squares start
            best = run_method(ninit, images, weights, px, lights, mat, prm)
            total += best.iters
        if wp.static(robust != "none"):
            # (robust "none" runs no reweighting round: irls_rounds is 0)
            for rnd in range(prm.irls_rounds):
                # robust reweighting from the residuals at the current best (Huber / Cauchy IRLS)
                scale = prm.robust_scale * wp.max(gmax, 1.0e-12)
                for k in range(lights.count):
                    wk = weights[k, i, j]
                    if wk != 0.0:
                        l = light_dir(lights, k, px.p)
                        e = light_radiance(lights, k, px.p)
                        o = images[k, i, j]
                        dg = diffuse_value_grad(best.n, l)
                        sg = spec_vg(mat, best.n, l, v)
                        r2 = float(0.0)
                        for c in range(3):
                            r = o[c] - e[c] * (best.kd[c] * dg[0] + mat.ks * sg[0])
                            if wk < 0.0:
                                # a dark term's residual is one-sided; a cast shadow is its outlier
                                r = wp.min(r, 0.0)
                            r2 += r * r
                        rr = wp.sqrt(r2 / 3.0) / scale
                        w = float(1.0)
                        if wp.static(robust == "huber"):
                            if rr > 1.0:
                                w = 1.0 / rr
                        elif wp.static(robust == "cauchy"):
                            w = 1.0 / (1.0 + rr * rr)
                        else:
                            # generic build: run-time switch
                            if prm.robust == ROBUST_HUBER:
                                if rr > 1.0:
                                    w = 1.0 / rr
                            else:
                                w = 1.0 / (1.0 + rr * rr)
                        w = wp.max(w, 1.0e-6)
                        if wk < 0.0:
                            w = -w
                        weights[k, i, j] = w
                res = run_method(best.n, images, weights, px, lights, mat, prm)
                total += res.iters
                best = res
        out = PixelSolution()
        out.best = best
        out.total = total
        return out

    return SimpleNamespace(
        evaluate=evaluate, run_lm=run_lm, run_dogleg=run_dogleg, run_bfgs=run_bfgs, run_method=run_method, solve_pixel=solve_pixel
    )


# generic (run-time dispatch) functions, for direct use from other kernels (e.g. the tests)
_GENERIC = _solver_funcs(None, None, None)
evaluate = _GENERIC.evaluate
run_lm = _GENERIC.run_lm
run_dogleg = _GENERIC.run_dogleg
run_bfgs = _GENERIC.run_bfgs
run_method = _GENERIC.run_method
solve_pixel = _GENERIC.solve_pixel


def _make_kernels(method, brdf, robust, module_name: str, sfx: str):
    module = wp.get_module(module_name)
    solve_pixel = _solver_funcs(method, brdf, robust, module, sfx).solve_pixel

    @wp.kernel(name="solve_kernel" + sfx, module=module, enable_backward=False)
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
        i, j = wp.tid()
        nl_ = lights.count
        if mask[i, j] == wp.uint8(0):
            if prm.keep_unmasked != 0:
                return
            normals[i, j] = wp.vec3(0.0)
            albedo[i, j] = wp.vec3(0.0)
            residual[i, j] = 0.0
            iterations[i, j] = 0
            flags[i, j] = 0
            cond[i, j] = 0.0
            for k in range(nl_):
                weights[k, i, j] = 0.0
            return
        px = make_pixel(cam, depth, i, j, prm)
        p = px.p
        v = px.v
        # ---- observation validity (shadows, saturation, caller's mask)
        gmax = float(0.0)
        for k in range(nl_):
            gmax = wp.max(gmax, grey(images[k, i, j]))
        ninfo = int(0)
        for k in range(nl_):
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
        flag = int(0)
        if ninfo < 3:
            # fewer than 3 lit observations: normal and albedo are not determined together
            flag = flag | FLAG_FEW_OBSERVATIONS
        # ---- lighting sensitivity (3.13): conditioning of the valid light directions
        gram = light_gram(weights, i, j, p, lights)
        cnd = cond_frobenius(gram)
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
        a = wp.mat33(0.0)
        bc0 = wp.vec3(0.0)
        bc1 = wp.vec3(0.0)
        bc2 = wp.vec3(0.0)
        for k in range(nl_):
            if warm_ok == 0 and (use_all != 0 or weights[k, i, j] != 0.0):
                l = light_dir(lights, k, p)
                e = light_radiance(lights, k, p)
                o = images[k, i, j]
                y = wp.vec3(0.0)
                for c in range(3):
                    if e[c] > 0.0:
                        y[c] = o[c] / e[c]
                a += wp.outer(l, l)
                bc0 += y[0] * l
                bc1 += y[1] * l
                bc2 += y[2] * l
        bg = bc0 + bc1 + bc2
        ninit = v
        kdw = wp.vec3(0.0)
        det = wp.determinant(a)
        fa = wp.sqrt(wp.ddot(a, a))
        if wp.abs(det) > 1.0e-12 * fa * fa * fa and fa > 0.0:
            ai = wp.inverse(a)
            gvec = ai * bg
            if wp.length(gvec) > 0.0:
                ninit = wp.normalize(gvec)
                kdw = wp.vec3(wp.dot(ai * bc0, ninit), wp.dot(ai * bc1, ninit), wp.dot(ai * bc2, ninit))
        if warm_ok != 0:
            ninit = wp.normalize(nw)
        if wp.static(method == "none"):
            store_least_squares(ninit, kdw, flag, use_all, images, weights, px, lights, normals, albedo, residual, iterations, flags)
        else:
            if wp.static(method is None):
                # generic build: run-time switch
                if prm.method == NONE:
                    store_least_squares(ninit, kdw, flag, use_all, images, weights, px, lights, normals, albedo, residual, iterations, flags)
                    return
            sol = solve_pixel(ninit, gmax, images, weights, px, lights, mat, prm)
            store_solution(sol, flag, weights, px, nl_, normals, albedo, residual, iterations, flags)

    if method == "none":
        return solve_kernel, None, None

    @wp.kernel(name="underdetermined_kernel" + sfx, module=module, enable_backward=False)
    def underdetermined_kernel(
        images: wp.array3d(dtype=wp.vec3),
        mask: wp.array2d(dtype=wp.uint8),
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
        """
        i, j = wp.tid()
        if mask[i, j] == wp.uint8(0) or prm.method == NONE:
            return
        f = flags[i, j]
        if (f & FLAG_FEW_OBSERVATIONS) == 0:
            return
        nb = neighbour_stats(i, j, radius, min_count, mask, flags, normals, albedo)
        if nb.count == 0.0:
            return
        px = make_pixel(cam, depth, i, j, prm)
        px.fix_kd = 1
        px.kd = nb.kd
        gmax = float(0.0)
        for k in range(lights.count):
            gmax = wp.max(gmax, grey(images[k, i, j]))
        ninit = normals[i, j]
        if wp.length(nb.n) > 0.0:
            px.prior_n = wp.normalize(nb.n)
            if nb.lin_ok != 0 and wp.length(nb.n_lin) > 0.0:
                nl = wp.normalize(nb.n_lin)
                if wp.dot(nl, px.v) > 0.05:
                    px.prior_n = nl
            px.prior_w = 1.0e-3 * gmax * gmax
            ninit = px.prior_n
        sol = solve_pixel(ninit, gmax, images, weights, px, lights, mat, prm)
        sol.total = sol.total + iterations[i, j]
        store_solution(sol, f | FLAG_ALBEDO_FROM_NEIGHBOURS, weights, px, lights.count, normals, albedo, residual, iterations, flags)

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

    return solve_kernel, underdetermined_kernel, smooth_kernel


_KERNELS: dict = {}


def specialisation_key(method, brdf, robust) -> tuple:
    """The normalised ``(method, brdf, robust)`` that :func:`get_solve_kernels` builds for these settings.

    Solver ``"none"`` (Woodham only) uses neither the model nor the loss, so it
    has one build.  ``None`` (any of them): run-time switch (the generic build).
    """
    if method is not None and method not in METHODS:
        raise ValueError(f"method: expected one of {list(METHODS)} or None, got {method!r}")
    if brdf is not None and brdf not in BRDFS:
        raise ValueError(f"brdf: expected one of {list(BRDFS)} or None, got {brdf!r}")
    if robust is not None and robust not in ROBUST:
        raise ValueError(f"robust: expected one of {list(ROBUST)} or None, got {robust!r}")
    if method == "none":
        brdf, robust = "lambertian", "none"
    return method, brdf, robust


def module_name(method, brdf, robust) -> str:
    """Name of the Warp module holding the kernels of one specialisation."""
    method, brdf, robust = specialisation_key(method, brdf, robust)
    tag = "_".join("any" if s is None else s.replace("-", "_") for s in (method, brdf, robust))
    return f"gpps.kernels.solve.{tag}"


def get_solve_kernels(method, brdf, robust="none"):
    """``(solve_kernel, underdetermined_kernel, smooth_kernel)`` specialised for one solver, reflectance model and robust loss.

    Args:
        method: ``"none"``, ``"lm"``, ``"dogleg"`` or ``"bfgs"`` (None: run-time ``prm.method``).
        brdf: a :data:`gpps.material.BRDF_NAMES` name (None: run-time ``mat.model``).
        robust: ``"none"``, ``"huber"`` or ``"cauchy"`` (None: run-time ``prm.robust``);
            ``"none"`` emits no IRLS round (``prm.irls_rounds`` must be 0).

    The pair is built once per normalised key (:func:`specialisation_key`) and
    cached; each pair lives in its own Warp module (:func:`module_name`), compiled
    on first launch or by ``wp.load_module``.  ``underdetermined_kernel`` is
    None for ``method="none"``, and so is ``smooth_kernel``.  ``prm.method`` / ``mat.model`` / ``prm.robust``
    must agree with the specialisation (:class:`gpps.pipeline.solver.PixelSolver`
    sees to it).
    """
    key = specialisation_key(method, brdf, robust)
    ks = _KERNELS.get(key)
    if ks is None:
        name = module_name(*key)
        ks = _make_kernels(*key, module_name=name, sfx="__" + name.rsplit(".", 1)[1])
        _KERNELS[key] = ks
    return ks


def __getattr__(name):
    # the former monolithic kernels: the generic build (run-time switches), made on first access
    if name == "solve_kernel":
        return get_solve_kernels(None, None, None)[0]
    if name == "smooth_kernel":
        return get_solve_kernels(None, None, None)[2]
    if name == "underdetermined_kernel":
        return get_solve_kernels(None, None, None)[1]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
