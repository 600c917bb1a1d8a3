"""Reflectance models, light and camera geometry as Warp device functions.

Device math only (``@wp.struct`` / ``@wp.func`` / ``@wp.kernel``); nothing here
allocates.  All vectors are in the gpps frame (see :mod:`gpps.camera`): unit
normal ``n`` toward the camera, unit ``l`` from the surface toward the light,
unit ``v`` from the surface toward the camera.

Image model for one light and one colour channel c (seed 2.13, 2.20-2.22, 5.1)::

    I_c = E_c * ( kd_c * max(n.l, 0) + ks * s(n, l, v) )

and for ``plastic`` (not in the seed: :func:`plastic_spec`, :func:`plastic_diffuse`) the
diffuse cosine is replaced by ``max(n.l, 0) (1 - F(n.l)) (1 - F(n.v))``, what passes the
dielectric coating on the way in and out (F: :func:`fresnel_dielectric`).

where ``E_c`` is the light's RGB radiance at the point (intensity, times 1/r^2
and the LED lobe for point lights, 2.30-2.31), ``kd`` the RGB albedo (diffuse
colour), ``ks`` the scalar specular weight (specularities take the colour of
the light) and ``s`` the model's specular term below.  Attached shadows:
``n.l <= 0`` gives 0 for both terms; ``n.v <= 0`` gives no specular term.

:func:`brdf_terms` returns ``(max(n.l, 0), s)`` (plastic: its diffuse factor) so that
callers (renderer, solvers) can use the linearity in ``kd``.
"""

import warp as wp

from gpps import names

# Device-side tags of the reflectance models.  Public code names models by
# their strings (gpps.names.BRDF); these are only the switch inside kernels.
LAMBERTIAN = wp.constant(names.LAMBERTIAN)
PHONG = wp.constant(names.PHONG)
BLINN_PHONG = wp.constant(names.BLINN_PHONG)
COOK_TORRANCE = wp.constant(names.COOK_TORRANCE)
ASHIKHMIN_SHIRLEY = wp.constant(names.ASHIKHMIN_SHIRLEY)
PLASTIC = wp.constant(names.PLASTIC)
CONDUCTOR = wp.constant(names.CONDUCTOR)

DIRECTIONAL = wp.constant(names.LIGHT_DIRECTIONAL)
POINT = wp.constant(names.LIGHT_POINT)

PI = wp.constant(3.14159265358979323846)


@wp.struct
class MaterialParams:
    """Per-scene material (all scalars; the albedo is a per-pixel map).

    Attributes:
        model: device tag (LAMBERTIAN ... CONDUCTOR).
        ks: specular weight (>= 0).
        shininess: exponent n of Phong / Blinn-Phong (2.20, 2.21).
        roughness: RMS microfacet slope m of Cook-Torrance (2.27) and plastic; GGX alpha of the conductor.
        f0: reflectance at normal incidence for Schlick's Fresnel (2.29), in [0, 1]; plastic:
            the coating's, in [0, 1), which fixes its index of refraction (:func:`ior_from_f0`); conductor:
            in (0, 1], the shape of its Fresnel rise (:func:`conductor_spec`).
        eta_u: Ashikhmin-Shirley exponent along the tangent u (5.2).
        eta_v: Ashikhmin-Shirley exponent along the tangent v (5.2).
    """

    model: wp.int32
    ks: wp.float32
    shininess: wp.float32
    roughness: wp.float32
    f0: wp.float32
    eta_u: wp.float32
    eta_v: wp.float32


@wp.struct
class CameraParams:
    """Camera (see gpps.camera): perspective pinhole or orthographic.

    Attributes:
        perspective: 1 for the pinhole, 0 for orthographic.
        fx, fy: focal lengths in pixels (pinhole).
        cx, cy: principal point / image centre in pixels.
        pixel_size: scene units per pixel (orthographic).
    """

    perspective: wp.int32
    fx: wp.float32
    fy: wp.float32
    cx: wp.float32
    cy: wp.float32
    pixel_size: wp.float32


@wp.struct
class LightParams:
    """N lights of one kind.

    Attributes:
        kind: DIRECTIONAL or POINT.
        count: N.
        vec: (N,) unit directions toward the lights, or positions (scene units).
        intensity: (N,) RGB intensity (radiance of a directional light; for a
            point light, radiant intensity: radiance at distance r is I / r^2).
        axis: (N,) unit principal direction of a point light (LED), pointing
            from the LED into the scene; ignored when ``mu[k] == 0``.
        mu: (N,) anisotropy: the LED's intensity falls as cos(angle to axis)^mu.
    """

    kind: wp.int32
    count: wp.int32
    vec: wp.array(dtype=wp.vec3)
    intensity: wp.array(dtype=wp.vec3)
    axis: wp.array(dtype=wp.vec3)
    mu: wp.array(dtype=wp.float32)


