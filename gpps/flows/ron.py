"""RON: the recurrent optimisation of normals, RGB albedo, depth and material (seed 4.1.10, Algorithm 2).

The seed's real-time method is a loop, not one solve.  Each round of
:class:`RON` runs the steps of Algorithm 2::
    start: Lambertian least squares (Woodham); DGMC start normals on highlight
           pixels (4.16-4.18, gpps.host.dgmc)
    repeat
      1. normals, per pixel, with the current material (and, for point lights,
         the light directions and 1/r^2 falloff from the current depth, 2.30-2.31):
         PixelSolver (Algorithm 3, 4 or 5), multi-start; highlight pixels also
         from their DGMC start (round 1) and every pixel also from its previous
         normal (later rounds); the lowest residual wins
      2. RGB albedo from those normals (the solver's variable projection: the
         closed-form least-squares albedo given the normal)
      3. depth: integrate the normals (4.20, Taichi multigrid, warm-started);
         with ``cast_shadows`` each light's cast shadows are marched over it and
         the shadowed observations leave the next solves and the material fit
      4. material: the parameters the caller did not give are updated
      5. = step 1 of the next round (normals with the recent albedo/material)
    until the energy and the normals stop changing, or the round cap

The energy of a round is the mean squared residual of the model per
observation and channel over the mask (after step 1); it is recorded per round
(``RONResult.energy``).

Material update (step 4).  The seed updates the Cook-Torrance roughness by
(4.19), the root-mean-square deviation of the integrated depth from the mean
surface.  As printed, (4.19) lacks the square, and it measures geometry
(a length), not the microfacet slope distribution ``m`` of the BRDF, so it
cannot recover a material's roughness from its images; it is kept as
``material_rule="depth-rms"`` (with the square, see :func:`depth_rms_roughness`).
The default ``material_rule="photometric"`` instead chooses the unknown scene
parameters (``ks`` and the lobe width: shininess, roughness ``m`` or the
Ashikhmin-Shirley exponents) that minimise the same energy, each pixel's
normal and albedo re-solved for every candidate (variable projection over the
per-pixel unknowns) on a fixed random sample of pixels (highlight pixels first):
a log-spaced grid, then Nelder-Mead from its best point.  With coloured
albedo or more than three images this identifies the material well (the
specular lobe is white, the diffuse part has the albedo's colour); with three
images of a grey object every candidate can fit each pixel.  The first fit
measures this on its grid (:func:`material_ambiguity`: how far apart the normals of
the candidates that fit within the noise are); beyond :data:`AMBIGUITY_DEG` the
fit is reported as ``identifiable=False`` in ``RONResult.material_fit`` and a
warning says so.

Point lights with an unknown depth start from a flat depth at
``reference_depth`` (the working distance); each round the integrated depth
(mean set to ``reference_depth``) moves the lights' directions and falloff.
"""

from __future__ import annotations

import importlib.util
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Literal

import numpy as np
from scipy.ndimage import gaussian_filter, label

from gpps._check import (
    as_array,
    as_mask,
    check_bool,
    check_choice,
    check_choices,
    check_number,
    warn,
)
from gpps._runtime import resolve_device, warp
from gpps._taichi import taichi_device
from gpps.host.dgmc import DGMCConfig
from gpps.host.model_evidence import energy_drop_evidence
from gpps.host.two_light import dark_observations, two_light_log_depth
from gpps.lights import PointLights
from gpps.material import Material
from gpps.names import BRDF_NAMES, BRDF_TAG, CONDUCTOR, LOBE_PARAMETERS, LOBE_RANGES
from gpps.pipeline.depth_refine import DepthRefineConfig, DepthRefiner
from gpps.pipeline.dgmc import DeviceDGMC
from gpps.pipeline.front import DeviceFront, propagate_front, propagate_front_device
from gpps.pipeline.integration import Integrator, IntegratorConfig, warn_log_depth_span
from gpps.pipeline.integration_rounds import DeviceSystem
from gpps.pipeline.material import MaterialScorer, scorer_kernels
from gpps.pipeline.material_search import NelderMeadSearch
from gpps.pipeline.render import Renderer
from gpps.pipeline.ron_rounds import DeviceRounds
from gpps.pipeline.ron_shadows import RoundShadows
from gpps.pipeline.shadows import ShadowConfig
from gpps.pipeline.prefetch import KernelPrefetch, prefetch_enabled
from gpps.pipeline.solver import PixelSolver, SolverConfig, solver_kernels
from gpps.pipeline.stream_material import lobe_value, with_lobe

__all__ = [
    "RON",
    "RONConfig",
    "RONResult",
    "MaterialRule",
    "LOBE_PARAMETERS",
    "estimable_parameters",
    "depth_rms_roughness",
]

MaterialSearch = Literal["pattern", "nelder-mead"]
MaterialLoop = Literal["auto", "host", "device"]
MaterialRule = Literal["photometric", "depth-rms"]
ShadowFew = Literal["flag", "keep"]
Progress = Callable[[float, float, str], None]

# the scene parameters RON can estimate per model and their log-space search ranges (gpps.names: the
# stream's full mode searches the same)
_RANGES = LOBE_RANGES
# Nelder-Mead's stopping size of the simplex (log units): the first fit only has to land in the optimum's
# basin (every later fit starts from it with a simplex of at most _LATER_STEP and refines to _XATOL)
_FIRST_XATOL, _XATOL = 0.05, 1e-3
# a later fit's initial simplex: twice the previous fit's move, within these bounds (log units)
_LATER_STEP = (0.01, 0.15)


#: the material fit's warning threshold (degrees): grid candidates that fit the sample within the noise give normals
#: this far apart on average (:func:`material_ambiguity`); the scale of the accuracy asked of calibrated PS on real
#: objects, so a material the images leave this open costs more than the accuracy itself
AMBIGUITY_DEG = 2.0


def material_ambiguity(energies, normals, noise_var: float) -> dict:
    """How far the images leave the material open, measured by what it does to the normals.

    A grid candidate *fits within the noise* when its sampled energy (mean squared residual per observation)
    exceeds the best candidate's by at most the images' noise variance: its extra misfit is below what one
    observation's noise could hide.  Three images of a grey object fit any lobe exactly (three observations
    per pixel for a normal and an albedo), so every candidate does, each with other normals; with colour or
    more images only the best and its neighbours do.  The ambiguity is the largest, over the candidates that
    fit within the noise, of the mean angle (over the sample pixels) between their normals and the best
    candidate's.  It says what a user wants to know (how much the unknown material can move the normals),
    not how flat the energy is: a diffuse object leaves the lobe open but its candidates agree on the normals.

    Args:
        energies: (K,) the candidates' sampled energies (image units squared).
        normals: (K, P, 3) each candidate's normals at the sample pixels (unit; non-finite or zero rows are
            pixels without a solve, left out).
        noise_var: the images' noise variance (image units squared; 0: only exact ties fit within it).

    Returns:
        ``{"ambiguity_deg", "near" (candidates within the noise, the best included), "candidates",
        "noise_var"}``.
    """
    e = np.asarray(energies, np.float64)
    n = np.asarray(normals, np.float64)
    if n.ndim != 3 or n.shape[0] != e.size or n.shape[2] != 3:
        raise ValueError(f"normals: expected ({e.size}, P, 3), got {n.shape}")
    best = int(np.argmin(e))
    near = np.nonzero(e - e[best] <= max(float(noise_var), 0.0))[0]
    # (per pixel: every candidate's normal finite and longer than 0.5; one pass over the (K, P) lengths)
    with np.errstate(invalid="ignore", over="ignore"):
        ln = np.sqrt(np.einsum("kpc,kpc->kp", n, n))
    ok = np.all(np.isfinite(ln) & (ln > 0.5), axis=0)
    worst = 0.0
    if ok.any():
        # (each pixel's cosines do not depend on the others: computed for all, then the usable pixels kept)
        with np.errstate(invalid="ignore"):
            cos = np.einsum("kpc,pc->kp", n[near], n[best])
        cos = np.clip(cos if ok.all() else cos[:, ok], -1.0, 1.0)
        worst = float(np.degrees(np.arccos(cos)).mean(axis=1).max())
    return {"ambiguity_deg": worst, "near": int(near.size), "candidates": int(e.size), "noise_var": float(noise_var)}


def on_bound(x, lo, hi) -> bool:
    """Whether a point (log units) lies on a face of the box ``[lo, hi]`` (within 1e-9)."""
    x = np.asarray(x, np.float64)
    return bool(np.any(x <= np.asarray(lo) + 1e-9) or np.any(x >= np.asarray(hi) - 1e-9))


