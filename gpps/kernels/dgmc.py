"""DGMC on the device (seed 4.1.9, 4.16-4.18): highlight test, region labels, geodesic candidates, curvatures
and the curvature-similarity start search, as Warp kernels (float64; the stage :mod:`gpps.pipeline.dgmc`
owns the buffers and launches them; :mod:`gpps.host.dgmc` is the reference they are tested against).

Where the parallel form differs from the host's (and the seed's) and why the results agree:

* Highlight test (the "brighter than any Lambertian explanation" rule of :func:`gpps.host.dgmc.detect_highlights`).
  The host refits, for every observation ``k`` of a pixel, the least-squares Lambertian ``b`` of the other
  active observations from scratch: ``O(N)`` per fit, ``O(N^2)`` per flagging round, ``O(N^3)`` per pixel in the
  worst case.  :func:`highlight_kernel` accumulates the moments of all active observations once per round,
  ``A = sum s_j s_j^T``, ``r = sum g_j s_j``, ``G = sum g_j^2`` (``O(N)``), and gets the leave-one-out fit of each
  ``k`` by a rank-one downdate ``A - s_k s_k^T``, ``r - g_k s_k``, ``G - g_k^2`` and a 3x3 solve (``O(1)``); the
  residual of the others is ``b^T A_k b - 2 b.r_k + G_k``.  So a round is ``O(N)`` and a pixel ``O(N (f + 1))``
  with ``f`` its flagged observations (the host's rounds, one flag each, are kept: the greedy order is what
  keeps a highlight from getting clean observations flagged).  In exact arithmetic the downdated moments are the
  host's sums, so predictions, consistency scores and decisions are the same; in float64 they differ by
  rounding (``1e-14`` relative), which moves a decision only when an observation lies within that of its
  threshold.  The exactly-two-others case (the reference-albedo fit) is computed as on the host.
* Distance to the boundary.  The host runs :func:`scipy.sparse.csgraph.dijkstra` from every boundary pixel of a
  region and keeps the ``K`` nearest per region pixel.  :func:`gpps.kernels.dgmc_geodesic.geodesic_relax_kernel` is a min-plus (Bellman-Ford)
  relaxation of ``K``-lists on the same graph: per sweep every region pixel merges its 8 neighbours' lists (plus
  the edge length) and the boundary pixels next to it into its own ``K`` smallest ``(distance, source)`` pairs,
  one entry per source (Jacobi: read the old lists, write new ones); sweeps repeat until none changes.  The
  fixed point is the exact ``K`` nearest: if ``q`` is among ``p``'s ``K`` nearest and ``u`` is the predecessor of
  ``p`` on a shortest ``q -> p`` path, every source nearer to ``u`` than ``q`` is nearer to ``p`` than ``q`` too, so
  ``q`` is among ``u``'s ``K`` nearest and reaches ``p`` through ``u``'s list.  Distances are carried as the exact
  counts ``(a, b)`` of unit and diagonal steps (``d = a + b sqrt(2)``, both packed in one int32), so sums do not
  depend on the path's order and ties (equal ``(a, b)``) go to the smaller flat source index, as on the host;
  the merge compares heads as one int64 (:func:`gpps.kernels.dgmc_geodesic.head_order`: a scaled floor of ``d``
  above the source index, exactly the ``(d, source)`` order, reasoned there).  How a sweep is computed (the slot
  kinds once, ping-pong buffers, a thread-local set of the sources taken) changes its cost, not its lists: each
  sweep is still ``new = the K smallest distinct-source entries of the neighbours' old lists (plus the edge
  lengths) and of the adjacent boundary pixels``.
* Curvatures (4.16): the same Gaussian-derivative filters (scipy's weights and ``reflect`` border) as separable
  passes, after the same fill of the pixels outside the mask (a mask-only index map from the host); float64
  sums in another order than scipy's, so ``GC``, ``MC`` agree to ``1e-12`` relative.
* Start search (4.17-4.18): :func:`select_kernel` applies :func:`gpps.host.dgmc.select_sources` per pixel to its
  sorted candidate list: identical rule.
"""

