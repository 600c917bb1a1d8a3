"""Uncalibrated photometric stereo: normals, albedo and lights from images alone (seed ch. 5).

Pipeline (:func:`solve_uncalibrated`):

1. **Rank-3 factorisation** (5.8; Hayakawa): the grey image matrix ``M`` (N x P)
   is factored as ``M ~ L B^T`` by weighted alternating least squares, with
   shadowed and saturated observations as missing data (the seed's plain SVD
   of ``P`` is the special case with no missing data; it is the start).
   Pseudo-normals ``B`` and pseudo-lights ``L`` are known up to a 3x3 ``A``.
2. **Integrability** reduces ``A`` to the generalized bas-relief (GBR) family
   (Yuille & Snow 1997): with ``b = A b^`` the condition
   ``d(b1/b3)/dy = d(b2/b3)/dx`` is linear in ``c1 = a3 x a1`` and
   ``c2 = a3 x a2``: ``(b^ x b^_y) . c1 - (b^ x b^_x) . c2 = 0`` at every pixel.
3. **GBR resolution** with the evidence the images carry, combined in one
   objective over ``(alpha, beta, gamma)`` of ``b' = [[1,0,a],[0,1,b],[0,0,g]] b``:
   the *light-intensity prior* (all lights equally bright: small variance of
   ``log |s_k|``) and the *albedo entropy* (Alldrin et al. 2007: the albedo
   distribution is most concentrated at the true GBR).
4. What remains is the convex/concave flip ``(n1, n2, n3) -> (-n1, -n2, n3)``,
   exact for orthographic Lambertian images.  With a perspective camera the
   flipped normal field is not integrable, so the perspective curl decides it;
   otherwise the result says ``flip="ambiguous"`` and carries the alternative.
5. **Refinement** (5.1-5.7): the Lambertian + Ashikhmin-Shirley image model
   with normals, RGB albedo, lights and the shared (ks, eta) as unknowns,
   fitted by Adam through Warp's autodiff (:mod:`gpps.pipeline.uncalibrated`).

Where we differ from the text: the seed trains one "pseudo auto-encoder" per
input image with hand-derived updates (5.3-5.6) and merges the per-image
normal sets by PCA (5.1.7).  We fit one joint objective over all images with
exact autodiff gradients, because every image constrains the same normals;
:func:`pca_merge` implements 5.1.7 for callers that do produce several normal
sets (``UncalibratedConfig.normal_sets > 1`` fits bootstrap subsets of the
images and merges them this way).  The seed's (5.1) also omits
``max(n.l, n.v)`` and the irradiance cosine; see
:func:`gpps.kernels.brdf.ashikhmin_shirley_spec`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from gpps._check import as_array, as_mask
from gpps.camera import Orthographic, Perspective

Cue = Literal["intensity", "entropy"]
Refine = Literal["ashikhmin-shirley", "blinn-phong", "lambertian", "none"]

__all__ = ["UncalibratedConfig", "UncalibratedResult", "solve_uncalibrated", "factorize", "integrability_gbr", "gbr", "resolve_gbr", "pca_merge", "light_direction_errors"]


@dataclass
class UncalibratedConfig:
    """Options of :func:`solve_uncalibrated`.

    Attributes:
        cues: GBR evidence to combine ("intensity": lights of equal brightness;
            "entropy": albedo-distribution entropy).  At least one.
        refine: image model of the refinement ("none" stops after the GBR).
        shadow_fraction: observations below this fraction of an image's 99th
            percentile are shadows (dropped).
        highlight_trim: fraction of each pixel's brightest observations left
            out of the factorisation (highlight candidates; at least 3 stay).
            0 for Lambertian data.
        saturation: observations at or above this value are dropped.
        als_iterations: weighted factorisation iterations.
        refine_iterations: Adam steps of the joint refinement.
        refine_pixels: pixels (random subset) used to fit lights and material;
            all pixels are then solved with the lights fixed.
        final_iterations: Adam steps of the per-pixel pass with fixed lights.
        lr: Adam step size.
        normal_sets: > 1 fits that many bootstrap subsets of the images in
            the per-pixel pass and merges them by PCA (5.1.7).
        flip_ratio: perspective curl ratio above which the flip is decided.
        seed: random seed (pixel subsets, bootstraps).
    """

    cues: tuple[Cue, ...] = ("intensity", "entropy")
    refine: Refine = "ashikhmin-shirley"
    shadow_fraction: float = 0.05
    highlight_trim: float = 0.3
    saturation: float = 0.99
    als_iterations: int = 40
    refine_iterations: int = 300
    refine_pixels: int = 6000
    final_iterations: int = 150
    lr: float = 0.01
    normal_sets: int = 0
    flip_ratio: float = 1.3
    seed: int = 0

    def __post_init__(self):
        self.cues = tuple(self.cues)
        if not self.cues or any(c not in get_args(Cue) for c in self.cues):
            raise ValueError(f"cues: expected a non-empty subset of {list(get_args(Cue))}, got {self.cues!r}")
        if self.refine not in get_args(Refine):
            raise ValueError(f"refine: expected one of {list(get_args(Refine))}, got {self.refine!r}")
        if not 0 <= self.shadow_fraction < 1:
            raise ValueError(f"shadow_fraction: expected a value in [0, 1), got {self.shadow_fraction!r}")
        if not 0 <= self.highlight_trim < 1:
            raise ValueError(f"highlight_trim: expected a value in [0, 1), got {self.highlight_trim!r}")
        if not 0 < self.saturation <= 1.0 + 1e-9:
            raise ValueError(f"saturation: expected a value in (0, 1], got {self.saturation!r}")
        for name in ("als_iterations", "refine_iterations", "refine_pixels", "final_iterations", "normal_sets"):
            v = getattr(self, name)
            if int(v) != v or v < 0:
                raise ValueError(f"{name}: expected an integer >= 0, got {v!r}")
        if not self.lr > 0:
            raise ValueError(f"lr: expected > 0, got {self.lr!r}")


@dataclass
class UncalibratedResult:
    """Output of :func:`solve_uncalibrated`.

    Attributes:
        normals: (H, W, 3) unit normals (gpps frame), 0 outside the mask.
        albedo: (H, W, 3) RGB albedo (relative to the mean light intensity).
        light_directions: (N, 3) unit directions toward the lights.
        light_intensities: (N,) relative intensities (mean 1).
        flip: "resolved" (perspective cue) or "ambiguous".
        alternative: when ambiguous, the flipped ``(normals, light_directions)``.
        baseline: factorisation + integrability + GBR (before refinement):
            dict with ``normals`` and ``light_directions``.
        gbr: the GBR parameters chosen and the cue values.
        material: estimated ``ks`` and ``eta`` (Ashikhmin-Shirley) when refined.
        losses: refinement loss every 10 steps.
        timings: seconds per stage.
    """

    normals: np.ndarray
    albedo: np.ndarray
    light_directions: np.ndarray
    light_intensities: np.ndarray
    flip: str
    alternative: tuple | None
    baseline: dict
    gbr: dict
    material: dict = field(default_factory=dict)
    losses: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- factorisation


def factorize(M: np.ndarray, W: np.ndarray, iterations: int = 40, robust_rounds: int = 3, robust_k: float = 3.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted, robust rank-3 factorisation ``M ~ L B^T`` (5.8).

    Args:
        M: (N, P) grey intensities.
        W: (N, P) weights (0 = missing).
        iterations: alternating least-squares sweeps after the SVD start.
        robust_rounds: rounds that drop observations farther than ``robust_k``
            robust standard deviations from the rank-3 model (highlights, cast
            shadows: a Lambertian rank-3 model cannot explain them) and refit.

    Returns:
        L (N, 3), B (P, 3), and the final weights (N, P).
    """
    W = W.astype(np.float64)
    L, B = _als(M, W, iterations)
    for _ in range(robust_rounds):
        r = M - L @ B.T
        sigma = 1.4826 * np.median(np.abs(r[W > 0])) + 1e-12
        Wn = W * (np.abs(r) < robust_k * sigma)
        if np.array_equal(Wn, W) or (Wn.sum(0) < 3).mean() > 0.5:
            break
        W = Wn
        L, B = _als(M, W, iterations, start=(L, B))
    return L, B, W


