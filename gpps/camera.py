"""Cameras and the one coordinate frame gpps uses everywhere.

The gpps frame (DiLiGenT's)::

                 y (up)
                 ^
                 |        scene: z < 0,  depth d = -z > 0
                 |
      camera  ---o-----> x (right)
     (origin)   /
               /
              z (toward the camera; the camera looks down -z)

    image:  (0,0) +------> j (column, u)
                  |
                  |
                  v  i (row, v)          rows go DOWN, y goes UP

* Normals, light directions and light positions are in this frame.  A visible
  normal points toward the camera (n_z > 0 under the orthographic camera,
  n . (-P) > 0 under the perspective one).
* Light directions point from the surface toward the light.
* Depth ``d`` is the positive distance along the optical axis (``d = -z``), in
  the same unit as light positions (e.g. mm).
* Pixel centres are at integer ``(u, v) = (j, i)``.

Perspective pinhole (K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels)::

    u = cx + fx * x / d          x = (u - cx) * d / fx
    v = cy - fy * y / d          y = -(v - cy) * d / fy,   z = -d

(the usual computer-vision camera with y and z flipped).  This covers the
seed's CCD model and "centerizing" (3.35-3.37): the principal point
``(cx, cy)`` is what centerizing subtracts, and ``fx = f / pixel_width``.

Orthographic (pixel size ``s`` in scene units, centre ``(cx, cy)`` in pixels)::

    x = (u - cx) * s,    y = -(v - cy) * s,    z = -d

so a height field ``z(x, y)`` has normal ``n ~ (-z_x, -z_y, 1)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from gpps._check import as_array, check_number

__all__ = ["Orthographic", "Perspective", "Camera", "camera_from_K"]


def _finite_positive(name: str, value) -> float:
    # (check_number: a string such as "1" or a bool is a TypeError, not a number float() converts)
    v = check_number(name, value)
    if v <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class Orthographic:
    """Orthographic camera looking down -z.

    Attributes:
        pixel_size: scene units per pixel (> 0).
        center: ``(cx, cy)`` pixel that sees x = y = 0; ``None`` means the image
            centre ``((W-1)/2, (H-1)/2)`` of whatever image it is used with.
    """

    pixel_size: float = 1.0
    center: tuple[float, float] | None = None
    kind: str = field(default="orthographic", init=False)

    def __post_init__(self):
        object.__setattr__(self, "pixel_size", _finite_positive("pixel_size", self.pixel_size))
        if self.center is not None:
            c = as_array("center", self.center, dtype=np.float64, finite=False)  # (strings, bools: TypeError)
            if c.shape != (2,) or not np.all(np.isfinite(c)):
                raise ValueError(f"center: expected (cx, cy) finite, got {self.center!r}")
            object.__setattr__(self, "center", (float(c[0]), float(c[1])))

    @property
    def is_perspective(self) -> bool:
        return False

    def principal_point(self, shape: tuple[int, int]) -> tuple[float, float]:
        """``(cx, cy)`` for an image of ``shape = (H, W)``."""
        if self.center is not None:
            return self.center
        h, w = shape
        return ((w - 1) / 2.0, (h - 1) / 2.0)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Points (H, W, 3) in the gpps frame from depth (H, W) (> 0 where used)."""
        depth = np.asarray(depth, dtype=np.float64)
        h, w = depth.shape
        cx, cy = self.principal_point((h, w))
        jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        return np.stack([(jj - cx) * self.pixel_size, -(ii - cy) * self.pixel_size, -depth], axis=-1)

    def rays(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins at z = 0 and unit directions, each (H, W, 3)."""
        o = self.backproject(np.zeros(shape))
        d = np.zeros_like(o)
        d[..., 2] = -1.0
        return o, d


@dataclass(frozen=True)
class Perspective:
    """Perspective pinhole camera from a full intrinsic matrix.

    Attributes:
        K: 3x3 intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels
            (fx, fy > 0, no skew), stored as a read-only float64 array.
    """

    K: np.ndarray
    kind: str = field(default="perspective", init=False)

    def __post_init__(self):
        # (as_array: strings, bools, complex and object arrays are a TypeError, never cast; a copy, made read-only)
        K = np.array(as_array("K", self.K, dtype=np.float64, finite=False), dtype=np.float64, copy=True)
        if K.shape != (3, 3):
            raise ValueError(f"K: expected shape (3, 3), got {K.shape}")
        if not np.all(np.isfinite(K)):
            raise ValueError("K: expected finite entries, got NaN or inf")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise ValueError(f"K: expected focal lengths fx = K[0,0] > 0 and fy = K[1,1] > 0, got {K[0,0]} and {K[1,1]}")
        if abs(K[0, 1]) > 1e-9 * K[0, 0] or np.any(np.abs(K[2] - [0, 0, 1]) > 1e-9) or abs(K[1, 0]) > 0:
            raise ValueError(f"K: expected [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}")
        K.setflags(write=False)
        object.__setattr__(self, "K", K)

    @property
    def is_perspective(self) -> bool:
        return True

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    def principal_point(self, shape: tuple[int, int] | None = None) -> tuple[float, float]:
        return (float(self.K[0, 2]), float(self.K[1, 2]))

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """Points (H, W, 3) in the gpps frame from depth (H, W)."""
        depth = np.asarray(depth, dtype=np.float64)
        o, d = self.rays(depth.shape)
        return d / (-d[..., 2:3]) * depth[..., None]

    def rays(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Ray origins (all zero) and unit directions through pixel centres, (H, W, 3)."""
        h, w = shape
        jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        d = np.stack([(jj - self.K[0, 2]) / self.fx, -(ii - self.K[1, 2]) / self.fy, -np.ones_like(jj)], axis=-1)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        return np.zeros_like(d), d

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates (..., 2) as (u, v) of points (..., 3) with z < 0."""
        p = np.asarray(points, dtype=np.float64)
        d = -p[..., 2]
        return np.stack([self.K[0, 2] + self.fx * p[..., 0] / d, self.K[1, 2] - self.fy * p[..., 1] / d], axis=-1)


Camera = Orthographic | Perspective


def camera_from_K(K) -> Perspective:
    """A :class:`Perspective` camera from a 3x3 K (as in DiLiGenT's ``K.txt``)."""
    return Perspective(K)  # (Perspective checks and converts it: strings, bools, complex are a TypeError there)
