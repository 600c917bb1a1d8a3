"""Cuckoo search with Levy flights (seed 6.1-6.9, Algorithm 6): device math only.

Many independent searches run side by side, one thread each (for
photometric stereo: one search per pixel).  Search ``p`` keeps ``K`` nests
(habitats) ``x`` of 5 numbers and their objective values; one *generation*:

1. every nest ``i`` lays an egg by a Levy flight (6.1-6.3)
   ``y = x_i + beta * R * psi (x_i - x_best)`` entry-wise, with ``R ~ N(0, 1)`` (6.4) and
   Mantegna's ``psi = u / |v|^(1/lambda)``, ``u ~ N(0, sigma_u^2)``, ``v ~ N(0, 1)`` (6.5-6.9);
   the egg replaces nest ``j`` when it is better (Algorithm 6, steps 4-6), with ``j = i`` as in
   Yang & Deb's reference code (``random_nest = 0``) or ``j`` drawn at random
   (``random_nest = 1``, the literal reading of Algorithm 6: it copies good eggs over the
   population and collapses it within a few generations, after which every step, being
   proportional to ``x_i - x_best``, is zero);
2. each nest but the best is found out with probability ``p_c`` and replaced by
   ``x_i + e (x_a - x_b)`` (``e ~ U(0, 1)``, ``a, b`` random nests) when that is better (step 7);
3. the best nest is ranked again (step 8).

The objective is *minimised* (the seed maximises a value; we minimise the
error).  It is a ``@wp.func objective(x: vec5, p: int, data: Data) -> float``
with ``Data`` a ``@wp.struct``; :func:`make_search_kernels` builds (and
caches) the kernels for one (objective, Data) pair.  Random numbers come from
``wp.rand_init(seed, generation * P + p)``: the same seed gives the same
search on every device.

The photometric objective (:func:`photometric_error`) is the Blinn-Phong
reprojection error of one pixel under estimated lights (seed 6.2.2: "We
constitute our system of equations F(X) using Blinn-Phong model"), with the
habitat ``x = (n_x, n_y, kd_r, kd_g, kd_b)`` (``n_z = sqrt(1 - n_x^2 - n_y^2)``,
a visible normal) and an optional pull toward a prior normal.
"""

import functools

import warp as wp

from gpps.kernels.brdf import blinn_phong_spec

vec5 = wp.types.vector(length=5, dtype=wp.float32)


@wp.func
def mantegna(u: float, v: float, lam: float):
    """Mantegna's Levy step ``psi = u / |v|^(1/lambda)`` (6.5); ``u`` already scaled by sigma_u (6.7)."""
    return u / wp.pow(wp.max(wp.abs(v), 1.0e-30), 1.0 / lam)


@wp.func
def clamp5(x: vec5, lo: vec5, hi: vec5):
    """``x`` clamped entry-wise to ``[lo, hi]``."""
    y = x
    for d in range(5):
        y[d] = wp.clamp(x[d], lo[d], hi[d])
    return y


@wp.kernel(enable_backward=False)
def levy_samples_kernel(seed: int, sigma_u: float, lam: float, out: wp.array(dtype=wp.float32)):
    """``out[t]`` = one Mantegna step (6.5-6.9) per thread (for testing the distribution)."""
    t = wp.tid()
    state = wp.rand_init(seed, t)
    u = wp.randn(state) * sigma_u
    v = wp.randn(state)
    out[t] = mantegna(u, v, lam)


