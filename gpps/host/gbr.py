"""Uncalibrated photometric stereo's host algorithms (seed ch. 5): rank-3 factorisation, the GBR
ambiguity and the evidence that resolves it.  numpy / scipy only; the whole flow is
:func:`gpps.flows.uncalibrated.solve_uncalibrated`, whose docstring explains the steps.

* :func:`factorize`: weighted rank-3 factorisation ``M ~ L B^T`` (5.8; Hayakawa) with missing data;
* :func:`integrability_gbr`: integrability reduces the 3x3 ambiguity to the GBR family (Yuille & Snow);
* :func:`resolve_gbr`: local diffuse maxima, albedo entropy and the light-intensity prior pick
  ``(alpha, beta, gamma)``;
* :func:`pca_merge` (5.1.7), :func:`restore_gauge`, :func:`specular_free` (S-U-V space),
  :func:`dark_images`, :func:`light_direction_errors`.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_erosion, gaussian_filter, maximum_filter
from scipy.optimize import minimize

from gpps.camera import Perspective

__all__ = ["factorize", "integrability_gbr", "gbr", "resolve_gbr", "ldr_candidates", "dark_images", "restore_gauge", "pca_merge",
           "light_direction_errors", "specular_free", "pixel_pseudo_normals", "albedo_ls", "to_map", "perspective_curls"]


def factorize(M: np.ndarray, W: np.ndarray, iterations: int = 40, robust_rounds: int = 3, robust_k: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted, robust rank-3 factorisation ``M ~ L B^T`` (5.8).

    Alternating least squares from two starts, keeping the one with the lower
    weighted residual: the SVD of ``M`` with missing entries filled by the row
    means (the seed's plain SVD when nothing is missing), and the SVD of the
    largest complete sub-matrix of the best-lit images (then lights of all
    images, then all pseudo-normals, by least squares).  With many shadowed
    observations (faces under grazing lights) the filled SVD can start ALS in a
    wrong basin; the complete sub-matrix is exact rank-3 data and does not.

    Args:
        M: (N, P) grey intensities.
        W: (N, P) weights (0 = missing).
        iterations: alternating least-squares sweeps after each start.
        robust_rounds: rounds that drop observations farther than ``robust_k``
            robust standard deviations from the rank-3 model (highlights, cast
            shadows: a Lambertian rank-3 model cannot explain them) and refit.

    Returns:
        L (N, 3), B (P, 3), and the final weights (N, P).
    """
    M = np.asarray(M, np.float64)
    W = np.asarray(W, np.float64)
    best = None
    for start in (_start_fill(M, W), _start_submatrix(M, W)):
        if start is None:
            continue
        L, B = _als(M, W, iterations, start)
        r = _weighted_rms(M, W, L, B)
        if best is None or r < best[0]:
            best = (r, L, B)
    _, L, B = best
    for _ in range(robust_rounds):
        r = M - L @ B.T
        sigma = 1.4826 * np.median(np.abs(r[W > 0])) + 1e-12
        Wn = W * (np.abs(r) < robust_k * sigma)
        few = Wn.sum(1) < np.minimum(W.sum(1), 10)  # every light keeps some observations
        Wn[few] = W[few]
        if np.array_equal(Wn, W) or (Wn.sum(0) < 3).mean() > 0.5:
            break
        W = Wn
        L, B = _als(M, W, iterations, start=(L, B))
    return L, B, W


def _weighted_rms(M, W, L, B):
    return float(np.sqrt(np.sum(W * (M - L @ B.T) ** 2) / max(float(W.sum()), 1e-12)))


def _start_fill(M, W):
    """Rank-3 SVD of ``M`` with the missing entries filled by the row means of the observed ones."""
    fill = np.where(W > 0, M, (M * W).sum(1, keepdims=True) / np.maximum(W.sum(1, keepdims=True), 1e-12))
    U, S, Vt = np.linalg.svd(fill, full_matrices=False)
    return U[:, :3] * np.sqrt(S[:3]), Vt[:3].T * np.sqrt(S[:3])


