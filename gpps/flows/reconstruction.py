"""``gpps.reconstruct``: the whole pipeline in one call (seed chapter 4).

Normals, RGB albedo, depth and the unknown material parameters from N >= 3
images with known lights::
    import gpps
    rec = gpps.reconstruct(images, mask, lights, camera=cam, material="cook-torrance")
    rec.normals, rec.albedo, rec.depth, rec.material, rec.estimated

Stages (each in :mod:`gpps.pipeline`, each usable alone): Lambertian least
squares, DGMC starts for highlight pixels (:mod:`gpps.host.dgmc`), then the
RON alternation (:mod:`gpps.flows.ron`: per-pixel normals and albedo by
Levenberg-Marquardt / dog leg / BFGS, Taichi Poisson integration, material
update; point-light directions recomputed from the depth every round).

Which material parameters are estimated: pass ``material`` as a model name
(``"blinn-phong"``) and every scene parameter of that model
(:data:`gpps.flows.ron.LOBE_PARAMETERS`: ``ks`` and the lobe width) is
estimated from the images; pass a :class:`gpps.material.Material` and its
parameters are used as known, unless ``estimate`` names some of them.  The
Fresnel ``f0`` of Cook-Torrance, Ashikhmin-Shirley and plastic (for plastic,
the coating's index of refraction) is never estimated (it trades off against
``ks`` with few images): the given or default value (0.5; plastic 0.04, index
1.5) is used and the result says so (``Reconstruction.fixed``).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from gpps._check import as_array, as_flags, as_mask, check_number, warn
from gpps._runtime import resolve_device
from gpps.flows.photometric import (
    WORKING_ALBEDO,
    WORKING_IMAGES,
    check_inputs,
    check_observations,
    detect_clipping,
    input_saturation,
    working_scale,
)
from gpps.flows.ron import LOBE_PARAMETERS, RON, RONConfig, default_integrator
from gpps.host.observations import gather_masked
from gpps.lights import DirectionalLights, PointLights
from gpps.material import BRDF_NAMES, Material, check_model_images
from gpps.names import MANY_IMAGES, SHADOW_RELATIVE_MANY
from gpps.pipeline.cpu_threads import submit
from gpps.pipeline.noise import noise_on_device
from gpps.pipeline.solver import estimate_noise

__all__ = ["reconstruct", "Reconstruction", "Reconstructor", "ResidentFrame", "RONConfig"]


@dataclass
class Reconstruction:
    """Output of :func:`reconstruct`.

    Attributes:
        normals: (H, W, 3) float32 unit normals, gpps frame, zeros outside the mask.
        albedo: (H, W, 3) float32 RGB albedo (diffuse kd).
        depth: (H, W) float32 depth (scene units, ``-z``), 0 outside ``depth_mask``;
            None when integration was switched off.  Perspective without a
            ``reference_depth``: known up to one scale (mean log-depth 0).
        mask: (H, W) bool pixels solved.
        depth_mask: (H, W) bool pixels with a depth.
        material: the material used at the end (estimated parameters filled in).
        estimated: ``{parameter: value}`` estimated from the images.
        fixed: parameters of the model that were neither given nor estimated
            (their default values were used).
        energy: model energy (mean squared residual) per RON round.
        rounds, converged: RON rounds run, and whether it stopped on its tolerance.
        residual, iterations, flags: per pixel, from the final normal solve.
        highlight: (H, W) bool DGMC highlight pixels.
        details: the full :class:`gpps.flows.ron.RONResult`.
        timings: seconds per stage and ``total``.
        determined: (H, W) bool pixels with 3 or more usable (lit, unsaturated) observations.
        warnings: messages of the :class:`gpps.GppsWarning` warnings issued (doubtful
            input, a material the images leave open, an estimate on its search bound, rounds that did not
            converge).
    """

    normals: np.ndarray
    albedo: np.ndarray
    depth: np.ndarray | None
    mask: np.ndarray
    depth_mask: np.ndarray
    material: Material
    estimated: dict
    fixed: dict
    energy: list
    rounds: int
    converged: bool
    residual: np.ndarray
    iterations: np.ndarray
    flags: np.ndarray
    highlight: np.ndarray
    details: object = None
    timings: dict = field(default_factory=dict)
    determined: np.ndarray | None = None
    warnings: list = field(default_factory=list)


def _material(material, estimate) -> tuple[Material, tuple[str, ...], dict, tuple[str, ...]]:
    models: tuple[str, ...] = ()
    if isinstance(material, (tuple, list)):
        if not material or not all(isinstance(b, str) for b in material):
            raise TypeError(f"material: expected a model name, a Material or a non-empty tuple of model names, "
                            f"got {material!r}")
        bad = [b for b in material if b not in BRDF_NAMES]
        if bad:
            raise ValueError(f"material: expected model names from {list(BRDF_NAMES)}, got {bad}")
        if estimate != "auto":
            raise ValueError(f"estimate: expected 'auto' with several models (each estimates its own lobe "
                             f"parameters), got {estimate!r}")
        models = tuple(material[1:])
        material = material[0]
    if isinstance(material, str):
        if material not in BRDF_NAMES:
            raise ValueError(f"material: expected a gpps.material.Material or one of {list(BRDF_NAMES)}, got {material!r}")
        mat = Material.default_for(material)
        names = LOBE_PARAMETERS[material] if estimate == "auto" else estimate
    elif isinstance(material, Material):
        mat = material
        names = () if estimate == "auto" else estimate
    else:
        raise TypeError(f"material: expected a gpps.material.Material or a model name, got {type(material).__name__}")
    if isinstance(names, str):
        names = (names,)
    if not isinstance(names, (tuple, list)) or not all(isinstance(k, str) for k in names):
        raise TypeError(f"estimate: expected 'auto', a parameter name or a sequence of them, got {estimate!r}")
    names = tuple(names)
    allowed = LOBE_PARAMETERS[mat.brdf]
    bad = [k for k in names if k not in allowed]
    if bad:
        raise ValueError(f"estimate: the {mat.brdf} model has the estimable parameters {list(allowed)}, got {bad}")
    # the Fresnel f0 of Cook-Torrance, Ashikhmin-Shirley and plastic (its index of refraction) is never
    # estimated: a model name uses the default
    fixed = {"f0": mat.f0} if isinstance(material, str) and mat.brdf in ("cook-torrance", "ashikhmin-shirley", "plastic") else {}
    return mat, names, fixed, models


def _scaled_material(mat: Material, scale: float) -> Material:
    """``mat`` for albedos times ``scale``: the image model is linear in the albedo and ks (both scale with the
    images over the radiance; the lobe's shape and Fresnel f0 do not)."""
    return replace(mat, ks=float(mat.ks) * scale)


def _unscaled_result(res, factor: float, s_images: float):
    """RON's result at the working scales (:func:`gpps.flows.photometric.working_scale`) in the caller's: the albedo
    and ks divided by ``factor`` (the working albedo over the caller's), the residuals by ``s_images`` and energies
    (squared residuals) by its square; normals, depth, flags and the lobe's shape are the same."""
    inv, res_inv, inv2 = 1.0 / factor, 1.0 / s_images, 1.0 / (s_images * s_images)
    fits = []
    for f in res.material_fit:
        f = dict(f)
        if "ks" in f.get("values", {}):
            f["values"] = {**f["values"], "ks": f["values"]["ks"] * inv}
        if f.get("energy") is not None:
            f["energy"] = f["energy"] * inv2
        if f.get("ambiguity") is not None:
            f["ambiguity"] = {**f["ambiguity"], "noise_var": f["ambiguity"]["noise_var"] * inv2}
        if "models" in f:  # (each compared model's sampled energy)
            f["models"] = {k: v * inv2 for k, v in f["models"].items()}
        if "evidence" in f:  # (the comparison's test: its energies are squared residuals, its ratios scale-free)
            f["evidence"] = {k: {**v, "energy_base": v["energy_base"] * inv2, "energy_other": v["energy_other"] * inv2}
                             for k, v in f["evidence"].items()}
        fits.append(f)
    ref = None
    if res.refinement is not None:
        ref = {**res.refinement, "energy": [v * inv2 for v in res.refinement["energy"]],
               "start_energy": res.refinement["start_energy"] * inv2, "sigma": res.refinement["sigma"] * res_inv}
    est = {k: (v * inv if k == "ks" else v) for k, v in res.estimated.items()}
    return replace(res, albedo=(res.albedo * np.float32(inv)).astype(res.albedo.dtype),
                   residual=(res.residual * np.float32(res_inv)).astype(res.residual.dtype),
                   energy=[e * inv2 for e in res.energy], material=_scaled_material(res.material, inv),
                   estimated=est, material_fit=fits, refinement=ref)


def reconstruct(
    images,
    mask,
    lights,
    *,
    camera=None,
    material: Material | str = "blinn-phong",
    estimate="auto",
    depth=None,
    reference_depth: float | None = None,
    valid=None,
    saturation: float | None = None,
    config: RONConfig | None = None,
    device=None,
    progress=None,
    start=None,
) -> Reconstruction:
    """Calibrated photometric stereo with DGMC starts and the RON alternation (Algorithm 2).

    Args:
        images: (N, H, W, 3) RGB or (N, H, W) grey images >= 0, N >= 3, divided by
            the light intensities when ``lights`` has unit intensities.  Any scale: far from an albedo
            and image scale of order one the solve runs on the images and intensities times powers of two
            (:func:`gpps.flows.photometric.working_scale`, with a warning), and the albedo, ks, residuals and
            energies come back in the images' scale.
        mask: (H, W) bool object mask.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N, scene units).
        camera: :class:`Orthographic` (default) or :class:`Perspective`.
        material: a model name (its scene parameters are estimated), a
            :class:`Material` (its parameters are known), or a tuple of model
            names (each one's parameters estimated in the first material fit,
            the model with the lowest sampled residual kept: ``RONConfig.models``;
            e.g. ``("cook-torrance", "plastic")``).
        estimate: ``"auto"`` (see above) or the names of parameters to estimate
            (``"ks"``, ``"shininess"``, ``"roughness"``, ``"eta"``).
        depth: (H, W) depth estimate (scene units > 0): for point lights, the
            loop's start (default flat at ``reference_depth``).
        reference_depth: the object's mean distance (scene units, > 0): fixes
            the depth's offset/scale; required for point lights without ``depth``.
        valid: optional (N, H, W) bool observations to use.  Without it and without ``saturation``, float
            images are searched for clipped observations (:func:`gpps.flows.photometric.detect_clipping`,
            :mod:`gpps.host.clipping`: per image and channel, a plateau of one value at the image's maximum
            that holds many more pixels than the next lower values and is not a flat, uniformly lit region,
            e.g. a sensor's full scale divided by the light's intensity, 1 / 0.8 = 1.25); those found are
            left out of every stage, with a warning that says how many and where.  uint8 / uint16 images
            need no search: an observation with a channel at their full scale is dropped from the fit (the
            camera clipped there), unless ``saturation`` says otherwise.
        saturation: observations with a channel >= this are dropped (e.g. the
            clipping level divided by the light intensity); given, no clipping is detected (see ``valid``).
        config: :class:`RONConfig` (its ``estimate`` is set from the arguments).
        device: Warp device (None: CUDA if present); the integrator runs on the same.
        progress: ``progress(done, total, message)``.
        start: optional earlier :class:`Reconstruction` of nearly the same images (or ``(normals, highlight)``):
            every pixel's solve starts warm from its normals, with no least squares, DGMC or cold starts
            (``RON.run``'s ``start``; the interreflection compensation's later reconstructions).

    Returns:
        :class:`Reconstruction`.

    Raises:
        ValueError / TypeError: bad shapes or values, unknown model or parameter
            names, fewer than 3 lights or degenerate light directions, point
            lights without a depth or a reference depth.
    """
    with ResidentFrame(images, mask, lights, camera=camera, material=material, estimate=estimate, depth=depth,
                       reference_depth=reference_depth, valid=valid, saturation=saturation, config=config,
                       device=device) as frame:
        return frame.run(progress=progress, start=start)


def _start_pair(start) -> tuple | None:
    """``start`` (a :class:`Reconstruction` or ``(normals, highlight)``) as the pair ``RON.run`` takes."""
    if start is not None and not isinstance(start, (tuple, list)):
        if not (hasattr(start, "normals") and hasattr(start, "highlight")):
            raise TypeError(f"start: expected a Reconstruction or (normals, highlight), got {type(start).__name__}")
        return (start.normals, start.highlight)
    if start is not None and len(start) != 2:
        raise ValueError(f"start: expected (normals, highlight), got {len(start)} items")
    return start


class ResidentFrame:
    """:func:`reconstruct` of one capture whose frame stays on the device for later solves of it as changed there.

    The interreflection compensation (:mod:`gpps.flows.interreflection`) reconstructs, gathers the light the
    surface sends itself and reconstructs the images less that light again.  Through :func:`reconstruct` the second
    reconstruction checks, scales, estimates the noise of and uploads the (N, H, W, 3) stack again, and builds the
    pipeline's stages again; here the stages and the frame of the first are kept: the compensation subtracts on the
    device, in the solver's buffer (:attr:`images`), and :meth:`again` solves it warm.  (DiLiGenT bear, 96 images,
    on an H200: the host's share of the second reconstruction was 0.4 s, perf/results/s40/README.md.)

    Args:
        images, mask, lights, camera, material, estimate, depth, reference_depth, valid, saturation, config, device:
            as :func:`reconstruct`'s (checked here, at construction).

    :meth:`run` is :func:`reconstruct`'s result; :meth:`again` re-solves the frame as changed on the device;
    :meth:`close` (or a ``with`` block) frees the stages.  One call at a time.
    """

    def __init__(self, images, mask, lights, *, camera=None, material: Material | str = "blinn-phong", estimate="auto",
                 depth=None, reference_depth: float | None = None, valid=None, saturation: float | None = None,
                 config: RONConfig | None = None, device=None):
        self._prep = _prepare(images, mask, lights, camera, material, estimate, depth, reference_depth, valid,
                              saturation, config, host_noise=not noise_on_device(device))
        self._ron = RON(self._prep.shape, self._prep.camera, self._prep.lights, self._prep.material, self._prep.mask,
                        self._prep.config, device=device)
        self._depth, self._reference = depth, reference_depth
        self.runs = 0  #: solves of the frame so far (:meth:`run` and :meth:`again`)
        self.timings: list[dict] = []  #: each solve's stage times (s), in order (:attr:`Reconstruction.timings`)

    @property
    def images(self):
        """The frame on the device: (N, H, W) ``wp.vec3`` images at the working scale (:attr:`scale` times the
        caller's); None before :meth:`run`."""
        return self._live().frame

    @property
    def scale(self) -> float:
        """The frame's values over the caller's images (:func:`gpps.flows.photometric.working_scale`; 1 for images
        of order one)."""
        return float(self._prep.scale["images"])

    @property
    def mask(self) -> np.ndarray:
        """(H, W) bool: the checked object mask."""
        return self._prep.mask

    def _live(self) -> RON:
        if self._ron is None:
            raise RuntimeError("ResidentFrame: closed")
        return self._ron

    def run(self, *, progress=None, start=None) -> Reconstruction:
        """:func:`reconstruct` of the images given at construction (``progress`` and ``start`` as its)."""
        ron = self._live()
        pair = _start_pair(start)
        p = self._prep
        res = ron.run(p.images, depth=self._depth, reference_depth=self._reference, valid=p.valid, progress=progress,
                      start=pair, noise=p.noise, checked=True)
        self.runs += 1
        out = _result(res, p)
        self.timings.append(dict(out.timings))
        return out

    def again(self, start: Reconstruction, *, progress=None) -> Reconstruction:
        """The frame as changed on the device since, solved again: ``start``'s material kept (nothing estimated),
        every pixel warm from its normals (``RON.rerun``); under point lights the rounds start from its depth (where it
        has one on the whole mask).

        Args:
            start: the last :class:`Reconstruction` of this frame (:meth:`run`'s or :meth:`again`'s).
            progress: ``progress(done, total, message)``.

        Returns:
            :class:`Reconstruction` (in the caller's scale, as :meth:`run`'s).

        Raises:
            RuntimeError: before :meth:`run`, or closed.
            TypeError: ``start`` is not a :class:`Reconstruction`.
        """
        ron = self._live()
        if not isinstance(start, Reconstruction):
            raise TypeError(f"start: expected a Reconstruction of this frame, got {type(start).__name__}")
        p = self._prep
        depth = self._depth
        if isinstance(p.lights, PointLights) and start.depth is not None and np.all(start.depth[p.mask] > 0):
            depth = start.depth
        # (the material in the working scale: Reconstruction's is in the caller's)
        material = _scaled_material(start.material, p.scale["images"] / p.scale["lights"])
        res = ron.rerun((start.normals, start.highlight), material, depth=depth, reference_depth=self._reference,
                        progress=progress)
        self.runs += 1
        out = _result(res, p)
        self.timings.append(dict(out.timings))
        return out

    def compile_ahead(self, kernels) -> None:
        """Warp kernels or modules of stages the caller launches after :meth:`run` (the interreflection
        compensation's), compiled ahead with the run's own on a first run (:meth:`gpps.flows.ron.RON.compile_ahead`)."""
        self._live().compile_ahead(kernels)

    def close(self) -> None:
        """Free the stages' buffers (later calls raise RuntimeError)."""
        if self._ron is not None:
            self._ron.close()
            self._ron = None

    def __enter__(self) -> "ResidentFrame":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class _Prepared:
    """A call's checked inputs at the working scale, and what its result needs (:func:`_prepare`)."""

    images: np.ndarray
    mask: np.ndarray
    lights: object
    camera: object
    material: Material
    config: RONConfig
    valid: np.ndarray | None
    notes: list
    determined: np.ndarray
    scale: dict
    fixed: dict
    models: tuple
    noise: np.ndarray | None = None  # (N,) the images' noise levels (estimate_noise), or None: the solver's upload

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(s) for s in self.images.shape[:3])


