"""Crease cut and stitch: normal integration that cuts the normal map at its creases, integrates each piece on
its own and sets the pieces' free constants from the cut edges (a host prototype, numpy / scipy only).

Why: a least-squares integrator (Poisson, and BiNI while its weights are still 1/2) couples the gradients of
neighbouring pixels across every edge.  Where the normals jump (a crease, an occluding rim, two overlapping
planes) the two sides' gradients are not the differences of one continuous surface, and the quadratic
coupling bends both sides.  Cutting those edges makes each piece's system consistent again (exact for planar
pieces); the piece constants (an offset of the depth, orthographic; of the log-depth, i.e. a scale,
perspective) are then chosen by least squares over the cut edges, so a crease that is continuous (a fold, a
cube's edge) is stitched back continuously and the result is one depth map.

Steps (:func:`integrate_creases`):

1. :func:`crease_edges`: an edge between 4-neighbours ``a, b`` (along one image axis) is a crease when the
   normal's *second* difference across it, ``D = (n_b - n_a) - ((n_a - n_{a-1}) + (n_{b+1} - n_b)) / 2``
   (unit normals, 3-vectors; ``|D|`` is an angle in radians to first order), exceeds
   ``max(floor, z * sigma)``.  Principle: a surface that is resolved at pixel scale has a normal field whose
   first difference varies slowly from edge to edge (constant curvature gives ``D = 0``, however strong);
   a crease or an occlusion puts a spike into the first difference.  ``sigma`` is a robust standard
   deviation (1.4826 MAD) of ``|D|`` over the map (its noise and quantisation level, 0 on noise-free maps),
   ``z`` a Gaussian outlier level, and ``floor`` the smallest crease worth cutting (default 2 degrees: above
   8-bit quantisation's second-difference spread, about 0.5 degree, and far below the 8-21 degree creases of
   the test scenes).  Neither is tuned on real data.
2. :func:`crease_pieces`: the connected pieces of the mask once the crease edges are removed.
3. Each piece is integrated alone, by the N_z^2-weighted Poisson system of (4.20)
   (:func:`gpps.host.poisson.edge_system`, sparse LU) or by BiNI's IRLS (:func:`bini_irls`, Jacobi-PCG as
   BiNI's reference) in which a cut edge is a missing neighbour.
4. :func:`stitch`: per-piece constants ``c`` minimising ``sum_e w_e (u_b + c_Q - u_a - c_P - t_e)^2`` over
   the cut edges ``e = (a in P, b in Q)``: ``t_e`` the N_z^2-weighted trapezoid target (each side's own
   gradient extrapolated to the edge's midpoint, ``"trapezoid"``) or 0 (``"continuity"``); ``w_e`` the
   edge's N_z^2 weight.  Optionally (``robust=True``) iteratively reweighted with Cauchy weights of the
   residuals, so a few rim edges whose targets disagree with the rest do not set a piece's constant.

Optionally (``refine="bini"``) BiNI's IRLS on the uncut graph starts from the stitched solution.

Units: orthographic ``u`` is depth (scene units, the camera's pixel size sets the scale); perspective ``u``
is log-depth and the result ``exp(u)`` is depth up to one scale.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from gpps.names import CUT_STITCH_NAMES

from gpps._check import check_choice
from gpps.host.poisson import divergence_rhs, edge_system, laplacian, pixel_gradients, solve_direct

__all__ = ["CreaseResult", "crease_edges", "crease_pieces", "separating_cuts", "bini_irls", "stitch", "stitch_bini",
           "stitch_cut_pieces",
           "integrate_creases"]

INNERS = ("poisson", "bini")
STITCHES = ("trapezoid", "continuity")
REFINES = ("none", "bini")
TARGETS = ("trapezoid", "mid")


def _check_map(normals, mask):
    n = np.asarray(normals)
    m = np.asarray(mask)
    if m.ndim != 2 or m.dtype != bool:
        raise ValueError(f"mask: expected an (H, W) bool array, got shape {m.shape}, dtype {m.dtype}")
    if n.ndim != 3 or n.shape[:2] != m.shape or n.shape[2] != 3:
        raise ValueError(f"normals: expected an (H, W, 3) array with (H, W) = mask's {m.shape}, got {n.shape}")
    n = n.astype(np.float64)
    ln = np.linalg.norm(n, axis=-1)
    valid = m & np.all(np.isfinite(n), axis=-1) & (ln > 0)
    if valid.sum() < 2:
        raise ValueError(f"mask: expected at least 2 pixels with finite non-zero normals, got {int(valid.sum())}")
    with np.errstate(all="ignore"):
        n = np.where(valid[..., None], n / ln[..., None], 0.0)
    return n, valid


def _check_camera(camera):
    if camera is None or not hasattr(camera, "is_perspective"):
        raise ValueError(f"camera: expected gpps.camera.Orthographic or Perspective, got {camera!r}")


def _edges(valid):
    """(H, W) bool j-edges ``(i, j)-(i, j+1)`` and i-edges ``(i, j)-(i+1, j)`` inside ``valid``."""
    ex = np.zeros(valid.shape, bool)
    ey = np.zeros(valid.shape, bool)
    ex[:, :-1] = valid[:, :-1] & valid[:, 1:]
    ey[:-1, :] = valid[:-1, :] & valid[1:, :]
    return ex, ey


def _second_difference(n, e):
    """``|D|`` of the module docstring along axis 1 for the edges ``e`` (H, W) of the (H, W, 3) normals ``n``.

    A side's first difference is used only where its edge exists; with neither, ``D`` is the first difference.

    Returns:
        ``(mag, peak)``: (H, W) ``|D|`` (0 where no edge) and bool, ``|D|`` at least its two neighbours' along
        the axis.
    """
    h, w = e.shape
    d = np.zeros((h, w, 3))
    d[:, :-1] = n[:, 1:] - n[:, :-1]
    d = np.where(e[..., None], d, 0.0)
    left = np.zeros_like(d)  # the edge before: (i, j-1)-(i, j)
    left[:, 1:] = d[:, :-1]
    el = np.zeros_like(e)
    el[:, 1:] = e[:, :-1]
    right = np.zeros_like(d)  # the edge after: (i, j+1)-(i, j+2)
    right[:, :-1] = d[:, 1:]
    er = np.zeros_like(e)
    er[:, :-1] = e[:, 1:]
    cnt = el.astype(float) + er
    side = (np.where(el[..., None], left, 0.0) + np.where(er[..., None], right, 0.0)) / np.maximum(cnt, 1)[..., None]
    mag = np.where(e, np.linalg.norm(d - side, axis=-1), 0.0)
    # the normal must change across the edge itself (at least half the second difference): beside a mask border
    # the one-sided side term makes the edge after a crease as large as the crease's own, and it must not win
    # the suppression below
    cand = np.where(np.linalg.norm(d, axis=-1) >= mag / 2, mag, 0.0)
    # non-maximum suppression along the axis: a crease's spike in the first difference leaves half its size in
    # the second differences of the two edges beside it; only the peak is the crease
    prev = np.zeros_like(mag)
    prev[:, 1:] = cand[:, :-1]
    nxt = np.zeros_like(mag)
    nxt[:, :-1] = cand[:, 1:]
    return mag, (cand > 0) & (cand >= prev) & (cand >= nxt)


def crease_edges(normals, mask, *, floor_deg: float = 2.0, z: float = 4.0, threshold_deg: float | None = None):
    """The crease edges of a normal map (second-difference test of the module docstring).

    Args:
        normals: (H, W, 3) normals (gpps frame; normalised here).
        mask: (H, W) bool pixels.
        floor_deg: smallest second difference that is cut (degrees).
        z: the cut also needs ``|D| > z * sigma`` (robust standard deviations of ``|D|`` over the map).
        threshold_deg: a fixed threshold (degrees) instead of ``max(floor, z * sigma)``.

    Returns:
        ``(cut_x, cut_y, info)``: (H, W) bool, the cut j-edges ``(i, j)-(i, j+1)`` and i-edges
        ``(i, j)-(i+1, j)``; ``info`` dict with ``threshold_deg`` and ``sigma_deg``.

    Raises:
        ValueError: bad shapes, fewer than 2 valid pixels, or a non-positive / non-finite parameter.
    """
    for name, v in (("floor_deg", floor_deg), ("z", z)) + ((("threshold_deg", threshold_deg),) if threshold_deg is not None else ()):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
            raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
    n, valid = _check_map(normals, mask)
    ex, ey = _edges(valid)
    dx, px = _second_difference(n, ex)
    dy, py = _second_difference(n.transpose(1, 0, 2), ey.T)
    dy, py = dy.T, py.T
    sample = np.concatenate([dx[ex], dy[ey]])
    sigma = float(1.4826 * np.median(sample)) if sample.size else 0.0
    thr = np.deg2rad(threshold_deg) if threshold_deg is not None else max(np.deg2rad(floor_deg), z * sigma)
    return ex & px & (dx > thr), ey & py & (dy > thr), {"threshold_deg": float(np.rad2deg(thr)),
                                             "sigma_deg": float(np.rad2deg(sigma))}


def crease_pieces(valid, ex, ey):
    """Connected pieces of the pixel graph with the edges ``ex``, ``ey``.

    Args:
        valid: (H, W) bool pixels.
        ex, ey: (H, W) bool kept j- and i-edges (inside ``valid``).

    Returns:
        ``(labels, n)``: (H, W) int, 1..n on ``valid``, 0 elsewhere.
    """
    h, w = valid.shape
    idx = np.arange(h * w).reshape(h, w)
    a = np.concatenate([idx[:, :-1][ex[:, :-1]], idx[:-1, :][ey[:-1, :]]])
    b = np.concatenate([idx[:, 1:][ex[:, :-1]], idx[1:, :][ey[:-1, :]]])
    g = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(h * w, h * w))
    _, lab = connected_components(g, directed=False)
    flat = lab.reshape(h, w)
    _, inv = np.unique(flat[valid], return_inverse=True)
    out = np.zeros((h, w), int)
    out[valid] = inv + 1
    return out, int(inv.max()) + 1


def separating_cuts(valid, cut_x, cut_y):
    """The cut edges that separate pieces; the others (slits) dropped.

    A cut edge whose two pixels stay connected through uncut edges adds no free constant (nothing for a stitch
    to set) and only removes the coupling across it.  Dropping such an edge joins two pixels of one piece, so
    no piece changes: one pass removes every slit, the pieces (and their labels) stay those of the full cut,
    and every kept cut still separates two pieces.

    Args:
        valid: (H, W) bool pixels.
        cut_x, cut_y: (H, W) bool cut j-edges ``(i, j)-(i, j+1)`` and i-edges ``(i, j)-(i+1, j)`` (edges leaving
            ``valid`` are ignored).

    Returns:
        ``(cut_x, cut_y, labels, n_pieces)``: the separating cuts (subsets of the input's edges inside
        ``valid``), the (H, W) int pieces 1..n_pieces (0 outside ``valid``) and their number.

    Raises:
        ValueError: ``valid``, ``cut_x`` or ``cut_y`` not (H, W) bool arrays of one shape.
    """
    v = np.asarray(valid)
    if v.ndim != 2 or v.dtype != bool:
        raise ValueError(f"valid: expected an (H, W) bool array, got shape {v.shape}, dtype {v.dtype}")
    cuts = []
    for name, c in (("cut_x", cut_x), ("cut_y", cut_y)):
        c = np.asarray(c)
        if c.shape != v.shape or c.dtype != bool:
            raise ValueError(f"{name}: expected an (H, W) = {v.shape} bool array, got shape {c.shape}, dtype {c.dtype}")
        cuts.append(c)
    ex, ey = _edges(v)
    cx, cy = ex & cuts[0], ey & cuts[1]
    labels, npc = crease_pieces(v, ex & ~cx, ey & ~cy)
    sx = np.zeros_like(cx)
    sy = np.zeros_like(cy)
    sx[:, :-1] = cx[:, :-1] & (labels[:, :-1] != labels[:, 1:])
    sy[:-1, :] = cy[:-1, :] & (labels[:-1, :] != labels[1:, :])
    return sx, sy, labels, npc


def _coefficients(n, valid, camera, min_nz):
    """BiNI's ``N`` and the per-pixel steps ``g`` (``N g = m``) from :func:`pixel_gradients`."""
    gj, gi, nzj, nzi = pixel_gradients(n, valid, camera, min_nz)
    return gj, gi, nzj, nzi


