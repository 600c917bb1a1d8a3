"""Photometric stereo on a capture folder as users have it: read, solve (calibrated or not), integrate, report.

:func:`reconstruct_folder` is what ``gpps reconstruct`` runs.  It reads the folder with
:func:`gpps.io.capture.read_capture` (any image format, optional light files, mask, K.txt, ambient
image, ground truth), then

* **uncalibrated** (no light files, or ``FolderConfig(uncalibrated=True)``): leaves out nearly dark
  images (failed captures), estimates the lights from the pixels lit in enough images
  (:func:`gpps.flows.uncalibrated.solve_uncalibrated`), takes the convex member of the convex/concave
  pair when the images cannot tell them apart (:func:`flip_decision`) and solves the rest of the mask
  by Lambertian least squares under the estimated lights;
* **calibrated**: builds the material from ``material.json`` and the given parameters, decides which
  parameters to estimate, the reference depth (given, else the ground truth's mean depth for
  perspective cameras or point lights) and the saturated observations, and runs one of the methods
  ``"ron"`` (:func:`gpps.flows.reconstruction.reconstruct`), ``"ppn"``
  (:func:`gpps.flows.photometric.solve_normals`) or ``"pps"``
  (:func:`gpps.host.perspective.pps_blinn_phong`), with the solver options of
  :func:`automatic_solver_options` (a robust loss and more starts with many images);

and finally integrates the normals into depth where the method did not, states the depth convention
(:func:`gpps.io.outputs.depth_convention`) and the errors against ``normal_gt.npy``.
:meth:`FolderResult.write` writes the output set (:data:`gpps.io.outputs.OUTPUT_FILES`), the estimated
lights and ``report.json`` into a folder.
"""

from __future__ import annotations

import importlib.util
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Literal

import numpy as np

from gpps._check import GppsWarning, as_path, check_bool, check_choice, check_choices, check_number
from gpps._runtime import resolve_device
from gpps.camera import Orthographic, Perspective, camera_from_K
from gpps.flows.integrate import integrate_normals
from gpps.flows.photometric import solve_normals
from gpps.flows.reconstruction import reconstruct
from gpps.flows.ron import LOBE_PARAMETERS, MaterialRule, RONConfig
from gpps.flows.uncalibrated import UncalibratedConfig, solve_uncalibrated
from gpps.host.automask import lit_pixels
from gpps.host.gbr import dark_images
from gpps.host.metrics import flag_counts, normal_errors
from gpps.host.perspective import pps_blinn_phong
from gpps.io import atomic_write, save_json
from gpps.io.capture import Capture, read_capture
from gpps.io.formats import Transfer
from gpps.io.outputs import apply_depth_convention, depth_convention, write_outputs
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.names import (BRDF, BRDF_NAMES, CONDUCTOR_MIN_IMAGES, INTERREFLECTION_MIN_IMAGES, MANY_IMAGES,
                        SHADOW_RELATIVE_MANY, InterreflectionName, RobustName, SolverName)
from gpps.pipeline.integration import IntegratorConfig
from gpps.pipeline.interreflection import Interreflections

__all__ = ["FolderConfig", "FolderResult", "reconstruct_folder", "automatic_solver_options", "flip_decision",
           "MANY_IMAGES", "REFINE_IMAGES", "CONDUCTOR_IMAGES", "AUTOMATIC_MODELS", "automatic_refine", "automatic_models",
           "automatic_interreflections",
           "ESTIMATED_FILES"]

FolderMethod = Literal["ron", "ppn", "pps"]
FolderIntegration = Literal["bini", "poisson"]
Progress = Callable[[float, float, str], None]


REFINE_IMAGES = 3
"""With this many images RON's depth refinement runs unless the caller says otherwise (:func:`automatic_refine`)."""

CONDUCTOR_IMAGES = CONDUCTOR_MIN_IMAGES
"""From this many images the folder flow also fits the rough conductor (a metal) and the plastic model in RON's first
material fit and keeps one where its residual is lower beyond the sample's noise (:func:`automatic_models`)."""

AUTOMATIC_MODELS: tuple[str, ...] = ("conductor", "plastic")
"""The models the automatic policy compares from :data:`CONDUCTOR_IMAGES` images on (:func:`automatic_models`)."""

ESTIMATED_FILES = ("lights_estimated.txt", "light_intensities_estimated.txt", "filenames_used.txt")
"""The files an uncalibrated result writes beside the output set (:meth:`FolderResult.write`)."""