import warp as wp

from gpps.kernels.dgmc_geodesic import key_value


# --------------------------------------------------------------------------- observations and lights


@wp.func
def grey_of(images: wp.array3d(dtype=wp.vec3), channels: int, k: int, i: int, j: int) -> wp.float64:
    """Grey value ``g_k`` of pixel (i, j): the RGB mean (float64, summed in channel order), or the value."""
    c = images[k, i, j]
    if channels == 1:
        return wp.float64(c[0])
    return ((wp.float64(c[0]) + wp.float64(c[1])) + wp.float64(c[2])) / wp.float64(3.0)


@wp.func
def cmax_of(images: wp.array3d(dtype=wp.vec3), channels: int, k: int, i: int, j: int) -> wp.float64:
    """Brightest channel of observation k at (i, j)."""
    c = images[k, i, j]
    if channels == 1:
        return wp.float64(c[0])
    return wp.float64(wp.max(wp.max(c[0], c[1]), c[2]))


@wp.func
def light_vec(kind: int, k: int, i: int, j: int, lvec: wp.array(dtype=wp.vec3d), laxis: wp.array(dtype=wp.vec3d),
              lmu: wp.array(dtype=wp.float64), lint: wp.array(dtype=wp.float64),
              points: wp.array2d(dtype=wp.vec3d)) -> wp.vec3d:
    """Light vector ``E_k l_k`` at (i, j): directional (``lvec[k]`` already scaled by the mean intensity), or a
    point light at ``lvec[k]`` with irradiance ``E / r^2 max(cos, 0)^mu`` (2.30-2.31; host ``_light_fields``)."""
    if kind == 0:
        return lvec[k]
    d = lvec[k] - points[i, j]
    r2 = wp.max(wp.dot(d, d), wp.float64(1e-300))
    ldir = d / wp.sqrt(r2)
    cosax = wp.max(wp.dot(-ldir, laxis[k]), wp.float64(0.0))
    e = lint[k] / r2 * wp.pow(cosax, lmu[k])
    return ldir * e


@wp.func
def solve3(a: wp.mat33d, r: wp.vec3d) -> wp.vec3d:
    """``(a + 1e-12 I)^-1 r`` (the host's regularised normal equations)."""
    eps = wp.float64(1e-12)
    m = a + wp.mat33d(eps, wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), eps, wp.float64(0.0),
                      wp.float64(0.0), wp.float64(0.0), eps)
    return wp.inverse(m) * r


@wp.func
def fit_all(kind: int, i: int, j: int, n: int, images: wp.array3d(dtype=wp.vec3), channels: int,
            lvec: wp.array(dtype=wp.vec3d), laxis: wp.array(dtype=wp.vec3d), lmu: wp.array(dtype=wp.float64),
            lint: wp.array(dtype=wp.float64), points: wp.array2d(dtype=wp.vec3d)) -> wp.float64:
    """``|b|`` of the least-squares Lambertian fit of all N observations (the reference-albedo sample)."""
    a = wp.mat33d()
    r = wp.vec3d()
    for k in range(n):
        s = light_vec(kind, k, i, j, lvec, laxis, lmu, lint, points)
        a += wp.outer(s, s)
        r += s * grey_of(images, channels, k, i, j)
    return wp.length(solve3(a, r))


@wp.func
def eval_ls(a: wp.mat33d, r: wp.vec3d, gg: wp.float64, esum: wp.float64, cnt: int, s: wp.vec3d, g: wp.float64,
            e: wp.float64, rho: wp.float64) -> wp.vec2d:
    """(prediction, inconsistency) of observation (s, g, |s| = e) from the others (cnt >= 3 of them), by a
    rank-one downdate of the active moments (a, r, gg, esum)."""
    ak = a - wp.outer(s, s)
    rk = r - s * g
    gk = gg - g * g
    b = solve3(ak, rk)
    pred = wp.max(wp.dot(s, b), wp.float64(0.0))
    ss = wp.max(wp.dot(b, ak * b) - wp.float64(2.0) * wp.dot(b, rk) + gk, wp.float64(0.0))
    c = wp.float64(cnt)
    inc = wp.sqrt(ss / c) + wp.abs(wp.length(b) - rho) * ((esum - e) / c)
    return wp.vec2d(pred, inc)


