"""The material scorer stage: the sample pixels resident on the device, K candidate materials scored per launch.

RON's photometric material update (:mod:`gpps.flows.ron`, step 4) searches
the unknown scene parameters (``ks`` and the lobe width) that minimise the
trimmed energy of a fixed pixel sample ``S`` (highlight pixels first)::

    E(m) = 1/|S'| sum_(p in S') r_p(m)^2

where ``r_p(m)`` is pixel p's RMS residual after its normal and albedo are
re-solved with the material ``m`` (variable projection, seed 4.1-4.2; the
same per-pixel multi-start solve as :class:`gpps.pipeline.solver.PixelSolver`)
and ``S'`` leaves out the ``trim`` fraction of the largest residuals (cast
shadows, inter-reflections).  Scoring each candidate through
``PixelSolver.run`` re-uploads the whole (N, H, W, 3) frame, re-estimates the
noise, launches over every pixel and fetches seven full frames; here::

    scorer = MaterialScorer(images.shape[:3], camera, lights, "cook-torrance", fit_config,
                            max_samples=2000, max_candidates=25, trim=0.02)
    scorer.upload(images, sample_mask, depth=depth, valid=valid)   # once: gathers the samples
    scorer.step([m1, m2, ..., mK])                                  # one launch, (K, P) pixel solves
    energies = scorer.fetch()                                       # (K,) float64, E(m_c)
    more = scorer.fetch_pixels(("normals", "residual"))             # (K, P, 3), (K, P)

:meth:`MaterialScorer.upload` gathers the sample pixels' observations,
``valid`` flags, depth and true (row, column) into a compact strip and
precomputes what does not depend on the material (observation weights with
PixelSolver's shadow, saturation and lit/dark rules, the noise levels
PixelSolver would use, Woodham's start); :meth:`MaterialScorer.step` runs the
candidates x pixels solve of :mod:`gpps.kernels.solve_batched`;
:meth:`MaterialScorer.fetch` copies the (K, P) residuals back and returns the
trimmed energies, computed on the host in float64 exactly as RON's fit did
(a (K, P) float32 copy: 200 KB at K = 25, P = 2000).  A candidate's energy
equals the one of ``PixelSolver`` with the same config on the same sample
mask (tests/test_material_device.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Sequence

import numpy as np

from gpps._check import as_array, as_mask, check_bool, check_choice, check_number, check_unit
from gpps._runtime import block_lanes, resolve_device, warp
from gpps.kernels import solve_batched as sb
from gpps.kernels.solve import batched_in_solve_module, term_cache_size
from gpps.kernels.brdf import MaterialParams
from gpps.lights import PointLights
from gpps.material import Material
from gpps.names import (
    BRDF_NAMES,
    LIGHT_LANES,
    LOBE_PARAMETERS,
    LOBE_RANGES,
    ParallelName,
)
from gpps.pipeline.cpu_threads import cpu_threads, load_first, run_all
from gpps.pipeline.params import camera_params, light_params, resolve_parallel, uses_lanes
from gpps.pipeline.solver import (
    SolverConfig,
    check_light_configuration,
    check_problem,
    estimate_noise,
    rgb_images,
    robust_code,
    solver_params,
)
from gpps.pipeline.stage import Stage

__all__ = ["LobeCandidates", "MaterialScorer", "trimmed_energy"]

Progress = Callable[[float, float, str], None]

_PIXEL_OUTPUTS = ("normals", "albedo", "residual", "iterations", "flags")
# the MaterialParams fields each lobe parameter sets (gpps.pipeline.stream_material.with_lobe's rule)
_LOBE_FIELDS = {"ks": ("ks",), "shininess": ("shininess",), "roughness": ("roughness",), "eta": ("eta_u", "eta_v")}


def trimmed_energy(residual, trim: float) -> np.ndarray:
    """Trimmed mean of the squared residuals, per row: RON's material energy.

    ``E = mean of the smallest max(1, round(P (1 - trim)))`` values of ``r^2``
    (float64), the computation of RON's ``_fit_energy`` on the sample pixels.

    Args:
        residual: (K, P) or (P,) RMS residuals (image units).
        trim: fraction of the largest squared residuals left out, in [0, 0.5].

    Returns:
        (K,) float64 energies (a 0-d array for a (P,) input), image units squared.
    """
    r = np.asarray(residual, np.float64)
    one = r.ndim == 1
    r = np.atleast_2d(r)
    keep = max(1, int(round(r.shape[1] * (1.0 - float(trim)))))
    # (a partition, not a sort: the smallest `keep` in O(P); the mean of the same values)
    r2 = r * r
    e = np.mean(r2 if keep >= r.shape[1] else np.partition(r2, keep - 1, axis=1)[:, :keep], axis=1)
    return e[0] if one else e


def _split_starts(config: SolverConfig, device: str, split_starts: bool | None, parallel: str) -> bool:
    """Whether a :class:`MaterialScorer` runs its starts on threads of their own (its ``split_starts``)."""
    if split_starts is None:
        split_starts = config.split_starts
    return (bool(split_starts) if split_starts is not None
            else (str(device).startswith("cuda") and max(int(config.starts), 1) > 1)) and parallel != "lights"


@dataclass(frozen=True)
class _Builds:
    """The kernel builds a :class:`MaterialScorer` launches (:func:`_scorer_builds`)."""

    robust: str
    parallel: str  #: resolved (:func:`gpps.pipeline.params.resolve_parallel`)
    split_starts: bool
    kernel: object  #: the pixels-parallel build, None for parallel "lights"
    lanes: object  #: the lights-parallel build, None for parallel "pixels"
    starts: tuple  #: the starts-parallel kernels, () without split_starts

    def launched(self, device: str) -> list:
        """Every module variant these builds launch on ``device``: the module of the trimmed energy and the gathers,
        the builds, the lights-parallel one as ``(kernel, block_dim)`` (its own variant)."""
        out = [warp().get_module(sb.__name__)] + [k for k in (self.kernel, *self.starts) if k is not None]
        if self.lanes is not None:
            out.append((self.lanes, block_lanes(device, LIGHT_LANES)))
        return out


def _scorer_builds(config: SolverConfig, brdf: str, device: str, lights: int, parallel: str,
                   split_starts: bool | None) -> _Builds:
    """What a :class:`MaterialScorer` with these settings launches: the one place that chooses it."""
    robust = robust_code(config)
    parallel = resolve_parallel(parallel, device, lights)
    split = _split_starts(config, device, split_starts, parallel)
    return _Builds(
        robust=robust, parallel=parallel, split_starts=split,
        kernel=(sb.get_batched_kernel(config.solver, brdf, robust, cache=term_cache_size(device, lights),
                                      in_solve_module=batched_in_solve_module(device))
                if parallel != "lights" else None),
        lanes=sb.get_batched_kernel(config.solver, brdf, robust, lanes=True) if parallel != "pixels" else None,
        starts=tuple(sb.get_batched_starts_kernels(config.solver, brdf, robust)) if split else (),
    )


def scorer_kernels(config: SolverConfig, brdf: str, device: str, lights: int) -> list:
    """The kernels a :class:`MaterialScorer` built with ``config`` (and its default ``parallel`` and
    ``split_starts``) launches for the model ``brdf``, ``lights`` images on ``device``; the lights-parallel build,
    when it may be launched, as ``(kernel, block_dim)`` (another module variant).  For
    :mod:`gpps.pipeline.prefetch`'s plans."""
    return _scorer_builds(config, brdf, device, lights, config.parallel, None).launched(device)