def _prepare(images, mask, lights, camera, material, estimate, depth, reference_depth, valid, saturation,
             config, *, host_noise: bool = True) -> _Prepared:
    """:func:`reconstruct`'s checks, its configuration of RON and the working scale; with ``host_noise`` (the
    solve's device estimates none itself: :func:`gpps.pipeline.noise.noise_on_device`) the images' noise levels
    too."""
    img, m, lights, camera = check_inputs(images, mask, lights, camera)  # (N >= 3 checked there)
    n, h, w = img.shape[:3]
    if saturation is not None:
        saturation = check_number("saturation", saturation, lo=0.0, lo_open=True)
    else:
        # uint8 / uint16 input: the camera clipped at its full scale (as_images scaled it to 1): dropped from the fit
        saturation = input_saturation(images)
    mat, names, fixed, models = _material(material, estimate)
    cfg = RONConfig() if config is None else config
    if not isinstance(cfg, RONConfig):
        raise TypeError(f"config: expected RONConfig, got {type(cfg).__name__}")
    if cfg.material_rule == "depth-rms":
        names = tuple(k for k in names if k == "roughness")
    solver = cfg.solver
    if saturation is not None:
        solver = replace(solver, saturation=float(saturation))
    if n > MANY_IMAGES and solver.robust == "none" and config is None:
        # observations beyond the fit's three unknowns to judge outliers by (cast shadows, interreflections):
        # robust loss, shadow dropping and the cast-shadow refit (gpps.names.MANY_IMAGES)
        solver = replace(solver, robust="cauchy", shadow_threshold=0.02, shadow_relative=SHADOW_RELATIVE_MANY,
                         starts=min(solver.starts, 4))
    cfg = replace(cfg, estimate=names, solver=solver, **({"models": models} if models else {}))
    if saturation is not None and cfg.dgmc_config.saturation is None:
        cfg = replace(cfg, dgmc_config=replace(cfg.dgmc_config, saturation=float(saturation)))
    val = None if valid is None else as_flags("valid", valid, (n, h, w))
    ref = reference_depth
    if ref is None and depth is not None:
        ref = float(np.mean(as_array("depth", depth, shape=(h, w))[m]))
    notes: list[str] = []
    # beside the checks, on the shared CPU pool: the working scale and, where the solver's device does not estimate
    # them (host_noise), the frame's noise levels (the solver's upload takes these: estimate_noise of the same
    # images; kept only at the working scale 1, where they are the images the solver gets)
    ws_job = submit(working_scale, img, m, lights, reference_depth=ref)
    noise_job = submit(estimate_noise, img, m) if cfg.solver.noise_level is None and host_noise else None
    # the mask's observations gathered once, for the clipping detection and the observation checks
    img4 = img if img.ndim == 4 else img[..., None]
    idx = np.flatnonzero(m)
    gathered = (idx, gather_masked(img4, idx))
    # (float images without saturation= or valid=: observations clipped at any level left out, with a warning)
    val, clipped = detect_clipping(images, img4, m, saturation=saturation, valid=val, sink=notes, gathered=gathered)
    determined = check_observations(img, m, lights, valid=val, saturation=input_saturation(images, saturation),
                                    reference_depth=ref, sink=notes, clipped=clipped, gathered=gathered)
    check_model_images((mat.brdf, *models), n, sink=notes)
    # images or albedos far from order one: solved at powers of two times their scales (working_scale)
    ws = ws_job.result()
    noise = noise_job.result() if noise_job is not None and ws["images"] == 1.0 else None
    factor = ws["images"] / ws["lights"]  # (the working albedo and ks over the caller's)
    if ws["images"] != 1.0 or ws["lights"] != 1.0:
        warn(f"images: their scale {ws['image_scale']:.3g} (brightest values) and albedo scale "
             f"{ws['albedo_scale']:.3g} (brightest values over the lights' radiance) lie outside "
             f"[{WORKING_IMAGES[0]:g}, {WORKING_IMAGES[1]:g}] and [{WORKING_ALBEDO[0]:g}, {WORKING_ALBEDO[1]:g}] "
             f"where the pipeline's constants hold; solved with the images times {ws['images']:g} and the "
             f"lights' intensities times {ws['lights']:g} (exact), albedo, ks and residuals returned in the images' "
             "scale (other warnings' ks values and search bounds are at the working scale)", notes)
        img = img * np.float32(ws["images"])
        lights = replace(lights, intensities=np.asarray(lights.intensities, np.float64) * ws["lights"])
        mat = _scaled_material(mat, factor)
        sv = cfg.solver.saturation
        cfg = replace(cfg, solver=replace(cfg.solver, saturation=None if sv is None else float(sv) * ws["images"]))
        if cfg.dgmc_config.saturation is not None:
            cfg = replace(cfg, dgmc_config=replace(cfg.dgmc_config,
                                                   saturation=float(cfg.dgmc_config.saturation) * ws["images"]))
    return _Prepared(images=img, mask=m, lights=lights, camera=camera, material=mat, config=cfg, valid=val,
                     notes=notes, determined=determined, scale=ws, fixed=fixed, models=models, noise=noise)


