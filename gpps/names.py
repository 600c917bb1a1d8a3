"""Every name list and constant that more than one layer uses, in one place.

The public API speaks in strings (``Literal`` types, checked by :func:`gpps._check.check_choice`);
the device kernels speak in small integers.  Both come from here: the kernels wrap the integers in
``wp.constant`` and the stages map strings to them with the ``*_TAG`` dictionaries, so the two sides
cannot drift apart.
"""

from __future__ import annotations

from typing import Literal, get_args

# ---------------------------------------------------------------- reflectance models (seed ch. 2, 5)
# "plastic" is not the seed's: a dielectric coating (exact Fresnel) over a diffuse base (gpps.kernels.brdf);
# nor is "conductor": a rough metal, GGX microfacets and no diffuse term (its albedo map is the metal's colour)
BRDF = Literal["lambertian", "phong", "blinn-phong", "cook-torrance", "ashikhmin-shirley", "plastic", "conductor"]
BRDF_NAMES: tuple[str, ...] = get_args(BRDF)
BRDF_TAG = {name: i for i, name in enumerate(BRDF_NAMES)}  # device tags of gpps.kernels.brdf
LAMBERTIAN, PHONG, BLINN_PHONG, COOK_TORRANCE, ASHIKHMIN_SHIRLEY, PLASTIC, CONDUCTOR = range(7)
# the seed's five models (chapters 2 and 5), e.g. for training sets drawn from them
SEED_BRDF_NAMES: tuple[str, ...] = BRDF_NAMES[:5]
# Fresnel f0 when a Material leaves it unset: the seed's 0.5 (Schlick, 2.29), and for plastic the
# normal-incidence reflectance of a dielectric of index 1.5 (((1.5 - 1) / (1.5 + 1))^2 = 0.04); for the conductor
# 1: Schlick's rise toward grazing incidence is off (the metal's colour at normal incidence is its albedo map)
DEFAULT_F0: dict[str, float] = {name: 0.5 for name in BRDF_NAMES} | {"plastic": 0.04, "conductor": 1.0}

# images below which a model's per-pixel fit does not determine the normals: the conductor (no diffuse term: a normal
# and a colour seen only through the lobe, which most lights miss).  A pixel's N values per channel are one colour
# times the lobe, so N - 1 ratios carry the normal's 2 degrees of freedom, and a light outside the lobe adds none.
# Measured on gpps's own noise-free metals (GGX alpha 0.15 and 0.3, bumps and spheres, directional and point lights,
# 48^2, the material known; perf/results/s36/README.md): 3 lights 3.9-10.1 deg mean, 4 lights 0.4-2.1, 5 lights
# 0.00-0.11, 6 lights 0.00 (tests/test_conductor.py asserts 5, 6 and 12).  Every model with a diffuse term needs 3
CONDUCTOR_MIN_IMAGES = 5
# RON's model comparison (RONConfig.models, gpps.host.model_evidence): another model replaces the configured one only
# when the sample pixels' paired differences of squared residuals are above zero by more than this many standard
# errors (one-sided, the normal distribution's 99th percentile: the conventional 1 % level)
MODEL_SWITCH_Z = 2.326

# the scene parameters the material searches estimate per model ("eta" ties Ashikhmin-Shirley's eta_u = eta_v),
# and each one's log-space search range (lo, hi): RON's material fit (gpps.flows.ron) and the stream's full mode
LOBE_PARAMETERS: dict[str, tuple[str, ...]] = {
    "lambertian": (),
    "phong": ("ks", "shininess"),
    "blinn-phong": ("ks", "shininess"),
    "cook-torrance": ("ks", "roughness"),
    "ashikhmin-shirley": ("ks", "eta"),
    "plastic": ("ks", "roughness"),
    "conductor": ("roughness",),  # its per-pixel albedo is the lobe's (RGB) weight: no ks
}
LOBE_RANGES: dict[str, tuple[float, float]] = {
    "ks": (0.02, 3.0), "shininess": (2.0, 500.0), "roughness": (0.03, 0.8), "eta": (2.0, 500.0),
}