def _start_submatrix(M, W, fraction: float = 0.25, min_pixels: int = 50):
    """Rank-3 SVD of the complete sub-matrix: the best-lit quarter of the images (at least 3) and
    the pixels observed in all of them; None when no such block has ``min_pixels`` pixels."""
    N = M.shape[0]
    order = np.argsort(-(W > 0).sum(1), kind="stable")
    n = max(3, round(fraction * N))
    while True:
        imgs = order[:n]
        pix = np.all(W[imgs] > 0, axis=0)
        if pix.sum() >= min_pixels or n == 3:
            break
        n -= 1
    if pix.sum() < max(min_pixels, 3):
        return None
    _, S, Vt = np.linalg.svd(M[np.ix_(imgs, pix)], full_matrices=False)
    Bs = Vt[:3].T * np.sqrt(S[:3])
    L = _solve_rows(W[:, pix], M[:, pix], Bs)
    return L, _solve_rows(W.T, M.T, L)


def _solve_rows(W, M, X):
    """Per row r of ``M`` (R x C): the 3-vector ``y`` minimising ``sum_c W[r, c] (M[r, c] - X[c] . y)^2``."""
    A = (W @ (X[:, :, None] * X[:, None, :]).reshape(-1, 9)).reshape(-1, 3, 3) + 1e-9 * np.eye(3)
    return np.linalg.solve(A, ((W * M) @ X)[..., None])[..., 0]


def _als(M, W, iterations, start):
    L, B = start
    for _ in range(iterations):
        B = _solve_rows(W.T, M.T, L)
        L = _solve_rows(W, M, B)
    return L, B


def integrability_gbr(Bmap: np.ndarray, valid: np.ndarray, smooth: float = 0.0, irls: int = 0) -> np.ndarray:
    """``A`` (3x3) such that ``A b^`` is integrable, up to a GBR (Yuille & Snow).

    Args:
        Bmap: (H, W, 3) pseudo-normals on the image grid.
        valid: (H, W) bool, pixels to use.
        smooth: Gaussian sigma (pixels) of a normalised convolution of the
            pseudo-normal map inside ``valid`` before differencing.  The
            constraint differentiates B; on real data (8-bit faces) per-pixel
            noise dominates the differences and biases ``A`` (yaleB01: the
            light error after integrability and the best GBR fitted to the
            true lights went from 18 deg to 9 with sigma 2, 7.7 with ``irls``;
            a 1%-noise synthetic capture: from useless to near exact).  ``A b`` is linear in ``b``, so smoothing ``b^``
            smooths the integrable field the same way.
        irls: iteratively reweighted rounds (Cauchy weights at twice the
            median residual) that down-weight pixels violating integrability
            (depth edges: nostrils, eyelids, occluding contours).

    Raises:
        ValueError: too few pixels with valid neighbours to fix ``A``.
    """
    valid = np.asarray(valid, bool)
    if smooth > 0:
        m = valid.astype(np.float64)
        den = np.maximum(gaussian_filter(m, smooth), 1e-12)
        Bmap = np.stack([gaussian_filter(Bmap[..., c] * m, smooth) / den for c in range(3)], -1)
    # x to the right (+j), y up (-i): forward differences where both pixels are valid
    ok = valid[1:, :-1] & valid[1:, 1:] & valid[:-1, :-1]
    b = Bmap[1:, :-1][ok]
    bx = (Bmap[1:, 1:] - Bmap[1:, :-1])[ok]
    by = (Bmap[:-1, :-1] - Bmap[1:, :-1])[ok]
    if len(b) < 20:
        raise ValueError("mask: expected at least 20 pixels with right and upper neighbours for the integrability constraint")
    wy = np.cross(b, by)
    wx = np.cross(b, bx)
    D = np.hstack([wy, -wx])
    D /= np.maximum(np.linalg.norm(D, axis=1, keepdims=True), 1e-12)
    w = np.ones(len(D))
    for _ in range(int(irls) + 1):
        _, _, Vt = np.linalg.svd(D * w[:, None], full_matrices=False)
        c = Vt[-1]
        r = np.abs(D @ c)
        w = 1.0 / np.sqrt(1.0 + (r / (2.0 * np.median(r) + 1e-15)) ** 2)
    c1, c2 = c[:3], c[3:]
    a3 = np.cross(c1, c2)
    n3 = np.dot(a3, a3)
    if n3 < 1e-20:
        raise ValueError("images: the integrability constraint is degenerate (a planar or featureless surface?)")
    a1 = np.cross(c1, a3) / n3
    a2 = np.cross(c2, a3) / n3
    A = np.stack([a1, a2, a3])
    if abs(np.linalg.det(A)) < 1e-12 * np.linalg.norm(A) ** 3:
        raise ValueError("images: the integrability solution is singular")
    return A