@dataclass(frozen=True)
class FolderConfig:
    """Settings of :func:`reconstruct_folder` (the options of ``gpps reconstruct``).

    Attributes:
        transfer: the images' transfer curve: ``"auto"`` decodes sRGB for JPEG only.
        max_size: downscale images whose longer side exceeds this many pixels (K scaled with them);
            None: full size.
        uncalibrated: estimate the lights even when light files are present (without them this is
            automatic).
        method: ``"ron"``: least squares, DGMC starts, RON rounds of normals/albedo/depth/material;
            ``"ppn"``: one per-pixel solve with the material known, then integration; ``"pps"``:
            perspective Blinn-Phong in log depth (perspective camera, directional lights).
        brdf: reflectance model; None: ``material.json``'s, else ``"blinn-phong"``.
        solver: per-pixel solver (``"none"``: Lambertian least squares).
        robust: robust loss; None: the automatic policy of :func:`automatic_solver_options`
            (``"cauchy"`` with more than :data:`MANY_IMAGES` images, ``"none"`` otherwise).
        ks, shininess, roughness, f0: known material parameters (unitless; ``shininess`` the
            Phong/Blinn-Phong exponent, ``roughness`` Cook-Torrance's m); None: estimated with
            ``method="ron"``, else the model's default (``f0`` is never estimated).
        eta: known Ashikhmin-Shirley exponent ``eta_u = eta_v``; None: estimated (as above).
        known_material: use ``material.json``'s parameters as known (no estimation).
        dgmc: RON: DGMC starts for highlight pixels.
        integrate: compute depth (integration, mesh).
        integration: the returned depth: ``"bini"``: bilateral normal integration of the final
            normals (keeps discontinuities); ``"poisson"``: one least-squares solve.
        estimate: RON: estimate the material parameters not given.
        rounds: RON's round cap (>= 1).
        material_rule: RON's material update (``"depth-rms"``: the seed's 4.19).
        models: RON: other reflectance models to compare with ``brdf`` by their fit residual in the first
            material fit (``RONConfig.models``; e.g. ``("plastic",)``; ``()``: none); only when every lobe
            parameter is estimated (no known parameters given, the photometric rule), else ignored with the
            report saying so.  None (default): the automatic policy of :func:`automatic_models` (the rough
            conductor and plastic from :data:`CONDUCTOR_IMAGES` images on, each kept only on evidence).
        cast_shadows: RON: leave observations in cast shadows (marched over each round's depth) out of the
            next round's fit (``RONConfig.cast_shadows``; off by default, see there).
        refine: RON: refine the depth itself after the rounds (robust misfit over every observation, normals
            tied to the surface: ``RONConfig.refine``); None (default): the automatic policy of
            :func:`automatic_refine` (on with :data:`REFINE_IMAGES` images, off with more).
        two_light: where the refinement runs, also from the surface the two-light pixels fix (shadows with 3
            directional lights), keeping the likelier refined surface (``RONConfig.refine_two_light``; default
            on; ``report["refinement"]`` then has each start's likelihood and the one ``chosen``).
        interreflections: RON: ``"subtract"`` takes the diffuse interreflections gathered over the
            reconstructed surface out of the images and reconstructs again (:mod:`gpps.flows.interreflection`;
            ``interreflection_rounds`` times; with models compared, the later reconstructions keep the model
            the first chose; none where the surface sends itself no light, a convex object, or where the model
            chosen is the conductor); ``"off"`` not; ``"auto"`` (default): the policy of
            :func:`automatic_interreflections` (subtract from :data:`gpps.names.INTERREFLECTION_MIN_IMAGES`
            images on).
        interreflection_rounds: compensation rounds (>= 1), each one gather and one more reconstruction.
        albedo_scale: the physical albedo over the estimated one for the compensation (> 0; 1 when the light
            intensities are radiometric; lowered where it would make the albedo exceed 1, and the compensation
            skipped with a warning where the albedo would exceed 1.5: a glossy or metallic surface).  None
            (default): the intensities' scale is unknown (relative, as most captures' and DiLiGenT's): the
            brightest pixels' albedo is taken as :data:`gpps.names.ASSUMED_BRIGHT_ALBEDO`
            (:func:`gpps.flows.interreflection.reconstruct_subtracting`).
        pixel_size: orthographic camera (no K.txt): scene units per pixel; None: depth in pixels.
        reference_depth: mean object distance (scene units): sets the depth's scale; needed for point
            lights unless the folder has ``depth_gt.npy``.
    """

    transfer: Transfer = "auto"
    max_size: int | None = None
    uncalibrated: bool = False
    method: FolderMethod = "ron"
    brdf: BRDF | None = None
    solver: SolverName = "lm"
    robust: RobustName | None = None
    ks: float | None = None
    shininess: float | None = None
    roughness: float | None = None
    eta: float | None = None
    f0: float | None = None
    known_material: bool = False
    dgmc: bool = True
    integrate: bool = True
    integration: FolderIntegration = "bini"
    estimate: bool = True
    rounds: int = 5
    material_rule: MaterialRule = "photometric"
    pixel_size: float | None = None
    reference_depth: float | None = None
    models: tuple[str, ...] | None = None
    cast_shadows: bool = False
    refine: bool | None = None
    two_light: bool = True
    interreflections: InterreflectionName = "auto"
    interreflection_rounds: int = 1
    albedo_scale: float | None = None

    def __post_init__(self):
        check_choices(self)
        object.__setattr__(self, "interreflection_rounds",
                           check_number("interreflection_rounds", self.interreflection_rounds, lo=1, integer=True))
        if self.albedo_scale is not None:
            object.__setattr__(self, "albedo_scale", check_number("albedo_scale", self.albedo_scale, lo=0.0,
                                                                  lo_open=True))
        if self.interreflections == "subtract" and (self.method != "ron" or not self.integrate
                                                    or self.solver == "none"):
            raise ValueError("interreflections: gathers over RON's depth, expected method='ron', integrate=True and "
                             f"a solver, got method={self.method!r}, integrate={self.integrate}, solver={self.solver!r}")
        check_bool("cast_shadows", self.cast_shadows)
        if self.refine is not None:
            check_bool("refine", self.refine)
        check_bool("two_light", self.two_light)
        if self.refine and not self.integrate:
            raise ValueError("refine: refines the integrated depth, expected integrate=True, got integrate=False")
        if self.models is not None:
            if not isinstance(self.models, (tuple, list)) or not all(isinstance(b, str) for b in self.models):
                raise TypeError(f"models: expected None or a tuple of reflectance model names, got {self.models!r}")
            object.__setattr__(self, "models", tuple(self.models))
            for b in self.models:
                check_choice("models", b, BRDF_NAMES)
        for name in ("uncalibrated", "known_material", "dgmc", "integrate", "estimate"):
            check_bool(name, getattr(self, name))
        object.__setattr__(self, "rounds", check_number("rounds", self.rounds, lo=1, integer=True))
        if self.max_size is not None:
            object.__setattr__(self, "max_size", check_number("max_size", self.max_size, lo=1, integer=True))
        for name in ("pixel_size", "reference_depth"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check_number(name, getattr(self, name), lo=0.0, lo_open=True))
        for name in ("ks", "shininess", "roughness", "eta", "f0"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, check_number(name, getattr(self, name)))
        if self.given_material():  # their ranges, by the material's own checks (before any image is read)
            try:
                Material.from_dict({**Material.default_for(self.brdf or "blinn-phong").to_dict(),
                                    **self.given_material()})
            except (ValueError, TypeError) as e:  # (eta is Material's eta_u and eta_v)
                msg = str(e)
                raise type(e)("eta" + msg[5:] if msg.startswith(("eta_u", "eta_v")) else msg) from None

    def given_material(self) -> dict:
        """The material parameters given (not None), as :meth:`gpps.Material.to_dict` keys (eta: eta_u, eta_v)."""
        given = {k: getattr(self, k) for k in ("ks", "shininess", "roughness", "f0") if getattr(self, k) is not None}
        if self.eta is not None:
            given.update(eta_u=self.eta, eta_v=self.eta)
        return given