@functools.lru_cache(maxsize=None)
def make_search_kernels(objective, data_type):
    """``(evaluate_kernel, generation_kernel)`` for one objective and its data struct type.

    ``evaluate_kernel(nests (P, K) vec5, data, fit (P, K) float32, best (P,) int32)``
    fills the objective values and the best nest of each search.

    ``generation_kernel(nests, fit, best, data, seed, generation, beta, p_c, sigma_u, lam, lo, hi, random_nest)``
    runs one generation of every search (see the module docstring); nests stay in ``[lo, hi]``.
    """

    @wp.kernel(enable_backward=False, module="unique")
    def evaluate_kernel(
        nests: wp.array2d(dtype=vec5),
        data: data_type,
        fit: wp.array2d(dtype=wp.float32),
        best: wp.array(dtype=wp.int32),
    ):
        p = wp.tid()
        k_best = int(0)
        f_best = float(1.0e30)
        for i in range(nests.shape[1]):
            f = objective(nests[p, i], p, data)
            fit[p, i] = f
            if f < f_best:
                f_best = f
                k_best = i
        best[p] = k_best

    @wp.kernel(enable_backward=False, module="unique")
    def generation_kernel(
        nests: wp.array2d(dtype=vec5),
        fit: wp.array2d(dtype=wp.float32),
        best: wp.array(dtype=wp.int32),
        data: data_type,
        seed: int,
        generation: int,
        beta: float,
        p_c: float,
        sigma_u: float,
        lam: float,
        lo: vec5,
        hi: vec5,
        random_nest: int,
    ):
        p = wp.tid()
        n_search = nests.shape[0]
        k = nests.shape[1]
        state = wp.rand_init(seed, generation * n_search + p)
        xb = nests[p, best[p]]
        # 1. Levy flights around the best nest (6.1-6.9); the egg goes into a random nest j
        for i in range(k):
            x = nests[p, i]
            y = x
            for d in range(5):
                u = wp.randn(state) * sigma_u
                v = wp.randn(state)
                r = wp.randn(state)
                y[d] = x[d] + beta * r * mantegna(u, v, lam) * (x[d] - xb[d])
            y = clamp5(y, lo, hi)
            j = i
            if random_nest != 0:
                j = wp.randi(state, 0, k)
            fy = objective(y, p, data)
            if fy < fit[p, j]:
                nests[p, j] = y
                fit[p, j] = fy
        # the best may have changed: rank before abandoning
        kb = int(0)
        for i in range(k):
            if fit[p, i] < fit[p, kb]:
                kb = i
        # 2. a fraction p_c of the nests is found out: a biased random walk replaces them if better
        for i in range(k):
            if i != kb and wp.randf(state) < p_c:
                a = wp.randi(state, 0, k)
                b = wp.randi(state, 0, k)
                e = wp.randf(state)
                y = clamp5(nests[p, i] + e * (nests[p, a] - nests[p, b]), lo, hi)
                fy = objective(y, p, data)
                if fy < fit[p, i]:
                    nests[p, i] = y
                    fit[p, i] = fy
        # 3. rank the nests
        for i in range(k):
            if fit[p, i] < fit[p, kb]:
                kb = i
        best[p] = kb

    return evaluate_kernel, generation_kernel


# --------------------------------------------------------------------------- photometric objective


@wp.struct
class PhotoData:
    """Per-pixel photometric data of a cuckoo refinement (one search per pixel).

    Attributes:
        images: (N, P) RGB intensities of the P pixels under N lights.
        view: (P,) unit directions toward the camera.
        prior: (P,) prior unit normals (the network's).
        light_dir: (N,) unit directions toward the lights.
        light_rgb: (N,) RGB light intensities.
        weight: (P,) per-pixel weight of the data term (0 drops a pixel's images).
        ks: Blinn-Phong specular weight.
        shininess: Blinn-Phong exponent.
        prior_weight: weight of ``|n - prior|^2``.
        albedo_from_normal: 1: the albedo is the least-squares one for the habitat's
            normal (habitat entries 2-4 ignored); 0: the habitat's albedo is used.
    """

    images: wp.array2d(dtype=wp.vec3)
    view: wp.array(dtype=wp.vec3)
    prior: wp.array(dtype=wp.vec3)
    light_dir: wp.array(dtype=wp.vec3)
    light_rgb: wp.array(dtype=wp.vec3)
    weight: wp.array(dtype=wp.float32)
    ks: float
    shininess: float
    prior_weight: float
    albedo_from_normal: int


