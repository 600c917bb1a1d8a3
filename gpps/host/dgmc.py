"""DGMC: Dijkstra Gaussian Mean Curvature start normals for highlight pixels (seed 4.1.9, 4.16-4.18).

The per-pixel solvers (Algorithms 3-5) need a start ``X^0``; the Lambertian
least-squares (Woodham) normal is a poor one where highlights corrupt the
observations.  DGMC replaces it there by the normal of a nearby pixel outside
the highlight that has a similar local geometry:

1. :func:`detect_highlights`: per-image highlight maps (saturated or brighter
   than any Lambertian explanation of the pixel allows), their union (the
   highlight region), its connected regions and their outer boundaries ``S``.
2. :func:`geodesic_candidates`: for every highlight pixel ``p`` the nearest
   ``K`` boundary pixels of its region, ordered by geodesic (Dijkstra) distance
   on the 8-neighbour pixel graph of region + boundary.
3. :func:`hessian_curvatures`: Gaussian and mean curvature from the eigenvalues
   of the local Hessian (4.16).
4. :func:`dgmc_start`: the nearest candidate ``q`` whose Gaussian and mean
   curvature are both within +-5 % of ``p``'s (4.17-4.18), the tolerance
   widened stepwise when none qualifies, else the nearest boundary pixel; ``p``
   starts from ``q``'s normal.
5. :func:`front_rings`: the rings of the front that the pipeline solves
   instead (:func:`gpps.pipeline.front.propagate_front`): the same rule with
   the boundary moved inward ring by ring as pixels get solved.

Pure numpy/scipy on the host (no Warp)::

    ls = solve_normals(images, mask, lights, camera=cam, solver="none")
    res = dgmc_start(images, mask, ls.normals, lights=lights)
    solver = PixelSolver(..., config=SolverConfig(warm_start=True, starts=1))
    solver.run(images, mask, init_normals=res.normals)

Conventions: pixel ``(i, j)`` = (row, column); geodesic distances are in pixels
(edge lengths 1 and sqrt(2)); ``source`` holds ``(row, column)``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import ndimage as ndi
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from gpps._check import as_array, as_mask, check_choice, check_choices, check_number, check_unit
from gpps.lights import DirectionalLights, PointLights

__all__ = [
    "CurvatureField",
    "DGMCConfig",
    "DGMCResult",
    "FrontResult",
    "HighlightRule",
    "Highlights",
    "StartMode",
    "detect_highlights",
    "dgmc_start",
    "fill_indices",
    "front_rings",
    "gaussian_derivative_weights",
    "geodesic_candidates",
    "hessian_curvatures",
    "outer_boundary",
    "select_sources",
]

HighlightRule = Literal["lambertian", "percentile"]
StartMode = Literal["front", "boundary"]
CurvatureField = Literal["intensity", "normals"]
Connectivity = Literal[4, 8]

_SQRT2 = float(np.sqrt(2.0))
# the 8 neighbour offsets (di, dj) and their Euclidean lengths (pixels)
_OFFSETS = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]
_LENGTHS = [_SQRT2 if di and dj else 1.0 for di, dj in _OFFSETS]


def _structure(connectivity: int) -> np.ndarray:
    return ndi.generate_binary_structure(2, 1 if connectivity == 4 else 2)


@dataclass(frozen=True)
class DGMCConfig:
    """Settings of :func:`dgmc_start` and its steps (the exact highlight rule is in :func:`detect_highlights`).

    Attributes:
        rule: ``"lambertian"``: an observation is a highlight when its grey value
            exceeds ``ratio`` times what a Lambertian fit of the pixel's other
            observations predicts for that light, plus ``margin`` (needs
            ``lights``; flagged one at a time per pixel); ``"percentile"``: when it
            exceeds ``ratio`` times the ``percentile``-th percentile of its image
            inside the mask, plus ``margin`` (no lights needed).
        ratio: the factor ``k`` of the rule (>= 1).
        margin: absolute grey margin added to the threshold (image units, >= 0):
            keeps noise in dark pixels from counting as highlights.
        percentile: the percentile (0-100) of the ``"percentile"`` rule.
        saturation: an observation with any channel >= this value is a highlight
            (image units; None: no saturation test).
        connectivity: 4 or 8: adjacency of highlight pixels within a region
            (:func:`scipy.ndimage.label`) and of boundary pixels to their region.
        k_nearest: boundary candidates kept per highlight pixel (nearest first).
        curvature_field: the scalar field whose local Hessian gives the
            curvatures (4.16): ``"intensity"`` (the seed's "Hessian matrix of the
            pixel local neighboring area": the mean grey image over all
            lights) or ``"normals"`` (the Hessian of the height field whose
            gradient ``(-n_x/n_z, -n_y/n_z)`` the given normals define).
        sigma: scale of the Gaussian-derivative filters (pixels, > 0).
        tolerance: relative tolerance of 4.17-4.18 (0.05: +-5 %).
        widen_factor: the tolerance is multiplied by this (> 1) when no candidate
            qualifies ...
        widen_steps: ... up to this many times; then the nearest boundary pixel wins.
        start: how the pipeline (:class:`gpps.flows.ron.RON`) uses the rule:
            ``"front"`` (default): :func:`gpps.pipeline.front.propagate_front`, sources on the solved
            front moving inward ring by ring (4.1-4.6 cost evaluations per
            highlight pixel and under 0.01 deg on ``perf/dgmc_start.py``'s
            scenes; the boundary candidates below are then not computed:
            ``DeviceDGMC.step(starts=False)``); ``"boundary"``: :func:`dgmc_start` as the seed states it,
            sources on the region's outer boundary, one warm solve from them
            (7.9-13.2 evaluations and 4-13 deg there: no faster than the
            least-squares start).
    """

    rule: HighlightRule = "lambertian"
    ratio: float = 1.1
    margin: float = 0.02
    percentile: float = 99.0
    saturation: float | None = None
    connectivity: Connectivity = 8
    k_nearest: int = 32
    curvature_field: CurvatureField = "intensity"
    sigma: float = 2.0
    tolerance: float = 0.05
    widen_factor: float = 2.0
    widen_steps: int = 3
    start: StartMode = "front"

    def __post_init__(self):
        check_choices(self)
        check_number("ratio", self.ratio, lo=1.0)
        check_number("margin", self.margin, lo=0.0)
        check_number("percentile", self.percentile, lo=0.0, hi=100.0)
        if self.saturation is not None:
            check_number("saturation", self.saturation, lo=0.0, lo_open=True)
        check_number("k_nearest", self.k_nearest, lo=1, integer=True)
        check_number("sigma", self.sigma, lo=0.0, lo_open=True)
        check_number("tolerance", self.tolerance, lo=0.0)
        check_number("widen_factor", self.widen_factor, lo=1.0, lo_open=True)
        check_number("widen_steps", self.widen_steps, lo=0, integer=True)


@dataclass
class Highlights:
    """Output of :func:`detect_highlights`.

    Attributes:
        maps: (N, H, W) bool, the highlight observations (False outside the mask).
        saturated: (N, H, W) bool, the observations that were saturated.
        region: (H, W) bool, pixels with a highlight in any image.
        labels: (H, W) int32, connected regions of ``region`` numbered 1..n, 0 elsewhere.
        n_regions: number of regions.
        boundary: (H, W) int32, outer-boundary pixels labelled with their region
            (a pixel next to several regions keeps the smallest label), 0 elsewhere.
        predicted: (N, H, W) float32, the threshold base ``g^_k`` of each
            observation (grey image units): the image percentile, or the
            Lambertian prediction (at a flagged observation the one it was
            flagged against, elsewhere the first round's; NaN where untestable
            and outside the mask).
    """

    maps: np.ndarray
    saturated: np.ndarray
    region: np.ndarray
    labels: np.ndarray
    n_regions: int
    boundary: np.ndarray
    predicted: np.ndarray


@dataclass
class DGMCResult:
    """Output of :func:`dgmc_start`.

    Attributes:
        normals: (H, W, 3) float32 start normals: DGMC's (the chosen ``q``'s
            given normal) on highlight pixels with a reachable boundary, the
            given normals elsewhere; zeros outside the mask.
        highlight: (H, W) bool, the highlight region.
        source: (H, W, 2) int32, ``(row, column)`` of the chosen ``q`` per
            highlight pixel; -1 elsewhere and where no boundary pixel is reachable.
        distance: (H, W) float32, geodesic distance ``p -> q`` (pixels); NaN
            where ``source`` is -1.
        rank: (H, W) int32, rank of ``q`` among ``p``'s candidates (0: nearest); -1
            where ``source`` is -1.
        tolerance: (H, W) float32, the relative tolerance at which ``q`` met
            4.17-4.18; inf where the nearest-pixel fallback was used, NaN where
            ``source`` is -1.
        gaussian: (H, W) float32, Gaussian curvature ``K1 K2`` (4.16).
        mean: (H, W) float32, mean curvature ``(K1 + K2) / 2`` (4.16).
        highlights: the :class:`Highlights` found.
        config: the settings used.
    """

    normals: np.ndarray
    highlight: np.ndarray
    source: np.ndarray
    distance: np.ndarray
    rank: np.ndarray
    tolerance: np.ndarray
    gaussian: np.ndarray
    mean: np.ndarray
    highlights: Highlights
    config: DGMCConfig


# --------------------------------------------------------------------------- input checks


def _check_images(images) -> tuple[np.ndarray, np.ndarray]:
    """(N, H, W) grey (RGB mean) and (N, H, W) max-channel float64 images."""
    arr = np.asarray(images.numpy() if hasattr(images, "numpy") and not isinstance(images, np.ndarray) else images)
    if arr.ndim not in (3, 4) or (arr.ndim == 4 and arr.shape[-1] not in (1, 3)):
        raise ValueError(f"images: expected (N, H, W) or (N, H, W, 3), got {arr.shape}")
    arr = as_array("images", arr, dtype=np.float64)
    if arr.shape[0] < 1 or arr.shape[1] < 1 or arr.shape[2] < 1:
        raise ValueError(f"images: expected (N, H, W) or (N, H, W, 3) with positive sizes, got {arr.shape}")
    if np.any(arr < 0):
        raise ValueError("images: expected values >= 0")
    if arr.ndim == 3:
        return arr, arr
    return arr.mean(-1), arr.max(-1)


def _light_fields(lights, n: int, shape, points) -> np.ndarray:
    """(N, H, W, 3) per-pixel light vectors ``E_k l_k`` (irradiance times unit direction)."""
    h, w = shape
    if isinstance(lights, DirectionalLights):
        if len(lights) != n:
            raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
        e = np.asarray(lights.intensities, np.float64).mean(1)
        s = np.asarray(lights.directions, np.float64) * e[:, None]
        return np.broadcast_to(s[:, None, None, :], (n, h, w, 3))
    if isinstance(lights, PointLights):
        if len(lights) != n:
            raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
        if points is None:
            raise ValueError("points: expected (H, W, 3) surface points for point lights (2.30-2.31), got None")
        pts = as_array("points", points, shape=(h, w, 3), dtype=np.float64)
        d = np.asarray(lights.positions)[:, None, None, :] - pts[None]
        r2 = np.maximum(np.sum(d * d, -1), 1e-300)
        ldir = d / np.sqrt(r2)[..., None]
        cosax = np.maximum(np.einsum("nhwc,nc->nhw", -ldir, np.asarray(lights.axes)), 0.0)
        e = np.asarray(lights.intensities, np.float64).mean(1)[:, None, None] / r2
        e = e * cosax ** np.asarray(lights.mu)[:, None, None]
        return ldir * e[..., None]
    arr = as_array("lights", lights, dtype=np.float64)
    if arr.shape != (n, 3):
        raise ValueError(f"lights: expected DirectionalLights, PointLights or an ({n}, 3) direction array, got {arr.shape}")
    return np.broadcast_to(arr[:, None, None, :], (n, h, w, 3))


# --------------------------------------------------------------------------- highlights


def _reference_albedo(g: np.ndarray, s: np.ndarray) -> float:
    """Median over the pixels of the least-squares Lambertian albedo ``|b|`` (all observations)."""
    ata = np.einsum("pni,pnj->pij", s, s) + 1e-12 * np.eye(3)
    b = np.linalg.solve(ata, np.einsum("pni,pn->pi", s, g)[..., None])[..., 0]
    return float(np.median(np.linalg.norm(b, axis=-1)))


def _lambertian_predictions(g: np.ndarray, s: np.ndarray, active: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """Largest Lambertian prediction of each observation from the pixel's other active observations.

    Args:
        g: (P, N) grey observations.
        s: (P, N, 3) light vectors ``E_k l_k``.
        active: (P, N) bool, the observations not (yet) flagged.
        rho: reference albedo (grey).

    Returns:
        ``(pred, incons)``: (P, N) predictions ``max(s_k . b, 0)``: with 3 or more
        other active observations, ``b`` is their least-squares fit; with exactly
        2, ``b`` is each of the (up to two) vectors that fit them exactly with
        ``|b| = rho`` (the one nearest ``|b| = rho`` when none reaches it), the
        visible ones (``b_z > 0``) preferred, and the larger prediction is kept;
        NaN with fewer than 2 (the observation cannot be tested).  ``incons``
        (grey units) measures how badly the others fit a Lambertian pixel of
        albedo ``rho``: their RMS residual plus ``||b| - rho|`` times their mean
        irradiance.
    """
    p, n = g.shape
    pred = np.full((p, n), np.nan)
    incons = np.full((p, n), np.nan)
    ebar = np.linalg.norm(s, axis=-1)
    for k in range(n):
        w = active.copy()
        w[:, k] = False
        cnt = w.sum(1)
        ls = cnt >= 3
        if ls.any():
            a = s[ls] * w[ls][..., None]
            ata = np.einsum("pni,pnj->pij", a, a) + 1e-12 * np.eye(3)
            b = np.linalg.solve(ata, np.einsum("pni,pn->pi", a, g[ls])[..., None])[..., 0]
            pred[ls, k] = np.maximum(np.einsum("pi,pi->p", s[ls, k], b), 0.0)
            res = (np.einsum("pni,pi->pn", s[ls], b) - g[ls]) * w[ls]
            e = (ebar[ls] * w[ls]).sum(1) / cnt[ls]
            incons[ls, k] = np.sqrt((res**2).sum(1) / cnt[ls]) + np.abs(np.linalg.norm(b, axis=-1) - rho) * e
        two = cnt == 2
        if two.any():
            o = np.argsort(~w[two], axis=1, kind="stable")[:, :2]  # the two active indices
            a = np.take_along_axis(s[two], o[..., None], 1)  # (P2, 2, 3)
            gg = np.take_along_axis(g[two], o, 1)
            aat = np.einsum("pni,pmi->pnm", a, a) + 1e-12 * np.eye(2)
            b0 = np.einsum("pni,pn->pi", a, np.linalg.solve(aat, gg[..., None])[..., 0])
            c = np.cross(a[:, 0], a[:, 1])
            c /= np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-300)
            t = np.sqrt(np.maximum(rho * rho - np.sum(b0 * b0, -1), 0.0))[:, None]
            cand = np.stack([b0 + t * c, b0 - t * c], 1)  # (P2, 2, 3)
            pk = np.maximum(np.einsum("pi,pci->pc", s[two, k], cand), 0.0)
            vis = cand[..., 2] > 0
            pk = np.where(vis | ~vis.any(1, keepdims=True), pk, -np.inf)
            pred[two, k] = pk.max(1)
            e = (ebar[two] * w[two]).sum(1) / 2
            incons[two, k] = np.maximum(np.linalg.norm(b0, axis=-1) - rho, 0.0) * e
    return pred, incons


def _lambertian_highlights(g: np.ndarray, s: np.ndarray, ratio: float, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy per-pixel flagging with the ``"lambertian"`` rule (see :func:`detect_highlights`).

    Returns:
        (P, N) bool flags and (P, N) predictions (at a flagged observation the one
        it was flagged against, elsewhere the first round's; NaN where untestable).
    """
    p, n = g.shape
    rho = _reference_albedo(g, s)
    ebar_pix = np.linalg.norm(s, axis=-1).mean(1, keepdims=True)
    active = np.ones((p, n), bool)
    flags = np.zeros((p, n), bool)
    reported = np.full((p, n), np.nan)
    todo = np.ones(p, bool)
    for round_ in range(n):
        pred = np.full((p, n), np.nan)
        incons = np.full((p, n), np.inf)
        pred[todo], incons[todo] = _lambertian_predictions(g[todo], s[todo], active[todo], rho)
        if round_ == 0:
            reported = pred.copy()
        over = active & np.isfinite(pred) & (g > ratio * np.nan_to_num(pred) + margin)
        todo = over.any(1)
        if not todo.any():
            break
        # flag the over-threshold observation whose removal leaves the most consistent
        # Lambertian fit; among (nearly) equally consistent ones the largest excess
        incons = np.where(over, np.nan_to_num(incons, nan=np.inf), np.inf)
        best = incons.min(1, keepdims=True)
        near = over & (incons <= best + 1e-3 * rho * ebar_pix)
        excess = np.where(near, (g - margin) / np.maximum(np.nan_to_num(pred), 1e-12), -np.inf)
        rows = np.nonzero(todo)[0]
        worst = np.argmax(excess[rows], 1)
        flags[rows, worst] = True
        active[rows, worst] = False
        reported[rows, worst] = pred[rows, worst]
    return flags, reported