def _result(res, prep: _Prepared) -> Reconstruction:
    """RON's result in the caller's scale, as a :class:`Reconstruction`."""
    ws = prep.scale
    if ws["images"] != 1.0 or ws["lights"] != 1.0:
        res = _unscaled_result(res, ws["images"] / ws["lights"], ws["images"])
    return Reconstruction(
        normals=res.normals, albedo=res.albedo, depth=res.depth, mask=prep.mask, depth_mask=res.depth_mask,
        material=res.material, estimated=res.estimated,
        fixed=_material(res.material.brdf, "auto")[2] if prep.models else prep.fixed, energy=res.energy,
        rounds=res.rounds, converged=res.converged, residual=res.residual, iterations=res.iterations, flags=res.flags,
        highlight=res.highlight, details=res, timings=res.timings, determined=prep.determined,
        warnings=prep.notes + list(res.warnings),
    )


def kept_stages_config(config: RONConfig, camera) -> RONConfig:
    """``config`` with the integrator's multigrid CG launched ``"auto"``: one persistent Taichi task a solve on CUDA
    (:class:`gpps.pipeline.integration.IntegratorConfig`), the fused launches on the CPU.  ``camera``: the call's
    (a config without an integrator gets RON's default for it, :func:`gpps.flows.ron.default_integrator`).

    :class:`Reconstructor`'s choice when it is given no config (applied to the config :func:`reconstruct` would
    run).  The persistent task is compiled for a frame size (about 10 s on an H200, once
    per size and installation: Taichi's offline cache keeps it) and then saves the host's launches of every CG
    iteration (about 5 ms a 256^2 call on an H200, perf/results/s43 and s44): a cost a kept set-up, whose frames
    share one size, pays once, and a one-off :func:`reconstruct` at a new size would pay every time.
    """
    integ = config.integrator if config.integrator is not None else default_integrator(camera)
    return replace(config, integrator=replace(integ, launch="auto"))