@wp.func
def eval_two(a0: wp.vec3d, g0: wp.float64, a1: wp.vec3d, g1: wp.float64, s: wp.vec3d, rho: wp.float64) -> wp.vec2d:
    """(prediction, inconsistency) of observation s from exactly two others: the (up to two) ``b`` fitting them
    exactly with ``|b| = rho``, visible ones preferred, the larger prediction (host ``_lambertian_predictions``)."""
    eps = wp.float64(1e-12)
    m00 = wp.dot(a0, a0) + eps
    m01 = wp.dot(a0, a1)
    m11 = wp.dot(a1, a1) + eps
    det = m00 * m11 - m01 * m01
    x0 = (m11 * g0 - m01 * g1) / det
    x1 = (m00 * g1 - m01 * g0) / det
    b0 = a0 * x0 + a1 * x1
    c = wp.cross(a0, a1)
    c = c / wp.max(wp.length(c), wp.float64(1e-300))
    t = wp.sqrt(wp.max(rho * rho - wp.dot(b0, b0), wp.float64(0.0)))
    ca = b0 + c * t
    cb = b0 - c * t
    pa = wp.max(wp.dot(s, ca), wp.float64(0.0))
    pb = wp.max(wp.dot(s, cb), wp.float64(0.0))
    va = ca[2] > wp.float64(0.0)
    vb = cb[2] > wp.float64(0.0)
    pred = wp.max(pa, pb)
    if va and not vb:
        pred = pa
    if vb and not va:
        pred = pb
    inc = wp.max(wp.length(b0) - rho, wp.float64(0.0)) * ((wp.length(a0) + wp.length(a1)) / wp.float64(2.0))
    return wp.vec2d(pred, inc)


@wp.func
def eval_obs(kind: int, k: int, i: int, j: int, images: wp.array3d(dtype=wp.vec3), channels: int,
             lvec: wp.array(dtype=wp.vec3d), laxis: wp.array(dtype=wp.vec3d), lmu: wp.array(dtype=wp.float64),
             lint: wp.array(dtype=wp.float64), points: wp.array2d(dtype=wp.vec3d), a: wp.mat33d, r: wp.vec3d,
             gg: wp.float64, esum: wp.float64, m: int, i0: int, i1: int, i2: int, rho: wp.float64) -> wp.vec2d:
    """(prediction, inconsistency) of active observation k from the other m - 1 >= 2 active ones: the downdated
    least-squares fit (m - 1 >= 3) or the two-others fit (m - 1 = 2; i0 < i1 < i2 the three active indices)."""
    s = light_vec(kind, k, i, j, lvec, laxis, lmu, lint, points)
    g = grey_of(images, channels, k, i, j)
    if m - 1 >= 3:
        return eval_ls(a, r, gg, esum, m - 1, s, g, wp.length(s), rho)
    o0 = i1
    o1 = i2
    if k == i1:
        o0 = i0
        o1 = i2
    elif k == i2:
        o0 = i0
        o1 = i1
    a0 = light_vec(kind, o0, i, j, lvec, laxis, lmu, lint, points)
    a1 = light_vec(kind, o1, i, j, lvec, laxis, lmu, lint, points)
    return eval_two(a0, grey_of(images, channels, o0, i, j), a1, grey_of(images, channels, o1, i, j), s, rho)


# --------------------------------------------------------------------------- the start normals in


