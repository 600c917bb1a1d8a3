"""Device math of the depth-parameterised refinement (:class:`gpps.pipeline.depth_refine.DepthRefiner`).

The unknown is the integrator's ``u`` (:mod:`gpps.host.poisson`): the log-depth under the perspective
camera (the seed's perspective PS, 4.20 with ``u = log d``), the depth under the orthographic one.  A
pixel's *steps* are ``u``'s differences per pixel, ``a = du/dj`` and ``c = du/di``: where both neighbours are in
the mask BiNI's blend of the forward and backward differences (weights from the one-sided differences through
a sigmoid of sharpness ``k``, with the ``N_z`` factors of a reference normal map, :func:`one_sided`: the side
across a depth edge weighs nothing, a smooth surface gets the central difference), one-sided where one
neighbour is, 0 where none is; its normal is the inverse of
:func:`gpps.host.poisson.pixel_gradients` (which maps a normal to its steps)::

    perspective:   n ~ (alpha, -gamma, 1 + alpha (j - cx) / fx + gamma (i - cy) / fy),   alpha = a fx, gamma = c fy
    orthographic:  n ~ (alpha, -gamma, 1),                                                alpha = a / s, gamma = c / s

(``alpha``, ``gamma``: the steps in slope units, the variables of the per-pixel model below).

:func:`refine_eval_kernel` evaluates the image model (:mod:`gpps.kernels.brdf`: ``I = E (kd t_d + ks t_s)``,
2.13, 2.20-2.31) of every valid observation of a pixel at the normal of the current ``u`` and at the four
normals of ``alpha +- h``, ``gamma +- h`` (central differences, ``h`` = :data:`FD_STEP` in slope units).  The
albedo is the weighted least-squares one of each normal (variable projection, as the pixel solver's 2.13),
so the differences are those of the residual with the albedo eliminated.  Robust weights: Cauchy's
``w = 1 / (1 + (r / sigma)^2)`` from the residual at the current normal with the previous albedo (fixed while
the pixel's sums are taken: iteratively reweighted least squares).  Outputs per pixel: the Gauss-Newton
Hessian ``H = J^T W J`` (2 x 2, in slope units), the gradient ``g = J^T W r`` and the new albedo; summed over
the mask, float64: the robust energy ``sum rho(r)`` (``rho = sigma^2 / 2 log(1 + r^2 / sigma^2)``, or ``r^2 /
2`` without the robust loss), the traces of ``H`` and the pixels.

:func:`refine_targets_kernel` turns ``(H, g)`` and the Levenberg damping ``lambda`` into the integrator's
system.  The model of a pixel, ``q(s) = g.(s - s0) + (s - s0)^T (H + lambda I) (s - s0) / 2``, couples its two
steps; ``D = diag(H_aa + |H_ac|, H_cc + |H_ac|) + lambda I`` dominates ``H + lambda I`` (Gershgorin: ``D - H -
lambda I`` is diagonally dominant with a non-negative diagonal), so ``g.(s - s0) + (s - s0)^T D (s - s0) / 2``
is a majorant of ``q`` that touches it at ``s0`` (majorisation-minimisation: its minimiser cannot increase
``q``) and it separates into the per-direction terms ``D_a (a - a*)^2 / 2 + D_c (c - c*)^2 / 2`` with ``a* =
a0 - g_a / D_a``: the integrator's weighted least squares (4.20) for the increment of ``u``, with confidences
``D`` and step increments ``a* - a0 = -g_a / D_a`` (in step units: ``c_j = D_a k_j^2``, ``-g_a / (D_a k_j)``;
``k_j = fx`` or ``1 / s``).  A pixel with no
usable observation has ``H = 0, g = 0``: confidence ``lambda`` toward its current step, so it follows its
neighbours through integrability.  The kernel also writes the normals: the surface's (of ``s0``), or the
per-pixel Levenberg-Marquardt normal, of ``s0 - (H + lambda I)^{-1} g`` (one step from the surface toward the
pixel's own data).

Only device code lives here; nothing allocates.
"""

import warp as wp

from gpps.kernels.brdf import CameraParams, LightParams, MaterialParams, brdf_terms, light_dir, light_radiance, pixel_point, view_dir
from gpps.kernels.solve_common import ASIDE

#: central-difference step of the per-pixel Jacobian, in slope units (float32 residuals: ~1e-4 relative error)
FD_STEP = wp.constant(1.0e-3)


