"""Perspective photometric stereo in the log-depth parameterisation (seed ch. 3).

Conventions (see :mod:`gpps.camera`): pixel ``(u, v) = (column, row)``, depth
``d = -z > 0``, the point seen at a pixel is ``P = d r`` with the ray
``r(u, v) = ((u - cx)/fx, -(v - cy)/fy, -1)``.  With ``nu = ln d`` (the seed's
``nu = ln z``, Tankus et al.) the surface tangents are
``P_u = d (nu_u r + r_u)``, ``P_v = d (nu_v r + r_v)`` with ``r_u = (1/fx, 0, 0)``,
``r_v = (0, -1/fy, 0)``, and the (unnormalised) normal toward the camera is::

    N(nu_u, nu_v) = (nu_u r + r_u) x -(nu_v r + r_v)
                  = -nu_u (r x r_v) - nu_v (r_u x r) - r_u x r_v        (2.34 in this frame)

affine in the log-depth gradient, which is what makes the Lambertian
perspective problem linear (3.4-3.11).

* PPN (3.2-3.3): normals -> perspective gradient, ``nu_u = -(n.r_u)/(n.r)``,
  ``nu_v = -(n.r_v)/(n.r)`` (the seed's ``p = -n1/d``, ``q = -n2/d`` with
  ``d = x n1 + y n2 + f n3`` = ``n . OP``): :func:`normals_to_gradient`.
* PPS: Lambertian closed form (3.5-3.12): :func:`lambertian_closed_form`;
  perspective Blinn-Phong (3.15-3.19) solved for ``(nu_u, nu_v, kd)`` by
  Levenberg-Marquardt, with the direct residual or the partial linearisation
  by image ratios (3.22-3.34): :func:`pps_blinn_phong`.
* The lighting sensitivity indicator (3.13): :func:`sensitivity_indicator`.

These are numpy (float64), vectorised over pixels: correct and tested, not fast.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from gpps._check import as_array, as_images, as_mask
from gpps.camera import Orthographic, Perspective
from gpps.lights import DirectionalLights

__all__ = [
    "normals_to_gradient",
    "gradient_to_normals",
    "affine_normal",
    "lambertian_closed_form",
    "pps_blinn_phong",
    "sensitivity_indicator",
]


def _rays(camera, shape):
    h, w = shape
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    if isinstance(camera, Perspective):
        cx, cy = camera.principal_point()
        r = np.stack([(jj - cx) / camera.fx, -(ii - cy) / camera.fy, -np.ones_like(jj)], -1)
        ru = np.array([1.0 / camera.fx, 0.0, 0.0])
        rv = np.array([0.0, -1.0 / camera.fy, 0.0])
        return r, ru, rv
    raise TypeError(f"camera: expected gpps.camera.Perspective, got {type(camera).__name__}")


def normals_to_gradient(normals, mask, camera) -> np.ndarray:
    """PPN (3.2-3.3): the gradient field an integrator needs, from unit normals.

    Args:
        normals: (H, W, 3) normals in the gpps frame (toward the camera).
        mask: (H, W) bool.
        camera: :class:`Perspective` -> gradient of ``ln d`` (log depth);
            :class:`Orthographic` -> gradient of the depth ``d`` itself.

    Returns:
        (H, W, 2) float32 ``(d/du, d/dv)`` per pixel (u = column to the right,
        v = row downward), 0 outside the mask and where the normal is parallel
        to the image plane (``n . r = 0``).

        Perspective: ``nu_u = -(n_x/fx) / (n.r)``, ``nu_v = (n_y/fy) / (n.r)``.
        Orthographic (pixel size s): ``d_u = s n_x / n_z``, ``d_v = -s n_y / n_z``.
    """
    m = as_mask("mask", mask)
    h, w = m.shape
    n = as_array("normals", normals, shape=(h, w, 3), dtype=np.float64)
    out = np.zeros((h, w, 2))
    if isinstance(camera, Orthographic):
        s = camera.pixel_size
        nz = n[..., 2]
        ok = m & (np.abs(nz) > 1e-8)
        safe = np.where(ok, nz, 1.0)
        out[..., 0] = np.where(ok, s * n[..., 0] / safe, 0.0)
        out[..., 1] = np.where(ok, -s * n[..., 1] / safe, 0.0)
        return out.astype(np.float32)
    r, ru, rv = _rays(camera, (h, w))
    nr = np.sum(n * r, -1)
    ok = m & (np.abs(nr) > 1e-12)
    safe = np.where(ok, nr, 1.0)
    out[..., 0] = np.where(ok, -(n @ ru) / safe, 0.0)
    out[..., 1] = np.where(ok, -(n @ rv) / safe, 0.0)
    return out.astype(np.float32)


def affine_normal(camera, shape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a, b, c)``, each (H, W, 3): the unnormalised normal ``N = u_x a + u_y b + c`` of a gradient
    ``(u_x, u_y)`` per pixel (x = column to the right, y = row downward) of the integrator's unknown: the log-depth
    under :class:`Perspective` (PPN, 3.2-3.3), the depth under :class:`Orthographic` (pixel size ``s``:
    ``(u_x / s, -u_y / s, 1)``).  :func:`gradient_to_normals` normalises it; the two-light equations
    (:mod:`gpps.host.two_light`) are linear in it."""
    h, w = shape
    if isinstance(camera, Orthographic):
        s = float(camera.pixel_size)
        return (np.broadcast_to(np.array([1.0 / s, 0.0, 0.0]), (h, w, 3)),
                np.broadcast_to(np.array([0.0, -1.0 / s, 0.0]), (h, w, 3)),
                np.broadcast_to(np.array([0.0, 0.0, 1.0]), (h, w, 3)))
    if not isinstance(camera, Perspective):
        raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
    r, ru, rv = _rays(camera, shape)
    a = -np.cross(r, rv)
    b = -np.cross(np.broadcast_to(ru, r.shape), r)
    c = np.broadcast_to(-np.cross(ru, rv), r.shape)
    return a, b, c