def _weighted_system(valid, ex, ey, gj, gi, nzj, nzi):
    """N_z^2-weighted edge weights and targets of (4.20) restricted to the edges ``ex``, ``ey``."""
    scale = float(np.mean(nzj[valid] ** 2))
    wx, wy, tx, ty = edge_system(valid, gj, gi, nzj ** 2 / scale, nzi ** 2 / scale)
    return np.where(ex, wx, 0.0), np.where(ey, wy, 0.0), tx, ty


def mid_normal_targets(n, valid, camera, min_nz: float = 1e-3):
    """Edge targets from the mid-normal ``n_a + n_b`` of each edge, evaluated at the edge's midpoint.

    For a surface whose cross-section along the edge is a circular arc (a plane, a sphere, a cylinder), the
    chord's slope between two samples equals the tangent's slope at the bisecting normal, so this target is
    exact there however steep the arc, where the trapezoid average of the two tangents (``(g_a + g_b) / 2``)
    grows without bound toward a grazing rim.

    Args:
        n: (H, W, 3) unit normals.
        valid: (H, W) bool.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        min_nz: slope bound (as :func:`gpps.host.poisson.pixel_gradients`).

    Returns:
        ``(tx, ty)``: (H, W) float64 targets of the j-edges ``(i, j)-(i, j+1)`` and i-edges ``(i, j)-(i+1, j)``
        (0 where there is no edge), in ``u`` per pixel step.
    """
    h, w = valid.shape
    ex, ey = _edges(valid)
    out = []
    for e, sl_a, sl_b, dj, di in ((ex, np.s_[:, :-1], np.s_[:, 1:], 0.5, 0.0), (ey, np.s_[:-1, :], np.s_[1:, :], 0.0, 0.5)):
        m = np.zeros((h, w, 3))
        m[sl_a] = n[sl_a] + n[sl_b]
        nx, ny, nz = m[..., 0], m[..., 1], m[..., 2]
        ln = np.maximum(np.linalg.norm(m, axis=-1), 1e-300)
        with np.errstate(all="ignore"):
            if camera.is_perspective:
                cx, cy = camera.principal_point((h, w))
                jj, ii = np.meshgrid(np.arange(w, dtype=np.float64) + dj, np.arange(h, dtype=np.float64) + di)
                mm = np.minimum((nx * (jj - cx) / camera.fx - ny * (ii - cy) / camera.fy - nz) / ln, -min_nz)
                t = -nx / ln / (camera.fx * mm) if dj else ny / ln / (camera.fy * mm)
            else:
                den = np.maximum(nz / ln, min_nz)
                t = camera.pixel_size * nx / ln / den if dj else -camera.pixel_size * ny / ln / den
        out.append(np.where(e, t, 0.0))
    return tuple(out)