def gbr(alpha: float, beta: float, gamma: float) -> np.ndarray:
    """The GBR acting on pseudo-normals: ``b' = H b``, ``H = [[1,0,alpha],[0,1,beta],[0,0,gamma]]``.

    Lights transform as ``s' = H^{-T} s`` so that ``s'.b' = s.b``.
    """
    return np.array([[1.0, 0.0, alpha], [0.0, 1.0, beta], [0.0, 0.0, gamma]])


def _entropy(values: np.ndarray, bins: int = 64) -> float:
    v = values / np.median(values)
    hist, _ = np.histogram(np.clip(v, 0, 3), bins=bins, range=(0, 3))
    p = hist[hist > 0] / len(v)
    return float(-(p * np.log(p)).sum())


def _cauchy(r: np.ndarray, scale: float) -> float:
    return float(np.mean(np.log1p((r / scale) ** 2)))


def ldr_candidates(M: np.ndarray, W: np.ndarray, mask: np.ndarray, *, sigma: float = 1.0, window: int = 7, rel: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Local diffuse reflectance maxima (Papadhimitri & Favaro 2014): (image k, pixel p) pairs.

    Where the albedo is locally constant, a Lambertian image is brightest
    where the normal points at the light, so a local maximum of image k in the
    image plane marks a pixel with ``n_p = l_k``.  This relation is not
    invariant under the GBR (``H b_p`` is parallel to ``H^-T s_k`` only for the
    true ``H``), so it fixes the GBR.

    Candidates: maxima of the Gaussian-smoothed (``sigma``) image over a
    ``window`` x ``window`` neighbourhood, inside the mask eroded by half a
    window, brighter than ``rel`` times the image's 99th percentile, and
    kept by the factorisation (``W[k, p] > 0``: not a shadow, saturated, a
    trimmed highlight or a rank-3 outlier).

    Args:
        M: (N, P) grey intensities of the ``P`` mask pixels.
        W: (N, P) factorisation weights.
        mask: (H, W) bool with ``P`` pixels.

    Returns:
        ``(k, p)``: image and pixel (index into the mask's pixels) arrays.
    """

    mask = np.asarray(mask, bool)
    idx = np.full(mask.shape, -1)
    idx[mask] = np.arange(int(mask.sum()))
    inner = binary_erosion(mask, iterations=window // 2 + 1)
    ks, ps = [], []
    img = np.zeros(mask.shape)
    for k in range(M.shape[0]):
        img[mask] = M[k]
        sm = gaussian_filter(img, sigma) if sigma > 0 else img
        peak = (sm == maximum_filter(sm, size=window)) & inner & (sm > rel * np.percentile(sm[mask], 99))
        p = idx[peak]
        p = p[W[k, p] > 0]
        ks.append(np.full(len(p), k))
        ps.append(p)
    return np.concatenate(ks), np.concatenate(ps)


def _cue_values(B, L, h, cues, ldr=None):
    H = gbr(*h)
    Hi = np.linalg.inv(H)
    out = {}
    if "intensity" in cues:
        e = np.log(np.maximum(np.linalg.norm(L @ Hi, axis=1), 1e-300))
        out["intensity"] = _cauchy(e - np.median(e), 0.1)
    if "entropy" in cues:
        out["entropy"] = _entropy(np.linalg.norm(B @ H.T, axis=1))
    if "ldr" in cues:
        k, b = ldr
        n = b @ H.T
        s = L[k] @ Hi
        c = np.sum(n * s, 1) / np.maximum(np.linalg.norm(n, axis=1) * np.linalg.norm(s, axis=1), 1e-300)
        out["ldr"] = _cauchy(np.arccos(np.clip(c, -1.0, 1.0)), 0.1)
    return out


def resolve_gbr(B: np.ndarray, L: np.ndarray, cues=("intensity", "ldr", "entropy"), seed: int = 0, ldr=None, min_ldr: int = 10, intensity_tolerance: float = 0.05) -> tuple[np.ndarray, dict]:
    """Choose the GBR ``(alpha, beta, gamma > 0)`` by the given cues.

    Cues (each a value to minimise):
    * ``"intensity"``: lights of equal brightness; a Cauchy loss (scale 0.1)
      of ``log |s_k|`` about its median, so that a few badly conditioned
      lights (lit in few pixels) do not decide it.  Combined with other cues
      it is a hypothesis that is tested first: at its own optimum the robust
      spread (1.4826 MAD) of ``log |s_k|`` must be at most
      ``intensity_tolerance``, else it is left out (``info["cues"]``).  Real
      captures often fail it: DiLiGenT's raw images (intensities not divided
      out), and Yale B, whose Lambertian fit makes grazing lights 2-3 times
      brighter than frontal ones (skin is not Lambertian near the terminator),
      so that the prior there pulls the GBR 5-10 deg off.
    * ``"entropy"``: entropy of the albedo ``|H b|`` (Alldrin et al. 2007).
    * ``"ldr"``: local diffuse maxima (:func:`ldr_candidates`): a Cauchy
      loss (scale 0.1 rad) of the angle between ``H b_p`` and ``H^-T s_k``
      over the candidate pairs.

    Each cue is divided by its smallest value on the search grid, so that the
    sum weighs relative increases and no cue dominates by its units.  The
    grid (13^3 over alpha, beta, log gamma in [-3, 3]) is polished by
    Nelder-Mead.

    Args:
        B: (P, 3) integrable pseudo-normals (a subset of pixels is enough).
        L: (N, 3) pseudo-lights.
        ldr: ``(k, b)``: light indices (Q,) and pseudo-normals (Q, 3) of the
            local-maximum pairs; needed for the ``"ldr"`` cue, which is left
            out (``info["cues"]`` says so) when fewer than ``min_ldr`` pairs.
    """

    cues = tuple(cues)
    if "ldr" in cues and (ldr is None or len(ldr[0]) < min_ldr):
        cues = tuple(c for c in cues if c != "ldr") or ("entropy",)
    rng = np.random.default_rng(seed)
    if len(B) > 4000:
        B = B[rng.choice(len(B), 4000, replace=False)]
    if ldr is not None and len(ldr[0]) > 4000:
        keep = rng.choice(len(ldr[0]), 4000, replace=False)
        ldr = (ldr[0][keep], ldr[1][keep])

    def h_of(x):
        return (x[0], x[1], np.exp(x[2]))

    axis = np.linspace(-3, 3, 13)
    grid = [(a, b, g) for a in axis for b in axis for g in axis]
    vals = [_cue_values(B, L, h_of(x), cues, ldr) for x in grid]
    spread = None
    if "intensity" in cues and len(cues) > 1:
        # equal brightness is a hypothesis: test it at the intensity cue's own optimum
        def fi(x):
            return _cue_values(B, L, h_of(x), ("intensity",))["intensity"]

        xi = np.array(grid[int(np.argmin([v["intensity"] for v in vals]))])
        xi = minimize(fi, xi, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-12, "maxiter": 2000, "initial_simplex": np.vstack([xi, xi + 0.5 * np.eye(3)])}).x
        e = np.log(np.linalg.norm(L @ np.linalg.inv(gbr(*h_of(xi))), axis=1))
        spread = float(1.4826 * np.median(np.abs(e - np.median(e))))
        if spread > intensity_tolerance:
            cues = tuple(c for c in cues if c != "intensity")
    scale = {c: max(min(v[c] for v in vals), 1e-12) for c in cues}
    total = [sum(v[c] / scale[c] for c in cues) for v in vals]
    x0 = np.array(grid[int(np.argmin(total))])

    def f(x):
        v = _cue_values(B, L, h_of(x), cues, ldr)
        return sum(v[c] / scale[c] for c in cues)

    # the initial simplex spans one grid step (scipy's default is 5% of x0: nothing at x0 = 0)
    simplex = np.vstack([x0, x0 + 0.5 * np.eye(3)])
    res = minimize(f, x0, method="Nelder-Mead", options={"xatol": 1e-6, "fatol": 1e-10, "maxiter": 3000, "initial_simplex": simplex})
    h = tuple(float(v) for v in h_of(res.x))
    info = {"alpha": h[0], "beta": h[1], "gamma": h[2], "objective": float(res.fun), "cues": list(cues), "cue_scale": scale, "intensity_spread": spread, **_cue_values(B, L, h, cues, ldr)}
    if ldr is not None:
        info["ldr_pairs"] = len(ldr[0])
    return gbr(*h), info


def pca_merge(normal_sets: np.ndarray) -> np.ndarray:
    """Merge several normal sets by PCA per component (5.1.7).

    For each component c in x, y, z the (P, S) matrix ``N_c`` of that component
    over the S sets is projected on its principal direction (the eigenvector of
    the largest eigenvalue of ``N_c^T N_c``, the seed's "third column" of an
    ascending eigen-decomposition), with the sign chosen so that the weights are
    positive; the result is renormalised.

    Args:
        normal_sets: (S, P, 3).

    Returns:
        (P, 3) unit normals.
    """
    S = np.asarray(normal_sets, dtype=np.float64)
    if S.ndim != 3 or S.shape[2] != 3:
        raise ValueError(f"normal_sets: expected shape (S, P, 3), got {S.shape}")
    out = np.empty(S.shape[1:])
    for c in range(3):
        Nc = S[:, :, c].T  # (P, S)
        w, V = np.linalg.eigh(Nc.T @ Nc)
        v = V[:, -1]
        v = v if v.sum() >= 0 else -v
        out[:, c] = Nc @ (v / v.sum())
    return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)


def restore_gauge(lights: np.ndarray, reference: np.ndarray, keep_gbr: bool = True, rounds: int = 5) -> np.ndarray:
    """Undo the linear drift of refined lights away from the integrable reference (rows: lights).

    With per-pixel albedo and normals free, a Lambertian image is unchanged by
    any invertible ``A`` (``b -> A b``, ``s -> A^-T s``); the refinement has no
    integrability term, so only its weak specular term holds this 9-dof
    "gauge", and Adam wanders along it.  Integrability fixed all of it but the
    GBR, so: fit the linear map ``G`` from ``lights`` to ``reference``
    (robustly: Cauchy IRLS, so that the lights the refinement genuinely
    corrected do not define it), apply it, and then (``keep_gbr``) put back
    the GBR that best approximates the drift, the part the specular term may
    legitimately decide.  A GBR changes only a light's z:
    ``s' = (s1, s2, p s1 + q s2 + r s3)``, so that is the (weighted)
    least-squares ``(p, q, r)`` mapping ``lights @ G`` onto the refined z.

    Args:
        lights: (N, 3) refined lights (direction times intensity).
        reference: (N, 3) the lights the refinement started from.
        keep_gbr: keep the refinement's GBR (else return exactly the reference gauge).
    """
    s = lights / np.median(np.linalg.norm(lights, axis=1))
    ref = reference / np.median(np.linalg.norm(reference, axis=1))
    w = np.ones(len(s))
    for _ in range(rounds):
        G = np.linalg.lstsq(s * w[:, None], ref * w[:, None], rcond=None)[0]
        r = np.linalg.norm(s @ G - ref, axis=1)
        w = 1.0 / np.sqrt(1.0 + (r / (2.0 * np.median(r) + 1e-15)) ** 2)
    out = s @ G
    if keep_gbr:
        pqr = np.linalg.lstsq(out * w[:, None], s[:, 2] * w, rcond=None)[0]
        c = np.sum(w[:, None] * s[:, :2] * out[:, :2]) / np.sum(w[:, None] * out[:, :2] ** 2)  # x, y on the refined scale
        out = np.column_stack([c * out[:, :2], out @ pqr])
    return out


def light_direction_errors(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Angles (deg) between estimated and true unit light directions, (N,)."""
    a = est / np.linalg.norm(est, axis=1, keepdims=True)
    b = true / np.linalg.norm(true, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, 1), -1, 1)))


