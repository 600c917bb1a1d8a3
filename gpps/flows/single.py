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
   (:func:`gpps.host.single.estimate_lights`); then the generalized bas-relief that Lambertian
   shading cannot see, with a global Blinn-Phong ``ks`` and ``shininess``, from the
   specular highlights (:func:`gpps.host.single.fit_highlights`): lights fitted to the network's
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
from typing import Literal

import numpy as np

from gpps._check import check_bool, check_choices, check_number
from gpps.camera import Orthographic
from gpps.flows.integrate import integrate_normals
from gpps.host.single import (
    estimate_lights,
    explained_fraction,
    factorization_normals,
    fit_highlights,
    integrable_normals,
    nest_normals,
    prepare_images,
    through_gbr,
    view_dirs,
)
from gpps.nn.model import SingleNet, TTAName
from gpps.pipeline.cuckoo import CuckooConfig, PhotometricCuckoo

__all__ = ["SingleConfig", "SingleResult", "reconstruct_single"]

AlbedoMode = Literal["search", "least-squares"]
LightStart = Literal["integrability", "factorization", "least-squares"]
SpecularMode = Literal["estimate", "ks", "off"]


@dataclass(frozen=True)
class SingleConfig:
    """Settings of :func:`reconstruct_single`.

    Attributes:
        cuckoo: the search (nests, generations per round, beta = 0.01, p_c = 0.4, seed).
        rounds: light-estimation / search rounds (0: the network's output only).
        prior_weight: weight of ``|n - n_prior|^2`` in the objective; ``"map"`` (three or more images): a first
            search at 0.002, then the maximum-a-posteriori objective from the misfit that search left and each
            pixel's network uncertainty (the spread of the per-image predictions; see ``_refine``); None: "map"
            with three or more images, 0.05 with fewer (one image cannot fix a normal).  Chosen on 30 scenes of
            our own recipe v2 with three lights (perf/single_dev.py): 0.002 left the refinement worse than the
            network on 80 % of them (mean 18.4 against 17.8 deg), "map" with ``min_lit=3`` on 40 % (17.4).
        shininess: Blinn-Phong exponent of the objective where it is not estimated
            (``specular="ks"``, or no highlight seen), and the start of its estimate.
        specular: ``"estimate"``: the lights' bas-relief, ``ks`` and ``shininess`` from the
            highlights each round (:func:`gpps.host.single.fit_highlights`); ``"ks"``: lights by least squares
            alone and one global ks at the fixed ``shininess``; ``"off"``: ks = 0.
        shininess_range: ``(lo, hi)`` bounds of the estimated shininess.
        highlight_prior_deg: angular spread (deg) of the normals' prior in
            :func:`gpps.host.single.fit_highlights`; None: the network's validation MAEN (its ``meta``), else 10.
        albedo: ``"search"``: the albedo is part of each habitat (x = (n_x, n_y, r, g, b));
            ``"least-squares"``: habitats carry the normal, the albedo is solved per candidate.
        init_spread: standard deviation of the nests' start around the current normal (n_x, n_y).
        net_size: the network's working resolution (longer side); None: the trained one.
        integrate: integrate the refined normals into depth.
        min_explained: after the rounds, a pixel whose observations' energy the refined image model explains
            less than this share of (:func:`gpps.host.single.explained_fraction`) keeps the network's normal:
            its observations do not measure it (a cast shadow, interreflection, or lights estimated wrong).
            0.5: the model must explain most of what was observed (0 keeps every refined normal).
        min_lit: after the rounds, a pixel with fewer lit observations than this (and than the images) keeps the
            prior: a normal and an albedo need three (Woodham); with fewer the search slides along the family of
            normals that fit them.  0: no such test.
        lit_fraction: an observation is lit when its grey value exceeds this share of the pixel's brightest.
        min_spread_deg: the least network uncertainty of the ``"map"`` weight (deg).
        tta: the network's test-time augmentation (:meth:`gpps.nn.model.SingleNet.predict`): ``"flips"``
            (default: the mean over the 4 mirror images; on 100 validation scenes of our own recipe, MAEN
            20.2 -> 19.3 deg, better on 75 % of them, perf/results/single_tta_*.json), ``"dihedral"`` (8: 19.2,
            twice the time) or ``"none"``.
        lights: the normals the first round's lights are fitted to, with three or more images:
            ``"integrability"`` (factorisation, integrability, GBR fitted to the network's
            normals: :func:`gpps.host.single.integrable_normals`), ``"factorization"`` (the whole 3x3 ambiguity
            fitted to the network's normals: :func:`gpps.host.single.factorization_normals`) or
            ``"least-squares"`` (the network's normals themselves); later rounds and single
            images always fit the lights to the current normals by least squares.
    """

    cuckoo: CuckooConfig = field(default_factory=lambda: CuckooConfig(nests=12, generations=80))
    rounds: int = 1
    prior_weight: float | Literal["map"] | None = None
    shininess: float = 30.0
    specular: SpecularMode = "estimate"
    shininess_range: tuple[float, float] = (5.0, 300.0)
    highlight_prior_deg: float | None = None
    albedo: AlbedoMode = "search"
    init_spread: float = 0.1
    net_size: int | None = None
    integrate: bool = True
    lights: LightStart = "least-squares"
    min_explained: float = 0.5
    min_lit: int = 3
    lit_fraction: float = 0.05
    min_spread_deg: float = 1.0
    tta: TTAName = "flips"

    def __post_init__(self):
        check_choices(self)
        if not isinstance(self.cuckoo, CuckooConfig):
            raise TypeError(f"cuckoo: expected CuckooConfig, got {type(self.cuckoo).__name__}")
        object.__setattr__(self, "rounds", check_number("rounds", self.rounds, lo=0, integer=True))
        if isinstance(self.prior_weight, str) and self.prior_weight != "map":
            raise ValueError(f"prior_weight: expected a number >= 0, 'map' or None, got {self.prior_weight!r}")
        if self.prior_weight is not None and self.prior_weight != "map":
            object.__setattr__(self, "prior_weight", float(check_number("prior_weight", self.prior_weight, lo=0.0)))
        object.__setattr__(self, "shininess", check_number("shininess", self.shininess, lo=0.0, lo_open=True))
        rng = self.shininess_range
        if not isinstance(rng, (tuple, list)) or len(rng) != 2:
            raise ValueError(f"shininess_range: expected (lo, hi), got {rng!r}")
        lo = check_number("shininess_range", rng[0], lo=0.0, lo_open=True)
        hi = check_number("shininess_range", rng[1], lo=lo)
        object.__setattr__(self, "shininess_range", (lo, hi))
        if self.highlight_prior_deg is not None:
            object.__setattr__(self, "highlight_prior_deg",
                               check_number("highlight_prior_deg", self.highlight_prior_deg, lo=0.0, lo_open=True, hi=90.0))
        object.__setattr__(self, "init_spread", check_number("init_spread", self.init_spread, lo=0.0))
        object.__setattr__(self, "min_explained", check_number("min_explained", self.min_explained, lo=0.0, hi=1.0))
        object.__setattr__(self, "min_lit", check_number("min_lit", self.min_lit, lo=0, integer=True))
        object.__setattr__(self, "lit_fraction", check_number("lit_fraction", self.lit_fraction, lo=0.0, hi=1.0))
        object.__setattr__(self, "min_spread_deg", check_number("min_spread_deg", self.min_spread_deg, lo=0.0,
                                                                lo_open=True))
        if self.net_size is not None:
            n = check_number("net_size", self.net_size, lo=16, integer=True)
            object.__setattr__(self, "net_size", n)
        check_bool("integrate", self.integrate)