def outer_boundary(region, mask, connectivity: int = 8) -> np.ndarray:
    """Outer boundary of a pixel set: pixels inside ``mask``, outside ``region``, adjacent to it.

    Args:
        region: (H, W) bool, the highlight pixels.
        mask: (H, W) bool, the object mask.
        connectivity: 4 (edge neighbours) or 8 (edge and corner neighbours).

    Returns:
        (H, W) bool.
    """
    if connectivity not in (4, 8) or isinstance(connectivity, bool):
        raise ValueError(f"connectivity: expected 4 or 8, got {connectivity!r}")
    m = np.asarray(mask, bool)
    r = np.asarray(region, bool)
    if r.shape != m.shape or r.ndim != 2:
        raise ValueError(f"region: expected shape {m.shape} (the mask's), got {r.shape}")
    r = r & m
    return ndi.binary_dilation(r, _structure(connectivity)) & m & ~r


def detect_highlights(images, mask, lights=None, *, config: DGMCConfig | None = None, points=None) -> Highlights:
    """Per-image highlight maps, the highlight region, its regions and their outer boundaries.

    The rule, per pixel ``p`` inside the mask, with grey values ``g_k`` (the RGB
    mean; the value itself for grey images) and brightest channels ``c_k``:

    * Saturation: observation ``k`` is a highlight when ``c_k >= config.saturation``
      (skipped when ``saturation`` is None).
    * ``rule="percentile"``: observation ``k`` is a highlight when
      ``g_k > config.ratio * P_k + config.margin``, ``P_k`` the
      ``config.percentile``-th percentile of image ``k`` inside the mask.
    * ``rule="lambertian"`` (specular lobe: brighter than any Lambertian
      explanation, 2.13): the Lambertian prediction of ``k`` from the pixel's
      *other* not-yet-flagged observations is ``g^_k = max(E_k l_k . b, 0)`` with
      ``b = rho n`` their least-squares fit when there are 3 or more of them, and,
      when there are exactly 2, each of the (up to two) vectors that fit them
      exactly with ``|b|`` equal to the reference albedo ``rho_ref`` (the median
      least-squares albedo of the mask; the visible solutions, ``b_z > 0``, are
      used and the larger prediction is kept).  Observation ``k`` is *over* when
      ``g_k > config.ratio * g^_k + config.margin``.  In rounds, per pixel: of the
      over observations, the one whose removal leaves the most consistent fit
      (RMS residual of the others plus ``||b| - rho_ref|`` times their mean
      irradiance; ties within ``1e-3 rho_ref`` broken by the largest
      ``(g_k - margin) / g^_k``) is flagged and removed, and the rest are tested
      again; an observation with fewer than 2 other unflagged ones is not
      tested.  So with 3 lights at most one highlight per pixel is found (some
      ``b`` always fits 3 observations exactly: only the albedo reference makes
      one testable).  Flagging one at a time keeps a highlight that distorts
      the fits of the clean observations from getting them flagged too; but an
      excess just under the threshold can still distort them enough that a
      clean observation is flagged in its place, and a pixel whose other
      observations are also corrupted may be missed.

    The highlight region is the set of pixels with a highlight in any image;
    its connected regions (``config.connectivity``) are labelled with
    :func:`scipy.ndimage.label`, and each gets its outer boundary
    (:func:`outer_boundary`).

    Args:
        images: (N, H, W) grey or (N, H, W, 3) RGB images >= 0 (divided by the
            light intensities when ``lights`` has unit intensities).
        mask: (H, W) bool, not empty.
        lights: :class:`DirectionalLights`, :class:`PointLights` (needs ``points``)
            or an (N, 3) array of unit directions; required for ``rule="lambertian"``
            (N >= 3).
        config: :class:`DGMCConfig` (its highlight fields are used).
        points: (H, W, 3) surface points (scene units) for point lights.

    Returns:
        :class:`Highlights`.

    Raises:
        ValueError: wrong shapes, NaN or inf, negative images, an empty mask, or
            ``rule="lambertian"`` without lights or with fewer than 3.
    """
    cfg = _check_config(config)
    grey, cmax = _check_images(images)
    m = as_mask("mask", mask, grey.shape[1:])
    return _detect(grey, cmax, m, lights, cfg, points)