def _als(M, W, iterations, start=None):
    if start is None:
        # SVD start on the observations, missing entries filled by the row means of the observed ones
        fill = np.where(W > 0, M, (M * W).sum(1, keepdims=True) / np.maximum(W.sum(1, keepdims=True), 1e-12))
        U, S, Vt = np.linalg.svd(fill, full_matrices=False)
        L = U[:, :3] * np.sqrt(S[:3])
        B = Vt[:3].T * np.sqrt(S[:3])
    else:
        L, B = start
    eye = 1e-9 * np.eye(3)
    for _ in range(iterations):
        # B: per-pixel 3x3 normal equations
        A = np.einsum("np,ni,nj->pij", W, L, L) + eye
        r = np.einsum("np,np,ni->pi", W, M, L)
        B = np.linalg.solve(A, r[..., None])[..., 0]
        A = np.einsum("np,pi,pj->nij", W, B, B) + eye
        r = np.einsum("np,np,pi->ni", W, M, B)
        L = np.linalg.solve(A, r[..., None])[..., 0]
    return L, B


def integrability_gbr(Bmap: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``A`` (3x3) such that ``A b^`` is integrable, up to a GBR (Yuille & Snow).

    Args:
        Bmap: (H, W, 3) pseudo-normals on the image grid.
        valid: (H, W) bool, pixels to use.

    Raises:
        ValueError: too few pixels with valid neighbours to fix ``A``.
    """
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
    _, _, Vt = np.linalg.svd(D, full_matrices=False)
    c = Vt[-1]
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


def _cue_values(B, L, h, cues):
    H = gbr(*h)
    Hit = np.linalg.inv(H).T
    out = {}
    if "intensity" in cues:
        e = np.linalg.norm(L @ Hit.T, axis=1)
        out["intensity"] = float(np.var(np.log(np.maximum(e, 1e-12))))
    if "entropy" in cues:
        out["entropy"] = _entropy(np.linalg.norm(B @ H.T, axis=1))
    return out


def resolve_gbr(B: np.ndarray, L: np.ndarray, cues=("intensity", "entropy"), seed: int = 0) -> tuple[np.ndarray, dict]:
    """Choose the GBR ``(alpha, beta, gamma > 0)`` by the given cues.

    The objective is ``var(log|s_k|) / 1e-4 + entropy / 0.1`` (each term
    divided by a typical resolution so that neither dominates), searched on a
    grid and polished by Nelder-Mead.

    Args:
        B: (P, 3) integrable pseudo-normals (a subset of pixels is enough).
        L: (N, 3) pseudo-lights.
    """
    from scipy.optimize import minimize

    rng = np.random.default_rng(seed)
    if len(B) > 4000:
        B = B[rng.choice(len(B), 4000, replace=False)]
    scale = {"intensity": 1e-4, "entropy": 0.1}

    def f(x):
        h = (x[0], x[1], np.exp(x[2]))
        v = _cue_values(B, L, h, cues)
        return sum(v[c] / scale[c] for c in cues)

    grid = np.linspace(-3, 3, 13)
    best = None
    for a in grid:
        for b in grid:
            for g in np.linspace(-3, 3, 13):
                val = f((a, b, g))
                if best is None or val < best[0]:
                    best = (val, (a, b, g))
    res = minimize(f, np.array(best[1]), method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-8, "maxiter": 2000})
    x = res.x
    h = (float(x[0]), float(x[1]), float(np.exp(x[2])))
    return gbr(*h), {"alpha": h[0], "beta": h[1], "gamma": h[2], "objective": float(res.fun), **_cue_values(B, L, h, cues)}


# --------------------------------------------------------------------------- post-processing


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


def light_direction_errors(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Angles (deg) between estimated and true unit light directions, (N,)."""
    a = est / np.linalg.norm(est, axis=1, keepdims=True)
    b = true / np.linalg.norm(true, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.sum(a * b, 1), -1, 1)))


