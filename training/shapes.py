"""Random training / test scenes for the single-image network (numpy only).

The data recipe of issue 8, extended for issue 24 (recipe v2): random shapes (height fields, surfaces of
revolution, blobs; composed solids that occlude each other; objects standing on a support that they
shadow; reliefs with terraces, strokes, ridges and rims), random RGB albedo textures (objects and support
apart), the seed's five reflectance models and the dielectric ``plastic`` with random parameters,
directional or point lights with cast shadows marched over the depth map, an indirect fill term, either
camera, exposure with clipping, noise and 8-bit quantisation.
Everything is drawn from one ``numpy.random.Generator`` so that a scene is a
pure function of its seed; training uses seeds ``[0, 10^6)`` and the held-out
tests seeds ``>= 10^9`` (plus gpps's own sphere / bumps scenes and their
sinusoid textures, which the recipe never draws).

Shapes are height maps on the pixel grid in normalised image coordinates
``X = (u - cx) / (S/2)``, ``Y = -(v - cy) / (S/2)`` (``S`` the longer side), so
the object spans about ``[-1, 1]^2``; the height ``H(X, Y)`` is in the same
unit and the depth is ``d = d0 - HALF_EXTENT * H`` (scene units, see
:mod:`gpps.host.scenes`).  Normals are those of the depth map as the camera sees it
(``Renderer.normals_from_depth`` in the recipe), so the ground truth matches
the rendered shading for both cameras.  The network's depth target is the
relative height ``H - mean(H)`` over the mask (offset-free, image-width units).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpps.material import Material
from gpps.names import SEED_BRDF_NAMES
from gpps.host.scenes import D0, HALF_EXTENT, default_camera

__all__ = ["RandomScene", "random_shape", "random_albedo", "random_material", "random_light", "random_scene",
           "SHAPE_FAMILIES", "TRAIN_SEED_LIMIT", "TEST_SEED_BASE"]

SHAPE_FAMILIES = ("heightfield", "revolution", "blobs", "solids", "tabletop", "relief")
# how often each family is drawn (recipe v2, issue 24): the scenes of images from the wild are mostly objects
# that occlude each other or stand on a support, so the composed families carry most of the weight
FAMILY_P = (0.12, 0.10, 0.10, 0.22, 0.30, 0.16)
TRAIN_SEED_LIMIT = 10**6
BRDF_CHOICES = SEED_BRDF_NAMES + ("plastic",)
BRDF_P = (0.2, 0.1, 0.1, 0.15, 0.1, 0.35)
TEST_SEED_BASE = 10**9


@dataclass
class RandomScene:
    """One random scene: height map, mask, albedo and how to light / render it.

    Attributes:
        height: (H, W) float64 height (normalised image units), 0 outside.
        mask: (H, W) bool.
        albedo: (H, W, 3) float32 RGB in [0.05, 1].
        depth: (H, W) float32 scene-unit depth (``d0 - HALF_EXTENT * height``), 0 outside.
        camera_kind: "orthographic" or "perspective".
        material: a :class:`gpps.material.Material`.
        family: the shape family.
        info: the random choices (for the data recipe log).
        parts: (H, W) int32 surface piece of each pixel (-1 outside), or None for one piece: the
            composed families' z-buffer owners.  Normals are differenced within a piece only, so an
            occlusion boundary (a depth jump) gets each side's own one-sided normal.
    """

    height: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    depth: np.ndarray
    camera_kind: str
    material: Material
    family: str
    info: dict = field(default_factory=dict)
    parts: np.ndarray | None = None

    @property
    def camera(self):
        return default_camera(self.camera_kind, self.mask.shape)

    def relative_height(self) -> np.ndarray:
        """The network's depth target: ``H - mean_mask(H)``, 0 outside the mask (float32)."""
        h = np.where(self.mask, self.height - self.height[self.mask].mean(), 0.0)
        return h.astype(np.float32)


def _grid(size):
    h, w = (size, size) if np.isscalar(size) else size
    s = 0.5 * max(h, w)
    X = (np.arange(w) - (w - 1) / 2) / s
    Y = -(np.arange(h) - (h - 1) / 2) / s
    return np.meshgrid(X, Y)


def _rotate(X, Y, rng):
    a = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(a), np.sin(a)
    return c * X - s * Y, s * X + c * Y