@dataclass
class FolderResult:
    """What :func:`reconstruct_folder` found.

    Attributes:
        normals: (H, W, 3) float32 unit normals, gpps frame, 0 outside ``mask``.
        albedo: (H, W, 3) float RGB albedo (linear, as estimated).
        mask: (H, W) bool, the object's pixels (read or automatic).
        depth: (H, W) float depth ``d = -z`` in ``depth_info``'s convention (NaN outside
            ``depth_mask``); None without integration.
        depth_mask: (H, W) bool where ``depth`` is defined; None without depth.
        camera: the camera (perspective from K.txt, else orthographic with ``pixel_size``).
        depth_info: the depth convention (:func:`gpps.io.outputs.depth_convention`); None without depth.
        lights: the lights used: read (directional or point), or estimated (directional, one per
            image used, the flip applied).
        uncalibrated: whether the lights were estimated.
        light_directions: uncalibrated: (N_used, 3) unit directions toward the estimated lights as
            written to ``lights_estimated.txt``; None when calibrated.
        light_intensities: uncalibrated: (N_used, 3) relative RGB intensities (mean 1); None when calibrated.
        images_used: uncalibrated: the file names of the images used, in order; calibrated: all.
        report: the ``report.json`` entries known after the solve (the outputs, the total time and
            the warnings are added by :meth:`write`).
        started: ``time.perf_counter()`` when the flow started (the report's total time counts from it).
        flags: (H, W) int32 the per-pixel solver's flag bits (:data:`gpps.names.FLAG_NAMES`; 0 outside ``mask``),
            written as ``flags.npy``; None where no per-pixel solver ran (method ``"pps"``, uncalibrated).
            ``report["flag_counts"]`` counts the mask's pixels by flag name.
    """

    normals: np.ndarray
    albedo: np.ndarray
    mask: np.ndarray
    depth: np.ndarray | None
    depth_mask: np.ndarray | None
    camera: Orthographic | Perspective
    depth_info: dict | None
    lights: DirectionalLights | PointLights
    uncalibrated: bool
    light_directions: np.ndarray | None = None
    light_intensities: np.ndarray | None = None
    images_used: list[str] = field(default_factory=list)
    report: dict = field(default_factory=dict)
    started: float = field(default_factory=time.perf_counter)
    flags: np.ndarray | None = None

    def write(self, folder, *, warnings: list[str] | None = None, started: float | None = None) -> dict:
        """Write the output set, the estimated lights (uncalibrated) and ``report.json`` into ``folder``.

        ``folder`` is written as is: give it a temporary folder of :func:`gpps.io.atomic_dir` so that
        the result appears complete or not at all.

        Args:
            folder: an existing folder.
            warnings: the warning messages to record in ``report.json`` (``"warnings"``).
            started: ``time.perf_counter()`` value the report's ``timings["total"]`` (s) counts from;
                None: :attr:`started`.

        Returns:
            The report as written (``report`` with ``outputs``, ``view``, ``timings["total"]`` and
            ``warnings`` added).
        """
        folder = Path(folder)
        written = write_outputs(folder, normals=self.normals, albedo=self.albedo, mask=self.mask, depth=self.depth,
                                depth_mask=self.depth_mask, camera=self.camera, depth_info=self.depth_info,
                                flags=self.flags)
        if self.uncalibrated:
            hdr = ("gpps uncalibrated estimate, one row per image used (images_used in report.json, in order): "
                   "{}; gpps frame: x right, y up, z toward the camera")
            _save_rows(folder / ESTIMATED_FILES[0], self.light_directions, hdr.format("unit directions toward the lights"))
            _save_rows(folder / ESTIMATED_FILES[1], self.light_intensities, hdr.format("relative RGB intensities (mean 1)"))
            (folder / ESTIMATED_FILES[2]).write_text("\n".join(self.images_used) + "\n")
            written["files"] += list(ESTIMATED_FILES)
        report = self.report
        report["outputs"] = written["files"]
        if "view" in written:
            report["view"] = written["view"]
        report.setdefault("timings", {})["total"] = time.perf_counter() - (self.started if started is None else started)
        report["warnings"] = list(warnings or [])
        save_json(folder / "report.json", report)
        return report


def _save_rows(path, rows, header: str) -> None:
    """``rows`` as a text matrix (``%.9g``, one row a line) under a ``#`` header, written atomically."""
    with atomic_write(path) as tmp:
        np.savetxt(tmp, np.atleast_2d(np.asarray(rows, np.float64)), fmt="%.9g", header=header)


def automatic_solver_options(n_images: int, robust: RobustName | None = None) -> dict:
    """The per-pixel solver options the folder flow uses for ``n_images`` images.

    With more than :data:`gpps.names.MANY_IMAGES` (3) images some observations are expected to be outliers
    (cast shadows, interreflections, highlights the model misses): the loss is Cauchy, observations
    below 0.02 of the pixel's brightest count as shadowed, a pixel whose fit contradicts its split into lit
    and dark observations (dark: below :data:`gpps.names.SHADOW_RELATIVE_MANY` of its lit level) is solved
    again with the dark ones set aside (``SolverConfig.shadow_relative``), and each pixel is started from 4
    normals.  With 3, every observation is needed (none beyond the three unknowns to judge a dark one against):
    no robust loss, the solver's defaults, and the neighbour pass's attached / cast shadow choice.

    Args:
        n_images: the number of images N.
        robust: a loss to use instead of the automatic one (None: automatic).

    Returns:
        ``{"robust": ...}``, plus ``shadow_threshold``, ``shadow_relative`` and ``starts`` with many images: keyword
        arguments of :func:`gpps.flows.photometric.solve_normals` and fields of :class:`gpps.SolverConfig`.
    """
    many = n_images > MANY_IMAGES
    opts = {"robust": robust or ("cauchy" if many else "none")}
    if many:
        opts.update(shadow_threshold=0.02, shadow_relative=SHADOW_RELATIVE_MANY, starts=4)
    return opts