def _perspective_curl(normals: np.ndarray, mask: np.ndarray, camera: Perspective) -> float:
    """Mean |curl| of the perspective log-depth gradient implied by ``normals``.

    With ``P = d r(u, v)``, ``r = ((u-cx)/fx, -(v-cy)/fy, -1)``:
    ``d(log d)/du = -(n1/fx)/(n.r)`` and ``d(log d)/dv = (n2/fy)/(n.r)``.
    """
    h, w = mask.shape
    cx, cy = camera.principal_point()
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    r = np.stack([(jj - cx) / camera.fx, -(ii - cy) / camera.fy, -np.ones((h, w))], -1)
    nr = np.sum(normals * r, -1)
    nr = np.where(np.abs(nr) < 1e-9, -1e-9, nr)
    gu = -(normals[..., 0] / camera.fx) / nr
    gv = (normals[..., 1] / camera.fy) / nr
    curl = (gu[1:, :-1] - gu[:-1, :-1]) - (gv[:-1, 1:] - gv[:-1, :-1])
    ok = mask[1:, :-1] & mask[:-1, :-1] & mask[:-1, 1:]
    scale = np.abs(gu[:-1, :-1][ok]).mean() + np.abs(gv[:-1, :-1][ok]).mean() + 1e-12
    return float(np.abs(curl[ok]).mean() / scale)


# --------------------------------------------------------------------------- the pipeline