def _region(X, Y, rng):
    """A random region: full frame, ellipse or super-ellipse."""
    kind = rng.choice(["full", "ellipse", "superellipse"], p=[0.2, 0.5, 0.3])
    if kind == "full":
        return np.ones(X.shape, bool), kind
    Xr, Yr = _rotate(X - rng.uniform(-0.1, 0.1), Y - rng.uniform(-0.1, 0.1), rng)
    a, b = rng.uniform(0.55, 0.95, 2)
    p = 2.0 if kind == "ellipse" else rng.uniform(3.0, 6.0)
    return (np.abs(Xr / a) ** p + np.abs(Yr / b) ** p) < 1.0, kind


def _heightfield(X, Y, rng):
    hgt = np.zeros_like(X)
    k = rng.integers(2, 9)
    for _ in range(k):
        c = rng.uniform(-0.8, 0.8, 2)
        s = rng.uniform(0.08, 0.45)
        a = rng.uniform(0.05, 0.45) * rng.choice([-1.0, 1.0], p=[0.3, 0.7])
        hgt += a * np.exp(-((X - c[0]) ** 2 + (Y - c[1]) ** 2) / (2 * s * s))
    if rng.random() < 0.4:  # low ripple
        kk = rng.normal(0, 6.0, 2)
        hgt += rng.uniform(0.005, 0.03) * np.sin(kk[0] * X + kk[1] * Y + rng.uniform(0, 2 * np.pi))
    if rng.random() < 0.3:  # global tilt / curvature
        hgt += rng.uniform(-0.2, 0.2) * X + rng.uniform(-0.2, 0.2) * Y - rng.uniform(0, 0.3) * (X * X + Y * Y)
    mask, kind = _region(X, Y, rng)
    return hgt, mask, {"bumps": int(k), "region": kind}


def _revolution(X, Y, rng):
    if rng.random() < 0.5:
        # about an axis in the image plane (a vase seen from the side), random axis angle
        Xr, Yr = _rotate(X, Y, rng) if rng.random() < 0.5 else (X, Y)
        y0, y1 = -rng.uniform(0.6, 0.95), rng.uniform(0.6, 0.95)
        r0 = rng.uniform(0.25, 0.6)
        R = np.full_like(Yr, r0)
        for _ in range(rng.integers(1, 4)):
            R += rng.uniform(0.03, 0.15) * np.sin(rng.uniform(1.0, 7.0) * Yr + rng.uniform(0, 2 * np.pi))
        R = np.clip(R, 0.12, 0.9)
        q = R * R - Xr * Xr
        depth_scale = rng.uniform(0.5, 1.0)
        mask = (q > (0.2 * R) ** 2) & (Yr > y0) & (Yr < y1)
        hgt = depth_scale * np.sqrt(np.maximum(q, 0.0))
        return hgt, mask, {"axis": "image-plane", "r0": float(r0)}
    # about the view axis: a radial profile f(r)
    cx, cy = rng.uniform(-0.15, 0.15, 2)
    r = np.sqrt((X - cx) ** 2 + (Y - cy) ** 2)
    rmax = rng.uniform(0.6, 0.95)
    kind = rng.choice(["dome", "ring", "cone", "steps"])
    t = r / rmax
    if kind == "dome":
        hgt = rng.uniform(0.3, 0.9) * rmax * np.sqrt(np.maximum(1 - t * t, 0.0))
        mask = t < 0.97
    elif kind == "ring":
        r1, s = rng.uniform(0.3, 0.7), rng.uniform(0.08, 0.2)
        hgt = rng.uniform(0.1, 0.4) * np.exp(-((t - r1) ** 2) / (2 * s * s))
        mask = t < 1.0
    elif kind == "cone":
        hgt = rng.uniform(0.2, 0.6) * rmax * np.sqrt(1e-3 + (1 - np.minimum(t, 1.0)) ** 2) * (1 - 0.5 * t)
        mask = t < 1.0
    else:
        hgt = np.zeros_like(t)
        for _ in range(rng.integers(2, 4)):
            hgt += rng.uniform(0.05, 0.15) / (1 + np.exp((t - rng.uniform(0.2, 0.9)) / 0.04))
        mask = t < 1.0
    return hgt, mask, {"axis": "view", "profile": str(kind)}