def _jacobi_pcg(A, b, x, tol, maxit):
    """BiNI's inner solver: Jacobi-preconditioned CG (diagonal clipped at 1e-5) to ``|r| <= tol |b|``."""
    d = 1.0 / np.clip(A.diagonal(), 1e-5, None)
    r = b - A @ x
    bb = float(b @ b)
    if bb == 0:
        return x, 0
    z = d * r
    p = z.copy()
    rz = float(r @ z)
    its = 0
    for _ in range(maxit):
        q = A @ p
        pq = float(p @ q)
        if pq <= 0:
            break
        a = rz / pq
        x = x + a * p
        r = r - a * q
        its += 1
        if float(r @ r) <= tol * tol * bb:
            break
        z = d * r
        rzn = float(r @ z)
        p = z + (rzn / rz) * p
        rz = rzn
    return x, its


def bini_irls(valid, ex, ey, gj, gi, nzj, nzi, u0=None, *, k: float = 2.0, max_iter: int = 150,
              tol: float = 1e-4, cg_tol: float = 1e-3, cg_max_iter: int = 5000):
    """BiNI's IRLS (Cao et al., ECCV 2022, eqs. (19)-(20)) on the pixel graph with the edges ``ex``, ``ey``.

    Each pixel owns four one-sided equations ``N (u_q - u_p) - N g`` (forward / backward along j and i);
    an edge that is not in ``ex`` / ``ey`` (outside the mask, or cut) is a missing neighbour, whose
    one-sided difference is 0 (BiNI's convention at mask borders).  Weights ``w+ = sigmoid(k ((N D-)^2 -
    (N D+)^2))``; inner Jacobi-PCG to relative residual ``cg_tol`` warm-started; stop when the energy's
    relative change is below ``tol``.  With every edge of the mask kept it is BiNI's reference algorithm.

    Args:
        valid: (H, W) bool pixels.
        ex, ey: (H, W) bool j- and i-edges to keep.
        gj, gi, nzj, nzi: (H, W) per-pixel steps and N factors (:func:`gpps.host.poisson.pixel_gradients`).
        u0: (H, W) start (None: 0, as BiNI).
        k, max_iter, tol, cg_tol, cg_max_iter: BiNI's parameters (its defaults).

    Returns:
        ``(u, info)``: (H, W) float64 solution (0 outside ``valid``); ``info`` with ``outer_iterations``,
        ``cg_iterations``, ``energy`` (list).
    """
    h, w = valid.shape
    mj, mi = nzj * gj, nzi * gi
    u = np.zeros((h, w)) if u0 is None else np.where(valid, np.asarray(u0, np.float64), 0.0)
    wpj = np.full((h, w), 0.5)
    wpi = np.full((h, w), 0.5)
    _, idx = laplacian(np.zeros((h, w)), np.zeros((h, w)), valid)
    ii, jj = np.unravel_index(idx, (h, w))

    def diffs(u):
        dp_j = np.zeros((h, w))
        dp_j[:, :-1] = np.where(ex[:, :-1], u[:, 1:] - u[:, :-1], 0.0)
        dm_j = np.zeros((h, w))
        dm_j[:, 1:] = dp_j[:, :-1]
        dp_i = np.zeros((h, w))
        dp_i[:-1, :] = np.where(ey[:-1, :], u[1:, :] - u[:-1, :], 0.0)
        dm_i = np.zeros((h, w))
        dm_i[1:, :] = dp_i[:-1, :]
        return dp_j, dm_j, dp_i, dm_i

    def energy(u, wpj, wpi):
        dp_j, dm_j, dp_i, dm_i = diffs(u)
        e = (wpj * (nzj * dp_j - mj) ** 2 + (1 - wpj) * (nzj * dm_j - mj) ** 2
             + wpi * (nzi * dp_i - mi) ** 2 + (1 - wpi) * (nzi * dm_i - mi) ** 2)
        return float(np.sum(e[valid]))

    e_old = energy(u, wpj, wpi)
    energies = []
    total = 0
    outer = 0
    for it in range(max_iter):
        # edge a -> b (b = right / down neighbour): W = N_a^2 w+_a + N_b^2 w-_b, flux N_a m_a w+_a + N_b m_b w-_b
        wx = np.zeros((h, w))
        fx = np.zeros((h, w))
        a = nzj[:, :-1] ** 2 * wpj[:, :-1]
        b = nzj[:, 1:] ** 2 * (1 - wpj[:, 1:])
        wx[:, :-1] = np.where(ex[:, :-1], a + b, 0.0)
        fx[:, :-1] = np.where(ex[:, :-1], nzj[:, :-1] * mj[:, :-1] * wpj[:, :-1] + nzj[:, 1:] * mj[:, 1:] * (1 - wpj[:, 1:]), 0.0)
        wy = np.zeros((h, w))
        fy = np.zeros((h, w))
        a = nzi[:-1, :] ** 2 * wpi[:-1, :]
        b = nzi[1:, :] ** 2 * (1 - wpi[1:, :])
        wy[:-1, :] = np.where(ey[:-1, :], a + b, 0.0)
        fy[:-1, :] = np.where(ey[:-1, :], nzi[:-1, :] * mi[:-1, :] * wpi[:-1, :] + nzi[1:, :] * mi[1:, :] * (1 - wpi[1:, :]), 0.0)
        with np.errstate(all="ignore"):
            tx = np.where(wx > 0, fx / wx, 0.0)
            ty = np.where(wy > 0, fy / wy, 0.0)
        A, _ = laplacian(wx, wy, valid)
        rhs = divergence_rhs(wx, wy, tx, ty).ravel()[idx]
        x, its = _jacobi_pcg(A, rhs, u.ravel()[idx], cg_tol, cg_max_iter)
        total += its
        u = np.zeros((h, w))
        u[ii, jj] = x
        dp_j, dm_j, dp_i, dm_i = diffs(u)
        with np.errstate(over="ignore"):
            wpj = 1.0 / (1.0 + np.exp(-k * ((nzj * dm_j) ** 2 - (nzj * dp_j) ** 2)))
            wpi = 1.0 / (1.0 + np.exp(-k * ((nzi * dm_i) ** 2 - (nzi * dp_i) ** 2)))
        e = energy(u, wpj, wpi)
        energies.append(e)
        outer = it + 1
        if e_old <= 0 or abs(e - e_old) / e_old < tol:
            break
        e_old = e
    return u, {"outer_iterations": outer, "cg_iterations": total, "energy": energies}


