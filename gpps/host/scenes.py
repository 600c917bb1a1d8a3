"""Synthetic scenes with exact ground truth (depth, normals, mask, albedo).

Every scene is an analytic surface in the gpps frame (see :mod:`gpps.camera`),
intersected exactly with the camera's pixel rays in float64: a sphere, or a
height field ``z = -d0 + h(x, y)`` whose normal ``(-h_x, -h_y, 1)/|.|`` comes from
the analytic gradient of ``h``, never from finite differences.

Scale: the object sits at depth ``d0 = 10`` units and fills about ``[-2.4, 2.4]^2``
units; the perspective camera's focal length is chosen so that both cameras
see the same extent.

* ``sphere``: radius 2 centred at (0, 0, -10).
* ``bumps``: five Gaussian bumps and dents on a plane, masked to a disc.
* ``microprint``: the seed's banknote case: text rasterised on a lattice of
  cells, each "on" cell a Gaussian of low amplitude; the whole frame is the mask.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Literal, get_args

import cv2
import numpy as np

from gpps._check import check_choice, check_number, check_shape
from gpps.camera import Orthographic, Perspective

SceneName = Literal["sphere", "bumps", "microprint"]
SCENE_NAMES: tuple[str, ...] = get_args(SceneName)
AlbedoKind = Literal["uniform", "texture"]

D0 = 10.0  # depth of the object's centre (scene units)
HALF_EXTENT = 2.4  # half-width of the field of view at depth D0 (scene units)
UNIFORM_ALBEDO = (0.6, 0.5, 0.4)

__all__ = ["Scene", "make_scene", "default_camera", "SCENE_NAMES", "HeightField"]


@dataclass
class Scene:
    """A synthetic scene with exact ground truth.

    Attributes:
        name: scene name.
        camera: the camera it was made for.
        mask: (H, W) bool, pixels that see the object.
        depth: (H, W) float32 depth (> 0) inside the mask, 0 outside.
        normals: (H, W, 3) float32 unit normals (gpps frame) inside, 0 outside.
        albedo: (H, W, 3) float32 RGB diffuse colour inside, 0 outside.
        points: (H, W, 3) float64 surface points (gpps frame), 0 outside.
        d0: nominal object depth (scene units).
    """

    name: str
    camera: object
    mask: np.ndarray
    depth: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    points: np.ndarray
    d0: float = D0
    info: dict = field(default_factory=dict)

    @property
    def shape(self) -> tuple[int, int]:
        return self.mask.shape


#: the largest side :func:`make_scene` takes (16384^2 pixels hold about 30 GB of scene arrays)
MAX_SCENE_SIDE = 16384

def default_camera(kind: Literal["orthographic", "perspective"], size: int | tuple[int, int]):
    """The camera that sees ``[-2.4, 2.4]^2`` units at depth 10 on an image of ``size``."""
    h, w = (size, size) if np.isscalar(size) else size
    if kind == "orthographic":
        return Orthographic(pixel_size=2 * HALF_EXTENT / max(h, w))
    if kind == "perspective":
        f = 0.5 * max(h, w) * D0 / HALF_EXTENT
        return Perspective(np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]]))
    raise ValueError(f"camera: expected 'orthographic' or 'perspective', got {kind!r}")


# --------------------------------------------------------------------------- height fields


@dataclass
class HeightField:
    """``z = -d0 + h(x, y)`` over the region ``inside(x, y)``.

    ``fn(x, y) -> (h, h_x, h_y)`` on flat float64 arrays.
    """

    fn: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]
    inside: Callable[[np.ndarray, np.ndarray], np.ndarray]
    d0: float = D0

    def intersect(self, origins: np.ndarray, dirs: np.ndarray, iters: int = 30):
        """Exact ray intersection (Newton on the ray parameter, float64).

        Returns:
            points (n, 3), normals (n, 3), ok (n,) bool.
        """
        o = origins.reshape(-1, 3)
        d = dirs.reshape(-1, 3)
        # start at the base plane z = -d0
        t = (-self.d0 - o[:, 2]) / d[:, 2]
        for _ in range(iters):
            p = o + t[:, None] * d
            h, hx, hy = self.fn(p[:, 0], p[:, 1])
            f = p[:, 2] + self.d0 - h
            df = d[:, 2] - hx * d[:, 0] - hy * d[:, 1]
            step = f / df
            t = t - step
            if np.max(np.abs(step)) < 1e-13 * self.d0:
                break
        p = o + t[:, None] * d
        h, hx, hy = self.fn(p[:, 0], p[:, 1])
        n = np.stack([-hx, -hy, np.ones_like(hx)], axis=1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        ok = self.inside(p[:, 0], p[:, 1]) & (np.abs(p[:, 2] + self.d0 - h) < 1e-9 * self.d0)
        return p, n, ok


def gaussian_bumps(centres, amplitudes, sigmas):
    """``h = sum_k a_k exp(-|x - c_k|^2 / (2 s_k^2))`` with its analytic gradient."""
    c = np.asarray(centres, float)
    a = np.asarray(amplitudes, float)
    s = np.asarray(sigmas, float)

    def fn(x, y):
        dx = x[:, None] - c[None, :, 0]
        dy = y[:, None] - c[None, :, 1]
        g = a * np.exp(-(dx**2 + dy**2) / (2 * s**2))
        return g.sum(1), (-dx / s**2 * g).sum(1), (-dy / s**2 * g).sum(1)

    return fn


def lattice_bumps(cells: np.ndarray, pitch: float, amplitude: float, sigma: float):
    """Gaussians of equal ``amplitude`` and ``sigma`` on the "on" cells of a raster.

    ``cells`` is (R, C) bool, row 0 at the top (largest y); the lattice is centred
    on x = y = 0 with spacing ``pitch``.  Separable: ``h = a gy(y)^T B gx(x)``.
    """
    B = np.asarray(cells, float)
    R, C = B.shape
    X = (np.arange(C) - (C - 1) / 2) * pitch
    Y = -(np.arange(R) - (R - 1) / 2) * pitch

    def fn(x, y):
        h = np.empty_like(x)
        hx = np.empty_like(x)
        hy = np.empty_like(x)
        for s in range(0, x.size, 1 << 15):
            xs, ys = x[s : s + (1 << 15)], y[s : s + (1 << 15)]
            dx = xs[:, None] - X[None]
            dy = ys[:, None] - Y[None]
            gx = np.exp(-(dx**2) / (2 * sigma**2))
            gy = np.exp(-(dy**2) / (2 * sigma**2))
            gxd = -dx / sigma**2 * gx
            gyd = -dy / sigma**2 * gy
            bx = gx @ B.T  # (n, R): sum over columns
            bxd = gxd @ B.T
            h[s : s + xs.size] = amplitude * np.sum(bx * gy, 1)
            hx[s : s + xs.size] = amplitude * np.sum(bxd * gy, 1)
            hy[s : s + xs.size] = amplitude * np.sum(bx * gyd, 1)
        return h, hx, hy

    return fn


def text_cells(text: str = "GPPS", height: int = 16) -> np.ndarray:
    """Rasterise ``text`` (OpenCV Hershey font) into a bool cell grid about ``height`` rows high."""

    scale = height / 22.0
    (tw, th), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    img = np.zeros((th + base + 4, tw + 4), np.uint8)
    cv2.putText(img, text, (2, th + 2), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 1, cv2.LINE_8)
    cells = img > 127
    rows = np.flatnonzero(cells.any(1))
    cols = np.flatnonzero(cells.any(0))
    return cells[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]


# --------------------------------------------------------------------------- albedo


def _albedo(kind: str, points: np.ndarray, mask: np.ndarray, seed: int) -> np.ndarray:
    h, w = mask.shape
    out = np.zeros((h, w, 3), np.float32)
    if kind == "uniform":
        out[mask] = UNIFORM_ALBEDO
        return out
    if kind != "texture":
        raise ValueError(f"albedo: expected 'uniform' or 'texture', got {kind!r}")
    rng = np.random.default_rng(seed)
    x, y = points[..., 0][mask], points[..., 1][mask]
    cols = []
    for c in range(3):
        v = np.zeros_like(x)
        for _ in range(4):
            k = rng.normal(0, 1.5, 2)
            v += np.sin(k[0] * x + k[1] * y + rng.uniform(0, 2 * np.pi))
        cols.append(0.55 + 0.25 * v / 4)
    out[mask] = np.clip(np.stack(cols, 1), 0.2, 0.9)
    return out


# --------------------------------------------------------------------------- scenes


def make_scene(
    name: SceneName = "sphere",
    size: int | tuple[int, int] = 256,
    camera: Literal["orthographic", "perspective"] | Orthographic | Perspective = "perspective",
    *,
    albedo: AlbedoKind = "uniform",
    seed: int = 0,
    text: str = "GPPS",
) -> Scene:
    """Make a synthetic scene with exact depth, normals and mask.

    Args:
        name: ``"sphere"``, ``"bumps"`` or ``"microprint"``.
        size: image size, an int (square) or (H, W); 8 to :data:`MAX_SCENE_SIDE` (16384) a side.
        camera: ``"orthographic"``, ``"perspective"`` (default cameras, see
            :func:`default_camera`) or a camera object.
        albedo: ``"uniform"`` (0.6, 0.5, 0.4) or ``"texture"`` (smooth random colours).
        seed: seed of the texture.
        text: the micro-print text.
    """
    check_choice("scene", name, SCENE_NAMES)
    try:  # (check_number: NaN, inf, strings and bools are errors naming size, not int()'s)
        h, w = (size, size) if np.isscalar(size) else check_shape("size", size, "HW")
        h, w = check_number("size", h, integer=True), check_number("size", w, integer=True)
    except (TypeError, ValueError):
        raise ValueError(f"size: expected an integer >= 8 or (H, W) of such, got {size!r}") from None
    if h < 8 or w < 8:
        raise ValueError(f"size: expected an integer >= 8 or (H, W) of such, got {size!r}")
    if h > MAX_SCENE_SIDE or w > MAX_SCENE_SIDE:
        # (a scene holds about 15 float64 values a pixel: 10**9 wide asked numpy for exabytes, a MemoryError)
        raise ValueError(f"size: expected at most {MAX_SCENE_SIDE} pixels a side, got {size!r}")
    seed = check_number("seed", seed, lo=0, integer=True)
    if not isinstance(text, str):
        raise TypeError(f"text: expected a non-empty string, got {text!r}")
    if name == "microprint" and not text.strip():
        raise ValueError(f"text: expected a non-empty string (the micro-print's text), got {text!r}")
    if isinstance(camera, str):
        camera = default_camera(camera, (h, w))
    if not isinstance(camera, (Orthographic, Perspective)):
        raise TypeError(f"camera: expected 'orthographic', 'perspective' or a camera object, got {camera!r}")
    check_choice("albedo", albedo, AlbedoKind)
    o, d = camera.rays((h, w))
    o = o.reshape(-1, 3)
    d = d.reshape(-1, 3)
    info: dict = {}
    if name == "sphere":
        c = np.array([0.0, 0.0, -D0])
        r = 2.0
        oc = o - c
        b = np.sum(oc * d, 1)
        disc = b * b - (np.sum(oc * oc, 1) - r * r)
        ok = disc > 0
        t = -b - np.sqrt(np.maximum(disc, 0))
        p = o + t[:, None] * d
        n = (p - c) / r
        # drop grazing pixels whose normal faces away from the ray
        ok &= np.sum(n * -d, 1) > 1e-3
        info.update(center=c.tolist(), radius=r)
    else:
        if name == "bumps":
            fn = gaussian_bumps(
                [(-0.9, 0.7), (0.8, 0.8), (0.0, -0.2), (-0.8, -1.0), (1.0, -0.9)],
                [0.45, -0.35, 0.6, 0.3, -0.4],
                [0.55, 0.5, 0.7, 0.45, 0.55],
            )
            hf = HeightField(fn, lambda x, y: x * x + y * y < 2.2**2)
        else:
            cells = text_cells(text)
            pitch = 4.2 / max(cells.shape[1], 1)
            fn = lattice_bumps(cells, pitch=pitch, amplitude=0.35 * pitch, sigma=0.7 * pitch)
            hf = HeightField(fn, lambda x, y: (np.abs(x) < 2.3) & (np.abs(y) < 2.3))
            info.update(text=text, pitch=pitch, amplitude=0.35 * pitch)
        p, n, ok = hf.intersect(o, d)
    mask = ok.reshape(h, w)
    points = np.where(ok[:, None], p, 0.0).reshape(h, w, 3)
    normals = np.where(ok[:, None], n, 0.0).reshape(h, w, 3).astype(np.float32)
    depth = np.where(mask, -points[..., 2], 0.0).astype(np.float32)
    if not mask.any():
        raise ValueError(f"size: the {name} scene sees no object at {(h, w)}")
    return Scene(
        name=name,
        camera=camera,
        mask=mask,
        depth=depth,
        normals=normals,
        albedo=_albedo(albedo, points, mask, seed),
        points=points,
        info=info,
    )