@dataclass
class SingleResult:
    """What :func:`reconstruct_single` found.

    Attributes:
        mask: (H, W) bool pixels reconstructed.
        normals_net: (H, W, 3) the network's normals: from all the images at once when the network was trained
            so (:attr:`gpps.nn.model.SingleNet.fusion`), else the mean of its one-image answers.
        normals_net_first: (H, W, 3) the network's normals from the first image alone.
        height_net: (H, W) the network's relative depth (a height: larger is nearer;
            units of half the longer image side, mean 0).
        normals: (H, W, 3) refined normals (= normals_net when rounds = 0).
        albedo: (H, W, 3) RGB albedo (relative).
        light_directions: (N, 3) estimated unit directions toward the lights.
        light_intensities: (N, 3) estimated RGB intensities (relative).
        ks: estimated Blinn-Phong specular weight.
        depth: (H, W) depth from the refined normals (0 outside; None when not integrated).
        objective: per round, the mean objective before and after the search (with ``prior_weight="map"``,
            ``after`` is in the second search's MAP units, and ``sigma``, ``theta_median_deg`` and the
            ``prior_weight`` it used are recorded).
        kept_network: pixels that kept the prior because the refined model explained less than
            ``SingleConfig.min_explained`` of their observations.
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
    kept_network: int = 0


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
    cfg = config or SingleConfig()
    if not isinstance(cfg, SingleConfig):
        raise TypeError(f"config: expected SingleConfig, got {type(cfg).__name__}")
    t0 = time.perf_counter()
    timings = {}
    I, m = prepare_images(images, mask)
    n_img, h, w = I.shape[:3]
    if net is not None and not isinstance(net, SingleNet):
        raise TypeError(f"net: expected a gpps.nn.model.SingleNet or None (the shipped weights), got {type(net).__name__}")
    net = net or SingleNet.load()
    total = 1 + cfg.rounds + (1 if cfg.integrate else 0)
    preds = [net.predict(I[k], m, size=cfg.net_size, tta=cfg.tta) for k in range(n_img)]
    n_first, h_net = preds[0]
    if n_img > 1 and net.fusion:  # a network trained on several images at once sees them together
        n_net, h_net = net.predict_many(I, m, size=cfg.net_size, tta=cfg.tta)
    else:  # else the mean of its one-image answers
        n_net = np.sum([p[0] for p in preds], 0)
        n_net /= np.maximum(np.linalg.norm(n_net, axis=-1, keepdims=True), 1e-8)
        n_net[~m] = 0.0
        h_net = np.mean([p[1] for p in preds], 0).astype(np.float32)
    timings["network"] = time.perf_counter() - t0
    if progress:
        progress(1, total, "network")

    t1 = time.perf_counter()
    Ip, view = I[:, m], view_dirs(camera, (h, w), m)  # (N, P, 3), (P, 3)
    st = _first_lights(Ip, n_net[m].astype(np.float32), view, m, cfg, net)
    kept = 0
    if cfg.rounds > 0:
        st["theta"] = _spread([p[0][m] for p in preds], n_net[m])
        _refine(Ip, view, st, cfg, device, progress, total)
        kept = _keep_unexplained(Ip, view, st, cfg)
    timings["refine"] = time.perf_counter() - t1

    normals = np.zeros((h, w, 3), np.float32)
    normals[m] = st["normals"]
    albedo = np.zeros((h, w, 3), np.float32)
    albedo[m] = st["kd"]
    depth = None
    if cfg.integrate:
        t2 = time.perf_counter()
        cam = camera or Orthographic(pixel_size=2.0 / max(h, w))
        depth = integrate_normals(normals, m, camera=cam, device=str(device) if device else "auto").depth
        timings["integrate"] = time.perf_counter() - t2
        if progress:
            progress(total, total, "integrated")
    timings["total"] = time.perf_counter() - t0
    return SingleResult(
        mask=m, normals_net=n_net.astype(np.float32), normals_net_first=n_first, height_net=h_net, normals=normals,
        albedo=albedo, light_directions=st["dirs"], light_intensities=st["rgb"], ks=float(st["ks"]), depth=depth,
        objective=st["objective"], timings=timings, shininess=float(st["shin"]), highlights=st["highlights"],
        kept_network=int(kept),
    )


def _keep_unexplained(Ip, view, st: dict, cfg: SingleConfig) -> int:
    """Where the refined image model explains less than ``cfg.min_explained`` of a pixel's observations'
    energy (:func:`gpps.host.single.explained_fraction`), the observations do not measure its normal (a cast
    shadow or interreflection the model lacks, lights that were estimated wrong): the pixel keeps the prior
    (the network's normal, through the highlights' bas-relief when one was accepted) instead of a normal
    fitted to what the model cannot explain.  So does a pixel with fewer than ``cfg.min_lit`` lit observations
    (``cfg.lit_fraction`` of its brightest), which cannot fix a normal and an albedo.  Returns how many pixels
    kept the prior."""
    frac = explained_fraction(Ip, st["normals"], view, st["dirs"], st["rgb"], st["kd"], float(st["ks"]), float(st["shin"]))
    bad = frac < cfg.min_explained
    if cfg.min_lit > 0:  # a normal and an albedo need three lit observations (Woodham): fewer do not fix them
        g = np.asarray(Ip, np.float64).sum(-1)  # (N, P) grey
        lit = g > cfg.lit_fraction * g.max(0, keepdims=True)
        bad |= lit.sum(0) < min(cfg.min_lit, Ip.shape[0])
    if np.any(bad):
        n = np.array(st["normals"], copy=True)
        n[bad] = st["prior"][bad]
        st["normals"] = n
    return int(bad.sum())


def _first_lights(Ip, npix, view, m, cfg: SingleConfig, net) -> dict:
    """Step 2 of the flow: the normals the first lights are fitted to, the lights, and with
    ``specular="estimate"`` the bas-relief, ks and shininess from the highlights.

    Returns:
        the state the rounds carry: ``normals`` (P, 3) the current normals, ``start`` and ``prior`` (P, 3)
        the search's start and prior normals, ``dirs``/``rgb`` (N, 3) the lights, ``kd`` (P, 3), ``ks``,
        ``shin``, ``hl`` (the highlight fit's settings) and the ``highlights`` / ``objective`` records.
    """
    n_img = Ip.shape[0]
    n_start = npix
    if n_img >= 3 and cfg.lights == "factorization":
        n_start, _ = factorization_normals(Ip, npix)
    elif n_img >= 3 and cfg.lights == "integrability":
        n_start = integrable_normals(Ip, npix, m)
    shin = cfg.shininess
    dirs, rgb, kd, ks = estimate_lights(Ip, n_start, view, shininess=shin, specular=cfg.specular == "ks")
    st = {"normals": npix, "start": n_start, "prior": npix, "hl": None, "highlights": [], "objective": []}
    if cfg.specular == "estimate":
        st["hl"] = {"prior_deg": _prior_deg(cfg, net), "shininess_range": cfg.shininess_range}
        fit = fit_highlights(Ip, n_start, view, dirs, rgb, kd, shininess=shin, **st["hl"])
        dirs, rgb, kd, ks, shin = fit.directions, fit.intensities, fit.albedo, fit.ks, fit.shininess
        st["start"], st["prior"] = fit.normals, through_gbr(npix, fit.gbr)
        st["highlights"].append({"round": 0, **fit.info})
    st.update(dirs=dirs, rgb=rgb, kd=kd, ks=ks, shin=shin)
    return st


def _spread(preds, mean) -> np.ndarray:
    """(P,) RMS angle (radians) of the per-image predictions ``preds`` ((P, 3) each) about their ``mean``."""
    c = [np.clip(np.sum(q * mean, -1), -1.0, 1.0) for q in preds]
    return np.sqrt(np.mean([np.arccos(x) ** 2 for x in c], 0))


def _prior_deg(cfg: SingleConfig, net) -> float:
    """The network's expected angular error (deg): ``cfg.highlight_prior_deg``, else its validation MAEN."""
    if cfg.highlight_prior_deg is not None:
        return float(cfg.highlight_prior_deg)
    return float((getattr(net, "meta", None) or {}).get("val_maen_deg", 10.0))


def _start_nests(st: dict, cfg: SingleConfig) -> np.ndarray:
    """(P, K, 5) starting habitats: half the nests around the current start normals, half around the
    (bas-relief corrected) network's normals, with ``init_spread`` noise; albedos around the estimate."""
    rng = np.random.default_rng(cfg.cuckoo.seed)
    n_start, n_prior, kd = st["start"], st["prior"], st["kd"]
    P, K = n_start.shape[0], cfg.cuckoo.nests
    start = np.zeros((P, K, 5), np.float32)
    start[:, :, :2] = n_start[:, None, :2]
    start[:, K // 2:, :2] = n_prior[:, None, :2]
    start[:, 1:, :2] += rng.normal(0, cfg.init_spread, (P, K - 1, 2)) * (np.arange(1, K) != K // 2)[None, :, None]
    r2 = np.sum(start[:, :, :2] ** 2, -1, keepdims=True)
    start[:, :, :2] *= np.where(r2 > 0.995**2, 0.995 / np.sqrt(np.maximum(r2, 1e-12)), 1.0)
    start[:, :, 2:] = kd[:, None, :] * (1 + rng.normal(0, 0.05, (P, K, 3)) * (np.arange(K) > 0)[None, :, None])
    return start


def _refine(Ip, view, st: dict, cfg: SingleConfig, device, progress, total: int) -> None:
    """Step 3, ``cfg.rounds`` times: cuckoo search of every pixel's normal and albedo on the device
    (:class:`gpps.pipeline.cuckoo.PhotometricCuckoo`, observations uploaded once), then the lights (and
    the highlights' bas-relief) again from the refined normals.  Updates ``st`` in place.

    With ``cfg.prior_weight = "map"`` (three or more images) the first round's search is followed by a second,
    from the same start, on the maximum-a-posteriori objective ``err / (2 sigma^2) + |n - n_prior|^2 /
    (2 theta_p^2)``: ``sigma^2`` the median squared residual of one observation (one image, one channel) the
    first search left, ``theta_p`` the pixel's network uncertainty, the RMS angle of the per-image predictions
    about their mean (``st["theta"]``, at least ``cfg.min_spread_deg``).  Where the network's answers agree, the
    observations must be explained by a model close to them; where they disagree, the observations decide."""
    n_img, P = Ip.shape[:2]
    mode = cfg.prior_weight if cfg.prior_weight is not None else ("map" if n_img >= 3 else 0.05)
    prior_w = mode if isinstance(mode, float) else (0.002 if n_img >= 3 else 0.05)  # ("map" starts at 0.002)
    stage = PhotometricCuckoo(n_img, P, config=cfg.cuckoo, device=device)
    stage.upload(Ip, view, st["prior"], _start_nests(st, cfg), prior_weight=prior_w, shininess=st["shin"],
                 albedo_from_normal=cfg.albedo == "least-squares")
    cur_kd = st["kd"]
    for r in range(cfg.rounds):
        stage.upload(light_dir=st["dirs"], light_rgb=st["rgb"], ks=st["ks"], shininess=st["shin"])
        stage.step(0)
        f_before = float(stage.fetch()["fit"].mean())
        stage.step(cfg.cuckoo.generations)
        out = stage.fetch()
        rec = {"round": r, "before": f_before, "prior_weight": float(prior_w)}
        if mode == "map" and n_img >= 3 and r == 0:
            # the misfit one observation keeps after the search, and each pixel's network uncertainty (the spread
            # of the per-image predictions): the MAP objective err / (2 sigma^2) + |dn|^2 / (2 theta_p^2), scaled
            # by 2 theta_med^2, searched again from the start
            frac = explained_fraction(Ip, out["normals"], view, st["dirs"], st["rgb"], out["albedo"], float(st["ks"]),
                                      float(st["shin"]))
            energy = np.sum(np.asarray(Ip, np.float64) ** 2, axis=(0, 2))
            sigma2 = float(np.median(np.maximum(1.0 - frac, 0.0) * energy)) / (n_img * 3)
            theta = np.maximum(st["theta"], np.radians(cfg.min_spread_deg))
            t_med = float(np.median(theta))
            prior_w = 2.0 * sigma2 / t_med**2
            rec.update(sigma=float(np.sqrt(sigma2)), theta_median_deg=float(np.degrees(t_med)), prior_weight=prior_w)
            stage.upload(nests=_start_nests(st, cfg), weight=(theta / t_med) ** 2, prior_weight=prior_w)
            stage.step(cfg.cuckoo.generations)
            out = stage.fetch()
        st["normals"], cur_kd = out["normals"], out["albedo"]
        rec.update(after=float(out["error"].mean()), ks=float(st["ks"]), shininess=float(st["shin"]))
        st["objective"].append(rec)
        if progress:
            progress(2 + r, total, f"cuckoo round {r + 1}/{cfg.rounds}")
        if r + 1 < cfg.rounds:  # lights for the next round from the refined normals; albedo follows
            _next_lights(stage, Ip, view, st, cur_kd, cfg, r)
    st["kd"] = cur_kd
    stage.close()


def _next_lights(stage, Ip, view, st: dict, cur_kd, cfg: SingleConfig, r: int) -> None:
    """Between rounds: the lights from the refined normals; with highlights, every nest's normal and
    the prior moved through the bas-relief they show; the nests' albedos rescaled with the lights."""
    dirs, rgb, kd_new, ks = estimate_lights(Ip, st["normals"], view, albedo=cur_kd, shininess=st["shin"],
                                            specular=cfg.specular == "ks")
    shin = st["shin"]
    nests = stage.fetch_nests()
    if cfg.specular == "estimate":
        fit = fit_highlights(Ip, st["normals"], view, dirs, rgb, kd_new, shininess=shin, **st["hl"])
        dirs, rgb, kd_new, ks, shin = fit.directions, fit.intensities, fit.albedo, fit.ks, fit.shininess
        st["highlights"].append({"round": r + 1, **fit.info})
        if fit.accepted:  # move every nest's normal, and the prior, through the bas-relief
            nests[:, :, :2] = through_gbr(nest_normals(nests), fit.gbr)[..., :2]
            st["prior"] = through_gbr(st["prior"], fit.gbr)
            stage.upload(prior=st["prior"])
    if cfg.albedo == "search":  # keep each nest's albedo consistent with the new light scale
        ratio = kd_new / np.maximum(cur_kd, 1e-6)
        nests[:, :, 2:] *= np.clip(ratio, 0.25, 4.0)[:, None, :]
    stage.upload(nests=nests, restart=False)
    st.update(dirs=dirs, rgb=rgb, ks=ks, shin=shin)