def initial_simplex(x0, step, lo, hi) -> np.ndarray:
    """Nelder-Mead's initial simplex in the box ``[lo, hi]``, as scipy's bounded Nelder-Mead builds it: vertex 0 is
    ``x0``, vertex ``i + 1`` moves parameter ``i`` by ``step[i]``, a vertex beyond the upper bound is reflected into
    the box (``2 hi - v``), and every vertex is clipped to it.  A start on the upper bound (where the grid's best
    point often lies: ks = 3) so gets a vertex a step inside, not one outside scored at the clipped point, a
    plateau the search drifted on and stopped (session 19: Cook-Torrance bumps under 6 lights ended at ks 3.0,
    m 0.15 and 3.5 deg instead of the true ks 0.8, m 0.2).

    Args:
        x0: (d,) the start (log units), inside the box.
        step: (d,) the edge lengths (> 0).
        lo, hi: (d,) the box.

    Returns:
        (d + 1, d) the simplex.
    """
    x0 = np.asarray(x0, np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    sim = np.vstack([x0, x0 + np.diag(np.asarray(step, np.float64))])
    return np.clip(np.where(sim > hi, 2.0 * hi - sim, sim), lo, hi)


def estimable_parameters(brdf: str) -> tuple[str, ...]:
    """Names of the scene parameters :class:`RON` can estimate for a reflectance model."""
    check_choice("brdf", brdf, LOBE_PARAMETERS)
    return LOBE_PARAMETERS[brdf]




@dataclass(frozen=True)
class RONConfig:
    """Settings of :class:`RON`.

    Attributes:
        rounds: cap on rounds of Algorithm 2.
        tol: stop when the normals change by less than ``tol_normals_deg`` on average between rounds and either
            the energy by less than this fraction or (photometric estimation, from round 3 on) the last material
            fit moved no parameter by its resolution (the rounds' fixed point: :meth:`RON._material_settled`).
        tol_normals_deg: see ``tol`` (degrees).
        dgmc: start highlight pixels from DGMC normals (4.16-4.18) in round 1.
        dgmc_config: the DGMC settings.
        integrate: run step 3 (depth).  Point lights need it unless their depth is given.
        estimate: scene parameters to estimate (names from
            :data:`LOBE_PARAMETERS` for the model); empty: none.
        material_rule: ``"photometric"`` (default) or ``"depth-rms"``, the
            seed's (4.19) (Cook-Torrance roughness only; see the module docstring).
        material_samples: the most pixels sampled for the photometric material fit.
        material_observations: the fit's budget of observations: the sample has
            ``clip(material_observations / N, min(500, material_samples), material_samples)`` pixels
            for N images.  The estimate's precision grows with the observations it rests on (each
            pixel adds N residual terms that sample its specular lobe at N half-angles), so with many
            lights fewer pixels carry the same information: 2000 pixels up to 12 images, 500 from 48
            (the floor keeps the sample spread over the object), at a quarter of the cost.
        material_grid: grid points per estimated parameter in the first fit.
        material_evals: the most candidate evaluations after the grid (and in each later round); a search
            that ends on a bound of the range away from its start runs once more from there with as many (its
            simplex may have collapsed into the bound's face: ``material_fit``'s ``restarted``).
            Nelder-Mead stops earlier when its simplex has shrunk below 0.05 log units in the
            first fit (which only has to find the optimum's basin: every later fit starts there)
            and below 1e-3 in later fits, whose initial simplex is twice the previous fit's move
            (0.01-0.15 log units): the material moves less from round to round.  So the rounds
            stop only after a later fit (at least 3 rounds when estimating photometrically).
        material_search: after the grid, ``"nelder-mead"`` (default): scipy's Nelder-Mead, its initial
            simplex scored in one batch, then one or two candidates a step; ``"pattern"``: a stencil search
            with a quadratic model whose ``3^d`` candidates are scored in one batch (fewer, fuller launches
            on the device; on rendered Cook-Torrance scenes it stopped further from the optimum than
            Nelder-Mead within the same budget: 0.38 against 0.13 deg MAEN on a 64^2 sphere).
        material_loop: who drives Nelder-Mead's steps after its initial simplex: ``"device"``: each step's
            points, trimmed energies and decision in device kernels around the scorer's solve, the loop a
            CUDA graph with a conditional node where the device has them
            (:class:`gpps.pipeline.material_search.NelderMeadSearch`: no host wait between steps, the same
            trajectory); ``"host"``: the host decides each step from the fetched energies (a progress report
            after every batch); ``"auto"`` (default): ``"device"`` on CUDA, ``"host"`` on the CPU (whose
            launches run on the host anyway, and whose long batches want the progress reports).
        material_trim: fraction of worst pixel residuals left out of the fit's
            energy (robust to cast shadows and inter-reflections).
        material_starts: starts per pixel in the fit's cold per-pixel solves.
        material_warm: score the candidates of the later fits (rounds 2, 3, ...) from warm starts
            (one start per pixel, continuation): from the round's normals, which were solved
            with the current material (cold multi-start and warm, the lower residual winning).
            A pixel's minimiser moves continuously with the material near it, so the local solve
            from there finds it at a fraction of the cold multi-start's cost.  The first fit
            stays cold: its grid spans the whole range, and with 3 images a start from a grid
            candidate's normals led Nelder-Mead into a false valley (ks 1.22 for 0.7 on a
            rendered Blinn-Phong scene).  False: every candidate cold.
        cold_rounds: rounds whose normals solve includes the cold multi-start (besides the
            warm start from the previous round's normals, the lower residual winning); later
            rounds only continue from the previous round's normals.  The default 2 covers the
            round with the start material and the first with an estimated one; after that the
            material moves little between rounds and each pixel's minimiser with it.
        roughness_window: Gaussian scale (pixels) of the mean surface of (4.19).
        solver: the per-pixel solver settings (steps 1 and 5).
        integrator: settings of the Taichi integrator (step 3); None: multigrid
            to a relative residual of 1e-5, with the ``"normal"`` (n_z^2) weighting
            for perspective cameras and ``"uniform"`` for orthographic ones.
        final_integrator: settings of the last integration, the depth that is
            returned (an IntegratorConfig); None: ``integrator``'s.  ``gpps
            reconstruct`` sets ``IntegratorConfig(bilateral=True)`` (BiNI, which
            keeps depth discontinuities) while the rounds, whose depth only moves
            point lights, keep the warm-started Poisson solve.
        seed: seed of the pixel sample (results are reproducible).
        device_rounds: when the rounds' depth feeds back (point lights, the depth-rms rule) and the
            integrator is the plain multigrid one: exchange normals and depth with the integrator on
            the device (:class:`gpps.pipeline.ron_rounds.DeviceRounds`: the system assembled and
            solved there, the depth written into the solver's buffer, the round's energy and normal
            change reduced there; only scalars come back per round, the outputs once at the end).
            The final depth is integrated there too when ``final_integrator`` is the rounds' one.
            The photometric material fit still takes the round's normals and depth on the host,
            the depth-rms rule the depth; a round whose normals have invalid pixels (NaN, zero,
            back-facing) is integrated on the host.  False: every round on the host (the reference).
            None (default): True on the CPU, and on CUDA where torch is installed (the ``gpps[cuda]``
            extra: the zero-copy views between Warp and Taichi); without torch, CUDA keeps the host
            rounds.  True on CUDA without torch raises ImportError.  (tests/test_ron_device.py
            passed on the CPU and on an H100.)
        cast_shadows: visibility from the shape (issue 25): from round 2 on, each light's cast-shadow mask
            is marched over the previous round's integrated depth on the device
            (:class:`gpps.pipeline.ron_shadows.RoundShadows`, :mod:`gpps.kernels.shadows`) and the shadowed
            observations are left out of the round's solves and of the material fit's sample.  The masks
            are recomputed every round from the caller's observations (``valid``), never accumulated.
            Only with ``integrate`` (without it there is no depth: no pass); the rounds then integrate a
            depth for directional lights too (its offset, orthographic, or scale, perspective, does not
            change a directional light's shadows); a pass
            that drops nothing after a round that dropped nothing ends the rounds when nothing else feeds
            back (directional lights, known material: one round on a scene without cast shadows).
            Default False (opt-in), from the development set below.  Principle: the image model has no
            visibility term, so an observation in a cast shadow is an outlier the model can only explain by
            bending the normal away from its light (a dark one-sided term reads it as an attached shadow); the
            depth RON integrates anyway says
            where the shadows are.  Only observations whose normal faces the light are dropped (behind the
            terminator the march meets the object's own surface: an attached shadow, which the model explains;
            :data:`gpps.pipeline.ron_shadows.FACING_MIN`).  Measured (perf/ron_shadows.py,
            perf/results/ron_shadows_cpu.json: 64^2, perspective, CPU, 12 lights directional / point,
            whole-mask MAEN deg off -> on): a Gaussian bump with exact analytic shadows 0.49 -> 0.07 / 0.50 ->
            0.07 (over the shadowed pixels 1.86 -> 0.17 / 1.45 -> 0.13), a hemisphere on a plane 2.64 -> 1.70 /
            3.06 -> 1.87, a box on a plane 6.00 -> 5.91 / 6.37 -> 6.25; Mitsuba path-traced captures (seeds
            2001-2003, Lambertian model): sphere on a plane 18.30 -> 16.73 / 21.26 -> 19.62, five spheres
            16.53 -> 15.33 / 17.86 -> 16.48, bumps 6.09 -> 5.48 / 6.39 -> 5.89; a sphere without cast shadows
            unchanged (0.08 / 0.09; 31 / 152 observations dropped, 1378 / 2063 without the facing test).
            But on the Mitsuba development set (perf/dev_eval.py, perf/results/dev_eval_cpu.md: 40 captures,
            10 scenes, seeds 3000-3009, the default pipeline) the pass does not pay with 12 lights: non-diffuse
            mean 5.60 -> 5.89 deg (torus under plastic 9.18 -> 10.75, ridges under a rough conductor 10.56 ->
            11.70, where the model misfits and the integrated depth is wrong), diffuse 2.78 -> 2.74; the
            integrated depth is only as good as the normals.  DiLiGenT as a final check (CPU, 96 images):
            ball 1.7876 -> 1.7963, bear 4.5734 -> 4.5212.  So it is off by default until the depth it marches
            is better (issue 25's depth-parameterised refinement).
            With 3 lights nothing could change under the default ``shadow_few`` (every shadowed pixel keeps
            its 3 observations), so there is no pass: the rounds and their cost stay as without it (the pass's
            integration every round took the 256^2 x 3 reconstruct on an H100 from 0.18 to 0.29 s for the
            same result).  Limits: the depth integrated from normals loses
            steep rims and depth steps (a box or hemisphere standing on a plane comes out lower, its
            shadows shorter: IoU 0.03 / 0.41 of the dropped cast shadows against the analytic ones there,
            0.92-0.95 on the smooth bump), and the march also drops attached-shadow observations near the
            terminator (harmless with 12 lights: the model predicts about 0 there).  Cost: one integration
            and one march a round, and rounds that a known material under directional lights did not run.
        shadow_config: the march's settings (:class:`gpps.pipeline.shadows.ShadowConfig`); default a
            tolerance of 0.5 pixel widths (the stage's default 1 was chosen for iid depth noise of 0.3 pixel
            widths, harsher than the smooth errors of an integrated depth).  Measured (perf/ron_shadows.py
            --tau 1 0.5, 12 lights, tolerance 1 -> 0.5): MAEN over the shadowed pixels of the analytic bump
            0.37 -> 0.17 (directional) and 0.30 -> 0.13 (point), IoU of the dropped cast shadows 0.84 ->
            0.92 and 0.86 -> 0.95; whole-mask MAEN of the six Mitsuba captures 0.02-0.33 deg lower.
        shadow_few: a pixel the shadows would leave with fewer than 3 valid observations: ``"keep"``
            (default): the pixel keeps all its observations (counted in ``RONResult.shadows``
            ``kept_pixels``); ``"flag"``: drops them anyway, and the solver flags the pixel
            ``FLAG_FEW_OBSERVATIONS`` (as every pixel with fewer than 3 lit observations) and solves it in its
            neighbour pass (albedo from the neighbours).  Measured with 3 lights (whole-mask MAEN, keep =
            off -> flag): better on 9 of the 12 captures with cast shadows (bump point 5.27 -> 3.15,
            hemisphere 8.10 -> 6.68 / 10.48 -> 9.38, Mitsuba 0.1-1.2 deg), equal on one, worse on the bump
            under directional lights (3.58 -> 4.09), Mitsuba bumps under point lights (6.44 -> 7.03) and the sphere
            without cast shadows under point lights (0.36 -> 0.63: attached-shadow observations dropped).
            A scene without cast shadows must not get worse, so the under-determined pixels keep theirs.
        models: other reflectance models to compare with the material's (issue 25: e.g. ``("plastic",)``,
            the dielectric coating, beside ``"cook-torrance"``): the first round's material fit runs for each
            (its lobe parameters, :data:`gpps.names.LOBE_PARAMETERS`, from the model's
            :meth:`Material.default_for`) on the same sample pixels, and the material's own model is kept for the
            later rounds unless another's sampled energy (trimmed mean of squared residuals at its best
            parameters) is lower beyond the sample's noise (:func:`gpps.host.model_evidence.energy_drop_evidence`:
            a one-sided paired test of the pixels' squared residuals at the 1 % level, session 33); of those that
            are, the lowest energy wins (``RONResult.material_fit[0]["models"]``: each one's energy;
            ``["evidence"]``: the test's numbers per other model).  Needs every lobe parameter of the
            material estimated by the photometric rule.  () (default): the material's model only.  Measured on
            Mitsuba captures (perf/plastic_vs_ct.py, perf/results/plastic_vs_ct_cpu.json, seeds 2501-2504):
            the model with the lower residual also had the lower MAEN in 6 of 8 captures, the other two within
            0.18 deg.
        refine: after the rounds, refine the depth itself (issue 25): the returned depth's log-depth (perspective)
            or depth is the unknown, each pixel's normal that of the surface, a robust (Cauchy) misfit over every
            valid observation, Levenberg-Marquardt steps solved by the rounds' integrator on the device
            (:class:`gpps.pipeline.depth_refine.DepthRefiner`).  Pixels that lost observations (cast shadows,
            saturation) take their normal from the surface their neighbours fix.  The returned normals are the refined
            surface's (``refine_config.normals``; on the mask's border each pixel's own), the depth the refined one.  Needs
            ``integrate`` and a plain multigrid rounds' integrator.  Off by default: on the Mitsuba development
            set (perf/results/dev_eval_cpu_refine_table.md, 40 captures) it is better on 28 and worse on 12
            (non-diffuse means 18.42 -> 17.00 deg with 3 lights, 5.60 -> 5.93 with 12), better on height fields,
            concavities and rough conductors (12 lights: bowl 3.08 -> 2.52, ridges 10.6 -> 5.7), worse on reliefs of
            one- or two-pixel facets (steps, 12 lights: 8.85 -> 14.4; a surface on the pixel grid cannot hold a wall
            one pixel wide) and on the torus under point lights (10.8 -> 17.1): reliefs are what many users scan.
            DiLiGenT, 96 images (final check, H100): ball 1.7875 -> 1.7475, bear 4.5741 -> 4.1360.
        refine_config: its settings (:class:`gpps.pipeline.depth_refine.DepthRefineConfig`).
        refine_two_light: with ``refine`` and directional lights, where some pixels keep only two lit
            observations (a cast or attached shadow: :func:`gpps.host.two_light.dark_observations`), refine also
            from a second start, the surface that the two-light Lambertian ratio and integrability fix there
            (:func:`gpps.host.two_light.two_light_log_depth`; elsewhere the per-pixel normals), and keep the
            refined surface of higher likelihood (:meth:`gpps.pipeline.depth_refine.DepthRefiner.likelihood`:
            Cauchy residuals at each surface's own maximum-likelihood scale).  Why: the per-pixel fit explains
            a cast shadow as a normal turned away from the light, the depth integrated from those normals carries
            the tilt, and the refinement does not leave that basin; the second start lies in the true surface's
            basin where the shadow is cast, and the likelihood keeps the first where it is the likelier (an
            attached shadow, as a convex object's terminator, where the dark observation is information).
            Measured (perf/results/s22/README.md; chosen on our own renders): a box on a plane with exact cast
            shadows, 3 lights, 11.7 -> 0.08 deg (perspective), 15.9 -> 0.06 (orthographic); Mitsuba development
            captures, 3 directional lights: sphere on a plane 16.29 -> 7.99, five spheres 11.22 -> 6.93, the torus
            20.61 -> 22.83 and the smooth synthetic bumps 0.98 -> 1.22 worse (the likelier surface mends the
            shadows and loses elsewhere: both refinements stop short of the truth, which is likelier than
            either), the rest within 0.1; non-diffuse mean 14.05 -> 13.77.  Point lights: not used (their
            directions depend on the depth being solved; a start linearised at the integrated depth never won on
            the development captures under 3 point lights).  Costs a second refinement where it runs (DiLiGenT
            ball from 3 images, CPU: 8.0 -> 12.6 s, the first start kept).
        material_warm_iters: the most cost evaluations of a warm candidate solve (``material_warm``: one start a
            pixel, from the round's normals); None: the solver's ``max_iters`` (50).  A warm solve starts near its
            minimum and LM converges there in a few evaluations (median 3-4 on the 256^2 x 3 Cook-Torrance case);
            the tail that runs on (3-5 % of the sample above 12, up to 37) is pixels in flat valleys or leaving
            their basin, whose residuals barely move or are not the continuation the warm start is for.  On the
            GPU a launch of the search costs its slowest solve, so the tail set each of its ~40 sequential passes'
            length.  12 = three times the median; chosen on our own data: the 256^2 x 3 case gives the same
            estimate and normals bit for bit at 12 and 16 as uncapped, and the 40 Mitsuba development captures
            (3 and 12 lights, seeds 3000-3009) the same MAEN in 21, a mean change of -0.02 deg, non-diffuse means
            13.77 -> 13.78 and 16.93 -> 16.85 (3 directional / point lights), 4.17 -> 4.16 and 4.40 -> 4.40 (12);
            the largest moves are 3-light point-light captures
            whose material is not identifiable (five spheres +0.69, copper superquadric -1.44).  The cold fits
            (the first round's grid and simplex) keep ``max_iters``.
    """

    rounds: int = 5
    tol: float = 1e-3
    tol_normals_deg: float = 0.05
    dgmc: bool = True
    dgmc_config: DGMCConfig = field(default_factory=DGMCConfig)
    integrate: bool = True
    estimate: tuple[str, ...] = ()
    material_rule: MaterialRule = "photometric"
    material_samples: int = 2000
    material_observations: int = 24000
    material_grid: int = 5
    material_evals: int = 40
    material_search: MaterialSearch = "nelder-mead"
    material_loop: MaterialLoop = "auto"
    material_trim: float = 0.02
    material_starts: int = 4
    material_warm: bool = True
    cold_rounds: int = 2
    roughness_window: float = 4.0
    solver: SolverConfig = field(default_factory=SolverConfig)
    integrator: object = None  # gpps.pipeline.integration.IntegratorConfig (None: defaults)
    final_integrator: object = None  # IntegratorConfig of the returned depth (None: integrator's)
    seed: int = 0
    device_rounds: bool | None = None
    cast_shadows: bool = False
    shadow_config: ShadowConfig = field(default_factory=lambda: ShadowConfig(tolerance_px=0.5))
    shadow_few: ShadowFew = "keep"
    models: tuple[str, ...] = ()
    refine: bool = False
    refine_config: DepthRefineConfig = field(default_factory=DepthRefineConfig)
    refine_two_light: bool = True
    material_warm_iters: int | None = 12

    def __post_init__(self):
        check_choices(self)
        check_bool("refine", self.refine)
        check_bool("refine_two_light", self.refine_two_light)
        if self.refine and not self.integrate:
            raise ValueError("refine: refines the integrated depth, expected integrate=True, got integrate=False")
        if not isinstance(self.refine_config, DepthRefineConfig):
            raise TypeError(f"refine_config: expected gpps.pipeline.depth_refine.DepthRefineConfig, got "
                            f"{type(self.refine_config).__name__}")
        check_number("rounds", self.rounds, lo=1, integer=True)
        if not isinstance(self.models, (tuple, list)) or not all(isinstance(b, str) for b in self.models):
            raise TypeError(f"models: expected a tuple of reflectance model names, got {self.models!r}")
        object.__setattr__(self, "models", tuple(self.models))
        for b in self.models:
            check_choice("models", b, BRDF_NAMES)
        check_bool("dgmc", self.dgmc)
        check_bool("integrate", self.integrate)
        check_bool("cast_shadows", self.cast_shadows)
        if not isinstance(self.shadow_config, ShadowConfig):
            raise TypeError(f"shadow_config: expected gpps.pipeline.shadows.ShadowConfig, got "
                            f"{type(self.shadow_config).__name__}")
        if self.device_rounds is not None:
            check_bool("device_rounds", self.device_rounds)
        check_number("seed", self.seed, lo=0, integer=True)
        check_number("tol", self.tol, lo=0.0)
        check_number("tol_normals_deg", self.tol_normals_deg, lo=0.0)
        if not isinstance(self.estimate, (tuple, list)) or not all(isinstance(e, str) for e in self.estimate):
            raise TypeError(f"estimate: expected a tuple of parameter names, got {self.estimate!r}")
        object.__setattr__(self, "estimate", tuple(self.estimate))
        bad = [e for e in self.estimate if e not in _RANGES]
        if bad:
            raise ValueError(f"estimate: expected names from {sorted(_RANGES)}, got {bad}")
        check_number("material_samples", self.material_samples, lo=16, integer=True)
        check_number("material_observations", self.material_observations, lo=1, integer=True)
        check_number("material_grid", self.material_grid, lo=1, hi=25, integer=True)
        check_number("material_evals", self.material_evals, lo=0, integer=True)
        check_number("material_trim", self.material_trim, lo=0.0, hi=0.5)
        check_number("material_starts", self.material_starts, lo=1, integer=True)
        check_bool("material_warm", self.material_warm)
        if self.material_warm_iters is not None:
            check_number("material_warm_iters", self.material_warm_iters, lo=1, integer=True)
        check_number("cold_rounds", self.cold_rounds, lo=1, integer=True)
        check_number("roughness_window", self.roughness_window, lo=0.5)
        if not isinstance(self.dgmc_config, DGMCConfig):
            raise TypeError(f"dgmc_config: expected DGMCConfig, got {type(self.dgmc_config).__name__}")
        if not isinstance(self.solver, SolverConfig):
            raise TypeError(f"solver: expected SolverConfig, got {type(self.solver).__name__}")
        if self.solver.solver == "none":
            raise ValueError("solver: expected a nonlinear solver ('lm', 'dogleg' or 'bfgs') for RON, got 'none'")
        if self.integrator is not None:
            if not isinstance(self.integrator, IntegratorConfig):
                raise TypeError(f"integrator: expected IntegratorConfig or None, got {type(self.integrator).__name__}")
        if self.final_integrator is not None:
            if not isinstance(self.final_integrator, IntegratorConfig):
                raise TypeError(f"final_integrator: expected IntegratorConfig or None, got "
                                f"{type(self.final_integrator).__name__}")
        if self.material_rule == "depth-rms" and any(e not in ("roughness",) for e in self.estimate):
            raise ValueError("material_rule: 'depth-rms' (4.19) estimates the Cook-Torrance roughness only; "
                             f"got estimate={self.estimate}")


@dataclass
class RONResult:
    """Output of :meth:`RON.run`.

    Attributes:
        normals: (H, W, 3) float32 unit normals (gpps frame), zeros outside the mask.
        albedo: (H, W, 3) float32 RGB albedo.
        depth: (H, W) float32 depth (> 0 inside ``depth_mask``, 0 outside), or
            None when integration was off.
        depth_mask: (H, W) bool pixels with a depth.
        material: the final material (estimated parameters filled in).
        estimated: ``{name: value}`` of the parameters RON estimated.
        energy: mean squared residual per observation and channel, per round.
        normal_change_deg: mean normal change per round (round 1: from the start).
        rounds: rounds run.
        converged: whether the change criteria were met before the round cap.
        residual, iterations, flags: per pixel, from the final solve (see PSResult).
        highlight: (H, W) bool DGMC highlight region (False without DGMC).
        start_normals: (H, W, 3) the round-1 start: least squares, and on highlight
            pixels the DGMC start (with ``DGMCConfig.start="front"``, the solved
            normal of the neighbour each was started from; least squares where no
            ring reached).
        material_fit: per material update: the parameters, energy, evaluations,
            and, for a fit with a grid (the first), ``ambiguity`` (:func:`material_ambiguity`) and
            ``identifiable`` (its ``ambiguity_deg`` at most :data:`AMBIGUITY_DEG`; None without a grid); ``kept``:
            a later fit found no candidate lower than the round's material and returned it as it was (the rounds
            then stop there, converged, when nothing else feeds the next round: no point lights, no shadow pass).
        integration_residual: relative residual of the last integration.
        timings: seconds per stage (summed over rounds) and ``total``; ``shadows``: the cast-shadow pass.
        shadows: per cast-shadow pass (``cast_shadows``; one after each round but the last): ``round`` (the
            round whose solves it feeds; a pass that ends the rounds, see ``RONConfig.cast_shadows``, feeds
            none), ``dropped`` (observations left out), ``kept_pixels`` (pixels that kept
            their observations, ``shadow_few="keep"``), ``few_pixels`` (pixels left with fewer than 3).
        shadowed: (N, H, W) bool, the observations the last pass left out (None without a pass).
        refinement: the depth refinement's record (``RONConfig.refine``): ``energy`` per accepted step
            (robust misfit, image units squared), ``accepted``, ``rejected``, ``sigma`` (Cauchy's scale); None
            without it.
        warnings: messages of the :class:`gpps.GppsWarning` warnings issued
            (an estimate on its search bound, rounds that did not converge).
    """

    normals: np.ndarray
    albedo: np.ndarray
    depth: np.ndarray | None
    depth_mask: np.ndarray
    material: Material
    estimated: dict
    energy: list
    normal_change_deg: list
    rounds: int
    converged: bool
    residual: np.ndarray
    iterations: np.ndarray
    flags: np.ndarray
    highlight: np.ndarray
    start_normals: np.ndarray
    material_fit: list = field(default_factory=list)
    integration_residual: float | None = None
    timings: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    shadows: list = field(default_factory=list)
    shadowed: np.ndarray | None = None
    refinement: dict | None = None


# the per-pixel outputs RON reads back from a solve
_OUTPUTS = ("normals", "albedo", "residual", "iterations", "flags", "cond")

#: ``RON.run``'s images when :meth:`RON.rerun` solves the frame the last run left on the solver's device
_RESIDENT = object()


def _part(progress, a: float, b: float):
    """A solver progress callback ``(done, total, message)`` mapped onto ``progress(fraction)`` in [a, b]."""
    if progress is None:
        return None
    return lambda d, t, msg: progress(a + (b - a) * d / max(t, 1.0))


def estimate_on_bound(name: str, value: float, rel: float = 0.01) -> str | None:
    """A warning message when ``value`` lies within ``rel`` of its log search range from a bound of it."""
    lo, hi = _RANGES[name]
    t = (np.log(value) - np.log(lo)) / (np.log(hi) - np.log(lo))
    if t <= rel or t >= 1.0 - rel:
        side = "lower" if t <= rel else "upper"
        return (f"material: the estimated {name} {value:.4g} is at the {side} bound of its search range "
                f"[{lo:g}, {hi:g}]: the images do not determine it (or it lies outside); treat it as unreliable")
    return None


def normal_change_deg(normals, prev, mask) -> float:
    """Mean angle (degrees) between two normal maps over ``mask``: ``atan2(|a x b|, a . b)`` in float64
    (accurate for small angles and vectors of any length; 90 degrees where either is zero), as the
    device rounds reduce it (:mod:`gpps.kernels.ron`).  (The earlier ``arccos`` of a float32 dot product
    read any change below about 0.02 degrees as 0 or 0.02: one float32 step below 1.)"""
    a = np.asarray(normals)[mask].astype(np.float64)
    b = np.asarray(prev)[mask].astype(np.float64)
    if a.shape[0] == 0:
        return 0.0
    ang = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1))
    zero = (np.sum(a * a, -1) == 0) | (np.sum(b * b, -1) == 0)
    return float(np.degrees(np.where(zero, np.pi / 2, ang)).mean())