def _prepare(images, mask):
    imgs = as_array("images", images)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    if imgs.ndim != 4 or imgs.shape[-1] not in (1, 3):
        raise ValueError(f"images: expected shape (N, H, W), (N, H, W, 1) or (N, H, W, 3), got {np.shape(images)}")
    if imgs.shape[0] < 3:
        raise ValueError(f"images: expected at least 3 images, got {imgs.shape[0]}")
    if imgs.shape[-1] == 1:
        imgs = np.repeat(imgs, 3, axis=-1)
    m = as_mask("mask", mask, imgs.shape[1:3])
    if m.sum() < 50:
        raise ValueError(f"mask: expected at least 50 pixels, got {int(m.sum())}")
    if np.any(imgs < 0):
        raise ValueError("images: expected values >= 0")
    dark = [k for k in range(imgs.shape[0]) if not np.any(imgs[k][m] > 1e-6)]
    if dark:
        raise ValueError(f"images: image(s) {dark} are all dark inside the mask")
    return imgs.astype(np.float32), m


def solve_uncalibrated(images, mask, *, camera=None, config: UncalibratedConfig | None = None, device=None, progress=None) -> UncalibratedResult:
    """Normals, RGB albedo, light directions and intensities from images alone.

    Args:
        images: (N, H, W[, C]) linear intensities, N >= 3 (C = 1 or 3).
        mask: (H, W) bool.
        camera: None / :class:`Orthographic` (flip stays ambiguous) or
            :class:`Perspective` (decides the flip; view vectors per pixel).
        config: :class:`UncalibratedConfig`.
        device: Warp device for the refinement.
        progress: optional ``progress(done, total, message)``.

    Raises:
        ValueError: fewer than 3 images, an all-dark image, rank < 3 data
            (e.g. coplanar lights), bad shapes or values.
    """
    cfg = config or UncalibratedConfig()
    if camera is not None and not isinstance(camera, (Orthographic, Perspective)):
        raise TypeError(f"camera: expected None, Orthographic or Perspective, got {type(camera).__name__}")
    step = progress or (lambda *a, **k: None)
    t0 = time.perf_counter()
    imgs, mask = _prepare(images, mask)
    N = imgs.shape[0]
    rgb = imgs[:, mask]  # (N, P, 3)
    M = rgb.mean(-1).astype(np.float64)
    hi = np.percentile(M, 99, axis=1, keepdims=True)
    W = ((M > cfg.shadow_fraction * hi) & (rgb.max(-1) < cfg.saturation)).astype(np.float64)
    W_obs = W.copy()  # what the refinement sees: it models highlights, so it keeps them
    drop = min(int(cfg.highlight_trim * N), N - 3)
    if drop > 0:
        rank = np.argsort(np.argsort(M, axis=0), axis=0)
        W = W * (rank < N - drop)
    # rank test on fully lit pixels (or all, if none are lit everywhere)
    full = W.all(0)
    S = np.linalg.svd(M[:, full] if full.sum() >= 10 else M, compute_uv=False)
    if len(S) < 3 or S[2] < 1e-3 * S[0]:
        raise ValueError(f"images: the data have rank < 3 (singular values {np.round(S[:4] / S[0], 5).tolist()}); the lights may be coplanar or too few differ")
    L0, B0, W = factorize(M, W, cfg.als_iterations)
    step(1, 5, "factorised")
    t_fact = time.perf_counter()
    Bmap = np.zeros(mask.shape + (3,))
    Bmap[mask] = B0
    fit_ok = np.zeros(mask.shape, bool)
    fit_ok[mask] = W.sum(0) >= 3
    A = integrability_gbr(Bmap, fit_ok)
    B = B0 @ A.T
    L = L0 @ np.linalg.inv(A)
    if np.median(B[:, 2]) < 0:  # the global sign: normals face the camera
        B, L = -B, -L
    H, gbr_info = resolve_gbr(B[W.sum(0) >= 3], L, cfg.cues, seed=cfg.seed)
    B = B @ H.T
    L = L @ np.linalg.inv(H)  # s' = H^-T s (rows)
    step(2, 5, "GBR resolved")
    t_gbr = time.perf_counter()

    def unit(a):
        return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)

    base_n = unit(B)
    base_l = unit(L)
    if np.median(base_l[:, 2]) < 0:
        base_l = -base_l
    baseline = {"normals": _to_map(base_n, mask), "light_directions": base_l}
    flip_m = np.diag([-1.0, -1.0, 1.0])
    # views
    P = int(mask.sum())
    if isinstance(camera, Perspective):
        _, rays = camera.rays(mask.shape)
        views = -rays[mask]
    else:
        views = np.tile([0.0, 0.0, 1.0], (P, 1))
    normals, lights, albedo = base_n, L, None
    material: dict = {}
    losses: list = []
    if cfg.refine != "none":
        from gpps.pipeline.uncalibrated import Refiner

        spec = {"lambertian": 0, "ashikhmin-shirley": 1, "blinn-phong": 2}[cfg.refine]
        Wrgb = W_obs
        rng = np.random.default_rng(cfg.seed)
        sub = rng.choice(P, min(P, cfg.refine_pixels), replace=False) if cfg.refine_pixels and cfg.refine_pixels < P else np.arange(P)
        # intensities normalised to mean 1; albedo by per-channel least squares
        e = np.linalg.norm(L, axis=1)
        L = L / e.mean()
        alb = _albedo_ls(rgb, Wrgb, normals, L)
        ref = Refiner(N, len(sub), device=device)
        r = ref.run(rgb[:, sub], Wrgb[:, sub], views[sub], normals[sub], alb[sub], L, specular=spec, iterations=cfg.refine_iterations, lr=cfg.lr,
                    progress=lambda d, t, m: step(2 + d / t, 5, "refining lights: " + m))
        lights = r.lights
        material = {"brdf": cfg.refine, "ks": r.ks}
        if cfg.refine == "ashikhmin-shirley":
            material.update(eta_u=r.eta, eta_v=r.eta, f0=0.5)
        elif cfg.refine == "blinn-phong":
            material.update(shininess=r.eta)
        losses = r.losses
        step(3, 5, "lights refined")
        sets = max(1, cfg.normal_sets)
        ref_all = Refiner(N, P, device=device) if len(sub) != P or sets > 1 else ref
        nsets = []
        for s in range(sets):
            Wk = Wrgb
            if sets > 1:
                keep = rng.random(N) < 0.7
                keep[rng.choice(N, 3, replace=False)] = True
                Wk = Wrgb * keep[:, None]
            if len(sub) == P and sets == 1:
                nsets.append(r.normals)
                albedo = r.albedo
                continue
            rr = ref_all.run(rgb, Wk, views, normals, _albedo_ls(rgb, Wk, normals, lights), lights, ks=max(r.ks, 1e-4), eta=r.eta, specular=spec,
                             fit_lights=False, iterations=cfg.final_iterations, lr=cfg.lr,
                             progress=lambda d, t, m: step(3 + (s + d / t) / sets, 5, "per-pixel pass: " + m))
            nsets.append(rr.normals)
            albedo = rr.albedo
        normals = nsets[0] if len(nsets) == 1 else pca_merge(np.stack(nsets))
    t_ref = time.perf_counter()
    e = np.linalg.norm(lights, axis=1)
    ldirs = lights / e[:, None]
    if albedo is None:
        albedo = _albedo_ls(rgb, W, normals, lights / e.mean())
    intens = e / e.mean()
    # the convex/concave flip
    flip = "ambiguous"
    alternative = (_to_map(normals @ flip_m, mask), ldirs @ flip_m)
    gbr_info["flip_curl"] = None
    if isinstance(camera, Perspective):
        c0 = _perspective_curl(_to_map(normals, mask), mask, camera)
        c1 = _perspective_curl(alternative[0], mask, camera)
        gbr_info["flip_curl"] = [c0, c1]
        if max(c0, c1) > cfg.flip_ratio * min(c0, c1):
            flip = "resolved"
            if c1 < c0:
                normals, ldirs = normals @ flip_m, ldirs @ flip_m
            alternative = None
    step(5, 5, "done")
    return UncalibratedResult(
        normals=_to_map(normals, mask),
        albedo=_to_map(albedo, mask),
        light_directions=ldirs,
        light_intensities=intens,
        flip=flip,
        alternative=alternative,
        baseline=baseline,
        gbr=gbr_info,
        material=material,
        losses=losses,
        timings={"factorisation": t_fact - t0, "gbr": t_gbr - t_fact, "refinement": t_ref - t_gbr, "total": time.perf_counter() - t0},
    )


def _albedo_ls(rgb, W, normals, L):
    """Per-channel least-squares albedo given unit normals and lights (direction * intensity)."""
    shade = np.maximum(L @ normals.T, 0.0)  # (N, P)
    w = W * (shade > 0)
    num = np.einsum("np,np,npc->pc", w, shade, rgb)
    den = np.einsum("np,np->p", w, shade**2)[:, None]
    return num / np.maximum(den, 1e-12)


def _to_map(v, mask):
    out = np.zeros(mask.shape + (v.shape[-1],), np.float32)
    out[mask] = v
    return out