def automatic_refine(n_images: int, config: FolderConfig, device: str) -> tuple[bool, str]:
    """Whether the folder flow runs RON's depth refinement (``RONConfig.refine``), and why.

    The caller's ``config.refine`` decides when given.  Otherwise the refinement runs with exactly
    :data:`REFINE_IMAGES` images.  Principle: with three images each pixel's fit has no redundancy (three
    observations per channel for a normal's two angles and an albedo), so a cast shadow, light bounced between
    parts or a misfitting model moves the normal freely, and a material the three images cannot identify (of a
    grey object every candidate fits each pixel) bends every normal; tying the normals to one surface is then the
    only redundancy there is.  With more images the per-pixel fits are over-determined and the surface's limits (a relief of
    one-pixel facets cannot be held by a surface on the pixel grid) cost more than it adds
    (``RONConfig.refine``).  Measured on our own Mitsuba development captures only (perf/results/s18/README.md;
    3 lights, 128^2, 16-bit): seeds 3000-3009, 10 directional and 10 point captures, non-diffuse means 16.34 ->
    14.05 deg (directional) and 24.40 -> 17.02 (point) against least squares' 15.38 / 17.96, better on 15 of 20;
    the rough conductors, where the unrefined pipeline was far worse than least squares (point: 58.8 and 52.9
    against 32.5 and 17.8), come back to least squares' level; it loses 0.2-2.3 deg on 5 (the stepped pyramid
    twice, under point lights the sphere standing on a plane, the five spheres and the superquadric).  It needs RON with a nonlinear solver and the integrated depth, and on CUDA
    PyTorch (the ``gpps[cuda]`` extra): without it the refinement is skipped and the reason reported.

    Args:
        n_images: the number of images N.
        config: the folder flow's settings.
        device: the resolved device (``"cpu"``, ``"cuda:0"``, ...).

    Returns:
        ``(on, reason)``: ``reason`` says which rule decided (for the report).
    """
    if config.refine is False:
        return False, "turned off"
    if config.method != "ron" or config.solver == "none" or not config.integrate:
        return False, ("asked, but " if config.refine else "automatic: ") + (
            "it needs RON's rounds with a nonlinear solver and the integrated depth")
    if config.refine:
        return True, "asked"
    if n_images != REFINE_IMAGES:
        return False, f"automatic: off with {n_images} images (on with {REFINE_IMAGES})"
    if str(device).startswith("cuda") and importlib.util.find_spec("torch") is None:
        return False, ("automatic: skipped on CUDA without PyTorch (pip install 'gpps[cuda]'): results differ from "
                       "the CPU's, which refines with 3 images")
    return True, f"automatic: on with {REFINE_IMAGES} images"


def automatic_interreflections(n_images: int, config: FolderConfig) -> tuple[bool, str]:
    """Whether the folder flow takes the interreflections out of the images (:mod:`gpps.flows.interreflection`),
    and why.

    The caller's ``config.interreflections`` decides when ``"off"`` or ``"subtract"``.  ``"auto"`` subtracts from
    :data:`gpps.names.INTERREFLECTION_MIN_IMAGES` images on, with RON, a nonlinear solver and the integrated depth
    (the gather runs over RON's surface).  Principle: every concave surface lights itself, and a per-pixel fit
    bends its normals toward the light its walls send each other; the compensation sends the fitted diffuse albedo's
    light, which from that many images is a diffuse albedo (the models compared: plastic's is the one under its
    coating; a metal, the conductor, is skipped), and where the surface sends itself nothing (a convex object) it
    stops after one gather.  The light's scale is taken from :data:`gpps.names.ASSUMED_BRIGHT_ALBEDO` unless
    ``config.albedo_scale`` is given.

    Measured (perf/results/s39/README.md; our Mitsuba development captures, seeds 3000-3009, which chose nothing
    but the rule's form; the held-out captures and DiLiGenT ran after): the compensation's result against its scale
    follows ``|rho - a|`` (the light left in): with 12 lights at half and at the true scale every concave non-metal
    capture better than without it, at twice it (the break-even) one of the four not skipped worse.  By default
    (5, 6 and 12 lights): development non-diffuse 12-light mean 3.83 -> 3.46 deg, the held-out captures 39 of 48
    better and none worse by more than 0.05 deg; DiLiGenT bear (96 images) 4.49 -> 4.01, ball unchanged.

    Args:
        n_images: the number of images N.
        config: the folder flow's settings.

    Returns:
        ``(on, reason)``: ``reason`` says which rule decided (for the report).
    """
    if config.interreflections == "off":
        return False, "turned off"
    if config.interreflections == "subtract":
        return True, "asked"
    if config.method != "ron" or config.solver == "none" or not config.integrate:
        return False, "automatic: it gathers over RON's integrated depth (method ron, a nonlinear solver, integrate)"
    if n_images < INTERREFLECTION_MIN_IMAGES:
        return False, f"automatic: off with {n_images} images (on from {INTERREFLECTION_MIN_IMAGES})"
    return True, f"automatic: on from {INTERREFLECTION_MIN_IMAGES} images"


def automatic_models(n_images: int, config: FolderConfig) -> tuple[tuple[str, ...], str]:
    """The reflectance models RON's first material fit compares with ``config.brdf`` (``RONConfig.models``), and why.

    The caller's ``config.models`` decides when given (``()``: none).  Otherwise, from :data:`CONDUCTOR_IMAGES`
    images on, the rough conductor and the plastic (dielectric coating) model, each kept only when its sampled
    energy is lower than the configured model's beyond the sample's noise
    (:func:`gpps.host.model_evidence.energy_drop_evidence`, session 33).

    The conductor: a metal has no diffuse term, which neither the seed's models nor plastic can
    drop, and the residual tells the two classes apart once the conductor's own per-pixel fit (a normal and a
    colour, nothing but the lobe to see them by) is determined.  With fewer images it is not: on gpps's own
    noise-free metals (:data:`gpps.names.CONDUCTOR_MIN_IMAGES`; tests/test_conductor.py) the known-material solve
    gets the normals exactly from 5 lights on and misses them by 0.4-2.1 deg with 4 and 4-10 deg with 3, where any
    surface fits the lobe of some normal and the comparison would pick the conductor on non-metals (with 4 it did
    on 2 of 16 non-metal development captures, perf/results/s36/README.md).  The threshold was 6 until session 36;
    at 5 (development captures, 5 lights, seeds 3000-3009) the metals went 27.65 -> 15.17 deg (the conductor chosen
    on 3 of 4) and the others 6.25 -> 5.70 (plastic chosen on 11 of 16); on the held-out captures (seeds 1000-1007,
    5 lights, run after the choice) the metals 17.22 -> 4.67 and the others 6.50 -> 6.59 (plastic chosen on two
    diffuse captures, at worst +1.02).  Checked on our Mitsuba development captures only (perf/results/s21/README.md;
    128^2, 16-bit, seeds 3000-3009): with 12 lights it is chosen on the four rough-copper captures and on none of
    the sixteen others (whose results stay the same bits); on the metals the mean goes 6.13 -> 5.05 deg (the convex
    superquadric 3.9 -> 0.6, a concave copper relief under directional light 7.2 -> 9.8: the light its ridges send
    each other looks like a diffuse term the conductor cannot hold, though its median goes 2.8 -> 2.0).  Run after
    the choice on our held-out scenes (seeds 1000-1007, 12 lights): chosen on the one metal only (a copper
    superquadric, 3.80 / 4.45 -> 0.65 / 0.70 deg).

    The plastic model: a dielectric coating's Fresnel on the way in and out, which most real objects (paints,
    plastics, ceramics) have and the seed's models do not.  With 3 images the models' energies differ by about
    1 % and the comparison decides little (perf/results/s33/README.md), so it joins the conductor's threshold.  On
    our development captures with 12 lights (perf/results/s33/README.md) it is chosen on 12 of 20 and the mean goes
    3.95 -> 3.67 deg (better on 9, worse on 3: concave or matte scenes with interreflections, at worst +0.7; a
    smooth plastic superquadric 2.9 -> 0.3); on the held-out scenes with 12 lights, run after the choice, 3.41 ->
    3.34 (chosen on 9 of 16; better on 5, worse on 4, at worst +0.34).  DiLiGenT, checked after: ball 1.79 -> 1.53,
    bear unchanged (the plastic model's energy there is 0.1 % lower, within the sample's noise).  Warm on an H200
    DiLiGenT's ball took 0.65 s before and 0.63 s after, bear 0.93-1.02 s and 1.19-1.23 s; on the 2-core CPU ball
    29 -> 39 s.

    Args:
        n_images: the number of images N.
        config: the folder flow's settings.

    Returns:
        ``(models, reason)``: ``reason`` says which rule decided (for the report).
    """
    if config.models is not None:
        return config.models, ("asked" if config.models else "turned off")
    if n_images < CONDUCTOR_IMAGES:
        return (), f"automatic: none with {n_images} images (the conductor and plastic from {CONDUCTOR_IMAGES})"
    return AUTOMATIC_MODELS, (f"automatic: the conductor and plastic with {n_images} images (from "
                              f"{CONDUCTOR_IMAGES})")