def depth_rms_roughness(depth, mask, camera, *, window: float = 4.0) -> float:
    """The seed's roughness update (4.19) with its square restored.

    ``m = sqrt(1/n sum (z - zbar)^2)``, where ``zbar`` is the mean surface: the
    depth smoothed by a normalised Gaussian of scale ``window`` pixels inside
    the mask.  To make ``m`` a slope (dimensionless, like the Beckmann
    roughness) the deviation is measured in units of the lateral extent of the
    window (``window`` pixel footprints: ``pixel_size`` orthographic,
    ``depth / f`` perspective).

    Args:
        depth: (H, W) depth (scene units, > 0 in the mask).
        mask: (H, W) bool.
        camera: the camera (footprint of a pixel).
        window: Gaussian scale in pixels.

    Returns:
        m (>= 0).
    """

    m = as_mask("mask", mask)
    z = as_array("depth", depth, shape=m.shape).astype(np.float64)
    w = m.astype(np.float64)
    zs = gaussian_filter(np.where(m, z, 0.0), window) / np.maximum(gaussian_filter(w, window), 1e-12)
    if camera.is_perspective:
        foot = np.abs(z) / np.sqrt(camera.fx * camera.fy)
    else:
        foot = np.full_like(z, float(camera.pixel_size))
    dev = (z - zs) / (window * foot)
    return float(np.sqrt(np.mean(dev[m] ** 2)))


def default_integrator(camera) -> IntegratorConfig:
    """RON's integrator when ``RONConfig.integrator`` is None: multigrid to a relative residual of 1e-5;
    perspective cameras with BiNI's n_z^2 confidence weighting (grazing rim normals, a few degrees off with 3
    images, otherwise dominate the log-depth: sphere 64^2, 2.6 % -> 0.2 % of the range), orthographic ones uniform
    (with n_z^2 weights a 256^2 sphere under point lights came out 10 % off)."""
    return IntegratorConfig(tol=1e-5, weighting="normal" if camera.is_perspective else "uniform")


