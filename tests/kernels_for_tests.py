"""Test-only Warp kernels (they must live in a real file) and an independent
float64 numpy implementation of the reflectance models used as the reference."""

from __future__ import annotations

import numpy as np
import warp as wp

from gpps.kernels.brdf import LightParams, MaterialParams
from gpps.kernels.jacobians import chart_normal, chart_normal_jacobian, diffuse_value_grad_of, specular_value_grad
from gpps.kernels.solve import Pixel, evaluate


@wp.kernel
def terms_grad_kernel(
    n0: wp.array(dtype=wp.vec3),
    t1: wp.array(dtype=wp.vec3),
    t2: wp.array(dtype=wp.vec3),
    x: wp.array(dtype=wp.vec2),
    l: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    mat: MaterialParams,
    out: wp.array2d(dtype=wp.float32),
):
    """out[t] = (d, s, d d/dx0, d d/dx1, d s/dx0, d s/dx1) at n(x); d: the diffuse factor (nl; plastic's)."""
    t = wp.tid()
    n = chart_normal(n0[t], t1[t], t2[t], x[t])
    dn = chart_normal_jacobian(n0[t], t1[t], t2[t], x[t])
    dn0 = wp.vec3(dn[0, 0], dn[1, 0], dn[2, 0])
    dn1 = wp.vec3(dn[0, 1], dn[1, 1], dn[2, 1])
    dg = diffuse_value_grad_of(mat, n, l[t], v[t])
    sg = specular_value_grad(mat, n, l[t], v[t])
    gd = wp.vec3(dg[1], dg[2], dg[3])
    gs = wp.vec3(sg[1], sg[2], sg[3])
    out[t, 0] = dg[0]
    out[t, 1] = sg[0]
    out[t, 2] = wp.dot(gd, dn0)
    out[t, 3] = wp.dot(gd, dn1)
    out[t, 4] = wp.dot(gs, dn0)
    out[t, 5] = wp.dot(gs, dn1)


@wp.kernel
def evaluate_kernel(
    n0: wp.vec3,
    t1: wp.vec3,
    t2: wp.vec3,
    x: wp.vec2,
    images: wp.array3d(dtype=wp.vec3),
    weights: wp.array3d(dtype=wp.float32),
    lights: LightParams,
    mat: MaterialParams,
    v: wp.vec3,
    grey_albedo: int,
    out: wp.array(dtype=wp.float32),
):
    """out = (cost, jtr0, jtr1, jtj00, jtj01, jtj11, kd0, kd1, kd2) for the pixel (0, 0)."""
    px = Pixel()
    px.i = 0
    px.j = 0
    px.p = wp.vec3(0.0, 0.0, -10.0)
    px.v = v
    px.fix_kd = 0
    px.kd = wp.vec3(0.0)
    px.grey_albedo = grey_albedo
    ev = evaluate(n0, t1, t2, x, images, weights, px, lights, mat)
    out[0] = ev.cost
    out[1] = ev.jtr[0]
    out[2] = ev.jtr[1]
    out[3] = ev.jtj[0, 0]
    out[4] = ev.jtj[0, 1]
    out[5] = ev.jtj[1, 1]
    out[6] = ev.kd[0]
    out[7] = ev.kd[1]
    out[8] = ev.kd[2]


# --------------------------------------------------------------------------- numpy reference (float64)