# --------------------------------------------------------------------------- camera


@wp.func
def pixel_point(cam: CameraParams, i: int, j: int, depth: float):
    """Surface point (gpps frame) seen at pixel row i, column j with ``depth`` > 0 (2.33)."""
    u = float(j) - cam.cx
    v = float(i) - cam.cy
    if cam.perspective != 0:
        return wp.vec3(u * depth / cam.fx, -v * depth / cam.fy, -depth)
    return wp.vec3(u * cam.pixel_size, -v * cam.pixel_size, -depth)


@wp.func
def view_dir(cam: CameraParams, p: wp.vec3):
    """Unit vector from the surface point ``p`` toward the camera."""
    if cam.perspective != 0:
        return wp.normalize(-p)
    return wp.vec3(0.0, 0.0, 1.0)


# --------------------------------------------------------------------------- lights


@wp.func
def light_dir(lights: LightParams, k: int, p: wp.vec3):
    """Unit direction from ``p`` toward light ``k`` (2.30)."""
    if lights.kind == POINT:
        return wp.normalize(lights.vec[k] - p)
    return lights.vec[k]


@wp.func
def light_radiance(lights: LightParams, k: int, p: wp.vec3):
    """RGB radiance of light ``k`` arriving at ``p``.

    Directional: the intensity.  Point: ``I / r^2`` (2.31) times the LED lobe
    ``max(cos(angle between axis and the ray LED->p), 0)^mu``.
    """
    e = lights.intensity[k]
    if lights.kind == POINT:
        d = p - lights.vec[k]
        r2 = wp.dot(d, d)
        s = 1.0 / r2
        mu = lights.mu[k]
        if mu != 0.0:
            c = wp.dot(d, lights.axis[k]) / wp.sqrt(r2)
            s = s * wp.pow(wp.max(c, 0.0), mu)
        return e * s
    return e



# --------------------------------------------------------------------------- accurate powers near 1
#
# Highlights live where c = n.h (or R.v) is close to 1, and c^n amplifies the
# float32 rounding of c by n (n = 50 turns 1 ulp into 3e-6).  For unit vectors
# 1 - a.b = |a - b|^2 / 2 exactly, which has no cancellation, and
# c^n = exp(n log1p(-e)) with e = 1 - c keeps the lobe accurate to a few ulps.


@wp.func
def one_minus_dot(a: wp.vec3, b: wp.vec3):
    """``1 - a.b`` for unit vectors, as ``|a - b|^2 / 2`` (no cancellation near a = b)."""
    d = a - b
    return 0.5 * wp.dot(d, d)


@wp.func
def log1p(x: float):
    """``log(1 + x)`` accurate for small |x| (Goldberg's trick), x > -1."""
    u = 1.0 + x
    if u == 1.0:
        return x
    return wp.log(u) * x / (u - 1.0)


@wp.func
def pow_one_minus(e: float, p: float):
    """``(1 - e)^p`` for 0 <= e < 1, accurate when e is small."""
    if e >= 1.0:
        return 0.0
    return wp.exp(p * log1p(-e))


# --------------------------------------------------------------------------- specular lobes


@wp.func
def phong_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, shininess: float):
    """Phong lobe (2.19-2.20): ``max(R.v, 0)^n`` with ``R = 2 (l.n) n - l``."""
    r = 2.0 * wp.dot(l, n) * n - l
    if wp.dot(r, v) <= 0.0:
        return 0.0
    return pow_one_minus(one_minus_dot(r, v), shininess)


@wp.func
def blinn_phong_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, shininess: float):
    """Blinn-Phong lobe (2.21 / 3.14): ``max(n.h, 0)^n`` with ``h = (l + v) / |l + v|``."""
    h = wp.normalize(l + v)
    if wp.dot(n, h) <= 0.0:
        return 0.0
    return pow_one_minus(one_minus_dot(n, h), shininess)


@wp.func
def schlick(f0: float, c: float):
    """Schlick's Fresnel (2.29): ``f0 + (1 - f0)(1 - c)^5`` with ``c = h.v``."""
    t = 1.0 - c
    t2 = t * t
    return f0 + (1.0 - f0) * t2 * t2 * t