def flip_decision(normals, mask, flip: str) -> tuple[bool, dict]:
    """The convex/concave decision for an uncalibrated result.

    When the images decided it (perspective cues, ``flip == "resolved"``) it is kept.  Otherwise the
    two members of the pair explain the images equally well, and the convex one is taken: its
    normals point away from the object's middle, ``mean(n_xy . (p - centroid) / |p - centroid|) > 0``
    over the mask (p the pixel's position in the gpps frame, y up), which holds for any surface that
    bulges toward the camera (faces, most objects).

    Args:
        normals: (H, W, 3) unit normals of the estimate, gpps frame.
        mask: (H, W) bool, the pixels to judge on.
        flip: the estimate's ``flip`` (:class:`gpps.flows.uncalibrated.UncalibratedResult`):
            ``"resolved"`` when the images decided.

    Returns:
        (whether to flip: ``n -> diag(-1, -1, 1) n``, the report entry).
    """
    h, w = mask.shape
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = jj[mask] - jj[mask].mean(), -(ii[mask] - ii[mask].mean())
    r = np.sqrt(x**2 + y**2) + 1e-9
    n = normals[mask]
    score = float(np.mean((n[:, 0] * x + n[:, 1] * y) / r))
    if flip == "resolved":
        return False, {"flip": "resolved", "by": "perspective cues (specular residual or curl)",
                       "surface": "convex" if score > 0 else "concave", "convexity_score": score}
    flipped = score < 0
    return flipped, {"flip": "ambiguous", "by": "convexity prior: the images cannot tell the pair apart; the member whose "
                                                "normals point away from the object's middle was kept",
                     "surface": "convex", "convexity_score": abs(score), "flipped": bool(flipped)}


def _uncalibrated(cap: Capture, camera, report: dict, device, progress) -> dict:
    """The uncalibrated branch: lights estimated from the evidence pixels, the rest by least squares.

    Returns:
        ``normals``, ``albedo``, ``lights``, ``directions`` (N_used, 3), ``intensities`` (N_used, 3),
        ``used`` (file names); the report entries are added to ``report``.
    """
    ds = cap.dataset
    n = ds.images.shape[0]
    cfg = UncalibratedConfig()
    drop = dark_images(ds.images, ds.mask, cfg.dark_fraction) if cfg.dark_fraction > 0 else []
    if drop:
        warnings.warn(f"left out {len(drop)} nearly dark image(s) (failed captures?): {', '.join(ds.filenames[k] for k in drop)}",
                      GppsWarning, stacklevel=3)
    keep = [k for k in range(n) if k not in drop]
    used = [ds.filenames[k] for k in keep]
    t = time.perf_counter()
    # the lights are estimated from the pixels that carry evidence: lit in enough images (a pupil or a
    # hole dark in nearly every image says nothing about them); the rest of the mask is then solved
    # with the estimated lights (Lambertian least squares)
    imgs_used = ds.images[keep]
    evidence = ds.mask & lit_pixels(imgs_used)
    if evidence.sum() < 0.5 * ds.mask.sum():
        evidence = ds.mask
    res = solve_uncalibrated(imgs_used, evidence, camera=camera if camera.is_perspective else None, config=cfg,
                             device=device, progress=progress)
    flip, decision = flip_decision(res.normals, evidence, res.flip)
    F = np.diag([-1.0, -1.0, 1.0])
    normals, ldirs = (res.normals @ F, res.light_directions @ F) if flip else (res.normals, res.light_directions)
    albedo = res.albedo
    intens = np.repeat(np.asarray(res.light_intensities, np.float64)[:, None], 3, 1)
    rest = ds.mask & ~evidence
    if rest.any():
        # least squares over the whole mask, kept on the rest: its pixels lack lit observations by construction
        # (with 3 images none has 3), so on their own they fail the solve's observation check; beside the
        # evidence pixels the under-determined ones take their neighbours' albedo
        ls = solve_normals(imgs_used / intens[:, None, None, :].astype(np.float32), ds.mask, DirectionalLights(ldirs),
                           camera=camera, solver="none", device=device)
        normals = np.where(rest[..., None], ls.normals, normals)
        albedo = np.where(rest[..., None], ls.albedo, albedo)
    report.update(method="uncalibrated", lights="estimated (directional)", convex_concave=decision,
                  images_used=used, images_left_out=[ds.filenames[k] for k in drop],
                  light_evidence_pixels=int(evidence.sum()), material=res.material, gbr=res.gbr,
                  timings={"uncalibrated": time.perf_counter() - t, **res.timings})
    return {"normals": normals, "albedo": albedo, "lights": DirectionalLights(ldirs), "directions": ldirs,
            "intensities": intens, "used": used}


