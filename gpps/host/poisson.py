"""The integrator's host algebra (4.20): per-pixel gradients from normals, the edge system of the
masked Poisson problem, robust and bilateral edge weights, the multigrid hierarchy, and the numpy
references of the operators the Taichi kernels apply.  numpy / scipy only, with the two host solvers
(sparse LU, Simchony's DCT); the stage that solves the system on the device is :class:`gpps.pipeline.integration.Integrator`, whose docstring gives the model.
"""

from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components
from scipy.fft import dctn, idctn
from scipy.special import expit

__all__ = ["pixel_gradients", "edge_system", "divergence_rhs", "laplacian", "apply_laplacian", "build_levels", "level_shapes",
           "diagonal", "normal_equation_residual", "edge_residuals", "ls_energy", "bilateral_weights", "loop_curl",
           "curl_edge_weights", "robust_edge_weights", "component_means", "component_means_at", "solve_direct", "solve_dct"]


def pixel_gradients(normals: np.ndarray, valid: np.ndarray, camera, min_nz: float):
    """Per-pixel steps of ``u`` and BiNI's N_z factors.

    Args:
        normals: (H, W, 3) unit normals (gpps frame).
        valid: (H, W) bool.
        camera: :class:`Orthographic` or :class:`Perspective`.
        min_nz: slope bound (see :class:`IntegratorConfig`).

    Returns:
        ``gj, gi, nzj, nzi``, each (H, W) float64, 0 outside ``valid``:
        ``du/dj``, ``du/di`` (per pixel step) and ``N_z`` such that BiNI's
        residual is ``N_z (du - g)`` (orthographic ``n_z/s``; perspective ``-f m``).
    """
    n = np.asarray(normals, dtype=np.float64)
    h, w = valid.shape
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    with np.errstate(all="ignore"):
        if camera.is_perspective:
            cx, cy = camera.principal_point((h, w))
            jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
            m = nx * (jj - cx) / camera.fx - ny * (ii - cy) / camera.fy - nz
            m = np.minimum(m, -min_nz)
            gj = -nx / (camera.fx * m)
            gi = ny / (camera.fy * m)
            nzj, nzi = -camera.fx * m, -camera.fy * m
        else:
            s = camera.pixel_size
            den = np.maximum(nz, min_nz)
            gj, gi = s * nx / den, -s * ny / den
            nzj = nzi = den / s
    out = []
    for a in (gj, gi, nzj, nzi):
        out.append(np.where(valid, a, 0.0))
    return tuple(out)


def edge_system(valid, gj, gi, cj=None, ci=None, wpj=None, wpi=None):
    """Edge weights and targets of (4.20).

    Args:
        valid: (H, W) bool.
        gj, gi: (H, W) per-pixel steps.
        cj, ci: (H, W) per-pixel confidences (None = 1).
        wpj, wpi: (H, W) forward-term weights w+ (backward w- = 1 - w+; None = 1/2).

    Returns:
        ``wx, wy, tx, ty``: (H, W) float64; ``wx[i, j]``/``tx[i, j]`` belong to
        the edge ``(i, j)-(i, j+1)``, ``wy``/``ty`` to ``(i, j)-(i+1, j)``;
        0 where the edge leaves the mask.
    """
    h, w = valid.shape
    one = np.ones((h, w))
    cj = one if cj is None else cj
    ci = one if ci is None else ci
    wpj = 0.5 * one if wpj is None else wpj
    wpi = 0.5 * one if wpi is None else wpi
    wx = np.zeros((h, w))
    wy = np.zeros((h, w))
    tx = np.zeros((h, w))
    ty = np.zeros((h, w))
    ex = valid[:, :-1] & valid[:, 1:]
    a = cj[:, :-1] * wpj[:, :-1]
    b = cj[:, 1:] * (1 - wpj[:, 1:])
    s = a + b
    ok = ex & (s > 0)
    with np.errstate(all="ignore"):
        wx[:, :-1] = np.where(ok, s, 0.0)
        tx[:, :-1] = np.where(ok, (a * gj[:, :-1] + b * gj[:, 1:]) / s, 0.0)
    ey = valid[:-1, :] & valid[1:, :]
    a = ci[:-1, :] * wpi[:-1, :]
    b = ci[1:, :] * (1 - wpi[1:, :])
    s = a + b
    ok = ey & (s > 0)
    with np.errstate(all="ignore"):
        wy[:-1, :] = np.where(ok, s, 0.0)
        ty[:-1, :] = np.where(ok, (a * gi[:-1, :] + b * gi[1:, :]) / s, 0.0)
    return wx, wy, tx, ty