@wp.func
def step_scale_j(cam: CameraParams):
    """``alpha / a``: slope units per step unit along j."""
    if cam.perspective != 0:
        return cam.fx
    return 1.0 / cam.pixel_size


@wp.func
def step_scale_i(cam: CameraParams):
    """``gamma / c``: slope units per step unit along i."""
    if cam.perspective != 0:
        return cam.fy
    return 1.0 / cam.pixel_size


@wp.func
def u_of(cam: CameraParams, d: float):
    """The integrator's unknown at depth ``d``: ``log d`` (perspective) or ``d``."""
    if cam.perspective != 0:
        return wp.log(d)
    return d


@wp.func
def bini_factors(cam: CameraParams, nref: wp.vec3, i: int, j: int, min_nz: float):
    """BiNI's ``(N_zj, N_zi)`` of the reference normal ``nref`` at pixel (i, j) (:func:`gpps.host.poisson.pixel_gradients`:
    orthographic ``n_z / s``, perspective ``-f m``); ``(0, 0)`` for a zero normal (central differences then)."""
    if wp.length(nref) < 1.0e-6:
        return wp.vec2(0.0, 0.0)
    n = wp.normalize(nref)
    if cam.perspective != 0:
        m = wp.min(n[0] * (float(j) - cam.cx) / cam.fx - n[1] * (float(i) - cam.cy) / cam.fy - n[2], -min_nz)
        return wp.vec2(-cam.fx * m, -cam.fy * m)
    den = wp.max(n[2], min_nz)
    return wp.vec2(den / cam.pixel_size, den / cam.pixel_size)


@wp.func
def one_sided(um: float, u0: float, up: float, has_m: bool, has_p: bool, nz: float, k: float):
    """``(step, w+)``: a pixel's step along one axis from its one-sided differences ``d- = u0 - um``, ``d+ = up - u0``
    and the forward difference's weight.  Both present: BiNI's blend ``w+ d+ + (1 - w+) d-`` with ``w+ =
    sigmoid(k ((N_z d-)^2 - (N_z d+)^2))`` (:func:`gpps.host.poisson.bilateral_weights`: the side with the smaller
    jump weighs more; ``k = 0``: the central difference, ``w+ = 1/2``); one present: it (``w+`` 1 or 0); none:
    ``(0, 1/2)``."""
    if has_m and has_p:
        dm = u0 - um
        dp = up - u0
        x = k * ((nz * dm) * (nz * dm) - (nz * dp) * (nz * dp))
        wpl = float(0.5)
        if x > 40.0:
            wpl = 1.0
        elif x < -40.0:
            wpl = 0.0
        else:
            wpl = 1.0 / (1.0 + wp.exp(-x))
        return wp.vec2(wpl * dp + (1.0 - wpl) * dm, wpl)
    if has_p:
        return wp.vec2(up - u0, 1.0)
    if has_m:
        return wp.vec2(u0 - um, 0.0)
    return wp.vec2(0.0, 0.5)


@wp.func
def steps_at(depth: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8), cam: CameraParams,
             nref: wp.array2d(dtype=wp.vec3), k: float, min_nz: float, i: int, j: int):
    """``(a, c, w+_j, w+_i)``: the steps of ``u`` at pixel (i, j) and their forward weights (:func:`one_sided` along
    j and along i, BiNI's weights from the reference normals ``nref``: module docstring)."""
    h = depth.shape[0]
    w = depth.shape[1]
    u0 = u_of(cam, depth[i, j])
    left = j > 0 and mask[i, j - 1] != wp.uint8(0)
    right = j < w - 1 and mask[i, j + 1] != wp.uint8(0)
    up = i > 0 and mask[i - 1, j] != wp.uint8(0)
    down = i < h - 1 and mask[i + 1, j] != wp.uint8(0)
    uL = u0
    uR = u0
    uU = u0
    uD = u0
    if left:
        uL = u_of(cam, depth[i, j - 1])
    if right:
        uR = u_of(cam, depth[i, j + 1])
    if up:
        uU = u_of(cam, depth[i - 1, j])
    if down:
        uD = u_of(cam, depth[i + 1, j])
    nz = bini_factors(cam, nref[i, j], i, j, min_nz)
    sj = one_sided(uL, u0, uR, left, right, nz[0], k)
    si = one_sided(uU, u0, uD, up, down, nz[1], k)
    return wp.vec4(sj[0], si[0], sj[1], si[1])