@wp.func
def habitat_normal(x: vec5):
    """The visible unit normal of a habitat: ``(n_x, n_y, sqrt(1 - n_x^2 - n_y^2))`` (n_z >= 0.01)."""
    n = wp.vec3(x[0], x[1], 0.0)
    r2 = x[0] * x[0] + x[1] * x[1]
    if r2 < 0.9999:
        n[2] = wp.sqrt(1.0 - r2)
    else:
        n[2] = 0.01
    return wp.normalize(n)


@wp.func
def ls_albedo(n: wp.vec3, p: int, data: PhotoData):
    """Least-squares RGB albedo (>= 0) of pixel ``p`` for the normal ``n`` under the estimated lights."""
    num = wp.vec3(0.0)
    den = wp.vec3(0.0)
    v = data.view[p]
    for k in range(data.light_dir.shape[0]):
        l = data.light_dir[k]
        a = wp.max(wp.dot(n, l), 0.0)
        if a > 0.0:
            e = data.light_rgb[k]
            s = data.ks * blinn_phong_spec(n, l, v, data.shininess)
            i = data.images[k, p]
            for c in range(3):
                num[c] = num[c] + (i[c] - e[c] * s) * e[c] * a
                den[c] = den[c] + e[c] * e[c] * a * a
    kd = wp.vec3(0.0)
    for c in range(3):
        if den[c] > 1.0e-12:
            kd[c] = wp.max(num[c] / den[c], 0.0)
    return kd


@wp.func
def photometric_error(x: vec5, p: int, data: PhotoData):
    """Blinn-Phong reprojection error of pixel ``p`` for the habitat ``x`` (+ the prior term).

    ``sum_k sum_c (I_kc - E_kc (kd_c max(n.l_k, 0) + ks max(n.h_k, 0)^shininess))^2 * weight_p
    + prior_weight |n - prior_p|^2``; attached shadows give 0 (2.21).
    """
    n = habitat_normal(x)
    kd = wp.vec3(x[2], x[3], x[4])
    if data.albedo_from_normal != 0:
        kd = ls_albedo(n, p, data)
    v = data.view[p]
    err = float(0.0)
    for k in range(data.light_dir.shape[0]):
        l = data.light_dir[k]
        e = data.light_rgb[k]
        a = wp.dot(n, l)
        m = wp.vec3(0.0)
        if a > 0.0:
            s = data.ks * blinn_phong_spec(n, l, v, data.shininess)
            m = wp.cw_mul(e, kd * a + wp.vec3(s))
        d = data.images[k, p] - m
        err += wp.dot(d, d)
    dn = n - data.prior[p]
    return data.weight[p] * err + data.prior_weight * wp.dot(dn, dn)


@wp.kernel(enable_backward=False)
def best_habitat_kernel(
    nests: wp.array2d(dtype=vec5),
    best: wp.array(dtype=wp.int32),
    fit: wp.array2d(dtype=wp.float32),
    data: PhotoData,
    normals: wp.array(dtype=wp.vec3),
    albedo: wp.array(dtype=wp.vec3),
    error: wp.array(dtype=wp.float32),
):
    """The best nest of each pixel as (normal, albedo, objective value)."""
    p = wp.tid()
    x = nests[p, best[p]]
    n = habitat_normal(x)
    normals[p] = n
    if data.albedo_from_normal != 0:
        albedo[p] = ls_albedo(n, p, data)
    else:
        albedo[p] = wp.vec3(x[2], x[3], x[4])
    error[p] = fit[p, best[p]]


@wp.kernel(enable_backward=False)
def photometric_error_kernel(x: wp.array(dtype=vec5), data: PhotoData, out: wp.array(dtype=wp.float32)):
    """``out[p] = photometric_error(x[p], p, data)`` (for testing the objective)."""
    p = wp.tid()
    out[p] = photometric_error(x[p], p, data)
