"""Clipped observations of float images, at whatever value the clip sits.

A raw camera image clips at the sensor's full scale; divided by the light intensities (as photometric stereo
wants its images) the clipped highlight pixels sit at ``1 / intensity``, e.g. 1.25, a value nothing marks as a
full scale (:data:`gpps.names.CLIP_LEVELS`).  A fit that trusts them pulls the normals and the material toward a
highlight too dim (issue 20's benchmark capture: 2-4 % of the observations clipped, 1.2 deg mean normal error
instead of 0.02).  The physics of a clipping sensor gives the rule, per image ``n`` and channel ``c`` over the
mask's pixels (constants in :mod:`gpps.names`):

* the *plateau*: the pixels whose value equals the image-channel's maximum (within ``PLATEAU_ULPS`` float32 ulps,
  relative): a clipping sensor gives one identical value, and dividing by one intensity per image and channel
  keeps them identical;
* a clip is a *pile-up*: the plateau holds at least ``PLATEAU_MIN`` pixels and at least ``PLATEAU_PILEUP`` times
  the mean pixel count of the next ``PLATEAU_LEVELS`` lower distinct values (quantised, unclipped data has
  similar counts at its top levels; a clip piles the whole bright tail into the top one);
* it is not a flat, uniformly lit region: those pixels' values in at least one other image spread by more than
  ``PLATEAU_SPREAD`` (relative); a flat uniform-albedo region under a directional light has one value in every
  image, clipped highlight pixels have different normals and differ elsewhere;
* it is not nearly everything: below ``SATURATED_SHARE`` of the image's observations (more is
  :func:`gpps.flows.photometric.check_observations`' "everything saturated" case).

An observation (pixel, image) is clipped when any of its channels lies on a plateau taken as clipped.
"""

from __future__ import annotations

import numpy as np

from gpps import names
from gpps.host.observations import gather_masked

__all__ = ["clipped_observations"]

_TOL = names.PLATEAU_ULPS * float(np.finfo(np.float32).eps)  # relative width of "the same value"
#: the largest values :func:`_levels_below` selects beyond a plateau's pixels at first (more when they do not hold
#: its levels): 8-bit data holds a level in about P / 256 pixels
_TOP_MARGIN = 256
#: the sample stride of :func:`_largest`'s threshold
_STRIDE = 16


def _reason(top, count, share) -> str | None:
    """Why a plateau (its value, pixel count and share of the image's observations) cannot be a clip, or None
    (before the pile-up and flat-region tests, which need the values below it and the other images)."""
    if not top > 0.0:
        return "black"
    if count < names.PLATEAU_MIN:
        return f"fewer than {names.PLATEAU_MIN} pixels"
    if share >= names.SATURATED_SHARE:
        return f"nearly everything ({100 * share:.0f}% of the observations)"
    return None


def _levels_below(rows, plateau_lo, count, levels):
    """The next ``levels`` lower distinct values of each row and their pixel counts.

    Args:
        rows: (M, P) values (-inf: out of use).
        plateau_lo: (M,) the plateau's lower edge (values at or above it are on the plateau).
        count: (M,) the plateau's pixels.
        levels: how many lower distinct values.

    Returns:
        ``(values, counts)``: (M, levels) float (-inf where a row has fewer) and (M, levels) int (0 there).

    Cost: the rule (level by level, the largest value below the previous level's lower edge and the count at or
    above its own; tests/test_clipping.py holds it written as it reads, over whole rows) only needs a row's largest
    values: each row's ``count`` plus :data:`_TOP_MARGIN` largest are selected (``np.partition``, one pass) and
    sorted, and the walk runs on them, taking twice as many while the selection's smallest value is not below the
    last level's lower edge (then a value outside it could still count).  The same values and counts as the rule over whole rows, one pass over a
    row instead of two a level.
    """
    m, p = rows.shape
    values = np.full((m, levels), -np.inf)
    counts = np.zeros((m, levels), np.int64)
    tol = rows.dtype.type(_TOL)
    for r in range(m):
        row = rows[r]
        k = min(p, int(count[r]) + _TOP_MARGIN)
        while True:
            top = _largest(row, k)  # (k,) ascending: the k largest
            lo, above, exact = plateau_lo[r], int(count[r]), True
            got = []
            for _ in range(levels):
                at = int(np.searchsorted(top, lo, side="left"))  # top[:at] < lo
                if at == 0:  # no value below lo among the k largest
                    exact = k >= p
                    break
                v = top[at - 1]
                if not np.isfinite(v):
                    break
                lo = v - np.abs(v) * tol
                at_or_above = k - int(np.searchsorted(top, lo, side="left"))
                got.append((v, at_or_above - above))
                above = at_or_above
            if exact and k < p and not top[0] < lo:
                exact = False  # (a value outside the k largest may still be at or above the last edge)
            if exact:
                break
            k = min(p, 2 * k)
        for i, (v, cnt) in enumerate(got):
            values[r, i] = v
            counts[r, i] = cnt
    return values, counts