class RON:
    """Algorithm 2 on N images: buffers (two pixel solvers, one integrator) allocated once.

    Args:
        shape: (N, H, W).
        camera: :class:`gpps.camera.Orthographic` or :class:`Perspective`.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N).
        material: the model and the starting / known parameters.
        mask: (H, W) bool, the pixels to reconstruct.
        config: :class:`RONConfig`.
        device: Warp device (None: CUDA if present).
    """

    def __init__(self, shape, camera, lights, material: Material, mask, config: RONConfig | None = None, device=None):
        self.config = RONConfig() if config is None else config
        if not isinstance(self.config, RONConfig):
            raise TypeError(f"config: expected RONConfig, got {type(self.config).__name__}")
        if not isinstance(material, Material):
            raise TypeError(f"material: expected gpps.material.Material, got {type(material).__name__}")
        allowed = estimable_parameters(material.brdf)
        bad = [e for e in self.config.estimate if e not in allowed]
        if bad:
            raise ValueError(f"estimate: {material.brdf} has the parameters {list(allowed)}, got {bad}")
        if self.config.models and (set(self.config.estimate) != set(allowed) or self.config.material_rule != "photometric"):
            raise ValueError(f"models: comparing models needs every lobe parameter of {material.brdf} estimated "
                             f"({list(allowed)}) by the photometric rule, got estimate={list(self.config.estimate)}, "
                             f"material_rule={self.config.material_rule!r}")
        if self.config.material_rule == "depth-rms" and self.config.estimate and material.brdf != "cook-torrance":
            raise ValueError(f"material_rule: 'depth-rms' needs the cook-torrance model, got {material.brdf!r}")
        self.device = resolve_device(device)
        n, h, w = (int(s) for s in shape)
        self.shape = (n, h, w)
        self.mask = as_mask("mask", mask, (h, w))
        self.camera = camera
        self.lights = lights
        self.material = material
        self.point = isinstance(lights, PointLights)
        self.solver = PixelSolver(self.shape, camera, lights, material, self.config.solver, device=self.device)
        self._fit_solver = None
        self._scorers: dict = {}  # the material fit's resident sample per model (MaterialScorer), built at its first fit
        self._scored: dict = {}  # the inputs each holds
        self._searches: dict = {}  # NelderMeadSearch per (model, dimension), on its model's scorer
        self._batch = max(25, self.config.material_grid ** max(len(self.config.estimate), 1))
        self._last_move = None  # log-space move of the last material fit (sizes the next fit's simplex)
        self._frame_key = self._frame_depth = None  # the frame on the solver's device (see _frame)
        self._noise = None  # the run's noise levels, when its caller gave them (run)
        self._checked = False  # whether the run's caller checked its observations (run)
        self._solver_mask = None  # the mask in the solver's buffer, when RON set it (see _set_mask)
        self._rounds = None  # the device side of the rounds (DeviceRounds), built at the first run that uses it
        self._rounds_integ = False  # whether self._rounds integrates (step 3 on the device)
        self._shadows = None  # the cast-shadow pass (RoundShadows), built at the first run that uses it
        self._dgmc = None  # DGMC's stage (DeviceDGMC), built at the first run that uses it
        self._front = None  # the solved front's stage on the solver (DeviceFront), likewise
        self._prefetch = None  # the first run's compiles ahead (KernelPrefetch), kept until close
        self._ahead: list = []  # modules a flow queued behind the plan (compile_ahead)
        self.integrator = None
        if self.config.integrate:
            icfg = self.config.integrator if self.config.integrator is not None else default_integrator(camera)
            self.integrator = Integrator(self.mask, camera=camera, config=icfg, device=taichi_device(self.device))

    def close(self) -> None:
        """Free the integrator's Taichi fields, the device rounds', the cast-shadow pass's, DGMC's, the front's, the
        material scorer's and searches' and the solvers' buffers (the RON refuses work afterwards)."""
        if self._prefetch is not None:
            self._prefetch.close()
            self._prefetch = None
        if self._rounds is not None:
            self._rounds.close()
            self._rounds = None
        if self._shadows is not None:
            self._shadows.close()
            self._shadows = None
        for name in ("_dgmc", "_front"):
            stage = getattr(self, name, None)
            if stage is not None:
                stage.close()
                setattr(self, name, None)
        for search in self._searches.values():
            search.close()
        self._searches.clear()
        for scorer in self._scorers.values():
            scorer.close()
        self._scorers.clear()
        if self.integrator is not None:
            self.integrator.close()
            self.integrator = None
        # the solvers' buffers go back to the process's pool (gpps.pipeline.buffers): the next RON of this
        # size (a loop over captures, gpps batch's workers) takes them instead of allocating its own
        for name in ("solver", "_fit_solver"):
            stage = getattr(self, name, None)
            if stage is not None:
                stage.close()
                setattr(self, name, None)

    def kernel_plan(self, *, warm_start: bool = False, compared: bool = True) -> list:
        """The Warp kernels and modules a :meth:`run` launches, in about the order of their first launch: what
        :class:`gpps.pipeline.prefetch.KernelPrefetch` compiles ahead on a first run (an empty kernel cache).

        Built from the stages' own choices (:func:`gpps.pipeline.solver.solver_kernels`,
        :func:`gpps.pipeline.material.scorer_kernels`, the stages' ``kernel_modules``); the Taichi kernels and the
        stages a run builds only for unusual settings are left out (they compile at their first launch, as
        without a plan).  The compared models' solve kernels come last: only the chosen model's are launched.
        ``tests/test_prefetch.py`` checks that a run launches no gpps module outside the plan.

        Args:
            warm_start: the plan of a run from given start normals (``run(start=...)``): no least squares, no DGMC.
            compared: include the solve kernels of the compared models (``RONConfig.models``), of which the run
                launches the chosen one's only.
        """
        c, n, dev, brdf = self.config, self.shape[0], self.device, self.material.brdf
        plan: list = []
        if not warm_start:
            plan += solver_kernels(replace(c.solver, solver="none", smoothness=0.0), brdf, dev, n)
            if c.dgmc and brdf != "lambertian":
                plan += DeviceDGMC.kernel_modules()
        plan += solver_kernels(c.solver, brdf, dev, n)
        plan += DeviceFront.kernel_modules()
        if c.device_rounds is not False and c.rounds > 1:
            plan += DeviceRounds.kernel_modules()
        models = (brdf,) + tuple(b for b in c.models if b != brdf)
        if c.estimate and c.material_rule == "photometric":
            fit = replace(c.solver, starts=c.material_starts, neighbour_radius=0, smoothness=0.0, warm_start=False)
            for b in models:
                plan += scorer_kernels(fit, b, dev, n)
            if self._device_loop():
                plan += NelderMeadSearch.kernel_modules()
        if c.cast_shadows and c.integrate and c.rounds > 1:
            plan += RoundShadows.kernel_modules()
        if compared:
            for b in models[1:]:
                plan += solver_kernels(c.solver, b, dev, n)
        return plan

    def compile_ahead(self, kernels) -> None:
        """Queue more Warp kernels or modules behind :meth:`kernel_plan`'s: those of stages a flow launches after the
        run (the interreflection compensation's), compiled ahead at the first run as the plan is (at once when the
        first run has begun).  A no-op with ``GPPS_PREFETCH=0``."""
        kernels = list(kernels)
        self._ahead += kernels
        if self._prefetch is not None:
            self._prefetch.submit(kernels)

    def _compile_ahead(self, warm_start: bool) -> None:
        """At the first run: :meth:`kernel_plan`'s modules compiled ahead on helper threads
        (:mod:`gpps.pipeline.prefetch`; ``GPPS_PREFETCH=0`` turns it off).  Each module already in the kernel cache
        costs the helper a hash; a loaded one nothing."""
        if self._prefetch is not None or not prefetch_enabled():
            return
        self._prefetch = KernelPrefetch(self.device)
        # (the compared models' solves: all but one compiled for nothing, on host cores the GPU's solves leave
        # idle.  On the CPU they are the material scorers' modules, compiled for the comparison anyway:
        # gpps.kernels.solve.batched_in_solve_module)
        self._prefetch.submit(self.kernel_plan(warm_start=warm_start) + self._ahead)

    # ------------------------------------------------------------------ steps

    def _frame(self, images, depth, valid) -> None:
        """The frame on the solver's device: uploaded once per run (images, observation mask, noise
        levels); later solves change only the mask, start normals, config or material there, and a new
        depth estimate (point lights, each round) is copied in alone.  ``images`` :data:`_RESIDENT`
        (:meth:`rerun`): the frame already there, uploaded by an earlier run."""
        s = self.solver
        key = self._frame_key if images is _RESIDENT else (id(images), id(valid))
        if self._frame_key != key:
            cfg = s.config
            if cfg.warm_start:
                s.set_config(replace(cfg, warm_start=False))
            s.upload(images, self.mask, depth=depth, valid=valid,
                     noise=self._noise if cfg.noise_level is None else None, checked=self._checked)
            s.set_config(cfg)
            self._frame_key, self._frame_depth = key, depth
            self._solver_mask = self.mask
        elif depth is not self._frame_depth:
            s.set_depth(depth, mask=self.mask)
            self._frame_depth = depth

    def _set_mask(self, mask) -> None:
        """The solver's mask, copied to the device only when it is not the one RON last set there."""
        if mask is not self._solver_mask:
            self.solver.set_mask(mask)
            self._solver_mask = mask

    def _set_start(self, init) -> None:
        """Start normals of the warm solve: a host array (copied in) or a Warp buffer on the solver's
        device (the device rounds' previous normals: copied device to device)."""
        if isinstance(init, np.ndarray):
            self.solver.set_start(init)
        else:
            warp().copy(self.solver.normals, init)

    def _solve(self, images, depth, valid, material, *, starts=None, init=None, init_mask=None, mask=None,
               cold: bool = True, progress=None, fetch: bool = True, load=None) -> dict | None:
        """Steps 1/2/5: cold multi-start solve of ``mask``; where ``init`` is given, also a
        warm-started solve from it (on ``init_mask``); the lower residual wins per pixel, merged on
        the device (:meth:`PixelSolver.merge_saved`).  ``cold=False`` (needs ``init`` on the whole
        mask): only the warm solve, with the configured neighbour pass for the under-determined
        pixels.  The frame stays on the device between solves (:meth:`_frame`); only the outputs
        RON reads come back.  ``progress(fraction)``: on the CPU, told as the solves' row ranges
        finish (the cold solve is the first 0.8 of a cold+warm pair).  ``init``: (H, W, 3) host
        normals or a Warp buffer of them on the solver's device.  ``fetch=False``: nothing comes
        back (None; the outputs stay in the solver's buffers).  ``load``: ``load(seconds, None, message)``, told
        every second while a solve's kernels compile before it (:meth:`PixelSolver.load`; a later round's solve
        can need kernels the first did not: another model, the warm configuration)."""
        s = self.solver

        def step(part):
            if load is not None:
                s.load(progress=load)  # (a no-op once loaded)
            s.step(part)

        cfg = self.config.solver
        m = self.mask if mask is None else mask
        s.set_material(material)
        self._frame(images, depth, valid)
        try:
            if not cold:
                if init is None or init_mask is not None:
                    raise ValueError("cold: False needs init normals on the whole mask")
                s.set_config(replace(cfg, warm_start=True, starts=1))
                self._set_mask(m)
                self._set_start(init)
                step(_part(progress, 0.0, 1.0))
                return s.fetch(_OUTPUTS) if fetch else None
            s.set_config(cfg if starts is None else replace(cfg, starts=starts))
            share = 0.8 if init is not None else 1.0
            self._set_mask(m)
            step(_part(progress, 0.0, share))
            if init is not None:
                im = m if init_mask is None else (init_mask & m)
                if im.any():
                    # under-determined pixels keep the neighbour pass of the cold solve
                    s.save()
                    s.set_config(replace(cfg, warm_start=True, starts=1, neighbour_radius=0, smoothness=0.0))
                    self._set_mask(im)
                    self._set_start(init)
                    step(_part(progress, share, 1.0))
                    s.merge_saved()
            return s.fetch(_OUTPUTS) if fetch else None
        finally:
            s.set_config(cfg)

    def _energy(self, residual, mask) -> float:
        r = residual[mask].astype(np.float64)
        return float(np.mean(r * r))

    def _sample(self, highlight) -> np.ndarray:
        """A fixed pixel sample for the material fit: highlight pixels (up to half), the rest at random."""
        c = self.config
        rng = np.random.default_rng(c.seed)
        idx = np.flatnonzero(self.mask.ravel())
        floor = min(500, c.material_samples)
        k = min(int(np.clip(c.material_observations // self.shape[0], floor, c.material_samples)), idx.size)
        hl = np.flatnonzero((highlight & self.mask).ravel())
        take = rng.choice(hl, min(hl.size, k // 2), replace=False) if hl.size else np.zeros(0, np.int64)
        left = self.mask.ravel().copy()
        left[take] = False
        rest = np.flatnonzero(left)  # (np.setdiff1d(idx, take): the same ascending indices, without its sort)
        take = np.concatenate([take, rng.choice(rest, min(rest.size, k - take.size), replace=False)])
        s = np.zeros(self.mask.size, bool)
        s[take] = True
        return s.reshape(self.mask.shape)

    def _fit_energy(self, images, depth, valid, material, sample) -> float:
        if self._fit_solver is None:
            cfg = replace(self.config.solver, starts=self.config.material_starts, neighbour_radius=0,
                          smoothness=0.0, warm_start=False)
            self._fit_solver = PixelSolver(self.shape, self.camera, self.lights, material, cfg, device=self.device)
        self._fit_solver.set_material(material)
        # (the frame's noise levels, as the scorer's: MaterialScorer.upload_from)
        out = self._fit_solver.run(images, sample, depth=depth, valid=valid, noise=self.solver.noise_level)
        r = np.sort(out["residual"][sample].astype(np.float64) ** 2)
        keep = max(1, int(round(r.size * (1.0 - self.config.material_trim))))
        return float(np.mean(r[:keep]))

    def _scorer_for(self, images, depth, valid, sample, material) -> MaterialScorer:
        """The resident sample (:class:`MaterialScorer`), built at the first fit and uploaded again only
        when the images, depth or observation mask change (point lights move the depth each round)."""
        c = self.config
        inputs = (images, depth, valid, sample)
        key = material.brdf  # (one scorer a model: RONConfig.models compares several)
        if key not in self._scorers:
            fit = replace(c.solver, starts=c.material_starts, neighbour_radius=0, smoothness=0.0, warm_start=False)
            self._scorers[key] = MaterialScorer(self.shape, self.camera, self.lights, material, fit,
                                                max_samples=int(sample.sum()), max_candidates=self._batch,
                                                trim=c.material_trim, warm_max_iters=c.material_warm_iters,
                                                device=self.device)
        held = self._scored.get(key)
        if held is None or any(a is not b for a, b in zip(held, inputs)):
            scorer = self._scorers[key]
            frame = self._frame_key is not None and self._frame_key[0] == id(images)
            if frame and self._frame_key[1] == id(valid) and depth is self._frame_depth:
                # the solver holds this frame, observation mask and depth: the sample is gathered there
                scorer.upload_from(self.solver, sample)
            else:  # (e.g. the shadow rounds' observations): from the host, with the frame's noise levels
                scorer.upload(images, sample, depth=depth, valid=valid,
                              noise=self.solver.noise_level if frame else None)
            self._scored[key] = inputs
        return self._scorers[key]

    def _score(self, images, depth, valid, materials: list, sample, *, warm: bool = False,
               progress=None, normals: list | None = None) -> np.ndarray:
        """The sampled fit energy of each candidate material, a batch at a time.

        ``materials``: a list of :class:`Material`, or ``(material, names, values (K, len(names)))``: ``material``
        with its lobe parameters ``names`` set to each row (:meth:`MaterialScorer.lobe_candidates`, no Material
        built per candidate).

        The sample pixels stay resident in a :class:`gpps.pipeline.material.MaterialScorer` (uploaded again
        only when the images, depth or observation mask change: point lights move the depth each round);
        each batch of up to ``max_candidates`` candidates is one launch.  The energies equal
        :meth:`_fit_energy`'s (tests/test_material_device.py).  ``warm``: from the scorer's
        warm start (:meth:`MaterialScorer.set_start`), one start per pixel.  ``progress(done, total,
        message)`` is passed to the scorer, which reports inside a batch on the CPU (chunked launches).
        ``normals``: a list that receives each batch's sample normals, (K, P, 3) (:func:`material_ambiguity`).
        """
        if isinstance(materials, tuple):  # (material, names, values (K, len(names))): lobe candidates
            base, names, values = materials
            scorer = self._scorer_for(images, depth, valid, sample, base)
            batches = [scorer.lobe_candidates(base, names, values[i:i + self._batch])
                       for i in range(0, len(values), self._batch)]
        else:
            scorer = self._scorer_for(images, depth, valid, sample, materials[0])
            batches = [materials[i:i + self._batch] for i in range(0, len(materials), self._batch)]
        out = []
        for b in batches:
            scorer.step(b, warm=warm, progress=progress)
            out.append(scorer.fetch())
            if normals is not None:
                normals.append(scorer.fetch_pixels(("normals",))["normals"])
        return np.concatenate(out)

    def _select_model(self, images, depth, valid, material, sample, *, progress=None) -> tuple[Material, dict]:
        """Step 4 of the first round with several models (``RONConfig.models``): each model's parameters
        fitted (:meth:`_fit_material`, grid and search, on the same sample pixels); the configured model is kept
        unless another's sampled energy is lower beyond the sample's noise (:func:`energy_drop_evidence`: the
        pixels' paired squared residuals at each model's best parameters), and of those that are, the lowest
        energy wins.  The energies compare directly: the same pixels, observations and trimmed mean of squared
        residuals, each model at its own best parameters.  ``info["models"]``: each model's energy;
        ``info["evidence"]``: per other model, the test's numbers.
        """
        c = self.config
        cands = [material.brdf] + [b for b in c.models if b != material.brdf]
        report = progress or (lambda *a: None)
        fits = []
        energies = {}
        for i, brdf in enumerate(cands):
            mat = material if brdf == material.brdf else Material.default_for(brdf)
            names = c.estimate if brdf == material.brdf else LOBE_PARAMETERS[brdf]

            def part(d, t, msg, i=i, brdf=brdf):
                report(i + d / max(t, 1.0), len(cands), f"{brdf} {msg}")

            self._last_move = None
            got, info = self._fit_material(images, depth, valid, mat, sample, grid=True, progress=part, names=names)
            energies[brdf] = info["energy"]
            fits.append((got, info, self._last_move, self._sample_residuals(images, depth, valid, got, sample)))
        evidence = {}
        best = fits[0]
        for (got, info, move, res), brdf in zip(fits[1:], cands[1:]):
            ok = np.isfinite(fits[0][3]) & np.isfinite(res)  # (a pixel a model's solve left without a residual
            # takes no part: the test compares what both models fitted)
            ev = energy_drop_evidence(fits[0][3][ok], res[ok], c.material_trim)
            evidence[brdf] = ev
            if ev["significant"] and info["energy"] < best[1]["energy"]:
                best = (got, info, move, res)
        got, info, self._last_move, _ = best
        info = dict(info, models=energies, evidence=evidence)
        return got, info

    def _sample_residuals(self, images, depth, valid, material, sample) -> np.ndarray:
        """(P,) RMS residual of each sample pixel solved with ``material`` (cold, as the first fit scores)."""
        scorer = self._scorer_for(images, depth, valid, sample, material)
        scorer.step([material])
        return scorer.fetch_pixels(("residual",))["residual"][0].astype(np.float64)

    def _fit_material(self, images, depth, valid, material, sample, *, grid: bool, progress=None,
                      normals=None, names=None) -> tuple[Material, dict]:
        """Step 4, photometric: the estimated parameters minimising the sampled energy.

        In log-parameter space: a grid over the whole range (first round), then ``material_search``
        from the best point.  Candidates are scored in batches (:meth:`_score`); ``progress(done,
        total, message)`` is told after each batch.  With ``material_warm`` and no grid (later rounds)
        the candidates are solved from one start per pixel: ``normals`` (H, W, 3), the round's
        normals (solved with ``material``): a host array, or the solver's device buffer (gathered
        at the sample pixels there).  ``names``: the parameters to fit (None: ``RONConfig.estimate``; the
        model's own with :meth:`_select_model`).
        """
        c = self.config
        names = c.estimate if names is None else tuple(names)
        lo = np.log([_RANGES[k][0] for k in names])
        hi = np.log([_RANGES[k][1] for k in names])
        evals = []
        report = progress or (lambda *a: None)

        warm = False
        device_scored = 0  # candidates the device search scored (NelderMeadSearch)
        restarted = False  # Nelder-Mead ran again from a bound (search_from)

        def score(xs, normals=None):
            xs = [np.clip(x, lo, hi) for x in xs]
            n0 = len(evals)

            def inside(d, t, msg):  # within this batch: candidates scored so far, in fractions
                report(n0 + len(xs) * d / max(t, 1.0), n0 + len(xs) + c.material_evals, msg)

            vals = self._score(images, depth, valid, (material, names, np.exp(np.array(xs, np.float64))),
                               sample, warm=warm, progress=inside if len(xs) > 4 else None, normals=normals)
            evals.extend(vals.tolist())
            report(len(evals), len(evals) + c.material_evals, f"material: {len(evals)} candidates scored")
            return vals

        self._scorer_for(images, depth, valid, sample, material)  # (the sample upload, once)
        report(0, c.material_evals, "material: sample uploaded")
        x0 = np.clip(np.log([lobe_value(material, k) for k in names]), lo, hi)
        step = (hi - lo) / max(c.material_grid - 1, 1)
        ambiguity = None
        if grid and c.material_grid > 1 and names:
            axes = [np.linspace(a, b, c.material_grid) for a, b in zip(lo, hi)]
            pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(names))
            grid_normals: list = []
            vals = score(list(pts), normals=grid_normals)
            x0 = pts[int(np.argmin(vals))]
            noise = np.asarray(self.solver.noise_level, np.float64)
            ambiguity = material_ambiguity(vals, np.concatenate(grid_normals),
                                           float(np.median(noise)) ** 2 if noise.size else 0.0)
            step = step / 2
            xatol = _FIRST_XATOL
        else:
            move = np.abs(self._last_move) if self._last_move is not None else np.full(len(names), np.inf)
            step = np.clip(2.0 * move, *_LATER_STEP)
            xatol = _XATOL
            if c.material_warm and normals is not None:
                scorer = self._scorer_for(images, depth, valid, sample, material)
                if isinstance(normals, np.ndarray):
                    scorer.set_start(normals[sample])
                else:
                    scorer.set_start(frame=normals)
                warm = True
        if c.material_evals > 0 and names and c.material_search != "pattern":
            scored = [0]  # candidates the device search scored (NelderMeadSearch)

            def search_from(x_start):
                """Nelder-Mead from ``x_start`` (:func:`initial_simplex`, every point clipped to the box):
                ``(energy, x, energy at x_start)``."""
                simplex = initial_simplex(x_start, step, lo, hi)
                if self._device_loop() and c.material_evals > len(names) + 1:
                    # every step on the device, and there the initial simplex too (its first pass) where its
                    # vertices fit a pass; else the simplex in one batch from the host first
                    search = self._search_for(material.brdf, len(names))
                    f_init = None if search.scores_simplex else score(list(simplex))
                    search.upload(material, names, simplex, f_init, lo=lo, hi=hi, maxfev=c.material_evals,
                                  xatol=xatol)
                    search.step(warm=warm)
                    got = search.fetch()
                    scored[0] += got["scored"]
                    report(len(evals) + scored[0], len(evals) + scored[0],
                           f"material: {len(evals) + scored[0]} candidates scored ({got['steps']} steps on the "
                           "device)")
                    return got["energy"], got["x"], float(f_init[0] if f_init is not None else got["f_start"])
                # on CUDA a launch costs its slowest thread, not its candidates: score every point a step may
                # read in one batch (the same trajectory: Nelder-Mead reads only what it needs); the start is
                # scored with the initial simplex
                return self._nelder_mead(score, simplex, None, c.material_evals, xatol, bounds=(lo, hi),
                                         speculate=self._speculate())

            fx, xb, f_start = search_from(x0)
            best = (fx, np.clip(xb, lo, hi)) if fx < f_start else (f_start, x0)
            if on_bound(best[1], lo, hi) and not np.array_equal(best[1], x0):
                # a simplex that met a bound can have collapsed into its face and stopped there (clipped points
                # keep no extent across it): once more from there, with a fresh simplex a step inside (from where
                # it started, that simplex is the one just searched: nothing to gain)
                fr, xr, _ = search_from(best[1])
                restarted = True
                if fr < best[0]:
                    best = (fr, np.clip(xr, lo, hi))
            device_scored = scored[0]
        else:
            best = (float(score([x0])[0]), x0)
            if c.material_evals > 0 and names:  # (a model without lobe parameters: its one energy)
                best = self._pattern_search(score, best, step, lo, hi, c.material_evals)
        own = np.log([lobe_value(material, k) for k in names])
        start = np.clip(own, lo, hi)
        self._last_move = best[1] - start
        # a later fit whose best point is its start, the round's material itself (inside the box): kept as it is
        kept = not grid and bool(names) and np.array_equal(best[1], start) and np.array_equal(start, own)
        values = ({k: lobe_value(material, k) for k in names} if kept
                  else dict(zip(names, (float(v) for v in np.exp(best[1])))))
        info = {"rule": "photometric", "search": c.material_search, "warm": warm, "values": values, "energy": best[0],
                "evaluations": len(evals) + device_scored, "grid": bool(grid), "restarted": restarted,
                "identifiable": None if ambiguity is None else ambiguity["ambiguity_deg"] <= AMBIGUITY_DEG,
                "kept": kept}
        if ambiguity is not None:
            info["ambiguity"] = ambiguity
        return (material if kept else with_lobe(material, values)), info

    def _material_settled(self, fits: list) -> bool:
        """Whether the material is at its fixed point: the last fit was a later (fine) one and it moved every
        estimated parameter by less than its own resolution (``_XATOL``, log units) from the material this round's
        normals were solved with.

        With the normals also changed by less than ``tol_normals_deg``, the round is then a fixed point of
        Algorithm 2 (5): the next fit would start from the same material with normals it cannot tell apart, so
        another round reproduces this one; the relative energy test need not hold as well.  That test alone
        misreads the rounds near the noise floor, where the energy is the noise's and its last digits move by more
        than ``tol`` between rounds whose normals and material no longer change (the 256^2 x 3 case of issue 20: a
        fourth fit that returned the third's values exactly, and a fifth round whose normals moved 8e-6 deg).
        """
        c = self.config
        if not (c.estimate and c.material_rule == "photometric" and fits) or self._last_move is None:
            return False
        # (a photometric fit records whether it had the grid; the depth-rms rule's records do not)
        return not fits[-1].get("grid", True) and bool(np.all(np.abs(self._last_move) < _XATOL))

    def _device_loop(self) -> bool:
        """Whether Nelder-Mead's steps run on the device (``RONConfig.material_loop``)."""
        loop = self.config.material_loop
        return loop == "device" or (loop == "auto" and self.device.startswith("cuda"))

    def _search_for(self, brdf: str, dims: int) -> NelderMeadSearch:
        """The device search on model ``brdf``'s scorer (built at its first use, kept with the scorer: its
        CUDA graphs replay in the later rounds)."""
        key = (brdf, int(dims))
        if key not in self._searches:
            self._searches[key] = NelderMeadSearch(self._scorers[brdf], dims)
        return self._searches[key]

    def _speculate(self) -> int:
        """How far Nelder-Mead scores ahead (:meth:`_nelder_mead`): on the CPU nothing (a candidate costs its
        work); on CUDA a launch of a few candidates costs its slowest pixel solve, so a step's points together.
        Two steps ahead (~40 candidates a batch, 34 launches instead of 50 on the 256^2 x 3 case) made the material
        stage slower on the H100, 44 -> 56 ms (perf/material_speculation.py): the larger launches and batches cost
        more than the round trips they saved."""
        return 1 if self.device.startswith("cuda") else 0

    @staticmethod
    def _nelder_mead(score, simplex, f0: float | None, maxfev: int, xatol: float, *, speculate: int = 0,
                     bounds=None):
        """Nelder-Mead (scipy's ``method="Nelder-Mead"``, standard coefficients, ``fatol`` infinite; with
        ``bounds``, scipy's bounded form: every new point clipped to the box) that
        scores in batches: the initial simplex in one (vertex 0 too unless ``f0`` is given), and with
        ``speculate`` the reflection, expansion and both contractions of a step in one (a shrink's vertices
        always together).  The trajectory and the result do not depend on ``speculate``: the method reads
        only the values it needs, and ``maxfev`` counts only those.  Converged when every vertex lies within
        ``xatol`` of the best (log units).

        Args:
            score: ``score(xs) -> (K,) energies`` of a list of points.
            simplex: (d + 1, d) initial simplex, vertex 0 the start.
            f0: the energy at vertex 0, or None (scored with the rest of the initial simplex).
            maxfev: the most evaluations the method needs (the initial simplex included).
            xatol: simplex size at convergence.
            speculate: score every candidate point of a step in one batch (0 or 1; True: 1).
            bounds: ``(lo, hi)``, (d,) each: the box the points are clipped to (the initial simplex must lie
                in it: :func:`initial_simplex`); None: unbounded.  A point outside the box would be scored at its
                clipped projection while the simplex kept it: a plateau the search drifts on and stops.

        Returns:
            ``(energy, x, f0)`` of the best vertex, and the energy at vertex 0.
        """
        rho, chi, psi, sigma = 1.0, 2.0, 0.5, 0.5
        if bounds is None:
            def box(x):
                return x
        else:
            lo_b, hi_b = (np.asarray(b, np.float64) for b in bounds)

            def box(x):
                return np.clip(x, lo_b, hi_b)
        spec = bool(speculate)
        sim = np.array(simplex, np.float64)
        d = sim.shape[1]
        cache: dict = {} if f0 is None else {tuple(sim[0]): float(f0)}
        need = [0 if f0 is None else 1]  # vertex 0 counts (as scipy counts it)

        class _Budget(Exception):
            pass

        def step_points(s):
            """The reflection, expansion and the two contractions of the sorted simplex ``s``."""
            xbar = s[:-1].sum(0) / d
            return [box((1 + rho) * xbar - rho * s[-1]), box((1 + rho * chi) * xbar - rho * chi * s[-1]),
                    box((1 + psi * rho) * xbar - psi * rho * s[-1]), box((1 - psi) * xbar + psi * s[-1])]

        def values(points, wanted):
            """Energies of ``wanted`` (indices into ``points``); when one is not known yet, a batch scores it
            (with ``speculate``, with the rest of ``points``)."""
            todo = []
            if any(tuple(points[i]) not in cache for i in wanted):
                todo = [p for p in (points if spec else [points[i] for i in wanted]) if tuple(p) not in cache]
            uniq = list({tuple(p): p for p in todo}.values())
            if uniq:
                for p, v in zip(uniq, score(uniq)):
                    cache[tuple(p)] = float(v)
            out = []
            for i in wanted:
                if need[0] >= maxfev:
                    raise _Budget
                need[0] += 1
                out.append(cache[tuple(points[i])])
            return out

        x_start = tuple(sim[0])
        fsim = np.full(d + 1, np.inf)
        k0 = 0 if f0 is None else 1
        if f0 is not None:
            fsim[0] = float(f0)
        try:
            fsim[k0:] = values(list(sim[k0:]), list(range(d + 1 - k0)))
            while True:
                order = np.argsort(fsim, kind="stable")
                sim, fsim = sim[order], fsim[order]
                if np.max(np.abs(sim[1:] - sim[0])) <= xatol:
                    break
                pts = step_points(sim)
                (fxr,) = values(pts, [0])
                shrink = False
                if fxr < fsim[0]:
                    (fxe,) = values(pts, [1])
                    sim[-1], fsim[-1] = (pts[1], fxe) if fxe < fxr else (pts[0], fxr)
                elif fxr < fsim[-2]:
                    sim[-1], fsim[-1] = pts[0], fxr
                elif fxr < fsim[-1]:
                    (fxc,) = values(pts, [2])
                    if fxc <= fxr:
                        sim[-1], fsim[-1] = pts[2], fxc
                    else:
                        shrink = True
                else:
                    (fxcc,) = values(pts, [3])
                    if fxcc < fsim[-1]:
                        sim[-1], fsim[-1] = pts[3], fxcc
                    else:
                        shrink = True
                if shrink:
                    sim[1:] = box(sim[0] + sigma * (sim[1:] - sim[0]))
                    fsim[1:] = values(list(sim[1:]), list(range(d)))
        except _Budget:
            if not np.all(np.isfinite(fsim)):  # (within the initial simplex: the vertices read so far)
                for i in range(k0, min(need[0], d + 1)):
                    fsim[i] = cache[tuple(sim[i])]
            order = np.argsort(fsim, kind="stable")
            sim, fsim = sim[order], fsim[order]
        return float(fsim[0]), sim[0], float(cache.get(x_start, np.inf))

    @staticmethod
    def _pattern_search(score, best, step, lo, hi, budget: int, xatol: float = 1e-3):
        """Batched stencil search with a quadratic model (log-parameter space).

        Each batch scores the ``3^d - 1`` stencil points ``x + step * u``, ``u`` in {-1, 0, 1}^d (clipped to
        the bounds), fits a quadratic to them and ``f(x)`` by least squares, and scores its minimiser
        (within two steps) as one more candidate: the model follows valleys that run across the axes
        (Cook-Torrance's ks and roughness trade against each other), where a compass search stalls.
        The best point becomes the centre; the steps halve when it lies within the stencil or nothing
        improved.  Stops when every step is below ``xatol`` (log units) or ``budget`` candidates are
        spent.  Returns ``(energy, x)``.
        """
        f0, x = best
        step = np.asarray(step, np.float64).copy()
        d = x.size
        grid = np.stack(np.meshgrid(*([np.array([-1.0, 0.0, 1.0])] * d), indexing="ij"), -1).reshape(-1, d)
        grid = grid[np.any(grid != 0, axis=1)]
        iu = np.triu_indices(d)
        used = 0
        while used < budget and np.max(step) >= xatol:
            cands = [np.clip(x + u * step, lo, hi) for u in grid]
            vals = list(score(cands))
            used += len(cands)
            # quadratic model in stencil units: f ~ c + g.u + 1/2 u^T H u
            U = np.vstack([np.zeros(d)] + [(y - x) / step for y in cands])
            F = np.array([f0] + vals)
            A = np.hstack([np.ones((len(U), 1)), U, np.stack([U[:, i] * U[:, j] * (0.5 if i == j else 1.0)
                                                              for i, j in zip(*iu)], 1)])
            coef = np.linalg.lstsq(A, F, rcond=None)[0]
            g = coef[1:1 + d]
            H = np.zeros((d, d))
            H[iu] = coef[1 + d:]
            H = H + np.triu(H, 1).T
            if used < budget and np.all(np.linalg.eigvalsh(H) > 0):
                u_star = np.clip(-np.linalg.solve(H, g), -2.0, 2.0)
                y = np.clip(x + u_star * step, lo, hi)
                if not np.array_equal(y, x):
                    cands.append(y)
                    vals.append(float(score([y])[0]))
                    used += 1
            k = int(np.argmin(vals))
            if vals[k] < f0:
                inside = bool(np.all(np.abs(cands[k] - x) <= step + 1e-12))
                f0, x = float(vals[k]), cands[k]
                if inside:
                    step = step / 2
            else:
                step = step / 2
        return f0, x

    # ------------------------------------------------------------------ the loop

    def run(self, images, *, depth=None, reference_depth: float | None = None, valid=None,
            progress: Progress | None = None, start=None, noise=None, checked: bool = False) -> RONResult:
        """Run Algorithm 2.

        Args:
            images: (N, H, W, 3) or (N, H, W) images (divided by the light
                intensities when the lights have unit intensities).
            depth: (H, W) depth estimate (scene units).  Point lights: the
                start of the loop (default: flat at ``reference_depth``).
            reference_depth: mean depth of the object (scene units, > 0): fixes
                the integrated depth's offset (orthographic) or scale
                (perspective).  Needed for point lights without ``depth``.
            valid: optional (N, H, W) bool observations to use.
            progress: ``progress(done, total, message)``.
            start: optional ``(normals, highlight)``: (H, W, 3) normals every mask pixel's solve starts from and
                (H, W) bool highlight pixels (or None: none), from an earlier reconstruction of nearly the same
                images (the interreflection compensation's later ones, :mod:`gpps.flows.interreflection`).  Every
                round then solves warm from the last normals only: no least squares, no DGMC, no cold starts (the
                earlier reconstruction ran them; a pixel its images moved by a little stays in its basin).
            noise: optional (N,) noise levels of the images (:func:`gpps.pipeline.solver.estimate_noise` of these
                images, e.g. computed beside the caller's checks), used instead of the solver's own estimate
                when its ``noise_level`` is None.
            checked: the caller ran :func:`gpps.flows.photometric.check_observations` on these images, mask and
                ``valid``: the solver's upload does not test them again (:meth:`PixelSolver.upload`).

        Returns:
            :class:`RONResult`.
        """
        t_all = time.perf_counter()
        resident = images is _RESIDENT
        warm_start = start is not None
        if warm_start:
            start_normals, start_highlight = start
            start_normals = np.asarray(start_normals, np.float32)
            if start_normals.shape != self.mask.shape + (3,):
                raise ValueError(f"start: expected ({self.mask.shape[0]}, {self.mask.shape[1]}, 3) normals, got shape "
                                 f"{start_normals.shape}")
            if not np.all(np.isfinite(start_normals[self.mask])):
                raise ValueError("start: expected finite normals on the mask")
            # (unit length; a pixel the earlier solve left without a normal starts facing the camera)
            length = np.linalg.norm(start_normals, axis=-1, keepdims=True)
            start_normals = np.where(length > 1e-6, start_normals / np.maximum(length, 1e-6),
                                     np.float32((0.0, 0.0, 1.0))).astype(np.float32)
            start_highlight = (np.zeros(self.mask.shape, bool) if start_highlight is None
                               else np.asarray(start_highlight, bool))
            if start_highlight.shape != self.mask.shape:
                raise ValueError(f"start: expected an ({self.mask.shape[0]}, {self.mask.shape[1]}) highlight mask, got "
                                 f"shape {start_highlight.shape}")
        c = self.config
        m = self.mask
        self._noise, self._checked = noise, bool(checked)
        self._compile_ahead(warm_start)
        self._last_move = None
        self._solver_mask = None
        if resident:
            if self._shadows is not None:
                self._shadows.restore()  # (the caller's observations: the last run's passes dropped some)
        else:
            self._frame_key = self._frame_depth = None
        step = progress or (lambda *a: None)
        timings = {"least_squares": 0.0, "dgmc": 0.0, "normals": 0.0, "integration": 0.0, "material": 0.0,
                   "shadows": 0.0}
        cur_depth, reference_depth = self._start_depth(depth, reference_depth)
        # (with shadow_few="keep" a pass can drop nothing from 3 images: a pixel losing one keeps fewer than 3)
        shadows = (c.cast_shadows and c.integrate and c.rounds > 1
                   and (c.shadow_few == "flag" or self.shape[0] > 3))
        rref = self._rounds_reference(reference_depth) if shadows else reference_depth
        solve_depth = cur_depth if self.point else None
        total = float(c.rounds * 3 + 2)
        if warm_start:
            start, highlight, dg = start_normals, start_highlight & m, None
        else:
            step(0, total, "least squares")
            start, highlight, dg = self._least_squares_and_dgmc(images, solve_depth, valid, timings,
                                                                report=lambda msg: step(0.5, total, msg))
            step(1, total, "dgmc")
        sh, shadow_stats, fit_valid = None, [], valid
        if shadows:
            sh = self._shadow_pass()
            sh.capture()  # the caller's observations, as uploaded with the frame

        material = self.material
        estimating = bool(c.estimate)
        sample = self._sample(highlight) if estimating and c.material_rule == "photometric" else None
        energies, changes, fits = [], [], []
        prev = start
        out = None
        converged = False
        integ = None
        # the rounds on the device (DeviceRounds): prev then lives in dev.prev (on_dev), out stays None
        dev = self._device_rounds(rref, estimating)
        on_dev = False
        r = 0
        for r in range(1, c.rounds + 1):
            # steps 1-2 (5): normals and albedo with the current material and depth
            t = time.perf_counter()
            init, init_mask = (start, highlight) if r == 1 else (dev.prev if on_dev else prev, None)
            front = r == 1 and highlight.any() and c.dgmc_config.start == "front" and not warm_start
            if r == 1 and warm_start:
                init_mask = None  # (every pixel from the given normals)
            elif r == 1 and (not highlight.any() or front):
                init = None
            # with the device rounds the front too stays there (its merge written back into the solver's outputs)
            on_device = dev is not None
            if r == 1:
                # the solver's kernels compile at their first use in an installation (seconds on the CPU): told
                # apart from the solve, whose progress comes as its rows finish
                step(3 * r - 2, total, f"round {r}: normals: loading the solver's kernels")
                self.solver.set_material(material)  # (the config is the cold solve's since least squares)
                self.solver.load(progress=lambda s, _t, msg, r=r: step(3 * r - 2, total,
                                                                         f"round {r}: normals: {msg}"))
                step(3 * r - 2, total, f"round {r}: normals")
            at = [3 * r - 2]  # (where the round's solves are: a kernels' load reports there, not back at the start)

            def solved(f, r=r, at=at):
                at[0] = 3 * r - 2 + f
                step(at[0], total, f"round {r}: normals")

            out = self._solve(images, solve_depth, valid, material, init=init, init_mask=init_mask,
                              cold=not warm_start and (r <= c.cold_rounds or init is None), fetch=not on_device,
                              progress=solved,
                              load=lambda _s, _t, msg, r=r, at=at: step(at[0], total, f"round {r}: normals: {msg}"))
            if front:
                # DGMC on the solved front (4.16-4.18): highlight pixels start from their solved
                # neighbours ring by ring; the lower residual wins per pixel; each front pixel started from
                # its source's final (solved) normal, which becomes its start normal
                tf = time.perf_counter()
                self.solver.set_material(material)
                start = start.copy()
                # the curvatures, as DGMC left them on the device (_least_squares_and_dgmc fetched none)
                gc, mc = (dg.gaussian, dg.mean) if dg.gaussian is not None else (self._dgmc.gc, self._dgmc.mc)
                if on_device:  # (read from and merged into the solver's outputs: nothing but the sources back)
                    if self._front is None:
                        self._front = DeviceFront(self.solver)
                    pix, src_normals = propagate_front_device(self.solver, m, highlight, gaussian=gc, mean=mc,
                                                              config=c.dgmc_config, keep_better=True,
                                                              front=self._front)
                    start.reshape(-1, 3)[pix] = src_normals
                else:  # (the frame is on the solver's device: _solve put it there)
                    fr = propagate_front(self.solver, None, m, highlight, out, gaussian=gc, mean=mc,
                                         depth=solve_depth, valid=valid, config=c.dgmc_config, keep_better=True)
                    for k in ("normals", "albedo", "residual", "flags"):
                        out[k] = getattr(fr, k)
                    out["iterations"] = out["iterations"] + fr.iterations
                    has = fr.source[..., 0] >= 0
                    start[has] = fr.normals[fr.source[has, 0], fr.source[has, 1]]
                timings["dgmc"] += time.perf_counter() - tf
                t += time.perf_counter() - tf
                self._solver_mask = None  # (the front solved its own masks)
            timings["normals"] += time.perf_counter() - t
            if on_device:
                if not on_dev:
                    dev.upload(prev)
                dev.step()
                got = dev.fetch()
                energies.append(got["energy"])
                changes.append(got["change_deg"])
                on_dev = True
            else:
                energies.append(self._energy(out["residual"], m))
                changes.append(normal_change_deg(out["normals"], prev, m))
                prev = out["normals"]
                on_dev = False
            step(1 + 3 * r - 2, total, f"round {r}: normals (energy {energies[-1]:.3g})")
            # a photometric estimate is final only after a later (fine) fit: the first one is coarse
            if r > (2 if estimating and c.material_rule == "photometric" else 1):
                de = abs(energies[-1] - energies[-2]) / max(energies[-2], 1e-300)
                if changes[-1] < c.tol_normals_deg and (de < c.tol or self._material_settled(fits)):
                    converged = True
                    break
            if r == c.rounds:
                break
            if not (estimating or self.point or shadows):
                # nothing that step 1 depends on changes: one round is the fixed point
                converged = True
                break
            # step 3: depth; it feeds back only through point lights (2.30-2.31) and the depth-rms
            # rule (4.19): otherwise the rounds' depths would be discarded, and only the final one is kept
            if c.integrate and (self.point or (estimating and c.material_rule == "depth-rms") or shadows):
                t = time.perf_counter()
                on_dev_depth = False
                if (on_device and dev.integrates and rref is not None
                        and dev.integrate(rref, into_solver=self.point)):
                    # the depth is in the solver's buffer; the host gets it only for a host rule
                    cur_depth = dev.depth if not estimating else dev.depth_host()
                    on_dev_depth = True
                    if self.point:
                        solve_depth = self._frame_depth = cur_depth
                else:
                    nrm = out["normals"] if out is not None else self.solver.fetch(("normals",))["normals"]
                    integ = self.integrator.run(nrm, reference_depth=rref)
                    cur_depth = self._fill_depth(integ.depth, integ.mask, rref)
                    if self.point:
                        solve_depth = cur_depth
                timings["integration"] += time.perf_counter() - t
                if shadows:
                    # the next round's observations (and this round's material fit's)
                    fitting = estimating and c.material_rule == "photometric"
                    got = self._shadow_round(sh, dev.depth if on_dev_depth else cur_depth, r, shadow_stats,
                                             timings, host_valid=fitting)
                    fit_valid = got if fitting else fit_valid
                    if not (estimating or self.point) and not any(x["dropped"] for x in shadow_stats[-2:]):
                        # the next round would see this round's observations again: the fixed point
                        converged = True
                        break
            step(1 + 3 * r - 1, total, f"round {r}: depth")
            # step 4: material
            if estimating:
                t = time.perf_counter()
                if c.material_rule == "photometric":
                    # the round's normals: host ones, or (device rounds) the solver's buffer, gathered
                    # at the sample pixels on the device
                    nrm = out["normals"] if out is not None else self.solver.normals
                    prog = lambda d, t, msg: step(1 + 3 * r - 1 + d / max(t, 1), total, f"round {r}: {msg}")  # noqa: E731
                    if r == 1 and c.models:
                        material, info = self._select_model(images, solve_depth, fit_valid, material, sample,
                                                            progress=prog)
                    else:
                        material, info = self._fit_material(
                            images, solve_depth, fit_valid, material, sample, grid=(r == 1), normals=nrm,
                            progress=prog, names=LOBE_PARAMETERS[material.brdf] if c.models else None)
                else:
                    if cur_depth is None:
                        raise ValueError("material_rule: 'depth-rms' needs integrate=True")
                    mr = depth_rms_roughness(cur_depth, m, self.camera, window=c.roughness_window)
                    mr = float(np.clip(mr, *_RANGES["roughness"]))
                    material = with_lobe(material, {"roughness": mr})
                    info = {"rule": "depth-rms", "values": {"roughness": mr}}
                fits.append(info)
                timings["material"] += time.perf_counter() - t
            step(1 + 3 * r, total, f"round {r}: material")
            if estimating and fits[-1].get("kept") and not (self.point or shadows):
                # the fit kept the material this round's normals were solved with (no candidate scored lower), and
                # nothing else the next round reads changes (no depth through point lights, no shadow pass): it
                # would solve with the same material and observations from these normals, its own solve's result,
                # and reproduce them, then fit from the same start again: Algorithm 2's fixed point
                converged = True
                break

        in_solver = out is None  # the final normals are the solver's buffer (device rounds)
        if out is None:  # device rounds: the outputs come back once
            out = self.solver.fetch(_OUTPUTS)
        depth_out, depth_mask, ires = self._final_depth(out["normals"], reference_depth, timings, dev=dev,
                                                        in_solver=in_solver)
        refinement = None
        if c.refine and depth_out is not None:
            step(total, total, "depth refinement")
            if resident and c.refine_two_light:  # (the two-light start reads the frame as it is on the device)
                images = self.solver.images.numpy().reshape(self.shape + (3,))
                v = self._shadows.valid0 if self._shadows is not None else self.solver.valid
                valid = v.numpy().astype(bool)
            depth_out, refinement = self._refine(out, depth_out, depth_mask, material, timings,
                                                 progress=lambda d, t, msg: step(total, total, msg),
                                                 images=None if images is _RESIDENT else images, valid=valid)
        shadowed = sh.shadowed() if sh is not None and shadow_stats else None
        step(total, total, "done")
        timings["total"] = time.perf_counter() - t_all
        estimated = {k: lobe_value(material, k) for k in (LOBE_PARAMETERS[material.brdf] if c.models else c.estimate)}
        notes = self._notes(estimated, converged, fits)
        return RONResult(
            normals=np.where(m[..., None], out["normals"], 0.0).astype(np.float32),
            albedo=out["albedo"], depth=depth_out, depth_mask=depth_mask, material=material, estimated=estimated,
            energy=energies, normal_change_deg=changes, rounds=r, converged=converged,
            residual=out["residual"], iterations=out["iterations"], flags=out["flags"], highlight=highlight,
            start_normals=start, material_fit=fits, integration_residual=ires, timings=timings, warnings=notes,
            shadows=shadow_stats, shadowed=shadowed, refinement=refinement,
        )

    @property
    def frame(self):
        """The solver's frame on its device: (N, H, W) ``wp.vec3`` images, as the last run uploaded them (a
        caller may change them there before :meth:`rerun`); None before a run."""
        return None if self._frame_key is None else self.solver.images

    def rerun(self, start, material: Material, *, depth=None, reference_depth: float | None = None,
              progress: Progress | None = None) -> RONResult:
        """:meth:`run` again on the frame the last run left on the solver's device, as a caller changed it there
        since (:attr:`frame`; the interreflection compensation subtracts the indirect light in place,
        :meth:`gpps.pipeline.interreflection.Interreflections.subtract_from`): nothing is uploaded, the noise
        levels are the last upload's, the observations the caller's of that run (the cast-shadow passes' drops
        undone).  ``material`` is known (nothing estimated, no models compared) and every pixel starts warm from
        ``start`` (``(normals, highlight)``, as :meth:`run`'s).

        Raises:
            RuntimeError: no run has put a frame on the device.
        """
        if self._frame_key is None:
            raise RuntimeError("rerun: no frame on the device (run first)")
        if not isinstance(material, Material):
            raise TypeError(f"material: expected gpps.material.Material, got {type(material).__name__}")
        if start is None:
            raise ValueError("start: expected (normals, highlight) to start every pixel from, got None")
        saved = self.config, self.material
        self.config, self.material = replace(self.config, estimate=(), models=()), material
        try:
            return self.run(_RESIDENT, depth=depth, reference_depth=reference_depth, progress=progress, start=start)
        finally:
            self.config, self.material = saved

    def _device_rounds(self, reference_depth, estimating: bool):
        """The device side of the rounds (:class:`DeviceRounds`, built once), or None (every round on
        the host: ``device_rounds=False``, or a single round).

        The round's energy and normal change are reduced on the device whenever it is used (no
        full-frame fetch a round).  Step 3 runs there too (:attr:`DeviceRounds.integrates`), in the rounds
        whose depth feeds back (point lights or the depth-rms rule; with a reference depth) and for the
        final depth, when the integrator's config is one
        :class:`DeviceSystem` builds and on CUDA torch is installed
        (zero-copy views; ``device_rounds=None`` falls back to the host's integration without it)."""
        c = self.config
        if c.device_rounds is False or c.rounds <= 1:
            return None
        # (the device integration also serves the final depth, whether or not the rounds' depth feeds back)
        integ = bool(c.integrate and self.integrator is not None)
        if integ and c.device_rounds is None and self.device.startswith("cuda"):
            integ = importlib.util.find_spec("torch") is not None  # (see RONConfig.device_rounds)
        if self._rounds is None or self._rounds_integ != integ:
            if self._rounds is not None:
                self._rounds.close()
            self._rounds = DeviceRounds(self.solver, self.mask, self.integrator if integ else None)
            self._rounds_integ = integ
        return self._rounds

    def _rounds_reference(self, reference_depth) -> float | None:
        """The mean depth of the rounds' integrations when they run for the cast shadows: the given one for
        point lights (they move with it); for directional lights, whose shadows depend on neither the depth's
        offset (orthographic) nor its scale (perspective), the given one or 1 (perspective) and, orthographic,
        ``100 (H + W)`` pixel widths (the march needs depth > 0 in the mask whatever the relief)."""
        if self.point:
            return reference_depth
        if self.camera.is_perspective:
            return reference_depth if reference_depth is not None else 1.0
        h, w = self.shape[1:]
        return 100.0 * (h + w) * float(self.camera.pixel_size)

    def _shadow_round(self, sh: RoundShadows, depth, r: int, stats: list, timings: dict, *, host_valid: bool):
        """The cast-shadow pass after round ``r``'s depth: the solver's observations become the original ones
        less the shadows of ``depth`` (a Warp buffer on the solver's device, marched in place: the device
        rounds; or a host array, uploaded).  Appends the pass's counts to ``stats``; returns the new
        observations as an (N, H, W) bool host array with ``host_valid`` (the material fit's sample is
        uploaded from the host), else None."""
        t = time.perf_counter()
        if isinstance(depth, np.ndarray):
            sh.upload(depth)
            sh.step()
        else:
            sh.step(depth)
        stats.append({"round": r + 1, **sh.fetch()})
        out = sh.valid_host() if host_valid else None
        timings["shadows"] += time.perf_counter() - t
        return out

    def _shadow_pass(self) -> RoundShadows:
        """The cast-shadow pass on the solver (:class:`RoundShadows`, built once per RON)."""
        if self._shadows is None:
            c = self.config
            self._shadows = RoundShadows(self.solver, self.mask, c.shadow_config, few=c.shadow_few)
        return self._shadows

    def _start_depth(self, depth, reference_depth):
        """Checked start depth (H, W) (None without depth or point lights) and the reference depth
        (the given one, else the start depth's mean)."""
        h, w = self.shape[1:]
        m = self.mask
        if reference_depth is not None:
            reference_depth = check_number("reference_depth", reference_depth, lo=0.0, lo_open=True)
        if depth is not None:
            depth = as_array("depth", depth, shape=(h, w))
            if np.any(depth[m] <= 0):
                raise ValueError("depth: expected values > 0 inside the mask")
            if reference_depth is None:
                reference_depth = float(np.mean(depth[m]))
        if self.point and depth is None:
            if reference_depth is None:
                raise ValueError("reference_depth: expected the object's distance (scene units) for point lights "
                                 "without a depth estimate, got None")
            depth = np.full((h, w), reference_depth, np.float32)
        cur_depth = None if depth is None else np.where(m, depth, reference_depth or 1.0).astype(np.float32)
        return cur_depth, reference_depth

    def _least_squares_and_dgmc(self, images, solve_depth, valid, timings, report=None):
        """The start (Algorithm 2's first step): least squares (Woodham), then DGMC's highlight pixels and
        starts (4.16-4.18, on the device: :class:`gpps.pipeline.dgmc.DeviceDGMC`, the host's decisions).  Returns
        ``(start normals (H, W, 3), highlight (H, W) bool, DGMC start maps (DGMCStart) or None)``.  ``report(message)``:
        told between the two (each compiles its kernels at its first use in an installation)."""
        c, m = self.config, self.mask
        t = time.perf_counter()
        s = self.solver
        s.set_config(replace(c.solver, solver="none", smoothness=0.0))
        self._frame(images, solve_depth, valid)
        self._set_mask(m)
        # (its kernels compile at their first use in an installation, or a helper compiling them ahead finishes:
        # gpps.pipeline.prefetch; told as a least-squares message)
        s.load(progress=None if report is None else (lambda _s, _t, msg: report(f"least squares: {msg}")))
        s.step()
        dgmc = c.dgmc and self.material.brdf != "lambertian"
        if not dgmc:
            start = s.fetch(("normals",))["normals"]  # (only the start normals are read)
        s.set_config(c.solver)
        timings["least_squares"] += time.perf_counter() - t
        highlight, dg = np.zeros(m.shape, bool), None
        if dgmc:
            if report is not None:
                report("dgmc: highlights and curvatures")
            t = time.perf_counter()
            pts = self.camera.backproject(np.where(m, solve_depth, 1.0)) if self.point else None
            # RGB frames: DGMC copies the solver's uploaded frame on the device (the same float32 values);
            # grey ones go up again (DGMC keeps one channel where the solver replicated it to three)
            rgb = np.ndim(images) == 4 and np.shape(images)[-1] == 3
            # the solved front (the default start) reads only the highlights and the curvatures: it picks its
            # sources among the solved pixels itself (4.17-4.18), so the boundary mode's starts are not computed;
            # its highlight pixels start from least squares until their ring's source is known (run())
            front = c.dgmc_config.start == "front"
            if self._dgmc is None:  # (kept for the RON's later runs: its buffers allocated once)
                self._dgmc = DeviceDGMC(self.shape, config=c.dgmc_config, device=self.device)
            stage = self._dgmc
            # the least-squares normals go from the solver's buffer to DGMC's on the device (the pixels least
            # squares left undetermined start from (0, 0, 1): DeviceDGMC.upload); the curvatures stay there for
            # the front (DeviceFront.upload reads them): only the highlights and the start normals come back
            stage.upload(self.solver.images if rgb else images, m, s.normals, lights=self.lights, points=pts)
            stage.step(starts=not front)
            dg = stage.fetch_start(curvatures=not front)
            if front:
                start = stage.normals.numpy().astype(np.float32)
            else:
                start = dg.normals.astype(np.float32)
            highlight = dg.highlight
            timings["dgmc"] += time.perf_counter() - t
        return start, highlight, dg

    def _final_depth(self, normals, reference_depth, timings, *, dev=None, in_solver: bool = False):
        """The returned depth, from the final normals, by the final integrator (BiNI by default).

        With ``dev`` (the rounds' :class:`DeviceRounds`) and the rounds' integrator as the final one, a
        system :class:`DeviceSystem` builds: integrated on the device (the same system, multigrid hierarchy
        and CG as the host path, tests/test_ron_device.py) from the solver's buffer (``in_solver``: it
        holds ``normals``) or from ``normals`` uploaded once; only the depth comes back (invalid normals
        dropped from the depth mask, as on the host).  Returns ``(depth or None, depth mask, integration residual or
        None)``: the host path's residual is recomputed in float64 on the host, the device path's is the
        CG's own (the recurrence, device precision)."""
        c = self.config
        if not c.integrate:
            return None, np.zeros(self.mask.shape, bool), None
        t = time.perf_counter()
        same = c.final_integrator is None or c.final_integrator == self.integrator.config
        if same and dev is not None and dev.integrates:
            # (without a reference depth normalised there as the host's Integrator.fetch does)
            if dev.integrate(reference_depth, into_solver=False, normals=None if in_solver else normals):
                # the pixels integrated: the mask, less invalid normals by the host's rule (the device
                # dropped the same ones and filled them)
                dmask = self.mask.copy() if dev.last["invalid"] == 0 else self.integrator._check_normals(normals)[1]
                if self.camera.is_perspective:
                    warn_log_depth_span(dev.last["span"])  # (as the host path's Integrator.fetch)
                depth = np.where(dmask, dev.depth_host(), 0.0).astype(np.float32)
                timings["integration"] += time.perf_counter() - t
                return depth, dmask, float(dev.last["residual"])
        if same:
            integ = self.integrator.run(normals, reference_depth=reference_depth)
        else:
            final = Integrator(self.mask, camera=self.camera, config=c.final_integrator, device=taichi_device(self.device))
            try:
                integ = final.run(normals, reference_depth=reference_depth)
            finally:
                final.close()
        timings["integration"] += time.perf_counter() - t
        return integ.depth, integ.mask, float(integ.residual)

    def _refine(self, out: dict, depth, depth_mask, material, timings, progress=None, *, images=None,
                valid=None) -> tuple[np.ndarray, dict]:
        """``RONConfig.refine``: the depth refinement from the final depth (its dropped pixels filled by the
        mean), on the solver's frame, and with ``RONConfig.refine_two_light`` from the two-light surface too
        (the likelier refined surface kept); ``out``'s normals, albedo and residual are replaced.  Returns the
        refined depth (0 outside ``depth_mask``) and the refiner's record (that of the surface kept; with the
        second start also ``starts``: each start's likelihood, steps accepted and rejected, and the two-light
        pixels; and ``chosen``).  The second refinement's progress messages say "(two-light start)"."""
        t = time.perf_counter()
        if not DeviceSystem.supports(self.integrator.config):
            raise ValueError("refine: expected a plain multigrid rounds' integrator (IntegratorConfig(solver="
                             f"'multigrid'), not robust or bilateral), got {self.integrator.config}")
        self.solver.set_material(material)
        start = self._fill_depth(depth, depth_mask, None)
        ref = DepthRefiner(self.solver, self.integrator, self.config.refine_config)
        try:
            ref.upload_from_solver(start)
            ref.step(progress)
            got = ref.fetch()
            second = (self._two_light_start(images, valid, out["normals"], start)
                      if self.config.refine_two_light and images is not None else None)
            if second is not None:
                alt, two = second
                first = {**ref.likelihood(), **{k: ref.last[k] for k in ("accepted", "rejected")}}
                ref.upload_from_solver(alt)
                ref.step(None if progress is None else (
                    lambda d, t, msg: progress(d, t, msg.replace("depth refinement:", "depth refinement (two-light start):", 1))))
                other = {**ref.likelihood(), **{k: ref.last[k] for k in ("accepted", "rejected")}}
                starts = {"integrated": first, "two-light": {**other, "pixels": int(two.sum())}}
                if other["nll"] < first["nll"]:
                    got = ref.fetch()
                    chosen = "two-light"
                else:
                    chosen = "integrated"
                got["info"] = {**got["info"], "starts": starts, "chosen": chosen}
        finally:
            ref.close()
        m = self.mask
        out["normals"] = got["normals"]
        out["albedo"] = got["albedo"]
        out["residual"] = np.where(m, got["residual"], out["residual"]).astype(np.float32)
        timings["refine"] = time.perf_counter() - t
        return np.where(depth_mask, got["depth"], 0.0).astype(np.float32), got["info"]

    def _two_light_start(self, images, valid, normals, start) -> tuple[np.ndarray, np.ndarray] | None:
        """The refinement's second start (``RONConfig.refine_two_light``): ``(depth, two-light pixels)``, each
        connected part of the mask at the mean ``u`` of ``start`` (the refinement keeps each part's mean), or
        None (point lights; a model without a diffuse term, the conductor; no pixel keeps exactly two lit
        observations; a degenerate system).

        The ratio holds for the diffuse term: the model's specular part at the per-pixel ``normals`` (the
        material as refined, rendered with a zero albedo) is taken out of the images first."""
        if self.point or BRDF_TAG[self.solver.material.brdf] == CONDUCTOR:
            return None
        m = self.mask
        y = np.asarray(images, dtype=np.float64)
        n = np.asarray(normals, dtype=np.float64)
        length = np.linalg.norm(n, axis=-1)
        good = m & np.isfinite(length) & (length > 0.5)
        n = np.where(good[..., None], n / np.where(good, length, 1.0)[..., None], (0.0, 0.0, 1.0))
        sat = self.config.solver.saturation
        if sat is not None:  # (saturated observations are no more lit than dark ones are: set aside)
            top = y.max(-1) if y.ndim == 4 else y
            ok = top < float(sat)
            valid = ok if valid is None else (np.asarray(valid, dtype=bool) & ok)
        with Renderer(m.shape, self.camera, self.lights, self.solver.material, device=self.device) as rd:
            # (directional lights: the shading does not depend on the depth)
            rd.upload(np.ones(m.shape), m, np.zeros(3), normals=n)
            rd.step()
            spec = rd.fetch().astype(np.float64)
        y = np.maximum(y - (spec if y.ndim == 4 else spec.mean(-1)), 0.0)
        e = np.asarray(self.lights.intensities, dtype=np.float64)  # (N, 3)
        if y.ndim == 4:
            y = y / np.where(e > 0, e, 1.0)[:, None, None, :]
        else:
            y = y / np.where(e.mean(1) > 0, e.mean(1), 1.0)[:, None, None]
        dark = dark_observations(y, m, valid)
        u, two = two_light_log_depth(y, dark, n, m, self.camera, self.lights.directions,
                                     min_nz=float(self.integrator.config.min_nz))
        if u is None:
            return None
        persp = self.camera.is_perspective
        base = np.log(np.maximum(start, 1e-30)) if persp else np.asarray(start, dtype=np.float64)
        lab, ncomp = label(m)  # (the 4-connected parts, as the integrator's)
        means = np.bincount(lab[m], weights=base[m], minlength=ncomp + 1) / np.maximum(
            np.bincount(lab[m], minlength=ncomp + 1), 1)
        level = means[lab]
        with np.errstate(over="ignore"):
            d = np.exp(u + level) if persp else u + level
        d = np.where(m, d, start).astype(np.float32)
        if not np.all(np.isfinite(d[m])) or (persp and np.any(d[m] <= 0)):
            return None  # (a degenerate system: no start)
        return d, two

    def _notes(self, estimated: dict, converged: bool, fits: list) -> list[str]:
        """Warnings of the run: a material the images leave open, estimates on their search bound, rounds that
        hit the cap."""
        c = self.config
        notes: list[str] = []
        for f in fits[:1]:
            a = f.get("ambiguity")
            if a is not None and not f["identifiable"]:
                warn(f"material: the images leave the material open: {a['near']} of {a['candidates']} candidate "
                     f"materials fit the sample within the images' noise and their normals differ by "
                     f"{a['ambiguity_deg']:.1f} deg on average (> {AMBIGUITY_DEG:g}), and the estimate is one of "
                     "them.  Give the material's parameters if they are known (a Material; gpps reconstruct "
                     "--ks/--shininess/--roughness), or use more images (three images of a grey object fit any lobe)",
                     notes)
        for k, v in estimated.items():
            msg = estimate_on_bound(k, v)
            if msg:
                warn(msg, notes)
        if not converged and c.rounds > 1:
            warn(f"rounds: RON stopped at its cap of {c.rounds} rounds before meeting its tolerances "
                 f"(energy change {c.tol:g}, normal change {c.tol_normals_deg:g} deg); more rounds may change the result",
                 notes)
        return notes

    def _fill_depth(self, depth, dmask, reference_depth) -> np.ndarray:
        """Integrated depth with the pixels it dropped filled by the mean (the solver needs depth > 0)."""
        fill = float(np.mean(depth[dmask])) if dmask.any() else (reference_depth or 1.0)
        d = np.where(dmask & (depth > 0), depth, fill)
        return np.where(self.mask, d, fill).astype(np.float32)