def gradient_to_normals(gradient, mask, camera) -> np.ndarray:
    """Inverse of :func:`normals_to_gradient`: unit normals (H, W, 3) float32, 0 outside the mask."""
    m = as_mask("mask", mask)
    h, w = m.shape
    g = as_array("gradient", gradient, shape=(h, w, 2), dtype=np.float64)
    a, b, c = affine_normal(camera, (h, w))
    N = g[..., :1] * a + g[..., 1:2] * b + c
    N /= np.linalg.norm(N, axis=-1, keepdims=True)
    return np.where(m[..., None], N, 0.0).astype(np.float32)


def _grey_images(images, n=None):
    x = as_images("images", images, dtype=np.float64)
    if x.ndim == 4:
        x = x.mean(-1)
    if x.ndim != 3:
        raise ValueError(f"images: expected shape (N, H, W) or (N, H, W, 3), got {x.shape}")
    if n is not None and x.shape[0] != n:
        raise ValueError(f"lights: expected {x.shape[0]} lights (one per image), got {n}")
    return x


def _check_lights(lights):
    if not isinstance(lights, DirectionalLights):
        raise TypeError(f"lights: expected DirectionalLights (PPS assumes distant lights), got {type(lights).__name__}")
    if len(lights) < 3:
        raise ValueError(f"lights: expected at least 3 lights, got {len(lights)}")
    s = np.linalg.svd(lights.directions, compute_uv=False)
    if s[-1] / s[0] < 1e-3:
        raise ValueError("lights: the light directions are coplanar or collinear; PPS needs 3 non-coplanar directions")


