"""Images from the wild (seed ch. 6): network prior refined by cuckoo search.

With one image, or three, of an object and nothing else (no lights, no
camera, no scene), :func:`reconstruct_single`

1. predicts normals and a relative depth with the shipped network
   (:class:`gpps.nn.model.SingleNet`, numpy) from each image and averages the
   normals (with one image: that image's prediction);
2. estimates the lights jointly (uncalibrated): given the current normals,
   each light's direction and RGB intensity by least squares on the
   Lambertian part (attached shadows and the brightest 2 % left out, 30
   alternations with the albedo) and the albedo by least squares
   (:func:`estimate_lights`); then the generalized bas-relief that Lambertian
   shading cannot see, with a global Blinn-Phong ``ks`` and ``shininess``, from the
   specular highlights (:func:`fit_highlights`): lights fitted to the network's
   normals inherit the network's bias along the bas-relief family (a flattened
   sphere makes them ~10 deg too oblique), the highlights do not;
3. refines every pixel's normal and albedo by cuckoo search
   (:mod:`gpps.pipeline.cuckoo`, Warp) on the Blinn-Phong reprojection error
   plus ``prior_weight |n - n_prior|^2`` (``n_prior``: the network's normals
   through the bas-relief of step 2), nests started around the current
   normals; steps 2-3 repeat ``rounds`` times;
4. integrates the refined normals into depth (:func:`gpps.flows.integrate.integrate_normals`).

Scale: images are divided by one common 99th percentile, so light
intensities and albedos are relative.  Without a camera the view is
orthographic and depth is in units of half the image's longer side.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal, get_args

import numpy as np

from gpps._check import as_images, check_number
from gpps._runtime import resolve_device, warp
from gpps.pipeline.cuckoo import CuckooConfig, CuckooSearch

__all__ = ["HighlightFit", "SingleConfig", "SingleResult", "estimate_lights", "factorization_normals", "fit_highlights",
           "integrable_normals", "prepare_images", "reconstruct_single"]

AlbedoMode = Literal["search", "least-squares"]
LightStart = Literal["integrability", "factorization", "least-squares"]
SpecularMode = Literal["estimate", "ks", "off"]


@dataclass(frozen=True)
class SingleConfig:
    """Settings of :func:`reconstruct_single`.

    Attributes:
        cuckoo: the search (nests, generations per round, beta = 0.01, p_c = 0.4, seed).
        rounds: light-estimation / search rounds (0: the network's output only).
        prior_weight: weight of ``|n - n_prior|^2`` in the objective; None: 0.002 with
            three or more images, 0.05 with fewer (one image cannot fix a normal).
        shininess: Blinn-Phong exponent of the objective where it is not estimated
            (``specular="ks"``, or no highlight seen), and the start of its estimate.
        specular: ``"estimate"``: the lights' bas-relief, ``ks`` and ``shininess`` from the
            highlights each round (:func:`fit_highlights`); ``"ks"``: lights by least squares
            alone and one global ks at the fixed ``shininess``; ``"off"``: ks = 0.
        shininess_range: ``(lo, hi)`` bounds of the estimated shininess.
        highlight_prior_deg: angular spread (deg) of the normals' prior in
            :func:`fit_highlights`; None: the network's validation MAEN (its ``meta``), else 10.
        albedo: ``"search"``: the albedo is part of each habitat (x = (n_x, n_y, r, g, b));
            ``"least-squares"``: habitats carry the normal, the albedo is solved per candidate.
        init_spread: standard deviation of the nests' start around the current normal (n_x, n_y).
        net_size: the network's working resolution (longer side); None: the trained one.
        integrate: integrate the refined normals into depth.
        lights: the normals the first round's lights are fitted to, with three or more images:
            ``"integrability"`` (factorisation, integrability, GBR fitted to the network's
            normals: :func:`integrable_normals`), ``"factorization"`` (the whole 3x3 ambiguity
            fitted to the network's normals: :func:`factorization_normals`) or
            ``"least-squares"`` (the network's normals themselves); later rounds and single
            images always fit the lights to the current normals by least squares.
    """

    cuckoo: CuckooConfig = field(default_factory=lambda: CuckooConfig(nests=12, generations=80))
    rounds: int = 1
    prior_weight: float | None = None
    shininess: float = 30.0
    specular: SpecularMode = "estimate"
    shininess_range: tuple[float, float] = (5.0, 300.0)
    highlight_prior_deg: float | None = None
    albedo: AlbedoMode = "search"
    init_spread: float = 0.1
    net_size: int | None = None
    integrate: bool = True
    lights: LightStart = "least-squares"

    def __post_init__(self):
        if self.lights not in get_args(LightStart):
            raise ValueError(f"lights: expected one of {list(get_args(LightStart))}, got {self.lights!r}")
        if not isinstance(self.cuckoo, CuckooConfig):
            raise TypeError(f"cuckoo: expected CuckooConfig, got {type(self.cuckoo).__name__}")
        object.__setattr__(self, "rounds", check_number("rounds", self.rounds, lo=0, integer=True))
        if self.prior_weight is not None:
            object.__setattr__(self, "prior_weight", check_number("prior_weight", self.prior_weight, lo=0.0))
        object.__setattr__(self, "shininess", check_number("shininess", self.shininess, lo=0.0, lo_open=True))
        if self.specular not in get_args(SpecularMode):
            raise ValueError(f"specular: expected one of {list(get_args(SpecularMode))}, got {self.specular!r}")
        rng = self.shininess_range
        if not isinstance(rng, (tuple, list)) or len(rng) != 2:
            raise ValueError(f"shininess_range: expected (lo, hi), got {rng!r}")
        lo = check_number("shininess_range", rng[0], lo=0.0, lo_open=True)
        hi = check_number("shininess_range", rng[1], lo=lo)
        object.__setattr__(self, "shininess_range", (lo, hi))
        if self.highlight_prior_deg is not None:
            object.__setattr__(self, "highlight_prior_deg",
                               check_number("highlight_prior_deg", self.highlight_prior_deg, lo=0.0, lo_open=True, hi=90.0))
        if self.albedo not in get_args(AlbedoMode):
            raise ValueError(f"albedo: expected one of {list(get_args(AlbedoMode))}, got {self.albedo!r}")
        object.__setattr__(self, "init_spread", check_number("init_spread", self.init_spread, lo=0.0))
        if self.net_size is not None:
            n = check_number("net_size", self.net_size, lo=16, integer=True)
            object.__setattr__(self, "net_size", n)


@dataclass
class SingleResult:
    """What :func:`reconstruct_single` found.

    Attributes:
        mask: (H, W) bool pixels reconstructed.
        normals_net: (H, W, 3) the network's normals (averaged over the images).
        normals_net_first: (H, W, 3) the network's normals from the first image alone.
        height_net: (H, W) the network's relative depth (a height: larger is nearer;
            units of half the longer image side, mean 0).
        normals: (H, W, 3) refined normals (= normals_net when rounds = 0).
        albedo: (H, W, 3) RGB albedo (relative).
        light_directions: (N, 3) estimated unit directions toward the lights.
        light_intensities: (N, 3) estimated RGB intensities (relative).
        ks: estimated Blinn-Phong specular weight.
        depth: (H, W) depth from the refined normals (0 outside; None when not integrated).
        objective: per round, the mean objective before and after the search.
        timings: seconds per stage.
        shininess: the Blinn-Phong exponent of the last round.
        highlights: per round, :attr:`HighlightFit.info` (empty unless ``specular="estimate"``).
    """

    mask: np.ndarray
    normals_net: np.ndarray
    normals_net_first: np.ndarray
    height_net: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    light_directions: np.ndarray
    light_intensities: np.ndarray
    ks: float
    depth: np.ndarray | None
    objective: list = field(default_factory=list)
    timings: dict = field(default_factory=dict)
    shininess: float = 30.0
    highlights: list = field(default_factory=list)


def prepare_images(images, mask=None) -> tuple[np.ndarray, np.ndarray]:
    """``(images (N, H, W, 3) float32 scaled by one common 99th percentile, mask (H, W) bool)``.

    ``images``: one (H, W) / (H, W, 3) image, or a sequence / array of N of them.
    """
    if isinstance(images, (list, tuple)):
        items = [as_images(f"images[{k}]", i) for k, i in enumerate(images)]
        items = [i[..., None] if i.ndim == 2 else i for i in items]
        if not items or any(i.ndim != 3 or i.shape != items[0].shape for i in items):
            raise ValueError(f"images: expected (H, W) or (H, W, 3) images of one shape, got {[i.shape for i in items]}")
        a = np.stack(items)
    else:
        a = as_images("images", images)
        if a.ndim == 2:
            a = a[None, ..., None]
        elif a.ndim == 3:  # one RGB image (H, W, 3), else N grey images (N, H, W)
            a = a[None] if a.shape[-1] == 3 else a[..., None]
    if a.ndim != 4 or a.shape[-1] not in (1, 3):
        raise ValueError(f"images: expected (H, W), (H, W, 3) or N of them, got shape {np.shape(images)}")
    if a.shape[-1] == 1:
        a = np.repeat(a, 3, -1)
    a = np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)
    a = np.maximum(a, 0.0)
    h, w = a.shape[1:3]
    m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    if m.shape != (h, w):
        raise ValueError(f"mask: expected shape {(h, w)}, got {m.shape}")
    m = m & (a.max(axis=(0, 3)) > 0)
    if m.sum() < 16:
        raise ValueError(f"mask: expected at least 16 lit object pixels, got {int(m.sum())}")
    p = float(np.percentile(a[:, m].max(-1), 99.0))
    return (a / max(p, 1e-12)).astype(np.float32), m


def _view_dirs(camera, shape, mask):
    if camera is None or not getattr(camera, "is_perspective", False):
        v = np.zeros((int(mask.sum()), 3), np.float32)
        v[:, 2] = 1.0
        return v
    _, d = camera.rays(shape)
    return (-d[mask]).astype(np.float32)


def _bp_spec(n, l, v, shininess):
    h = l[None] + v
    h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    c = np.sum(n * h, -1)
    return np.where((c > 0) & (np.sum(n * l, -1) > 0), np.maximum(c, 0.0) ** shininess, 0.0)


def estimate_lights(I, n, view, *, albedo=None, shininess=30.0, specular=True, iterations=30):
    """Lights, albedo and ks from images and normals (the uncalibrated step of each round).

    Args:
        I: (N, P, 3) intensities of P pixels.
        n: (P, 3) unit normals.
        view: (P, 3) unit view directions.
        albedo: (P, 3) start albedo (None: ones).

    Returns:
        (directions (N, 3), intensities (N, 3), albedo (P, 3), ks): the mean intensity is
        kept at 1 (the scale is shared with the albedo).
    """
    I = np.asarray(I, np.float64)
    n = np.asarray(n, np.float64)
    nl, npx = I.shape[0], I.shape[1]
    kd = np.ones((npx, 3)) if albedo is None else np.maximum(np.asarray(albedo, np.float64), 1e-3)
    dirs = np.tile([0.0, 0.0, 1.0], (nl, 1))
    rgb = np.ones((nl, 3))
    bright = np.zeros((nl, npx), bool)
    for k in range(nl):
        g = I[k].sum(-1)
        bright[k] = g > np.quantile(g, 0.98)
    for it in range(iterations):
        for k in range(nl):
            Lc = np.zeros((3, 3))
            for c in range(3):
                ok = ~bright[k] & (I[k, :, c] > 1e-4) if it == 0 else ~bright[k] & (n @ dirs[k] > 0.05)
                if ok.sum() < 10:
                    ok = ~bright[k]
                A = kd[ok, c, None] * n[ok]
                Lc[c] = np.linalg.lstsq(A, I[k, ok, c], rcond=None)[0]
            s = Lc.sum(0)
            if np.linalg.norm(s) < 1e-12:
                continue
            dirs[k] = s / np.linalg.norm(s)
            rgb[k] = np.maximum(Lc @ dirs[k], 1e-6)
        shade = np.maximum(n @ dirs.T, 0.0)  # (P, N)
        num = np.einsum("pk,kpc,kc->pc", shade, I, rgb)
        den = np.einsum("pk,kc->pc", shade**2, rgb**2)
        kd = np.where(den > 1e-12, np.maximum(num / np.maximum(den, 1e-12), 0.0), kd)
        scale = rgb.mean()
        rgb /= scale
        kd *= scale
    ks = 0.0
    if specular:
        v = np.asarray(view, np.float64)
        num = den = 0.0
        for k in range(nl):
            s = _bp_spec(n, dirs[k], v, shininess)  # (P,)
            r = I[k] - rgb[k] * kd * np.maximum(n @ dirs[k], 0.0)[:, None]
            es = rgb[k][None] * s[:, None]
            num += float(np.sum(r * es))
            den += float(np.sum(es * es))
        ks = float(np.clip(num / den, 0.0, 2.0)) if den > 1e-12 else 0.0
    return dirs.astype(np.float32), rgb.astype(np.float32), kd.astype(np.float32), ks


@dataclass
class HighlightFit:
    """What :func:`fit_highlights` found.

    Attributes:
        gbr: (3, 3) the bas-relief ``G = [[1, 0, 0], [0, 1, 0], [mu, nu, lam]]`` (identity when rejected).
        directions: (N, 3) unit light directions ``G l / |G l|``.
        intensities: (N, 3) RGB intensities ``E |G l|``, rescaled to mean 1.
        normals: (P, 3) unit normals ``G^-T n / |G^-T n|``.
        albedo: (P, 3) albedo that keeps the Lambertian part of every image unchanged.
        ks: specular weight (0 when rejected).
        shininess: Blinn-Phong exponent.
        accepted: the highlights were seen and explain the images (see :func:`fit_highlights`).
        info: the numbers of the fit (``lam``, ``mu``, ``nu``, ``ks``, ``shininess``, ``accepted``,
            ``evidence`` (BIC gain), ``sse_ratio`` (residual after / before the lobe), ``normal_change_rms_deg``,
            ``peak`` (per light, the largest lobe value ``max_p s``)).
    """

    gbr: np.ndarray
    directions: np.ndarray
    intensities: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    ks: float
    shininess: float
    accepted: bool
    info: dict


def _gbr(theta) -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [theta[1], theta[2], np.exp(theta[0])]])


def fit_highlights(I, n, view, directions, intensities, albedo, *, prior_deg: float = 10.0, shininess: float = 30.0,
                   shininess_range=(5.0, 300.0), max_pixels: int = 16384) -> HighlightFit:
    """The lights' generalized bas-relief, ``ks`` and ``shininess`` from the specular highlights.

    Lambertian shading cannot tell normals ``n`` and lights ``l`` from ``G^-T n`` and ``G l``
    for any bas-relief ``G = [[1, 0, 0], [0, 1, 0], [mu, nu, lam]]`` (Belhumeur, Kriegman
    and Yuille 1999: ``(G^-T n).(G l) = n.l``, attached shadows kept), so lights fitted
    to a prior's normals by least squares (:func:`estimate_lights`) inherit the prior's bias
    along that family (on the 256^2 Blinn-Phong sphere of ``perf/single_image.py`` the
    network's slants are 3-14 deg too small and the lights come out 9-11 deg too oblique,
    after which the refinement fits the flattened shape and ends worse than the network).  The
    specular lobe peaks where ``n = h = (l + v) / |l + v|``, which ``G`` moves, so the
    highlights fix ``G`` (Drbohlav and Sara 2002; Georghiades 2003).

    The estimate maximises the posterior with Gaussian residuals of unknown variance and
    the prior ``angle(G^-T n, n) ~ N(0, prior_deg^2)`` per pixel:
    ``(M / 2) log SSE(G, ks, s) + sum_p angle_p^2 / (2 prior_deg^2)``, ``M`` the lit
    observations, ``SSE`` the squared residual of the Lambertian model (unchanged by
    ``G``) minus the lobe ``E'_k ks max(n'.h'_k, 0)^s``.  ``ks`` is solved in closed form,
    at most what the brightest observation allows (``ks E'_k max_p s_kp <= max_p I_kp``);
    ``(log lam, mu, nu, log s)`` by Nelder-Mead from the identity and the best ``s`` of a
    grid.  The fit is *accepted* when every light's lobe reaches half its peak on some
    pixel (``max_p s_kp >= 1/2``; a lobe fitted by its tail alone explains shading
    errors, not a highlight) and the lobe with ``G`` (5 parameters) beats the Lambertian
    model alone by the Bayesian information criterion (``evidence > 0``; noise alone
    fits a small lobe too).  Rejected: ``G = I``, ``ks = 0``, the given ``shininess``.

    Args:
        I: (N, P, 3) intensities; n: (P, 3) unit normals the lights were fitted to;
        view: (P, 3) unit view directions; directions, intensities: (N, 3) lights;
        albedo: (P, 3) albedo (the Lambertian part is ``E_k albedo max(n.l_k, 0)``).
        prior_deg: spread of the normals' prior (deg), e.g. the network's validation MAEN.
        shininess: start (and the exponent returned when rejected).
        shininess_range: bounds ``(lo, hi)`` of the exponent.
        max_pixels: the fit uses every k-th pixel to at most this many (the output covers all).

    Raises:
        ValueError: inconsistent shapes or a bad setting, naming the argument.
    """
    from scipy.optimize import minimize

    I = np.asarray(I, np.float64)
    n = np.asarray(n, np.float64)
    view = np.asarray(view, np.float64)
    dirs = np.asarray(directions, np.float64)
    rgb = np.asarray(intensities, np.float64)
    kd = np.asarray(albedo, np.float64)
    if I.ndim != 3 or I.shape[-1] != 3:
        raise ValueError(f"I: expected shape (N, P, 3), got {I.shape}")
    nl, npx = I.shape[:2]
    for name, a, shape in (("n", n, (npx, 3)), ("view", view, (npx, 3)), ("directions", dirs, (nl, 3)),
                           ("intensities", rgb, (nl, 3)), ("albedo", kd, (npx, 3))):
        if a.shape != shape:
            raise ValueError(f"{name}: expected shape {shape}, got {a.shape}")
    prior_deg = check_number("prior_deg", prior_deg, lo=0.0, lo_open=True, hi=90.0)
    shininess = check_number("shininess", shininess, lo=0.0, lo_open=True)
    if len(shininess_range) != 2:
        raise ValueError(f"shininess_range: expected (lo, hi), got {shininess_range!r}")
    s_lo = check_number("shininess_range", shininess_range[0], lo=0.0, lo_open=True)
    s_hi = check_number("shininess_range", shininess_range[1], lo=s_lo)
    max_pixels = check_number("max_pixels", max_pixels, lo=1, integer=True)

    sel = np.arange(0, npx, max(1, -(-npx // max_pixels)))
    Is, ns, vs = I[:, sel], n[sel], view[sel]
    shade = np.maximum(ns @ dirs.T, 0.0).T  # (N, Ps)
    r = Is - rgb[:, None, :] * kd[sel][None] * shade[:, :, None]  # Lambertian residual, the same for every G
    m_obs = max(3 * int(np.count_nonzero(shade > 0)), 1)
    i_max = Is.max(axis=(1, 2))
    sig2 = np.radians(prior_deg) ** 2

    def model(theta):
        G = _gbr(theta)
        sh = float(np.clip(np.exp(theta[3]), s_lo, s_hi))
        b = ns @ np.linalg.inv(G)  # rows G^-T n
        n2 = b / np.linalg.norm(b, axis=1, keepdims=True)
        gl = dirs @ G.T
        gn = np.linalg.norm(gl, axis=1)
        l2 = gl / gn[:, None]
        e2 = rgb * gn[:, None]
        e2 /= e2.mean()
        lobe = np.zeros(shade.shape)
        for k in range(nl):
            h = l2[k][None] + vs
            h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
            c = np.sum(n2 * h, 1)
            lobe[k] = np.where((c > 0) & (shade[k] > 0), np.maximum(c, 1e-30) ** sh, 0.0)
        es = e2[:, None, :] * lobe[:, :, None]
        den = float(np.sum(es * es))
        ks = max(float(np.sum(es * r)) / den, 0.0) if den > 1e-20 else 0.0
        peak = lobe.max(1)
        ks = min(ks, float(np.min(i_max / np.maximum(e2.max(1) * peak, 1e-12))))
        sse = float(np.sum((r - ks * es) ** 2))
        ang2 = float(np.sum(np.arccos(np.clip(np.sum(n2 * ns, 1), -1.0, 1.0)) ** 2))
        return sse, ang2, ks, sh, peak

    def objective(theta):
        sse, ang2 = model(theta)[:2]
        return 0.5 * m_obs * np.log(max(sse, 1e-300)) + ang2 / (2.0 * sig2)

    grid = np.unique(np.append(np.geomspace(s_lo, s_hi, 9), np.clip(shininess, s_lo, s_hi)))
    j0 = [objective(np.array([0.0, 0.0, 0.0, np.log(g)])) for g in grid]
    t0 = np.array([0.0, 0.0, 0.0, np.log(grid[int(np.argmin(j0))])])
    opt = minimize(objective, t0, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-3, "maxiter": 800})
    theta = opt.x if opt.fun <= objective(t0) else t0
    sse, ang2, ks, sh, peak = model(theta)
    sse0 = float(np.sum(r * r))
    # BIC of the lobe and the bas-relief (5 parameters) against the Lambertian model alone
    evidence = 0.5 * m_obs * np.log(max(sse0, 1e-300) / max(sse, 1e-300)) - 2.5 * np.log(m_obs)
    accepted = bool(ks > 0.0 and evidence > 0.0 and np.all(peak >= 0.5))
    info = {"lam": float(np.exp(theta[0])), "mu": float(theta[1]), "nu": float(theta[2]), "ks": float(ks),
            "shininess": sh, "accepted": accepted, "evidence": float(evidence), "sse_ratio": sse / max(sse0, 1e-300),
            "normal_change_rms_deg": float(np.degrees(np.sqrt(ang2 / len(sel)))), "peak": peak.tolist()}
    if not accepted:
        return HighlightFit(np.eye(3), dirs.astype(np.float32), rgb.astype(np.float32), n.astype(np.float32),
                            kd.astype(np.float32), 0.0, float(shininess), False, info)
    G = _gbr(theta)
    b = n @ np.linalg.inv(G)
    bn = np.linalg.norm(b, axis=1, keepdims=True)
    gl = dirs @ G.T
    gn = np.linalg.norm(gl, axis=1)
    e2 = rgb * gn[:, None]
    scale = e2.mean()
    return HighlightFit(G, (gl / gn[:, None]).astype(np.float32), (e2 / scale).astype(np.float32),
                        (b / bn).astype(np.float32), (kd * bn * scale).astype(np.float32), float(ks), sh, True, info)


def factorization_normals(I, prior, *, irls: int = 3, shadow: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Uncalibrated Lambertian normals from N >= 3 images, their linear ambiguity fixed by a prior.

    The grey intensities ``M`` (P, N) are factorised to rank 3, ``M ~ B0 S0`` (SVD); any
    ``B = B0 A``, ``S = A^-1 S0`` fits as well.  ``A`` (3 x 3, up to scale) is the one that
    makes ``B`` most parallel to the ``prior`` normals: the smallest eigenvector of
    ``sum_p w_p G_p^T (I - n_p n_p^T) G_p`` (``G_p a = B0_p A``), re-weighted ``irls`` times by
    ``w = 1 / (1 + (angle / 15 deg)^2)``.  Pixels in shadow in any image (below ``shadow`` x
    the image's 99th percentile) or among an image's brightest 2 % get no weight.

    Returns:
        (normals (P, 3), lights (N, 3) = intensity x direction, grey).
    """
    g = np.asarray(I, np.float64).sum(-1)  # (N, P)
    n = np.asarray(prior, np.float64)
    nl, npx = g.shape
    if nl < 3:
        raise ValueError(f"images: the factorisation needs at least 3 images, got {nl}")
    U, sv, Vt = np.linalg.svd(g.T, full_matrices=False)
    B0 = U[:, :3] * np.sqrt(sv[:3])
    S0 = np.sqrt(sv[:3])[:, None] * Vt[:3]
    ok = np.ones(npx, bool)
    for k in range(nl):
        q99 = np.quantile(g[k], 0.99)
        ok &= (g[k] > shadow * q99) & (g[k] < np.quantile(g[k], 0.98))
    if ok.sum() < 20:
        ok = np.ones(npx, bool)
    w = ok.astype(np.float64)
    G = np.zeros((npx, 3, 9))
    for i in range(3):
        for j in range(3):
            G[:, j, 3 * i + j] = B0[:, i]
    Pp = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
    for _ in range(irls + 1):
        Q = np.einsum("p,pji,pjk,pkl->il", w, G, Pp, G)
        a = np.linalg.eigh(Q)[1][:, 0]
        A = a.reshape(3, 3)
        B = B0 @ A
        if np.sum(w * np.sum(B * n, 1)) < 0:
            A, B = -A, -B
        Bn = B / np.maximum(np.linalg.norm(B, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.sum(Bn * n, 1), -1, 1)))
        w = ok / (1.0 + (ang / 15.0) ** 2)
    S = np.linalg.solve(A, S0)  # (3, N)
    return Bn.astype(np.float32), S.T.astype(np.float32)


def integrable_normals(I, prior, mask, *, smooth: float = 1.0, irls: int = 2):
    """Uncalibrated Lambertian normals from N >= 3 images: factorisation, integrability, GBR from a prior.

    Rank-3 factorisation of the grey intensities, the 3x3 ambiguity reduced to a GBR by
    integrability (:func:`gpps.host.gbr.integrability_gbr`), and the GBR
    ``b -> (b_x + a b_z, b_y + c b_z, d b_z)`` fitted to the ``prior`` normals by robust least
    squares (three parameters, linear; Cauchy-like weights at 15 deg).

    Args:
        I: (N, P, 3) intensities of the P mask pixels; prior: (P, 3); mask: (H, W) with P pixels.

    Returns:
        (P, 3) unit normals.
    """
    from gpps.host.gbr import integrability_gbr

    g = np.asarray(I, np.float64).sum(-1)
    n = np.asarray(prior, np.float64)
    U, sv, _ = np.linalg.svd(g.T, full_matrices=False)
    B0 = U[:, :3] * np.sqrt(sv[:3])
    h, w = mask.shape
    Bmap = np.zeros((h, w, 3))
    Bmap[mask] = B0
    A = integrability_gbr(Bmap, mask, smooth=smooth, irls=irls)
    B = B0 @ A.T
    wgt = np.ones(len(n))
    for _ in range(4):
        # residual (I - n n^T) (b + [a b_z, c b_z, (d - 1) b_z]) = 0, linear in (a, c, d)
        Pp = np.eye(3)[None] - n[:, :, None] * n[:, None, :]
        cols = np.zeros((len(n), 3, 3))
        cols[:, 0, 0] = B[:, 2]
        cols[:, 1, 1] = B[:, 2]
        cols[:, 2, 2] = B[:, 2]
        Jm = Pp @ cols  # (P, 3, 3)
        r0 = np.einsum("pij,pj->pi", Pp, B * [1, 1, 0])
        sw = np.sqrt(wgt)[:, None, None]
        theta = np.linalg.lstsq((Jm * sw).reshape(-1, 3), (-(r0 * sw[..., 0])).reshape(-1), rcond=None)[0]
        Bg = np.stack([B[:, 0] + theta[0] * B[:, 2], B[:, 1] + theta[1] * B[:, 2], theta[2] * B[:, 2]], 1)
        if np.sum(wgt * np.sum(Bg * n, 1)) < 0:
            Bg = -Bg
        Bn = Bg / np.maximum(np.linalg.norm(Bg, axis=1, keepdims=True), 1e-12)
        ang = np.degrees(np.arccos(np.clip(np.sum(Bn * n, 1), -1, 1)))
        wgt = 1.0 / (1.0 + (ang / 15.0) ** 2)
    return Bn.astype(np.float32)


def _through_gbr(n, G) -> np.ndarray:
    """Unit normals ``G^-T n / |G^-T n|`` (any leading shape; n_z > 0 stays > 0)."""
    b = np.asarray(n, np.float64) @ np.linalg.inv(G)
    return (b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)).astype(np.float32)


def _nest_normals(nests) -> np.ndarray:
    """The unit normals of habitats ``(..., 5)`` (as :func:`gpps.kernels.cuckoo.habitat_normal`)."""
    x, y = nests[..., 0], nests[..., 1]
    r2 = x * x + y * y
    n = np.stack([x, y, np.where(r2 < 0.9999, np.sqrt(np.maximum(1.0 - r2, 0.0)), 0.01)], -1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def reconstruct_single(images, mask=None, *, camera=None, config: SingleConfig | None = None, net=None,
                       device=None, progress=None) -> SingleResult:
    """Normals, albedo, lights and depth from one or three images with nothing else known.

    Args:
        images: one image (H, W) / (H, W, 3), or N of them (same object, same camera, other
            lights): list or array (N, H, W[, 3]); any positive scale.
        mask: (H, W) bool object pixels (None: every lit pixel).
        camera: optional :class:`gpps.camera.Orthographic` / :class:`Perspective` (view
            directions and integration); None: orthographic, depth in half-image units.
        config: :class:`SingleConfig`.
        net: a :class:`gpps.nn.model.SingleNet` (None: the shipped weights).
        device: Warp device of the search.
        progress: optional ``progress(done, total, message)``.

    Raises:
        ValueError: bad shapes or an empty mask, naming the argument.
    """
    from gpps.kernels import cuckoo as ck
    from gpps.nn.model import SingleNet

    cfg = config or SingleConfig()
    if not isinstance(cfg, SingleConfig):
        raise TypeError(f"config: expected SingleConfig, got {type(cfg).__name__}")
    t0 = time.perf_counter()
    timings = {}
    I, m = prepare_images(images, mask)
    n_img, h, w = I.shape[:3]
    net = net or SingleNet.load()
    total = 1 + cfg.rounds + (1 if cfg.integrate else 0)
    preds = [net.predict(I[k], m, size=cfg.net_size) for k in range(n_img)]
    n_first, h_net = preds[0]
    n_net = np.sum([p[0] for p in preds], 0)
    n_net /= np.maximum(np.linalg.norm(n_net, axis=-1, keepdims=True), 1e-8)
    n_net[~m] = 0.0
    h_net = np.mean([p[1] for p in preds], 0).astype(np.float32)
    timings["network"] = time.perf_counter() - t0
    if progress:
        progress(1, total, "network")

    P = int(m.sum())
    Ip = I[:, m]  # (N, P, 3)
    view = _view_dirs(camera, (h, w), m)
    npix = n_net[m].astype(np.float32)
    t1 = time.perf_counter()
    n_start = npix
    if n_img >= 3 and cfg.lights == "factorization":
        n_start, _ = factorization_normals(Ip, npix)
    elif n_img >= 3 and cfg.lights == "integrability":
        n_start = integrable_normals(Ip, npix, m)
    shin = cfg.shininess
    dirs, rgb, kd, ks = estimate_lights(Ip, n_start, view, shininess=shin, specular=cfg.specular == "ks")
    n_prior = npix
    highlights = []
    if cfg.specular == "estimate":
        prior_deg = cfg.highlight_prior_deg
        if prior_deg is None:
            prior_deg = float((getattr(net, "meta", None) or {}).get("val_maen_deg", 10.0))
        hl = {"prior_deg": prior_deg, "shininess_range": cfg.shininess_range}
        fit = fit_highlights(Ip, n_start, view, dirs, rgb, kd, shininess=shin, **hl)
        dirs, rgb, kd, ks, shin = fit.directions, fit.intensities, fit.albedo, fit.ks, fit.shininess
        n_start, n_prior = fit.normals, _through_gbr(npix, fit.gbr)
        highlights.append({"round": 0, **fit.info})
    objective = []
    if cfg.rounds > 0:
        wp = warp()
        dev = resolve_device(device)
        prior_w = cfg.prior_weight if cfg.prior_weight is not None else (0.002 if n_img >= 3 else 0.05)
        search = CuckooSearch(P, objective=ck.photometric_error, data_type=ck.PhotoData, config=cfg.cuckoo,
                              lo=[-1, -1, 0, 0, 0], hi=[1, 1, 4, 4, 4], device=dev)
        data = ck.PhotoData()
        data.images = wp.array(Ip, dtype=wp.vec3, device=dev)
        data.view = wp.array(view, dtype=wp.vec3, device=dev)
        data.prior = wp.array(n_prior, dtype=wp.vec3, device=dev)
        data.weight = wp.array(np.ones(P, np.float32), dtype=wp.float32, device=dev)
        data.shininess = float(shin)
        data.prior_weight = float(prior_w)
        data.albedo_from_normal = int(cfg.albedo == "least-squares")
        rng = np.random.default_rng(cfg.cuckoo.seed)
        K = cfg.cuckoo.nests
        start = np.zeros((P, K, 5), np.float32)
        start[:, :, :2] = n_start[:, None, :2]
        start[:, K // 2:, :2] = n_prior[:, None, :2]  # half the nests around the (bas-relief corrected) network's normal
        start[:, 1:, :2] += rng.normal(0, cfg.init_spread, (P, K - 1, 2)) * (np.arange(1, K) != K // 2)[None, :, None]
        r2 = np.sum(start[:, :, :2] ** 2, -1, keepdims=True)
        start[:, :, :2] *= np.where(r2 > 0.995**2, 0.995 / np.sqrt(np.maximum(r2, 1e-12)), 1.0)
        start[:, :, 2:] = kd[:, None, :] * (1 + rng.normal(0, 0.05, (P, K, 3)) * (np.arange(K) > 0)[None, :, None])
        search.init(start)
        cur_n, cur_kd = npix, kd
        for r in range(cfg.rounds):
            data.light_dir = wp.array(dirs, dtype=wp.vec3, device=dev)
            data.light_rgb = wp.array(rgb, dtype=wp.vec3, device=dev)
            data.ks = float(ks)
            data.shininess = float(shin)
            search.evaluate(data)
            f_before = float(search.best()[1].mean())
            search.run(data, cfg.cuckoo.generations)
            best = wp.zeros(P, dtype=wp.vec3, device=dev)
            alb = wp.zeros(P, dtype=wp.vec3, device=dev)
            err = wp.zeros(P, dtype=wp.float32, device=dev)
            wp.launch(ck.best_habitat_kernel, dim=P, inputs=[search.nests, search.best_index, search.fit, data],
                      outputs=[best, alb, err], device=dev)
            cur_n, cur_kd = best.numpy(), alb.numpy()
            objective.append({"round": r, "before": f_before, "after": float(err.numpy().mean()), "ks": float(ks),
                              "shininess": float(shin)})
            if progress:
                progress(2 + r, total, f"cuckoo round {r + 1}/{cfg.rounds}")
            if r + 1 < cfg.rounds:  # lights for the next round from the refined normals; albedo follows
                dirs, rgb, kd_new, ks = estimate_lights(Ip, cur_n, view, albedo=cur_kd, shininess=shin,
                                                        specular=cfg.specular == "ks")
                nests = search.nests.numpy()
                if cfg.specular == "estimate":
                    fit = fit_highlights(Ip, cur_n, view, dirs, rgb, kd_new, shininess=shin, **hl)
                    dirs, rgb, kd_new, ks, shin = fit.directions, fit.intensities, fit.albedo, fit.ks, fit.shininess
                    highlights.append({"round": r + 1, **fit.info})
                    if fit.accepted:  # move every nest's normal, and the prior, through the bas-relief
                        nests[:, :, :2] = _through_gbr(_nest_normals(nests), fit.gbr)[..., :2]
                        n_prior = _through_gbr(n_prior, fit.gbr)
                        data.prior = wp.array(n_prior, dtype=wp.vec3, device=dev)
                if cfg.albedo == "search":  # keep each nest's albedo consistent with the new light scale
                    ratio = kd_new / np.maximum(cur_kd, 1e-6)
                    nests[:, :, 2:] *= np.clip(ratio, 0.25, 4.0)[:, None, :]
                search.nests.assign(nests)
        npix_ref, kd = cur_n, cur_kd
    else:
        npix_ref = npix
    timings["refine"] = time.perf_counter() - t1

    normals = np.zeros((h, w, 3), np.float32)
    normals[m] = npix_ref
    albedo = np.zeros((h, w, 3), np.float32)
    albedo[m] = kd
    depth = None
    if cfg.integrate:
        from gpps.camera import Orthographic
        from gpps.flows.integrate import integrate_normals

        t2 = time.perf_counter()
        cam = camera or Orthographic(pixel_size=2.0 / max(h, w))
        res = integrate_normals(normals, m, camera=cam, device=str(device) if device else "auto")
        depth = res.depth
        timings["integrate"] = time.perf_counter() - t2
        if progress:
            progress(total, total, "integrated")
    timings["total"] = time.perf_counter() - t0
    return SingleResult(
        mask=m, normals_net=n_net.astype(np.float32), normals_net_first=n_first, height_net=h_net, normals=normals,
        albedo=albedo, light_directions=dirs, light_intensities=rgb, ks=float(ks), depth=depth,
        objective=objective, timings=timings, shininess=float(shin), highlights=highlights,
    )
