"""How far each reflectance model's own best fit moves the normals from the truth on a capture (session 21, issue 25).

For each model, written here in numpy from its equations (independent of the kernels): the global material that best
explains the images at the ground-truth normals (a grid over the lobe parameter and ks; the per-pixel albedo by
linear least squares), then on every 7th mask pixel the normal nearest the truth that minimises the model's residual
(Nelder-Mead in a chart around the true normal, the albedo eliminated).  The mean angle of those normals to the truth
is the model's bias on the capture: what no solver or start can remove.  Models: Blinn-Phong (the default),
``ggx-ct`` (a diffuse term and a grey GGX lobe), ``conductor+diffuse`` (per-pixel colours of both), ``conductor``
(gpps's rough conductor: the per-pixel colour weighing a GGX lobe, no diffuse term).  Directional captures only.
Usage: ``python perf/model_ceiling.py "GLOB" [OUT.jsonl]`` (captures under $GPPS_CACHE_DIR/mitsuba_captures).
"""
import json
import glob
import os
import sys
import numpy as np
from scipy.optimize import minimize
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from gpps.io import read_capture
from gpps.camera import camera_from_K

PI = np.pi


def dot(a, b):
    return np.sum(a * b, -1)


def nrm(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def beckmann(nh, m):
    c2 = nh * nh
    t2 = (1 - c2) / np.maximum(c2, 1e-12)
    return np.exp(-t2 / m**2) / (PI * m**2 * c2 * c2)


def ggx(nh, a):
    a2 = a * a
    d = nh * nh * (a2 - 1) + 1
    return a2 / (PI * d * d)


def smith_g1(x, a):
    x = np.clip(x, 1e-6, 1)
    return 2 * x / (x + np.sqrt(a * a + (1 - a * a) * x * x))


def fres_d(c, eta):
    c = np.clip(c, 1e-6, 1)
    g = np.sqrt(eta * eta - 1 + c * c)
    A = (g - c) / (g + c)
    B = (c * (g + c) - 1) / (c * (g - c) + 1)
    return 0.5 * A * A * (1 + B * B)


def terms(model, p, n, l, v):
    """(cos-term, spec-term) each (N, P): I = E (kd cos + ks spec); conductor: I = E a spec (cos = 0)."""
    h = nrm(l + v)
    nh, nl, nv, vh = dot(n, h), dot(n, l), dot(n, v), dot(v, h)
    lit = (nl > 0) & (nv > 0)
    nlc = np.clip(nl, 0, None)
    if model == "blinn-phong":
        s = np.clip(nh, 0, None) ** p
        return nlc, np.where(lit, s, 0)
    if model == "ct":
        G = np.minimum(1, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
        F = 0.5 + 0.5 * (1 - vh) ** 5
        s = beckmann(nh, p) * G * F / (4 * np.clip(nv, 1e-6, None))
        return nlc, np.where(lit & (nh > 0), s, 0)
    if model in ("plastic", "plastic-ggx"):
        eta = 1.5
        if model == "plastic":
            G = np.minimum(1, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
            D = beckmann(nh, p)
        else:
            G = smith_g1(nl, p) * smith_g1(nv, p)
            D = ggx(nh, p)
        s = PI * D * G * fres_d(vh, eta) / (4 * np.clip(nv, 1e-6, None))
        d = nlc * (1 - fres_d(nl, eta)) * (1 - fres_d(np.clip(nv, 1e-6, 1), eta))
        return np.where(lit, d, 0), np.where(lit & (nh > 0), s, 0)
    if model == "ggx-ct":
        G = smith_g1(nl, p) * smith_g1(nv, p)
        s = PI * ggx(nh, p) * G / (4 * np.clip(nv, 1e-6, None))
        return nlc, np.where(lit & (nh > 0), s, 0)
    if model == "conductor+diffuse":
        G = smith_g1(nl, p) * smith_g1(nv, p)
        s = PI * ggx(nh, p) * G / (4 * np.clip(nv, 1e-6, None))
        return np.where(lit, nlc, 0), np.where(lit & (nh > 0), s, 0)
    if model in ("conductor", "conductor-beckmann"):
        if model == "conductor":
            G = smith_g1(nl, p) * smith_g1(nv, p)
            D = ggx(nh, p)
        else:
            G = np.minimum(1, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
            D = beckmann(nh, p)
        s = PI * D * G / (4 * np.clip(nv, 1e-6, None))
        return np.zeros_like(nl), np.where(lit & (nh > 0), s, 0)
    raise ValueError(model)


def fit_linear(model, I, c, s, ks):
    """Per-pixel, per-channel least squares: kd (and for conductor the colour a) given ks; returns residual (N,P,3)."""
    if model == "conductor+diffuse":
        A = np.stack([c, s], -1)  # N P 2
        M = np.einsum("npi,npj->pij", A, A) + 1e-9 * np.eye(2)
        b = np.einsum("npi,npc->pic", A, I)
        x = np.linalg.solve(M, b)  # P 2 3
        x = np.clip(x, 0, None)
        return I - np.einsum("npi,pic->npc", A, x)
    if model.startswith("conductor"):
        a = np.einsum("np,npc->pc", s, I) / np.maximum(np.einsum("np,np->p", s, s), 1e-12)[:, None]
        return I - s[..., None] * a[None]
    r = I - ks * s[..., None]
    kd = np.einsum("np,npc->pc", c, r) / np.maximum(np.einsum("np,np->p", c, c), 1e-12)[:, None]
    kd = np.clip(kd, 0, None)
    return r - c[..., None] * kd[None]


def main(pattern, out=None):
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", ".cache"), "mitsuba_captures")
    for cap in sorted(glob.glob(os.path.join(root, pattern))):
        ds = read_capture(cap).dataset
        m = ds.mask
        I = ds.images[:, m].astype(np.float64)  # N P 3
        cam = camera_from_K(ds.K)
        _, d = cam.rays(m.shape)
        v = -d[m]
        L = ds.light_directions / np.linalg.norm(ds.light_directions, axis=1, keepdims=True)
        l = np.broadcast_to(L[:, None, :], (len(L), v.shape[0], 3))
        # (read_capture divides each image by its light intensity: E = 1 below)
        ngt = ds.normal_gt[m]
        vv = np.broadcast_to(v[None], l.shape)
        # shadowed/dark observations: drop where the observation is ~0 (cast shadow) for fairness to all models
        valid = I.sum(-1) > 1e-3
        print(os.path.basename(cap)[:60], "pixels", m.sum(), "valid share", valid.mean().round(3))
        for model, grid in [("blinn-phong", np.geomspace(2, 500, 25)), ("ggx-ct", np.geomspace(0.03, 0.8, 25)),
                            ("conductor+diffuse", np.geomspace(0.03, 0.8, 25)),
                            ("conductor", np.geomspace(0.03, 0.8, 25))]:
            best = None
            ngtb = np.broadcast_to(ngt[None], l.shape)
            for p in grid:
                c, s = terms(model, p, ngtb, l, vv)
                kss = [0.0] if model.startswith("conductor") else np.geomspace(0.02, 3, 15)
                for ks in kss:
                    r = fit_linear(model, I, c * valid, s * valid, ks) * valid[..., None]
                    e = float((r**2).sum())
                    if best is None or e < best[0]:
                        best = (e, p, ks)
            e, p, ks = best
            rel = np.sqrt(e / (I**2 * valid[..., None]).sum())
            # per-pixel normal refit from the truth (2 params: a chart around n_gt)
            sub = np.arange(0, m.sum(), 7)
            errs = []
            t1 = nrm(np.cross(ngt[sub], [0, 0, 1.0]) + 1e-9)
            t2 = np.cross(ngt[sub], t1)
            for q, k in enumerate(sub):
                def f(x):
                    n = nrm(ngt[k] + x[0] * t1[q] + x[1] * t2[q])[None, None]
                    c, s = terms(model, p, np.broadcast_to(n, (len(L), 1, 3)), L[:, None], v[k][None, None].repeat(len(L), 0))
                    vk = valid[:, k:k + 1]
                    rr = fit_linear(model, I[:, k:k + 1], c * vk, s * vk, ks) * vk[..., None]
                    return float((rr**2).sum())
                x = minimize(f, np.zeros(2), method="Nelder-Mead", options=dict(xatol=1e-4, fatol=1e-12)).x
                n = nrm(ngt[k] + x[0] * t1[q] + x[1] * t2[q])
                errs.append(np.degrees(np.arccos(np.clip(dot(n, ngt[k]), -1, 1))))
            print(f"  {model:20s} p={p:.3g} ks={ks:.3g} rel.resid={rel:.4f} bias MAEN={np.mean(errs):.2f} median={np.median(errs):.2f}")
            if out:
                with open(out, "a") as f:
                    f.write(json.dumps(dict(capture=os.path.basename(cap), model=model, lobe=float(p), ks=float(ks),
                                            relative_residual=rel, bias_maen=float(np.mean(errs)),
                                            bias_median=float(np.median(errs)))) + "\n")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else None)