def perspective_curls(candidates, mask: np.ndarray, camera: Perspective, min_cos: float = 0.5) -> list[float]:
    """Relative mean |curl| of the perspective log-depth gradient implied by each normal map.

    With ``P = d r(u, v)``, ``r = ((u-cx)/fx, -(v-cy)/fy, -1)``:
    ``d(log d)/du = -(n1/fx)/(n.r)`` and ``d(log d)/dv = (n2/fy)/(n.r)``.
    All candidates are scored on the same pixels: those (with their right and
    upper neighbours) where every candidate's normal is at least ``min_cos``
    away from grazing its ray.  Near an occluding contour ``n.r -> 0`` and the
    gradient's finite differences blow up for the true field only (the
    flipped one turns away from the ray there), which on a sphere made the
    true normals look the less integrable by 10x.
    """
    h, w = mask.shape
    cx, cy = camera.principal_point()
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    r = np.stack([(jj - cx) / camera.fx, -(ii - cy) / camera.fy, -np.ones((h, w))], -1)
    rn = np.linalg.norm(r, axis=-1)
    good = mask.copy()
    grads = []
    for n in candidates:
        nr = np.sum(n * r, -1)
        good &= np.abs(nr) >= min_cos * rn * np.maximum(np.linalg.norm(n, axis=-1), 1e-12)
        nr = np.where(np.abs(nr) < 1e-9, -1e-9, nr)
        grads.append((-(n[..., 0] / camera.fx) / nr, (n[..., 1] / camera.fy) / nr))
    ok = good[1:, 1:] & good[:-1, :-1] & good[:-1, 1:] & good[1:, :-1]
    if ok.sum() < 20:
        return [float("nan")] * len(grads)
    out = []
    for gu, gv in grads:
        # circulation around each 2x2 cell, trapezoids on its edges: centred, so that the
        # discretisation error of an integrable field is second order (forward differences
        # taken at different points left the true sphere 5x less integrable than its flip)
        circ = 0.5 * (gu[:-1, :-1] + gu[:-1, 1:]) + 0.5 * (gv[:-1, 1:] + gv[1:, 1:]) - 0.5 * (gu[1:, :-1] + gu[1:, 1:]) - 0.5 * (gv[:-1, :-1] + gv[1:, :-1])
        scale = np.abs(gu[:-1, :-1][ok]).mean() + np.abs(gv[:-1, :-1][ok]).mean() + 1e-12
        out.append(float(np.abs(circ[ok]).mean() / scale))
    return out