def robust_edge_weights(u, ex, ey, tx, ty, scale: float, floor: float = 1e-6):
    """Cauchy IRLS weights of the edges of (4.20) from the current solution.

    Args:
        u: (H, W) current solution (depth or log-depth).
        ex, ey: (H, W) bool, the existing j- and i-edges (as ``wx > 0``, ``wy > 0``).
        tx, ty: (H, W) edge targets (:func:`edge_system`).
        scale: ``sigma`` in robust standard deviations (1.4826 MAD) of the residuals.
        floor: smallest weight (keeps every edge, so no region is cut loose).

    Returns:
        ``(rwx, rwy, sigma)``: (H, W) multipliers of the edge weights (0 where no
        edge) and the ``sigma`` used.
    """
    rx, ry = edge_residuals(u, tx, ty)
    return _cauchy_edge_weights(rx, ry, ex, ey, np.concatenate([rx[ex], ry[ey]]), scale, floor)


def _cauchy_edge_weights(cx, cy, ex, ey, sample, scale: float, floor: float):
    """``1 / (1 + (c / sigma)^2)`` per existing edge (at least ``floor``, 0 where no edge), with
    ``sigma = scale * 1.4826 * median |sample|``; all 1 when ``sigma`` is 0 (nothing to down-weight).

    Returns:
        ``(rwx, rwy, sigma)``.
    """
    sigma = float(scale * 1.4826 * np.median(np.abs(sample))) if sample.size else 0.0
    if not sigma > 0:
        return ex.astype(np.float64), ey.astype(np.float64), sigma
    rwx = np.where(ex, np.maximum(1.0 / (1.0 + (cx / sigma) ** 2), floor), 0.0)
    rwy = np.where(ey, np.maximum(1.0 / (1.0 + (cy / sigma) ** 2), floor), 0.0)
    return rwx, rwy, sigma


def loop_curl(ex, ey, tx, ty):
    """Integrability defect of the edge targets around each 2x2 pixel loop.

    The loop with top-left pixel ``(i, j)`` runs ``(i, j) -> (i, j+1) -> (i+1,
    j+1) -> (i+1, j) -> (i, j)``; its curl is ``tx[i, j] + ty[i, j+1] -
    tx[i+1, j] - ty[i, j]``, the discrete ``∮ grad u . dl``, which is 0 for
    targets that are the differences of any ``u``.

    Args:
        ex, ey: (H, W) bool, the existing j- and i-edges.
        tx, ty: (H, W) edge targets (:func:`edge_system`).

    Returns:
        ``(curl, ok)``: (H, W) float64 curl and bool, where the loop's four
        edges all exist (the last row and column are never loop corners).
    """
    h, w = ex.shape
    ok = np.zeros((h, w), bool)
    curl = np.zeros((h, w))
    ok[:-1, :-1] = ex[:-1, :-1] & ex[1:, :-1] & ey[:-1, :-1] & ey[:-1, 1:]
    curl[:-1, :-1] = tx[:-1, :-1] + ty[:-1, 1:] - tx[1:, :-1] - ty[:-1, :-1]
    return np.where(ok, curl, 0.0), ok