def stitch(u, labels, n_pieces, cut_x, cut_y, wx, wy, tx, ty, *, mode: str = "trapezoid", robust: bool = False,
           robust_scale: float = 2.0, robust_iterations: int = 10):
    """Per-piece constants from the cut edges (least squares on the graph of pieces).

    Args:
        u: (H, W) per-piece solution (each piece's constant arbitrary).
        labels: (H, W) int pieces 1..n_pieces (0 outside).
        n_pieces: number of pieces.
        cut_x, cut_y: (H, W) bool cut j- and i-edges.
        wx, wy, tx, ty: (H, W) the N_z^2-weighted edge weights and trapezoid targets of every edge
            (:func:`gpps.host.poisson.edge_system`).
        mode: ``"trapezoid"`` (target ``t_e``) or ``"continuity"`` (target 0).
        robust: Cauchy-reweight the cut edges by their residuals (``sigma = robust_scale * 1.4826 MAD``).
        robust_scale, robust_iterations: the reweighting's scale and rounds.

    Returns:
        ``(u_stitched, c)``: (H, W) ``u + c[labels]`` and the (n_pieces + 1,) constants (``c[0] = 0``); each
        connected group of pieces has its pixels' mean change 0.
    """
    if mode not in STITCHES:
        raise ValueError(f"mode: expected one of {STITCHES}, got {mode!r}")
    la = np.concatenate([labels[:, :-1][cut_x[:, :-1]], labels[:-1, :][cut_y[:-1, :]]])
    lb = np.concatenate([labels[:, 1:][cut_x[:, :-1]], labels[1:, :][cut_y[:-1, :]]])
    du = np.concatenate([(u[:, 1:] - u[:, :-1])[cut_x[:, :-1]], (u[1:, :] - u[:-1, :])[cut_y[:-1, :]]])
    we = np.concatenate([wx[:, :-1][cut_x[:, :-1]], wy[:-1, :][cut_y[:-1, :]]])
    te = np.concatenate([tx[:, :-1][cut_x[:, :-1]], ty[:-1, :][cut_y[:-1, :]]])
    if mode == "continuity":
        te = np.zeros_like(te)
    keep = (la != lb) & (we > 0)
    la, lb, d, we = la[keep], lb[keep], (te - du)[keep], we[keep]  # want c_b - c_a = d
    npc = n_pieces + 1
    c = np.zeros(npc)
    if la.size:
        g = sp.coo_matrix((np.ones(la.size), (la, lb)), shape=(npc, npc))
        ncomp, comp = connected_components(g, directed=False)
        rw = np.ones_like(we)
        for _ in range(robust_iterations + 1 if robust else 1):
            ww = we * rw
            rows = np.concatenate([la, lb, la, lb])
            cols = np.concatenate([lb, la, la, lb])
            vals = np.concatenate([-ww, -ww, ww, ww])
            A = sp.coo_matrix((vals, (rows, cols)), shape=(npc, npc)).tocsr()
            b = np.zeros(npc)
            np.add.at(b, lb, ww * d)
            np.add.at(b, la, -ww * d)
            # pin the first piece of each group (label 0 is its own group, pinned too)
            _, first = np.unique(comp, return_index=True)
            free = np.ones(npc, bool)
            free[first] = False
            c = np.zeros(npc)
            if free.any():
                c[free] = spla.spsolve(A[free][:, free].tocsc(), b[free])
            if not robust:
                break
            r = c[lb] - c[la] - d
            sigma = robust_scale * 1.4826 * float(np.median(np.abs(r)))
            if not sigma > 0:
                break
            rw = 1.0 / (1.0 + (r / sigma) ** 2)
        # each group's pixel-weighted mean change 0
        cnt = np.bincount(labels.ravel(), minlength=npc).astype(float)
        cnt[0] = 0
        gm = np.bincount(comp, weights=c * cnt, minlength=ncomp) / np.maximum(np.bincount(comp, weights=cnt, minlength=ncomp), 1)
        c = c - gm[comp]
        c[0] = 0
    return np.where(labels > 0, u + c[labels], 0.0), c


