"""Uncalibrated photometric stereo: normals, albedo and lights from images alone (seed ch. 5).

Pipeline (:func:`solve_uncalibrated`):
0. **Channel** (``UncalibratedConfig.channel``): with colour images the stages
   1-3 see the *specular-free* magnitude (:func:`specular_free`, the S-U-V
   space of Mallick et al. 2005): the part of the RGB orthogonal to the light's
   colour, which under the dichromatic model is Lambertian shading times the
   albedo's chromatic part, exactly rank 3 whatever the specular lobe.  On
   Blinn-Phong / Ashikhmin-Shirley renders the grey path left 50% of the
   observations with some highlight, the rank-3 subspace 6 deg off and the
   lights 20-30 deg off; the specular-free path gives them to 0.4-1.4 deg.
   Grey images (Yale B) and grey albedos keep the grey level.
1. **Rank-3 factorisation** (5.8; Hayakawa): the grey image matrix ``M`` (N x P)
   is factored as ``M ~ L B^T`` by weighted alternating least squares, with
   shadowed and saturated observations as missing data (the seed's plain SVD
   of ``P`` is the special case with no missing data).  ALS starts from the
   better (lower residual) of that SVD with row-mean fill-in and the SVD of
   the complete block of the best-lit images (:func:`factorize`).
   Pseudo-normals ``B`` and pseudo-lights ``L`` are known up to a 3x3 ``A``.
2. **Integrability** reduces ``A`` to the generalized bas-relief (GBR) family
   (Yuille & Snow 1997): with ``b = A b^`` the condition
   ``d(b1/b3)/dy = d(b2/b3)/dx`` is linear in ``c1 = a3 x a1`` and
   ``c2 = a3 x a2``: ``(b^ x b^_y) . c1 - (b^ x b^_x) . c2 = 0`` at every pixel;
   on a lightly smoothed ``b^`` map, with robust reweighting
   (:func:`integrability_gbr`).
3. **GBR resolution** with the evidence the images carry, combined in one
   objective over ``(alpha, beta, gamma)`` of ``b' = [[1,0,a],[0,1,b],[0,0,g]] b``
   (:func:`resolve_gbr`): *local diffuse maxima* (Papadhimitri & Favaro 2014:
   where an image peaks, ``n = l``), the *albedo entropy* (Alldrin et al.
   2007) and the *light-intensity prior* (all lights equally bright), the
   last only when the data pass it (real captures often do not).
4. What remains is the convex/concave flip ``(n1, n2, n3) -> (-n1, -n2, n3)``,
   exact for orthographic Lambertian images.  With a perspective camera the
   flipped normal field is not integrable, so the perspective curl decides it
   when the view directions spread enough for that to show; otherwise the
   result says ``flip="ambiguous"`` and carries the alternative.
5. **Refinement**, on the specular-free path (``final_solver="lm"``): the
   lights stay as found; the shared material (``ks`` and the lobe's exponent)
   is the one whose calibrated per-pixel fit leaves the smallest residual
   (:func:`estimate_material`), and the normals and RGB albedo are that fit
   on every pixel (:func:`gpps.flows.photometric.solve_normals`, Levenberg-Marquardt
   with the specular model).  With a perspective camera both members of the
   flip pair are fitted: the lobe depends on the view vectors, which the flip
   leaves alone, so the residuals decide the flip.
   On the grey path (``final_solver="adam"``) (5.1-5.7): the Lambertian + Ashikhmin-Shirley image model
   with normals, RGB albedo, lights and the shared (ks, eta) as unknowns,
   fitted by Adam through Warp's autodiff (:mod:`gpps.pipeline.uncalibrated`).
   The model has no integrability term, so the lights' linear drift is then
   undone (:func:`restore_gauge`; ``refine_gauge``): the refinement corrects
   lights within the gauge that integrability and the GBR cues chose.  Then
   the normals are fitted per pixel with the lights fixed (Cauchy loss).

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
from scipy.optimize import minimize

from gpps._check import as_images, as_mask, check_choices, check_number
from gpps.camera import Orthographic, Perspective
from gpps.flows.photometric import solve_normals
from gpps.host.gbr import (
    albedo_ls,
    dark_images,
    factorize,
    integrability_gbr,
    ldr_candidates,
    pca_merge,
    perspective_curls,
    pixel_pseudo_normals,
    resolve_gbr,
    restore_gauge,
    specular_free,
    to_map,
)
from gpps.lights import DirectionalLights
from gpps.material import Material
from gpps.pipeline.uncalibrated import Refiner

Cue = Literal["intensity", "entropy", "ldr"]
Refine = Literal["ashikhmin-shirley", "blinn-phong", "lambertian", "none"]
Gauge = Literal["gbr", "fixed", "free"]
Channel = Literal["auto", "specular-free", "grey"]
LightFit = Literal["auto", "fit", "fixed"]
Final = Literal["auto", "adam", "lm"]

__all__ = ["UncalibratedConfig", "UncalibratedResult", "solve_uncalibrated", "estimate_material"]


@dataclass
class UncalibratedConfig:
    """Options of :func:`solve_uncalibrated`.

    Attributes:
        cues: GBR evidence to combine (see :func:`resolve_gbr`; "intensity":
            lights of equal brightness; "entropy": albedo-distribution entropy;
            "ldr": local diffuse maxima).  At least one.
        channel: what the factorisation, integrability and GBR stages see:
            "grey" the mean of the channels; "specular-free" the part of the
            RGB orthogonal to ``source_color`` (:func:`specular_free`: diffuse
            only under the dichromatic model, so highlights neither corrupt the
            rank-3 subspace nor the integrability; on Blinn-Phong renders the
            grey path's lights were 20-30 deg off); "auto" the latter when the
            ratio of the specular-free to the full RGB magnitude (per pixel the
            median over its lit observations, then the median over the pixels)
            is at least ``chroma_min`` (a grey albedo, or grey images, has
            none), else grey.  Measured: the textured bumps 0.096-0.108 (with
            highlights - without), the uniform sphere 0.16, DiLiGenT bear 0.39,
            DiLiGenT ball 0.059 (nearly grey: its tint is the lights'; grey path).
        source_color: RGB colour of the lights (white by default).
        chroma_min: the "auto" threshold.
        refine: image model of the refinement ("none" stops after the GBR).
        dark_fraction: images whose 99th percentile is below this fraction of
            the median image's are refused (:func:`dark_images`); 0 accepts all.
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
        refine_robust: Cauchy scale of the residuals of the joint (lights)
            fit, as a fraction of the median observed grey intensity; 0: least
            squares (on Yale B the robust loss made the lights 0.1-0.3 deg worse).
        final_robust: the same for the per-pixel pass (normals, albedo): it
            keeps cast shadows and highlights the model misses from pulling
            the normals (DiLiGenT ball: MAEN 2.9 -> 2.4 deg).
        refine_gauge: what the refined lights keep of their linear drift
            (:func:`restore_gauge`): "fixed" none (the gauge integrability and
            the GBR cues chose; the refinement only corrects lights within it),
            "gbr" its GBR part (the part a specular term can decide), "free"
            all of it.  Measured (light error, deg): "free" drifts (DiLiGenT
            ball 0.5 -> 3.2, yaleB04 3.4 -> 4.5 with 600 steps); "gbr" beat
            "fixed" on the four Yale B faces by 0.1-0.3 but cost ball
            0.5 -> 3.0 and bear 3.2 -> 4.5 (the specular lobe's pull on the GBR
            is not reliable); "fixed" improved the faces by 0.4-0.6 and bear by
            0.1, ball 0.51 -> 0.54 (perf/uncalibrated_real.py).
        refine_lights: whether the joint refinement moves the lights: "fit",
            "fixed", or "auto" (fit on the grey path, fixed on the
            specular-free path, whose lights are already near the noise floor:
            the Adam fit moved them 0.7 -> 1.9 deg on the Blinn-Phong bumps).
        final_solver: normals, albedo (and material) by "adam" (the Refiner
            with the material it fitted) or "lm" (:func:`estimate_material`,
            then the calibrated Levenberg-Marquardt solver); "auto": "lm" on the
            specular-free path, "adam" on the grey one (whose results on Yale B
            and DiLiGenT were measured with it).
        material_pixels: pixels of :func:`estimate_material`'s objective.
        normal_sets: > 1 fits that many bootstrap subsets of the images in
            the per-pixel pass and merges them by PCA (5.1.7).
        flip_ratio: perspective curl ratio above which the flip is decided.
        flip_specular_ratio: with a perspective camera and a specular
            refinement finished by "lm", the material is fitted with both
            members of the flip pair (the lobe depends on the view vectors,
            which the flip does not move): the lower residual is kept, and the
            flip is "resolved" when the other is this many times larger (the
            perspective curl decides otherwise).
        flip_min_spread: the flip is decided only when the view directions
            over the mask spread by at least this many degrees (the largest
            angle to their mean): the wrong flip's curl grows with that
            spread, and below a few degrees (DiLiGenT's f = 3770 px lens: 1-2
            deg) it drowns in the curl of the noise, so the ratio test picks at
            random.  Then the result stays "ambiguous".
        flip_min_curl: and only when the two candidates' relative curls
            differ by more than this: a surface of revolution about the optical
            axis (a centred sphere) has a radial gradient field, curl-free
            either way up, so its flip is undecidable (differences ~1e-5 against
            ~3e-3 for the bumps scene at 96 px).
        integrability_smooth: Gaussian sigma (pixels) applied to the
            pseudo-normal map before the integrability constraint (0: none).
        integrability_irls: robust reweighting rounds of that constraint.
        ldr_window: neighbourhood (pixels, odd) of the local-maximum search of
            the ``"ldr"`` cue.
        seed: random seed (pixel subsets, bootstraps).
    """

    cues: tuple[Cue, ...] = ("intensity", "ldr", "entropy")
    channel: Channel = "auto"
    source_color: tuple = (1.0, 1.0, 1.0)
    chroma_min: float = 0.08
    refine: Refine = "ashikhmin-shirley"
    dark_fraction: float = 0.1
    shadow_fraction: float = 0.15
    highlight_trim: float = 0.1
    saturation: float = 0.99
    als_iterations: int = 40
    refine_iterations: int = 300
    refine_pixels: int = 6000
    final_iterations: int = 150
    lr: float = 0.01
    refine_robust: float = 0.0
    final_robust: float = 0.03
    refine_gauge: Gauge = "fixed"
    refine_lights: LightFit = "auto"
    final_solver: Final = "auto"
    material_pixels: int = 1500
    normal_sets: int = 0
    flip_ratio: float = 1.3
    flip_specular_ratio: float = 2.0
    flip_min_spread: float = 5.0
    flip_min_curl: float = 1e-3
    integrability_smooth: float = 2.0
    integrability_irls: int = 5
    ldr_window: int = 7
    seed: int = 0

    def __post_init__(self):
        check_choices(self)
        cues = (self.cues,) if isinstance(self.cues, str) else self.cues
        try:
            cues = tuple(cues)
        except TypeError:
            raise TypeError(f"cues: expected a non-empty sequence of {list(get_args(Cue))}, got {self.cues!r}") from None
        if not cues or any(not isinstance(c, str) or c not in get_args(Cue) for c in cues):
            raise ValueError(f"cues: expected a non-empty subset of {list(get_args(Cue))}, got {self.cues!r}")
        self.cues = cues
        try:
            color = tuple(float(v) for v in np.ravel(self.source_color))
        except (TypeError, ValueError):
            color = ()
        if len(color) != 3 or not np.all(np.isfinite(color)) or min(color) < 0 or max(color) <= 0:
            raise ValueError(f"source_color: expected 3 finite values >= 0, not all 0, got {self.source_color!r}")
        self.source_color = color
        self.chroma_min = check_number("chroma_min", self.chroma_min, lo=0.0, hi=1.0)
        for name in ("dark_fraction", "shadow_fraction", "highlight_trim"):  # fractions in [0, 1)
            v = check_number(name, getattr(self, name), lo=0.0, hi=1.0)
            if v >= 1.0:
                raise ValueError(f"{name}: expected a value in [0, 1), got {getattr(self, name)!r}")
            setattr(self, name, v)
        self.saturation = check_number("saturation", self.saturation, lo=0.0, hi=1.0 + 1e-9, lo_open=True)
        for name in ("integrability_smooth", "flip_min_curl", "flip_min_spread", "refine_robust", "final_robust"):
            setattr(self, name, check_number(name, getattr(self, name), lo=0.0))
        for name in ("flip_ratio", "flip_specular_ratio"):
            setattr(self, name, check_number(name, getattr(self, name), lo=1.0))
        self.lr = check_number("lr", self.lr, lo=0.0, lo_open=True)
        for name in ("als_iterations", "refine_iterations", "refine_pixels", "final_iterations", "normal_sets",
                     "integrability_irls", "material_pixels", "seed"):
            setattr(self, name, check_number(name, getattr(self, name), lo=0, integer=True))
        self.ldr_window = check_number("ldr_window", self.ldr_window, lo=3, integer=True)
        if self.ldr_window % 2 == 0:
            raise ValueError(f"ldr_window: expected an odd integer >= 3, got {self.ldr_window!r}")


@dataclass
class UncalibratedResult:
    """Output of :func:`solve_uncalibrated`.

    Attributes:
        normals: (H, W, 3) unit normals (gpps frame), 0 outside the mask.
        albedo: (H, W, 3) RGB albedo (relative to the mean light intensity).
        light_directions: (N, 3) unit directions toward the lights.
        light_intensities: (N,) relative intensities (mean 1).
        flip: "resolved" (perspective cues: specular residual or curl) or "ambiguous".
        alternative: when ambiguous, the flipped ``(normals, light_directions)``.
        baseline: factorisation + integrability + GBR (before refinement):
            dict with ``normals`` and ``light_directions``.
        gbr: the GBR parameters chosen and the cue values.
        material: estimated ``ks`` (relative to the mean light intensity) and
            the exponent (``eta_u = eta_v`` or ``shininess``) when refined.
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


# --------------------------------------------------------------------------- post-processing


# --------------------------------------------------------------------------- the pipeline


def _factorisation_channel(rgb, cfg):
    """The (N, P) matrix the factorisation sees: the grey level, or the specular-free magnitude when
    ``cfg.channel`` asks for it ("auto": when the images carry enough colour)."""
    grey = rgb.mean(-1).astype(np.float64)
    info = {"used": False, "fraction": 0.0}
    if cfg.channel == "grey":
        return grey, info
    sf = specular_free(rgb, cfg.source_color)
    lit = grey > 0.15 * np.percentile(grey, 99, axis=1, keepdims=True)
    # the albedo's chromatic fraction: per pixel the median ratio over its lit observations (a few
    # highlights do not move it), the median over the pixels lit at least once
    cols = lit.any(0)
    if cols.any():
        ratio = np.where(lit, sf / np.maximum(np.linalg.norm(rgb, axis=-1), 1e-12), np.nan)[:, cols]
        frac = float(np.median(np.nanmedian(ratio, axis=0)))
    else:
        frac = 0.0
    info["fraction"] = frac
    if cfg.channel == "specular-free" or frac >= cfg.chroma_min:
        info["used"] = True
        return sf, info
    return grey, info


def _prepare(images, mask, dark_fraction: float = 0.0):
    imgs = as_images("images", images)
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
    dim = dark_images(imgs, m, dark_fraction) if dark_fraction > 0 else []
    if dim:
        raise ValueError(
            f"images: image(s) {dim} are nearly dark (99th percentile below {dark_fraction} x the median image's): "
            "too little signal to estimate their lights; leave them out (gpps.host.gbr.dark_images finds them)"
        )
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
        ValueError: fewer than 3 images, an all-dark or nearly dark image
            (``config.dark_fraction``), an image with fewer than 3 usable
            pixels, rank < 3 data (e.g. coplanar lights), bad shapes or values.
    """
    cfg = UncalibratedConfig() if config is None else config
    if not isinstance(cfg, UncalibratedConfig):
        raise TypeError(f"config: expected UncalibratedConfig, got {type(cfg).__name__}")
    if camera is not None and not isinstance(camera, (Orthographic, Perspective)):
        raise TypeError(f"camera: expected None, Orthographic or Perspective, got {type(camera).__name__}")
    step = progress or (lambda *a, **k: None)
    t0 = time.perf_counter()
    imgs, mask = _prepare(images, mask, cfg.dark_fraction)
    rgb = imgs[:, mask]  # (N, P, 3)
    M, chroma = _factorisation_channel(rgb, cfg)
    W, W_obs, grey = _observation_weights(rgb, M, chroma, cfg)
    L0, B0, W = factorize(M, W, cfg.als_iterations)
    step(1, 5, "factorised")
    t_fact = time.perf_counter()
    B, L, gbr_info = _resolve_ambiguity(B0, L0, M, W, mask, cfg)
    step(2, 5, "GBR resolved")
    t_gbr = time.perf_counter()

    def unit(a):
        return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)

    base_n = unit(B)
    if chroma["used"]:
        # the specular-free channel fixed the lights; its pseudo-normals are only as good as the
        # albedo's chromatic part (noisy where the albedo is near grey): take the normals from
        # the full-intensity images with those lights, highlights (positive outliers) trimmed
        base_n = unit(pixel_pseudo_normals(grey, W_obs, L))
    base_l = unit(L)
    if np.median(base_l[:, 2]) < 0:
        base_l = -base_l
    baseline = {"normals": to_map(base_n, mask), "light_directions": base_l}
    views = _view_vectors(camera, mask)
    normals, lights, albedo = base_n, L, None
    material: dict = {}
    losses: list = []
    spec_flip = False  # the flip decided by the specular fit (perspective camera)
    if cfg.refine != "none":
        normals, lights, albedo, material, losses, spec_flip = _refine(
            imgs, mask, rgb, M, W_obs, normals, L, views, chroma, gbr_info, camera, cfg, device, step)
    t_ref = time.perf_counter()
    e = np.linalg.norm(lights, axis=1)
    ldirs = lights / e[:, None]
    if albedo is None:
        albedo = albedo_ls(rgb, W, normals, lights / e.mean())
    else:  # albedo and ks relative to the mean light intensity, as light_intensities are
        albedo = albedo * e.mean()
        if "ks" in material:
            material["ks"] = float(material["ks"] * e.mean())
    intens = e / e.mean()
    gbr_info["channel"] = "specular-free" if chroma["used"] else "grey"
    gbr_info["chroma_fraction"] = chroma["fraction"]
    flip, alternative, normals, ldirs = _decide_flip(normals, ldirs, mask, views, camera, spec_flip, gbr_info, cfg)
    step(5, 5, "done")
    return UncalibratedResult(
        normals=to_map(normals, mask),
        albedo=to_map(albedo, mask),
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


def _observation_weights(rgb, M, chroma: dict, cfg: UncalibratedConfig):
    """Observation weights of the factorisation ``W`` (N, P) (lit, unsaturated, the brightest trimmed on
    the grey path), those of the refinement ``W_obs`` (it models highlights, so it keeps them) and the
    grey level (N, P).  Raises ValueError for images with fewer than 3 lit pixels or rank < 3 data."""
    N = M.shape[0]
    unsat = rgb.max(-1) < cfg.saturation
    W = ((M > cfg.shadow_fraction * np.percentile(M, 99, axis=1, keepdims=True)) & unsat).astype(np.float64)
    # what the refinement sees: it models highlights, so it keeps them; the shadows are judged on the
    # grey level (the specular-free magnitude is small where the albedo is nearly grey, not shadowed)
    grey = rgb.mean(-1).astype(np.float64)
    W_obs = W.copy() if not chroma["used"] else ((grey > cfg.shadow_fraction * np.percentile(grey, 99, axis=1, keepdims=True)) & unsat).astype(np.float64)
    drop = 0 if chroma["used"] else min(int(cfg.highlight_trim * N), N - 3)
    if drop > 0:
        rank = np.argsort(np.argsort(M, axis=0), axis=0)
        W = W * (rank < N - drop)
        # an image whose lit pixels are all among their brightest (a frontal light) keeps them
        few = W.sum(1) < np.minimum(W_obs.sum(1), max(10, 0.01 * W.shape[1]))
        W[few] = W_obs[few]
    poor = np.where(W.sum(1) < 3)[0]
    if len(poor):
        raise ValueError(f"images: image(s) {poor.tolist()} have fewer than 3 pixels that are lit (> shadow_fraction of the image's 99th percentile) and unsaturated")
    # rank test on fully lit pixels (or all, if none are lit everywhere)
    full = W.all(0)
    S = np.linalg.svd(M[:, full] if full.sum() >= 10 else M, compute_uv=False)
    if len(S) < 3 or S[2] < 1e-3 * S[0]:
        raise ValueError(f"images: the data have rank < 3 (singular values {np.round(S[:4] / S[0], 5).tolist()}); the lights may be coplanar or too few differ")
    return W, W_obs, grey


def _resolve_ambiguity(B0, L0, M, W, mask, cfg: UncalibratedConfig):
    """Integrability (the 3x3 ambiguity down to GBR), the global sign, then the GBR from the cues.
    Returns pseudo-normals B (P, 3), pseudo-lights L (N, 3) and the GBR report."""
    Bmap = np.zeros(mask.shape + (3,))
    Bmap[mask] = B0
    fit_ok = np.zeros(mask.shape, bool)
    fit_ok[mask] = W.sum(0) >= 3
    A = integrability_gbr(Bmap, fit_ok, smooth=cfg.integrability_smooth, irls=cfg.integrability_irls)
    B = B0 @ A.T
    L = L0 @ np.linalg.inv(A)
    if np.median(B[:, 2]) < 0:  # the global sign: normals face the camera
        B, L = -B, -L
    ldr = None
    if "ldr" in cfg.cues:
        lk, lp = ldr_candidates(M, W, mask, window=cfg.ldr_window)
        ldr = (lk, B[lp])
    H, gbr_info = resolve_gbr(B[W.sum(0) >= 3], L, cfg.cues, seed=cfg.seed, ldr=ldr)
    B = B @ H.T
    L = L @ np.linalg.inv(H)  # s' = H^-T s (rows)
    return B, L, gbr_info


def _view_vectors(camera, mask) -> np.ndarray:
    """(P, 3) unit vectors toward the camera at the mask's pixels."""
    P = int(mask.sum())
    if isinstance(camera, Perspective):
        _, rays = camera.rays(mask.shape)
        return -rays[mask]
    return np.tile([0.0, 0.0, 1.0], (P, 1))


def _refine(imgs, mask, rgb, M, W_obs, normals, L, views, chroma: dict, gbr_info: dict, camera, cfg: UncalibratedConfig,
            device, step):
    """Step 5: the lights refined through the image model (Adam, :class:`gpps.pipeline.uncalibrated.Refiner`)
    and/or the shared material estimated, then the normals and albedo per pixel.

    Returns:
        ``(normals (P, 3), lights (N, 3), albedo (P, 3) or None, material dict, losses, spec_flip)``.
    """
    N, P = imgs.shape[0], int(mask.sum())
    flip_m = np.diag([-1.0, -1.0, 1.0])
    albedo, material, losses, spec_flip = None, {}, [], False
    spec = cfg.refine  # the lobe of the refinement's model (a Refiner Lobe name)
    Wrgb = W_obs
    rng = np.random.default_rng(cfg.seed)
    sub = rng.choice(P, min(P, cfg.refine_pixels), replace=False) if cfg.refine_pixels and cfg.refine_pixels < P else np.arange(P)
    # intensities normalised to mean 1; albedo by per-channel least squares
    e = np.linalg.norm(L, axis=1)
    L = L / np.median(e)  # the median: a badly conditioned light can be far off
    alb = albedo_ls(rgb, Wrgb, normals, L)
    level = float(np.median(M[Wrgb > 0]))
    robust, final_robust = cfg.refine_robust * level, cfg.final_robust * level
    final = cfg.final_solver
    if final == "auto":
        final = "lm" if chroma["used"] else "adam"
    fit_lights = cfg.refine_lights == "fit" or (cfg.refine_lights == "auto" and not chroma["used"])
    lights = L
    if final == "adam" or fit_lights:
        ref = Refiner(N, len(sub), device=device)
        r = ref.run(rgb[:, sub], Wrgb[:, sub], views[sub], normals[sub], alb[sub], L, specular=spec, robust=robust, iterations=cfg.refine_iterations, lr=cfg.lr, fit_lights=fit_lights,
                    progress=lambda d, t, m: step(2 + d / t, 5, "refining lights: " + m))
        lights = r.lights if fit_lights else L
        material = {"brdf": cfg.refine, "ks": r.ks}
        if cfg.refine == "ashikhmin-shirley":
            material.update(eta_u=r.eta, eta_v=r.eta, f0=0.5)
        elif cfg.refine == "blinn-phong":
            material.update(shininess=r.eta)
        losses = r.losses
        if fit_lights and cfg.refine_gauge != "free":
            lights = restore_gauge(lights, L, keep_gbr=cfg.refine_gauge == "gbr")
    step(3, 5, "lights refined")
    if final == "lm":
        material = {"brdf": cfg.refine}
        if spec != "lambertian":
            # with a perspective camera the view vectors are not symmetric under the flip, so the
            # specular lobe tells the two members of the pair apart: fit both, keep the better
            cands = [lights, lights @ flip_m] if isinstance(camera, Perspective) else [lights]
            fits = [estimate_material(imgs, mask, c, cfg.refine, camera=camera, pixels=cfg.material_pixels, seed=cfg.seed, device=device) for c in cands]
            res_ = [f[1]["residual"] for f in fits]
            j = int(np.argmin(res_))
            lights = cands[j]
            material.update(fits[j][0], search=fits[j][1])
            if len(cands) == 2:
                gbr_info["flip_specular_residuals"] = res_
                spec_flip = max(res_) > cfg.flip_specular_ratio * max(min(res_), 1e-30)
        step(4, 5, "material estimated")
        normals, albedo = _calibrated_pass(imgs, mask, lights, material, camera, final_robust > 0, device)
    else:
        sets = max(1, cfg.normal_sets)
        # the joint fit already solved every pixel with these lights (and this loss)
        reuse = len(sub) == P and sets == 1 and cfg.refine_gauge == "free" and cfg.final_robust == cfg.refine_robust
        ref_all = ref if len(sub) == P else Refiner(N, P, device=device)
        nsets = []
        for s in range(sets):
            Wk = Wrgb
            if sets > 1:
                keep = rng.random(N) < 0.7
                keep[rng.choice(N, 3, replace=False)] = True
                Wk = Wrgb * keep[:, None]
            if reuse:
                nsets.append(r.normals)
                albedo = r.albedo
                continue
            rr = ref_all.run(rgb, Wk, views, normals, albedo_ls(rgb, Wk, normals, lights), lights, ks=max(r.ks, 1e-4), eta=r.eta, specular=spec,
                             fit_lights=False, robust=final_robust, iterations=cfg.final_iterations, lr=cfg.lr,
                             progress=lambda d, t, m: step(3 + (s + d / t) / sets, 5, "per-pixel pass: " + m))
            nsets.append(rr.normals)
            albedo = rr.albedo
        normals = nsets[0] if len(nsets) == 1 else pca_merge(np.stack(nsets))
    return normals, lights, albedo, material, losses, spec_flip


def _decide_flip(normals, ldirs, mask, views, camera, spec_flip: bool, gbr_info: dict, cfg: UncalibratedConfig):
    """The convex/concave flip: decided by the specular fit, or by the perspective curl when the view
    directions spread enough; otherwise ambiguous with the alternative returned.

    Returns:
        ``(flip "resolved" or "ambiguous", alternative (normal map, light directions) or None, normals, ldirs)``.
    """
    flip_m = np.diag([-1.0, -1.0, 1.0])
    # the convex/concave flip
    flip = "ambiguous"
    alternative = (to_map(normals @ flip_m, mask), ldirs @ flip_m)
    gbr_info["flip_curl"] = None
    if spec_flip:
        flip, alternative = "resolved", None
    elif isinstance(camera, Perspective):
        c0, c1 = perspective_curls([to_map(normals, mask), alternative[0]], mask, camera)
        vm = views.mean(0) / np.linalg.norm(views.mean(0))
        spread = float(np.degrees(np.arccos(np.clip((views @ vm).min(), -1.0, 1.0))))
        gbr_info["flip_curl"] = [c0, c1]
        gbr_info["view_spread_deg"] = spread
        decisive = abs(c1 - c0) > cfg.flip_min_curl and max(c0, c1) > cfg.flip_ratio * min(c0, c1)
        if np.isfinite(c0 + c1) and spread >= cfg.flip_min_spread and decisive:
            flip = "resolved"
            if c1 < c0:
                normals, ldirs = normals @ flip_m, ldirs @ flip_m
            alternative = None
    return flip, alternative, normals, ldirs


def estimate_material(images, mask, lights, brdf: str, *, camera=None, pixels: int = 1500, seed: int = 0, start=None, device=None) -> tuple[dict, dict]:
    """The shared specular parameters that best explain the images with the lights fixed.

    The objective of a candidate ``(ks, exponent)`` is the mean squared residual
    of the calibrated per-pixel fit (:func:`gpps.flows.photometric.solve_normals`,
    Levenberg-Marquardt; normals and RGB albedo free per pixel) on a random
    subset of ``pixels`` pixels: the residual of the true material is at the
    quantisation level, a wrong lobe leaves highlights unexplained.  A 3 x 3 grid
    over ``ks`` (0.1, 0.3, 1 relative to the mean light intensity) and the
    exponent (10, 30, 100; plus ``start`` when given) picks the start of a
    Nelder-Mead search in log space.  The Fresnel ``f0`` of Ashikhmin-Shirley is
    fixed at 0.5 and its two exponents are equal (isotropic), as in the refinement.

    Args:
        images: (N, H, W, 3).
        mask: (H, W) bool.
        lights: (N, 3) direction times intensity.
        brdf: "blinn-phong" or "ashikhmin-shirley".
        start: optional ``(ks, exponent)`` added to the grid.

    Returns:
        (material fields for :class:`gpps.material.Material`, info with the evaluations).
    """


    if brdf not in ("blinn-phong", "ashikhmin-shirley"):
        raise ValueError(f"brdf: expected 'blinn-phong' or 'ashikhmin-shirley', got {brdf!r}")
    mask = np.asarray(mask, bool)
    idx = np.flatnonzero(mask)
    rng = np.random.default_rng(seed)
    sub = np.zeros(mask.size, bool)
    sub[idx if len(idx) <= pixels else rng.choice(idx, pixels, replace=False)] = True
    sub = sub.reshape(mask.shape)
    e = np.linalg.norm(lights, axis=1)
    L = DirectionalLights(lights / e[:, None], np.repeat(e[:, None], 3, 1))

    def fields(x):
        ks, ex = float(np.exp(x[0])), float(np.exp(x[1]))
        return {"ks": ks, "shininess": ex} if brdf == "blinn-phong" else {"ks": ks, "eta_u": ex, "eta_v": ex, "f0": 0.5}

    evals = []

    def f(x):
        x = np.clip(x, [-7.0, 0.0], [2.0, 7.0])
        r = solve_normals(images, sub, L, camera=camera, material=Material(brdf, **fields(x)), solver="lm", device=device)
        v = float(np.mean(r.residual[sub].astype(np.float64) ** 2))
        evals.append((float(np.exp(x[0])), float(np.exp(x[1])), v))
        return v

    grid = [np.log([k, ex]) for k in (0.1, 0.3, 1.0) for ex in (10.0, 30.0, 100.0)]
    if start is not None and start[0] > 0 and start[1] > 0:
        grid.append(np.log(np.asarray(start, np.float64)))
    vals = [f(x) for x in grid]
    x0 = grid[int(np.argmin(vals))]
    minimize(f, x0, method="Nelder-Mead", options={"xatol": 0.01, "fatol": 1e-12, "maxfev": 30, "initial_simplex": np.vstack([x0, x0 + [0.5, 0.0], x0 + [0.0, 0.5]])})
    best = min(evals, key=lambda t: t[2])
    return fields(np.log(best[:2])), {"evaluations": len(evals), "residual": best[2]}


def _calibrated_pass(imgs, mask, lights, material, camera, robust, device):
    """Normals and RGB albedo per pixel by the calibrated solver (:func:`gpps.flows.photometric.solve_normals`,
    Levenberg-Marquardt with the specular model) with the estimated lights and material."""

    e = np.linalg.norm(lights, axis=1)
    L = DirectionalLights(lights / e[:, None], np.repeat(e[:, None], 3, 1))
    kw = {k: v for k, v in material.items() if k not in ("brdf", "search")}
    mat = Material(material["brdf"], **kw) if material.get("brdf", "lambertian") != "lambertian" else Material("lambertian", ks=0.0)
    res = solve_normals(imgs, mask, L, camera=camera, material=mat, solver="lm", robust="cauchy" if robust else None, device=device)
    return res.normals[mask].astype(np.float64), res.albedo[mask].astype(np.float64)