@wp.func
def cook_torrance_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, m: float, f0: float):
    """Cook-Torrance specular radiance factor (2.22-2.29).

    ``D G F / (4 n.v)`` with the Beckmann distribution
    ``D = exp(-tan^2(a) / m^2) / (pi m^2 cos^4(a))``, ``cos(a) = n.h`` (2.27-2.28),
    the geometric term ``G = min(1, 2 (n.h)(n.v)/(v.h), 2 (n.h)(n.l)/(v.h))``
    (2.23-2.26) and Schlick's Fresnel in ``h.v`` (2.29).  The usual ``1/(n.l)``
    of the BRDF cancels against the cosine of the irradiance, as in (2.22).
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nv = wp.dot(n, v)
    nl = wp.dot(n, l)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return 0.0
    c2 = nh * nh
    m2 = m * m
    e = one_minus_dot(n, h)
    tan2 = e * (2.0 - e) / c2  # (1 - c^2) / c^2 without cancellation
    d = wp.exp(-tan2 / m2) / (PI * m2 * c2 * c2)
    g = wp.min(1.0, wp.min(2.0 * nh * nv / vh, 2.0 * nh * nl / vh))
    f = schlick(f0, vh)
    return d * g * f / (4.0 * nv)


@wp.func
def tangent_frame_u(n: wp.vec3):
    """Unit tangent u: the camera x axis projected onto the tangent plane (y axis if degenerate)."""
    a = wp.vec3(1.0, 0.0, 0.0)
    if wp.abs(n[0]) > 0.9:
        a = wp.vec3(0.0, 1.0, 0.0)
    return wp.normalize(a - wp.dot(a, n) * n)


@wp.func
def ashikhmin_shirley_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, eta_u: float, eta_v: float, f0: float):
    """Ashikhmin-Shirley specular radiance factor (5.1-5.2).

    ``sqrt((eu+1)(ev+1)) / (8 pi) * (n.h)^zeta / ((h.v) max(n.l, n.v)) * F(h.v) * (n.l)``
    with ``zeta = (eu hu^2 + ev hv^2) / (1 - (n.h)^2)`` (5.2).  The seed's (5.1)
    drops ``max(n.l, n.v)`` and the irradiance cosine ``n.l``; we keep both, as in
    Ashikhmin & Shirley (2000), so that the lobe conserves energy.  ``hu, hv``
    are the components of h along the tangents u (camera x projected on the
    tangent plane) and ``n x u``; since ``hu^2 + hv^2 = 1 - (n.h)^2`` for unit h,
    zeta is evaluated as ``(eu hu^2 + ev hv^2) / (hu^2 + hv^2)`` (-> (eu+ev)/2 at h = n).
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nl <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return 0.0
    tu = tangent_frame_u(n)
    tv = wp.cross(n, tu)
    hu = wp.dot(h, tu)
    hv = wp.dot(h, tv)
    s2 = hu * hu + hv * hv
    zeta = 0.5 * (eta_u + eta_v)
    if s2 > 1.0e-12:
        zeta = (eta_u * hu * hu + eta_v * hv * hv) / s2
    norm = wp.sqrt((eta_u + 1.0) * (eta_v + 1.0)) / (8.0 * PI)
    lobe = pow_one_minus(one_minus_dot(n, h), zeta)
    return norm * lobe * schlick(f0, vh) * nl / (vh * wp.max(nl, nv))


# --------------------------------------------------------------------------- dielectric coating (plastic)
#
# Not in the seed.  A smooth or rough dielectric coating (index of refraction eta, air outside) over a
# diffuse base: the model of Mitsuba 3's ``plastic`` (smooth) and ``roughplastic`` plugins (W. Jakob et
# al., Mitsuba 3 plugin reference; roughplastic is "partly based on" Walter et al. 2007; for layered
# coatings in general cf. Weidlich & Wilkie, "Arbitrarily layered micro-facet surfaces", GRAPHITE 2007),
# in their linear mode (``nonlinear = false``):
#
#   specular: Cook-Torrance's microfacet lobe D G / (4 n.v) (2.22-2.28, the same Beckmann D and
#             V-cavity G) with the exact unpolarised dielectric Fresnel F(h.v, eta) instead of Schlick's
#             (Walter et al., "Microfacet models for refraction through rough surfaces", EGSR 2007, eq. 22);
#   diffuse:  kd max(n.l, 0) (1 - F(n.l, eta)) (1 - F(n.v, eta)): the light the coating does not reflect
#             enters, scatters in the base and leaves through the coating again (Mitsuba's smooth
#             ``plastic``; ``roughplastic`` uses the rough coating's transmittance in place of 1 - F).
#
# Mitsuba's per-material factor of the diffuse term, 1 / (eta^2 (1 - F_dr,int)) (the light reflected back
# inside the coating, linear in the base albedo), is left in kd: kd is the effective albedo and stays
# linear (brdf_terms' contract).  The specular lobe carries the factor pi of gpps's radiometry (the diffuse
# kd max(n.l, 0) is the Lambertian BRDF kd / pi lit by radiance pi E, see training/mitsuba_scenes.py), so
# ks = 1 is the physical coating (Mitsuba's specular_reflectance = 1).  tests/test_plastic.py checks both
# terms against Mitsuba's BSDFs (Beckmann roughplastic where both G are 1; plastic up to its constant).
# eta is not a field of MaterialParams: f0 = ((eta - 1) / (eta + 1))^2 is, and eta is derived from it.