def _bini_forward_weights(u, ex, ey, nzj, nzi, k):
    """BiNI's forward weights ``w+ = sigmoid(k ((N D-)^2 - (N D+)^2))`` of ``u`` on the edges ``ex``, ``ey``
    (a missing edge's difference is 0), clipped to ``[1e-12, 1 - 1e-12]`` so an edge's total weight stays > 0."""
    out = []
    for uu, e, nz in ((u, ex, nzj), (u.T, ey.T, nzi.T)):
        dp = np.zeros_like(uu)
        dp[:, :-1] = np.where(e[:, :-1], uu[:, 1:] - uu[:, :-1], 0.0)
        dm = np.zeros_like(uu)
        dm[:, 1:] = dp[:, :-1]
        with np.errstate(over="ignore"):
            wp = 1.0 / (1.0 + np.exp(-k * ((nz * dm) ** 2 - (nz * dp) ** 2)))
        out.append(np.clip(wp, 1e-12, 1.0 - 1e-12))
    return out[0], out[1].T


def stitch_bini(u, labels, n_pieces, cut_x, cut_y, valid, gj, gi, nzj, nzi, *, k: float = 2.0, tol: float = 1e-4,
                max_iter: int = 150):
    """Per-piece constants by BiNI's own criterion: its bilateral energy restricted to the cut edges.

    A cut edge ``e = (a, b)`` (``b`` the right / lower neighbour, ``a`` in piece ``P``, ``b`` in ``Q``, ``P != Q``)
    owns two of BiNI's one-sided equations (Cao et al., ECCV 2022, (19)): ``a``'s forward one
    ``w+_a (N_a D_e - m_a)^2`` and ``b``'s backward one ``w-_b (N_b D_e - m_b)^2``, with
    ``D_e = u_b + c_Q - u_a - c_P``, ``m = N g`` and ``w-_b = 1 - w+_b``.  With the weights fixed this is a
    weighted least squares in the constants ``c`` (edge weight ``W_e = N_a^2 w+_a + N_b^2 w-_b``, target
    ``(N_a m_a w+_a + N_b m_b w-_b) / W_e``, solved by :func:`stitch`); the weights are then BiNI's
    ``w+ = sigmoid(k ((N D-)^2 - (N D+)^2))`` of the stitched ``u + c[labels]`` on the uncut graph (20), and the
    two steps repeat from ``w = 1/2`` (BiNI's start) until the energy's relative change is below ``tol``.  So a
    crease whose two sides meet is stitched continuously (the weights stay near 1/2), while an edge whose
    stitched difference is much larger than its neighbours' gets its weight moved to the one-sided equation
    that does not cross it, as BiNI keeps a jump.  The pieces' shapes are not touched.

    Args:
        u: (H, W) per-piece solution (each piece's constant arbitrary).
        labels: (H, W) int pieces 1..n_pieces (0 outside).
        n_pieces: number of pieces.
        cut_x, cut_y: (H, W) bool cut j- and i-edges (edges inside one piece are ignored).
        valid: (H, W) bool pixels (the uncut graph is every edge inside ``valid``).
        gj, gi, nzj, nzi: (H, W) per-pixel steps and N factors (:func:`gpps.host.poisson.pixel_gradients`).
        k: BiNI's sigmoid sharpness.
        tol: relative energy change that stops the iteration (BiNI's 1e-4).
        max_iter: iterations at most.

    Returns:
        ``(u_stitched, c, info)``: (H, W) ``u + c[labels]`` (0 outside), the (n_pieces + 1,) constants (each
        connected group of pieces keeps its pixels' mean) and ``info`` with ``iterations`` and ``energy`` (list).
    """
    valid = np.asarray(valid, bool)
    ex, ey = _edges(valid)
    cut_x = ex & np.asarray(cut_x, bool)
    cut_y = ey & np.asarray(cut_y, bool)
    cut_x[:, :-1] &= labels[:, :-1] != labels[:, 1:]
    cut_y[:-1, :] &= labels[:-1, :] != labels[1:, :]
    u = np.where(valid, np.asarray(u, np.float64), 0.0)
    mj, mi = nzj * gj, nzi * gi
    h, w = valid.shape
    c = np.zeros(n_pieces + 1)
    if not (cut_x.any() or cut_y.any()):
        return u, c, {"iterations": 0, "energy": []}

    def system(wpj, wpi):
        """Edge weights, targets (for :func:`stitch`) and the two equations' weights of every cut edge."""
        wx, wy, tx, ty = (np.zeros((h, w)) for _ in range(4))
        parts = []
        for W, T, cut, wp, nz, m, sa, sb in ((wx, tx, cut_x, wpj, nzj, mj, np.s_[:, :-1], np.s_[:, 1:]),
                                             (wy, ty, cut_y, wpi, nzi, mi, np.s_[:-1, :], np.s_[1:, :])):
            wa, wb = wp[sa], 1.0 - wp[sb]
            tot = nz[sa] ** 2 * wa + nz[sb] ** 2 * wb
            flux = nz[sa] * m[sa] * wa + nz[sb] * m[sb] * wb
            on = cut[sa]
            W[sa] = np.where(on, tot, 0.0)
            with np.errstate(all="ignore"):
                T[sa] = np.where(on, flux / tot, 0.0)
            parts.append((on, wa, wb, nz[sa], nz[sb], m[sa], m[sb], sa, sb))
        return wx, wy, tx, ty, parts

    def energy(us, parts):
        e = 0.0
        for on, wa, wb, na, nb, ma, mb, sa, sb in parts:
            d = us[sb] - us[sa]
            e += float(np.sum((wa * (na * d - ma) ** 2 + wb * (nb * d - mb) ** 2)[on]))
        return e

    wpj = np.full((h, w), 0.5)
    wpi = np.full((h, w), 0.5)
    energies = []
    us = u
    for it in range(max_iter):
        wx, wy, tx, ty, _ = system(wpj, wpi)
        us, c = stitch(u, labels, n_pieces, cut_x, cut_y, wx, wy, tx, ty)
        wpj, wpi = _bini_forward_weights(us, ex, ey, nzj, nzi, k)
        e = energy(us, system(wpj, wpi)[4])
        energies.append(e)
        if it > 0 and (energies[-2] <= 0 or abs(e - energies[-2]) / energies[-2] < tol):
            break
    return us, c, {"iterations": len(energies), "energy": energies}