class Reconstructor:
    """:func:`reconstruct` for one fixed capture set-up, called again and again: the stages are kept between calls.

    A production line, a turntable or a lab rig takes capture after capture with the same lights, camera and
    object mask.  :func:`reconstruct` builds the pipeline's stages (:class:`gpps.flows.ron.RON`: the pixel solvers'
    buffers, the integrator's Taichi fields, the material scorer, the device search and its CUDA graphs) for every
    call and frees them after; a ``Reconstructor`` builds them at its first call and keeps them, so each later call
    pays only for its own work.  The results are those of :func:`reconstruct` with the same arguments, bit for bit
    (tests/test_reconstructor.py), with one exception: without a ``config``, on CUDA, the integrator's CG runs as one
    persistent task a solve (:func:`kept_stages_config`: compiled once per frame size, then no launch an
    iteration), which sums its dot products in another order, so the depth's last bits (and, where the depth feeds
    back: point lights, cast shadows, the depth-rms rule, the normals' last bits) may differ from
    :func:`reconstruct`'s.  On the CPU, and with a ``config``, there is no exception.

    The stages are rebuilt, once, when a call's working scale (:func:`gpps.flows.photometric.working_scale`) or its
    ``saturation`` differs from the previous call's: both enter the stages' lights, material and settings.

    Args:
        mask: (H, W) bool object mask, the same for every call.
        lights: :class:`gpps.DirectionalLights` or :class:`gpps.PointLights` (N).
        camera, material, estimate, config, device: as :func:`reconstruct`.

    Call it with what varies per capture: ``rec = reconstructor(images, depth=..., reference_depth=..., valid=...,
    saturation=..., progress=...)`` -> :class:`Reconstruction` (the arguments as :func:`reconstruct`'s; ``images``
    (N, H, W, 3) or (N, H, W)).  One call at a time (not thread-safe).  :meth:`close` (or a ``with`` block) gives
    the device buffers back; a closed reconstructor refuses calls.

    Example::

        with gpps.Reconstructor(mask, lights, camera=cam, material="cook-torrance", device="cuda:0") as rc:
            for images in captures:
                rec = rc(images)
    """

    def __init__(self, mask, lights, *, camera=None, material: Material | str = "blinn-phong", estimate="auto",
                 config: RONConfig | None = None, device=None):
        if not isinstance(lights, (DirectionalLights, PointLights)):
            raise TypeError(f"lights: expected gpps.DirectionalLights or gpps.PointLights, got {type(lights).__name__}")
        self.mask = as_mask("mask", mask)
        self.lights = lights
        self.camera = camera
        self.material = material
        self.estimate = estimate
        if config is not None and not isinstance(config, RONConfig):
            raise TypeError(f"config: expected RONConfig, got {type(config).__name__}")
        self.config = config
        _material(material, estimate)  # (bad names fail here, not at the first call)
        self.device = resolve_device(device)
        self._ron = None
        self._key = None
        self.builds = 0  #: how many times the stages were built
        self._closed = False

    def __call__(self, images, *, depth=None, reference_depth: float | None = None, valid=None,
                 saturation: float | None = None, progress=None) -> Reconstruction:
        """One capture: :func:`reconstruct` with this set-up's mask, lights, camera, material and config.

        Args:
            images: (N, H, W, 3) or (N, H, W) images, as :func:`reconstruct`'s.
            depth, reference_depth, valid, saturation, progress: as :func:`reconstruct`'s.

        Returns:
            :class:`Reconstruction`.

        Raises:
            RuntimeError: the reconstructor is closed.
            ValueError / TypeError: as :func:`reconstruct`.  A call that fails inside the pipeline drops the kept
                stages (the next call builds them again).
        """
        if self._closed:
            raise RuntimeError("Reconstructor: closed")
        prep = _prepare(images, self.mask, self.lights, self.camera, self.material, self.estimate, depth,
                        reference_depth, valid, saturation, self.config, host_noise=not noise_on_device(self.device))
        if self.config is None:  # (after _prepare's rules for a call without a config)
            prep = replace(prep, config=kept_stages_config(prep.config, prep.camera))
        ron = self._stages(prep)
        try:
            res = ron.run(prep.images, depth=depth, reference_depth=reference_depth, valid=prep.valid,
                          progress=progress, noise=prep.noise, checked=True)
        except BaseException:
            ron.close()  # (a run cut short may leave its stages half-stepped: not kept)
            self._ron = self._key = None
            raise
        return _result(res, prep)

    def _stages(self, prep: _Prepared) -> RON:
        """The kept RON when this call's stages would be the same (shape, settings, material and lights' radiance
        at the working scale), else a new one (the old one closed)."""
        key = (prep.shape, prep.config, prep.material)
        inten = np.asarray(prep.lights.intensities)
        if self._ron is not None and self._key[0] == key and np.array_equal(self._key[1], inten):
            return self._ron
        if self._ron is not None:
            self._ron.close()
            self._ron = None
        self._ron = RON(prep.shape, prep.camera, prep.lights, prep.material, prep.mask, prep.config,
                        device=self.device)
        self._key = (key, inten.copy())
        self.builds += 1
        return self._ron

    def close(self) -> None:
        """Give the stages' buffers back (:meth:`gpps.flows.ron.RON.close`); later calls raise RuntimeError."""
        if self._ron is not None:
            self._ron.close()
            self._ron = None
        self._closed = True

    def __enter__(self) -> "Reconstructor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
