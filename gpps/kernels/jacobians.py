"""Analytic derivatives of the reflectance terms with respect to the normal.

Device math only.  Each ``*_value_grad`` returns a ``vec4`` ``(value, dvalue/dn)``
where ``n`` is treated as a free 3-vector and the value is the *formula as
written* in :mod:`gpps.kernels.brdf` (so the gradient is exact in every
direction; callers only use its tangential part through the chart Jacobian
:func:`chart_normal_jacobian`).  The gating (attached shadow ``n.l <= 0``, no
specular term for ``n.v <= 0``, the lobes' own cut-offs) is the same as in
:func:`gpps.kernels.brdf.brdf_terms`, so value and gradient are zero together.

Models (seed numbering): Lambertian (2.13), Phong (2.19-2.20), Blinn-Phong
(2.21 / 3.14), Cook-Torrance (2.22-2.29, 4.1), Ashikhmin-Shirley (5.1-5.2); and plastic
(not the seed's, :func:`gpps.kernels.brdf.plastic_spec`), whose *diffuse* factor depends on
the model too (:func:`diffuse_value_grad_of`); and the rough conductor (not the seed's either,
:func:`gpps.kernels.brdf.conductor_spec`), whose GGX lobe is its albedo-weighted (diffuse-slot) term.

Normal parameterisation used by the solvers (no singularity near the camera
axis): a chart around a base unit normal ``n0`` with an orthonormal tangent
basis ``(t1, t2)``::

    n(x) = m / |m|,   m = n0 + x0 t1 + x1 t2,   dn/dx_i = (I - n n^T) t_i / |m|
"""

import warp as wp

from gpps.kernels.brdf import (
    ASHIKHMIN_SHIRLEY,
    BLINN_PHONG,
    CONDUCTOR,
    COOK_TORRANCE,
    LAMBERTIAN,
    PHONG,
    PI,
    PLASTIC,
    MaterialParams,
    fresnel_dielectric,
    ggx_q,
    ior_from_f0,
    one_minus_dot,
    schlick,
    tangent_frame_u,
)

# --------------------------------------------------------------------------- chart

mat32 = wp.types.matrix(shape=(3, 2), dtype=wp.float32)


# A unit vector orthogonal to n (continuous away from n = +-x): the same tangent as the
# Ashikhmin-Shirley frame, so the chart and the anisotropic lobe share one definition.
tangent_basis_t1 = tangent_frame_u


@wp.func
def chart_normal(n0: wp.vec3, t1: wp.vec3, t2: wp.vec3, x: wp.vec2):
    """``n(x) = normalize(n0 + x0 t1 + x1 t2)``."""
    return wp.normalize(n0 + x[0] * t1 + x[1] * t2)


@wp.func
def chart_normal_jacobian(n0: wp.vec3, t1: wp.vec3, t2: wp.vec3, x: wp.vec2):
    """``(dn/dx0, dn/dx1)`` as the two columns of a 3x2 matrix (rows x, y, z)."""
    m = n0 + x[0] * t1 + x[1] * t2
    lm = wp.length(m)
    n = m / lm
    d0 = (t1 - wp.dot(n, t1) * n) / lm
    d1 = (t2 - wp.dot(n, t2) * n) / lm
    return mat32(d0[0], d1[0], d0[1], d1[1], d0[2], d1[2])


# --------------------------------------------------------------------------- diffuse


@wp.func
def diffuse_value_grad(n: wp.vec3, l: wp.vec3):
    """``(max(n.l, 0), d/dn)`` (2.13)."""
    nl = wp.dot(n, l)
    if nl <= 0.0:
        return wp.vec4(0.0)
    return wp.vec4(nl, l[0], l[1], l[2])


# --------------------------------------------------------------------------- specular lobes


@wp.func
def _vg(s: float, g: wp.vec3):
    return wp.vec4(s, g[0], g[1], g[2])


@wp.func
def phong_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, shininess: float):
    """Phong (2.20): ``c = R.v = 2 (l.n)(n.v) - l.v``, ``s = c^e``, ``ds = e c^(e-1) 2 ((n.v) l + (l.n) v)``."""
    ln_ = wp.dot(l, n)
    r = 2.0 * ln_ * n - l
    c = wp.dot(r, v)
    if c <= 0.0:
        return wp.vec4(0.0)
    s = wp.pow(c, shininess)
    dc = 2.0 * (wp.dot(n, v) * l + ln_ * v)
    return _vg(s, (shininess * s / c) * dc)


@wp.func
def blinn_phong_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, shininess: float):
    """Blinn-Phong (2.21): ``s = (n.h)^e``, ``ds = e (n.h)^(e-1) h``."""
    h = wp.normalize(l + v)
    c = wp.dot(n, h)
    if c <= 0.0:
        return wp.vec4(0.0)
    s = wp.pow(c, shininess)
    return _vg(s, (shininess * s / c) * h)


