"""Continuous test surfaces for crease cut and stitch (gpps.host.creases), written independently of gpps.

Each surface is a depth function ``d(j, i)`` over the pixel grid (pixel centres at integer column j, row i),
continuous over the whole mask; the 3-D point of a pixel is

* perspective (focal ``f = F_PX * w``, centre ``c = ((w - 1) / 2, (h - 1) / 2)``):
  ``X = d ((j - cx) / f, -(i - cy) / f, -1)``;
* orthographic (pixel size ``s``): ``X = ((j - cx) s, -(i - cy) s, -d)``;

and its normal is ``X_j x X_i`` (derivatives by central differences of step 1e-4 px), turned toward the
camera.  Surfaces (``SURFACES``):

* ``ridge``: two planes meeting at a vertical fold that lies between pixel centres (not at the midpoint), no
  depth jump; the normal turns by about 30 degrees across it;
* ``ridge_oblique``: the same fold at 30 degrees to the columns;
* ``sphere``: a sphere seen from the front, the mask its disc less a 1-pixel rim (grazing pixels excluded);
* ``bump``: a Gaussian bump on a tilted plane (smooth, not circular in any cross-section).

``perturb(normals, deg, seed)`` adds noise; ``quantise8(normals)`` codes them in 8 bits as an image would.
"""

from __future__ import annotations

import numpy as np

F_PX = 1.2
Z0 = 10.0
SURFACES = ("ridge", "ridge_oblique", "sphere", "bump")


def _depth_fn(name, h, w, L):
    cj, ci = (w - 1) / 2, (h - 1) / 2
    k = 2 * L / w  # scene units per pixel at the working distance
    if name == "ridge":
        c = cj + 0.3
        return lambda j, i: Z0 - 0.3 * k * np.abs(j - c) + 0.1 * k * (i - ci) + 0.05 * k * (j - cj)
    if name == "ridge_oblique":
        ca, sa = np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30))
        return lambda j, i: Z0 - 0.3 * k * np.abs((j - cj - 0.3) * ca + (i - ci) * sa) + 0.1 * k * (i - ci)
    if name == "bump":
        sig = 0.18 * w
        return lambda j, i: (Z0 + 0.1 * k * (j - cj) - 0.15 * k * (i - ci)
                             - 0.25 * w * k * np.exp(-((j - cj) ** 2 + (i - ci) ** 2) / (2 * sig ** 2)))
    raise ValueError(name)


def render_surface(name: str, size: int = 64, camera: str = "orthographic"):
    """One continuous surface.

    Args:
        name: one of ``SURFACES``.
        size: image height and width (pixels).
        camera: ``"orthographic"`` or ``"perspective"``.

    Returns:
        dict with ``depth`` (H, W), ``normals`` (H, W, 3) unit, ``mask`` (H, W) bool, ``K`` (perspective) or
        ``pixel_size`` (orthographic).
    """
    h = w = size
    L = Z0 / (2 * F_PX)
    s = 2 * L / w
    f = F_PX * w
    cj, ci = (w - 1) / 2, (h - 1) / 2
    ii, jj = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    if name == "sphere":
        R = 0.8 * L
        C = np.array([0.0, 0.0, -(Z0 + R)])

        def d_fn(j, i):
            if camera == "perspective":
                r = np.stack([(j - cj) / f, -(i - ci) / f, -np.ones_like(j)], -1)
                a = np.sum(r * r, -1)
                b = -2 * r @ C
                c = C @ C - R * R
                return (-b - np.sqrt(np.maximum(b * b - 4 * a * c, 0))) / (2 * a)
            x, y = (j - cj) * s, -(i - ci) * s
            return -C[2] - np.sqrt(np.maximum(R * R - x * x - y * y, 0))
    else:
        d_fn = _depth_fn(name, h, w, L)

    def X(j, i):
        d = d_fn(j, i)
        if camera == "perspective":
            return np.stack([d * (j - cj) / f, -d * (i - ci) / f, -d], -1)
        return np.stack([(j - cj) * s, -(i - ci) * s, -d], -1)

    e = 1e-4
    xj = (X(jj + e, ii) - X(jj - e, ii)) / (2 * e)
    xi = (X(jj, ii + e) - X(jj, ii - e)) / (2 * e)
    n = np.cross(xj, xi)
    P = X(jj, ii)
    n = np.where((np.sum(n * -P, -1) < 0)[..., None], -n, n) if camera == "perspective" else \
        np.where((n[..., 2] < 0)[..., None], -n, n)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    depth = d_fn(jj, ii)
    mask = np.ones((h, w), bool)
    if name == "sphere":
        if camera == "perspective":
            r = np.stack([(jj - cj) / f, -(ii - ci) / f, -np.ones_like(jj)], -1)
            a = np.sum(r * r, -1)
            b = -2 * r @ C
            inside = b * b - 4 * a * (C @ C - R * R) > 0
        else:
            inside = ((jj - cj) * s) ** 2 + ((ii - ci) * s) ** 2 < R * R
        from scipy import ndimage

        mask = ndimage.binary_erosion(inside, np.ones((3, 3), bool))
    out = dict(depth=np.where(mask, depth, np.nan), normals=np.where(mask[..., None], n, 0.0), mask=mask)
    if camera == "perspective":
        out["K"] = np.array([[f, 0, cj], [0, f, ci], [0, 0, 1.0]])
    else:
        out["pixel_size"] = s
    return out


def perturb(normals, deg: float, seed: int = 0):
    """Unit normals plus isotropic Gaussian noise of ``tan(deg)`` per component, renormalised (rms angle
    about ``deg * sqrt(2)`` degrees)."""
    rng = np.random.default_rng(seed)
    n = normals + np.tan(np.deg2rad(deg)) * rng.standard_normal(normals.shape)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def quantise8(normals):
    """The normals as an 8-bit image codes them: ``round((n + 1) / 2 * 255)``, decoded and renormalised."""
    q = np.round((np.asarray(normals) + 1) / 2 * 255) / 255 * 2 - 1
    ln = np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(ln > 0, q / np.maximum(ln, 1e-300), 0.0)


def global_error(est, gt, mask, perspective: bool):
    """Mean and max ``|error|`` / depth range after ONE offset (orthographic, median) or scale (perspective,
    median ratio) for the whole mask."""
    e, g = est[mask].astype(np.float64), gt[mask]
    a = e * np.median(g / e) if perspective else e + np.median(g - e)
    err = np.abs(a - g)
    rng = float(g.max() - g.min())
    return float(err.mean() / rng), float(err.max() / rng)
