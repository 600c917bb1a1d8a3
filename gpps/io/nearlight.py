"""Real near-light (LED) captures: the reader and a working-distance estimate.

The layout read here (``../shared/data/nearlight/hehe12``)::
    photometric_sample_raw_0001.png ... _000N.png   one image per LED (8-bit, paletted grey)
    photometric_sample_raw_ambient.png              all LEDs off
    photometric_sample_mask_raw.png                 object mask
    light.mat    S (N x 3) LED positions in mm, Phi (N x 1) radiant intensities,
                 Dir (N x 3) LED principal directions, mu (N x 1) anisotropy
    camera.mat   K (3 x 3), stored transposed ([[fx, 0, 0], [0, fy, 0], [cx, cy, 1]])

Frames.  ``light.mat`` is in the usual computer-vision camera frame (x right,
y down, z forward into the scene, origin at the camera centre): the LEDs sit
at z ~ +74 mm, in front of the camera centre, and their ``Dir`` point forward
(z > 0) and inward toward the optical axis.  The gpps frame is x right, y up,
z toward the camera (points in front have z < 0), so positions and axes are
converted by ``(x, y, z) -> (x, -y, -z)``.  The LED model is gpps's
``Phi * max(cos(angle(Dir, P - S)), 0)^mu / |P - S|^2`` (2.30-2.31).

Images.  Each LED image minus the ambient image (clipped at 0), divided by
``Phi_k / mean(Phi)`` (the LEDs' relative powers).  The returned
:class:`PointLights` carry the intensity ``D^2`` (mm^2) for every LED, ``D``
the distance the LEDs are aimed at (:func:`aim_distance`), so that
``intensity / r^2 * lobe * albedo * cos`` models the returned images with the
albedo in grey units (about the grey value of a frontal white patch at ``D``).
The albedo's absolute scale is arbitrary for photometric stereo, but the
material fit of :func:`gpps.reconstruct` searches ``ks`` over an absolute
range (0.02-3) that assumes albedos of order 0.1-1: with ``Phi`` itself as the
intensity (albedo ~ 0.003 here) every candidate specular weight would be
many times the diffuse one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.io import loadmat

from gpps._check import as_images, as_mask
from gpps.camera import Perspective
from gpps.io.files import _cv2
from gpps.lights import PointLights

__all__ = ["CV_TO_GPPS", "NearLightCapture", "aim_distance", "estimate_distance", "read_nearlight"]

# computer-vision camera frame (x right, y down, z forward) -> gpps frame (x right, y up, z toward the camera)
CV_TO_GPPS = np.array([1.0, -1.0, -1.0])


@dataclass
class NearLightCapture:
    """A near-light capture as read by :func:`read_nearlight`.

    Attributes:
        images: (N, H, W) float32 grey images (ambient subtracted, divided by
            ``phi / mean(phi)``).  The lights' intensity is ``working_distance^2``
            (see the module docstring).
        mask: (H, W) bool object mask.
        K: (3, 3) intrinsics (pixels, gpps convention ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``),
            scaled for ``downsample`` and shifted for ``crop``.
        camera: :class:`Perspective` from ``K``.
        lights: :class:`PointLights` in the gpps frame (mm).
        phi: (N,) the LEDs' intensities as in ``light.mat``.
        working_distance: rough object distance (mm): where the LEDs' axes
            pass closest to the optical axis (:func:`aim_distance`); refine it
            with :func:`estimate_distance`.
        saturated: (N, H, W) bool: observations clipped in the file (255).
        downsample: the factor applied.
        crop: (row0, row1, col0, col1) in full-resolution pixels, or None.
        names: image file names.
    """

    images: np.ndarray
    mask: np.ndarray
    K: np.ndarray
    camera: Perspective
    lights: PointLights
    phi: np.ndarray
    working_distance: float
    saturated: np.ndarray
    downsample: int
    crop: tuple | None
    names: list


def _loadmat(path: Path) -> dict:
    if not path.is_file():
        raise FileNotFoundError(f"{path.name}: file not found: {path}")
    return {k: np.asarray(v) for k, v in loadmat(str(path)).items() if not k.startswith("__")}


def _block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over f x f blocks of the last two axes (trailing rows/columns dropped)."""
    h, w = a.shape[-2] // f * f, a.shape[-1] // f * f
    a = a[..., :h, :w]
    return a.reshape(a.shape[:-2] + (h // f, f, w // f, f)).mean(axis=(-3, -1))


def read_nearlight(root, *, downsample: int = 1, crop=None, prefix: str = "photometric_sample") -> NearLightCapture:
    """Read a near-light LED capture (see the module docstring for the layout and frames).

    Args:
        root: the capture's folder.
        downsample: integer factor: images are averaged over ``f x f`` blocks,
            the mask keeps blocks entirely inside the object, and K is scaled
            (pixel centres at integers: ``c' = (c - (f - 1) / 2) / f``, ``f' = f / downsample``).
        crop: optional ``(row0, row1, col0, col1)`` window in full-resolution
            pixels, applied before downsampling (K's principal point shifted).
        prefix: the file-name prefix of the images.

    Returns:
        :class:`NearLightCapture`.  ``working_distance`` is a rough start (the
        range the LEDs are aimed at, :func:`aim_distance`); the object's
        distance is better found by :func:`estimate_distance`.

    Raises:
        FileNotFoundError: missing files.
        ValueError: bad ``downsample`` / ``crop``, inconsistent shapes, or light
            and image counts that differ.
    """

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"root: capture folder not found: {root}")
    if int(downsample) != downsample or downsample < 1:
        raise ValueError(f"downsample: expected an integer >= 1, got {downsample!r}")
    f = int(downsample)
    light = _loadmat(root / "light.mat")
    cam = _loadmat(root / "camera.mat")
    for k in ("S", "Phi"):
        if k not in light:
            raise ValueError(f"light.mat: expected the variable {k}, got {sorted(light)}")
    S = light["S"].astype(np.float64)
    n = S.shape[0]
    if S.shape != (n, 3):
        raise ValueError(f"light.mat: expected S of shape (N, 3), got {S.shape}")
    phi = light["Phi"].astype(np.float64).reshape(-1)
    if phi.shape != (n,) or np.any(phi <= 0):
        raise ValueError(f"light.mat: expected {n} positive Phi, got {light['Phi'].ravel()}")
    axes = light["Dir"].astype(np.float64) if "Dir" in light else np.tile([0.0, 0.0, 1.0], (n, 1))
    mu = light["mu"].astype(np.float64).reshape(-1) if "mu" in light else np.zeros(n)
    if "K" not in cam:
        raise ValueError(f"camera.mat: expected the variable K, got {sorted(cam)}")
    K = cam["K"].astype(np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"camera.mat: expected K of shape (3, 3), got {K.shape}")
    if abs(K[2, 2] - 1) < 1e-9 and K[2, 0] != 0 and K[0, 2] == 0:
        K = K.T  # stored transposed
    K = K.copy()

    names = sorted(p.name for p in root.glob(f"{prefix}_raw_[0-9]*.png"))
    if len(names) != n:
        raise ValueError(f"root: expected {n} images {prefix}_raw_NNNN.png (one per LED in light.mat), got {len(names)}")
    cv2 = _cv2()

    def grey(p):  # paletted grey PNG (colour would be converted to luminance), floats in [0, 1]
        if not p.is_file():
            raise FileNotFoundError(f"{p.name}: file not found: {p}")
        im = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if im is None:
            raise ValueError(f"{p}: not a readable image")
        return im.astype(np.float32) / 255.0

    mask = grey(root / f"{prefix}_mask_raw.png") > 0.5
    h, w = mask.shape
    win = (slice(0, h), slice(0, w))
    if crop is not None:
        r0, r1, c0, c1 = (int(c) for c in crop)
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w):
            raise ValueError(f"crop: expected 0 <= row0 < row1 <= {h} and 0 <= col0 < col1 <= {w}, got {crop}")
        win = (slice(r0, r1), slice(c0, c1))
        if not mask[win].any():
            raise ValueError(f"crop: the window {crop} holds no object pixels")
        K[0, 2] -= c0
        K[1, 2] -= r0
        crop = (r0, r1, c0, c1)
    mask = mask[win]
    raw = np.stack([grey(root / nm)[win] for nm in names])
    if raw.shape[1:] != mask.shape:
        raise ValueError(f"root: images {raw.shape[1:]} and mask {mask.shape} differ in shape")
    amb_p = root / f"{prefix}_raw_ambient.png"
    ambient = grey(amb_p)[win] if amb_p.is_file() else np.zeros(mask.shape, np.float32)
    if ambient.shape != mask.shape:
        raise ValueError(f"root: ambient image {ambient.shape} and mask {mask.shape} differ in shape")
    sat = raw >= 1.0 - 0.5 / 255
    img = np.clip(raw - ambient[None], 0.0, None)
    img = img / (phi / phi.mean()).astype(np.float32)[:, None, None]
    if f > 1:
        img = _block_mean(img, f)
        sat = _block_mean(sat.astype(np.float32), f) > 0
        mask = _block_mean(mask.astype(np.float32), f) > 0.999
        K[0, 0] /= f
        K[1, 1] /= f
        K[0, 2] = (K[0, 2] - (f - 1) / 2) / f
        K[1, 2] = (K[1, 2] - (f - 1) / 2) / f
    if not mask.any():
        raise ValueError(f"downsample: no {f}x{f} block lies entirely inside the object mask")
    aim = aim_distance(S, axes)
    unit = aim**2 if np.isfinite(aim) else float(np.mean(np.abs(S[:, 2]))) ** 2
    lights = PointLights(S * CV_TO_GPPS, intensities=np.full(n, unit), axes=axes * CV_TO_GPPS, mu=mu)
    return NearLightCapture(
        images=img.astype(np.float32), mask=mask, K=K, camera=Perspective(K), lights=lights, phi=phi,
        working_distance=aim, saturated=sat, downsample=f, crop=crop,
        names=names,
    )