def lambertian_closed_form(images, mask, lights, camera) -> dict:
    """Perspective Lambertian PS in closed form (Tankus et al.; 3.4-3.12).

    Dividing the irradiance equations by the first one removes kd; what is left
    is linear in ``X = (nu_u, nu_v)``: ``(I_1 l_k - I_k l_1) . N(X) = 0`` for
    k = 2..N (3.5-3.10), solved per pixel (3.11; least squares for N > 3), and
    kd from the first image (3.12).  Images are divided by the grey light
    intensities first.

    Args:
        images: (N, H, W) or (N, H, W, 3).
        mask: (H, W).
        lights: :class:`DirectionalLights` (N >= 3, non-coplanar).
        camera: :class:`Perspective`.

    Returns:
        dict: ``gradient`` (H, W, 2) log-depth gradient, ``normals`` (H, W, 3),
        ``albedo`` (H, W) grey kd, ``det`` (H, W) determinant of ``M^T M`` (the
        non-singularity of 3.13; tiny values flag lighting-sensitive pixels).
    """
    _check_lights(lights)
    I = _grey_images(images, len(lights))
    n_img, h, w = I.shape
    m = as_mask("mask", mask, (h, w))
    I = I / np.asarray(lights.intensities).mean(1)[:, None, None]
    a, b, c = affine_normal(camera, (h, w))
    L = np.asarray(lights.directions)
    # rows k: (I_1 l_k - I_k l_1) . (nu_u a + nu_v b + c) = 0
    D = I[0][None, ..., None] * L[1:, None, None, :] - I[1:, ..., None] * L[0][None, None, None, :]  # (N-1, H, W, 3)
    Mu = np.sum(D * a[None], -1)
    Mv = np.sum(D * b[None], -1)
    Hc = -np.sum(D * c[None], -1)
    A11 = np.sum(Mu * Mu, 0)
    A12 = np.sum(Mu * Mv, 0)
    A22 = np.sum(Mv * Mv, 0)
    b1 = np.sum(Mu * Hc, 0)
    b2 = np.sum(Mv * Hc, 0)
    det = A11 * A22 - A12 * A12
    ok = m & (np.abs(det) > 1e-30)
    sd = np.where(ok, det, 1.0)
    g = np.zeros((h, w, 2))
    g[..., 0] = np.where(ok, (A22 * b1 - A12 * b2) / sd, 0.0)
    g[..., 1] = np.where(ok, (A11 * b2 - A12 * b1) / sd, 0.0)
    N = g[..., :1] * a + g[..., 1:2] * b + c
    n = N / np.linalg.norm(N, axis=-1, keepdims=True)
    ln = n @ L[0]
    kd = np.where(ok & (ln > 1e-6), I[0] / np.where(ln > 1e-6, ln, 1.0), 0.0)  # (3.12)
    return {
        "gradient": np.where(ok[..., None], g, 0.0).astype(np.float32),
        "normals": np.where(ok[..., None], n, 0.0).astype(np.float32),
        "albedo": kd.astype(np.float32),
        "det": np.where(m, det, 0.0),
    }


def _bp_model(X, a, b, c, L, v, ks, shin):
    """Perspective Blinn-Phong (3.15): ``kd max(n.l, 0) + ks (n.h)^n`` with n = N(X)/|N(X)|; X (P, 3) = (nu_u, nu_v, kd)."""
    N = X[:, :1] * a + X[:, 1:2] * b + c
    n = N / np.linalg.norm(N, axis=-1, keepdims=True)
    nl = n @ L.T  # (P, K)
    hvec = L[None] + v[:, None, :]
    hvec /= np.linalg.norm(hvec, axis=-1, keepdims=True)
    nh = np.einsum("pc,pkc->pk", n, hvec)
    nv = np.sum(n * v, -1, keepdims=True)
    lit = (nl > 0) & (nv > 0)
    spec = np.where(lit & (nh > 0), np.maximum(nh, 0.0) ** shin, 0.0)
    return X[:, 2:3] * np.maximum(nl, 0.0) + ks * spec


