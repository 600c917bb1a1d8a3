"""Robust statistics of the well-determined pixels around an under-determined one (the solver's neighbour pass).

Device math only: :func:`neighbour_stats` is what the ``underdetermined_kernel``
of :mod:`gpps.kernels.solve_kernels` reads to hold a pixel's albedo and to
break the ties of its normal (see :class:`gpps.pipeline.solver.SolverConfig`'s
``neighbour_radius``).
"""

import warp as wp

from gpps.kernels.solve_common import FLAG_FEW_OBSERVATIONS, Pixel

NEIGHBOUR_MIN_COUNT = 16  # well-determined pixels the neighbour pass gathers (before its 2 extra rings)
WEISZFELD_ITERS = wp.constant(8)  # iterations of the neighbours' geometric median
LINEAR_ITERS = wp.constant(5)  # IRLS rounds of the neighbours' first-order normal model


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


NEIGHBOUR_LIST = 256  # determined neighbours :func:`neighbour_stats` keeps in its list (more: it scans the rings)
_NeighbourList = wp.types.vector(length=NEIGHBOUR_LIST, dtype=wp.int32)


@wp.func
def _pack_offset(di: int, dj: int):
    """``(di, dj)`` (each within +-511: ``SolverConfig.neighbour_radius`` is at most 256) in one non-negative int32."""
    return ((di + 512) << 10) | (dj + 512)


@wp.func
def _unpack_offset(code: int):
    """The ``(di, dj)`` of :func:`_pack_offset`."""
    return (code >> 10) - 512, (code & 1023) - 512


@wp.func
def _weiszfeld_terms(a: wp.vec3, q: wp.vec3, mk: wp.vec3, mn: wp.vec3, ek: float):
    """One neighbour's terms of a Weiszfeld step: ``(u a, u, z q, z)`` with ``u = 1 / |a - mk|``, ``z = 1 / |q - mn|``
    (floored)."""
    u = 1.0 / wp.max(wp.length(a - mk), ek)
    z = 1.0 / wp.max(wp.length(q - mn), 1.0e-4)
    return u * a, u, z * q, z


@wp.func
def _linear_terms(q: wp.vec3, di: int, dj: int, it: int, lin: wp.vec3, gi: wp.vec3, gj: wp.vec3):
    """One neighbour's terms of an IRLS round of the first-order model: ``(w x x^T, w q0 x, w q1 x, w q2 x)``,
    ``x = (1, di, dj)``, ``w`` 1 in round 0 and ``1 / |residual|`` (floored) after."""
    x = wp.vec3(1.0, float(di), float(dj))
    wgt = float(1.0)
    if it > 0:
        wgt = 1.0 / wp.max(wp.length(q - lin - float(di) * gi - float(dj) * gj), 1.0e-3)
    return wgt * wp.outer(x, x), wgt * q[0] * x, wgt * q[1] * x, wgt * q[2] * x


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

    The ring search keeps the found pixels' offsets in a list (up to :data:`NEIGHBOUR_LIST`, in the search's
    order), and the 13 passes of the two fits run over that list instead of scanning the rings' squares again
    (a pixel deep in an under-determined region scans hundreds of pixels a pass to find its few dozen: that scan
    was most of the neighbour pass's time on the GPU, where a launch costs its slowest thread).  The terms are
    summed in the same order either way, so the results are the same bits; more pixels than the list holds
    fall back to the scans.
    """
    out = NeighbourStats()
    acc = wp.vec3(0.0)
    nacc = wp.vec3(0.0)
    cnt = float(0.0)
    r_stop = radius
    reach = int(0)
    lst = _NeighbourList()
    k = int(0)
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
                if k < NEIGHBOUR_LIST:
                    lst[k] = _pack_offset(di, dj)
                k += 1
        if cnt >= float(min_count) and r_stop == radius:
            r_stop = wp.min(r + 2, radius)
    listed = k <= NEIGHBOUR_LIST
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
        if listed:
            for m in range(k):
                di, dj = _unpack_offset(lst[m])
                ua, u, zq, z = _weiszfeld_terms(albedo[i + di, j + dj], normals[i + di, j + dj], mk, mn, ek)
                ak += ua
                wk += u
                an += zq
                wn += z
        else:
            for r in range(1, reach + 1):
                for t in range(8 * r):
                    di, dj = ring_offset(r, t)
                    if is_determined(mask, flags, i + di, j + dj):
                        ua, u, zq, z = _weiszfeld_terms(albedo[i + di, j + dj], normals[i + di, j + dj], mk, mn, ek)
                        ak += ua
                        wk += u
                        an += zq
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
        if listed:
            for m in range(k):
                di, dj = _unpack_offset(lst[m])
                ta, t0, t1, t2 = _linear_terms(normals[i + di, j + dj], di, dj, it, lin, gi, gj)
                am += ta
                b0 += t0
                b1 += t1
                b2 += t2
        else:
            for r in range(1, reach + 1):
                for t in range(8 * r):
                    di, dj = ring_offset(r, t)
                    if is_determined(mask, flags, i + di, j + dj):
                        ta, t0, t1, t2 = _linear_terms(normals[i + di, j + dj], di, dj, it, lin, gi, gj)
                        am += ta
                        b0 += t0
                        b1 += t1
                        b2 += t2
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


@wp.func
def neighbour_prior(nb: NeighbourStats, v: wp.vec3, gmax: float):
    """The prior normal and its weight that the neighbour pass puts on an under-determined pixel, as a vec4
    ``(n, w)`` (zeros when the neighbours gave no normal): their first-order extrapolation ``n_lin`` where that
    fit held and faces the camera (``n . v > 0.05``), else their geometric median ``n``; the weight ``1e-3
    gmax^2`` (of the data's scale: it only breaks the ties of 1-2 observations)."""
    if wp.length(nb.n) <= 0.0:
        return wp.vec4(0.0)
    pn = wp.normalize(nb.n)
    if nb.lin_ok != 0 and wp.length(nb.n_lin) > 0.0:
        nl = wp.normalize(nb.n_lin)
        if wp.dot(nl, v) > 0.05:
            pn = nl
    return wp.vec4(pn[0], pn[1], pn[2], 1.0e-3 * gmax * gmax)


@wp.func
def prior_start(prior: wp.vec4, n: wp.vec3):
    """The start normal of an under-determined pixel's solve: the prior's normal (:func:`neighbour_prior`) where it
    set one, else ``n`` (the pixel's current normal)."""
    pn = wp.vec3(prior[0], prior[1], prior[2])
    if wp.length(pn) > 0.0:
        return pn
    return n


@wp.func
def held_pixel(px: Pixel, kd: wp.vec3, prior: wp.vec4):
    """``px`` with its albedo held at ``kd`` (the neighbours') and, where ``prior`` holds a normal
    (:func:`neighbour_prior`), that normal as its prior with the prior's weight."""
    out = px
    out.fix_kd = 1
    out.kd = kd
    pn = wp.vec3(prior[0], prior[1], prior[2])
    if wp.length(pn) > 0.0:  # (a unit normal where neighbour_prior set one)
        out.prior_n = pn
        out.prior_w = prior[3]
    return out