def stitch_cut_pieces(u, normals, valid, camera, cut_x, cut_y, *, min_nz: float = 1e-3, mode: str = "mid",
                      k: float = 2.0, tol: float = 1e-4):
    """Set the free constants of the pieces of a solution integrated with the edges ``cut_x``, ``cut_y`` cut.

    The pieces are the connected parts of ``valid`` without the cut edges; their constants (an offset of ``u``:
    depth orthographic, log-depth perspective) come from the cut edges: ``mode="mid"``: :func:`stitch` with the
    mid-normal targets (:func:`mid_normal_targets`) and the N_z^2 edge weights of (4.20) (continuity);
    ``mode="bini"``: :func:`stitch_bini` (BiNI's bilateral energy of the cut edges, its IRLS with ``k``,
    ``tol``).  A piece without cut edges to another piece keeps its ``u`` exactly (its constant is 0.0).

    Args:
        u: (H, W) float64 solution of each piece (e.g. BiNI with the cut edges as missing neighbours).
        normals: (H, W, 3) unit normals (gpps frame).
        valid: (H, W) bool integrated pixels.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        cut_x, cut_y: (H, W) bool cut j-edges ``(i, j)-(i, j+1)`` and i-edges ``(i, j)-(i+1, j)``.
        min_nz: slope bound of grazing normals (:func:`gpps.host.poisson.pixel_gradients`).
        mode: ``"mid"`` or ``"bini"`` (:data:`gpps.names.CUT_STITCH_NAMES`).
        k, tol: ``mode="bini"``: BiNI's sigmoid sharpness and energy tolerance.

    Returns:
        ``(u_stitched, labels, n_pieces)``: (H, W) float64 ``u`` plus each piece's constant (0 outside
        ``valid``), the (H, W) int pieces 1..n_pieces and their number.
    """
    _check_camera(camera)
    check_choice("mode", mode, CUT_STITCH_NAMES)
    n = np.asarray(normals, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool)
    ex, ey = _edges(valid)
    cut_x, cut_y = ex & np.asarray(cut_x, bool), ey & np.asarray(cut_y, bool)
    labels, npc = crease_pieces(valid, ex & ~cut_x, ey & ~cut_y)
    u = np.where(valid, np.asarray(u, np.float64), 0.0)
    if not (cut_x.any() or cut_y.any()):
        return u, labels, npc
    gj, gi, nzj, nzi = _coefficients(n, valid, camera, min_nz)
    if mode == "bini":
        us, _, _ = stitch_bini(u, labels, npc, cut_x, cut_y, valid, gj, gi, nzj, nzi, k=k, tol=tol)
        return us, labels, npc
    wx, wy, _, _ = _weighted_system(valid, ex, ey, gj, gi, nzj, nzi)
    tx, ty = mid_normal_targets(n, valid, camera, min_nz)
    us, _ = stitch(u, labels, npc, cut_x, cut_y, wx, wy, tx, ty)
    return us, labels, npc


