"""Independent float64 numpy implementations of the seed's image model (for tests only).

Written from the equations, not from the kernels: each function takes unit
vectors n, l, v of shape (..., 3) and returns the diffuse cosine and the
specular factor s with I = E * (kd * cos + ks * s).
"""

import numpy as np


def dot(a, b):
    return np.sum(a * b, axis=-1)


def normalize(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def phong(n, l, v, shininess):  # (2.19)-(2.20)
    r = 2 * dot(l, n)[..., None] * n - l
    return np.maximum(dot(r, v), 0.0) ** shininess


def blinn_phong(n, l, v, shininess):  # (2.21)
    h = normalize(l + v)
    return np.maximum(dot(n, h), 0.0) ** shininess


def cook_torrance(n, l, v, m, f0):  # (2.22)-(2.29), the 1/(n.l) cancelled by the cosine
    h = normalize(l + v)
    nh, nv, nl, vh = dot(n, h), dot(n, v), dot(n, l), dot(v, h)
    alpha = np.arccos(np.clip(nh, -1, 1))
    D = np.exp(-np.tan(alpha) ** 2 / m**2) / (np.pi * m**2 * np.cos(alpha) ** 4)
    T = 2 * nh * nv / vh
    R = 2 * nh * nl / vh
    G = np.minimum(1.0, np.minimum(T, R))
    F = f0 + (1 - f0) * (1 - vh) ** 5
    return G * D * F / (4 * nv)


def ashikhmin_shirley(n, l, v, eu, ev, f0):  # (5.1)-(5.2) with A&S 2000's max(n.l, n.v) and the cosine n.l
    h = normalize(l + v)
    nh, nv, nl, vh = dot(n, h), dot(n, v), dot(n, l), dot(v, h)
    ex = np.broadcast_to([1.0, 0.0, 0.0], n.shape)
    ey = np.broadcast_to([0.0, 1.0, 0.0], n.shape)
    a = np.where((np.abs(n[..., 0]) > 0.9)[..., None], ey, ex)
    u = normalize(a - dot(a, n)[..., None] * n)
    w = np.cross(n, u)
    hu, hw = dot(h, u), dot(h, w)
    zeta = (eu * hu**2 + ev * hw**2) / (1 - nh**2)
    F = f0 + (1 - f0) * (1 - vh) ** 5
    return np.sqrt((eu + 1) * (ev + 1)) / (8 * np.pi) * nh**zeta / (vh * np.maximum(nl, nv)) * F * nl


def fresnel_dielectric(c, eta):
    """Unpolarised Fresnel reflectance from the s- and p-polarised amplitudes (Snell's law; light from outside, index eta)."""
    c = np.asarray(c, np.float64)
    sin_t2 = (1.0 - c**2) / eta**2
    ct = np.sqrt(1.0 - sin_t2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs**2 + rp**2)


def ior(f0):
    return (1 + np.sqrt(f0)) / (1 - np.sqrt(f0))


def plastic(n, l, v, m, f0):
    """Coating lobe: pi x Beckmann D x V-cavity G x exact dielectric F(h.v) / (4 n.v), and the diffuse factor
    (n.l)(1 - F(n.l))(1 - F(n.v)) (gpps.kernels.brdf's plastic)."""
    eta = ior(f0)
    h = normalize(l + v)
    vh = dot(v, h)
    s = np.pi * cook_torrance(n, l, v, m, 1.0) * fresnel_dielectric(vh, eta)  # Schlick with f0 = 1 is 1
    nl, nv = np.clip(dot(n, l), 1e-12, None), np.clip(dot(n, v), 1e-12, None)
    d = nl * (1 - fresnel_dielectric(nl, eta)) * (1 - fresnel_dielectric(nv, eta))
    return d, s


def conductor(n, l, v, a, f0):
    """Rough metal (not the seed's): pi x GGX D x Smith's separable G1(n.l) G1(n.v) x Schlick's F(h.v) / f0 over 4 n.v,
    from Walter et al. 2007 (eqs. 33-34) as written there; the albedo weighs it (no diffuse term)."""
    h = normalize(l + v)
    nh, nv, nl, vh = dot(n, h), dot(n, v), dot(n, l), dot(v, h)
    theta = np.arccos(np.clip(nh, -1, 1))
    D = a**2 / (np.pi * np.cos(theta) ** 4 * (a**2 + np.tan(theta) ** 2) ** 2)  # Walter's (33)

    def g1(c):  # Walter's (34): 2 / (1 + sqrt(1 + a^2 tan^2))
        c = np.clip(c, 1e-12, 1.0)
        return 2.0 / (1.0 + np.sqrt(1.0 + a**2 * (1 - c**2) / c**2))

    F = (f0 + (1 - f0) * (1 - vh) ** 5) / f0
    ok = (nh > 0) & (vh > 0) & (nl > 0) & (nv > 0)
    return np.where(ok, np.pi * D * g1(nl) * g1(nv) * F / (4 * np.clip(nv, 1e-12, None)), 0.0)


def terms(material, n, l, v):
    """(cos, s) for a gpps.Material, with attached shadows (plastic: its diffuse factor for cos; conductor: its lobe
    for cos and 0 for s)."""
    nl = dot(n, l)
    b = material.brdf
    if b == "conductor":  # the lobe is the albedo-weighted term
        lit = (nl > 0) & (dot(n, v) > 0)
        return np.where(lit, conductor(n, l, v, material.roughness, material.f0), 0.0), np.zeros_like(nl)
    if b == "plastic":
        d, s = plastic(n, l, v, material.roughness, material.f0)
        lit = (nl > 0) & (dot(n, v) > 0)
        return np.where(lit, d, 0.0), np.where(lit, s, 0.0)
    if b == "lambertian":
        s = np.zeros_like(nl)
    elif b == "phong":
        s = phong(n, l, v, material.shininess)
    elif b == "blinn-phong":
        s = blinn_phong(n, l, v, material.shininess)
    elif b == "cook-torrance":
        s = cook_torrance(n, l, v, material.roughness, material.f0)
    else:
        s = ashikhmin_shirley(n, l, v, material.eta_u, material.eta_v, material.f0)
    lit = nl > 0
    return np.where(lit, nl, 0.0), np.where(lit & (dot(n, v) > 0), s, 0.0)
