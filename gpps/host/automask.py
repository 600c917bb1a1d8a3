"""Automatic object mask from the photometric-stereo images themselves.

A pixel belongs to the object when it is *lit in enough images*: the object
reflects every light that faces it, while the background (far, dark or matte
black) stays dark in nearly all of them.  For each image the "lit" level is a
fraction of that image's bright level (its 99th percentile), so lights of
different strengths count alike.  The lit pixels are then cleaned: a small
opening removes speckle (noise, dust), only the largest connected components
are kept (those at least ``min_component`` times the largest), and holes are
filled (pupils, dark spots and cast-shadowed pockets are part of the object;
the solvers drop their dark observations themselves).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from gpps._check import as_array

__all__ = ["AutoMaskConfig", "automatic_mask", "lit_pixels"]


@dataclass(frozen=True)
class AutoMaskConfig:
    """Options of :func:`automatic_mask`.

    Attributes:
        level: a pixel is lit in an image when its grey value exceeds this
            fraction of the image's 99th percentile.
        fraction: ... in at least this fraction of the images (an object
            point sees about half of a hemisphere of lights; the rim less).
        min_component: keep connected components with at least this fraction
            of the largest one's pixels.
        opening: radius (pixels) of the opening that removes speckle; 0: none.
        fill_holes: fill the holes of the kept components.
    """

    level: float = 0.1
    fraction: float = 0.25
    min_component: float = 0.2
    opening: int = 1
    fill_holes: bool = True

    def __post_init__(self):
        if not 0 < self.level < 1:
            raise ValueError(f"level: expected a value in (0, 1), got {self.level!r}")
        if not 0 < self.fraction <= 1:
            raise ValueError(f"fraction: expected a value in (0, 1], got {self.fraction!r}")
        if not 0 < self.min_component <= 1:
            raise ValueError(f"min_component: expected a value in (0, 1], got {self.min_component!r}")
        if int(self.opening) != self.opening or self.opening < 0:
            raise ValueError(f"opening: expected an integer >= 0, got {self.opening!r}")


def _grey(images):
    imgs = as_array("images", images)
    if imgs.ndim == 4:
        grey = imgs.mean(-1)
    elif imgs.ndim == 3:
        grey = imgs
    else:
        raise ValueError(f"images: expected (N, H, W) or (N, H, W, C), got shape {imgs.shape}")
    if grey.shape[0] < 1:
        raise ValueError("images: expected at least one image")
    return np.nan_to_num(grey.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)


def lit_pixels(images, config: AutoMaskConfig | None = None) -> np.ndarray:
    """(H, W) bool: pixels lit (above ``level`` x the image's 99th percentile) in at least ``fraction`` of the images.

    The raw criterion of :func:`automatic_mask`, before any cleaning: the
    pixels that carry photometric evidence (a pixel dark in nearly every image,
    such as a pupil, says nothing about the lights).
    """
    cfg = config or AutoMaskConfig()
    grey = _grey(images)
    n = grey.shape[0]
    bright = np.percentile(grey.reshape(n, -1), 99, axis=1)
    return (grey > cfg.level * np.maximum(bright, 1e-12)[:, None, None]).sum(0) >= max(1, int(np.ceil(cfg.fraction * n)))


def automatic_mask(images, config: AutoMaskConfig | None = None) -> tuple[np.ndarray, dict]:
    """Object mask from images under different lights.

    Args:
        images: (N, H, W[, C]) linear intensities (any scale).
        config: :class:`AutoMaskConfig`.

    Returns:
        ``(mask, info)``: (H, W) bool and a dict (``pixels``, ``components``
        kept, ``lit_pixels`` before cleaning, the config).

    Raises:
        ValueError: bad shapes, or no pixel lit in enough images.
    """

    cfg = config or AutoMaskConfig()
    lit = lit_pixels(images, cfg)
    raw_count = int(lit.sum())
    m = lit
    if cfg.opening > 0:
        st = ndimage.generate_binary_structure(2, 1)
        m = ndimage.binary_opening(m, structure=st, iterations=int(cfg.opening))
    lab, k = ndimage.label(m)
    if k == 0:
        raise ValueError("images: no pixel is lit in enough images for an automatic mask; give mask.png")
    sizes = np.bincount(lab.ravel())[1:]
    keep = np.where(sizes >= cfg.min_component * sizes.max())[0] + 1
    m = np.isin(lab, keep)
    if cfg.fill_holes:
        m = ndimage.binary_fill_holes(m)
    info = {"method": "lit in enough images", "pixels": int(m.sum()), "lit_pixels": raw_count,
            "components": int(len(keep)), "level": cfg.level, "fraction": cfg.fraction}
    return m, info