def _check_config(config) -> DGMCConfig:
    cfg = DGMCConfig() if config is None else config
    if not isinstance(cfg, DGMCConfig):
        raise TypeError(f"config: expected DGMCConfig, got {type(cfg).__name__}")
    return cfg


def _detect(grey: np.ndarray, cmax: np.ndarray, m: np.ndarray, lights, cfg: DGMCConfig, points) -> Highlights:
    """:func:`detect_highlights` on checked (N, H, W) grey and max-channel images and an (H, W) mask."""
    n, h, w = grey.shape
    if cfg.rule == "lambertian":
        if lights is None:
            raise ValueError("lights: expected DirectionalLights, PointLights or (N, 3) directions for rule='lambertian', got None")
        if n < 3:
            raise ValueError(f"images: expected N >= 3 images for rule='lambertian', got N = {n}")
        s = _light_fields(lights, n, (h, w), points)
        gp = grey[:, m].T  # (P, N)
        sp = np.moveaxis(s[:, m], 0, 1)  # (P, N, 3)
        fl, pr = _lambertian_highlights(gp, sp, cfg.ratio, cfg.margin)
        maps = np.zeros((n, h, w), bool)
        maps[:, m] = fl.T
        pred = np.full((n, h, w), np.nan)
        pred[:, m] = pr.T
    else:
        q = np.percentile(grey[:, m], cfg.percentile, axis=1)
        pred = np.broadcast_to(q[:, None, None], (n, h, w)).copy()
        maps = grey > cfg.ratio * pred + cfg.margin
    sat = np.zeros_like(maps) if cfg.saturation is None else cmax >= cfg.saturation
    maps = (maps | sat) & m[None]
    sat &= m[None]
    region = maps.any(0)
    labels, nreg = ndi.label(region, _structure(cfg.connectivity))
    # boundary labels: the smallest adjacent region label (grey erosion of labels, 0 as +inf)
    big = np.where(labels > 0, labels, np.iinfo(np.int32).max).astype(np.int64)
    nearest = ndi.grey_erosion(big, footprint=_structure(cfg.connectivity), mode="constant", cval=np.iinfo(np.int32).max)
    bnd = outer_boundary(region, m, cfg.connectivity)
    boundary = np.where(bnd, nearest, 0).astype(np.int32)
    return Highlights(
        maps=maps,
        saturated=sat,
        region=region,
        labels=labels.astype(np.int32),
        n_regions=int(nreg),
        boundary=boundary,
        predicted=pred.astype(np.float32),
    )