@dataclass
class CreaseResult:
    """Output of :func:`integrate_creases`.

    Attributes:
        depth: (H, W) float64 depth, 0 outside ``mask``: orthographic with mean 0 per mask component,
            perspective ``exp(u)`` with mean log-depth 0 per mask component (scene units up to that).
        u: (H, W) float64 depth (orthographic) or log-depth (perspective).
        mask: (H, W) bool pixels integrated (finite, non-zero normals inside the mask).
        cut_x, cut_y: (H, W) bool the cut j- and i-edges.
        labels: (H, W) int pieces (1..n_pieces, 0 outside).
        n_pieces: number of pieces.
        info: threshold, sigma, BiNI iteration counts.
        timings: seconds per step.
    """

    depth: np.ndarray
    u: np.ndarray
    mask: np.ndarray
    cut_x: np.ndarray
    cut_y: np.ndarray
    labels: np.ndarray
    n_pieces: int
    info: dict = field(default_factory=dict)
    timings: dict = field(default_factory=dict)


def integrate_creases(normals, mask, camera, *, inner: str = "poisson", stitch_mode: str = "trapezoid",
                      robust_stitch: bool = False, refine: str = "none", floor_deg: float = 2.0, z: float = 4.0,
                      threshold_deg: float | None = None, min_nz: float = 1e-3, bini_k: float = 2.0,
                      target: str = "trapezoid"):
    """Crease cut and stitch integration of a normal map (see the module docstring).

    Args:
        normals: (H, W, 3) normals, gpps frame (visible normals face the camera).
        mask: (H, W) bool pixels to integrate.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        inner: ``"poisson"`` (N_z^2-weighted least squares per piece, sparse LU) or ``"bini"`` (BiNI's IRLS per
            piece, cut edges as missing neighbours).
        stitch_mode: ``"trapezoid"`` or ``"continuity"`` (:func:`stitch`).
        robust_stitch: Cauchy-reweighted stitch.
        refine: ``"none"`` or ``"bini"`` (BiNI's IRLS on the uncut graph from the stitched solution).
        floor_deg, z, threshold_deg: the crease test (:func:`crease_edges`).
        min_nz: slope bound of grazing normals (:func:`gpps.host.poisson.pixel_gradients`).
        bini_k: BiNI's ``k``.
        target: the Poisson pieces' and the stitch's edge targets: ``"trapezoid"`` (N_z^2-weighted average of
            the two pixels' steps, as (4.20)) or ``"mid"`` (:func:`mid_normal_targets`).

    Returns:
        :class:`CreaseResult`.

    Raises:
        ValueError: bad shapes, camera or option.
    """
    for name, v, ch in (("inner", inner, INNERS), ("stitch_mode", stitch_mode, STITCHES), ("refine", refine, REFINES),
                        ("target", target, TARGETS)):
        if v not in ch:
            raise ValueError(f"{name}: expected one of {ch}, got {v!r}")
    _check_camera(camera)
    if isinstance(min_nz, bool) or not isinstance(min_nz, (int, float)) or not 0 < min_nz < 1:
        raise ValueError(f"min_nz: expected a number in (0, 1), got {min_nz!r}")
    t0 = time.perf_counter()
    n, valid = _check_map(normals, mask)
    cut_x, cut_y, info = crease_edges(n, valid, floor_deg=floor_deg, z=z, threshold_deg=threshold_deg)
    ex, ey = _edges(valid)
    kx, ky = ex & ~cut_x, ey & ~cut_y
    labels, npc = crease_pieces(valid, kx, ky)
    gj, gi, nzj, nzi = _coefficients(n, valid, camera, min_nz)
    wx, wy, tx, ty = _weighted_system(valid, ex, ey, gj, gi, nzj, nzi)
    if target == "mid":
        tx, ty = mid_normal_targets(n, valid, camera, min_nz)
    t1 = time.perf_counter()
    if inner == "poisson":
        u, _, _, _ = solve_direct(valid, np.where(kx, wx, 0.0), np.where(ky, wy, 0.0), tx, ty, labels)
        binfo = {}
    else:
        u, binfo = bini_irls(valid, kx, ky, gj, gi, nzj, nzi, k=bini_k)
    t2 = time.perf_counter()
    u, _ = stitch(u, labels, npc, cut_x, cut_y, wx, wy, tx, ty, mode=stitch_mode, robust=robust_stitch)
    t3 = time.perf_counter()
    if refine == "bini":
        u, rinfo = bini_irls(valid, ex, ey, gj, gi, nzj, nzi, u0=u, k=bini_k)
        binfo = {**binfo, **{"refine_" + key: v for key, v in rinfo.items() if key != "energy"}}
    t4 = time.perf_counter()
    comp, nc = crease_pieces(valid, ex, ey)
    s = np.bincount(comp.ravel(), weights=np.where(valid, u, 0).ravel(), minlength=nc + 1)
    cnt = np.bincount(comp.ravel(), minlength=nc + 1)
    mean = s / np.maximum(cnt, 1)
    u = np.where(valid, u - mean[comp], 0.0)
    depth = np.where(valid, np.exp(u), 0.0) if camera.is_perspective else u
    info.update({key: v for key, v in binfo.items() if key != "energy"})
    info.update(cut_edges=int(cut_x.sum() + cut_y.sum()), edges=int(ex.sum() + ey.sum()))
    return CreaseResult(depth=depth, u=u, mask=valid, cut_x=cut_x, cut_y=cut_y, labels=labels, n_pieces=npc,
                        info=info, timings={"detect": t1 - t0, "inner": t2 - t1, "stitch": t3 - t2,
                                            "refine": t4 - t3, "total": t4 - t0})