# ---------------------------------------------------------------- crease-cut normal integration (issue 21)
# how the pieces of a crease-cut BiNI solve get their constants (gpps.host.creases.stitch_cut_pieces):
# "mid": least squares on the cut edges' mid-normal targets (continuity); "bini": BiNI's own bilateral energy
# restricted to the cut edges' one-sided equations, by its IRLS (a real jump keeps its one-sided side)
CutStitchName = Literal["mid", "bini"]
CUT_STITCH_NAMES: tuple[str, ...] = get_args(CutStitchName)
# which crease cuts reach BiNI: "keep" all of them; "drop" the slits (cuts whose two pixels stay connected
# through uncut edges: no new constant, only lost coupling)
SlitsName = Literal["keep", "drop"]
SLITS_NAMES: tuple[str, ...] = get_args(SlitsName)

# what the folder flow does about light the surface sends itself (gpps.flows.interreflection): "off" nothing;
# "subtract" the diffuse interreflections gathered over the reconstructed surface, then reconstruct again; "auto"
# subtract from INTERREFLECTION_MIN_IMAGES images on (gpps.flows.folder.automatic_interreflections)
InterreflectionName = Literal["auto", "off", "subtract"]
INTERREFLECTION_NAMES: tuple[str, ...] = get_args(InterreflectionName)
# images from which the folder flow compensates interreflections by default: the compensation sends the fitted
# diffuse albedo's light, and only from CONDUCTOR_MIN_IMAGES images does the folder flow compare models (plastic,
# whose albedo is the diffuse one under the coating; the conductor, a metal, which the compensation skips); below,
# a glossy surface is fitted with Blinn-Phong and its "albedo" holds some of the lobe (3 lights, session 34: the
# glossy development captures got worse, the matte ones better)
INTERREFLECTION_MIN_IMAGES = CONDUCTOR_MIN_IMAGES
# the albedo the compensation assumes for the surface's brightest pixels (their 99th percentile) when the light
# intensities are not known to be radiometric (FolderConfig.albedo_scale None; DiLiGenT's are relative).  The light a
# surface of albedo rho sends itself scales as rho (times the gathered radiance, which the images give); taken as
# if its albedo were a, the light left in or taken out too much scales as |rho - a|.  Over every albedo in [0, 1] the
# worst case is smallest at a = 1/2 (half that of no compensation, a = 0, on a white surface), and any
# rho > a / 2 gains (gpps.flows.interreflection)
ASSUMED_BRIGHT_ALBEDO = 0.5

# ---------------------------------------------------------------- lights
LIGHT_DIRECTIONAL, LIGHT_POINT = 0, 1  # device tags of gpps.kernels.brdf.LightParams.kind

# ---------------------------------------------------------------- per-pixel solver (seed ch. 3)
SolverName = Literal["none", "lm", "dogleg", "bfgs"]
RobustName = Literal["none", "huber", "cauchy"]
SOLVER_NAMES: tuple[str, ...] = get_args(SolverName)
ROBUST_NAMES: tuple[str, ...] = get_args(RobustName)
SOLVER_TAG = {name: i for i, name in enumerate(SOLVER_NAMES)}  # none 0, lm 1, dogleg 2, bfgs 3
ROBUST_TAG = {name: i for i, name in enumerate(ROBUST_NAMES)}  # none 0, huber 1, cauchy 2