@wp.func
def ior_from_f0(f0: float):
    """Index of refraction ``eta = (1 + sqrt(f0)) / (1 - sqrt(f0))`` whose normal-incidence reflectance is ``f0`` < 1."""
    r = wp.sqrt(f0)
    return (1.0 + r) / (1.0 - r)


@wp.func
def fresnel_dielectric(c: float, eta: float):
    """Unpolarised Fresnel reflectance of a dielectric of relative index ``eta`` >= 1, light from outside.

    ``F = 1/2 (g - c)^2 / (g + c)^2 (1 + ((c (g + c) - 1) / (c (g - c) + 1))^2)`` with
    ``g = sqrt(eta^2 - 1 + c^2)`` and ``c`` in (0, 1] the cosine of the angle of incidence
    (Cook & Torrance 1982, their Fresnel term; Walter et al. 2007, eq. 22): the mean of the s- and
    p-polarised reflectances.  ``F(1) = ((eta - 1) / (eta + 1))^2``, ``F -> 1`` at grazing incidence.
    """
    g = wp.sqrt(eta * eta - 1.0 + c * c)
    a = (g - c) / (g + c)
    b = (c * (g + c) - 1.0) / (c * (g - c) + 1.0)
    return 0.5 * a * a * (1.0 + b * b)


@wp.func
def plastic_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, m: float, eta: float):
    """The coating's specular factor ``pi D G F(h.v, eta) / (4 n.v)``.

    D and G are Cook-Torrance's (2.23-2.28, :func:`cook_torrance_spec` with Schlick's f0 = 1,
    where his Fresnel is exactly 1); F is :func:`fresnel_dielectric`; pi: see the section comment.
    """
    vh = wp.dot(v, wp.normalize(l + v))
    if vh <= 0.0:
        return 0.0
    return PI * cook_torrance_spec(n, l, v, m, 1.0) * fresnel_dielectric(vh, eta)


@wp.func
def plastic_diffuse(nl: float, nv: float, eta: float):
    """The coated base's diffuse factor ``max(n.l, 0) (1 - F(n.l, eta)) (1 - F(n.v, eta))`` (0 unless n.l, n.v > 0)."""
    if nl <= 0.0 or nv <= 0.0:
        return 0.0
    return nl * (1.0 - fresnel_dielectric(nl, eta)) * (1.0 - fresnel_dielectric(nv, eta))


# --------------------------------------------------------------------------- rough metal (conductor)
#
# Not in the seed.  A rough conductor: no light enters the metal, so there is no diffuse term, and the microfacet
# lobe carries the metal's colour.  The distribution is GGX / Trowbridge-Reitz with Smith's separable shadowing
# (Walter et al., "Microfacet models for refraction through rough surfaces", EGSR 2007: D and G1 from their
# eqs. 33-34, the product of the two G1 as their eq. 23; Heitz, "Understanding the masking-shadowing function in
# microfacet-based BRDFs", JCGT 2014): the distribution of Mitsuba 3's ``roughconductor`` (distribution "ggx") and
# of pbrt's default, whose long tails (Walter et al. found them closer to measured rough surfaces) the Beckmann
# lobe of Cook-Torrance (2.27) does not have.
#
#   s = pi D(n.h) G1(n.l) G1(n.v) F(h.v) / (4 n.v),   D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2),
#   G1(x) = 2 x / (x + sqrt(a^2 + (1 - a^2) x^2)),     F(c) = schlick(f0, c) / f0 = 1 + (1/f0 - 1)(1 - c)^5
#
# with a = ``roughness`` (GGX alpha).  The image model is I = E * kd * s: the per-pixel albedo kd (RGB) is the
# metal's reflectance at normal incidence (a coloured F0, e.g. copper's), so the model stays linear in the albedo
# (brdf_terms' contract: s sits in the diffuse slot and the specular slot is 0; ks is not used).  F is Schlick's
# rise toward grazing incidence relative to normal incidence, with the scalar ``f0`` (default 1: no rise; a
# coloured rise would need a per-channel f0 and is not modelled).  pi: the factor of gpps's radiometry (see the
# plastic section).  tests/test_conductor.py checks s against Mitsuba's roughconductor.