def np_normalize(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def np_chart(n0, t1, t2, x):
    return np_normalize(n0 + x[..., :1] * t1 + x[..., 1:2] * t2)


def np_tangent_t1(n):
    a = np.where(np.abs(n[..., :1]) > 0.9, [0.0, 1.0, 0.0], [1.0, 0.0, 0.0])
    return np_normalize(a - np.sum(a * n, -1, keepdims=True) * n)


def _schlick(f0, c):
    return f0 + (1 - f0) * (1 - c) ** 5


def np_fresnel_dielectric(c, eta):
    """Unpolarised dielectric Fresnel from Snell's law and the s / p amplitudes (not the kernels' closed form)."""
    ct = np.sqrt(1.0 - (1.0 - c**2) / eta**2)
    rs = (c - eta * ct) / (c + eta * ct)
    rp = (eta * c - ct) / (eta * c + ct)
    return 0.5 * (rs**2 + rp**2)


def np_ior(f0):
    return (1 + np.sqrt(f0)) / (1 - np.sqrt(f0))


def np_specular(brdf, n, l, v, p):
    """Specular factor s(n, l, v) of each model, written from the seed's equations (float64).

    ``p`` is a dict with shininess, roughness, f0, eta_u, eta_v.  Gating as in
    gpps.kernels.brdf.brdf_terms (0 when n.l <= 0 or n.v <= 0).
    """
    dot = lambda a, b: np.sum(a * b, -1)  # noqa: E731
    nl, nv = dot(n, l), dot(n, v)
    h = np_normalize(l + v)
    nh, vh = dot(n, h), dot(v, h)
    ok = (nl > 0) & (nv > 0)
    if brdf in ("lambertian", "conductor"):  # (the conductor's lobe is its albedo-weighted term, np_diffuse)
        s = np.zeros_like(nl)
    elif brdf == "phong":
        r = 2 * nl[..., None] * n - l
        c = dot(r, v)
        s = np.where(c > 0, np.maximum(c, 0) ** p["shininess"], 0.0)
    elif brdf == "blinn-phong":
        s = np.where(nh > 0, np.maximum(nh, 0) ** p["shininess"], 0.0)
    elif brdf == "cook-torrance":
        m = p["roughness"]
        c2 = nh**2
        d = np.exp(-(1 - c2) / c2 / m**2) / (np.pi * m**2 * c2**2)
        g = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
        s = np.where((nh > 0) & (vh > 0), d * g * _schlick(p["f0"], vh) / (4 * nv), 0.0)
    elif brdf == "ashikhmin-shirley":
        eu, ev = p["eta_u"], p["eta_v"]
        tu = np_tangent_t1(n)
        tv = np.cross(n, tu)
        hu, hv = dot(h, tu), dot(h, tv)
        zeta = (eu * hu**2 + ev * hv**2) / (hu**2 + hv**2)
        norm = np.sqrt((eu + 1) * (ev + 1)) / (8 * np.pi)
        s = np.where((nh > 0) & (vh > 0), norm * np.maximum(nh, 1e-300) ** zeta * _schlick(p["f0"], vh) * nl / (vh * np.maximum(nl, nv)), 0.0)
    elif brdf == "plastic":
        m = p["roughness"]
        c2 = nh**2
        d = np.exp(-(1 - c2) / c2 / m**2) / (np.pi * m**2 * c2**2)
        g = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
        f = np_fresnel_dielectric(np.clip(vh, 0, 1), np_ior(p["f0"]))
        s = np.where((nh > 0) & (vh > 0), np.pi * d * g * f / (4 * nv), 0.0)
    else:
        raise ValueError(brdf)
    return np.where(ok, s, 0.0)


def np_conductor(n, l, v, p):
    """The conductor's GGX lobe pi D G1(n.l) G1(n.v) F / (4 n.v) (Walter et al. 2007, eqs. 33-34; F Schlick's / f0)."""
    dot = lambda a, b: np.sum(a * b, -1)  # noqa: E731
    a2, f0 = p["roughness"] ** 2, p["f0"]
    h = np_normalize(l + v)
    nl, nv, nh, vh = dot(n, l), dot(n, v), dot(n, h), dot(v, h)
    c2 = np.clip(nh, 1e-12, 1.0) ** 2
    D = a2 / (np.pi * c2**2 * (a2 + (1 - c2) / c2) ** 2)
    g1 = lambda c: 2.0 / (1.0 + np.sqrt(1.0 + a2 * (1 - c**2) / c**2))  # noqa: E731
    cl, cv = np.clip(nl, 1e-12, 1.0), np.clip(nv, 1e-12, 1.0)
    F = (f0 + (1 - f0) * (1 - vh) ** 5) / f0
    ok = (nl > 0) & (nv > 0) & (nh > 0) & (vh > 0)
    return np.where(ok, np.pi * D * g1(cl) * g1(cv) * F / (4 * cv), 0.0)


def np_diffuse(brdf, n, l, v, p):
    """The diffuse factor: max(n.l, 0); plastic: (n.l)(1 - F(n.l))(1 - F(n.v)) where n.l, n.v > 0; the conductor:
    its lobe (:func:`np_conductor`)."""
    nl, nv = np.sum(n * l, -1), np.sum(n * v, -1)
    if brdf == "conductor":
        return np_conductor(n, l, v, p)
    if brdf != "plastic":
        return np.maximum(nl, 0.0)
    eta = np_ior(p["f0"])
    ok = (nl > 0) & (nv > 0)
    cl, cv = np.clip(nl, 1e-12, 1.0), np.clip(nv, 1e-12, 1.0)
    return np.where(ok, cl * (1 - np_fresnel_dielectric(cl, eta)) * (1 - np_fresnel_dielectric(cv, eta)), 0.0)


def np_terms(brdf, n, l, v, p):
    nl = np.sum(n * l, -1)
    return np_diffuse(brdf, n, l, v, p), np.where(nl > 0, np_specular(brdf, n, l, v, p), 0.0)


def np_reduced_cost(brdf, n, lights_dir, radiance, obs, weights, v, p, ks, grey=False):
    """Variable-projection cost 1/2 sum w (y - kd a)^2 with kd eliminated per channel (float64).

    lights_dir (N, 3), radiance (N, 3), obs (N, 3), weights (N,).
    """
    nl, s = np_terms(brdf, n[None], lights_dir, v[None], p)
    a = radiance * nl[:, None]
    y = obs - radiance * ks * s[:, None]
    w = weights[:, None]
    saa = np.sum(w * a * a, 0)
    say = np.sum(w * a * y, 0)
    if grey:
        saa = np.full(3, saa.sum())
        say = np.full(3, say.sum())
    kd = np.where(saa > 1e-20, np.maximum(say / np.where(saa > 0, saa, 1), 0.0), 0.0)
    r = y - kd * a
    return 0.5 * np.sum(w * r * r), kd, (np.sqrt(w) * r).ravel()


@wp.kernel
def valley_residual_kernel(
    mats: wp.array(dtype=MaterialParams),
    weights: wp.array(dtype=wp.float32),
    residual: wp.array2d(dtype=wp.float32),
):
    """A fake material scorer's residuals (tests/test_material_search.py): ``residual[k, i] = w_i sqrt(f)`` with
    ``f`` a curved valley in (log ks, log roughness) across the axes, minimum 0.01 at (log 0.4, log 0.2)."""
    k, i = wp.tid()
    a = wp.log(mats[k].ks) - wp.log(0.4)
    b = wp.log(mats[k].roughness) - wp.log(0.2)
    u = b - 0.3 * a - 0.5 * a * a
    f = a * a + 8.0 * u * u + 0.01
    residual[k, i] = weights[i] * wp.sqrt(f)


def make_scale_kernel(factor: float):
    """A kernel ``out[i] = factor * a[i]`` in a Warp module of its own (a new module each call: a compile that no
    cache holds for a new ``factor``; tests/test_prefetch.py)."""

    @wp.kernel(module="unique")
    def scale_kernel(a: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
        i = wp.tid()
        out[i] = wp.static(factor) * a[i]

    return scale_kernel