@wp.kernel
def start_normals_kernel(src: wp.array2d(dtype=wp.vec3), mask: wp.array2d(dtype=wp.uint8),
                         out: wp.array2d(dtype=wp.vec3d)):
    """out = a solve's float32 normals in float64 inside the mask where they are unit (``| |n| - 1 | < 1e-3``, the
    length in float64); (0, 0, 1) elsewhere: outside the mask and at pixels the solve left undetermined (zero
    or non-finite normals)."""
    i, j = wp.tid()
    s = src[i, j]
    n = wp.vec3d(wp.float64(s[0]), wp.float64(s[1]), wp.float64(s[2]))
    ok = False
    if mask[i, j] != wp.uint8(0):
        ln = wp.sqrt((n[0] * n[0] + n[1] * n[1]) + n[2] * n[2])
        ok = wp.abs(ln - wp.float64(1.0)) < wp.float64(1e-3)  # (NaN: False)
    if ok:
        out[i, j] = n
    else:
        out[i, j] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))


# --------------------------------------------------------------------------- highlights


@wp.kernel
def albedo_sample_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, mask: wp.array2d(dtype=wp.uint8),
                         kind: int, lvec: wp.array(dtype=wp.vec3d), laxis: wp.array(dtype=wp.vec3d),
                         lmu: wp.array(dtype=wp.float64), lint: wp.array(dtype=wp.float64),
                         points: wp.array2d(dtype=wp.vec3d), keys: wp.array(dtype=wp.float64),
                         vals: wp.array(dtype=wp.int32)):
    """keys[i W + j] = ``|b|`` of the all-observation fit inside the mask, +inf outside (sorted next: the median is
    the reference albedo ``rho``)."""
    i, j = wp.tid()
    w = mask.shape[1]
    idx = i * w + j
    vals[idx] = idx
    if mask[i, j] == wp.uint8(0):
        keys[idx] = wp.float64(wp.inf)
        return
    keys[idx] = fit_all(kind, i, j, images.shape[0], images, channels, lvec, laxis, lmu, lint, points)


@wp.kernel
def grey_keys_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, mask: wp.array2d(dtype=wp.uint8), k: int,
                     keys: wp.array(dtype=wp.float64), vals: wp.array(dtype=wp.int32)):
    """keys = grey values of image k inside the mask, +inf outside (sorted next: its percentile)."""
    i, j = wp.tid()
    idx = i * mask.shape[1] + j
    vals[idx] = idx
    if mask[i, j] == wp.uint8(0):
        keys[idx] = wp.float64(wp.inf)
    else:
        keys[idx] = grey_of(images, channels, k, i, j)


@wp.kernel
def median_kernel(keys: wp.array(dtype=wp.float64), count: int, out: wp.array(dtype=wp.float64), slot: int):
    """out[slot] = median of the ``count`` smallest (sorted) keys (numpy's: the mean of the middle two)."""
    h = count // 2
    if count % 2 == 1:
        out[slot] = keys[h]
    else:
        out[slot] = (keys[h - 1] + keys[h]) / wp.float64(2.0)


@wp.kernel
def percentile_kernel(keys: wp.array(dtype=wp.float64), count: int, q: wp.float64, out: wp.array(dtype=wp.float64),
                      slot: int):
    """out[slot] = the q-quantile (0..1) of the ``count`` smallest sorted keys, numpy's ``linear`` method."""
    v = q * wp.float64(count - 1)
    lo = int(wp.floor(v))
    hi = wp.min(lo + 1, count - 1)
    t = v - wp.float64(lo)
    a = keys[lo]
    b = keys[hi]
    d = b - a
    if t >= wp.float64(0.5):
        out[slot] = b - d * (wp.float64(1.0) - t)
    else:
        out[slot] = a + d * t


