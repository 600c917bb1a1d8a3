"""Calibrated photometric stereo on arrays: normals and albedo from N >= 3 images.

Thin API over :class:`gpps.pipeline.solver.PixelSolver`::
    res = solve_normals(images, mask, lights, camera=cam, material=mat, solver="lm")
    res.normals  # (H, W, 3) unit normals in the gpps frame, 0 outside the mask

Methods (seed chapters 3-4):
* ``solver="none"``: Woodham's Lambertian least squares (the baseline).
* ``solver="lm" | "dogleg" | "bfgs"``: per-pixel nonlinear least squares on
  ``f_h = I_h - model`` (4.2) for the material's reflectance model
  (Lambertian, Phong, Blinn-Phong, Cook-Torrance, Ashikhmin-Shirley) with
  analytic Jacobians, started from the least-squares normal and several
  other starts.  The albedo is eliminated by variable projection (faster and
  better conditioned than solving for it jointly).

For a perspective camera the normal is the same unknown; the perspective
log-depth gradient the integrator needs is :func:`gpps.host.perspective.normals_to_gradient`
(PPN, 3.2-3.3).  Near point lights need a depth estimate (2.30-2.31).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, fields, replace

import numpy as np

from gpps import names
from gpps._check import IMAGE_FULL_SCALE, as_array, as_flags, as_images, as_mask, clipping, warn
from gpps._runtime import warp
from gpps.camera import Orthographic, Perspective
from gpps.host.clipping import clipped_observations
from gpps.host.observations import grey_peak, masked_grey
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material, check_model_images
from gpps.pipeline.render import Renderer
from gpps.pipeline.solver import PixelSolver, SolverConfig, check_scale

__all__ = ["PSResult", "solve_normals", "reproject", "SolverConfig"]


@dataclass
class PSResult:
    """Output of :func:`solve_normals`.

    Attributes:
        normals: (H, W, 3) float32 unit normals (gpps frame), zeros outside the mask.
        albedo: (H, W, 3) float32 RGB albedo kd.
        residual: (H, W) float32 RMS weighted residual per observation and channel.
        iterations: (H, W) int32 cost evaluations spent (all starts and rounds).
        flags: (H, W) int32 bits ``gpps.pipeline.solver.FLAG_*`` (ill-conditioned
            lights, fewer than 3 lit observations, not converged, ...).
        cond: (H, W) float32 condition number of the valid light directions (3.13).
        weights: (N, H, W) float32 final observation weights (0: dropped; -1: dark, a one-sided
            attached-shadow term that only penalises a model brighter than the observation).
        mask: (H, W) bool.
        timings: seconds: ``setup``, ``solve`` (device), ``total``.
        config: the solver settings used.
        material: the reflectance model used.
        determined: (H, W) bool pixels with 3 or more usable (lit, unsaturated) observations.
        warnings: messages of the :class:`gpps.GppsWarning` warnings issued.
    """

    normals: np.ndarray
    albedo: np.ndarray
    residual: np.ndarray
    iterations: np.ndarray
    flags: np.ndarray
    cond: np.ndarray
    weights: np.ndarray
    mask: np.ndarray
    timings: dict = field(default_factory=dict)
    config: SolverConfig | None = None
    material: Material | None = None
    determined: np.ndarray | None = None
    warnings: list = field(default_factory=list)


def input_saturation(images, saturation=None):
    """The saturation level of the check: ``saturation``, else full scale (1.0) for uint8/uint16 input, else None."""
    if saturation is not None:
        return float(saturation)
    return 1.0 if getattr(images, "dtype", None) in IMAGE_FULL_SCALE else None


def detect_clipping(images, img, mask, *, saturation=None, valid=None, sink: list | None = None, gathered=None):
    """The observations to use when the caller gave neither ``saturation`` nor ``valid``: clipped ones left out.

    Float images clipped by the sensor and divided by the light intensities sit at a value no full-scale rule
    knows (1 / 0.8 = 1.25); :func:`gpps.host.clipping.clipped_observations` finds them from the images alone (a
    plateau of identical values at an image's maximum that piles up, is not a flat region and is not nearly
    everything).  When it finds some, they are left out (the result is the ``valid`` to use) and a
    :class:`gpps.GppsWarning` says so.  With ``saturation`` or ``valid`` given, or integer (uint8 / uint16) input
    (whose full scale is the saturation level, :func:`input_saturation`), nothing is detected.

    Args:
        images: the images as the caller gave them (their dtype decides integer input).
        img: (N, H, W, C) or (N, H, W) float images (checked, :func:`check_inputs`).
        mask: (H, W) bool.
        saturation: the caller's saturation level or None.
        valid: the caller's (N, H, W) bool observations or None.
        sink: list that collects the warning messages.
        gathered: optional ``(idx, x)``, the mask's observations gathered once
            (:func:`gpps.host.observations.gather_masked`; :func:`check_observations` reads them too).

    Returns:
        ``(valid, clipped)``: the (N, H, W) bool observations to use (the caller's ``valid`` when nothing was
        detected or detection did not run), and the (N, H, W) bool observations left out as clipped (None when
        none).
    """
    if valid is not None or input_saturation(images, saturation) is not None:
        return valid, None
    keep, info = clipped_observations(img, mask, gathered=gathered)
    if keep is None:
        return valid, None
    hit = info["clipped_images"]
    values = ", ".join(f"{info['images'][k]['value']:.6g}" for k in hit[:8]) + (", ..." if len(hit) > 8 else "")
    total = int(np.count_nonzero(mask)) * img.shape[0]
    warn(f"images: {info['observations']} observations ({100 * info['observations'] / total:.1f}%) in images "
         f"{[k + 1 for k in hit[:8]]}{' ...' if len(hit) > 8 else ''} sat on a plateau of one value at the image's "
         f"maximum ({values}) and were left out as clipped (saturated); pass saturation= or valid= to decide "
         "instead", sink)
    return keep, ~keep & mask[None]


def check_inputs(images, mask, lights, camera=None):
    """Check the arguments shared by :func:`solve_normals` and :func:`gpps.reconstruct`.

    Returns:
        ``(images, mask, lights, camera)``: images as an array of shape
        (N, H, W, 3) or (N, H, W), the (H, W) bool mask, the lights, and the
        camera (orthographic when None).
    """
    img = as_images("images", images)
    if img.ndim not in (3, 4) or (img.ndim == 4 and img.shape[-1] not in (1, 3)):
        raise ValueError(f"images: expected shape (N, H, W, 3) or (N, H, W), got {img.shape}")
    n, h, w = img.shape[:3]
    if n < 3:  # (before the lights' count: an empty stack is the images' fault, not the lights')
        raise ValueError(f"images: expected at least 3 images, got {n}")
    m = as_mask("mask", mask, (h, w))
    if not isinstance(lights, (DirectionalLights, PointLights)):
        raise TypeError(f"lights: expected gpps.lights.DirectionalLights or PointLights, got {type(lights).__name__}")
    if len(lights) != n:
        raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
    lit = int(np.count_nonzero(np.asarray(lights.intensities).max(axis=1) > 0))
    if lit < 3:  # (the model of a dark light is 0 whatever the normal: fewer than 3 lit ones determine nothing)
        raise ValueError(f"lights: expected at least 3 lights with an intensity > 0, got {lit} of {n}")
    camera = Orthographic() if camera is None else camera
    if not isinstance(camera, (Orthographic, Perspective)):
        raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
    return img, m, lights, camera


#: Observations at or below this fraction of the mask's brightest (99.9th percentile) grey value are unlit.
UNLIT_FRACTION = 1e-3
#: ALBEDO_RANGE: the mask's brightest observations over the brightest directional light's intensity (an albedo)
#: that the float32 solver takes (above ~1e10 the albedo comes out 0); SCALE_RANGE (:mod:`gpps.pipeline.solver`):
#: the observations' own.
ALBEDO_RANGE = (1e-12, 1e9)
#: Below this share of determined mask pixels the input is degenerate (an error); below WARN_DETERMINED a warning.
MIN_DETERMINED = 0.2
WARN_DETERMINED = 0.5
#: WORKING_ALBEDO: the albedo scale (:func:`working_scale`) within which the pipeline's absolute constants hold
#: (the material searches' ranges, :data:`gpps.names.LOBE_RANGES`, and the solvers' tolerances); outside it
#: :func:`gpps.reconstruct` solves at a power of two times it that brings it to about 1.
WORKING_ALBEDO = (1.0 / 16.0, 4.0)
#: WORKING_IMAGES: the same for the images' own scale (their brightest values, the residuals' unit)
WORKING_IMAGES = (2.0 ** -12, 2.0 ** 12)
#: about the most observations :func:`working_scale` reads (a strided grid of pixels, every image; at least
#: 1024 pixels): its percentiles only have to be right within a factor of about 2 (powers of two, wide bands)
SCALE_SAMPLE = 1 << 14


def _power_of_two_into(x: float, band: tuple[float, float]) -> float:
    """1 when ``x`` lies in ``band`` (or is not a positive number), else the power of two nearest ``1 / x``."""
    if not (x > 0.0 and np.isfinite(x)) or band[0] <= x <= band[1]:
        return 1.0
    return float(2.0 ** int(np.round(-np.log2(x))))


def working_scale(images, mask, lights, *, reference_depth: float | None = None) -> dict:
    """The powers of two the pipeline's solves multiply the images and the lights' radiance by.

    The image model ``I = E (kd t_d + ks t_s)`` is linear in the images, the radiance ``E`` and the albedo and
    ks, but the pipeline's constants are absolute: the material searches' ranges (ks in [0.02, 3],
    :data:`gpps.names.LOBE_RANGES`) assume albedos of order one, and the solvers' tolerances images of order one
    (8- and 16-bit images read as [0, 1]).  Raw sensor counts with unit intensities (albedo scale in the
    thousands) or images in radiometric units (1e-6) left the estimated ks on a bound of its range and the
    normals 5-25 deg off.  So two scales are measured on the observations of a strided grid of the mask's pixels
    (about :data:`SCALE_SAMPLE` observations):

    * the image scale ``b``: the 99.9th percentile of the grey values;
    * the albedo scale ``a``: the 99.9th percentile of the grey value over the light's radiance at the object,
      ``I_k / E_k`` for directional lights, ``I_k r_k^2 / E_k`` for point lights (``r_k`` the light's distance to
      the point on the optical axis at ``reference_depth``; without it, ``I_k / E_k``).

    Within :data:`WORKING_IMAGES` and :data:`WORKING_ALBEDO` nothing changes.  Outside, the images are multiplied
    by ``s_images``, the power of two nearest ``1 / b`` (else 1), and the radiance by ``s_lights = s_images / t``
    with ``t`` the power of two nearest ``1 / a`` (else 1): the working albedo ``a t`` is near 1, or ``a`` itself
    when it was in its band.  Powers of two are exact in floating point: the same normals and depth, the albedo
    and ks ``t`` times the caller's.  The bands are where the pipeline was
    measured scale-free on synthetic ground truth (session 18, ``perf/results/s18/README.md``: Blinn-Phong bumps
    under 8 lights and Cook-Torrance bumps and sphere under 3 and 4: the same MAEN from 1/16 to 4 times a 16-bit
    rendering's albedo scale, and for images and radiance scaled together from 1e-3 to 1e9).

    Args:
        images: (N, H, W, C) float images (checked).
        mask: (H, W) bool.
        lights: the lights (their intensities are the radiance ``E_k``).
        reference_depth: the object's mean depth (scene units), for point lights.

    Returns:
        ``{"images": s_images, "lights": s_lights, "image_scale": b, "albedo_scale": a}``.
    """
    img = images if images.ndim == 4 else images[..., None]
    n = img.shape[0]
    pixels = max(SCALE_SAMPLE // max(n, 1), 1024)
    step = max(1, int(np.sqrt(np.count_nonzero(mask) / pixels)))
    h, w = mask.shape
    r, c = np.nonzero(mask[::step, ::step])
    # (N, P): a strided grid's observations, their channels' mean in float64 as img[:, ::step, ::step][:, sub]
    # .mean(axis=-1, dtype=np.float64) sums them (left to right, then / C), gathered by flat index
    x = np.take(img.reshape(n, h * w, img.shape[-1]), (r * step) * w + c * step, axis=1).astype(np.float64)
    grey = x[..., 0]
    for k in range(1, x.shape[-1]):
        grey = grey + x[..., k]
    grey = grey / x.shape[-1]
    e = np.asarray(lights.intensities, np.float64).mean(axis=1)  # (N,)
    per = np.where(e > 0, 1.0 / np.where(e > 0, e, 1.0), 0.0)
    if isinstance(lights, PointLights) and reference_depth is not None:
        p = np.asarray(lights.positions, np.float64) - np.array([0.0, 0.0, -float(reference_depth)])
        per = per * np.einsum("ij,ij->i", p, p)
    b = float(np.percentile(grey, 99.9)) if grey.size else 0.0
    a = float(np.percentile(grey * per[:, None], 99.9)) if grey.size else 0.0
    s_images = _power_of_two_into(b, WORKING_IMAGES)
    t = _power_of_two_into(a, WORKING_ALBEDO)  # the working albedo over the caller's: s_images / s_lights
    return {"images": s_images, "lights": s_images / t, "image_scale": b, "albedo_scale": a}


def _masked_statistics(img, mask, valid, saturation, gathered=None):
    """The statistics :func:`check_observations` needs, on the mask's pixels only, image by image.

    Args:
        img: (N, H, W, C) images; mask: (H, W) bool; valid: (N, H, W) or None; saturation: level or None.
        gathered: optional ``(idx, x)``: the mask's flat indices and observations
            (:func:`gpps.host.observations.gather_masked`), read instead of the frames.

    Returns:
        ``(grey, bad, peak)``: (N, P) ``img.mean(axis=-1)[:, mask]`` (the same values: numpy's mean over the
        channel axis sums left to right, then divides by C; tests/test_host_overheads.py pins it), (N, P) bool
        ``max over channels >= saturation`` or not ``valid`` (None when neither is given), and (N, P) the
        max over channels.  One pass over each image (in cache), no (N, H, W) temporaries.
    """
    n, c = img.shape[0], img.shape[-1]
    if img.dtype not in (np.float32, np.float64) or c not in (1, 3):  # other inputs: the plain formula
        grey = img.mean(axis=-1)[:, mask]
        peak = img.max(axis=-1)[:, mask]
        bad = None if saturation is None else peak >= saturation
        if valid is not None:
            inv = ~np.asarray(valid, bool)[:, mask]
            bad = inv if bad is None else bad | inv
        return grey, bad, peak
    if gathered is not None:
        idx, x = gathered
        grey, peak = grey_peak(x) if c == 3 else (x[:, 0], x[:, 0])
    elif c == 3:
        idx = np.flatnonzero(mask)
        grey, peak = masked_grey(img, mask, idx=idx, peak=True)
    else:
        idx = np.flatnonzero(mask)
        grey = np.take(img[..., 0].reshape(n, -1), idx, axis=1)
        peak = grey
    bad = None if saturation is None and valid is None else np.zeros((n, idx.size), bool)
    val = None if valid is None else np.asarray(valid, bool)
    for k in range(n):
        if saturation is not None:
            bad[k] = peak[k] >= saturation
        if val is not None:
            bad[k] |= ~np.take(val[k].reshape(-1), idx)
    return grey, bad, peak


def check_observations(images, mask, lights, *, valid=None, saturation=None, reference_depth=None,
                       sink: list | None = None, clipped=None, gathered=None) -> np.ndarray:
    """Refuse degenerate input and warn about doubtful input, before any solve.

    A pixel is *determined* when it has at least 3 usable observations: lit
    (grey value above :data:`UNLIT_FRACTION` of the mask's 99.9th percentile)
    and not saturated (no channel at or above ``saturation``, and ``valid``
    where given).  Errors (ValueError naming the cause): every observation in
    the mask black; fewer than :data:`MIN_DETERMINED` of the mask pixels
    determined (all dark, all saturated, or the mask outside the lit area).
    With no ``saturation``, float images whose brightest channels top out at a
    full-scale value (:data:`gpps.names.CLIP_LEVELS`, e.g. 1.0) are taken as clipped there
    (:func:`gpps._check.clipping`): ``names.SATURATED_SHARE`` or more of the observations at it is an error,
    ``names.CLIPPED_SHARE`` or more (and ``names.CLIPPED_MIN``) a warning, unless ``clipped`` (the observations
    :func:`detect_clipping` left out) holds enough of them that fewer than those remain.  Warnings
    (:class:`gpps.GppsWarning`, messages appended to ``sink``): that clipping;
    fewer than :data:`WARN_DETERMINED` determined; a directional light behind
    the object (``z <= 0``: it lights only surfaces that face away from the
    camera) or a point light at or beyond the object's mean depth.

    Args:
        images: (N, H, W, 3) or (N, H, W) float images (checked).
        mask: (H, W) bool.
        lights: the lights.
        valid: optional (N, H, W) bool observations to use.
        saturation: raw level at or above which a channel is saturated (None: unknown).
        reference_depth: the object's mean depth (scene units), for point lights.
        sink: list that collects the warning messages.
        clipped: optional (N, H, W) bool observations :func:`detect_clipping` left out as clipped (already
            out of ``valid``): the full-scale warning counts only the others, and the error of too few
            determined pixels says that they were left out.
        gathered: optional ``(idx, x)``: ``np.flatnonzero(mask)`` and the images' (N, C, P) observations there
            (:func:`gpps.host.observations.gather_masked`), read instead of the frames (the same values).

    Returns:
        (H, W) bool: the determined pixels.
    """

    img = images if images.ndim == 4 else images[..., None]
    # (N, P) grey values, (N, P) unusable or None, (N, P) brightest channels
    grey, bad, peak = _masked_statistics(img, mask, valid, saturation, gathered)
    scale = float(np.percentile(grey, 99.9)) if grey.size else 0.0
    if not scale > 0.0:
        outside = img.mean(axis=-1)[:, ~mask]
        where = (" while pixels outside it are lit: the mask lies outside the lit area"
                 if outside.size and float(outside.max()) > 0 else "")
        raise ValueError(f"images: every observation inside the mask is black (0){where}; nothing is lit")
    check_scale(scale)
    if isinstance(lights, DirectionalLights):  # (a point light's radiance also falls with the squared distance)
        ratio = scale / float(np.max(np.asarray(lights.intensities).mean(axis=1)))
        if not ALBEDO_RANGE[0] <= ratio <= ALBEDO_RANGE[1]:
            raise ValueError(f"lights: expected intensities of the images' order (the brightest observations over "
                             f"the brightest light's intensity, an albedo, between {ALBEDO_RANGE[0]:g} and "
                             f"{ALBEDO_RANGE[1]:g}), got {ratio:.3g}; rescale the lights' intensities")
    lit = grey > UNLIT_FRACTION * scale
    usable = lit if bad is None else lit & ~bad
    inside = np.count_nonzero(usable, axis=0) >= 3  # (P,)
    determined = np.zeros(mask.shape, bool)
    determined[mask] = inside
    frac = float(inside.mean())
    if frac < MIN_DETERMINED:
        sat_share = 0.0 if bad is None else float(bad.mean())
        if sat_share > 0.5:
            cause = f"{100 * sat_share:.0f}% of the observations are saturated (over-exposed)"
        elif lit.mean() < 0.5:
            cause = (f"{100 * (1 - lit.mean()):.0f}% of the observations are dark: under-exposed images, lights "
                     "that missed the object, or a mask outside the lit area")
        else:
            cause = "too few lights reach each pixel"
        if clipped is not None:
            cause += ("; the observations on a plateau at an image's maximum were taken as clipped and left out "
                      "(pass saturation= or valid= to decide)")
        raise ValueError(f"images: only {100 * frac:.1f}% of the mask pixels have 3 or more usable (lit, "
                         f"unsaturated) observations; {cause}")
    verdict, top, share = clipping(peak) if saturation is None else (None, 0.0, 0.0)
    if verdict == "saturated":
        raise ValueError(f"images: {100 * share:.0f}% of the observations inside the mask are at {top:g}, the "
                         "full scale: everything is saturated (over-exposed), there is no shading to fit")
    if verdict == "clipped" and clipped is not None:
        # (the detection left out its plateaus and said so: only the full-scale observations it kept count)
        kept = np.count_nonzero((peak >= top) & ~np.asarray(clipped, bool)[:, mask])
        share = kept / peak.size
        if share < names.CLIPPED_SHARE or kept < names.CLIPPED_MIN:
            verdict = None
    if verdict == "clipped":
        left = "" if clipped is None else " (besides those left out as clipped)"
        warn(f"images: {100 * share:.1f}% of the observations inside the mask sit at {top:g}, the full scale{left}: "
             f"clipped (saturated)? Pass saturation={top:g} to leave them out of the fit", sink)
    if frac < WARN_DETERMINED:
        warn(f"images: {100 * (1 - frac):.0f}% of the mask pixels have fewer than 3 usable (lit, unsaturated) "
             "observations; their normals rest on neighbours and priors", sink)
    if isinstance(lights, DirectionalLights):
        behind = np.nonzero(np.asarray(lights.directions)[:, 2] <= 0.0)[0]
        if behind.size:
            warn(f"lights: {behind.size} of {len(lights)} directional lights point away from the camera side "
                 f"(z <= 0; lights {(behind + 1).tolist()[:8]}): they light only surfaces facing away from the camera",
                 sink)
    elif reference_depth is not None:
        behind = np.nonzero(np.asarray(lights.positions)[:, 2] <= -float(reference_depth))[0]
        if behind.size:
            warn(f"lights: {behind.size} of {len(lights)} point lights are at or beyond the object's mean depth "
                 f"{float(reference_depth):g} (lights {(behind + 1).tolist()[:8]}): they light it from behind", sink)
    return determined


def solve_normals(
    images,
    mask,
    lights,
    *,
    camera=None,
    material: Material | None = None,
    solver: str = "lm",
    depth=None,
    robust: str | None = None,
    valid=None,
    init_normals=None,
    config: SolverConfig | None = None,
    device=None,
    progress=None,
    **options,
) -> PSResult:
    """Per-pixel calibrated photometric stereo.

    Args:
        images: (N, H, W, 3) RGB or (N, H, W) grey images >= 0, N >= 3, already
            divided by the light intensities when ``lights`` has unit intensities
            (the model uses ``lights.intensities`` as the radiance).
        mask: (H, W) bool, pixels to solve.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N).
        camera: :class:`Orthographic` (default) or :class:`Perspective`.
        material: reflectance model and per-scene parameters (default Lambertian).
        solver: ``"lm"``, ``"dogleg"``, ``"bfgs"`` or ``"none"`` (Woodham least squares).
        depth: (H, W) depth estimate (scene units, > 0): required for point lights.
        robust: None / ``"none"``, ``"huber"`` or ``"cauchy"`` (IRLS).
        valid: optional (N, H, W) bool of observations to use (e.g. not saturated).  Without it and without
            ``saturation`` (in ``options`` or ``config``), float images are searched for clipped observations
            (:func:`detect_clipping`: a plateau of one value at an image's maximum, e.g. a sensor's full scale
            divided by the light's intensity): those found are left out, with a warning.  uint8 / uint16 images
            need no search: an observation with a channel at their full scale is dropped from the fit (the
            camera clipped there), unless ``saturation`` says otherwise.
        init_normals: (H, W, 3) warm start (with ``warm_start=True``).
        config: a full :class:`SolverConfig` (then ``solver``, ``robust`` and
            ``options`` must be left at their defaults).
        device: Warp device (None: CUDA if present).
        progress: optional ``progress(done, total, message)`` callback.
        **options: further :class:`SolverConfig` fields (``starts``, ``max_iters``,
            ``shadow_threshold``, ``saturation``, ...).  ``saturation``: observations with a channel at or
            above it are dropped; given, no clipping is detected (see ``valid``).

    Returns:
        :class:`PSResult`.

    Raises:
        ValueError: wrong shapes, non-finite values, fewer than 3 lights or
            collinear/coplanar light directions (before any solve).
    """
    t0 = time.perf_counter()
    unknown = sorted(set(options) - {f.name for f in fields(SolverConfig)})
    if unknown:
        raise TypeError(f"options: unexpected keyword(s) {unknown}; expected fields of gpps.SolverConfig")
    if config is None:
        config = SolverConfig(solver=solver, robust=robust or "none", **options)
    elif not isinstance(config, SolverConfig):
        raise TypeError(f"config: expected SolverConfig, got {type(config).__name__}")
    elif options or solver != "lm" or robust is not None:
        raise ValueError("config: pass either config or solver/robust/options, not both")
    img, m, lights, camera = check_inputs(images, mask, lights, camera)
    n, h, w = img.shape[:3]
    if valid is not None:  # (as_flags: NaN or strings are an error, not True)
        valid = as_flags("valid", valid, (n, h, w))
    notes: list[str] = []
    ref = None
    if depth is not None:
        dep = as_array("depth", depth, shape=(h, w))
        ref = float(np.mean(dep[m]))
    if config.saturation is None and input_saturation(images) is not None:
        # uint8 / uint16 input: the camera clipped at its full scale (as_images scaled it to 1): dropped from the fit
        config = replace(config, saturation=input_saturation(images))
    valid, clipped = detect_clipping(images, img, m, saturation=config.saturation, valid=valid, sink=notes)
    determined = check_observations(img, m, lights, valid=valid, saturation=input_saturation(images, config.saturation),
                                    reference_depth=ref, sink=notes, clipped=clipped)
    material = Material("lambertian", ks=0.0) if material is None else material
    if not isinstance(material, Material):
        raise TypeError(f"material: expected gpps.material.Material, got {type(material).__name__}")
    check_model_images((material.brdf,), n, sink=notes)
    if progress:
        progress(0, 3, "setup")
    ps = PixelSolver((n, h, w), camera, lights, material, config, device=device)
    ps.upload(img, m, depth=depth, valid=valid, init_normals=init_normals)
    t1 = time.perf_counter()
    if progress:
        progress(1, 3, "solve")
    ps.step()

    warp().synchronize_device(ps.device)
    t2 = time.perf_counter()
    out = ps.fetch()
    if progress:
        progress(3, 3, "done")
    t3 = time.perf_counter()
    return PSResult(
        normals=out["normals"],
        albedo=out["albedo"],
        residual=out["residual"],
        iterations=out["iterations"],
        flags=out["flags"],
        cond=out["cond"],
        weights=out["weights"],
        mask=m,
        timings={"setup": t1 - t0, "solve": t2 - t1, "total": t3 - t0},
        config=config,
        material=material,
        determined=determined,
        warnings=notes,
    )


def reproject(result: PSResult, lights, *, camera=None, depth=None, device=None) -> np.ndarray:
    """Re-render the images (N, H, W, 3) from a result's normals and albedo with its material.

    Args:
        result: a :class:`PSResult`.
        lights: the lights used to solve.
        camera: the camera used (default orthographic).
        depth: (H, W) depth (needed for point lights; default ones).
    """

    h, w = result.mask.shape
    camera = Orthographic() if camera is None else camera
    dep = np.ones((h, w), np.float32) if depth is None else as_array("depth", depth, shape=(h, w))
    r = Renderer((h, w), camera, lights, result.material, device=device)
    nrm = result.normals.copy()
    bad = result.mask & (np.linalg.norm(nrm, axis=-1) < 0.5)
    nrm[bad] = (0.0, 0.0, 1.0)
    return r.run(np.where(result.mask, dep, 1.0), result.mask, np.maximum(result.albedo, 0.0), normals=nrm)