# how a batched solve is spread over GPU threads: one thread a (candidate, pixel) pair, or one block of
# LIGHT_LANES threads a pair with the lights split over the lanes (gpps.kernels.solve_cost.evaluate_for).
# "auto", per launch on CUDA: "lights" from LIGHTS_PARALLEL_MIN images on when the launch has at most
# LIGHTS_PARALLEL_PAIRS_PER_IMAGE x N (candidate, pixel) pairs, else "pixels".  Measured on an H100
# (perf/results/material_lanes_H100.json, Cauchy IRLS, 4 starts cold / 1 warm): a launch of few pairs is
# latency-bound (its slowest thread's light loops), the lanes cut that: 4 x 500 warm pairs at 96 images
# 30.5 -> 2.7 ms, at 16 images 4 x 1500 6.8 -> 3.1 ms; a launch of many pairs already fills the GPU and the
# lanes' reductions cost more than they save: 25 x 1000 pairs at 24 images 19.8 -> 24.7 ms, 25 x 2000 at
# 12 images 15.8 -> 46.9 ms (but 25 x 500 at 96 images 73.9 -> 27.9 ms).
ParallelName = Literal["auto", "pixels", "lights"]
PARALLEL_NAMES: tuple[str, ...] = get_args(ParallelName)
LIGHT_LANES = 32
# register cap of the starts-parallel cold whole-image solve's CUDA module (gpps.kernels.solve_split): its
# H x W x starts threads are throughput-bound, and at the compiler's 216 registers a thread only 8 warps fit an
# SM.  Measured on the H100 (perf/register_cap.py, 256^2 x 3 Cook-Torrance, 10 starts; the normals bit-identical):
# no cap 4.54 ms a solve, 168: 4.29, 128: 3.26, 96: 3.41.  The latency-bound launches (the material scorer's, the
# front's rings) keep the compiler's choice: a cap there only adds spill latency to their few threads.
SPLIT_SOLVE_MAX_REGISTERS = 128
# the same cap for the starts-parallel neighbour pass (gpps.kernels.solve_split.split_under_kernels_for): given the
# split solve's value, not measured apart.  Its launches have H x W x starts threads of which only the
# under-determined pixels' work (256^2 x 3: 3352 of 43234 pixels), which may make them latency-bound; with the cap
# its starts kernel spills ~0.5 kB a thread (sm_90, perf/results/s27/README.md), without it 207 registers and no
# spills.  perf/neighbour_pass.py times both ways.
SPLIT_UNDER_MAX_REGISTERS = 128
# thread blocks a streaming multiprocessor for the launches of a starts-parallel subset re-solve
# (PixelSolver.step_subset with SolverConfig(split_starts=True) on CUDA): one wave of blocks strides over the
# (rows, W, starts) launch (Warp's grid-stride loop), so the pixels outside the subset cost a mask read each
# instead of a block of their own.  With ~70 of 1M pixels marked its starts launch took 0.156 ms on an H200
# against 0.179 over the whole grid (perf/stream_frame_split.py); 8 x 256 threads fill an SM.
SUBSET_BLOCKS_PER_SM = 8
# sets of recorded launches a PixelSolver keeps, one per (config, material) pair, most recent first: RON switches
# among a few configs (least squares, the cold and warm solves, the front's) with one material inside a round, and
# each switch used to drop the recorded launches, so the next launches packed their arguments again (on the H200
# host ~0.1 ms a launch; 154 of the 165 recordings of a 256^2 x 3 reconstruction on the CPU were repeats)
SOLVER_CMD_SETS = 8
# lights whose reflectance terms the solver's cost evaluation keeps between its two passes (the albedo's normal
# equations, then the residuals: gpps.kernels.solve_cost.evaluate_for); the lights after them are evaluated
# again in the second pass.  4 covers the streamed triples and the 3-image captures, whose solves spend most of
# their time in the specular lobe's value and gradient; it is the GPU's size (a thread's local matrix, zeroed at
# each evaluation; the lights-parallel build gives each lane N / 32 lights).  The CPU build takes the smallest of
# SOLVE_TERM_CACHE_CPU that holds all N lights (the largest beyond): 12 floats a light on the thread's stack, and
# the zeroing costs less than a second evaluation of the lights (gpps.kernels.solve.term_cache_size).
SOLVE_TERM_CACHE = 4
SOLVE_TERM_CACHE_CPU = (4, 16, 128)
# the cast-shadow refit of a per-pixel fit with many images (gpps.pipeline.solver.SolverConfig.shadow_relative):
# observations darker than this fraction of the pixel's lit level (the grey value a quarter of its observations
# reach) are set aside when the fit contradicts the pixel's split into lit and dark ones.  Such an observation is
# explained as well by a cast shadow at any normal as by a tilted normal that misfits the lit ones, so it cannot
# choose between them.
SHADOW_RELATIVE_MANY = 0.1
# ... and the refit is made when the fit predicts such a dark observation at least this fraction of the lit level,
# or one at the lit level or above below this fraction of its value (a contradiction: dark where the fit says lit,
# or lit where it says dark; gpps.kernels.solve_methods, cast_shadow_start)
CAST_CONFLICT = 0.5
# the neighbour pass's test of an unlit observation (held_dark_refit of gpps.kernels.solve_methods.solve_pixel_for):
# with the albedo held at the neighbours', a pixel's fit with its unlit observations in (an attached shadow: the
# normal faces away from the light) is compared with its fit without them (a cast shadow: dark at any normal).  The
# second fit is taken when it predicts a set-aside observation above this fraction of the pixel's brightest value
# and the first paid for the terms: a misfit of more than one observation off by it in every channel.  The level is
# the one the cast-shadow refit calls dark (SHADOW_RELATIVE_MANY)
HELD_DARK_CONFLICT = SHADOW_RELATIVE_MANY
# with more images than this the per-pixel solves expect outliers (cast shadows, interreflections, highlights the model
# misses) and fit robustly: a Cauchy loss, observations below 0.02 of the pixel's brightest taken as shadowed, the
# cast-shadow refit (SHADOW_RELATIVE_MANY) and 4 starts (gpps.flows.folder.automatic_solver_options, and
# gpps.reconstruct without a config).  Principle: a pixel's fit has 3 unknowns (a normal's two angles and an albedo);
# from 4 images on one observation beyond them lets the cast-shadow refit judge a dark observation against the fit
# of the others (a cast shadow predicted lit is set aside), and from 5 the Cauchy loss can outvote one outlier.  With
# 3 images the neighbour pass's attached / cast shadow choice does it (SolverConfig.held_dark_refit).  Sessions up to
# 34 used 6 (robust from 7 images).  Measured in session 35 on the Mitsuba captures (folder flow, this CPU, from 7
# -> from 4): 4 lights development dielectric mean 13.12 -> 8.62 deg, diffuse 10.87 -> 4.56, metals 36.35 -> 36.13;
# held-out 4 lights dielectric 13.36 -> 6.24, diffuse 13.52 -> 10.29, metals 28.99 -> 27.91; 5 lights development
# dielectric 12.12 -> 6.66, diffuse 11.06 -> 5.03, metals 21.92 -> 27.65 (a rough conductor fitted with
# Blinn-Phong); 6 lights development dielectric 10.09 -> 4.87, diffuse 10.28 -> 3.75, metals 17.06 -> 14.71;
# held-out 6 lights dielectric 10.49 -> 4.38, diffuse 12.03 -> 7.31, metals 1.89 -> 4.17
MANY_IMAGES = 3
# the weight that marks a set-aside observation in the solver's weights buffer: negative (a one-sided term, as a
# dark observation) and so small that it adds nothing to a cost, a gradient or an albedo
ASIDE_WEIGHT = -1.0e-30
# the stream integrator's tolerance mode stops in float32 after this many residual checks in a row that do not halve
# the best |r|^2 (its floor; gpps.pipeline.integration_device.StreamIntegrator.step)
STALL_CHECKS = 3
# where a stage may run its per-frame or per-step launches as a CUDA graph: "auto" (on CUDA, after a first eager
# pass), "off" (launched from the host every time)
GraphName = Literal["auto", "off"]
GRAPH_NAMES: tuple[str, ...] = get_args(GraphName)
# how an iterative device solve is launched on CUDA: "tasks" (a Taichi launch per phase, the host polling),
# "persistent" (one task whose phases meet at software grid barriers), "auto" (persistent on CUDA, tasks off it)
LaunchName = Literal["auto", "tasks", "persistent"]
LAUNCH_NAMES: tuple[str, ...] = get_args(LaunchName)
LIGHTS_PARALLEL_MIN = 16
LIGHTS_PARALLEL_PAIRS_PER_IMAGE = 500