def dark_images(images, mask, fraction: float = 0.1) -> list[int]:
    """Indices of the images whose 99th percentile (grey, inside ``mask``) is below ``fraction``
    times the median image's: failed captures whose light cannot be estimated (Yale B's
    yaleB02 ``A+095E+00`` at 0.01 and ``A-130E+20`` at 0.05; every other Yale B 01-04 and
    DiLiGenT ball / bear image is above 0.26)."""
    imgs = np.asarray(images)
    m = np.asarray(mask, bool)
    grey = imgs[:, m].reshape(imgs.shape[0], int(m.sum()), -1).mean(-1)
    p = np.percentile(grey, 99, axis=1)
    return [int(k) for k in np.where(p < fraction * np.median(p))[0]]


def specular_free(rgb: np.ndarray, source_color=(1.0, 1.0, 1.0)) -> np.ndarray:
    """The specular-free magnitude of RGB observations (the S-U-V colour space, Mallick et al. 2005).

    Under the dichromatic model ``I = E (a max(n.l, 0) + ks s c)`` the specular
    term has the colour ``c`` of the source, so the part of ``I`` orthogonal to
    ``c`` is diffuse only: ``|I - (I.c) c| = E max(n.l, 0) |a - (a.c) c|``
    (``c`` unit): a Lambertian image with the albedo's chromatic part as its
    albedo, whatever the specular lobe.  It is empty for a grey albedo
    (``a`` parallel to ``c``).

    Args:
        rgb: (..., 3) observations.
        source_color: the light's RGB colour (any scale).

    Returns:
        (...) magnitudes.
    """
    c = np.asarray(source_color, np.float64)
    if c.shape != (3,) or not np.all(np.isfinite(c)) or np.linalg.norm(c) <= 0:
        raise ValueError(f"source_color: expected 3 finite values, not all 0, got {source_color!r}")
    c = c / np.linalg.norm(c)
    x = np.asarray(rgb, np.float64)
    return np.linalg.norm(x - (x @ c)[..., None] * c, axis=-1)