@wp.func
def slope_normal(cam: CameraParams, i: int, j: int, alpha: float, gamma: float):
    """The unit normal of the slopes ``(alpha, gamma)`` at pixel (i, j) (module docstring)."""
    nz = float(1.0)
    if cam.perspective != 0:
        nz = 1.0 + alpha * (float(j) - cam.cx) / cam.fx + gamma * (float(i) - cam.cy) / cam.fy
    return wp.normalize(wp.vec3(alpha, -gamma, nz))


@wp.func
def surface_or_reference(depth: wp.array2d(dtype=wp.float32), mask: wp.array2d(dtype=wp.uint8),
                         nref: wp.array2d(dtype=wp.vec3), cam: CameraParams, i: int, j: int, ns: wp.vec3):
    """The returned normal of pixel (i, j): the surface's ``ns``, except on the mask's border (a neighbour missing
    along j or i: the step there is a one-sided extrapolation, and at an occluding contour the surface is grazing,
    so the depth does not fix the normal) or where ``ns`` faces away from the camera: there the reference
    (per-pixel) normal, when it has one."""
    h = depth.shape[0]
    w = depth.shape[1]
    inner = j > 0 and j < w - 1 and i > 0 and i < h - 1
    if inner:
        inner = (mask[i, j - 1] != wp.uint8(0) and mask[i, j + 1] != wp.uint8(0) and mask[i - 1, j] != wp.uint8(0)
                 and mask[i + 1, j] != wp.uint8(0))
    v = view_dir(cam, pixel_point(cam, i, j, depth[i, j]))
    nr = nref[i, j]
    if (not inner or wp.dot(ns, v) <= 0.0) and wp.length(nr) > 1.0e-6:
        return wp.normalize(nr)
    return ns


@wp.func
def cauchy_weight(r: float, sigma: float, robust: int):
    if robust == 0:
        return 1.0
    q = r / sigma
    return 1.0 / (1.0 + q * q)


@wp.func
def cauchy_rho(r: float, sigma: float, robust: int):
    if robust == 0:
        return 0.5 * r * r
    q = r / sigma
    return 0.5 * sigma * sigma * wp.log(1.0 + q * q)


@wp.func
def albedo_of(num: wp.vec3, den: wp.vec3, fallback: wp.vec3):
    out = fallback
    for c in range(3):
        if den[c] > 0.0:
            out[c] = num[c] / den[c]
    return out


@wp.func
def albedo_terms(e: float, obs: float, t: wp.vec2, ks: float):
    """One observation's terms of the albedo's normal equation in one channel: ``(A y, A^2)`` with ``A = E t_d``
    and ``y = I - E ks t_s`` (the albedo is ``sum w A y / sum w A^2``)."""
    a = e * t[0]
    return wp.vec2(a * (obs - e * ks * t[1]), a * a)


@wp.func
def predict(e: wp.vec3, t: wp.vec2, kd: wp.vec3, ks: float):
    return wp.cw_mul(e, kd * t[0] + wp.vec3(ks * t[1]))