# bits of the solver's per-pixel ``flags`` (int32)
FLAG_ILL_CONDITIONED = 1  # light matrix of the pixel's valid lights is (nearly) singular (3.13)
FLAG_FEW_OBSERVATIONS = 2  # fewer than 3 valid observations (or an unfounded fit: FLAG_UNFOUNDED)
FLAG_NOT_CONVERGED = 4  # the best start hit the iteration cap
FLAG_WOODHAM_FALLBACK = 8  # weighted least squares was singular; all observations used
FLAG_ALBEDO_FROM_NEIGHBOURS = 16  # under-determined pixel solved with its neighbours' albedo
# the fit explained every observation it kept with a diffuse shading below UNFOUNDED_SHADING of a frontal light's
# (its albedo over UNFOUNDED_SHADING times the largest I_k / E_k it kept): the data fix no albedo there, and the
# normal came from a free albedo (e.g. a normal grazing to the view, where plastic's diffuse term vanishes, with an
# albedo of 1e5).  Set with FLAG_FEW_OBSERVATIONS, so that the neighbour pass re-solves the pixel with its
# neighbours' albedo and no neighbour reads it (gpps.kernels.solve_common.unfounded_flag)
FLAG_UNFOUNDED = 32
FLAG_NAMES = {
    FLAG_ILL_CONDITIONED: "ill_conditioned",
    FLAG_FEW_OBSERVATIONS: "few_observations",
    FLAG_NOT_CONVERGED: "not_converged",
    FLAG_WOODHAM_FALLBACK: "woodham_fallback",
    FLAG_ALBEDO_FROM_NEIGHBOURS: "albedo_from_neighbours",
    FLAG_UNFOUNDED: "unfounded",
}
# FLAG_UNFOUNDED's level: a diffuse shading of 0.05 is a Lambertian surface lit 87 deg from its normal; a fit that
# puts every kept observation beyond it has all its brightness in a term the albedo multiplies by almost nothing
UNFOUNDED_SHADING = 0.05