@wp.func
def cook_torrance_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, m: float, f0: float):
    """Cook-Torrance ``D G F / (4 n.v)`` (2.22-2.29) and its gradient.

    ``d ln D / d(n.h) = 2 / (m^2 c^3) - 4 / c`` (Beckmann, c = n.h); G is
    differentiated on its active branch (2.23-2.26); F depends on h.v only.
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nv = wp.dot(n, v)
    nl = wp.dot(n, l)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return wp.vec4(0.0)
    c2 = nh * nh
    m2 = m * m
    tan2 = (1.0 - c2) / c2
    d = wp.exp(-tan2 / m2) / (PI * m2 * c2 * c2)
    g1 = 2.0 * nh * nv / vh
    g2 = 2.0 * nh * nl / vh
    gmin = wp.min(g1, g2)
    g = wp.min(1.0, gmin)
    dg = wp.vec3(0.0)
    if gmin < 1.0:
        if g1 <= g2:
            dg = (2.0 / vh) * (nv * h + nh * v)
        else:
            dg = (2.0 / vh) * (nl * h + nh * l)
    f = schlick(f0, vh)
    s = d * g * f / (4.0 * nv)
    dlnd = 2.0 / (m2 * c2 * nh) - 4.0 / nh
    grad = s * (dlnd * h - v / nv)
    if g > 0.0:
        grad = grad + (s / g) * dg
    return _vg(s, grad)


@wp.func
def ashikhmin_shirley_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, eta_u: float, eta_v: float, f0: float):
    """Ashikhmin-Shirley (5.1-5.2, see :func:`gpps.kernels.brdf.ashikhmin_shirley_spec`) and its gradient.

    ``ln s = ln c + zeta ln(n.h) + ln F(h.v) + ln(n.l) - ln(h.v) - ln max(n.l, n.v)``;
    zeta depends on n through the tangent frame ``tu = normalize(a - (a.n) n)``,
    ``tv = n x tu``: ``d tu/dn = (I - tu tu^T)/|w| * (-(n a^T) - (a.n) I)``,
    ``d(h.tv)/dn = tu x h + (d tu/dn)^T (h x n)``.
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nl <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return wp.vec4(0.0)
    a = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        a = wp.vec3(0.0, 1.0, 0.0)
    an = wp.dot(a, n)
    w = a - an * n
    lw = wp.length(w)
    tu = w / lw
    tv = wp.cross(n, tu)
    hu = wp.dot(h, tu)
    hv = wp.dot(h, tv)
    s2 = hu * hu + hv * hv
    zeta = 0.5 * (eta_u + eta_v)
    dzeta = wp.vec3(0.0)
    if s2 > 1.0e-12:
        num = eta_u * hu * hu + eta_v * hv * hv
        zeta = num / s2
        eye = wp.identity(n=3, dtype=wp.float32)
        jw = -wp.outer(n, a) - an * eye
        jtu = ((eye - wp.outer(tu, tu)) / lw) * jw
        dhu = wp.transpose(jtu) * h
        dhv = wp.cross(tu, h) + wp.transpose(jtu) * wp.cross(h, n)
        dnum = 2.0 * (eta_u * hu * dhu + eta_v * hv * dhv)
        ds2 = 2.0 * (hu * dhu + hv * dhv)
        dzeta = (dnum * s2 - num * ds2) / (s2 * s2)
    norm = wp.sqrt((eta_u + 1.0) * (eta_v + 1.0)) / (8.0 * PI)
    mx = nl
    dmx = l / nl
    if nv > nl:
        mx = nv
        dmx = v / nv
    s = norm * wp.pow(nh, zeta) * schlick(f0, vh) * nl / (vh * mx)
    dln = wp.log(nh) * dzeta + (zeta / nh) * h + l / nl - dmx
    return _vg(s, s * dln)