def _material(ds, config: FolderConfig) -> tuple[Material, tuple[str, ...], set[str]]:
    """The material of the calibrated solve: (material, the parameters to estimate, the names given).

    ``material.json``'s model unless ``config.brdf`` names another; its parameters only with
    ``known_material`` (else the model's defaults); the parameters given in ``config`` override.
    RON estimates the model's lobe parameters that were not given.
    """
    base = Material.from_dict(ds.material) if ds.material else None
    brdf = config.brdf or (base.brdf if base is not None else "blinn-phong")
    if config.known_material and base is not None and base.brdf == brdf:
        mat_d = base.to_dict()
    else:
        mat_d = Material.default_for(brdf).to_dict()
    given = config.given_material()
    mat_d.update(brdf=brdf, **given)
    given_names = {"eta" if k in ("eta_u", "eta_v") else k for k in given}
    if config.known_material or not config.estimate or config.method != "ron":
        estimate = ()
    else:
        estimate = tuple(k for k in LOBE_PARAMETERS[brdf] if k not in given_names)
    return Material.from_dict(mat_d), estimate, given_names


def _saturation(cap: Capture) -> np.ndarray | None:
    """(N, H, W) bool, False where an observation was saturated in the file; None for float images.

    Integer images were read as 0..full scale, so a value >= 0.995 (before the division by the light
    intensities) was clipped by the camera; float formats (EXR, 32-bit TIFF) have no ceiling.
    """
    ds = cap.dataset
    integer_input = all(f["format"] not in ("exr",) and not (f["format"] == "tiff" and f["bits"] == 32) for f in cap.formats)
    if not integer_input:
        return None
    images = ds.images
    n, h, w, c = images.shape
    li = None
    if ds.light_intensities is not None and ds.normalised:
        li = np.asarray(ds.light_intensities, np.float32)
    # image by image (in cache, no (N, H, W, 3) temporaries): not any(raw_c >= 0.995), raw = images *
    # intensities in float32 as before; any(x_c >= t) is fmax_c(x_c) >= t (fmax skips NaN as the comparison does)
    valid = np.empty((n, h, w), bool)
    raw = np.empty((h, w, c), images.dtype if li is None else np.result_type(images.dtype, li.dtype))
    top = np.empty((h, w), raw.dtype)
    for k in range(n):
        if li is None:
            raw[...] = images[k]
        else:
            np.multiply(images[k], li[k], out=raw)
        if c == 1:
            top[...] = raw[..., 0]
        else:
            np.fmax(raw[..., 0], raw[..., 1], out=top)
        for j in range(2, c):
            np.fmax(top, raw[..., j], out=top)
        np.greater_equal(top, 0.995, out=valid[k])
        np.logical_not(valid[k], out=valid[k])
    return valid


def _reference_depth(ds, camera, lights, reference, source) -> tuple[float | None, str | None]:
    """The reference depth (scene units) and the name of what gave the depth's scale (None: relative).

    Given by the user, else the ground truth's mean depth when the camera is perspective or the lights
    are points; point lights set a metric scale themselves but need the distance.
    """
    if reference is None and ds.depth_gt is not None and (camera.is_perspective or isinstance(lights, PointLights)):
        reference = float(np.nanmean(np.asarray(ds.depth_gt, np.float64)[ds.mask]))
        source = "depth_gt.npy"
    if isinstance(lights, PointLights):
        if reference is None:
            both = (" (light_positions.txt is used when a folder has both it and light_directions.txt: remove it"
                    " for directional lights)" if ds.light_directions is not None else "")
            raise ValueError("reference_depth: expected the object's distance for point lights (light_positions.txt), "
                             f"got none{both}")
        source = "light_positions.txt" + (f" (distance from {source})" if source else "")
    return reference, source