def _largest(row, k: int) -> np.ndarray:
    """The ``k`` largest values of ``row`` (1-D), sorted ascending: ``np.sort(np.partition(row, p - k)[p - k:])``.

    A full partition reads and moves the whole row (0.24 ms for 65k float32 values); here a threshold comes from
    every :data:`_STRIDE`-th value (their ``2 k / stride + 8``-th largest), one compare keeps the values at or
    above it, and only those are sorted.  When they are at least ``k`` they hold the ``k`` largest (every value
    left out is below all of them), so the result is the partition's exactly; otherwise (a sample that missed a
    dense top) the partition runs.
    """
    p = row.size
    if k >= p:
        return np.sort(row)
    if p >= 8 * _STRIDE and 4 * k <= p:
        sub = row[::_STRIDE]
        j = min(sub.size - 1, 2 * k // _STRIDE + 8)
        thr = np.partition(sub, sub.size - 1 - j)[sub.size - 1 - j]
        kept = row[row >= thr]
        if kept.size >= k:
            kept.sort()
            return kept[kept.size - k:]
    return np.sort(np.partition(row, p - k)[p - k:])


def clipped_observations(images, mask, *, valid=None, gathered=None) -> tuple[np.ndarray | None, dict]:
    """The observations of float images that are not clipped, by the plateau rule of this module.

    Args:
        images: (N, H, W, C) or (N, H, W) (one channel) float images >= 0, already checked (finite).
        mask: (H, W) bool pixels to look at; the others are never taken as clipped.
        valid: optional (N, H, W) bool observations already in use; the others take no part in the statistics
            and stay out of the result.
        gathered: optional ``(idx, x)``: ``np.flatnonzero(mask)`` and the images' observations there,
            :func:`gpps.host.observations.gather_masked` (a caller that reads them too gathers them once).

    Returns:
        ``(keep, info)``: ``keep`` the (N, H, W) bool observations to use (``valid`` when given, else all)
        without the clipped ones, or None when no plateau is taken as clipped.  ``info``: ``"observations"``
        (int, clipped observations inside the mask), ``"clipped_images"`` (list of the image indices with any)
        and ``"images"``, one dict per image: ``"value"`` (the plateau's value: the largest clipped channel's, else
        the brightest channel's), ``"count"`` (its pixels), ``"observations"`` (the image's clipped
        observations), ``"clipped"`` (bool), ``"reason"`` (None when clipped, else why the brightest channel's
        plateau is not a clip) and ``"channels"``: per channel ``value``, ``count`` (the plateau), ``below``
        (the pixel counts of the next lower distinct values, up to :data:`gpps.names.PLATEAU_LEVELS`, for the
        plateaus that got as far as the pile-up test, else None), ``clipped`` and ``reason``.
    """
    img = np.asarray(images)
    if img.ndim == 3:
        img = img[..., None]
    n, h, w, c = img.shape
    m = np.asarray(mask, bool)
    if gathered is None:
        idx = np.flatnonzero(m)
        x = gather_masked(img, idx)  # (N, C, P) the mask's observations
    else:
        idx, x = gathered
        if x.shape != (n, c, idx.size):
            raise ValueError(f"gathered: expected observations of shape {(n, c, idx.size)}, got {x.shape}")
        if valid is not None:
            x = x.copy()  # (the caller's: out-of-use observations are set to -inf below)
    tol = x.dtype.type(_TOL)
    used = None
    if valid is not None:
        used = np.asarray(valid, bool).reshape(n, h * w)[:, idx]  # (N, P)
        x[np.broadcast_to(~used[:, None, :], x.shape)] = -np.inf  # (-inf: never on a plateau, never a level)
    p_used = np.full(n, idx.size) if used is None else np.count_nonzero(used, axis=1)
    top = x.max(axis=-1) if idx.size else np.zeros((n, c), x.dtype)  # (N, C)
    lo = top - np.abs(top) * tol  # (N, C) the plateau's lower edge
    count = np.count_nonzero(x >= lo[..., None], axis=-1)  # (N, C) its pixels

    why = {(k, j): _reason(float(top[k, j]), int(count[k, j]), count[k, j] / max(int(p_used[k]), 1))
           for k in range(n) for j in range(c)}
    cand = [kj for kj, r in why.items() if r is None]
    below = {}
    if cand:  # the pile-up: the plateau against the next lower distinct values (only where it can be a clip)
        ks, js = np.array([kj[0] for kj in cand]), np.array([kj[1] for kj in cand])
        _, counts = _levels_below(x[ks, js], lo[ks, js], count[ks, js], names.PLATEAU_LEVELS)
        for i, kj in enumerate(cand):
            got = counts[i][counts[i] > 0]
            below[kj] = got.tolist()
            per_level = float(got.mean()) if got.size else 0.0
            if count[kj] < names.PLATEAU_PILEUP * per_level:
                why[kj] = (f"no pile-up ({int(count[kj])} pixels, fewer than {names.PLATEAU_PILEUP:g} times the "
                           f"{per_level:.3g} per value of the next lower ones)")
            elif not _varies_elsewhere(x, np.flatnonzero(x[kj] >= lo[kj]), *kj):
                why[kj] = ("the same values in every other image (a flat, uniformly lit region)" if n > 1
                           else "no other image to tell a flat region from a clip")

    clipped = np.zeros((n, idx.size), bool)  # (N, P)
    images_info = []
    for k in range(n):
        channels = []
        for j in range(c):
            if why[k, j] is None:
                clipped[k] |= x[k, j] >= lo[k, j]
            channels.append({"value": float(top[k, j]), "count": int(count[k, j]), "below": below.get((k, j)),
                             "clipped": why[k, j] is None, "reason": why[k, j]})
        taken = [ch for ch in channels if ch["clipped"]]
        head = max(taken or channels, key=lambda ch: ch["value"])
        images_info.append({"value": head["value"], "count": head["count"],
                            "observations": int(np.count_nonzero(clipped[k])), "clipped": bool(taken),
                            "reason": head["reason"], "channels": channels})
    info = {"observations": int(np.count_nonzero(clipped)),
            "clipped_images": [k for k, im in enumerate(images_info) if im["clipped"]], "images": images_info}
    if not info["observations"]:
        return None, info
    keep = np.ones((n, h * w), bool) if valid is None else np.array(np.asarray(valid, bool).reshape(n, h * w))
    for k in info["clipped_images"]:  # (a scatter of the few clipped pixels: fancy-indexing all P is ~20x slower)
        keep[k, idx[clipped[k]]] = False
    return keep.reshape(n, h, w), info


def _varies_elsewhere(x, plateau, k, j) -> bool:
    """Whether the ``plateau`` pixels (their indices into P) of image ``k``, channel ``j`` spread by more than
    :data:`gpps.names.PLATEAU_SPREAD` (relative to their largest value) in at least one other image of ``x``
    (N, C, P); observations out of use (-inf) take no part."""
    for m in range(x.shape[0]):
        if m == k:
            continue
        v = np.take(x[m, j], plateau)
        v = v[np.isfinite(v)]
        if v.size < 2:
            continue
        hi, lo = float(v.max()), float(v.min())
        if hi > 0.0 and hi - lo > names.PLATEAU_SPREAD * hi:
            return True
    return False
