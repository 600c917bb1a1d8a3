"""Accuracy measures: angular error of normals (MAEN), slant and tilt (3.38-3.39), reprojection error."""

from __future__ import annotations

import numpy as np

from gpps._check import as_array, as_images, as_mask, check_number

__all__ = ["angular_error", "slant_tilt", "normal_errors", "reprojection_error", "depth_error", "flag_counts"]


def _normals_pair(est, gt, mask):
    m = as_mask("mask", mask)
    h, w = m.shape
    a = as_array("normals", est, shape=(h, w, 3), dtype=np.float64)
    b = as_array("normals_gt", gt, shape=(h, w, 3), dtype=np.float64)
    return a, b, m


def angular_error(est, gt, mask) -> np.ndarray:
    """Angle in degrees between estimated and true normals, (H, W); 0 outside ``mask``.

    Both are normalised first; a zero vector inside the mask counts as 180 deg.
    """
    a, b, m = _normals_pair(est, gt, mask)
    na = np.linalg.norm(a, axis=-1)
    nb = np.linalg.norm(b, axis=-1)
    c = np.sum(a * b, -1) / np.maximum(na * nb, 1e-300)
    c = np.where((na > 0) & (nb > 0), c, -1.0)
    err = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    return np.where(m, err, 0.0)


def slant_tilt(normals) -> tuple[np.ndarray, np.ndarray]:
    """Slant and tilt (degrees) of unit normals (..., 3) (3.38-3.39).

    With the gradient ``p = -n_x / n_z``, ``q = -n_y / n_z``: slant
    ``sigma = arctan(sqrt(p^2 + q^2))`` (= arccos n_z, the angle to the line of
    sight) and tilt ``tau = arctan(q / p)``, evaluated as ``atan2(n_y, n_x)`` so
    that the quadrant is kept (the text's ``arctan(q/p)`` loses it); tilt in (-180, 180].
    """
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-300)
    slant = np.degrees(np.arccos(np.clip(n[..., 2], -1.0, 1.0)))
    tilt = np.degrees(np.arctan2(n[..., 1], n[..., 0]))
    return slant, tilt


def normal_errors(est, gt, mask, *, tilt_min_slant_deg: float = 1.0) -> dict:
    """Summary of normal accuracy inside ``mask``.

    Returns:
        dict with ``mean`` (MAEN) and ``median`` angular error (deg),
        ``under_5deg`` / ``under_10deg`` (fractions of pixels), ``max``,
        ``slant_mae`` (mean |slant error|, deg), ``tilt_mae`` (mean wrapped
        |tilt error|, deg, over pixels whose true slant exceeds
        ``tilt_min_slant_deg``: the tilt of a fronto-parallel patch is undefined)
        and ``pixels``.
    """
    a, b, m = _normals_pair(est, gt, mask)
    tilt_min_slant_deg = check_number("tilt_min_slant_deg", tilt_min_slant_deg, lo=0.0, hi=180.0)
    e = angular_error(a, b, m)[m]
    sa, ta = slant_tilt(a[m])
    sb, tb = slant_tilt(b[m])
    dt = np.abs((ta - tb + 180.0) % 360.0 - 180.0)
    sel = sb > tilt_min_slant_deg
    return {
        "mean": float(e.mean()),
        "median": float(np.median(e)),
        "under_5deg": float(np.mean(e < 5.0)),
        "under_10deg": float(np.mean(e < 10.0)),
        "max": float(e.max()),
        "slant_mae": float(np.mean(np.abs(sa - sb))),
        "tilt_mae": float(dt[sel].mean()) if sel.any() else 0.0,
        "pixels": int(m.sum()),
    }