class MaterialScorer(Stage):
    """Scores candidate materials on a resident pixel sample: K candidates x P pixels per launch.

    Args:
        shape: (N, H, W) of the frames the sample is taken from.
        camera: :class:`gpps.camera.Orthographic` or :class:`Perspective`.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N), unit
            intensities when the images were divided by them.
        brdf: the reflectance model of every candidate (a :class:`Material` or
            its ``brdf`` name): the kernel is specialised for it.
        config: the per-pixel solve's settings, a :class:`SolverConfig` with
            a nonlinear solver, ``neighbour_radius=0``, ``smoothness=0`` and
            ``warm_start=False`` (RON's fit: ``replace(solver, starts=material_starts,
            neighbour_radius=0, smoothness=0.0, warm_start=False)``); the scorer
            solves each pixel on its own, as PixelSolver does with those settings.
        max_samples: capacity P_max of the sample (pixels).
        max_candidates: capacity K_max of one step (candidates).
        trim: fraction of the largest squared residuals left out of each energy, in [0, 0.5].
        parallel: None: ``config.parallel``; ``"pixels"``: one thread a (candidate, pixel) solve; ``"lights"``: one block of
            :data:`gpps.names.LIGHT_LANES` threads a solve, the lights split over the lanes (a GPU
            launch costs its slowest thread: with many images one thread's light loops are the
            critical path, and K x P threads fill a fraction of the GPU); ``"auto"``: chosen per
            launch on CUDA, "lights" with :data:`gpps.names.LIGHTS_PARALLEL_MIN` images or more
            and at most ``LIGHTS_PARALLEL_PAIRS_PER_IMAGE x N`` (candidate, pixel) pairs in the
            launch (measured: :mod:`gpps.names`), else "pixels"; on the CPU always "pixels".
            The two differ only in the order of the light sums (float rounding).  On the CPU a
            block runs as one lane unless ``warp.config.enable_cpu_blocks`` is set.
        split_starts: cold steps of the one-thread build run each of the config's starts in a
            thread of its own, then pick the best per (candidate, pixel) in start order (two
            launches: :func:`gpps.kernels.solve_batched.batched_starts_kernels_for`; the same
            energies up to the code generator's choices).  A GPU launch costs its slowest thread:
            S sequential starts per thread are S times its critical path.  None (default): on
            CUDA when ``config.starts > 1`` (``config.split_starts`` when that is set); False on
            the CPU, whose launch runs its threads one after another anyway (True there is for tests).
        warm_max_iters: cap on the cost evaluations of a warm step's solve (``step(..., warm=True)``: one start a
            pixel, from :meth:`set_start`'s normals); None: ``config.max_iters``, as the cold steps.  A warm
            step's launch costs its slowest solve (see :attr:`gpps.flows.ron.RONConfig.material_warm_iters`).
        device: Warp device (None: CUDA if present).

    Buffers (allocated once, N x K_max x P_max): the strip ``strip`` (N, 1, P_max)
    and its weights, per-sample ``points``/``views``/``ninit``/``gmax``/``flags``,
    the candidates ``mats`` (K_max,), and the outputs ``normals``, ``albedo``,
    ``residual``, ``iterations``, ``flags_k`` (K_max, P_max); robust losses
    add an (N, K_max, P_max) float32 weight buffer.
    """

    def __init__(self, shape, camera, lights, brdf, config: SolverConfig, *, max_samples: int = 2000,
                 max_candidates: int = 25, trim: float = 0.02, parallel: ParallelName | None = None,
                 split_starts: bool | None = None, warm_max_iters: int | None = None, device=None):
        wp = warp()
        n, h, w = check_problem(shape, lights)
        if isinstance(brdf, Material):
            brdf = brdf.brdf
        if brdf not in BRDF_NAMES:
            raise ValueError(f"brdf: expected a Material or one of {list(BRDF_NAMES)}, got {brdf!r}")
        if not isinstance(config, SolverConfig):
            raise TypeError(f"config: expected SolverConfig, got {type(config).__name__}")
        if config.solver == "none":
            raise ValueError("config: expected a nonlinear solver ('lm', 'dogleg' or 'bfgs'), got solver='none' "
                             "(its least-squares normals do not depend on the material)")
        if config.neighbour_radius != 0 or config.smoothness != 0.0 or config.warm_start:
            raise ValueError("config: expected neighbour_radius=0, smoothness=0 and warm_start=False (the scorer "
                             f"solves each pixel on its own), got neighbour_radius={config.neighbour_radius}, "
                             f"smoothness={config.smoothness}, warm_start={config.warm_start}")
        self.max_samples = check_number("max_samples", max_samples, lo=1, integer=True)
        self.max_candidates = check_number("max_candidates", max_candidates, lo=1, integer=True)
        self.trim = check_number("trim", trim, lo=0.0, hi=0.5)
        self.device = resolve_device(device)
        self.shape = (n, h, w)
        self.camera = camera
        self.cam = camera_params(camera, (h, w))
        self.lights = lights
        self.lp = light_params(lights, self.device)
        self.brdf = brdf
        self.config = config
        # the parameter struct and specialisation PixelSolver uses for this config, without the cast-shadow refit
        # (SolverConfig.shadow_relative): the scores compare candidate materials on the same observations, and a
        # refit that sets aside the observations a fit contradicts would let a wrong material discard its misfit
        # (on a Mitsuba bowl it drove ks to the search's bound, 0.83 -> 3.0)
        self.prm = solver_params(replace(config, shadow_relative=0.0))
        # warm steps: one start per pixel, from ``nwarm`` (set_start)
        if warm_max_iters is not None:
            check_number("warm_max_iters", warm_max_iters, lo=1, integer=True)
        self.warm_max_iters = int(config.max_iters if warm_max_iters is None else warm_max_iters)
        self.prm_warm = solver_params(replace(config, warm_start=True, starts=1, shadow_relative=0.0,
                                              max_iters=self.warm_max_iters))
        self._cmds: dict = {}  # recorded launches of _launch_chunk
        parallel = check_choice("parallel", config.parallel if parallel is None else parallel, ParallelName)
        if split_starts is not None:
            check_bool("split_starts", split_starts)
        builds = _scorer_builds(config, brdf, self.device, n, parallel, split_starts)
        self._robust = builds.robust
        self.parallel = builds.parallel  # "auto" here: per launch (_uses_lanes)
        self._kernel, self._kernel_lanes = builds.kernel, builds.lanes
        d, pm, km = self.device, int(self.max_samples), int(self.max_candidates)
        ns = max(int(config.starts), 1)
        self.split_starts = builds.split_starts
        if self.split_starts:
            self._starts_kernels = builds.starts
            self._start_bufs = [self._buffer((km, pm, ns), dt, d)
                                for dt in (wp.vec3, wp.vec3, wp.float32, wp.int32, wp.int32)]
        self._settle(*builds.launched(self.device))
        self.strip = self._buffer((n, 1, pm), wp.vec3, d)
        self.strip_valid = self._buffer((n, 1, pm), wp.uint8, d, fill=1)
        self.rows = self._buffer(pm, wp.int32, d)
        self.cols = self._buffer(pm, wp.int32, d)
        self.sample_depth = self._buffer(pm, wp.float32, d, fill=1)
        self.noise = self._buffer(n, wp.float32, d)
        self.noise_level = np.zeros(n, np.float32)
        self.base_weights = self._buffer((n, 1, pm), wp.float32, d)
        self.points = self._buffer(pm, wp.vec3, d)
        self.views = self._buffer(pm, wp.vec3, d)
        self.ninit = self._buffer(pm, wp.vec3, d)
        self.nwarm = self._buffer(pm, wp.vec3, d)
        self.warm_ready = False
        self.gmax = self._buffer(pm, wp.float32, d)
        self.flags = self._buffer(pm, wp.int32, d)
        self.cond = self._buffer(pm, wp.float32, d)
        self.mats = self._buffer(km, MaterialParams, d)
        self.normals = self._buffer((km, pm), wp.vec3, d)
        self.albedo = self._buffer((km, pm), wp.vec3, d)
        self.residual = self._buffer((km, pm), wp.float32, d)
        self.iterations = self._buffer((km, pm), wp.int32, d)
        self.flags_k = self._buffer((km, pm), wp.int32, d)
        # one copy of the observations (and, without IRLS, of the weights) serves every candidate
        self._strip_k = _broadcast_k(wp, self.strip, km)
        self._base_k = _broadcast_k(wp, self.base_weights, km)  # (the starts-parallel build's starts read it)
        if self._robust == "none":
            self._weights_k = _broadcast_k(wp, self.base_weights, km)
        else:
            self._weights_k = self._buffer((n, km, pm), wp.float32, d)
        self._mats_host = np.zeros(km, dtype=MaterialParams.numpy_dtype())
        self.samples = 0  # P of the current upload
        self.candidates = 0  # K of the last step
        self.rows_host = np.zeros(0, np.int64)
        self.cols_host = np.zeros(0, np.int64)
        # upload_device without depth / valid: never-read stand-ins of the gather's unused arguments
        self._no_depth = self._buffer((1, 1), wp.float32, d, fill=1)
        self._no_valid = self._buffer((n, 1, 1), wp.uint8, d, fill=1)
        self._device_noise = None
        self._closed = False

    # ------------------------------------------------------------------ upload

    def _images(self, images) -> np.ndarray:
        return rgb_images(images, self.shape)

    def upload(self, images, sample_mask, *, depth=None, valid=None, noise=None) -> None:
        """Gather the sample pixels into the device strip and precompute their material-free terms.

        Args:
            images: (N, H, W, 3) RGB or (N, H, W) grey observations >= 0 (image units,
                divided by the light intensities when the lights have unit intensity).
            sample_mask: (H, W) bool, the P <= ``max_samples`` pixels to score on.
            depth: (H, W) depth (> 0 on the sample, scene units); required for point
                lights (2.30-2.31), optional otherwise (then 1, as PixelSolver).
            valid: optional (N, H, W) bool observations to use.
            noise: optional (N,) noise standard deviation of each image's grey values
                (image units).  None: what ``PixelSolver.upload`` would use for this
                frame and mask: ``config.noise_level``, else
                :func:`gpps.pipeline.solver.estimate_noise` of ``images`` on ``sample_mask``.

        Raises:
            ValueError: shapes, an empty or too large sample, depth <= 0 on the
                sample, degenerate point lights at the sample's median point.
        """
        self._check_open()
        n, h, w = self.shape
        img = self._images(images)
        m = as_mask("sample_mask", sample_mask, (h, w))
        rows, cols = np.nonzero(m)
        p = int(rows.size)
        if p > self.max_samples:
            raise ValueError(f"sample_mask: expected at most max_samples={self.max_samples} pixels, got {p}")
        if depth is None:
            if isinstance(self.lights, PointLights):
                raise ValueError("depth: expected an (H, W) depth estimate for point lights (2.30-2.31), got None")
            dep = np.ones(p, np.float32)
        else:
            dep = as_array("depth", depth, shape=(h, w))[rows, cols].astype(np.float32)
            if np.any(dep <= 0):
                raise ValueError("depth: expected values > 0 inside the sample mask")
        if valid is None:
            val = np.ones((n, p), np.uint8)
        else:
            val = np.asarray(valid)
            if val.shape != (n, h, w):
                raise ValueError(f"valid: expected shape ({n}, {h}, {w}), got {val.shape}")
            val = (val[:, rows, cols] > 0).astype(np.uint8)
        if isinstance(self.lights, PointLights):
            # as PixelSolver: the configuration must determine normals at the sample's centre
            full = np.zeros((h, w), np.float32)
            full[rows, cols] = dep
            pts = self.camera.backproject(full)
            check_light_configuration(self.lights, np.median(pts[m], axis=0))
        if noise is not None:
            lev = as_array("noise", noise, shape=(n,))
            if np.any(lev < 0):
                raise ValueError("noise: expected values >= 0")
            self.noise_level = lev.astype(np.float32)
        elif self.config.noise_level is not None:
            self.noise_level = np.full(n, self.config.noise_level, np.float32)
        else:
            self.noise_level = estimate_noise(img, m)
        pm = self.max_samples
        strip = np.zeros((n, 1, pm, 3), np.float32)
        strip[:, 0, :p] = img[:, rows, cols]
        vstrip = np.zeros((n, 1, pm), np.uint8)
        vstrip[:, 0, :p] = val
        self.strip.assign(strip)
        self.strip_valid.assign(vstrip)
        self.rows.assign(np.pad(rows.astype(np.int32), (0, pm - p)))
        self.cols.assign(np.pad(cols.astype(np.int32), (0, pm - p)))
        self.sample_depth.assign(np.pad(dep, (0, pm - p), constant_values=1.0))
        self.noise.assign(self.noise_level)
        self.samples = p
        self.candidates = 0
        self.warm_ready = False
        self.rows_host, self.cols_host = rows, cols
        self._prepare(p)

    def upload_device(self, images, rows, cols, count: int, *, valid=None, depth=None, noise=None) -> None:
        """Gather the sample from frame buffers already on the device: no host copy, no host wait.

        The device form of :meth:`upload` for a caller whose frames live on the device (the stream's
        full mode, :mod:`gpps.pipeline.stream_material`): two launches (the gather, then the
        material-free terms of :data:`gpps.kernels.solve_batched.prepare_samples_kernel`) and, where the
        arguments are not the scorer's own buffers, device-to-device copies, so it can be captured in a
        CUDA graph and re-run on every frame of a moving scene.  Unlike :meth:`upload` it checks no
        values (pixels in range, depth > 0 and the point lights' configuration are the caller's) and
        estimates no noise; :attr:`rows_host` / :attr:`cols_host` are None (the pixels live on the device).

        Args:
            images: (N, H, W) Warp vec3 array on the scorer's device: RGB observations (image units,
                divided by the light intensities when the lights have unit intensity).
            rows, cols: Warp int32 arrays on the device, at least ``count`` long: the sample pixels' row and
                column (``self.rows`` / ``self.cols`` themselves: nothing is copied).
            count: P <= ``max_samples``, the sample size (host int: fixes the launch size).
            valid: (N, H, W) Warp uint8 array, 1 where an observation is used; None: all.
            depth: (H, W) Warp float32 depth (scene units) at every pixel; None: 1 (directional lights).
            noise: (N,) Warp float32 noise level of each image's grey values (image units); None:
                ``config.noise_level``, else 0 (no noise test, as a stream's solver).

        Raises:
            ValueError / TypeError: an array of the wrong shape, dtype or device, a bad ``count``, no
                depth for point lights.
        """
        self._check_open()
        wp = warp()
        n, h, w = self.shape
        p = check_number("count", count, lo=1, hi=self.max_samples, integer=True)

        def need(name, a, shape, dtype, *, at_least=False):
            if not isinstance(a, wp.array):
                raise TypeError(f"{name}: expected a Warp array on {self.device}, got {type(a).__name__}")
            ok = (len(a.shape) == 1 and a.shape[0] >= shape[0]) if at_least else tuple(a.shape) == shape
            if not ok or a.dtype != dtype or str(a.device) != str(wp.get_device(self.device)):
                want = f"({shape[0]},) or longer" if at_least else str(shape)
                raise ValueError(f"{name}: expected a {want} {dtype.__name__} array on {self.device}, got "
                                 f"{tuple(a.shape)} {getattr(a.dtype, '__name__', a.dtype)} on {a.device}")

        need("images", images, (n, h, w), wp.vec3)
        need("rows", rows, (p,), wp.int32, at_least=True)
        need("cols", cols, (p,), wp.int32, at_least=True)
        if valid is not None:
            need("valid", valid, (n, h, w), wp.uint8)
        if depth is not None:
            need("depth", depth, (h, w), wp.float32)
        elif isinstance(self.lights, PointLights):
            raise ValueError("depth: expected an (H, W) depth estimate for point lights (2.30-2.31), got None")
        if noise is not None:
            need("noise", noise, (n,), wp.float32)
        if rows is not self.rows:
            wp.copy(self.rows, rows, count=p)
        if cols is not self.cols:
            wp.copy(self.cols, cols, count=p)
        if noise is not None:
            wp.copy(self.noise, noise)
        elif self._device_noise is None or self._device_noise != self.config.noise_level:
            lev = 0.0 if self.config.noise_level is None else float(self.config.noise_level)
            self.noise_level = np.full(n, lev, np.float32)
            self.noise.assign(self.noise_level)
            self._device_noise = self.config.noise_level
        if valid is None:
            self.strip_valid.fill_(1)
        if depth is None:
            self.sample_depth.fill_(1.0)
        self.samples = p
        self.warm_ready = False
        self.rows_host = self.cols_host = None  # (the candidates of set_candidates stay: launch() scores them)
        wp.launch(sb.gather_samples_kernel, dim=p,
                  inputs=[images, self._no_valid if valid is None else valid,
                          self._no_depth if depth is None else depth, self.rows, self.cols,
                          int(valid is not None), int(depth is not None)],
                  outputs=[self.strip, self.strip_valid, self.sample_depth],
                  device=self.device)
        self._prepare(p)

    def upload_from(self, solver, sample_mask) -> None:
        """:meth:`upload` from a :class:`gpps.pipeline.solver.PixelSolver` that holds the frame (its last upload):
        the sample is gathered on the device from the solver's images, observation mask and depth
        (:meth:`upload_device`), and scored with the solver's noise levels (:attr:`PixelSolver.noise`: the whole
        frame's estimate, which decides there which dim observations count as lit), so the candidates are fitted
        to the observations the solver's own fits use.  Only the sample's pixel indices go to the device.

        Args:
            solver: a PixelSolver on this scorer's device, for this (N, H, W), with this scorer's camera and lights
                (only the shape and the device are checked), holding the frame.
            sample_mask: (H, W) bool, the P <= ``max_samples`` pixels to score on (inside the solver's mask).

        Raises:
            ValueError: another shape or device, an empty or too large sample.
        """
        self._check_open()
        _, h, w = self.shape
        if tuple(solver.shape) != self.shape or str(solver.device) != str(self.device):
            raise ValueError(f"solver: expected a PixelSolver for {self.shape} on {self.device}, got "
                             f"{tuple(solver.shape)} on {solver.device}")
        m = as_mask("sample_mask", sample_mask, (h, w))
        rows, cols = np.nonzero(m)
        p = int(rows.size)
        if p > self.max_samples:
            raise ValueError(f"sample_mask: expected at most max_samples={self.max_samples} pixels, got {p}")
        pm = self.max_samples
        self.rows.assign(np.pad(rows.astype(np.int32), (0, pm - p)))
        self.cols.assign(np.pad(cols.astype(np.int32), (0, pm - p)))
        self.upload_device(solver.images, self.rows, self.cols, p, valid=solver.valid, depth=solver.depth,
                           noise=solver.noise)
        self.noise_level = np.asarray(solver.noise_level, np.float32).copy()
        self.candidates = 0
        self.rows_host, self.cols_host = rows, cols

    def _prepare(self, p: int) -> None:
        """The material-free terms of the ``p`` gathered sample pixels (one launch)."""
        warp().launch(sb.prepare_samples_kernel, dim=p,
                      inputs=[self.strip, self.strip_valid, self.rows, self.cols, self.sample_depth, self.noise,
                              self.cam, self.lp, self.prm],
                      outputs=[self.base_weights, self.points, self.views, self.ninit, self.gmax, self.flags,
                               self.cond],
                      device=self.device)

    def set_start(self, normals=None, *, candidate: int | None = None, frame=None) -> None:
        """The start normals of later warm steps (``step(..., warm=True)``): one start per pixel.

        Args:
            normals: (P, 3) unit normals of the sample pixels, in ``(rows_host, cols_host)``
                order (as ``x[sample_mask]``), e.g. the normals RON solved this round.
            candidate: instead of ``normals``: the normals the last step solved for its
                candidate ``candidate`` (a device copy, nothing comes back).
            frame: instead of ``normals``: an (H, W) ``wp.vec3`` array on the scorer's device
                (e.g. :attr:`PixelSolver.normals` after a round's solve), gathered at the sample
                pixels on the device; a pixel whose normal there is not a unit vector starts
                from Woodham's normal.

        Raises:
            ValueError: not exactly one given, wrong shape or device, no upload / step to take them from.
        """
        self._check_open()
        if sum(x is not None for x in (normals, candidate, frame)) != 1:
            raise ValueError("normals, candidate, frame: expected exactly one of them")
        p = self.samples
        if p == 0:
            raise ValueError("set_start: expected an upload of the sample pixels first")
        wp = warp()
        if frame is not None:
            h, w = self.shape[1:]
            if not isinstance(frame, wp.array) or frame.dtype != wp.vec3 or frame.shape != (h, w):
                raise ValueError(f"frame: expected an ({h}, {w}) wp.vec3 array, got "
                                 f"{getattr(frame, 'shape', type(frame).__name__)}")
            if str(frame.device) != str(self.ninit.device):
                raise ValueError(f"frame: expected an array on {self.ninit.device}, got one on {frame.device}")
            wp.launch(sb.gather_start_kernel, dim=p, inputs=[frame, self.rows, self.cols, self.ninit],
                      outputs=[self.nwarm], device=self.device)
        elif candidate is not None:
            k = int(candidate)
            if not 0 <= k < self.candidates:
                raise ValueError(f"candidate: expected 0 <= candidate < {self.candidates} (the last step's), got {k}")
            wp.copy(self.nwarm, self.normals, dest_offset=0, src_offset=k * self.max_samples, count=p)
        else:
            nrm = as_array("normals", normals, shape=(p, 3)).astype(np.float32)
            check_unit("normals", nrm, where="at the sample pixels")
            full = np.zeros((self.max_samples, 3), np.float32)
            full[:p] = nrm
            self.nwarm.assign(full)
        self.warm_ready = True

    # ------------------------------------------------------------------ step

    def set_candidates(self, candidates: Sequence[Material]) -> None:
        """Copy K <= ``max_candidates`` candidate materials to the device, for :meth:`launch` (a small
        host-to-device copy: call it where the host may wait, e.g. after a frame's synchronisation)."""
        self._check_open()
        self.candidates = self._set_candidates(candidates)

    def launch(self, *, count: int | None = None, warm: bool = False) -> None:
        """Score the candidates of the last :meth:`set_candidates` on the current sample: one launch of
        K x P threads, no copy and no host wait (graph-capturable; the candidates are read from the
        device buffer ``mats``, so a captured launch scores whatever was set last).

        Args:
            count: score the first ``count`` rows of ``mats`` as they are on the device (rows a kernel wrote,
                e.g. :class:`gpps.pipeline.material_search.NelderMeadSearch`'s), instead of the last
                :meth:`set_candidates`' K.
            warm: from :meth:`set_start`'s normals, one start per pixel (as ``step(..., warm=True)``).
        """
        self._check_open()
        if self.samples == 0:
            raise ValueError("launch: expected an upload of the sample pixels first")
        if count is not None:
            self.candidates = check_number("count", count, lo=1, hi=self.max_candidates, integer=True)
        if self.candidates == 0:
            raise ValueError("launch: expected set_candidates first")
        if warm and not self.warm_ready:
            raise ValueError("warm: expected set_start(...) after the last upload")
        self._launch_chunk(self.candidates, 0, self.samples, warm=bool(warm))

    def _launch_chunk(self, k: int, a: int, b: int, *, warm: bool = False) -> None:
        """One launch: candidates ``0..k`` x sample pixels ``a..b``, cold (Woodham's start, the config's
        multi-start) or ``warm`` (one start from :meth:`set_start`'s normals)."""
        self._chunk_cmd(k, a, b, warm=warm).launch()

    def _chunk_cmd(self, k: int, a: int, b: int, *, warm: bool = False):
        """The recorded launch(es) of :meth:`_launch_chunk` (recorded at the first use; record on the calling
        thread before launching from several: a CPU recording raced with another thread's launch (segfault))."""
        lanes = self._uses_lanes(k * int(b - a))
        key = (bool(warm), int(k), int(a), int(b), lanes)
        cmd = self._cmds.get(key)
        if cmd is None:
            # recorded once per (warm, K, pixel range, build): the ~17 arguments (three structs) are packed
            # once, not at every candidate batch of the search (the buffers never change: the candidates
            # are read from ``mats``, the sample from the strip)
            ninit, prm = (self.nwarm, self.prm_warm) if warm else (self.ninit, self.prm)
            args = dict(inputs=[self._strip_k, self.base_weights, self.points, self.views, ninit, self.gmax,
                                self.flags, self.lp, self.mats, prm, int(a)],
                        outputs=[self._weights_k, self.normals, self.albedo, self.residual, self.iterations,
                                 self.flags_k],
                        device=self.device, record_cmd=True)
            wp = warp()
            if lanes:
                nl = block_lanes(self.device, LIGHT_LANES)
                cmd = wp.launch(self._kernel_lanes, dim=(k, int(b - a), nl), block_dim=nl, **args)
            elif self.split_starts and not warm:
                starts, finish = self._starts_kernels
                ns = int(self._start_bufs[0].shape[2])
                one = wp.launch(starts, dim=(k, int(b - a), ns), device=self.device, record_cmd=True,
                                inputs=[self._strip_k, self._base_k, self.points, self.views, ninit, self.lp,
                                        self.mats, prm, int(a)], outputs=self._start_bufs)
                two = wp.launch(finish, dim=(k, int(b - a)), device=self.device, record_cmd=True,
                                inputs=[self._strip_k, self.base_weights, self.points, self.views, ninit, self.gmax,
                                        self.flags, self.lp, self.mats, prm, int(a)] + self._start_bufs,
                                outputs=args["outputs"])
                cmd = _Both(one, two)
            else:
                cmd = wp.launch(self._kernel, dim=(k, int(b - a)), **args)
            if len(self._cmds) >= 256:
                self._cmds.clear()
            self._cmds[key] = cmd
        return cmd

    def _uses_lanes(self, pairs: int) -> bool:
        """Whether a launch of ``pairs`` (candidate, pixel) solves runs the lights-parallel build."""
        return uses_lanes(self.parallel, self.shape[0], pairs)

    def _set_candidates(self, candidates) -> int:
        if isinstance(candidates, LobeCandidates):
            if candidates.material.brdf != self.brdf or candidates.values.shape[0] > self.max_candidates:
                raise ValueError("candidates: expected lobe_candidates() of this scorer")
            c = candidates.material
            host = self._mats_host
            k = candidates.values.shape[0]
            row = (c.device_tag, c.ks, c.shininess, c.roughness, c.f0, c.eta_u, c.eta_v)
            host[:k] = row
            for i, n in enumerate(candidates.names):
                for field in _LOBE_FIELDS[n]:
                    host[field][:k] = candidates.values[:, i]
            self.mats.assign(host)
            return k
        if isinstance(candidates, Material):
            candidates = [candidates]
        try:
            cands = list(candidates)
        except TypeError:
            raise TypeError("candidates: expected a Material or a sequence of them, "
                            f"got {type(candidates).__name__}") from None
        if not 1 <= len(cands) <= self.max_candidates:
            raise ValueError(f"candidates: expected 1 to max_candidates={self.max_candidates} materials, "
                             f"got {len(cands)}")
        for c in cands:
            if not isinstance(c, Material):
                raise TypeError(f"candidates: expected gpps.Material items, got {type(c).__name__}")
            if c.brdf != self.brdf:
                raise ValueError(f"candidates: expected {self.brdf!r} materials (the scorer's model), got {c.brdf!r}")
        host = self._mats_host
        for k, c in enumerate(cands):
            # (the fields of material_params' struct, read straight from the Material: no Warp struct a candidate)
            host[k] = (c.device_tag, c.ks, c.shininess, c.roughness, c.f0, c.eta_u, c.eta_v)
        self.mats.assign(host)
        return len(cands)

    def lobe_candidates(self, material: Material, names: Sequence[str], values) -> "LobeCandidates":
        """K candidates that differ from ``material`` only in its lobe parameters ``names`` (``"eta"``:
        ``eta_u = eta_v``), one row of ``values`` (K, len(names)) each, for :meth:`step`: packed for the device
        without a :class:`Material` per candidate (the search's inner loop).  Each value must lie in the parameter's
        range (:data:`gpps.names.LOBE_RANGES`), which keeps every candidate a valid material."""
        if not isinstance(material, Material):
            raise TypeError(f"material: expected gpps.Material, got {type(material).__name__}")
        if material.brdf != self.brdf:
            raise ValueError(f"material: expected a {self.brdf!r} material (the scorer's model), got {material.brdf!r}")
        names = tuple(names)
        bad = [n for n in names if n not in LOBE_PARAMETERS[self.brdf]]
        if bad:
            raise ValueError(f"names: expected parameters of {self.brdf!r} from {LOBE_PARAMETERS[self.brdf]}, "
                             f"got {bad}")
        v = np.asarray(values, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != len(names) or not 1 <= v.shape[0] <= self.max_candidates:
            raise ValueError(f"values: expected (K, {len(names)}) with 1 <= K <= max_candidates={self.max_candidates}, "
                             f"got {v.shape}")
        for i, n in enumerate(names):
            lo, hi = LOBE_RANGES[n]
            if not np.all(np.isfinite(v[:, i])) or v[:, i].min() < lo * (1 - 1e-12) or v[:, i].max() > hi * (1 + 1e-12):
                raise ValueError(f"values: expected {n} in [{lo:g}, {hi:g}], "
                                 f"got {v[:, i].min():g} .. {v[:, i].max():g}")
        return LobeCandidates(material, names, v)

    def step(self, candidates: Sequence[Material], *, warm: bool = False, progress: Progress | None = None,
             chunks: int | None = None) -> None:
        """Solve every sample pixel for every candidate: one launch of K x P threads.

        Args:
            candidates: K <= ``max_candidates`` materials of the scorer's model
                (their parameters may all differ).
            warm: solve each pixel from one start, the normals of :meth:`set_start`
                (continuation: candidates near the material those normals were solved
                with), instead of the config's cold multi-start from Woodham's normal.
            progress: optional ``progress(done, total, message)`` in pixel solves
                (``total = K * P``), called after each launch has finished.
            chunks: launches the pixels are split over (each launch still holds all
                K candidates), so that ``progress`` moves during a long step.  None:
                1 without ``progress``; with it, 1 on CUDA and 16 on the CPU (whose
                Warp backend runs a launch on one thread: each chunk is split over the threads).  With ``chunks > 1`` (or a
                ``progress``) the host waits for each launch.

        No copy comes back; without ``progress`` and with one chunk the host
        does not wait.
        """
        self._check_open()
        if self.samples == 0:
            raise ValueError("step: expected an upload of the sample pixels first")
        if warm and not self.warm_ready:
            raise ValueError("warm: expected set_start(...) after the last upload")
        k = self._set_candidates(candidates)
        self.candidates = k
        p = self.samples
        cuda = self.device.startswith("cuda")
        if chunks is None:
            chunks = 1 if progress is None or cuda else 16
        chunks = min(check_number("chunks", chunks, lo=1, integer=True), p)
        # on the CPU each chunk is split again over the threads (gpps.pipeline.cpu_threads), run together
        threads = 1 if cuda else min(cpu_threads(), max(1, p // max(chunks, 1)))
        if self.parallel == "lights":
            threads = 1  # Warp's CPU tile code keeps block scratch memory that concurrent launches share (segfault)
        kernels = [x for x in (self._kernel, self._kernel_lanes) if x is not None]
        if self.split_starts:
            kernels += list(self._starts_kernels)
        wp = warp()
        bounds = np.linspace(0, p, chunks + 1).round().astype(int)

        if threads > 1:
            for kern in kernels:
                load_first(kern, self.device)
        for a, b in zip(bounds[:-1], bounds[1:]):
            parts = np.linspace(a, b, threads + 1).round().astype(int)
            # recorded here, on this thread; the threads only launch
            cmds = [self._chunk_cmd(k, int(x), int(y), warm=warm) for x, y in zip(parts[:-1], parts[1:]) if y > x]
            run_all([c.launch for c in cmds])
            if progress is not None or chunks > 1:
                wp.synchronize_device(self.device)
            if progress is not None:
                progress(float(k * b), float(k * p), f"material: {k} candidates, {int(b)}/{p} pixels")

    # ------------------------------------------------------------------ fetch

    def fetch(self) -> np.ndarray:
        """The last step's trimmed energies: (K,) float64, image units squared (see :func:`trimmed_energy`)."""
        return trimmed_energy(self.fetch_pixels(("residual",))["residual"], self.trim)

    def fetch_pixels(self, names=_PIXEL_OUTPUTS) -> dict:
        """The last step's per-(candidate, pixel) results as numpy copies, pixels in ``(rows_host, cols_host)`` order
        (row-major, as ``x[sample_mask]``): ``normals`` (K, P, 3) unit normals, ``albedo`` (K, P, 3), ``residual``
        (K, P) RMS residual (image units), ``iterations`` (K, P), ``flags`` (K, P) (bits of :mod:`gpps.names`).
        """
        self._check_open()
        if self.candidates == 0:
            raise ValueError("fetch: expected a step first")
        bad = [x for x in names if x not in _PIXEL_OUTPUTS]
        if bad:
            raise ValueError(f"names: expected names from {list(_PIXEL_OUTPUTS)}, got {bad}")
        k, p = self.candidates, self.samples
        out = {}
        for x in names:
            buf = self.flags_k if x == "flags" else getattr(self, x)
            # only the K scored rows cross (a view of the first K rows of the max_candidates buffer)
            out[x] = np.array(buf[:k].numpy()[:, :p], copy=True)
        return out

    def run(self, images, sample_mask, candidates, *, depth=None, valid=None, noise=None, progress=None) -> np.ndarray:
        """``upload``, ``step(candidates)`` and ``fetch()`` in one: (K,) energies."""
        self.upload(images, sample_mask, depth=depth, valid=valid, noise=noise)
        self.step(candidates, progress=progress)
        return self.fetch()

    def close(self) -> None:
        """Give the device buffers back to the process's pool (:mod:`gpps.pipeline.buffers`); the scorer
        refuses work afterwards."""
        self._release_buffers()
        for name in ("strip", "strip_valid", "rows", "cols", "sample_depth", "noise", "base_weights", "points",
                     "views", "ninit", "nwarm", "gmax", "flags", "cond", "mats", "normals", "albedo", "residual",
                     "iterations", "flags_k", "_strip_k", "_weights_k", "lp", "_no_depth", "_no_valid", "_cmds",
                     "_base_k", "_start_bufs", "_starts_kernels"):
            self.__dict__.pop(name, None)
        self._closed = True


class _Both:
    """Two recorded launches run as one (the starts-parallel step)."""

    def __init__(self, one, two):
        self.one, self.two = one, two

    def launch(self) -> None:
        self.one.launch()
        self.two.launch()


@dataclass(frozen=True)
class LobeCandidates:
    """Candidates of :meth:`MaterialScorer.lobe_candidates`: ``material`` with its lobe parameters ``names`` set to
    each row of ``values`` (K, len(names))."""

    material: Material
    names: tuple
    values: np.ndarray


def _broadcast_k(wp, base, k: int):
    """An (N, k, P) view of an (N, 1, P) array with stride 0 along axis 1 (no copy)."""
    n, _, p = base.shape
    return wp.array(ptr=base.ptr, dtype=base.dtype, shape=(n, k, p), strides=(base.strides[0], 0, base.strides[2]),
                    device=base.device, copy=False)