def _calibrated(cap: Capture, camera, config: FolderConfig, reference, source, report: dict, device, progress,
                pixel_solve=None) -> dict:
    """The calibrated branch: the material, the reference depth, then the method (pps, ppn or ron).

    Returns:
        ``normals``, ``albedo``, ``lights``, ``depth`` and ``depth_mask`` (RON's, else None),
        ``reference`` and ``source`` (the depth's scale); the report entries are added to ``report``.
    """
    ds = cap.dataset
    n, h, w = ds.images.shape[:3]
    report["method"] = config.method
    refine, why = automatic_refine(n, config, resolve_device(device))  # (says "asked, but ..." when it cannot run)
    report["refine"] = {"on": refine, "why": why}
    lights = PointLights(ds.light_positions) if ds.light_positions is not None else DirectionalLights(ds.light_directions)
    report["lights"] = lights.kind
    material, estimate, given_names = _material(ds, config)
    reference, source = _reference_depth(ds, camera, lights, reference, source)
    internal_reference = reference
    if internal_reference is None and camera.is_perspective:
        internal_reference = float(np.sqrt(camera.fx * camera.fy))  # any scale: the shape does not depend on it
    valid = _saturation(cap)
    opts = automatic_solver_options(n, config.robust)
    robust = opts["robust"]
    out = {"lights": lights, "depth": None, "depth_mask": None, "reference": reference, "source": source,
           "flags": None}
    if config.method == "pps":
        if not camera.is_perspective or not isinstance(lights, DirectionalLights):
            raise ValueError("method pps: expected a perspective camera (K.txt) and directional lights")
        t = time.perf_counter()
        r = pps_blinn_phong(ds.images, ds.mask, lights, camera, ks=material.ks, shininess=material.shininess)
        out.update(normals=r["normals"], albedo=np.repeat(r["albedo"][..., None], 3, -1))
        report["timings"] = {"solve": time.perf_counter() - t}
        report["material"] = material.to_dict()
    elif config.method == "ppn" or config.solver == "none":
        res = (pixel_solve or solve_normals)(
            ds.images, ds.mask, lights, camera=camera, material=material, solver=config.solver,
            depth=None if not isinstance(lights, PointLights) else np.full((h, w), internal_reference, np.float32),
            valid=valid, device=device, progress=progress, **opts,
        )
        out.update(normals=res.normals, albedo=res.albedo, flags=res.flags)
        report.update(solver=config.solver, robust=robust, timings=res.timings, material=material.to_dict(),
                      mean_iterations=float(res.iterations[ds.mask].mean()),
                      flagged_pixels=int(np.count_nonzero(res.flags[ds.mask])),
                      flag_counts=flag_counts(res.flags, ds.mask))
    else:
        # (comparing models needs every lobe parameter estimated by the photometric rule: RONConfig.models)
        models, models_why = automatic_models(n, config)
        compare = (models if config.material_rule == "photometric"
                   and set(estimate) == set(LOBE_PARAMETERS[material.brdf]) else ())
        report["models"] = {"compared": list(compare), "why": models_why}
        if config.models and not compare:
            report["models_ignored"] = ("models: needs every lobe parameter of the model estimated by the "
                                        "photometric rule (no known parameters)")
        cfg = RONConfig(rounds=config.rounds, dgmc=config.dgmc, integrate=config.integrate,
                        material_rule=config.material_rule, models=compare, cast_shadows=config.cast_shadows,
                        refine=refine, refine_two_light=config.two_light,
                        final_integrator=IntegratorConfig(bilateral=True) if config.integration == "bini" else None)
        cfg = replace(cfg, solver=replace(cfg.solver, solver=config.solver, **opts))
        subtract, subtract_why = automatic_interreflections(n, config)
        # (the compensation's stages launch after the first reconstruction: their kernels compile ahead with its own)
        solve = _FolderSolve(ds.mask, lights, camera, material, estimate, internal_reference, valid, cfg, device,
                             progress, ahead=Interreflections.kernel_modules() if subtract else ())
        try:
            if subtract:
                from gpps.flows.interreflection import reconstruct_subtracting

                t = time.perf_counter()
                rec, info = reconstruct_subtracting(solve, ds.images, ds.mask, lights, camera,
                                                    rounds=config.interreflection_rounds,
                                                    albedo_scale=config.albedo_scale, device=device, progress=progress)
                report["interreflections"] = {**info, "seconds": time.perf_counter() - t, "why": subtract_why}
            else:
                rec = solve(ds.images)
                report["interreflections"] = {"skipped": True, "why": subtract_why}
        finally:
            solve.close()
        out.update(normals=rec.normals, albedo=rec.albedo, depth=rec.depth, depth_mask=rec.depth_mask, flags=rec.flags)
        # (the stage times of every reconstruction the call ran, summed; the compensation's gathers as a stage)
        timings = solve.timings()
        gathers = report["interreflections"].get("round_seconds", {}).get("gather", [])
        if gathers:
            timings["interreflections"] = float(sum(gathers))
            timings["total"] = report["interreflections"]["seconds"]
        report.update(solver=config.solver, robust=robust, timings=timings, material=rec.material.to_dict(),
                      estimated=rec.estimated, fixed=rec.fixed,
                      known=sorted(given_names) if not config.known_material else "material.json",
                      energy_per_round=rec.energy, rounds=rec.rounds, converged=rec.converged,
                      highlight_pixels=int(rec.highlight.sum()),
                      mean_iterations=float(rec.iterations[ds.mask].mean()),
                      flagged_pixels=int(np.count_nonzero(rec.flags[ds.mask])),
                      flag_counts=flag_counts(rec.flags, ds.mask),
                      cast_shadows=rec.details.shadows)  # (RON's passes: observations dropped per round)
        if rec.details.refinement is not None:
            report["refinement"] = rec.details.refinement
        # (the material's ambiguity and the models' comparison come from the first fit on the observed images)
        fits = solve.first.details.material_fit
        if fits and fits[0].get("ambiguity") is not None:  # (how far the images leave the material open)
            report["material_ambiguity"] = {**fits[0]["ambiguity"], "identifiable": fits[0]["identifiable"]}
        if fits and "models" in fits[0]:  # (compared models: each one's sampled energy and the switch's test)
            report["model_energies"] = fits[0]["models"]
            report["model_evidence"] = fits[0].get("evidence", {})
    return out


class _FolderSolve:
    """The folder flow's ``solve(images) -> Reconstruction`` for :func:`gpps.flows.interreflection.reconstruct_subtracting`.

    The first call reconstructs the observed images (:class:`gpps.flows.reconstruction.ResidentFrame`, kept open as
    :attr:`frame`: the compensation's later rounds subtract on the device and solve it again there).  A later call
    with host images (probes that run their own rounds, perf/_common.folder_solve) is one of the compensation's later
    reconstructions: the rounds iterate one forward model, images <- observed - indirect(surface), with the material the
    first reconstruction estimated on the observed images (re-deciding the model on images a fraction of a percent
    apart flipped DiLiGenT bear's choice at z = 2.39 against the threshold's 2.33 and cost 1.1 deg, session 34; the
    lobe is seen in the highlights, which the diffuse indirect light hardly moves), every pixel's solve warm from the
    last reconstruction's normals (no least squares, DGMC or cold starts: the images moved by a few percent), and
    under point lights the rounds from its depth.  :meth:`close` frees the frame.
    """

    def __init__(self, mask, lights, camera, material, estimate, reference, valid, config, device, progress, *,
                 ahead=()):
        self.ahead = list(ahead)  #: Warp modules of the stages launched after the first reconstruction (compiled ahead)
        self.mask, self.lights, self.camera = mask, lights, camera
        self.material, self.estimate, self.reference, self.valid = material, estimate, reference, valid
        self.config, self.device, self.progress = config, device, progress
        self.frame = None  #: the first reconstruction's ResidentFrame (its frame on the device), after the first call
        self.first = self.last = None  #: the first and the last reconstruction
        self.calls = []  #: the stage times (s) of the reconstructions through this call's ``reconstruct``
        self.frame_calls = []  #: the frame's solves' stage times (s): its first and its :meth:`ResidentFrame.again`

    def timings(self) -> dict:
        """Every reconstruction's stage times summed (s): the whole call's, not only the last reconstruction's."""
        out = {}
        for t in (self.frame.timings if self.frame is not None else self.frame_calls) + self.calls:
            for k, v in t.items():
                out[k] = out.get(k, 0.0) + v
        return out

    def __call__(self, images):
        from gpps.flows.reconstruction import ResidentFrame

        if self.first is None:
            self.frame = ResidentFrame(images, self.mask, self.lights, camera=self.camera, material=self.material,
                                       estimate=self.estimate, reference_depth=self.reference, valid=self.valid,
                                       config=self.config, device=self.device)
            if self.ahead:
                self.frame.compile_ahead(self.ahead)
            self.first = self.last = self.frame.run(progress=self.progress)
            return self.first
        last = self.last
        self.last = reconstruct(images, self.mask, self.lights, camera=self.camera, material=last.material,
                                estimate=(), depth=last.depth if isinstance(self.lights, PointLights)
                                and last.depth is not None and np.all(last.depth[self.mask] > 0) else None,
                                reference_depth=self.reference, valid=self.valid,
                                config=replace(self.config, models=()), device=self.device, progress=self.progress,
                                start=last)
        self.calls.append(dict(self.last.timings))
        return self.last

    def close(self) -> None:
        if self.frame is not None:
            self.frame_calls = list(self.frame.timings)
            self.frame.close()
            self.frame = None