def _blobs(X, Y, rng):
    m = int(rng.integers(1, 7))
    k = rng.uniform(0.03, 0.08)  # smooth-union width
    acc = np.zeros_like(X)
    inside = np.zeros(X.shape, bool)
    for _ in range(m):
        c = rng.uniform(-0.55, 0.55, 2)
        r = rng.uniform(0.2, 0.6)
        sq = r * r - (X - c[0]) ** 2 - (Y - c[1]) ** 2
        ok = sq > (0.25 * r) ** 2
        hz = rng.uniform(-0.2, 0.2) + np.sqrt(np.maximum(sq, 0.0))
        acc += np.where(ok, np.exp(hz / k), 0.0)
        inside |= ok
    hgt = np.where(inside, k * np.log(np.maximum(acc, 1e-300)), 0.0)
    return hgt, inside, {"spheres": m}


# --------------------------------------------------------------------------- composed families (recipe v2)
# Primitives return ``(height, inside)``: the visible (front) surface of a solid as a height map over its
# silhouette.  A composition keeps, per pixel, the primitive nearest the camera (a z-buffer), so parts occlude
# each other with real depth jumps, and records which primitive owns the pixel (``parts``).


def _rotation3(rng) -> np.ndarray:
    """A uniformly random 3D rotation matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _superellipsoid(X, Y, rng, c, r, base):
    """Front surface of ``|x/a|^p + |y/b|^p + |z/c|^q = 1`` (domes, pills, cushions, near-boxes), in-plane rotated."""
    Xr, Yr = _rotate(X - c[0], Y - c[1], rng)
    a, b = r * rng.uniform(0.55, 1.0, 2)
    p = rng.choice([2.0, rng.uniform(1.5, 8.0)])
    t = np.abs(Xr / a) ** p + np.abs(Yr / b) ** p
    q = rng.choice([2.0, rng.uniform(1.5, 6.0)])
    cz = rng.uniform(0.35, 1.0) * min(a, b)
    return base + cz * np.maximum(1.0 - t, 0.0) ** (1.0 / q), t < 1.0


def _box(X, Y, rng, c, r, base):
    """Front surface of a box of random size and 3D orientation: the lowest of its upper faces over the
    silhouette where the upper faces lie above the lower ones (planar facets meeting at creases)."""
    R = _rotation3(rng)
    s = r * rng.uniform(0.3, 0.8, 3)
    c3 = np.array([c[0], c[1], base + 0.6 * r])
    top = np.full(X.shape, np.inf)
    bot = np.full(X.shape, -np.inf)
    inside = np.ones(X.shape, bool)
    for k in range(3):
        for sign in (1.0, -1.0):
            n = sign * R[:, k]
            rhs = n @ c3 + s[k] - n[0] * X - n[1] * Y
            if abs(n[2]) < 1e-6:
                inside &= rhs >= 0
            elif n[2] > 0:
                top = np.minimum(top, rhs / n[2])
            else:
                bot = np.maximum(bot, rhs / n[2])
    inside &= top > bot
    return np.where(inside, top, 0.0), inside


def _torus(X, Y, rng, c, r, base):
    """Front surface of a torus lying on its side (an ellipse in the image: a tilted ring)."""
    Xr, Yr = _rotate(X - c[0], Y - c[1], rng)
    e = rng.uniform(0.5, 1.0)
    rho = np.sqrt(Xr**2 + (Yr / e) ** 2)
    rt = r * rng.uniform(0.2, 0.4)
    R = r - rt
    q = rt**2 - (rho - R) ** 2
    return base + rt + np.sqrt(np.maximum(q, 0.0)), q > 0


def _cylinder(X, Y, rng, c, r, base):
    """Front surface of a cylinder lying down (length ``2 r L``), optionally with rounded ends."""
    Xr, Yr = _rotate(X - c[0], Y - c[1], rng)
    rc = r * rng.uniform(0.25, 0.55)
    L = r * rng.uniform(0.6, 1.0)
    q = rc**2 - Xr**2
    if rng.random() < 0.5:  # a capsule: hemispherical ends
        dy = np.maximum(np.abs(Yr) - L, 0.0)
        q = rc**2 - Xr**2 - dy**2
        inside = q > 0
    else:
        inside = (q > 0) & (np.abs(Yr) < L)
    return base + rc + np.sqrt(np.maximum(q, 0.0)), inside


PRIMITIVES = {"superellipsoid": _superellipsoid, "box": _box, "torus": _torus, "cylinder": _cylinder}


def _compose(X, Y, rng, items, hgt=None, inside=None, parts=None):
    """z-buffer union of ``items`` ((name, centre, size, base) each) onto an optional support."""
    if hgt is None:
        hgt = np.full(X.shape, -np.inf)
        inside = np.zeros(X.shape, bool)
        parts = np.full(X.shape, -1, np.int32)
    names = []
    for name, c, r, base in items:
        h, m = PRIMITIVES[name](X, Y, rng, c, r, base)
        m = m & np.isfinite(h)
        front = m & (~inside | (h > hgt))
        hgt = np.where(front, h, hgt)
        parts = np.where(front, int(parts.max()) + 1, parts)
        inside |= m
        names.append(name)
    return np.where(inside, hgt, 0.0), inside, parts, names


def _primitive_name(rng) -> str:
    return str(rng.choice(list(PRIMITIVES), p=[0.4, 0.3, 0.15, 0.15]))


def _solids(X, Y, rng):
    """One to four primitives of random kind, size and place, occluding each other (no support)."""
    k = int(rng.integers(1, 5))
    items = []
    for _ in range(k):
        r = rng.uniform(0.25, 0.75) if k == 1 else rng.uniform(0.2, 0.55)
        items.append((_primitive_name(rng), rng.uniform(-0.5, 0.5, 2), r, rng.uniform(-0.3, 0.3)))
    hgt, inside, parts, names = _compose(X, Y, rng, items)
    return hgt, inside, {"primitives": names}, parts


def _tabletop(X, Y, rng):
    """Objects standing on a tilted support (a table, a wall or a disc behind them): the support fills the
    frame, a disc or a rotated rectangle; each object sits at the support's height under its centre, so
    parts of it hide the support and cast shadows on it."""
    gx, gy = rng.normal(0, 0.25, 2)
    g0 = rng.uniform(-0.6, -0.2)
    plane = g0 + gx * X + gy * Y
    kind = str(rng.choice(["full", "disc", "rect"], p=[0.45, 0.35, 0.2]))
    if kind == "full":
        sup = np.ones(X.shape, bool)
    elif kind == "disc":
        Xr, Yr = _rotate(X - rng.uniform(-0.1, 0.1), Y - rng.uniform(-0.1, 0.1), rng)
        a = rng.uniform(0.8, 1.2)
        sup = (Xr / a) ** 2 + (Yr / (a * rng.uniform(0.7, 1.0))) ** 2 < 1
    else:
        Xr, Yr = _rotate(X, Y, rng)
        sup = (np.abs(Xr) < rng.uniform(0.7, 1.1)) & (np.abs(Yr) < rng.uniform(0.6, 1.1))
    hgt = np.where(sup, plane, -np.inf)
    parts = np.where(sup, 0, -1).astype(np.int32)
    k = int(rng.integers(1, 5))
    items = []
    for _ in range(k):
        c = rng.uniform(-0.6, 0.6, 2)
        r = rng.uniform(0.3, 0.7) if k == 1 else rng.uniform(0.15, 0.5)
        base = g0 + gx * c[0] + gy * c[1] - rng.uniform(0.0, 0.1) * r
        items.append((_primitive_name(rng), c, r, base))
    hgt, inside, parts, names = _compose(X, Y, rng, items, hgt, sup.copy(), parts)
    return hgt, inside, {"support": kind, "primitives": names}, parts


def _relief(X, Y, rng):
    """A relief on a plane or a low dome (coins, embossed paper, carvings): terraces, strokes, ridges or a
    raised rim, with steep but continuous walls."""
    base = rng.uniform(-0.15, 0.15) * X + rng.uniform(-0.15, 0.15) * Y
    if rng.random() < 0.4:
        base = base + rng.uniform(0.1, 0.5) * np.sqrt(np.maximum(1.2 - X * X - Y * Y, 0.0))
    kind = str(rng.choice(["terraces", "strokes", "ridges", "rim"]))
    if kind == "terraces":
        f = _smooth_noise(X.shape, rng, rng.uniform(10, 40)).astype(np.float64)
        levels = int(rng.integers(2, 6))
        wall = rng.uniform(0.02, 0.12)  # wall width, in noise units
        t = f * levels
        feat = (np.floor(t) + 1.0 / (1.0 + np.exp(-(t - np.floor(t) - 0.5) / wall))) / levels
        feat = rng.uniform(0.05, 0.2) * feat
    elif kind == "strokes":
        feat = np.zeros_like(X)
        for _ in range(int(rng.integers(3, 12))):
            p0, p1 = rng.uniform(-0.8, 0.8, 2), rng.uniform(-0.8, 0.8, 2)
            d = p1 - p0
            t = np.clip(((X - p0[0]) * d[0] + (Y - p0[1]) * d[1]) / max(d @ d, 1e-9), 0, 1)
            dist2 = (X - p0[0] - t * d[0]) ** 2 + (Y - p0[1] - t * d[1]) ** 2
            w = rng.uniform(0.015, 0.06)
            feat += rng.uniform(0.02, 0.08) * rng.choice([-1.0, 1.0], p=[0.3, 0.7]) * np.exp(-dist2 / (2 * w * w))
    elif kind == "ridges":
        Xr, Yr = _rotate(X, Y, rng)
        k = rng.uniform(6, 25)
        feat = rng.uniform(0.02, 0.08) * np.sin(k * Xr + rng.uniform(0.5, 2.0) * np.sin(rng.uniform(1, 4) * Yr))
    else:
        rr = np.sqrt(X * X + Y * Y)
        r0 = rng.uniform(0.6, 0.9)
        feat = rng.uniform(0.04, 0.12) / (1 + np.exp((np.abs(rr - r0) - 0.05) / 0.015))
        feat += rng.uniform(0.02, 0.08) * np.exp(-((X - rng.uniform(-0.3, 0.3)) ** 2 + (Y - rng.uniform(-0.3, 0.3)) ** 2) / 0.08)
    mask, region = _region(X, Y, rng)
    return base + feat, mask, {"relief": kind, "region": region}


def random_shape(size, rng, family: str | None = None):
    """A random height map ``(height, mask, family, info, parts)`` on an image of ``size`` (``parts``: (H, W)
    int32 surface pieces of the composed families, -1 outside; None for one piece)."""
    X, Y = _grid(size)
    fam = family or str(rng.choice(SHAPE_FAMILIES, p=FAMILY_P))
    fn = {"heightfield": _heightfield, "revolution": _revolution, "blobs": _blobs, "solids": _solids,
          "tabletop": _tabletop, "relief": _relief}[fam]
    for _ in range(20):
        out = fn(X, Y, rng)
        hgt, mask, info = out[:3]
        parts = out[3] if len(out) > 3 else None
        if mask.sum() > 0.08 * mask.size:
            break
    hgt = np.where(mask, hgt, 0.0)
    if parts is not None:
        parts = np.where(mask, parts, -1).astype(np.int32)
    return hgt, mask, fam, info, parts


def _smooth_noise(shape, rng, scale):
    import cv2

    h, w = shape
    gh, gw = max(2, int(h / scale)), max(2, int(w / scale))
    g = rng.normal(0, 1, (gh, gw)).astype(np.float32)
    return cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)


def random_albedo(shape, rng):
    """A random RGB albedo texture (H, W, 3) in [0.05, 1] and its family name."""
    h, w = shape
    kind = str(rng.choice(["uniform", "noise", "cells", "stripes", "mixed"], p=[0.3, 0.25, 0.2, 0.1, 0.15]))
    base = rng.uniform(0.25, 0.9, 3)
    if rng.random() < 0.35:  # grey objects (plaster, faces in grey images)
        base[:] = base[0]
    if kind == "uniform":
        a = np.broadcast_to(base, (h, w, 3)).copy()
    elif kind == "noise":
        a = base + rng.uniform(0.05, 0.3) * np.stack([_smooth_noise(shape, rng, rng.uniform(4, 32)) for _ in range(3)], -1)
    elif kind == "cells":
        import cv2

        n = int(rng.integers(3, 20))
        lab = _smooth_noise(shape, rng, rng.uniform(6, 30))
        edges = np.quantile(lab, np.linspace(0, 1, n + 1)[1:-1])
        idx = np.digitize(lab, edges)
        cols = rng.uniform(0.1, 0.95, (n, 3))
        a = cols[idx]
        a = cv2.GaussianBlur(a.astype(np.float32), (0, 0), 0.7)
    elif kind == "stripes":
        X, Y = _grid(shape)
        f = rng.uniform(3, 25)
        t = np.sin(f * (np.cos(rng.uniform(0, np.pi)) * X + np.sin(rng.uniform(0, np.pi)) * Y)) > 0
        c2 = rng.uniform(0.1, 0.95, 3)
        a = np.where(t[..., None], base, c2)
    else:
        a = base * (1 + 0.3 * _smooth_noise(shape, rng, rng.uniform(8, 40))[..., None])
        a = a + rng.uniform(0.0, 0.1) * rng.normal(0, 1, (h, w, 3))
    if rng.random() < 0.35:
        a = np.repeat(a.mean(-1, keepdims=True), 3, -1)
    return np.clip(a, 0.05, 1.0).astype(np.float32), kind


def random_material(rng) -> Material:
    """A random reflectance: the seed's five models and the dielectric ``plastic`` (Fresnel coating over a
    diffuse base, index 1.3-1.8, the common material of real objects), Lambertian a fifth of the time."""
    brdf = str(rng.choice(BRDF_CHOICES, p=BRDF_P))
    if brdf == "lambertian":
        return Material("lambertian", ks=0.0)
    if brdf == "plastic":
        return Material.from_ior("plastic", float(rng.uniform(1.3, 1.8)), ks=float(rng.uniform(0.5, 1.0)),
                                 roughness=float(rng.uniform(0.05, 0.5)))
    return Material(
        brdf,
        ks=float(rng.uniform(0.05, 0.9)),
        shininess=float(rng.uniform(5.0, 200.0)),
        roughness=float(rng.uniform(0.05, 0.5)),
        f0=float(rng.uniform(0.1, 0.9)),
        eta_u=float(rng.uniform(5.0, 200.0)),
        eta_v=float(rng.uniform(5.0, 200.0)),
    )


def random_direction(rng, max_slant_deg: float = 60.0) -> np.ndarray:
    """A unit vector toward a light, slant (from the view axis) uniform in [0, max_slant]."""
    s = np.deg2rad(rng.uniform(0.0, max_slant_deg))
    a = rng.uniform(0, 2 * np.pi)
    return np.array([np.sin(s) * np.cos(a), np.sin(s) * np.sin(a), np.cos(s)])


def random_light(rng, n: int = 1, kind: str | None = None, d0: float = D0):
    """``n`` random lights of one kind (directional 70 %, point 30 %) with slightly tinted colours."""
    from gpps.lights import DirectionalLights, PointLights

    kind = kind or str(rng.choice(["directional", "point"], p=[0.7, 0.3]))
    dirs = np.stack([random_direction(rng) for _ in range(n)])
    tint = 1.0 + rng.uniform(-0.15, 0.15, (n, 3))
    if kind == "directional":
        return DirectionalLights(dirs, rng.uniform(0.6, 1.0, (n, 1)) * tint)
    dist = rng.uniform(1.5, 4.0, (n, 1)) * d0
    pos = dirs * dist + np.array([0.0, 0.0, -d0])
    return PointLights(pos, rng.uniform(0.6, 1.0, (n, 1)) * tint * dist**2)


def random_scene(size, seed: int, *, family: str | None = None) -> RandomScene:
    """The random scene of ``seed`` (shape, albedo, material, camera) on an image of ``size``."""
    rng = np.random.default_rng(seed)
    hgt, mask, fam, info, parts = random_shape(size, rng, family)
    albedo, akind = random_albedo(mask.shape, rng)
    if parts is not None and parts.max() > 0 and rng.random() < 0.7:  # the objects in other colours than the support
        second, _ = random_albedo(mask.shape, rng)
        albedo = np.where((parts > 0)[..., None], second, albedo)
    albedo[~mask] = 0.0
    material = random_material(rng)
    cam = "orthographic" if rng.random() < 0.5 else "perspective"
    depth = np.where(mask, D0 - HALF_EXTENT * hgt, 0.0).astype(np.float32)
    info = dict(info, albedo=akind, seed=int(seed))
    return RandomScene(hgt, mask, albedo, depth, cam, material, fam, info, parts)


class SceneRenderer:
    """Renders :class:`RandomScene` s with gpps's Warp :class:`~gpps.pipeline.render.Renderer`.

    One renderer per (image size, camera kind) is kept and re-used (lights and
    material are swapped per scene), so thousands of scenes cost one allocation.
    """

    def __init__(self, device=None):
        self.device = device
        self._r: dict = {}

    def _renderer(self, scene: RandomScene, lights):
        from gpps.pipeline.render import Renderer

        key = (scene.mask.shape, scene.camera_kind, len(lights))
        r = self._r.get(key)
        if r is None:
            r = self._r[key] = Renderer(scene.mask.shape, scene.camera, lights, scene.material, device=self.device)
        else:
            r.set_lights(lights)
            r.set_material(scene.material)
        return r

    def normals(self, scene: RandomScene) -> np.ndarray:
        """Ground-truth unit normals (H, W, 3) of the depth map as the scene's camera sees it, differenced
        within each surface piece (:attr:`RandomScene.parts`): one-sided at occlusion boundaries."""
        from gpps.lights import DirectionalLights

        r = self._renderer(scene, DirectionalLights(np.array([[0.0, 0.0, 1.0]])))
        if scene.parts is None:
            n = r.normals_from_depth(scene.depth, scene.mask).copy()
        else:
            n = np.zeros(scene.mask.shape + (3,), np.float32)
            for k in np.unique(scene.parts[scene.mask]):
                piece = scene.parts == k
                nk = r.normals_from_depth(np.where(piece, scene.depth, 1.0).astype(np.float32), piece)
                n[piece] = nk[piece]
        n[~scene.mask] = 0.0
        return n

    def shadows(self, scene: RandomScene, lights) -> np.ndarray:
        """(N, H, W) bool visibility of each light over the scene's depth map (cast shadows;
        :class:`gpps.pipeline.shadows.CastShadows`)."""
        from gpps.pipeline.shadows import CastShadows

        n = len(lights)
        with CastShadows((n,) + scene.mask.shape, scene.camera, lights, device=self.device) as cs:
            return cs.run(scene.depth, scene.mask)

    def render(self, scene: RandomScene, lights, normals: np.ndarray, *, rng=None, noise: float = 0.0,
               ambient: float = 0.0, bits: int | None = None, shadows: bool = False, exposure: float = 1.0) -> np.ndarray:
        """(N, H, W, 3) float32 images: the model (times each light's cast-shadow visibility with ``shadows``),
        plus an indirect term ``ambient * albedo * (0.5 + 0.5 n_z)`` (light bounced from the surroundings: it
        fills shadows as in physically based renders), times ``exposure``, Gaussian noise, quantisation."""
        from gpps.pipeline.render import quantise

        r = self._renderer(scene, lights)
        img = r.run(scene.depth, scene.mask, scene.albedo, normals=normals)
        if shadows:
            img = img * self.shadows(scene, lights)[..., None]
        if ambient > 0:
            img = img + (ambient * scene.albedo * (0.5 + 0.5 * normals[..., 2:3]))[None]
        img = img * exposure
        if noise > 0:
            rng = rng or np.random.default_rng(0)
            img = img + rng.normal(0.0, noise, img.shape).astype(np.float32)
        img[:, ~scene.mask] = 0.0
        return quantise(np.maximum(img, 0.0).astype(np.float32), bits) if bits else np.maximum(img, 0.0).astype(np.float32)


def render_random_sample(size, seed: int, renderer: SceneRenderer, *, n_lights: int = 1, family: str | None = None,
                         light_kind: str | None = None, scene: RandomScene | None = None):
    """The recipe's sample of ``seed``: (scene, normals, images (N, H, W, 3), lights).

    Cast shadows with probability 0.85; noise: with probability 0.7 Gaussian of sigma U(0, 0.02); 8-bit
    quantisation with probability 0.5; an indirect term U(0.01, 0.12) x albedo with probability 0.6; an
    exposure U(0.7, 1.6) (values above 1 clip, as saturated highlights do, when quantised).
    ``scene``: the already drawn ``random_scene(size, seed, family=family)`` (drawn here when None).
    """
    if scene is None:
        scene = random_scene(size, seed, family=family)
    rng = np.random.default_rng([seed, 1])
    lights = random_light(rng, n_lights, light_kind)
    normals = renderer.normals(scene)
    noise = float(rng.uniform(0, 0.02)) if rng.random() < 0.7 else 0.0
    ambient = float(rng.uniform(0.01, 0.12)) if rng.random() < 0.6 else 0.0
    bits = 8 if rng.random() < 0.5 else None
    shadows = bool(rng.random() < 0.85)
    exposure = float(np.exp(rng.uniform(np.log(0.7), np.log(1.6))))
    images = renderer.render(scene, lights, normals, rng=rng, noise=noise, ambient=ambient, bits=bits, shadows=shadows,
                             exposure=exposure)
    scene.info.update(noise=noise, ambient=ambient, bits=bits, lights=lights.kind, brdf=scene.material.brdf,
                      camera=scene.camera_kind, shadows=shadows, exposure=exposure)
    return scene, normals, images, lights