def pixel_pseudo_normals(M, W, L, rounds: int = 3, k: float = 3.0):
    """Per pixel, the least-squares ``b`` of ``M[:, p] ~ L b`` over its weighted observations, refitted
    ``rounds`` times without the observations brighter than the fit by more than ``k`` robust standard
    deviations (highlights: a specular term only adds light), keeping at least 3."""
    W = W.copy()
    b = _solve_rows(W.T, M.T, L)
    for _ in range(rounds):
        r = M - L @ b.T
        sigma = 1.4826 * np.median(np.abs(r[W > 0])) + 1e-12
        Wn = W * (r < k * sigma)
        few = Wn.sum(0) < 3
        Wn[:, few] = W[:, few]
        if np.array_equal(Wn, W):
            break
        W = Wn
        b = _solve_rows(W.T, M.T, L)
    return b


def albedo_ls(rgb, W, normals, L):
    """Per-channel least-squares albedo given unit normals and lights (direction * intensity)."""
    shade = np.maximum(L @ normals.T, 0.0)  # (N, P)
    w = W * (shade > 0)
    num = np.einsum("np,np,npc->pc", w, shade, rgb)
    den = np.einsum("np,np->p", w, shade**2)[:, None]
    return num / np.maximum(den, 1e-12)


def to_map(v, mask):
    out = np.zeros(mask.shape + (v.shape[-1],), np.float32)
    out[mask] = v
    return out