@wp.kernel(enable_backward=False)
def refine_eval_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    nref: wp.array2d(dtype=wp.vec3),
    edge_k: float,
    min_nz: float,
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    cam: CameraParams,
    lights: LightParams,
    mat: MaterialParams,
    albedo_prev: wp.array2d(dtype=wp.vec3),
    sigma: float,
    robust: int,
    hess: wp.array2d(dtype=wp.vec3),
    grad: wp.array2d(dtype=wp.vec2),
    albedo: wp.array2d(dtype=wp.vec3),
    rms: wp.array2d(dtype=wp.float32),
    sums: wp.array(dtype=wp.float64),
):
    """Per pixel (dim (H, W)): ``hess`` = (H_aa, H_ac, H_cc), ``grad`` = (g_a, g_c) (slope units), the new
    ``albedo`` and ``rms`` (the root mean square residual of the used observations, unweighted); ``sums`` (3,)
    float64, added to: [0] robust energy, [1] ``H_aa + H_cc``, [2] mask pixels.  Off the mask all zero."""
    i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        hess[i, j] = wp.vec3(0.0)
        grad[i, j] = wp.vec2(0.0)
        albedo[i, j] = wp.vec3(0.0)
        rms[i, j] = 0.0
        return
    kj = step_scale_j(cam)
    ki = step_scale_i(cam)
    s = steps_at(depth, mask, cam, nref, edge_k, min_nz, i, j)
    al = s[0] * kj
    ga = s[1] * ki
    hh = FD_STEP
    n0 = slope_normal(cam, i, j, al, ga)
    n1 = slope_normal(cam, i, j, al + hh, ga)
    n2 = slope_normal(cam, i, j, al - hh, ga)
    n3 = slope_normal(cam, i, j, al, ga + hh)
    n4 = slope_normal(cam, i, j, al, ga - hh)
    p = pixel_point(cam, i, j, depth[i, j])
    v = view_dir(cam, p)
    kd0 = albedo_prev[i, j]
    ks = mat.ks
    nl = valid.shape[0]
    # pass 1: the weighted least-squares albedo of each of the five normals
    num0 = wp.vec3(0.0)
    num1 = wp.vec3(0.0)
    num2 = wp.vec3(0.0)
    num3 = wp.vec3(0.0)
    num4 = wp.vec3(0.0)
    den0 = wp.vec3(0.0)
    den1 = wp.vec3(0.0)
    den2 = wp.vec3(0.0)
    den3 = wp.vec3(0.0)
    den4 = wp.vec3(0.0)
    for k in range(nl):
        if valid[k, i, j] != wp.uint8(0):
            l = light_dir(lights, k, p)
            e = light_radiance(lights, k, p)
            obs = images[k, i, j]
            t0 = brdf_terms(mat, n0, l, v)
            t1 = brdf_terms(mat, n1, l, v)
            t2 = brdf_terms(mat, n2, l, v)
            t3 = brdf_terms(mat, n3, l, v)
            t4 = brdf_terms(mat, n4, l, v)
            r0 = predict(e, t0, kd0, ks) - obs
            for c in range(3):
                w = cauchy_weight(r0[c], sigma, robust)
                q0 = albedo_terms(e[c], obs[c], t0, ks) * w
                q1 = albedo_terms(e[c], obs[c], t1, ks) * w
                q2 = albedo_terms(e[c], obs[c], t2, ks) * w
                q3 = albedo_terms(e[c], obs[c], t3, ks) * w
                q4 = albedo_terms(e[c], obs[c], t4, ks) * w
                num0[c] += q0[0]
                den0[c] += q0[1]
                num1[c] += q1[0]
                den1[c] += q1[1]
                num2[c] += q2[0]
                den2[c] += q2[1]
                num3[c] += q3[0]
                den3[c] += q3[1]
                num4[c] += q4[0]
                den4[c] += q4[1]
    kda = albedo_of(num0, den0, kd0)
    kd1 = albedo_of(num1, den1, kd0)
    kd2 = albedo_of(num2, den2, kd0)
    kd3 = albedo_of(num3, den3, kd0)
    kd4 = albedo_of(num4, den4, kd0)
    # pass 2: residuals, central differences, the sums
    haa = float(0.0)
    hac = float(0.0)
    hcc = float(0.0)
    gaa = float(0.0)
    gcc = float(0.0)
    en = float(0.0)
    sq = float(0.0)
    cnt = int(0)
    inv2h = 0.5 / hh
    for k in range(nl):
        if valid[k, i, j] != wp.uint8(0):
            l = light_dir(lights, k, p)
            e = light_radiance(lights, k, p)
            obs = images[k, i, j]
            t0 = brdf_terms(mat, n0, l, v)
            rw = predict(e, t0, kd0, ks) - obs
            r = predict(e, t0, kda, ks) - obs
            ja = (predict(e, brdf_terms(mat, n1, l, v), kd1, ks) - predict(e, brdf_terms(mat, n2, l, v), kd2, ks)) * inv2h
            jc = (predict(e, brdf_terms(mat, n3, l, v), kd3, ks) - predict(e, brdf_terms(mat, n4, l, v), kd4, ks)) * inv2h
            for c in range(3):
                w = cauchy_weight(rw[c], sigma, robust)
                haa += w * ja[c] * ja[c]
                hac += w * ja[c] * jc[c]
                hcc += w * jc[c] * jc[c]
                gaa += w * ja[c] * r[c]
                gcc += w * jc[c] * r[c]
                en += cauchy_rho(r[c], sigma, robust)
                sq += r[c] * r[c]
            cnt += 3
    hess[i, j] = wp.vec3(haa, hac, hcc)
    grad[i, j] = wp.vec2(gaa, gcc)
    albedo[i, j] = kda
    if cnt > 0:
        rms[i, j] = wp.sqrt(sq / float(cnt))
    else:
        rms[i, j] = 0.0
    wp.atomic_add(sums, 0, wp.float64(en))
    wp.atomic_add(sums, 1, wp.float64(haa + hcc))
    wp.atomic_add(sums, 2, wp.float64(1.0))