# clipping of images given without a saturation level (gpps._check.clipping, for check_observations and the
# single-image flow's gpps.host.single.prepare_images): observations whose brightest channel sits at one of these values (the
# full scale of float or raw integer data; integer images arrive scaled to 1) are taken as clipped there: at or
# above SATURATED_SHARE of the mask's observations an error (everything saturated), at or above CLIPPED_SHARE (and
# CLIPPED_MIN observations) a warning.  (Any other repeated maximum is left alone: a flat target under a ring of
# lights gives one value everywhere.)
CLIP_LEVELS = (1.0, 255.0, 1023.0, 4095.0, 16383.0, 65535.0)
SATURATED_SHARE = 0.9
CLIPPED_SHARE = 0.05
CLIPPED_MIN = 16
# clipping at any level (gpps.host.clipping.clipped_observations, run by gpps.reconstruct, gpps.Reconstructor and
# solve_normals on float images given without saturation= or valid=): raw images clipped at the sensor's full scale
# and then divided by the lights' intensities sit at 1 / intensity (e.g. 1.25), not at a CLIP_LEVELS value.  A
# clipping sensor gives one identical value at every clipped pixel, and a division by one intensity per image and
# channel keeps them identical, so per image and channel the clipped pixels are the *plateau* at the maximum:
# * PLATEAU_ULPS: the plateau is the values within this many float32 ulps (relative) of the maximum: the same value
#   rounded once more (a float64 quotient cast to float32) still counts, the next 16-bit level (1.5e-5) does not;
# * PLATEAU_MIN: a plateau of fewer pixels is not taken as a clip: a few equal values at the top are chance (or a
#   symmetric scene's mirrored pixels), and leaving out a handful of observations would change nothing anyway;
# * PLATEAU_PILEUP, PLATEAU_LEVELS: a clip piles the whole bright tail into the top value, so the plateau holds at
#   least PLATEAU_PILEUP times the mean pixel count of the next PLATEAU_LEVELS lower distinct values (the tail is
#   at least that many levels' worth); quantised but unclipped data (8-bit with a maximum of 200) has similar
#   counts at its top levels (near a smooth peak each level holds a band of about the same area).  Against the
#   next value alone the counts are too few to compare: unclipped 8-bit renders of the bumps and the sphere had top
#   levels of 9-12 pixels over a next one of 1-6 (counts such as 9, 1, 4, 9, 5 going down).  Measured on 8- and
#   16-bit renders of the bumps, sphere and micro-print scenes (3 and 8 lights, Lambertian, Blinn-Phong,
#   Cook-Torrance, exposures 0.2-2 times the brightest value): against the mean of the next 4 values the unclipped
#   bumps and sphere plateaus reach ratios of up to 3.0 in 8-bit (a Lambertian bumps image whose top level gathers
#   the bumps' inflection ring: 160 pixels over 47-59 a level; 7 of them above 2, 1 at 3.0), so 3 times; the clips
#   this misses are small (8-50 pixels) or channels that only just reach the clip level.  (Noise-free renders of
#   faceted relief, the micro-print, still pile 10-40 unclipped pixels of one normal at the top of some 8- and
#   16-bit images: exact ties no histogram rule tells from a clip; real images' noise breaks such ties);
# * PLATEAU_SPREAD: clipped highlight pixels have different normals, so in at least one other image their values
#   differ by more than this (relative to their largest value there); a flat, uniform-albedo region under a
#   directional light has one value at all its pixels in every image, and a plateau that stays flat everywhere is
#   that region, not a clip;
# and a plateau of SATURATED_SHARE or more of an image's observations is not taken (check_observations' "everything
# saturated" case: nothing is left to fit).
PLATEAU_ULPS = 4
PLATEAU_MIN = 8
PLATEAU_PILEUP = 3.0
PLATEAU_LEVELS = 4
PLATEAU_SPREAD = 1e-3