def reconstruct_folder(folder, config: FolderConfig | None = None, *, lights=None, mask=None, ambient: str | None = "auto",
                       device: str | None = None, progress: Progress | None = None,
                       read_progress: Progress | None = None, pixel_solve: Callable | None = None) -> FolderResult:
    """Normals, albedo, depth (and the lights, when not given) of the object in a capture folder.

    Args:
        folder: the capture folder (images in any format :mod:`gpps.io.formats` reads; optional
            filenames.txt, light_directions.txt or light_positions.txt, light_intensities.txt,
            mask.*, K.txt, an ``*ambient*`` image, normal_gt.npy, depth_gt.npy, material.json).
        config: :class:`FolderConfig` (None: the defaults).
        lights: another folder to read the light files from (rows in the images' order); None: ``folder``.
        mask: None (``mask.*`` in the folder, else automatic), ``"auto"`` (always automatic),
            ``"none"`` (every pixel) or a mask file.
        ambient: ``"auto"`` (an image named ``*ambient*`` in the folder), ``"none"`` or None (never),
            or a file: subtracted from every image.
        device: Warp/Taichi device (None or "auto": CUDA if present).
        progress: optional ``progress(done, total, message)`` of the solve.
        read_progress: optional ``progress(done, total, message)`` while the images are read.
        pixel_solve: a replacement for :func:`gpps.flows.photometric.solve_normals` (same arguments and
            result) in the calibrated ``"ppn"`` solve: the tiled solve of :func:`gpps.batch.reconstruct_tiled`;
            None: ``solve_normals``.  Other methods refuse it.

    Returns:
        :class:`FolderResult`; :meth:`FolderResult.write` writes it.

    Raises:
        FileNotFoundError: no folder, or a named file is missing.
        ValueError: no images, fewer than 10 object pixels, point lights without a reference depth,
            ``method="pps"`` without a perspective camera and directional lights, degenerate images.
    """
    started = time.perf_counter()
    folder = as_path("folder", folder)
    config = FolderConfig() if config is None else config
    if not isinstance(config, FolderConfig):
        raise TypeError(f"config: expected FolderConfig, got {type(config).__name__}")
    device = None if device == "auto" else device
    cap = read_capture(folder, transfer=config.transfer, max_size=config.max_size,
                       ambient=None if ambient == "none" else ambient,
                       mask=mask, normalise=not config.uncalibrated, lights=lights, progress=read_progress)
    ds = cap.dataset
    n, h, w = ds.images.shape[:3]
    camera = camera_from_K(ds.K) if ds.K is not None else Orthographic(config.pixel_size or 1.0)
    uncalibrated = config.uncalibrated or not cap.calibrated
    report = {"dir": str(folder), "images": n, "shape": [h, w], "camera": camera.kind,
              "integration": None if not config.integrate else config.integration,
              "input": {"formats": cap.formats, "mask": cap.mask_source, "ambient_subtracted": cap.ambient,
                        "downscale": cap.scale, "filenames": ds.filenames}}
    if cap.automask is not None:
        report["input"]["automatic_mask"] = cap.automask
    if ds.mask.sum() < 10:
        raise ValueError(f"mask: expected at least 10 object pixels, got {int(ds.mask.sum())}")
    if pixel_solve is not None and (uncalibrated or (config.method != "ppn" and config.solver != "none")):
        raise ValueError(f"pixel_solve: expected a calibrated capture and method 'ppn', got "
                         f"{'uncalibrated' if uncalibrated else repr(config.method)}")
    reference = config.reference_depth
    source = "--reference-depth" if reference is not None else None  # report.json's name for a given reference depth
    if uncalibrated:
        sol = _uncalibrated(cap, camera, report, device, progress)
        sol.update(depth=None, depth_mask=None)
        report["refine"] = {"on": False, "why": ("asked, but " if config.refine else "automatic: ")
                            + "an uncalibrated capture runs no RON rounds to refine after"}
        if config.interreflections != "off":
            report["interreflections"] = {"skipped": True, "why": (
                "asked, but " if config.interreflections == "subtract" else "automatic: ")
                + "an uncalibrated capture has no RON surface to gather over"}
    else:
        sol = _calibrated(cap, camera, config, reference, source, report, device, progress, pixel_solve)
        reference, source = sol["reference"], sol["source"]
    normals = np.where(ds.mask[..., None], sol["normals"], 0.0).astype(np.float32)
    depth, dmask = sol["depth"], sol["depth_mask"]
    if depth is None and config.integrate:
        t = time.perf_counter()
        ref_i = reference if reference is not None else (float(np.sqrt(camera.fx * camera.fy)) if camera.is_perspective else None)
        # the Integrator takes "auto", not None
        ir = integrate_normals(normals, ds.mask, camera=camera, reference_depth=ref_i, device=device or "auto",
                               bilateral=config.integration == "bini")
        depth, dmask = ir.depth, ir.mask
        report.setdefault("timings", {})["integration"] = time.perf_counter() - t
    conv = depth_convention(camera, known_scale=source)
    if config.pixel_size is not None and not camera.is_perspective:
        conv = depth_convention(camera)
    if depth is not None:
        depth = apply_depth_convention(depth, dmask, conv)
        report["depth"] = conv
    if ds.normal_gt is not None and ds.normal_gt.shape[:2] == (h, w):
        report["errors"] = normal_errors(normals, ds.normal_gt, ds.mask)
        report["maen_deg"] = report["errors"]["mean"]
    return FolderResult(normals=normals, albedo=sol["albedo"], mask=ds.mask, depth=depth, depth_mask=dmask, camera=camera,
                        depth_info=conv if depth is not None else None, lights=sol["lights"], uncalibrated=uncalibrated,
                        light_directions=sol.get("directions"), light_intensities=sol.get("intensities"),
                        images_used=sol.get("used", list(ds.filenames)), report=report, started=started,
                        flags=None if sol.get("flags") is None else np.where(ds.mask, sol["flags"], 0).astype(np.int32))