# --------------------------------------------------------------------------- geodesic candidates


def _tie_key(d: np.ndarray) -> np.ndarray:
    """Distances rounded to 1e-9 pixels for ordering: equal path lengths ``a + b sqrt(2)`` summed in different
    orders differ by an ulp in Dijkstra's floats; rounded, they tie and go to the smaller source index (as the
    docstring says, and as the device form :mod:`gpps.kernels.dgmc`, which counts steps exactly, orders them)."""
    return np.round(d, 9)


def geodesic_candidates(region, boundary, k: int = 32, *, chunk: int = 256) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``k`` boundary pixels nearest to each region pixel by geodesic distance (multi-source Dijkstra).

    The graph: nodes are the region and boundary pixels; 8-neighbour edges of
    length 1 (edge neighbours) or sqrt(2) (corner neighbours) join region
    pixels in both directions and lead from a boundary pixel into an adjacent
    region pixel (never into a boundary pixel, so no path runs along or through
    ``S``).  The distance from boundary pixel ``q`` to region pixel ``p`` is the
    length of the shortest such path (pixels); it is computed exactly with
    :func:`scipy.sparse.csgraph.dijkstra` from every boundary pixel (in chunks,
    keeping the ``k`` smallest per region pixel).

    Args:
        region: (H, W) bool, the pixels to serve (e.g. one highlight region).
        boundary: (H, W) bool, the source pixels (e.g. its outer boundary); must
            not overlap ``region``.
        k: candidates kept per region pixel (>= 1).
        chunk: sources per Dijkstra call (memory ``chunk x pixels``).

    Returns:
        ``(pixels, sources, distances)``: ``pixels`` (P, 2) int32 ``(row, column)``
        of the region pixels in raster order; ``sources`` (P, k) int32 flat
        indices (``row * W + column``) of their nearest boundary pixels, nearest
        first (ties by flat index), -1 where fewer are reachable;
        ``distances`` (P, k) float64, inf where ``sources`` is -1.
    """
    r = np.asarray(region, bool)
    b = np.asarray(boundary, bool)
    if r.ndim != 2 or b.shape != r.shape:
        raise ValueError(f"boundary: expected shape {r.shape} (the region's), got {b.shape}")
    if np.any(r & b):
        raise ValueError("boundary: expected no pixel in both region and boundary")
    k = int(check_number("k", k, lo=1, integer=True))
    h, w = r.shape
    ri, rj = np.nonzero(r)
    bi, bj = np.nonzero(b)
    nr, nb = ri.size, bi.size
    pixels = np.stack([ri, rj], 1).astype(np.int32)
    sources = np.full((nr, k), -1, np.int32)
    dists = np.full((nr, k), np.inf)
    if nr == 0 or nb == 0:
        return pixels, sources, dists
    node = np.full((h + 2, w + 2), -1, np.int64)  # padded node index map
    node[ri + 1, rj + 1] = np.arange(nr)
    node[bi + 1, bj + 1] = nr + np.arange(nb)
    rows, cols, wts = [], [], []
    for (di, dj), length in zip(_OFFSETS, _LENGTHS):
        # edges u -> v with v a region pixel and u its neighbour (region or boundary)
        u = node[ri + 1 + di, rj + 1 + dj]
        ok = u >= 0
        rows.append(u[ok])
        cols.append(np.arange(nr)[ok])
        wts.append(np.full(int(ok.sum()), length))
    g = csr_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(nr + nb, nr + nb))
    flat_b = (bi * w + bj).astype(np.int64)
    best_d = np.full((k, nr), np.inf)
    best_s = np.full((k, nr), -1, np.int64)
    for start in range(0, nb, chunk):
        idx = np.arange(start, min(start + chunk, nb))
        d = dijkstra(g, directed=True, indices=nr + idx)[:, :nr]  # (c, nr)
        all_d = np.concatenate([best_d, d], 0)
        all_s = np.concatenate([best_s, np.broadcast_to(idx[:, None], d.shape)], 0)
        if all_d.shape[0] > k:
            # keep the k smallest (ties toward the smaller source index, found by a stable sort)
            order = np.lexsort((all_s, _tie_key(all_d)), axis=0)[:k]
            all_d = np.take_along_axis(all_d, order, 0)
            all_s = np.take_along_axis(all_s, order, 0)
        best_d, best_s = all_d, all_s
    order = np.lexsort((best_s, _tie_key(best_d)), axis=0)
    best_d = np.take_along_axis(best_d, order, 0)
    best_s = np.take_along_axis(best_s, order, 0)
    kk = best_d.shape[0]
    reach = np.isfinite(best_d)
    dists[:, :kk] = np.where(reach, best_d, np.inf).T
    sources[:, :kk] = np.where(reach, flat_b[np.maximum(best_s, 0)], -1).T
    return pixels, sources, dists


# --------------------------------------------------------------------------- curvature


# fill_indices of the last few masks (a stream or repeated reconstructions keep one mask; the transform costs
# 3-7 ms at 256^2, more than the rest of DGMC's upload)
_FILL_CACHE: OrderedDict = OrderedDict()
_FILL_CACHE_SIZE = 4
_FILL_LOCK = threading.Lock()


def fill_indices(mask) -> np.ndarray:
    """(H, W, 2) int32 ``(row, column)`` of the nearest pixel inside ``mask`` (itself inside; Euclidean, scipy's
    :func:`~scipy.ndimage.distance_transform_edt` ties): the fill of :func:`hessian_curvatures` (also used by the
    device stage :mod:`gpps.pipeline.dgmc`, which depends on the mask only).  The result is read-only: the last
    few masks' results are kept and handed out again."""
    m = np.asarray(mask, bool)
    key = (m.shape, np.packbits(m).tobytes())
    with _FILL_LOCK:
        got = _FILL_CACHE.get(key)
        if got is not None:
            _FILL_CACHE.move_to_end(key)
            return got
    if m.all():
        ii, jj = np.indices(m.shape)
    else:
        _, (ii, jj) = ndi.distance_transform_edt(~m, return_indices=True)
    out = np.stack([ii, jj], -1).astype(np.int32)
    out.setflags(write=False)
    with _FILL_LOCK:
        _FILL_CACHE[key] = out
        while len(_FILL_CACHE) > _FILL_CACHE_SIZE:
            _FILL_CACHE.popitem(last=False)
    return out