@wp.func
def specular_value_grad(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
    """``(s, ds/dn)`` of the material's lobe with the gating of ``brdf_terms`` (0 for the conductor, whose lobe is
    its albedo-weighted term, :func:`diffuse_value_grad_of`)."""
    if mat.model == LAMBERTIAN or mat.model == CONDUCTOR:
        return wp.vec4(0.0)
    if wp.dot(n, l) <= 0.0 or wp.dot(n, v) <= 0.0:
        return wp.vec4(0.0)
    if mat.model == PHONG:
        return phong_value_grad(n, l, v, mat.shininess)
    if mat.model == BLINN_PHONG:
        return blinn_phong_value_grad(n, l, v, mat.shininess)
    if mat.model == COOK_TORRANCE:
        return cook_torrance_value_grad(n, l, v, mat.roughness, mat.f0)
    if mat.model == ASHIKHMIN_SHIRLEY:
        return ashikhmin_shirley_value_grad(n, l, v, mat.eta_u, mat.eta_v, mat.f0)
    if mat.model == PLASTIC:
        return plastic_value_grad(n, l, v, mat.roughness, ior_from_f0(mat.f0))
    return wp.vec4(0.0)


# --------------------------------------------------------------------------- dielectric coating (plastic)


@wp.func
def fresnel_dielectric_value_grad(c: float, eta: float):
    """``(F, dF/dc)`` of :func:`gpps.kernels.brdf.fresnel_dielectric`.

    ``F = a^2 (1 + b^2) / 2`` with ``a = (g - c) / (g + c)``, ``b = (c (g + c) - 1) / (c (g - c) + 1)``,
    ``g = sqrt(eta^2 - 1 + c^2)``, ``dg/dc = c / g``: ``da/dc = -2 (eta^2 - 1) / (g (g + c)^2)`` and
    ``db/dc = (P' Q - P Q') / Q^2`` with ``P' = g + c^2 / g + 2c``, ``Q' = g + c^2 / g - 2c``.
    """
    e2 = eta * eta - 1.0
    g = wp.sqrt(e2 + c * c)
    gc = g + c
    a = (g - c) / gc
    da = -2.0 * e2 / (g * gc * gc)
    p = c * gc - 1.0
    q = c * (g - c) + 1.0
    b = p / q
    t = g + c * c / g
    db = ((t + 2.0 * c) * q - p * (t - 2.0 * c)) / (q * q)
    return wp.vec2(0.5 * a * a * (1.0 + b * b), a * da * (1.0 + b * b) + a * a * b * db)


@wp.func
def plastic_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, m: float, eta: float):
    """The coating's lobe ``pi D G F(h.v, eta) / (4 n.v)`` (:func:`gpps.kernels.brdf.plastic_spec`) and its gradient:
    F depends on ``h.v`` only, so it is Cook-Torrance's with f0 = 1 (Schlick's F = 1) times ``pi F``."""
    vh = wp.dot(v, wp.normalize(l + v))
    if vh <= 0.0:
        return wp.vec4(0.0)
    return (PI * fresnel_dielectric(vh, eta)) * cook_torrance_value_grad(n, l, v, m, 1.0)


@wp.func
def plastic_diffuse_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, eta: float):
    """``d = (n.l) T(n.l) T(n.v)``, ``T = 1 - F`` (:func:`gpps.kernels.brdf.plastic_diffuse`) and
    ``dd/dn = (T_l T_v - (n.l) F'_l T_v) l - (n.l) T_l F'_v v``; 0 unless n.l, n.v > 0."""
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    if nl <= 0.0 or nv <= 0.0:
        return wp.vec4(0.0)
    fl = fresnel_dielectric_value_grad(nl, eta)
    fv = fresnel_dielectric_value_grad(nv, eta)
    tl = 1.0 - fl[0]
    tv = 1.0 - fv[0]
    return _vg(nl * tl * tv, (tl * tv - nl * fl[1] * tv) * l - (nl * tl * fv[1]) * v)


# --------------------------------------------------------------------------- rough metal (conductor)


@wp.func
def conductor_value_grad(n: wp.vec3, l: wp.vec3, v: wp.vec3, a: float, f0: float):
    """The conductor's GGX lobe (:func:`gpps.kernels.brdf.conductor_spec`) and its gradient.

    ``s = a^2 G1(n.l) F / (2 q^2 (n.v + r_v))`` with ``q = e (2 - e) + (n.h)^2 a^2``, ``e = |n - h|^2 / 2``
    (:func:`gpps.kernels.brdf.ggx_q`), ``r_x = sqrt(a^2 + (1 - a^2) x^2)``, ``G1(x) = 2 x / (x + r_x)``; F depends
    on ``h.v`` only.  ``d ln s = -2 dq / q + (1 / (n.l) - (1 + (1 - a^2)(n.l) / r_l) / (n.l + r_l)) l
    - ((1 + (1 - a^2)(n.v) / r_v) / (n.v + r_v)) v`` with ``dq/dn = 2 (1 - e)(n - h) + 2 (n.h) a^2 h``.
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nl <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return wp.vec4(0.0)
    a2 = a * a
    b = 1.0 - a2
    e = one_minus_dot(n, h)
    q = ggx_q(n, h, a2)
    rl = wp.sqrt(a2 + b * nl * nl)
    rv = wp.sqrt(a2 + b * nv * nv)
    s = a2 * (2.0 * nl / (nl + rl)) * (schlick(f0, vh) / f0) / (2.0 * q * q * (nv + rv))
    dq = (2.0 * (1.0 - e)) * (n - h) + (2.0 * nh * a2) * h
    dln = (-2.0 / q) * dq + (1.0 / nl - (1.0 + b * nl / rl) / (nl + rl)) * l - ((1.0 + b * nv / rv) / (nv + rv)) * v
    return _vg(s, s * dln)


@wp.func
def diffuse_value_grad_of(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
    """The material's diffuse (albedo-weighted) factor and its gradient (run-time switch on ``mat.model``): plastic's
    :func:`plastic_diffuse_value_grad`, the conductor's lobe (:func:`conductor_value_grad`, 0 unless n.l, n.v > 0),
    the others' :func:`diffuse_value_grad` (2.13)."""
    if mat.model == PLASTIC:
        return plastic_diffuse_value_grad(n, l, v, ior_from_f0(mat.f0))
    if mat.model == CONDUCTOR:
        return conductor_value_grad(n, l, v, mat.roughness, mat.f0)
    return diffuse_value_grad(n, l)