@wp.kernel(enable_backward=False)
def refine_targets_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    nref: wp.array2d(dtype=wp.vec3),
    edge_k: float,
    min_nz: float,
    cam: CameraParams,
    hess: wp.array2d(dtype=wp.vec3),
    grad: wp.array2d(dtype=wp.vec2),
    lam: float,
    pixel_normals: int,
    steps: wp.array3d(dtype=wp.float32),
    conf: wp.array3d(dtype=wp.float32),
    wplus: wp.array3d(dtype=wp.float32),
    normals: wp.array2d(dtype=wp.vec3),
):
    """Per pixel (dim (H, W)): the majorant's step increments ``steps[i, j] = (a* - a0, c* - c0)`` and confidences
    ``conf[i, j] = (c_j, c_i)`` (step units), and ``normals``: with ``pixel_normals`` the Levenberg-Marquardt
    normal (module docstring), else the surface's (of ``s0``; :func:`surface_or_reference` on the mask's border).  Off the mask: zeros (the integrator drops the
    pixel)."""
    i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        steps[i, j, 0] = 0.0
        steps[i, j, 1] = 0.0
        conf[i, j, 0] = 0.0
        conf[i, j, 1] = 0.0
        wplus[i, j, 0] = 0.5
        wplus[i, j, 1] = 0.5
        normals[i, j] = wp.vec3(0.0)
        return
    kj = step_scale_j(cam)
    ki = step_scale_i(cam)
    s = steps_at(depth, mask, cam, nref, edge_k, min_nz, i, j)
    al = s[0] * kj
    ga = s[1] * ki
    hv = hess[i, j]
    g = grad[i, j]
    off = wp.abs(hv[1])
    da = hv[0] + off + lam
    dc = hv[2] + off + lam
    steps[i, j, 0] = -(g[0] / da) / kj
    steps[i, j, 1] = -(g[1] / dc) / ki
    conf[i, j, 0] = da * kj * kj
    conf[i, j, 1] = dc * ki * ki
    wplus[i, j, 0] = s[2]
    wplus[i, j, 1] = s[3]
    # the pixel's own Levenberg-Marquardt step (2 x 2 solve)
    a11 = hv[0] + lam
    a12 = hv[1]
    a22 = hv[2] + lam
    det = a11 * a22 - a12 * a12
    sa = al
    sc = ga
    if pixel_normals != 0 and det > 0.0:
        sa = al - (a22 * g[0] - a12 * g[1]) / det
        sc = ga - (a11 * g[1] - a12 * g[0]) / det
    n_out = slope_normal(cam, i, j, sa, sc)
    if pixel_normals == 0:
        n_out = surface_or_reference(depth, mask, nref, cam, i, j, n_out)
    normals[i, j] = n_out


@wp.kernel(enable_backward=False)
def residual_sample_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    nref: wp.array2d(dtype=wp.vec3),
    edge_k: float,
    min_nz: float,
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    cam: CameraParams,
    lights: LightParams,
    mat: MaterialParams,
    albedo: wp.array2d(dtype=wp.vec3),
    stride: int,
    out: wp.array3d(dtype=wp.float32),
):
    """The absolute residuals (mean over the channels) of every observation of every ``stride``-th pixel in each
    direction (dim (N, ceil(H / stride), ceil(W / stride))) at the normal of the current depth with ``albedo``:
    ``out[k, a, b]`` for pixel ``(a stride, b stride)``; -1 where the pixel is off the mask or the observation
    not valid.  The robust scale's sample (:class:`gpps.pipeline.depth_refine.DepthRefiner`)."""
    k, a, b = wp.tid()
    i = a * stride
    j = b * stride
    r = float(-1.0)
    if mask[i, j] != wp.uint8(0) and valid[k, i, j] != wp.uint8(0):
        s = steps_at(depth, mask, cam, nref, edge_k, min_nz, i, j)
        n = slope_normal(cam, i, j, s[0] * step_scale_j(cam), s[1] * step_scale_i(cam))
        p = pixel_point(cam, i, j, depth[i, j])
        v = view_dir(cam, p)
        d = predict(light_radiance(lights, k, p), brdf_terms(mat, n, light_dir(lights, k, p), v), albedo[i, j], mat.ks) - images[k, i, j]
        r = (wp.abs(d[0]) + wp.abs(d[1]) + wp.abs(d[2])) / 3.0
    out[k, a, b] = r