@wp.kernel
def highlight_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, mask: wp.array2d(dtype=wp.uint8),
                     kind: int, lvec: wp.array(dtype=wp.vec3d), laxis: wp.array(dtype=wp.vec3d),
                     lmu: wp.array(dtype=wp.float64), lint: wp.array(dtype=wp.float64),
                     points: wp.array2d(dtype=wp.vec3d), rho_arr: wp.array(dtype=wp.float64),
                     ratio: wp.float64, margin: wp.float64, flags: wp.array3d(dtype=wp.uint8),
                     predicted: wp.array3d(dtype=wp.float32)):
    """The ``"lambertian"`` rule, one thread per pixel, O(N) per flagging round (module docstring).

    Args:
        images: (N, H, W) RGB (or grey in x, ``channels`` = 1).
        rho_arr: [rho_ref] the reference albedo.
        flags: (N, H, W) out: 1 where observation k is flagged, 0 elsewhere (and outside the mask).
        predicted: (N, H, W) out: the prediction an observation was flagged against, elsewhere the first
            round's (NaN where untestable and outside the mask).
    """
    i, j = wp.tid()
    n = images.shape[0]
    nan = wp.float32(wp.nan)
    for k in range(n):
        flags[k, i, j] = wp.uint8(0)
        predicted[k, i, j] = nan
    if mask[i, j] == wp.uint8(0):
        return
    rho = rho_arr[0]
    ebar_pix = wp.float64(0.0)
    for k in range(n):
        ebar_pix += wp.length(light_vec(kind, k, i, j, lvec, laxis, lmu, lint, points))
    tie = wp.float64(1e-3) * rho * (ebar_pix / wp.float64(n))
    for rnd in range(n):
        # moments of the active observations, and the first three active indices (for the two-others case)
        a = wp.mat33d()
        r = wp.vec3d()
        gg = wp.float64(0.0)
        esum = wp.float64(0.0)
        m = int(0)
        i0 = int(-1)
        i1 = int(-1)
        i2 = int(-1)
        for k in range(n):
            if flags[k, i, j] == wp.uint8(0):
                s = light_vec(kind, k, i, j, lvec, laxis, lmu, lint, points)
                g = grey_of(images, channels, k, i, j)
                a += wp.outer(s, s)
                r += s * g
                gg += g * g
                esum += wp.length(s)
                if m == 0:
                    i0 = k
                elif m == 1:
                    i1 = k
                elif m == 2:
                    i2 = k
                m += 1
        if m - 1 < 2:
            break
        # two passes over the active observations: the least inconsistency among the over-threshold ones,
        # then the largest excess among those within the tie band of it
        best = wp.float64(wp.inf)
        any_over = int(0)
        for k in range(n):
            if flags[k, i, j] == wp.uint8(0):
                g = grey_of(images, channels, k, i, j)
                pi = eval_obs(kind, k, i, j, images, channels, lvec, laxis, lmu, lint, points, a, r, gg, esum, m,
                              i0, i1, i2, rho)
                if rnd == 0:
                    predicted[k, i, j] = wp.float32(pi[0])
                if g > ratio * pi[0] + margin:
                    any_over = 1
                    best = wp.min(best, pi[1])
        if any_over == 0:
            break
        worst = int(-1)
        worst_excess = wp.float64(-wp.inf)
        worst_pred = wp.float64(0.0)
        for k in range(n):
            if flags[k, i, j] == wp.uint8(0):
                g = grey_of(images, channels, k, i, j)
                pi = eval_obs(kind, k, i, j, images, channels, lvec, laxis, lmu, lint, points, a, r, gg, esum, m,
                              i0, i1, i2, rho)
                if g > ratio * pi[0] + margin and pi[1] <= best + tie:
                    ex = (g - margin) / wp.max(pi[0], wp.float64(1e-12))
                    if ex > worst_excess:
                        worst_excess = ex
                        worst = k
                        worst_pred = pi[0]
        if worst < 0:
            break
        flags[worst, i, j] = wp.uint8(1)
        predicted[worst, i, j] = wp.float32(worst_pred)


@wp.kernel
def percentile_rule_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, mask: wp.array2d(dtype=wp.uint8),
                           level: wp.array(dtype=wp.float64), ratio: wp.float64, margin: wp.float64,
                           flags: wp.array3d(dtype=wp.uint8), predicted: wp.array3d(dtype=wp.float32)):
    """The ``"percentile"`` rule: flagged where ``g_k > ratio P_k + margin`` (P_k = level[k]); predicted = P_k."""
    k, i, j = wp.tid()
    p = level[k]
    predicted[k, i, j] = wp.float32(p)
    f = wp.uint8(0)
    if mask[i, j] != wp.uint8(0) and grey_of(images, channels, k, i, j) > ratio * p + margin:
        f = wp.uint8(1)
    flags[k, i, j] = f