def reprojection_error(images, rendered, mask, valid=None) -> dict:
    """Difference between observed and re-rendered images inside ``mask``.

    Args:
        images: (N, H, W, 3) or (N, H, W) observations.
        rendered: same shape, the model's images at the estimate.
        mask: (H, W).
        valid: optional (N, H, W) bool: observations to count.

    Returns:
        dict with ``rmse``, ``mae`` (all valid observations and channels) and
        ``mse_per_image`` (list of N).
    """
    x = as_images("images", images, dtype=np.float64)
    y = as_images("rendered", rendered, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"rendered: expected shape {x.shape}, got {y.shape}")
    if x.ndim == 3:
        x, y = x[..., None], y[..., None]
    if x.ndim != 4:
        raise ValueError(f"images: expected shape (N, H, W, 3) or (N, H, W), got {x.shape}")
    m = as_mask("mask", mask, x.shape[1:3])
    sel = np.broadcast_to(m[None], x.shape[:3]).copy()
    if valid is not None:
        v = np.asarray(valid, bool)
        if v.shape != x.shape[:3]:
            raise ValueError(f"valid: expected shape {x.shape[:3]}, got {v.shape}")
        sel &= v
    d = (x - y)[sel]
    per = [float(np.mean((x[k] - y[k])[sel[k]] ** 2)) if sel[k].any() else 0.0 for k in range(x.shape[0])]
    return {"rmse": float(np.sqrt(np.mean(d**2))), "mae": float(np.mean(np.abs(d))), "mse_per_image": per}


def depth_error(depth, depth_mask, scene) -> float:
    """Mean absolute depth error as a fraction of the true depth range, after alignment.

    Orthographic depth is known up to an offset (the means are matched),
    perspective depth up to a scale (the median ratio is matched).

    Args:
        depth: (H, W) estimated depth.
        depth_mask: (H, W) bool pixels with an estimate.
        scene: a :class:`gpps.host.scenes.Scene` (or anything) with the true ``depth``, ``mask`` and ``camera``.

    Raises:
        TypeError / ValueError: naming the argument: a ``scene`` without those, shapes that differ from the
            scene's, non-finite depth, no pixel in both masks, a perspective depth <= 0 there (no scale to
            match), or a true depth without range there (the error is relative to it).
    """
    if not all(hasattr(scene, k) for k in ("depth", "mask", "camera")):
        raise TypeError(f"scene: expected a gpps.host.scenes.Scene (with depth, mask and camera), "
                        f"got {type(scene).__name__}")
    sm = as_mask("scene.mask", scene.mask)
    g_all = as_array("scene.depth", scene.depth, shape=sm.shape, dtype=np.float64)
    dep = as_array("depth", depth, shape=sm.shape, dtype=np.float64)
    m = as_mask("depth_mask", depth_mask, sm.shape, allow_empty=True) & sm
    if not m.any():
        raise ValueError("depth_mask: expected pixels inside the scene's mask, got none in both masks")
    d, g = dep[m], g_all[m]
    span = float(g.max() - g.min())
    if not span > 0:
        raise ValueError(f"scene.depth: expected a depth range inside the masks (the error is relative to it), "
                         f"got constant depth {float(g[0]):g} over {g.size} pixel(s)")
    if scene.camera.is_perspective:
        if np.any(d <= 0):
            raise ValueError("depth: expected values > 0 inside depth_mask (perspective depth is matched by a scale)")
        d = d * np.median(g / d)
    else:
        d = d - np.mean(d - g)
    return float(np.mean(np.abs(d - g)) / span)


def flag_counts(flags, mask) -> dict:
    """How many of the mask's pixels carry each of the per-pixel solver's flag bits.

    Args:
        flags: (H, W) int the solver's flags (:data:`gpps.names.FLAG_NAMES`).
        mask: (H, W) bool.

    Returns:
        ``{name: count}`` for every flag name, and ``"any"``: the pixels with at least one bit.
    """
    from gpps.names import FLAG_NAMES

    f = np.asarray(flags)[np.asarray(mask, bool)]
    out = {name: int(np.count_nonzero(f & bit)) for bit, name in FLAG_NAMES.items()}
    out["any"] = int(np.count_nonzero(f))
    return out