def aim_distance(positions, axes) -> float:
    """The distance the LEDs are aimed at: the median depth (along the optical axis) of
    the point of each LED's axis closest to the optical axis.

    Args:
        positions: (N, 3) LED positions, z along the optical axis (either sign convention).
        axes: (N, 3) LED principal directions in the same frame.

    Returns:
        The distance (positive, the positions' unit); NaN when no axis turns toward the optical axis.
    """
    S = np.asarray(positions, dtype=np.float64)
    D = np.asarray(axes, dtype=np.float64)
    D = D / np.linalg.norm(D, axis=1, keepdims=True)
    dxy = np.sum(D[:, :2] ** 2, 1)
    t = -np.sum(S[:, :2] * D[:, :2], 1) / np.maximum(dxy, 1e-12)
    ok = (t > 0) & (dxy > 1e-12)
    if not ok.any():
        return float("nan")
    return float(np.median(np.abs(S[ok, 2] + t[ok] * D[ok, 2])))


def estimate_distance(images, mask, camera, lights: PointLights, candidates, *, samples: int = 4000,
                      seed: int = 0) -> tuple[float, dict]:
    """The flat object distance whose Lambertian point-light fit explains the images best.

    For each candidate distance ``d`` every sampled pixel is put at depth ``d``,
    the LEDs' directions, falloff and lobes are computed there, and the
    pixel's scaled normal ``b = albedo * n`` is fitted by least squares to its
    N observations; the score is the relative residual
    ``sum |I - A b|^2 / sum |I|^2``.  Only the ratios between the LEDs'
    irradiances tell the distance (the albedo absorbs the absolute level), so
    this is a coarse estimate: it is meant to start :func:`gpps.reconstruct`'s
    depth loop, which then refines the shape.

    Args:
        images: (N, H, W) or (N, H, W, C) images (already scaled for ``lights.intensities``).
        mask: (H, W) bool.
        camera: :class:`Perspective`.
        lights: :class:`PointLights` (gpps frame, scene units).
        candidates: distances to try (scene units, > 0).
        samples: pixels sampled from the mask.
        seed: the sample's seed.

    Returns:
        ``(best distance, {distance: score})``.
    """

    img = as_images("images", images)
    if img.ndim == 4:
        img = img.mean(axis=-1)
    if img.ndim != 3:
        raise ValueError(f"images: expected shape (N, H, W) or (N, H, W, C), got {img.shape}")
    n, h, w = img.shape
    m = as_mask("mask", mask, (h, w))
    if not isinstance(lights, PointLights) or len(lights) != n:
        raise ValueError(f"lights: expected PointLights with {n} lights")
    cands = np.asarray(candidates, dtype=np.float64).reshape(-1)
    if cands.size == 0 or np.any(~np.isfinite(cands)) or np.any(cands <= 0):
        raise ValueError(f"candidates: expected distances > 0, got {candidates!r}")
    idx = np.flatnonzero(m.ravel())
    rng = np.random.default_rng(seed)
    idx = rng.choice(idx, min(samples, idx.size), replace=False)
    I = img.reshape(n, -1)[:, idx].T.astype(np.float64)  # (P, N)
    _, rays = camera.rays((h, w))
    rays = rays.reshape(-1, 3)[idx]
    rays = rays / (-rays[:, 2:3])  # points at depth 1
    pos, ax, mu = lights.positions, lights.axes, lights.mu
    e0 = lights.intensities.mean(axis=1)
    scores = {}
    for d in cands:
        P = rays * d  # (P, 3)
        L = pos[None] - P[:, None]  # (P, N, 3)
        r2 = np.sum(L * L, -1)
        Lh = L / np.sqrt(r2)[..., None]
        lobe = np.clip(np.sum(-Lh * ax[None], -1), 0.0, None) ** mu[None]
        A = (e0[None] * lobe / r2)[..., None] * Lh  # (P, N, 3)
        AtA = np.einsum("pni,pnj->pij", A, A)
        Atb = np.einsum("pni,pn->pi", A, I)
        b = np.linalg.solve(AtA + 1e-12 * np.trace(AtA, axis1=1, axis2=2)[:, None, None] * np.eye(3), Atb[..., None])[..., 0]
        res = I - np.einsum("pni,pi->pn", A, b)
        scores[float(d)] = float(np.sum(res * res) / np.sum(I * I))
    best = min(scores, key=scores.get)
    return best, scores