def curl_edge_weights(ex, ey, tx, ty, scale: float, floor: float = 1e-6):
    """Edge weights from the integrability of the targets (``IntegratorConfig.robust="curl"``).

    A target that disagrees with the surface (a wrong normal at a grazing rim,
    an acquisition artefact, a depth jump) leaves the two 2x2 loops through
    its edge unclosed; on a smooth surface every loop closes up to the
    discretisation error.  Each edge gets ``1 / (1 + (c / sigma)^2)`` with
    ``c`` the larger ``|curl|`` of its (one or two) loops and ``sigma = scale *
    1.4826 * median |curl|`` over all closed loops; an edge in no loop keeps
    weight 1 (it carries no integrability information).  Curl-based trust in
    the gradient field follows Agrawal, Raskar and Chellappa, "What is the
    range of surface reconstructions from a gradient field?", ECCV 2006.

    Args:
        ex, ey: (H, W) bool, the existing j- and i-edges.
        tx, ty: (H, W) edge targets (:func:`edge_system`).
        scale: ``sigma`` in robust standard deviations of the loop curls.
        floor: smallest weight (keeps every edge, so no region is cut loose).

    Returns:
        ``(rwx, rwy, sigma)``: (H, W) multipliers of the edge weights (0 where
        no edge) and the ``sigma`` used (0: every loop closes, weights 1).
    """
    curl, ok = loop_curl(ex, ey, tx, ty)
    a = np.abs(curl)
    h, w = a.shape
    # j-edge (i, j)-(i, j+1) borders the loops with corners (i-1, j) and (i, j);
    # i-edge (i, j)-(i+1, j) borders (i, j-1) and (i, j)
    cx = a.copy()
    cx[1:, :] = np.maximum(cx[1:, :], a[:-1, :])
    cy = a.copy()
    cy[:, 1:] = np.maximum(cy[:, 1:], a[:, :-1])
    return _cauchy_edge_weights(cx, cy, ex, ey, a[ok], scale, floor)


def divergence_rhs(wx, wy, tx, ty) -> np.ndarray:
    """``b = -div(w t)``: the right-hand side of the normal equations of (4.20)."""
    fx = wx * tx
    fy = wy * ty
    b = -fx - fy
    b[:, 1:] += fx[:, :-1]
    b[1:, :] += fy[:-1, :]
    return b


def laplacian(wx, wy, valid):
    """Sparse weighted graph Laplacian over the valid pixels.

    Returns:
        ``(A, idx)``: CSR matrix (n x n, float64) and the flat indices of the
        n valid pixels in row-major order.
    """

    h, w = valid.shape
    lab = -np.ones(h * w, dtype=np.int64)
    idx = np.flatnonzero(valid.ravel())
    lab[idx] = np.arange(idx.size)
    lab = lab.reshape(h, w)
    rows, cols, vals = [], [], []
    for wgt, da, db in ((wx[:, :-1], (slice(None), slice(None, -1)), (slice(None), slice(1, None))),
                        (wy[:-1, :], (slice(None, -1), slice(None)), (slice(1, None), slice(None)))):
        sel = wgt > 0
        a = lab[da][sel]
        bb = lab[db][sel]
        v = wgt[sel]
        rows += [a, bb]
        cols += [bb, a]
        vals += [-v, -v]
    rows = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    cols = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    vals = np.concatenate(vals) if vals else np.zeros(0)
    off = sp.coo_matrix((vals, (rows, cols)), shape=(idx.size, idx.size)).tocsr()
    A = off - sp.diags(np.asarray(off.sum(axis=1)).ravel())
    return A.tocsr(), idx


def apply_laplacian(u, wx, wy):
    """``A u`` on the image grid (float64)."""
    ex = wx[:, :-1] * (u[:, 1:] - u[:, :-1])
    ey = wy[:-1, :] * (u[1:, :] - u[:-1, :])
    out = np.zeros_like(u)
    out[:, :-1] -= ex
    out[:, 1:] += ex
    out[:-1, :] -= ey
    out[1:, :] += ey
    return out


