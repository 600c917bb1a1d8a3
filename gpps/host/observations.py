"""Per-observation values of a frame's masked pixels, image by image (host numpy).

The input checks (:func:`gpps.flows.photometric.check_observations`) and the solver's upload
(:meth:`gpps.pipeline.solver.PixelSolver.upload`) both read the grey values of the mask's pixels.  Indexing the
(N, H, W, 3) stack by the mask costs ~10x a pass over each image's whole frame (in cache) followed by a gather of
the mask's pixels, which is what :func:`masked_grey` does.
"""

from __future__ import annotations

import numpy as np

__all__ = ["masked_grey"]


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