@wp.func
def ggx_q(n: wp.vec3, h: wp.vec3, a2: float):
    """``(n.h)^2 (a^2 - 1) + 1 = (1 - (n.h)^2) + (n.h)^2 a^2`` without cancellation near ``n.h = 1``."""
    nh = wp.dot(n, h)
    e = one_minus_dot(n, h)
    return e * (2.0 - e) + nh * nh * a2


@wp.func
def smith_g1_ggx(x: float, a2: float):
    """Smith's GGX shadowing of one direction at cosine ``x`` > 0: ``2 x / (x + sqrt(a^2 + (1 - a^2) x^2))``."""
    return 2.0 * x / (x + wp.sqrt(a2 + (1.0 - a2) * x * x))


@wp.func
def conductor_spec(n: wp.vec3, l: wp.vec3, v: wp.vec3, a: float, f0: float):
    """The rough conductor's lobe ``pi D G1(n.l) G1(n.v) F(h.v) / (4 n.v)`` (section comment above).

    Written as ``a^2 G1(n.l) F / (2 q^2 (n.v + sqrt(a^2 + (1 - a^2)(n.v)^2)))`` with ``q`` = :func:`ggx_q`
    (``G1(n.v) / n.v`` has no pole at grazing view).  0 unless ``n.l, n.v, n.h, h.v > 0``.
    """
    h = wp.normalize(l + v)
    nh = wp.dot(n, h)
    nl = wp.dot(n, l)
    nv = wp.dot(n, v)
    vh = wp.dot(v, h)
    if nh <= 0.0 or nl <= 0.0 or nv <= 0.0 or vh <= 0.0:
        return 0.0
    a2 = a * a
    q = ggx_q(n, h, a2)
    rv = wp.sqrt(a2 + (1.0 - a2) * nv * nv)
    return a2 * smith_g1_ggx(nl, a2) * (schlick(f0, vh) / f0) / (2.0 * q * q * (nv + rv))


@wp.func
def specular_term(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
    """The model's specular factor ``s(n, l, v)`` (without ``ks`` and light colour; the conductor's lobe is its
    albedo-weighted term, :func:`brdf_terms`, so its specular factor is 0)."""
    if mat.model == PHONG:
        return phong_spec(n, l, v, mat.shininess)
    if mat.model == BLINN_PHONG:
        return blinn_phong_spec(n, l, v, mat.shininess)
    if mat.model == COOK_TORRANCE:
        return cook_torrance_spec(n, l, v, mat.roughness, mat.f0)
    if mat.model == ASHIKHMIN_SHIRLEY:
        return ashikhmin_shirley_spec(n, l, v, mat.eta_u, mat.eta_v, mat.f0)
    if mat.model == PLASTIC:
        return plastic_spec(n, l, v, mat.roughness, ior_from_f0(mat.f0))
    return 0.0


@wp.func
def brdf_terms(mat: MaterialParams, n: wp.vec3, l: wp.vec3, v: wp.vec3):
    """``(max(n.l, 0), s)``: diffuse cosine (2.13) and specular factor; both 0 in attached shadow.

    Plastic: the diffuse factor is :func:`plastic_diffuse` (0 too when ``n.v <= 0``).  Conductor: the first
    (albedo-weighted) term is :func:`conductor_spec` and the second 0.
    """
    nl = wp.dot(n, l)
    if nl <= 0.0:
        return wp.vec2(0.0, 0.0)
    if mat.model == CONDUCTOR:
        return wp.vec2(conductor_spec(n, l, v, mat.roughness, mat.f0), 0.0)
    s = float(0.0)
    if mat.model != LAMBERTIAN and wp.dot(n, v) > 0.0:
        s = specular_term(mat, n, l, v)
    if mat.model == PLASTIC:
        return wp.vec2(plastic_diffuse(nl, wp.dot(n, v), ior_from_f0(mat.f0)), s)
    return wp.vec2(nl, s)


@wp.func
def shade(mat: MaterialParams, albedo: wp.vec3, n: wp.vec3, l: wp.vec3, v: wp.vec3, radiance: wp.vec3):
    """RGB intensity ``E * (kd * max(n.l, 0) + ks * s)`` for one light."""
    t = brdf_terms(mat, n, l, v)
    return wp.cw_mul(radiance, albedo * t[0] + wp.vec3(mat.ks * t[1]))