@wp.kernel
def saturation_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, mask: wp.array2d(dtype=wp.uint8),
                      saturation: wp.float64, use: int, flags: wp.array3d(dtype=wp.uint8),
                      saturated: wp.array3d(dtype=wp.uint8), region: wp.array2d(dtype=wp.uint8)):
    """Saturated observations (any channel >= saturation when ``use``) join the flags; region = any flag."""
    i, j = wp.tid()
    reg = wp.uint8(0)
    for k in range(images.shape[0]):
        sat = wp.uint8(0)
        if use != 0 and mask[i, j] != wp.uint8(0) and cmax_of(images, channels, k, i, j) >= saturation:
            sat = wp.uint8(1)
            flags[k, i, j] = wp.uint8(1)
        saturated[k, i, j] = sat
        if flags[k, i, j] != wp.uint8(0):
            reg = wp.uint8(1)
    region[i, j] = reg


# --------------------------------------------------------------------------- curvature (4.16)


@wp.func
def reflect(x: int, n: int) -> int:
    """scipy.ndimage's ``reflect`` border (d c b a | a b c d | d c b a), any distance out."""
    period = 2 * n
    y = x % period
    if y < 0:
        y += period
    if y >= n:
        y = period - 1 - y
    return y


@wp.kernel
def field_kernel(images: wp.array3d(dtype=wp.vec3), channels: int, normals: wp.array2d(dtype=wp.vec3d), kind: int,
                 fill: wp.array3d(dtype=wp.int32), f0: wp.array2d(dtype=wp.float64),
                 f1: wp.array2d(dtype=wp.float64)):
    """The field the curvatures differentiate, filled outside the mask from the nearest inside pixel
    (fill[i, j] = its row, column): kind 0: f0 = mean grey image over all N; kind 1: the height gradient
    f0 = p = -n_x / n_z, f1 = q = -n_y / n_z (n_z clamped to >= 0.05)."""
    i, j = wp.tid()
    a = fill[i, j, 0]
    b = fill[i, j, 1]
    if kind == 0:
        s = wp.float64(0.0)
        for k in range(images.shape[0]):
            s += grey_of(images, channels, k, a, b)
        f0[i, j] = s / wp.float64(images.shape[0])
    else:
        nv = normals[a, b]
        nz = wp.max(nv[2], wp.float64(0.05))
        f0[i, j] = -nv[0] / nz
        f1[i, j] = -nv[1] / nz


@wp.kernel
def correlate_kernel(src: wp.array2d(dtype=wp.float64), weights: wp.array(dtype=wp.float64), axis: int,
                     dst: wp.array2d(dtype=wp.float64)):
    """dst[i, j] = sum_t weights[t] src[. + t - r] along ``axis`` (scipy.ndimage.correlate1d, reflect border)."""
    i, j = wp.tid()
    nw = weights.shape[0]
    r = nw // 2
    s = wp.float64(0.0)
    for t in range(nw):
        if axis == 0:
            s += weights[t] * src[reflect(i + t - r, src.shape[0]), j]
        else:
            s += weights[t] * src[i, reflect(j + t - r, src.shape[1])]
    dst[i, j] = s


