"""Light calibration from images of spheres: a mirror (chrome) sphere for directions, a matte sphere or grey card for intensities.

Geometry (gpps frame, :mod:`gpps.camera`):
* **Outline** (:func:`fit_sphere`): sub-pixel points of the sphere's silhouette
  (found in the images, :func:`find_outline`, or from a given circle or mask).
  With a perspective camera the silhouette is the cone of rays tangent to the
  sphere: every outline ray ``r_i`` (unit) makes the same angle ``theta`` with
  the direction ``c`` to the sphere's centre, ``r_i . c = cos(theta)``, which is
  linear in ``c / cos(theta)`` (least squares, then a geometric refinement of
  the angles).  The sphere is then known up to scale: radius ``R`` at distance
  ``R / sin(theta)`` along ``c`` (an off-axis sphere images as an ellipse; the
  cone handles that exactly).  Orthographic: a circle (centre, radius) in pixels.
* **Highlight** (:func:`highlight_centroid`): the intensity-weighted centroid of
  the brightest blob on the sphere (weights: intensity above half the way from
  the sphere's median to its peak; a saturated blob counts evenly).
* **Direction** (:func:`mirror_directions`): the pixel's ray hits the sphere at
  ``P`` with normal ``n``; the view vector ``v`` is ``-ray`` (orthographic:
  ``(0, 0, 1)``), and the light is the mirror direction ``l = 2 (n.v) n - v``
  (a distant light).
* **Near lights** (:func:`triangulate_lights`): with two mirror spheres of
  known radius (scene units) and a perspective camera, each sphere's reflected
  ray leaves its surface point; the light is the point closest to both rays
  (least squares), reported with the rays' miss distance and the angle
  between them (small angles: the lights are too far for positions).
* **Intensities** (:func:`matte_intensities`, :func:`card_intensities`): a
  Lambertian sphere's pixels give ``I = e_k rho max(n.l_k, 0)``: ``e_k`` by
  least squares per colour channel over its lit, unsaturated pixels; a grey
  card of known normal (default: facing the camera) gives
  ``e_k = mean(I) / (n_card . l_k)``.  Intensities are relative (mean 1 over
  the images and channels).

:func:`render_spheres` renders such captures (for the tests and
``perf/calibrate_spheres.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy import ndimage
from scipy.optimize import least_squares

from gpps.camera import Orthographic, Perspective
from gpps.lights import PointLights

__all__ = ["SphereFit", "fit_sphere", "circle_points", "mask_outline", "find_outline", "disc_mask", "highlight_centroid",
           "mirror_directions", "highlight_direction", "sphere_normals", "matte_intensities", "card_intensities", "triangulate_lights",
           "render_spheres"]


@dataclass
class SphereFit:
    """A sphere fitted to its outline.

    Attributes:
        camera: the camera.
        center_px: (u, v) image of the centre direction (perspective) or the
            circle's centre (orthographic).
        radius_px: the circle's radius (orthographic) or the outline's mean
            distance from ``center_px`` (perspective; for display).
        direction: (3,) unit direction to the centre (perspective), else (0, 0, -1).
        half_angle: ``theta`` (radians) of the tangent cone (perspective), else 0.
        rms_px: RMS distance of the outline points from the fitted outline (pixels).
        points: number of outline points used.
        radius: the sphere's radius in scene units if given (sets the centre's distance).
    """

    camera: object
    center_px: tuple
    radius_px: float
    direction: np.ndarray
    half_angle: float
    rms_px: float
    points: int
    radius: float | None = None
    extra: dict = field(default_factory=dict)

    def center3d(self, radius: float | None = None) -> np.ndarray:
        """Centre in the gpps frame for a sphere of ``radius`` (scene units; perspective only)."""
        R = self.radius if radius is None else radius
        if R is None or not isinstance(self.camera, Perspective):
            raise ValueError("radius: expected the sphere's radius and a perspective camera for a 3-D centre")
        return self.direction * (R / np.sin(self.half_angle))

    def to_dict(self) -> dict:
        d = {"center_px": [float(self.center_px[0]), float(self.center_px[1])], "radius_px": float(self.radius_px),
             "rms_px": float(self.rms_px), "outline_points": int(self.points)}
        if isinstance(self.camera, Perspective):
            d.update(direction=self.direction.tolist(), half_angle_deg=float(np.degrees(self.half_angle)))
            if self.radius is not None:
                d.update(radius=self.radius, center=self.center3d().tolist())
        return d


def _rays(camera, uv):
    uv = np.asarray(uv, np.float64)
    K = camera.K
    d = np.stack([(uv[:, 0] - K[0, 2]) / K[0, 0], -(uv[:, 1] - K[1, 2]) / K[1, 1], -np.ones(len(uv))], -1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fit_sphere(points, camera=None, *, radius: float | None = None, outlier_k: float = 3.0) -> SphereFit:
    """Fit a sphere's silhouette to outline points.

    Args:
        points: (M, 2) outline points (u, v) in pixels, M >= 5.
        camera: :class:`Orthographic` (default) or :class:`Perspective`.
        radius: the sphere's radius in scene units (perspective: fixes its distance), or None.
        outlier_k: points farther than this many robust deviations are dropped (one refit).

    Raises:
        ValueError: too few points, or a degenerate fit.
    """

    camera = camera if camera is not None else Orthographic()
    uv = np.asarray(points, np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or len(uv) < 5:
        raise ValueError(f"points: expected (M, 2) outline points with M >= 5, got shape {uv.shape}")
    keep = np.ones(len(uv), bool)
    for _ in range(2):
        p = uv[keep]
        if isinstance(camera, Perspective):
            r = _rays(camera, p)
            x, *_ = np.linalg.lstsq(r, np.ones(len(r)), rcond=None)
            c = x / np.linalg.norm(x)
            theta = float(np.arccos(min(1.0 / np.linalg.norm(x), 1.0)))

            def resid(q, r=r):
                cc = np.array([np.sin(q[0]) * np.cos(q[1]), np.sin(q[0]) * np.sin(q[1]), -np.cos(q[0])])
                return np.arccos(np.clip(r @ cc, -1, 1)) - q[2]

            q0 = [np.arccos(np.clip(-c[2], -1, 1)), np.arctan2(c[1], c[0]), theta]
            sol = least_squares(resid, q0, method="lm")
            a, b, theta = sol.x
            c = np.array([np.sin(a) * np.cos(b), np.sin(a) * np.sin(b), -np.cos(a)])
            ang = resid(sol.x)
            # residual in pixels: angle x focal length / cos^2 of the off-axis angle (approximately)
            res_px = ang * np.sqrt(camera.fx * camera.fy)
            cu = camera.K[0, 2] + camera.fx * c[0] / -c[2]
            cv = camera.K[1, 2] - camera.fy * c[1] / -c[2]
            center, rad = (float(cu), float(cv)), float(np.mean(np.hypot(p[:, 0] - cu, p[:, 1] - cv)))
        else:
            A = np.column_stack([2 * p, np.ones(len(p))])
            sol0, *_ = np.linalg.lstsq(A, (p**2).sum(1), rcond=None)
            cx, cy = sol0[0], sol0[1]
            rr = np.sqrt(max(sol0[2] + cx**2 + cy**2, 1e-12))
            sol = least_squares(lambda q, p=p: np.hypot(p[:, 0] - q[0], p[:, 1] - q[1]) - q[2], [cx, cy, rr], method="lm")
            cx, cy, rr = sol.x
            res_px = np.hypot(p[:, 0] - cx, p[:, 1] - cy) - rr
            center, rad, c, theta = (float(cx), float(cy)), float(abs(rr)), np.array([0.0, 0.0, -1.0]), 0.0
        # drop outliers once (a highlight or a neighbour touching the silhouette)
        full = np.zeros(len(uv))
        full[keep] = res_px
        s = 1.4826 * np.median(np.abs(res_px)) + 1e-6
        new = keep & (np.abs(full) <= max(outlier_k * s, 0.5))
        if new.sum() == keep.sum() or new.sum() < 5:
            break
        keep = new
    if not np.isfinite(rad) or rad <= 0:
        raise ValueError("points: the outline does not fit a sphere")
    return SphereFit(camera=camera, center_px=center, radius_px=rad, direction=c, half_angle=float(theta),
                     rms_px=float(np.sqrt(np.mean(res_px**2))), points=int(keep.sum()), radius=radius)


def circle_points(cx: float, cy: float, r: float, n: int = 360) -> np.ndarray:
    """(n, 2) points on a circle (a given outline; exact for orthographic cameras, an approximation of
    the ellipse an off-axis sphere makes in a perspective image)."""
    if not r > 0:
        raise ValueError(f"r: expected a radius > 0 pixels, got {r!r}")
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], -1)


def _edge_points(field_, level, inside):
    """Sub-pixel crossings of ``field_`` through ``level`` between 4-neighbours with one pixel in ``inside``."""
    pts = []
    f = np.asarray(field_, np.float64)
    for axis in (0, 1):
        a = inside[:-1, :] if axis == 0 else inside[:, :-1]
        b = inside[1:, :] if axis == 0 else inside[:, 1:]
        fa = f[:-1, :] if axis == 0 else f[:, :-1]
        fb = f[1:, :] if axis == 0 else f[:, 1:]
        e = a != b
        ii, jj = np.nonzero(e)
        den = fb[e] - fa[e]
        t = np.where(np.abs(den) > 1e-12, (level - fa[e]) / np.where(np.abs(den) > 1e-12, den, 1.0), 0.5)
        t = np.clip(t, 0.0, 1.0)
        if axis == 0:
            pts.append(np.stack([jj.astype(float), ii + t], -1))
        else:
            pts.append(np.stack([jj + t, ii.astype(float)], -1))
    return np.concatenate(pts, 0)


def mask_outline(mask) -> np.ndarray:
    """Outline points (u, v) of a binary mask: midpoints between inside and outside 4-neighbours."""
    m = np.asarray(mask, bool)
    return _edge_points(m.astype(np.float64), 0.5, m)


def find_outline(images, *, region=None) -> tuple[np.ndarray, np.ndarray]:
    """Find a sphere's outline in images of it under different lights.

    The per-pixel median over the images suppresses the moving highlights and
    keeps what the sphere reflects of the room (and a matte sphere's shading);
    it is thresholded (Otsu, on the log intensities) and the most circular
    large component of either polarity is the sphere.  Its outline is the
    sub-pixel crossing of the threshold.

    Args:
        images: (N, H, W[, C]) linear images.
        region: optional (H, W) bool where to look.

    Returns:
        ``(points (M, 2), mask (H, W))``.

    Raises:
        ValueError: no round component found (give the outline: a circle or a mask).
    """

    imgs = np.asarray(images, np.float64)
    grey = imgs.mean(-1) if imgs.ndim == 4 else imgs
    med = np.median(grey, axis=0)
    med = ndimage.gaussian_filter(med, 0.7)
    lg = np.log(np.maximum(med, 1e-5))
    sel = np.ones(med.shape, bool) if region is None else np.asarray(region, bool)
    lo, hi = np.percentile(lg[sel], [1, 99])
    u8 = np.clip((lg - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    thr, _ = cv2.threshold(u8[sel][None], 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    level = float(np.exp(lo + thr / 255.0 * (hi - lo)))
    best = None
    for inside in (med > level, med <= level):
        inside = inside & sel
        lab, k = ndimage.label(ndimage.binary_opening(inside, iterations=2))
        if k == 0:
            continue
        sizes = np.bincount(lab.ravel())[1:]
        for idx in np.argsort(sizes)[::-1][:5]:
            comp = ndimage.binary_fill_holes(lab == idx + 1)
            area = comp.sum()
            if area < 50:
                continue
            ii, jj = np.nonzero(comp)
            # circularity: the component against the disc of the same centre and area
            cy, cx = ii.mean(), jj.mean()
            r = np.sqrt(area / np.pi)
            disc = (ii - cy) ** 2 + (jj - cx) ** 2 <= r**2
            score = disc.mean() * min(1.0, area / (0.002 * med.size))
            touches = ii.min() == 0 or jj.min() == 0 or ii.max() == med.shape[0] - 1 or jj.max() == med.shape[1] - 1
            if touches:
                score *= 0.1
            if best is None or score > best[0]:
                best = (score, comp)
    if best is None or best[0] < 0.8:
        raise ValueError("images: could not find a round sphere outline; give it (--chrome CX CY R or chrome_mask.png)")
    comp = best[1]
    # the sub-pixel outline: half-way between the sphere's and the background's levels (linear), where
    # an anti-aliased edge is half covered (the Otsu level of the log image only segments)
    band_in = ndimage.binary_erosion(comp, iterations=2) & ~ndimage.binary_erosion(comp, iterations=6)
    band_out = ndimage.binary_dilation(comp, iterations=5) & ~ndimage.binary_dilation(comp, iterations=1)
    a_in, a_out = float(np.median(med[band_in])), float(np.median(med[band_out]))
    half = 0.5 * (a_in + a_out)
    near = ndimage.binary_dilation(comp, iterations=3)
    inside = ((med > half) if a_in > a_out else (med < half)) & near
    lab, k = ndimage.label(inside)
    if k > 1:
        inside = lab == (np.argmax(np.bincount(lab.ravel())[1:]) + 1)
    comp = ndimage.binary_fill_holes(inside)
    pts = _edge_points(med, half, comp)
    return pts, comp


def sphere_normals(fit: SphereFit, uv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normals and view vectors of the sphere at pixels (u, v).

    Returns:
        ``(normals (M, 3), views (M, 3), hit (M,) bool)``: unit normals and unit
        vectors toward the camera, gpps frame; ``hit`` False where the ray misses.
    """
    uv = np.atleast_2d(np.asarray(uv, np.float64))
    cam = fit.camera
    if isinstance(cam, Perspective):
        d = _rays(cam, uv)
        C = fit.direction / np.sin(fit.half_angle)  # radius 1
        b = d @ C
        disc = b**2 - (C @ C - 1.0)
        hit = disc >= 0
        t = b - np.sqrt(np.maximum(disc, 0.0))
        P = t[:, None] * d
        n = P - C
        v = -d
    else:
        cx, cy = fit.center_px
        x = (uv[:, 0] - cx) / fit.radius_px
        y = -(uv[:, 1] - cy) / fit.radius_px
        rr = x**2 + y**2
        hit = rr <= 1.0
        n = np.stack([x, y, np.sqrt(np.maximum(1.0 - rr, 0.0))], -1)
        v = np.tile([0.0, 0.0, 1.0], (len(uv), 1))
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n, v, hit


def mirror_directions(fit: SphereFit, uv) -> np.ndarray:
    """Unit light directions (M, 3) from highlight pixels (u, v) on a mirror sphere: ``l = 2 (n.v) n - v``."""
    n, v, hit = sphere_normals(fit, uv)
    if not np.all(hit):
        raise ValueError(f"uv: {int((~hit).sum())} highlight(s) outside the sphere's outline")
    l = 2.0 * np.sum(n * v, 1, keepdims=True) * n - v
    return l / np.linalg.norm(l, axis=1, keepdims=True)


def disc_mask(fit: SphereFit, shape, shrink: float = 0.0) -> np.ndarray:
    """(H, W) bool: the pixels inside the sphere's outline, shrunk by ``shrink`` pixels.

    Args:
        fit: the sphere (:func:`fit_sphere`).
        shape: (H, W) of the image.
        shrink: pixels to leave out along the outline (perspective: as an angle, ``shrink / sqrt(fx fy)`` rad).
    """
    h, w = shape
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    uv = np.stack([jj.ravel(), ii.ravel()], -1)
    if isinstance(fit.camera, Perspective):
        d = _rays(fit.camera, uv)
        ang = np.arccos(np.clip(d @ fit.direction, -1, 1))
        inside = ang < fit.half_angle - shrink / np.sqrt(fit.camera.fx * fit.camera.fy)
    else:
        inside = np.hypot(uv[:, 0] - fit.center_px[0], uv[:, 1] - fit.center_px[1]) < fit.radius_px - shrink
    return inside.reshape(h, w)


_disc_mask = disc_mask  # the name the tests know


def highlight_centroid(image, region, *, min_contrast: float = 3.0) -> tuple[np.ndarray | None, dict]:
    """The highlight's intensity-weighted centroid in ``region``.

    Args:
        image: (H, W[, C]) linear image.
        region: (H, W) bool, the sphere (shrunk off its rim).
        min_contrast: the peak must exceed the region's median by this factor
            (else no highlight: the light is behind the sphere or off).

    Returns:
        ``((u, v) or None, info)`` with the peak, the blob's pixels, whether it is saturated.
    """

    g = np.asarray(image, np.float64)
    g = g.mean(-1) if g.ndim == 3 else g
    r = np.asarray(region, bool)
    vals = g[r]
    peak = float(vals.max()) if vals.size else 0.0
    base = float(np.median(vals)) if vals.size else 0.0
    info = {"peak": peak, "background": base}
    if vals.size == 0 or peak <= min_contrast * max(base, 1e-6) or peak <= 0:
        info["reason"] = "no highlight (peak not above the sphere's median)"
        return None, info
    # the blob: pixels above half the way from the sphere's level to the peak, connected to the peak;
    # the weights (intensity above the sphere's level) are taken over the blob grown by 2 pixels, so
    # that the partly covered pixels at its edge (the sub-pixel information) count too
    thr = base + 0.5 * (peak - base)
    lab, _ = ndimage.label((g > thr) & r)
    ii, jj = np.unravel_index(np.argmax(np.where(r, g, -np.inf)), g.shape)
    core = lab == lab[ii, jj]
    comp = ndimage.binary_dilation(core, iterations=2) & r & (g > base + 0.02 * (peak - base))
    wts = (g - base)[comp]
    ii, jj = np.nonzero(comp)
    u = float(np.sum(wts * jj) / np.sum(wts))
    v = float(np.sum(wts * ii) / np.sum(wts))
    info.update(pixels=int(core.sum()), saturated=bool(peak >= 0.99), others=int(lab.max() - 1),
                blob_uv=np.stack([jj, ii], -1).astype(np.float64), blob_weights=wts)
    return np.array([u, v]), info


def highlight_direction(fit: SphereFit, image, region, *, min_contrast: float = 3.0) -> tuple[np.ndarray | None, dict]:
    """A mirror sphere's light direction from one image: the weighted mean of the mirror directions of
    the highlight blob's pixels (the same weights as :func:`highlight_centroid`; averaging directions
    rather than pixels removes the foreshortening bias of the image centroid near the rim).

    Returns:
        ``(unit direction (3,) or None, info)`` (info as :func:`highlight_centroid`'s, plus ``centroid``).
    """
    c, info = highlight_centroid(image, region, min_contrast=min_contrast)
    if c is None:
        return None, info
    uv, w = info.pop("blob_uv"), info.pop("blob_weights")
    ls = mirror_directions(fit, uv)
    l = (w[:, None] * ls).sum(0)
    info["centroid"] = [float(c[0]), float(c[1])]
    return l / np.linalg.norm(l), info


def matte_intensities(images, fit: SphereFit, directions, *, shrink: float = 2.0, min_cos: float = 0.1,
                      saturation: float = 0.98) -> tuple[np.ndarray, dict]:
    """Relative RGB light intensities from a Lambertian sphere and known light directions.

    Returns:
        ``(intensities (N, 3) with mean 1, info)`` (info: albedo-free RMS relative residual per image).
    """
    imgs = np.asarray(images, np.float64)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    n_img, h, w, c = imgs.shape
    region = disc_mask(fit, (h, w), shrink)
    ii, jj = np.nonzero(region)
    normals, _, hit = sphere_normals(fit, np.stack([jj, ii], -1))
    L = np.asarray(directions, np.float64)
    e = np.zeros((n_img, c))
    resid = []
    for k in range(n_img):
        s = normals @ L[k]
        I = imgs[k][ii, jj]  # (P, C)
        ok = hit & (s > min_cos) & np.all(I < saturation, -1)
        if ok.sum() < 10:
            raise ValueError(f"images: image {k} lights fewer than 10 unsaturated pixels of the matte sphere")
        e[k] = (I[ok] * s[ok, None]).sum(0) / (s[ok] ** 2).sum()
        resid.append(float(np.sqrt(np.mean((I[ok] - s[ok, None] * e[k]) ** 2)) / max(np.mean(I[ok]), 1e-12)))
    e = e / e.mean()
    return np.repeat(e, 3, 1) if c == 1 else e, {"relative_rms_residual": resid, "pixels": int(region.sum())}


def card_intensities(images, region, directions, normal=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, dict]:
    """Relative RGB intensities from a flat grey (Lambertian) card of known normal: ``e_k = mean(I) / (n . l_k)``."""
    imgs = np.asarray(images, np.float64)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    r = np.asarray(region, bool)
    nc = np.asarray(normal, np.float64)
    nc = nc / np.linalg.norm(nc)
    cos = np.asarray(directions, np.float64) @ nc
    if np.any(cos <= 0.05):
        raise ValueError(f"card: the card faces away from light(s) {np.where(cos <= 0.05)[0].tolist()} (n.l <= 0.05): give --card-normal")
    means = np.stack([im[r].mean(0) for im in imgs])
    e = means / cos[:, None]
    e = e / e.mean()
    return np.repeat(e, 3, 1) if e.shape[1] == 1 else e, {"pixels": int(r.sum())}


def triangulate_lights(fits, highlights, radii) -> tuple[np.ndarray, dict]:
    """Near-light positions from two (or more) mirror spheres of known radius (perspective camera).

    Args:
        fits: list of :class:`SphereFit` (perspective).
        highlights: list (per sphere) of (N, 2) highlight pixels (NaN rows: none).
        radii: list of the spheres' radii (scene units).

    Returns:
        ``(positions (N, 3), info)``: info has per light the rays' miss distance
        and the largest angle between them (degrees).
    """
    S = len(fits)
    if S < 2:
        raise ValueError(f"fits: expected two or more spheres for light positions, got {S}")
    N = len(highlights[0])
    pos = np.full((N, 3), np.nan)
    miss, angle = [], []
    for k in range(N):
        A = np.zeros((3, 3))
        b = np.zeros(3)
        dirs, origins = [], []
        for f, hl, R in zip(fits, highlights, radii):
            uv = np.asarray(hl[k], np.float64)
            if not np.all(np.isfinite(uv)):
                continue
            if not isinstance(f.camera, Perspective):
                raise ValueError("fits: expected a perspective camera for light positions")
            d = _rays(f.camera, uv[None])[0]
            C = f.center3d(R)
            bb = d @ C
            t = bb - np.sqrt(max(bb**2 - (C @ C - R**2), 0.0))
            P = t * d
            n = (P - C) / R
            v = -d
            l = 2 * (n @ v) * n - v
            l /= np.linalg.norm(l)
            M = np.eye(3) - np.outer(l, l)
            A += M
            b += M @ P
            dirs.append(l)
            origins.append(P)
        if len(dirs) < 2:
            miss.append(float("nan"))
            angle.append(float("nan"))
            continue
        x = np.linalg.lstsq(A, b, rcond=None)[0]
        pos[k] = x
        dist = [np.linalg.norm((np.eye(3) - np.outer(l, l)) @ (x - P)) for l, P in zip(dirs, origins)]
        miss.append(float(np.max(dist)))
        angle.append(float(max(np.degrees(np.arccos(np.clip(a @ c, -1, 1))) for a in dirs for c in dirs)))
    return pos, {"miss_distance": miss, "ray_angle_deg": angle}


def render_spheres(shape, camera, spheres, lights, *, intensities=None, source_deg: float = 3.0, environment: float = 0.05,
                   supersample: int = 4, peak: float = 4.0) -> np.ndarray:
    """Render spheres lit by directional or point lights (synthetic calibration captures).

    Args:
        shape: (H, W).
        camera: :class:`Orthographic` or :class:`Perspective`.
        spheres: list of dicts ``{"center": (3,), "radius": R, "kind": "chrome" | "matte", "albedo": (3,)}``.
        lights: :class:`gpps.lights.DirectionalLights` or :class:`gpps.lights.PointLights`.
        intensities: (N, 3) RGB intensities (default: the lights').
        source_deg: angular radius of each light source as a mirror sees it (soft-edged disc).
        environment: radiance of the uniform room a mirror reflects (the background is 0).
        supersample: sub-pixels per side (anti-aliasing of the outline).
        peak: a mirror highlight's radiance, times the light's intensity (> 1 saturates).

    Returns:
        (N, H, W, 3) linear images (not clipped).
    """

    h, w = shape
    s = int(supersample)
    off = (np.arange(s) + 0.5) / s - 0.5
    uu = (np.arange(w)[:, None] + off[None, :]).ravel()
    vv = (np.arange(h)[:, None] + off[None, :]).ravel()
    U, V = np.meshgrid(uu, vv)
    if isinstance(camera, Perspective):
        K = camera.K
        d = np.stack([(U - K[0, 2]) / K[0, 0], -(V - K[1, 2]) / K[1, 1], -np.ones_like(U)], -1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.zeros_like(d)
    else:
        cx, cy = camera.principal_point((h, w))
        o = np.stack([(U - cx) * camera.pixel_size, -(V - cy) * camera.pixel_size, np.zeros_like(U)], -1)
        d = np.zeros_like(o)
        d[..., 2] = -1.0
    tbest = np.full(U.shape, np.inf)
    which = np.full(U.shape, -1)
    for k, sp in enumerate(spheres):
        C = np.asarray(sp["center"], np.float64)
        R = float(sp["radius"])
        oc = o - C
        b = np.sum(oc * d, -1)
        disc = b**2 - (np.sum(oc * oc, -1) - R**2)
        t = -b - np.sqrt(np.maximum(disc, 0.0))
        hit = (disc >= 0) & (t > 0) & (t < tbest)
        tbest = np.where(hit, t, tbest)
        which = np.where(hit, k, which)
    P = o + np.where(np.isfinite(tbest), tbest, 0.0)[..., None] * d
    N_l = len(lights)
    E = np.asarray(lights.intensities if intensities is None else intensities, np.float64).reshape(N_l, -1)
    if E.shape[1] == 1:
        E = np.repeat(E, 3, 1)
    out = np.zeros((N_l, h * s, w * s, 3))
    soft = np.radians(source_deg) * 0.25
    for k, sp in enumerate(spheres):
        m = which == k
        if not m.any():
            continue
        C = np.asarray(sp["center"], np.float64)
        n = (P[m] - C) / float(sp["radius"])
        v = -d[m]
        for li in range(N_l):
            if isinstance(lights, PointLights):
                lv = np.asarray(lights.positions[li]) - P[m]
                r2 = np.sum(lv**2, -1)
                lv = lv / np.sqrt(r2)[:, None]
                fall = 1.0 / r2
            else:
                lv = np.tile(np.asarray(lights.directions[li], np.float64), (int(m.sum()), 1))
                fall = np.ones(int(m.sum()))
            if sp.get("kind", "chrome") == "chrome":
                refl = 2 * np.sum(n * v, -1, keepdims=True) * n - v
                ang = np.arccos(np.clip(np.sum(refl * lv, -1), -1, 1))
                edge = np.clip((np.radians(source_deg) - ang) / soft + 0.5, 0.0, 1.0)
                rad = environment + peak * edge[:, None] * E[li][None, :] * (fall[:, None] / fall.mean() if isinstance(lights, PointLights) else 1.0)
                out[li][m] = rad
            else:
                alb = np.asarray(sp.get("albedo", (0.8, 0.8, 0.8)), np.float64)
                out[li][m] = alb[None, :] * E[li][None, :] * (np.clip(np.sum(n * lv, -1), 0, None) * fall)[:, None]
    return out.reshape(N_l, h, s, w, s, 3).mean((2, 4))