def gaussian_derivative_weights(sigma: float, order: int, truncate: float = 4.0) -> np.ndarray:
    """(2r + 1,) float64 correlation weights ``w`` of :func:`scipy.ndimage.gaussian_filter1d` (``order``-th
    derivative, radius ``r = int(truncate sigma + 0.5)``): ``out[i] = sum_t w[t] in[i + t - r]``.  Read off the
    filter's impulse response, so they are scipy's own weights."""
    sigma = check_number("sigma", sigma, lo=0.0, lo_open=True)
    r = int(truncate * float(sigma) + 0.5)
    imp = np.zeros(4 * r + 1)
    imp[2 * r] = 1.0
    out = ndi.gaussian_filter1d(imp, sigma, order=int(order), mode="constant", truncate=truncate)
    # out[i] = w[2r - i + r] for |i - 2r| <= r
    return out[r:3 * r + 1][::-1].copy()


def _fill_outside(f: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``f`` with pixels outside ``mask`` set to the nearest inside value (keeps filters off the edge step)."""
    if mask.all():
        return f
    idx = fill_indices(mask)
    return f[idx[..., 0], idx[..., 1]]


def hessian_curvatures(field, mask, *, sigma: float = 2.0, kind: CurvatureField = "intensity") -> tuple[np.ndarray, np.ndarray]:
    """Gaussian and mean curvature from the eigenvalues of the local Hessian (4.16).

    ``GC = K1 K2`` and ``MC = (K1 + K2) / 2`` with ``K1 <= K2`` the eigenvalues of
    the 2x2 Hessian at each pixel (equivalently ``GC = det H``, ``MC = trace H / 2``).
    The Hessian is taken with Gaussian-derivative filters of scale ``sigma``
    (:func:`scipy.ndimage.gaussian_filter` with ``order=``) after the values
    outside the mask are replaced by the nearest inside value.  Eigenvalues do
    not depend on the image axes' orientation (rows down or y up).

    Args:
        field: for ``kind="intensity"``: (H, W) scalar image (e.g. the mean grey
            image; Hessian in image units per pixel^2); for ``kind="normals"``:
            (H, W, 3) unit normals, whose height-field gradient
            ``(p, q) = (-n_x / n_z, -n_y / n_z)`` (``n_z`` clamped to >= 0.05) is
            differentiated once, ``H = [[p_x, (p_y + q_x)/2], [., q_y]]`` (per pixel).
        mask: (H, W) bool.
        sigma: filter scale (pixels, > 0).
        kind: ``"intensity"`` or ``"normals"``.

    Returns:
        ``(gaussian, mean)``: (H, W) float64 each, 0 outside the mask.
    """
    m = np.asarray(mask, bool)
    sigma = check_number("sigma", sigma, lo=0.0, lo_open=True)
    if kind == "intensity":
        f = as_array("field", field, shape=m.shape, dtype=np.float64)
        f = _fill_outside(f, m)
        a = ndi.gaussian_filter(f, sigma, order=(2, 0))  # d2/di2
        c = ndi.gaussian_filter(f, sigma, order=(0, 2))  # d2/dj2
        b = ndi.gaussian_filter(f, sigma, order=(1, 1))
    elif kind == "normals":
        nrm = as_array("field", field, shape=m.shape + (3,), dtype=np.float64)
        nz = np.maximum(nrm[..., 2], 0.05)
        p = _fill_outside(-nrm[..., 0] / nz, m)  # dz/dx, x = column
        q = _fill_outside(-nrm[..., 1] / nz, m)  # dz/dy, y = -row
        c = ndi.gaussian_filter(p, sigma, order=(0, 1))  # p_x
        a = -ndi.gaussian_filter(q, sigma, order=(1, 0))  # q_y
        b = 0.5 * (-ndi.gaussian_filter(p, sigma, order=(1, 0)) + ndi.gaussian_filter(q, sigma, order=(0, 1)))
    else:
        check_choice("kind", kind, CurvatureField)
    half_tr = 0.5 * (a + c)
    root = np.sqrt(0.25 * (a - c) ** 2 + b * b)
    k1, k2 = half_tr - root, half_tr + root
    return np.where(m, k1 * k2, 0.0), np.where(m, 0.5 * (k1 + k2), 0.0)


def select_sources(
    gc_p, mc_p, gc_q, mc_q, valid, *, tolerance: float = 0.05, widen_factor: float = 2.0, widen_steps: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Choose, per pixel, the nearest candidate whose curvatures match (4.17-4.18).

    A candidate ``q`` qualifies at tolerance ``t`` when
    ``|GC_q - GC_p| <= t |GC_p|`` and ``|MC_q - MC_p| <= t |MC_p|``.  The first
    (nearest) qualifying candidate at ``t = tolerance`` wins; when none does, ``t``
    is multiplied by ``widen_factor``, at most ``widen_steps`` times; when still
    none does, the nearest candidate (rank 0) is taken.

    Args:
        gc_p, mc_p: (P,) curvatures of the pixels.
        gc_q, mc_q: (P, K) curvatures of their candidates, nearest first.
        valid: (P, K) bool, existing candidates (a prefix of each row).
        tolerance, widen_factor, widen_steps: as in :class:`DGMCConfig`.

    Returns:
        ``(rank, tol)``: (P,) int rank of the chosen candidate (-1 where the pixel
        has none) and (P,) float tolerance at which it qualified (inf for the
        fallback, NaN where none).
    """
    gc_p = np.asarray(gc_p, np.float64)[:, None]
    mc_p = np.asarray(mc_p, np.float64)[:, None]
    gc_q = np.asarray(gc_q, np.float64)
    mc_q = np.asarray(mc_q, np.float64)
    valid = np.asarray(valid, bool)
    p = valid.shape[0]
    rank = np.full(p, -1, np.int64)
    tol_used = np.full(p, np.nan)
    has = valid[:, 0] if valid.shape[1] else np.zeros(p, bool)
    todo = has.copy()
    t = float(tolerance)
    for _ in range(int(widen_steps) + 1):
        ok = valid & (np.abs(gc_q - gc_p) <= t * np.abs(gc_p)) & (np.abs(mc_q - mc_p) <= t * np.abs(mc_p))
        hit = todo & ok.any(1)
        rank[hit] = np.argmax(ok[hit], 1)
        tol_used[hit] = t
        todo &= ~hit
        t *= float(widen_factor)
    rank[todo] = 0
    tol_used[todo] = np.inf
    return rank, tol_used


# --------------------------------------------------------------------------- DGMC


def dgmc_start(images, mask, normals, *, lights=None, config: DGMCConfig | None = None, points=None) -> DGMCResult:
    """DGMC start normals (seed 4.1.9, 4.16-4.18): highlight pixels take a matching boundary pixel's normal.

    For each highlight pixel ``p`` (:func:`detect_highlights`), its region's
    outer-boundary pixels are ordered by geodesic distance to ``p``
    (:func:`geodesic_candidates`, the nearest ``config.k_nearest`` kept); the
    nearest ``q`` whose Gaussian and mean curvature (:func:`hessian_curvatures`,
    4.16) are within ``config.tolerance`` of ``p``'s (4.17-4.18) is chosen, the
    tolerance widened by ``config.widen_factor`` up to ``config.widen_steps``
    times, else the nearest ``q`` (:func:`select_sources`); ``p``'s start normal is
    ``normals[q]``.  Highlight pixels whose region has no boundary (it fills its
    part of the mask) keep their given normal.

    Args:
        images: (N, H, W) grey or (N, H, W, 3) RGB images >= 0.
        mask: (H, W) bool object mask, not empty.
        normals: (H, W, 3) unit normals inside the mask (e.g. the Lambertian
            least-squares solution, ``solve_normals(..., solver="none")``): the
            normals copied from ``q`` and kept elsewhere.
        lights: lights for ``config.rule="lambertian"`` (see :func:`detect_highlights`).
        config: :class:`DGMCConfig`.
        points: (H, W, 3) surface points, for point lights.

    Returns:
        :class:`DGMCResult`.

    Raises:
        ValueError: wrong shapes, NaN or inf, non-unit normals inside the mask,
            an empty mask, or missing lights for ``rule="lambertian"``.
    """
    cfg = _check_config(config)
    grey, cmax = _check_images(images)
    h, w = grey.shape[1:]
    m = as_mask("mask", mask, (h, w))
    nrm = np.asarray(normals.numpy() if hasattr(normals, "numpy") and not isinstance(normals, np.ndarray) else normals)
    if nrm.shape != (h, w, 3):
        raise ValueError(f"normals: expected (H, W, 3) = ({h}, {w}, 3), got {nrm.shape}")
    nrm = as_array("normals", nrm, dtype=np.float64)
    check_unit("normals", nrm[m])

    hl = _detect(grey, cmax, m, lights, cfg, points)
    field = grey.mean(0) if cfg.curvature_field == "intensity" else nrm
    gc, mc = hessian_curvatures(field, m, sigma=cfg.sigma, kind=cfg.curvature_field)

    out = np.where(m[..., None], nrm, 0.0)
    source = np.full((h, w, 2), -1, np.int32)
    distance = np.full((h, w), np.nan)
    rank_map = np.full((h, w), -1, np.int32)
    tol_map = np.full((h, w), np.nan)
    for lab in range(1, hl.n_regions + 1):
        reg = hl.labels == lab
        bnd = outer_boundary(reg, m, cfg.connectivity)
        pix, src, dst = geodesic_candidates(reg, bnd, cfg.k_nearest)
        valid = src >= 0
        if not valid[:, 0].any():
            continue
        si, sj = np.divmod(np.maximum(src, 0), w)
        pi, pj = pix[:, 0], pix[:, 1]
        rank, tol = select_sources(
            gc[pi, pj], mc[pi, pj], gc[si, sj], mc[si, sj], valid,
            tolerance=cfg.tolerance, widen_factor=cfg.widen_factor, widen_steps=cfg.widen_steps,
        )
        ok = rank >= 0
        rows = np.nonzero(ok)[0]
        qi, qj = si[rows, rank[ok]], sj[rows, rank[ok]]
        pi, pj = pi[ok], pj[ok]
        out[pi, pj] = nrm[qi, qj]
        source[pi, pj, 0], source[pi, pj, 1] = qi, qj
        distance[pi, pj] = dst[rows, rank[ok]]
        rank_map[pi, pj] = rank[ok]
        tol_map[pi, pj] = tol[ok]
    return DGMCResult(
        normals=out.astype(np.float32),
        highlight=hl.region,
        source=source,
        distance=distance.astype(np.float32),
        rank=rank_map,
        tolerance=tol_map.astype(np.float32),
        gaussian=gc.astype(np.float32),
        mean=mc.astype(np.float32),
        highlights=hl,
        config=cfg,
    )


# --------------------------------------------------------------------------- the solved front


@dataclass
class FrontResult:
    """Output of :func:`gpps.pipeline.front.propagate_front` (the rings: :func:`front_rings`).

    Attributes:
        normals: (H, W, 3) float32: the given solution, with each highlight
            pixel's front solve where it won (see ``won``).
        albedo: (H, W, 3) float32, likewise.
        residual: (H, W) float32, likewise.
        flags: (H, W) int32 solver flags, likewise.
        iterations: (H, W) int32 cost evaluations of the front solve (its one
            start; 0 off the highlight region and on unreached pixels).
        ring: (H, W) int32 ring of each highlight pixel (1: next to the
            region's outer boundary, k: next to ring k - 1), 0 elsewhere, -1 on
            highlight pixels no ring reached (a region with no boundary).
        source: (H, W, 2) int32 ``(row, column)`` of the pixel ``q`` whose
            solved normal started ``p``; -1 elsewhere.
        won: (H, W) bool, highlight pixels where the front solve was kept.
        n_rings: number of rings solved.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    flags: np.ndarray
    iterations: np.ndarray
    ring: np.ndarray
    source: np.ndarray
    won: np.ndarray
    n_rings: int


def front_rings(mask, highlight) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rings of DGMC's solved front, from the masks alone.

    The front (:func:`gpps.pipeline.front.propagate_front`) solves the highlight pixels ring by ring: ring 1 is
    the highlight pixels with a solved 8-neighbour (a mask pixel outside the highlights), ring ``k`` those next
    to ring ``k - 1``: the 8-neighbour breadth-first distance from the solved pixels, through highlight pixels.
    No solve changes it, so all rings are found here at once; so are the sources (4.17-4.18: each ring pixel's
    nearest neighbour solved before its ring whose curvatures match, :func:`gpps.kernels.front.front_source_kernel`
    on the device), and only the start normals wait for the earlier rings' solves.

    That distance is the chessboard distance to the nearest solved pixel wherever a chain of highlight pixels
    leads there one step a ring, which holds for most highlight regions (their solved pixels surround them).
    So the rings come from :func:`scipy.ndimage.distance_transform_cdt` on the highlights' bounding box, and are
    checked: every highlight pixel at distance ``k > 1`` needs a highlight 8-neighbour at ``k - 1`` (then, by
    induction on ``k``, the walk through highlight pixels reaches it at ``k`` too, and it cannot reach it
    sooner).  Where the check fails (a region reached round a corner, or not at all) the breadth-first walk
    itself runs (:func:`_front_rings_walk`).  Both give the same rings (tests/test_dgmc.py); on issue 20's 256^2
    capture (18.8k highlight pixels, 32 rings) this takes 0.95 ms on the 2-core development CPU, the walk alone
    2.15 ms (``perf/results/s43``).  A ring's pixels are listed in raster order (their order changes no result:
    every ring pixel is solved and merged on its own).

    Args:
        mask: (H, W) bool object mask.
        highlight: (H, W) bool highlight region (only its pixels inside ``mask`` count).

    Returns:
        ``(ring, pixels, sizes)``: (H, W) int32 ring of each highlight pixel (1, 2, ...; -1 where no ring
        reaches it, a region with no solved pixel next to it; 0 off the highlights); (P,) int64 flat indices
        ``y * W + x`` of the ring pixels, ring 1 first, each ring in raster order; (n_rings + 1,) int64 pixels per
        ring (``sizes[0] = 0``), so ring ``k`` is ``pixels[sizes[:k].sum() : sizes[:k + 1].sum()]``.
    """
    m = as_mask("mask", mask, allow_empty=True)
    h, w = m.shape
    hl = np.asarray(highlight, bool)
    if hl.shape != (h, w):
        raise ValueError(f"highlight: expected shape ({h}, {w}), got {hl.shape}")
    hl = hl & m
    ring = _front_rings_distance(m, hl)
    if ring is None:
        ring = _front_rings_walk(m, hl)
    return _rings_listed(ring)


def _rings_listed(ring) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`front_rings`' ``(ring, pixels, sizes)`` from its ring map: the pixels ring by ring, in raster order."""
    flat = ring.ravel()
    pix = np.flatnonzero(flat > 0)
    if pix.size == 0:
        return ring, np.zeros(0, np.int64), np.zeros(1, np.int64)
    r = flat[pix]
    n = int(r.max())
    # (a stable sort of 16-bit keys is a radix sort in numpy)
    pixels = pix[np.argsort(r.astype(np.uint16) if n < 65536 else r, kind="stable")].astype(np.int64)
    sizes = np.bincount(r, minlength=n + 1).astype(np.int64)
    sizes[0] = 0
    return ring, pixels, sizes


def _front_rings_distance(m, hl) -> np.ndarray | None:
    """The ring map of :func:`front_rings` as the chessboard distance to the solved pixels, or None where the
    check of :func:`front_rings`' docstring fails (the caller walks then).

    The distance is taken to every solved pixel (a mask pixel outside the highlights) in the highlights' bounding
    box grown by one pixel, which holds every solved pixel next to a highlight: it is at most a pixel's walking
    distance, and the check makes it equal (a pixel at 1 lies next to a solved pixel; one at ``k > 1`` next to a
    highlight pixel at ``k - 1``).
    """
    ring = np.where(hl, -1, 0).astype(np.int32)
    if not hl.any():
        return ring
    rows = np.flatnonzero(hl.any(axis=1))
    cols = np.flatnonzero(hl.any(axis=0))
    i0, i1 = max(rows[0] - 1, 0), min(rows[-1] + 2, hl.shape[0])
    j0, j1 = max(cols[0] - 1, 0), min(cols[-1] + 2, hl.shape[1])
    hc = hl[i0:i1, j0:j1]
    solved = m[i0:i1, j0:j1] & ~hc
    if not solved.any():
        return ring  # (no solved pixel next to any highlight: none reached)
    d = ndi.distance_transform_cdt(~solved, metric="chessboard")  # (int32)
    big = np.iinfo(np.int32).max // 2
    dh = np.pad(np.where(hc, d, big), 1, constant_values=big)
    hh, ww = hc.shape
    nb = np.full((hh, ww), big, np.int32)
    for di, dj in _OFFSETS:
        np.minimum(nb, dh[1 + di:1 + di + hh, 1 + dj:1 + dj + ww], out=nb)
    dk = d[hc]
    if not np.all((dk == 1) | (nb[hc] == dk - 1)):
        return None
    ring[i0:i1, j0:j1][hc] = dk
    return ring


def _front_rings_walk(m, hl) -> np.ndarray:
    """The ring map of :func:`front_rings` by the breadth-first walk from the seeds through the highlight pixels
    (``hl`` inside ``m``), one ring a step."""
    h, w = m.shape
    # breadth-first on flat indices of the image padded by one pixel (the pad is never a highlight), from the
    # solved pixels next to a highlight; each step visits only the last ring's neighbours
    wpad = w + 2
    steps = np.array([di * wpad + dj for di, dj in _OFFSETS])
    todo = np.pad(hl, 1).ravel()
    seen = np.zeros(todo.size, np.int64)
    front = np.flatnonzero(np.pad(m & ~hl & ndi.binary_dilation(hl, _structure(8)), 1))
    ring = np.where(hl, -1, 0).astype(np.int32)
    k = 0
    while front.size:
        nb = (front[:, None] + steps).ravel()
        nb = nb[todo[nb]]
        if nb.size == 0:
            break
        todo[nb] = False
        # one entry per pixel (the last of its repeats)
        idx = np.arange(nb.size)
        seen[nb] = idx
        nb = nb[seen[nb] == idx]
        k += 1
        ring.ravel()[(nb // wpad - 1) * w + (nb % wpad - 1)] = k
        front = nb
    return ring
