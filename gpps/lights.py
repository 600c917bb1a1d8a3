"""Light sources: directional lights and near point lights (LEDs).

Directions point from the surface toward the light, in the gpps frame (see
:mod:`gpps.camera`).  Intensities are RGB.  A point light at position Y lights
the point S with direction (Y - S)/|Y - S| and radiance I/|Y - S|^2 (2.30-2.31),
times ``max(cos(angle(axis, S - Y)), 0)^mu`` for an anisotropic LED.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps._check import _source, check_number

__all__ = ["DirectionalLights", "PointLights", "Lights", "ring_directions", "ring_positions", "spiral_directions"]


def _as_n3(name, a, n=None):
    try:
        # (_source: strings, bools, complex and object arrays are a TypeError, never cast to floats)
        arr = np.array(_source(name, a), dtype=np.float64)
    except (TypeError, ValueError) as e:
        if str(e).startswith(f"{name}: "):
            raise
        raise TypeError(f"{name}: expected an (N, 3) array of numbers, got {type(a).__name__}") from None
    if arr.ndim == 1 and arr.shape == (3,):
        arr = arr[None]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (N, 3), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name}: expected shape ({n}, 3), got {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name}: expected shape (N, 3) with N >= 1 lights, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    arr.setflags(write=False)
    return arr


def _intensities(intensities, n):
    if intensities is None:
        arr = np.ones((n, 3))
    else:
        arr = np.array(_source("intensities", intensities), dtype=np.float64)
        if arr.ndim == 1 and arr.shape == (n,):
            arr = np.repeat(arr[:, None], 3, axis=1)
    arr = _as_n3("intensities", arr, n)
    if np.any(arr < 0):
        raise ValueError("intensities: expected values >= 0")
    return arr


def _subset_index(idx, n) -> np.ndarray:
    """``idx`` of :meth:`DirectionalLights.subset` checked: integer indices in [-n, n) or an (n,) bool selection,
    selecting at least one light."""
    arr = np.asarray(idx)
    if arr.dtype == bool:
        if arr.shape != (n,):
            raise ValueError(f"idx: expected {n} booleans (one per light) or integer indices, got shape {arr.shape}")
    elif arr.dtype.kind not in "iu" and not (arr.dtype.kind == "f" and arr.size == 0):
        raise TypeError(f"idx: expected integer indices or {n} booleans, got dtype {arr.dtype}")
    else:
        arr = arr.astype(np.intp).reshape(-1)
        bad = arr[(arr < -n) | (arr >= n)]
        if bad.size:
            raise ValueError(f"idx: expected light indices in [0, {n}), got {bad[0]}")
    chosen = np.count_nonzero(arr) if arr.dtype == bool else arr.size
    if chosen == 0:
        raise ValueError("idx: expected at least one light, got an empty selection")
    return arr


@dataclass(frozen=True)
class DirectionalLights:
    """N distant lights.

    Attributes:
        directions: (N, 3) unit vectors toward the lights (norm 1 within 1e-3;
            they are renormalised).
        intensities: (N, 3) RGB radiance (default ones).
    """

    directions: np.ndarray
    intensities: np.ndarray | None = None

    def __post_init__(self):
        d = _as_n3("directions", self.directions)
        norms = np.linalg.norm(d, axis=1)
        if np.any(norms < 1e-12):
            raise ValueError(f"directions: expected unit vectors, got a zero vector at row {int(np.argmin(norms))}")
        if np.any(np.abs(norms - 1.0) > 1e-3):
            k = int(np.argmax(np.abs(norms - 1.0)))
            raise ValueError(f"directions: expected unit vectors, got norm {norms[k]:.6g} at row {k}")
        d = d / norms[:, None]
        d.setflags(write=False)
        object.__setattr__(self, "directions", d)
        object.__setattr__(self, "intensities", _intensities(self.intensities, d.shape[0]))

    kind = "directional"

    def __len__(self):
        return self.directions.shape[0]

    def subset(self, idx) -> "DirectionalLights":
        """The lights at ``idx`` (indices, or an (N,) bool selection) as a new object."""
        idx = _subset_index(idx, len(self))
        return DirectionalLights(self.directions[idx], self.intensities[idx])


@dataclass(frozen=True)
class PointLights:
    """N near point lights (LEDs).

    Attributes:
        positions: (N, 3) positions in the gpps frame (scene units, e.g. mm).
        intensities: (N, 3) RGB radiant intensity (default ones).
        axes: (N, 3) unit principal directions of the LEDs (from the LED into
            the scene); default (0, 0, -1), the camera's viewing direction.
        mu: (N,) anisotropy exponents >= 0 (0: isotropic, the default).
    """

    positions: np.ndarray
    intensities: np.ndarray | None = None
    axes: np.ndarray | None = None
    mu: np.ndarray | None = None

    kind = "point"

    def __post_init__(self):
        p = _as_n3("positions", self.positions)
        n = p.shape[0]
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "intensities", _intensities(self.intensities, n))
        if self.axes is None:
            ax = np.tile([0.0, 0.0, -1.0], (n, 1))
        else:
            ax = np.array(_as_n3("axes", self.axes, n))
            norms = np.linalg.norm(ax, axis=1)
            if np.any(norms < 1e-12):
                raise ValueError("axes: expected non-zero vectors")
            ax = ax / norms[:, None]
        ax.setflags(write=False)
        object.__setattr__(self, "axes", ax)
        mu = np.zeros(n) if self.mu is None else np.array(_source("mu", self.mu), dtype=np.float64).reshape(-1)
        if mu.size == 1 and n > 1:
            mu = np.full(n, float(mu[0]))
        if mu.shape != (n,) or not np.all(np.isfinite(mu)) or np.any(mu < 0):
            raise ValueError(f"mu: expected {n} finite values >= 0, got {self.mu!r}")
        mu.setflags(write=False)
        object.__setattr__(self, "mu", mu)

    def __len__(self):
        return self.positions.shape[0]

    def subset(self, idx) -> "PointLights":
        """The lights at ``idx`` (indices, or an (N,) bool selection) as a new object."""
        idx = _subset_index(idx, len(self))
        return PointLights(self.positions[idx], self.intensities[idx], self.axes[idx], self.mu[idx])

    def directions_at(self, points: np.ndarray) -> np.ndarray:
        """Unit directions (N, ..., 3) from ``points`` (..., 3) toward each light (2.30)."""
        d = self.positions.reshape((-1,) + (1,) * (points.ndim - 1) + (3,)) - points[None]
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


Lights = DirectionalLights | PointLights


def _count(n) -> int:
    """``n`` lights: a positive integer (NaN, bools, strings and 3.5 are errors naming ``n``)."""
    try:
        n = check_number("n", n, integer=True)
    except (TypeError, ValueError):
        raise ValueError(f"n: expected a positive integer, got {n!r}") from None
    if n < 1:
        raise ValueError(f"n: expected a positive integer, got {n!r}")
    return n


def ring_directions(n: int, slant_deg: float = 35.0, phase_deg: float = 90.0) -> np.ndarray:
    """``n`` unit directions evenly spread in azimuth at a fixed slant from the view axis."""
    n = _count(n)
    az = np.deg2rad(phase_deg) + 2 * np.pi * np.arange(n) / n
    s = np.deg2rad(slant_deg)
    return np.stack([np.sin(s) * np.cos(az), np.sin(s) * np.sin(az), np.full(n, np.cos(s))], axis=1)


def ring_positions(n: int, radius: float, z: float = 0.0, phase_deg: float = 90.0) -> np.ndarray:
    """``n`` positions on a circle of ``radius`` around the optical axis at height ``z``."""
    n = _count(n)
    az = np.deg2rad(phase_deg) + 2 * np.pi * np.arange(n) / n
    return np.stack([radius * np.cos(az), radius * np.sin(az), np.full(n, float(z))], axis=1)


def spiral_directions(n: int, min_slant_deg: float = 15.0, max_slant_deg: float = 50.0) -> np.ndarray:
    """``n`` unit directions on a golden-angle spiral, slants growing from ``min`` to ``max``.

    Unlike a ring, the slants differ, which uncalibrated PS needs (a ring of equal
    slants leaves the GBR scale undetermined by the light-intensity prior).
    """
    n = _count(n)
    k = np.arange(n)
    s = np.deg2rad(min_slant_deg + (max_slant_deg - min_slant_deg) * (k / max(n - 1, 1)))
    az = np.deg2rad(90.0) + k * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([np.sin(s) * np.cos(az), np.sin(s) * np.sin(az), np.cos(s)], axis=1)