def normal_equation_residual(u, wx, wy, b) -> float:
    """Relative residual ``|b - A u| / |b|`` (float64)."""
    nb = float(np.linalg.norm(b))
    r = b - apply_laplacian(np.asarray(u, np.float64), wx, wy)
    return float(np.linalg.norm(r)) / nb if nb > 0 else float(np.linalg.norm(r))


def edge_residuals(u, tx, ty):
    """(H, W) residuals ``u_b - u_a - t_e`` of the j- and i-edges of (4.20) (0 on the last column / row)."""
    rx = np.zeros_like(u, dtype=np.float64)
    ry = np.zeros_like(u, dtype=np.float64)
    rx[:, :-1] = u[:, 1:] - u[:, :-1] - tx[:, :-1]
    ry[:-1, :] = u[1:, :] - u[:-1, :] - ty[:-1, :]
    return rx, ry


def ls_energy(u, wx, wy, tx, ty) -> float:
    """The discrete (4.20) energy ``sum_e w_e (u_b - u_a - t_e)^2``."""
    rx, ry = edge_residuals(u, tx, ty)
    return float(np.sum(wx * rx * rx) + np.sum(wy * ry * ry))


def level_shapes(h: int, w: int, coarsest: int) -> list[tuple[int, int]]:
    shapes = [(h, w)]
    while max(shapes[-1]) > coarsest:
        hh, ww = shapes[-1]
        shapes.append(((hh + 1) // 2, (ww + 1) // 2))
    return shapes


def build_levels(wx, wy, coarsest: int = 8, alpha: float = 0.5):
    """Coarsened edge weights for the multigrid hierarchy.

    2x2 blocks aggregate into one coarse cell; a coarse edge's weight is
    ``alpha`` times the sum of the fine edge weights that cross it (``alpha =
    1`` would be the Galerkin operator of piecewise-constant interpolation;
    ``1/2`` rediscretises the Laplacian at twice the spacing, the usual fix for
    aggregation's too-weak coarse correction).

    Returns:
        list of ``(wx_k, wy_k)`` per level, level 0 first.
    """
    levels = [(wx, wy)]
    h, w = wx.shape
    for (hc, wc) in level_shapes(h, w, coarsest)[1:]:
        fx, fy = levels[-1]
        ph, pw = 2 * hc - fx.shape[0], 2 * wc - fx.shape[1]
        fx = np.pad(fx, ((0, ph), (0, pw)))
        fy = np.pad(fy, ((0, ph), (0, pw)))
        cx = np.zeros((hc, wc))
        cy = np.zeros((hc, wc))
        cx[:, :] = alpha * (fx[0::2, 1::2] + fx[1::2, 1::2])
        cy[:, :] = alpha * (fy[1::2, 0::2] + fy[1::2, 1::2])
        cx[:, -1] = 0
        cy[-1, :] = 0
        levels.append((cx, cy))
    return levels


def coarsest_pinv(lx, ly, ncmax: int, col_offset: int, dtype) -> tuple[np.ndarray, np.ndarray, int]:
    """The exact coarse solve of the multigrid V-cycle: the pseudo-inverse of the coarsest level's weighted
    Laplacian over its active cells (diagonal > 0), for :func:`gpps.kernels.poisson.coarse_exact`.

    Args:
        lx, ly: (hc, wc) the coarsest level's edge weights (right and down neighbours).
        ncmax: rows of the ``pinv`` buffer (>= the active cells).
        col_offset: the level's first column in the packed level layout (added to ``cidx[:, 1]``).
        dtype: the buffers' float dtype.

    Returns:
        ``(pinv (ncmax, ncmax), cidx (ncmax, 2) int32, nc)``: the active cells' pseudo-inverse in the top-left
        ``nc x nc`` block (zeros elsewhere), and their (row, packed column) in raster order.
    """
    dgc = diagonal(lx, ly)
    act = np.argwhere(dgc > 0)
    nc = len(act)
    pinv = np.zeros((ncmax, ncmax), dtype=dtype)
    cidx = np.zeros((ncmax, 2), dtype=np.int32)
    if nc:
        A, _ = laplacian(lx, ly, dgc > 0)
        pinv[:nc, :nc] = laplacian_pinv(A.toarray())
        cidx[:nc, 0] = act[:, 0]
        cidx[:nc, 1] = act[:, 1] + col_offset
    return pinv, cidx, nc


def laplacian_pinv(A) -> np.ndarray:
    """Moore-Penrose pseudo-inverse of a dense weighted graph Laplacian ``A`` (n, n) without isolated nodes.

    ``A`` is symmetric positive semi-definite; its null space is spanned by the indicator vectors of its
    connected components, whose orthogonal projector is ``P = sum_c 1_c 1_c^T / n_c``.  ``A + P`` is positive
    definite (``A`` on the range of ``A``, the identity on the null space), so ``A^+ = (A + P)^-1 - P``.  The
    inverse is a Gauss-Jordan elimination without pivoting (stable for a positive definite matrix) in float64
    by rank-one updates: no LAPACK call, whose multi-threaded BLAS took 2-30 ms for a 64 x 64 matrix on a
    16-core host (thread wake-ups; the elimination takes about 1 ms).  Equal to
    ``numpy.linalg.pinv(A, hermitian=True)`` to rounding (tests/test_integration.py)."""
    A = np.asarray(A, dtype=np.float64)
    n = A.shape[0]
    if n == 0:
        return np.zeros((0, 0))
    _, lab = connected_components(A != 0, directed=False)
    cnt = np.bincount(lab).astype(np.float64)
    P = (lab[:, None] == lab[None, :]) / cnt[lab][None, :]
    inv = A + P
    for p in range(n):
        piv = inv[p, p]
        row = inv[p, :] / piv
        col = inv[:, p].copy()
        inv -= np.outer(col, row)
        inv[p, :] = row
        inv[:, p] = -col / piv
        inv[p, p] = 1.0 / piv
    return inv - P


def diagonal(wx, wy):
    d = wx.copy() + wy
    d[:, 1:] += wx[:, :-1]
    d[1:, :] += wy[:-1, :]
    return d


def _sigmoid(x, floor=0.0):
    """Logistic ``1 / (1 + exp(-x))`` (overflow-free), clipped to ``[floor, 1 - floor]``."""


    return np.clip(expit(x), floor, 1.0 - floor)


def bilateral_weights(u, valid, wx, wy, nzj, nzi, k, floor=0.0):
    """BiNI's IRLS update of the forward-term weights ``w+`` (backward: ``1 - w+``).

    ``w+ = sigmoid(k ((N_z d-)^2 - (N_z d+)^2))`` with ``d+-`` the one-sided
    differences of ``u`` at each pixel (0 where the neighbour is missing) and
    ``N_z`` the pixel's own coefficient (:func:`pixel_gradients`): the side
    with the smaller jump gets the larger weight.

    Returns:
        ``wpj, wpi, (dj, djm, di, dim)``: weights and the one-sided differences.
    """
    ex = wx[:, :-1] > 0
    ey = wy[:-1, :] > 0
    dj = np.zeros_like(u)
    dj[:, :-1] = np.where(ex, u[:, 1:] - u[:, :-1], 0.0)  # forward step at (i, j)
    djm = np.zeros_like(u)
    djm[:, 1:] = dj[:, :-1]  # backward step at (i, j)
    di = np.zeros_like(u)
    di[:-1, :] = np.where(ey, u[1:, :] - u[:-1, :], 0.0)
    dim = np.zeros_like(u)
    dim[1:, :] = di[:-1, :]
    wpj = _sigmoid(k * ((nzj * djm) ** 2 - (nzj * dj) ** 2), floor)
    wpi = _sigmoid(k * ((nzi * dim) ** 2 - (nzi * di) ** 2), floor)
    return np.where(valid, wpj, 0.5), np.where(valid, wpi, 0.5), (dj, djm, di, dim)


def component_means(a, valid, labels, n: int) -> np.ndarray:
    """(H, W) each valid pixel's connected-component mean of ``a`` (0 at label 0, outside ``valid``).

    Args:
        a: (H, W) values.
        valid: (H, W) bool.
        labels: (H, W) int component labels (0 = none), ``n`` components (``scipy.ndimage.label``).
    """
    s = np.bincount(labels.ravel(), weights=np.where(valid, a, 0).ravel(), minlength=n + 1)
    c = np.bincount(labels.ravel(), minlength=n + 1)
    mean = s / np.maximum(c, 1)
    mean[0] = 0
    return mean[labels]


def component_means_at(values, labels, n: int) -> np.ndarray:
    """(P,) each pixel's connected-component mean of ``values``, on a list of pixels: the form of
    :func:`component_means` for a mask that is a small part of its frame.  Given the valid pixels in row-major
    order, the sums (and the means) equal the frame form's bit for bit.

    Args:
        values: (P,) values at the pixels.
        labels: (P,) their component labels (1..n).
        n: the number of components.
    """
    s = np.bincount(labels, weights=values, minlength=n + 1)
    return (s / np.maximum(np.bincount(labels, minlength=n + 1), 1))[labels]


def solve_direct(valid, wx, wy, tx, ty, labels):
    """The normal equations of (4.20) by sparse LU (scipy), the first pixel of each component pinned to 0.

    Args:
        valid: (H, W) bool; wx, wy, tx, ty: the edge system (:func:`edge_system`).
        labels: (H, W) int connected components of ``valid`` (0 = none).

    Returns:
        ``(u (H, W), iterations 1, None, timings)``.
    """
    t0 = time.perf_counter()
    b = divergence_rhs(wx, wy, tx, ty)
    A, idx = laplacian(wx, wy, valid)
    labv = labels.ravel()[idx]
    # pin the first pixel of each component (Dirichlet 0), solve the SPD rest
    _, first = np.unique(labv, return_index=True)
    keep = np.ones(idx.size, bool)
    keep[first] = False
    bv = b.ravel()[idx]
    t1 = time.perf_counter()
    x = np.zeros(idx.size)
    if keep.any():
        Ak = A[keep][:, keep].tocsc()
        x[keep] = spla.spsolve(Ak, bv[keep])
    u = np.zeros(valid.shape)
    u.ravel()[idx] = x
    t2 = time.perf_counter()
    return u, 1, None, {"rhs": t1 - t0, "solve": t2 - t1}


def solve_dct(valid, wx, wy, tx, ty):
    """Simchony et al.'s DCT solution of (4.20) on a full rectangle with uniform weights (scipy).

    Returns:
        ``(u (H, W), iterations 1, None, timings)``.

    Raises:
        ValueError: a mask that is not the full rectangle, or non-uniform weights.
    """
    h, w = valid.shape
    full = valid.all() and np.all(wx[:, :-1] == 1) and np.all(wy[:-1, :] == 1)
    if not full:
        raise ValueError(
            "solver: 'dct' (Simchony) needs a full rectangular mask, valid normals everywhere and uniform, "
            "non-bilateral weights; use 'direct' or 'multigrid' on masked domains"
        )
    t0 = time.perf_counter()
    b = divergence_rhs(wx, wy, tx, ty)
    t1 = time.perf_counter()
    lam = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    lam[0, 0] = 1.0
    bh = dctn(b, type=2, norm="ortho")
    bh /= lam  # A = -Laplacian (positive semi-definite): A u = b
    bh[0, 0] = 0.0
    u = idctn(bh, type=2, norm="ortho")
    return u, 1, None, {"rhs": t1 - t0, "solve": time.perf_counter() - t1}
