"""Per-observation values of a frame's masked pixels, image by image (host numpy).

The input checks (:func:`gpps.flows.photometric.check_observations`) and the solver's upload
(:meth:`gpps.pipeline.solver.PixelSolver.upload`) both read the grey values of the mask's pixels.  Indexing the
(N, H, W, 3) stack by the mask costs ~10x a pass over each image's whole frame (in cache) followed by a gather of
the mask's pixels, which is what :func:`masked_grey` does.  A caller that has the mask's observations gathered
per image and channel (:func:`gather_masked`, which the clipping detection reads too) takes them from there
(:func:`grey_peak`): the same values from P-long rows instead of whole frames.
"""

from __future__ import annotations

import numpy as np

__all__ = ["masked_grey", "gather_masked", "grey_peak", "noise_selection"]


def masked_grey(img: np.ndarray, mask: np.ndarray, *, idx: np.ndarray | None = None, peak: bool = False):
    """The mask's grey values (and optionally brightest channels) of (N, H, W, 3) float images.

    Args:
        img: (N, H, W, 3) float32 or float64 images.
        mask: (H, W) bool.
        idx: ``np.flatnonzero(mask)`` when the caller has it.
        peak: also return the max over the channels.

    Returns:
        (N, P) ``img.mean(axis=-1)[:, mask]`` bit for bit (numpy's mean over the channel axis sums left to right,
        then divides by 3; tests/test_host_overheads.py pins it), in the images' dtype; with ``peak`` the pair
        ``(grey, img.max(axis=-1)[:, mask])``.
    """
    n, h, w = img.shape[:3]
    idx = np.flatnonzero(mask) if idx is None else idx
    grey = np.empty((n, idx.size), img.dtype)
    top = np.empty((n, idx.size), img.dtype) if peak else None
    tmp = np.empty(h * w, img.dtype)
    for k in range(n):
        a = img[k].reshape(h * w, 3)
        np.add(a[:, 0], a[:, 1], out=tmp)
        tmp += a[:, 2]
        tmp /= 3
        np.take(tmp, idx, out=grey[k])
        if peak:
            np.maximum(a[:, 0], a[:, 1], out=tmp)
            np.maximum(tmp, a[:, 2], out=tmp)
            np.take(tmp, idx, out=top[k])
    return (grey, top) if peak else grey


def gather_masked(img: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """The observations of the pixels ``idx`` of (N, H, W, C) images, contiguous per image and channel.

    Args:
        img: (N, H, W, C) images (any dtype: floats are kept, others read as float32).
        idx: (P,) flat pixel indices into H * W (``np.flatnonzero(mask)``).

    Returns:
        (N, C, P) array: reductions over P run at memory speed.  Each image's pixel rows of C values come in one
        gather, then are transposed (2x faster than C strided gathers).
    """
    n, h, w, c = img.shape
    dtype = img.dtype if np.issubdtype(img.dtype, np.floating) else np.dtype(np.float32)
    x = np.empty((n, c, idx.size), dtype)
    for k in range(n):
        x[k] = np.take(img[k].reshape(h * w, c), idx, axis=0).T
    return x


def grey_peak(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The grey values and brightest channels of gathered RGB observations (:func:`gather_masked`).

    Args:
        x: (N, 3, P) float observations.

    Returns:
        ``(grey, peak)``: (N, P) each, :func:`masked_grey`'s values bit for bit (the channels summed left to right,
        then divided by 3, in the observations' dtype) and their max.
    """
    grey = x[:, 0] + x[:, 1]
    grey += x[:, 2]
    grey /= 3
    return grey, np.maximum(np.maximum(x[:, 0], x[:, 1]), x[:, 2])


def noise_selection(mask, *, max_pixels: int = 1 << 16):
    """The pixels :func:`gpps.pipeline.solver.estimate_noise` reads (and its device form,
    :class:`gpps.pipeline.noise.DeviceNoise`).

    Args:
        mask: (H, W) bool.
        max_pixels: about the most pixels an image.

    Returns:
        ``(rows, sel, c0, c1)``, or None when no pixel has its 3x3 neighbourhood in the mask: every ``st``-th row
        (about ``max_pixels`` pixels) with such pixels, as indices ``r`` whose neighbourhoods span image rows
        ``r .. r + 2`` (centre ``r + 1``); ``sel`` (R, c1 - c0 - 2) bool, the pixels of those rows whose
        neighbourhood lies in the mask, centre column ``c0 + 1 + c``; image columns ``c0 .. c1 - 1`` hold every
        such neighbourhood.
    """
    m = np.asarray(mask, bool)
    h, w = m.shape
    if h < 3 or w < 3:
        return None
    inner = m[1:-1, 1:-1].copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            inner &= m[1 + di : h - 1 + di, 1 + dj : w - 1 + dj]
    rows = np.nonzero(inner.any(axis=1))[0]
    if rows.size == 0:
        return None
    # every st-th row with inner pixels: about max_pixels pixels
    st = max(1, int(np.ceil(inner[rows].sum() / max_pixels)))
    rows = rows[::st]
    sel = inner[rows]  # (R, W - 2)
    cols = np.nonzero(sel.any(axis=0))[0]
    c0, c1 = int(cols[0]), int(cols[-1]) + 3  # image columns c0 .. c1 - 1 hold every 3x3 neighbourhood
    return rows, sel[:, c0 : c1 - 2], c0, c1