@wp.func
def pixel_energy(n: wp.vec3, kd0: wp.vec3, images: wp.array3d(dtype=wp.vec3), valid: wp.array3d(dtype=wp.uint8),
                 lights: LightParams, mat: MaterialParams, p: wp.vec3, v: wp.vec3, i: int, j: int, sigma: float):
    """The pixel's robust (Cauchy, scale ``sigma``) misfit at normal ``n``, its albedo the weighted least-squares one
    (weights from the residuals with ``kd0``), as :func:`refine_eval_kernel` computes it at the current normal."""
    num = wp.vec3(0.0)
    den = wp.vec3(0.0)
    nl = valid.shape[0]
    for k in range(nl):
        if valid[k, i, j] != wp.uint8(0):
            e = light_radiance(lights, k, p)
            t = brdf_terms(mat, n, light_dir(lights, k, p), v)
            obs = images[k, i, j]
            r0 = predict(e, t, kd0, mat.ks) - obs
            for c in range(3):
                q = albedo_terms(e[c], obs[c], t, mat.ks) * cauchy_weight(r0[c], sigma, 1)
                num[c] += q[0]
                den[c] += q[1]
    kd = albedo_of(num, den, kd0)
    en = float(0.0)
    for k in range(nl):
        if valid[k, i, j] != wp.uint8(0):
            e = light_radiance(lights, k, p)
            r = predict(e, brdf_terms(mat, n, light_dir(lights, k, p), v), kd, mat.ks) - images[k, i, j]
            for c in range(3):
                en += cauchy_rho(r[c], sigma, 1)
    return en


@wp.kernel(enable_backward=False)
def select_normals_kernel(
    depth: wp.array2d(dtype=wp.float32),
    mask: wp.array2d(dtype=wp.uint8),
    nref: wp.array2d(dtype=wp.vec3),
    edge_k: float,
    min_nz: float,
    images: wp.array3d(dtype=wp.vec3),
    valid: wp.array3d(dtype=wp.uint8),
    cam: CameraParams,
    lights: LightParams,
    mat: MaterialParams,
    albedo: wp.array2d(dtype=wp.vec3),
    sigma: float,
    scale: float,
    threshold: float,
    normals: wp.array2d(dtype=wp.vec3),
    counts: wp.array(dtype=wp.int32),
):
    """Per pixel (dim (H, W)): ``normals`` = the surface's normal, or the reference (per-pixel) normal ``nref`` where
    the pixel's own data reject the surface's: ``2 (E_surface - E_ref) / scale^2 > threshold`` (a likelihood-ratio
    test of the two normal parameters the surface fixes, ``E``: :func:`pixel_energy` with Cauchy's ``sigma``,
    ``scale`` the residuals' scale).  ``counts[0]`` += the pixels that keep ``nref``."""
    i, j = wp.tid()
    if mask[i, j] == wp.uint8(0):
        normals[i, j] = wp.vec3(0.0)
        return
    s = steps_at(depth, mask, cam, nref, edge_k, min_nz, i, j)
    ns = surface_or_reference(depth, mask, nref, cam, i, j,
                              slope_normal(cam, i, j, s[0] * step_scale_j(cam), s[1] * step_scale_i(cam)))
    out = ns
    nr = nref[i, j]
    if wp.length(nr) > 1.0e-6:
        nr = wp.normalize(nr)
        p = pixel_point(cam, i, j, depth[i, j])
        v = view_dir(cam, p)
        kd0 = albedo[i, j]
        es = pixel_energy(ns, kd0, images, valid, lights, mat, p, v, i, j, sigma)
        er = pixel_energy(nr, kd0, images, valid, lights, mat, p, v, i, j, sigma)
        if 2.0 * (es - er) > threshold * scale * scale:
            out = nr
            wp.atomic_add(counts, 0, 1)
    normals[i, j] = out


@wp.kernel(enable_backward=False)
def kept_observations_kernel(
    valid: wp.array3d(dtype=wp.uint8),
    weights: wp.array3d(dtype=wp.float32),
    kept: wp.array3d(dtype=wp.uint8),
):
    """``kept = valid`` except the observations the pixel solver set aside as cast shadows (weight ``ASIDE``:
    its neighbour pass's attached / cast shadow choice, or its robust fit's cast-shadow refit); dim (N, H, W)."""
    k, i, j = wp.tid()
    out = valid[k, i, j]
    if weights[k, i, j] == ASIDE:
        out = wp.uint8(0)
    kept[k, i, j] = out