def pps_blinn_phong(
    images,
    mask,
    lights,
    camera,
    *,
    ks: float,
    shininess: float,
    residual: Literal["direct", "ratio"] = "direct",
    iterations: int = 30,
) -> dict:
    """PPS: perspective Blinn-Phong PS in ``nu = ln d`` (3.15-3.19), per pixel LM (3.20-3.21).

    Unknowns ``X = (nu_u, nu_v, kd)``; started from :func:`lambertian_closed_form`.

    Residuals:
        ``"direct"``: ``I_k - model_k(X)`` (3.15).
        ``"ratio"``: the partial linearisation by image ratios (3.22-3.34): for
            each pair (a, b) the cross-multiplied ratio ``I_a model_b - I_b model_a``
            (3.34), normalised by ``I_a + I_b``, plus the direct equation of the
            brightest image (the ratios alone admit the trivial ``model = 0``).

    Levenberg-Marquardt with forward-difference Jacobians (float64), vectorised
    over pixels; ``iterations`` steps.  Lights are :class:`DirectionalLights`;
    images are divided by their grey intensities.

    Returns:
        dict: ``gradient`` (H, W, 2), ``normals`` (H, W, 3), ``albedo`` (H, W),
        ``cost`` (H, W) final 1/2 |residual|^2.
    """
    if residual not in ("direct", "ratio"):
        raise ValueError(f"residual: expected 'direct' or 'ratio', got {residual!r}")
    if not isinstance(camera, Perspective):
        raise TypeError(f"camera: expected gpps.camera.Perspective, got {type(camera).__name__}")
    init = lambertian_closed_form(images, mask, lights, camera)
    I = _grey_images(images, len(lights))
    I = I / np.asarray(lights.intensities).mean(1)[:, None, None]
    h, w = I.shape[1:]
    m = as_mask("mask", mask, (h, w))
    a, b, c = (t[m] for t in affine_normal(camera, (h, w)))
    r, _, _ = _rays(camera, (h, w))
    v = -r[m]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    L = np.asarray(lights.directions)
    obs = I[:, m].T  # (P, K)
    X = np.concatenate([init["gradient"][m].astype(np.float64), init["albedo"][m][:, None].astype(np.float64)], 1)
    K = L.shape[0]
    pairs = [(p, q) for p in range(K) for q in range(p + 1, K)]
    kb = np.argmax(obs, 1)

    def res(X):
        mod = _bp_model(X, a, b, c, L, v, ks, shininess)
        if residual == "direct":
            return obs - mod
        cols = [(obs[:, p] * mod[:, q] - obs[:, q] * mod[:, p]) / np.maximum(obs[:, p] + obs[:, q], 1e-6) for p, q in pairs]
        cols.append(np.take_along_axis(obs - mod, kb[:, None], 1)[:, 0])
        return np.stack(cols, 1)

    lam = np.full(X.shape[0], 1e-3)
    r0 = res(X)
    cost = 0.5 * np.sum(r0**2, 1)
    for _ in range(int(iterations)):
        J = np.empty(r0.shape + (3,))
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-7 * (1.0 + np.abs(X[:, k]).mean())
            J[..., k] = (res(X + e) - r0) / e[k]
        A = np.einsum("pmi,pmj->pij", J, J)
        g = np.einsum("pmi,pm->pi", J, r0)
        Ad = A + lam[:, None, None] * (np.eye(3) * (np.einsum("pii->pi", A)[:, :, None] + 1e-12))
        step = -np.linalg.solve(Ad, g[..., None])[..., 0]
        Xn = X + step
        rn = res(Xn)
        cn = 0.5 * np.sum(rn**2, 1)
        acc = np.isfinite(cn) & (cn < cost)
        X = np.where(acc[:, None], Xn, X)
        r0 = np.where(acc[:, None], rn, r0)
        cost = np.where(acc, cn, cost)
        lam = np.where(acc, lam * 0.3, lam * 10.0)
    grad = np.zeros((h, w, 2))
    grad[m] = X[:, :2]
    alb = np.zeros((h, w))
    alb[m] = X[:, 2]
    cmap = np.zeros((h, w))
    cmap[m] = cost
    return {"gradient": grad.astype(np.float32), "normals": gradient_to_normals(grad, m, camera), "albedo": alb.astype(np.float32), "cost": cmap}


def sensitivity_indicator(lights, camera, shape) -> dict:
    """Lighting sensitivity indicator (3.13) for the first three directional lights.

    The first three expressions are the 2x2 minors of the light directions
    (PPN needs only ``det L != 0``); the other eight involve the pixel
    position (x, y) and are what makes PPS more sensitive to the lighting.
    (x, y) are image-plane coordinates in pixels relative to the principal
    point, y up, as in the seed's (x, y, f).

    Returns:
        dict: ``det_L`` (the 3x3 determinant of the first three directions),
        ``terms`` (11, H, W) the expressions of (3.13), ``min_abs`` (H, W) the
        smallest |term| (0 where the indicator fails).
    """
    _check_lights(lights)
    if not isinstance(camera, Perspective):
        raise TypeError(f"camera: expected gpps.camera.Perspective, got {type(camera).__name__}")
    h, w = shape
    (a1, b1, g1), (a2, b2, g2), (a3, b3, g3) = np.asarray(lights.directions[:3])
    cx, cy = camera.principal_point()
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = jj - cx, -(ii - cy)
    one = np.ones_like(x)
    terms = np.stack(
        [
            (b1 * a3 - a1 * b3) * one,
            (b2 * a1 - a2 * b1) * one,
            (a2 * b3 - b2 * a3) * one,
            y * a1 * g1 - x * b1 * g1,
            x * b2 * a1 - y * a2 * g1,
            y * a2 * g3 - x * b2 * g3,
            x * g1 * b1 - y * g1 * a1,
            y * g1 * a3 - x * g1 * b3,
            y * g2 * a1 - x * g2 * b1,
            y * a2 * g1 - x * b2 * g1,
            x * g2 * b3 - y * g2 * a3,
        ]
    )
    return {"det_L": float(np.linalg.det(np.asarray(lights.directions[:3]))), "terms": terms, "min_abs": np.abs(terms).min(0)}