@wp.kernel
def curvature_kernel(mask: wp.array2d(dtype=wp.uint8), kind: int, d0: wp.array2d(dtype=wp.float64),
                     d1: wp.array2d(dtype=wp.float64), d2: wp.array2d(dtype=wp.float64),
                     d3: wp.array2d(dtype=wp.float64), gc: wp.array2d(dtype=wp.float64),
                     mc: wp.array2d(dtype=wp.float64)):
    """GC = K1 K2, MC = (K1 + K2) / 2 from the Hessian's eigenvalues (4.16), 0 outside the mask.

    kind 0 (intensity): d0 = f_ii, d1 = f_ij, d2 = f_jj; kind 1 (normals): H = [[-q_i, (-p_i + q_j) / 2],
    [., p_j]] with d0 = q_i, d1 = p_i, d2 = q_j, d3 = p_j (host :func:`gpps.host.dgmc.hessian_curvatures`).
    """
    i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        gc[i, j] = wp.float64(0.0)
        mc[i, j] = wp.float64(0.0)
        return
    a = d0[i, j]
    b = d1[i, j]
    c = d2[i, j]
    if kind == 1:
        a = -d0[i, j]
        b = wp.float64(0.5) * (-d1[i, j] + d2[i, j])
        c = d3[i, j]
    half_tr = wp.float64(0.5) * (a + c)
    root = wp.sqrt(wp.float64(0.25) * (a - c) * (a - c) + b * b)
    k1 = half_tr - root
    k2 = half_tr + root
    gc[i, j] = k1 * k2
    mc[i, j] = wp.float64(0.5) * (k1 + k2)


# --------------------------------------------------------------------------- start search (4.17-4.18)


@wp.kernel
def select_kernel(mask: wp.array2d(dtype=wp.uint8), region: wp.array2d(dtype=wp.uint8),
                  keys: wp.array3d(dtype=wp.int32), srcs: wp.array3d(dtype=wp.int32),
                  gc: wp.array2d(dtype=wp.float64), mc: wp.array2d(dtype=wp.float64),
                  normals: wp.array2d(dtype=wp.vec3d), tolerance: wp.float64, widen_factor: wp.float64,
                  widen_steps: int, out_normals: wp.array2d(dtype=wp.vec3), source: wp.array3d(dtype=wp.int32),
                  distance: wp.array2d(dtype=wp.float32), rank: wp.array2d(dtype=wp.int32),
                  tol_used: wp.array2d(dtype=wp.float32)):
    """Per highlight pixel p: the nearest candidate q (its sorted list) with |GC_q - GC_p| <= t |GC_p| and
    |MC_q - MC_p| <= t |MC_p| (4.17-4.18), t widened by ``widen_factor`` up to ``widen_steps`` times, else the
    nearest (tolerance inf); p starts from normals[q].  Off the region (or no candidate): the given normal, -1/NaN.
    """
    i, j = wp.tid()
    w = mask.shape[1]
    nan = wp.float32(wp.nan)
    source[i, j, 0] = -1
    source[i, j, 1] = -1
    distance[i, j] = nan
    rank[i, j] = -1
    tol_used[i, j] = nan
    if mask[i, j] == wp.uint8(0):
        out_normals[i, j] = wp.vec3(0.0)
        return
    nv = normals[i, j]
    out_normals[i, j] = wp.vec3(wp.float32(nv[0]), wp.float32(nv[1]), wp.float32(nv[2]))
    if region[i, j] == wp.uint8(0) or srcs[i, j, 0] < 0:
        return
    kk = srcs.shape[2]
    gp = gc[i, j]
    mp = mc[i, j]
    t = tolerance
    found = int(-1)
    tf = wp.float64(wp.inf)
    for stp in range(widen_steps + 1):
        if found < 0:
            for r in range(kk):
                q = srcs[i, j, r]
                if found < 0 and q >= 0:
                    a = q // w
                    b = q % w
                    if wp.abs(gc[a, b] - gp) <= t * wp.abs(gp) and wp.abs(mc[a, b] - mp) <= t * wp.abs(mp):
                        found = r
                        tf = t
            t = t * widen_factor
    if found < 0:
        found = 0
    q = srcs[i, j, found]
    a = q // w
    b = q % w
    nq = normals[a, b]
    out_normals[i, j] = wp.vec3(wp.float32(nq[0]), wp.float32(nq[1]), wp.float32(nq[2]))
    source[i, j, 0] = a
    source[i, j, 1] = b
    distance[i, j] = wp.float32(key_value(keys[i, j, found]))
    rank[i, j] = found
    tol_used[i, j] = wp.float32(tf)
