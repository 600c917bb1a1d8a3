"""Real-time photometric stereo on a stream of frame sets (e.g. triples under three lights).

:class:`Stream` is configured once (camera, lights, material, mask, frame size)
and allocates every buffer once on its device.  Per frame it runs:
1. upload (host frames into a pinned staging buffer, then an asynchronous copy
   on a separate CUDA stream; two slots, so the next frame's upload overlaps the
   current frame's compute in :meth:`Stream.run`);
2. conversion of the raw frame (uint8 / uint16 / float32, grey or RGB) to
   the solver's RGB images, divided by full scale and light intensities;
3. the per-pixel solve (:class:`gpps.pipeline.solver.PixelSolver`) warm-started
   from the previous frame's normals with a fixed number of iterations (the
   first frame gets the full multi-start solve);
4. integration (:class:`gpps.pipeline.integration_device.StreamIntegrator`),
   warm-started from the previous frame's depth, a fixed number of PCG
   iterations (the first frame: to tolerance); for point lights the depth is
   the solver's depth estimate of the next frame (one frame of lag, the RON
   loop spread over the stream).

On CUDA steps 2-3 are captured in CUDA graphs after ``capture_after`` frames
(never the first: modules may still be loading) and replayed; the integration
is a few fused Taichi launches.  Warp and Taichi share the buffers in place
(``wp.to_torch`` views); nothing returns to the host unless asked for.

Bad frames yield a :class:`StreamResult` with ``error`` set and leave the state
(warm starts, running levels) untouched; the stream goes on.  A frame is bad
when it has the wrong shape or dtype, NaN/inf or negative values, or fails the
per-frame sanity check (``StreamConfig.check``): too few lit observations (a
black frame, lights that did not fire), too many saturated ones, a
high-frequency (noise) ratio far above the running level, or a residual after
the solve far above the running level.  The statistics come from one small
kernel over the converted frame and one over the residual, read back at the
frame's one synchronisation point.  On a warm-started frame, the pixels whose
residual jumps above ``jump_factor`` times the running level are re-solved cold
(multi-start) within the frame, so a scene change or a bad start heals at once.

Length: the config (every check's threshold documented in place), the result and the one stage whose
frame state (upload slots, graphs, running levels of the sanity check) must stay together.
"""

from __future__ import annotations

import importlib.util
import time
from dataclasses import dataclass
from typing import Any, Iterable, Iterator, Literal

import numpy as np

from gpps import _taichi
from gpps._check import as_mask, check_bool, check_choices, check_number, check_shape
from gpps._runtime import resolve_device, warp
from gpps.camera import Orthographic, Perspective
from gpps.host.dgmc import DGMCConfig
from gpps.host.merge import ranks_better
from gpps.kernels import stream as ks
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material, check_model_images
from gpps.names import FLAG_FEW_OBSERVATIONS, LOBE_RANGES, GraphName
from gpps.pipeline.dgmc import DeviceDGMC
from gpps.pipeline.integration_device import StreamIntegrator
from gpps.pipeline.solver import PixelSolver, SolverConfig
from gpps.pipeline.stage import Stage
from gpps.pipeline.stream_material import StreamMaterial, lobe_names

__all__ = ["StreamConfig", "StreamResult", "Stream"]

Output = Literal["device", "numpy"]
StreamSolver = Literal["lm", "dogleg", "bfgs"]
MaterialMode = Literal["known", "estimate"]
_DTYPES = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0, np.dtype(np.float32): 1.0}


@dataclass(frozen=True)
class StreamConfig:
    """Options of :class:`Stream`.

    Attributes:
        solver: per-pixel solver of the warm-started frames.
        iterations: solver cost evaluations per pixel and frame (warm frames, fixed work).
        first_starts: starts per pixel of the first (cold) frame's full solve.
        first_iterations: evaluation cap per start of the first frame.
        integrate: compute depth.
        integration_iterations: iterations of the integrator per warm frame
            (V-cycle corrections with the default
            :class:`~gpps.pipeline.integration_device.StreamIntegratorConfig`;
            one keeps a streaming step within 1e-4 of the depth range).
        first_tol: relative residual of the first frame's integration (or the float32
            floor where that lies above it: :meth:`StreamIntegrator.step`).
        reference_depth: mean depth per mask component (scene units); required
            for point lights (their 1/r^2 needs metric depth), optional otherwise
            (perspective default: mean log-depth 0; orthographic: mean depth 0).
        graph: ``"auto"`` captures CUDA graphs on CUDA, ``"off"`` never.
        capture_after: frames run eagerly before the capture.
        output: ``"device"`` results are Warp arrays (views of a ring of
            ``ring`` output slots, valid for that many frames); ``"numpy"`` copies.
        ring: output slots (device output).
        saturation: raw observations with a channel at or above this fraction
            of full scale are dropped from the fit (default 1.0: the full scale,
            where the camera clipped; None: keep all).
        check: run the per-frame sanity check and the cold re-solve of
            jumped pixels (see the module docstring).
        min_lit_fraction: a frame with fewer lit observations (grey above
            1e-3 of full scale) than this share, or than half the running
            share, is rejected.
        max_saturated_fraction: a frame with more observations at full scale
            (any channel) than this share, or 0.25 more than the running share,
            is rejected.
        max_noise_ratio: a frame whose high-frequency ratio exceeds this, or
            ``noise_factor`` times the running ratio (and 0.05), is rejected.  The
            ratio is the Immerkaer noise estimate of the shading ratios
            ``N I_k / sum_l I_l`` (the albedo cancels, so texture does not
            count): 0.0001-0.008 for lit renders (textured, 8 or 16 bit), 0.22 for
            an RGB noise frame, 0.43 for a grey one
            (:func:`gpps.kernels.stream.frame_stats`).
        noise_factor: see ``max_noise_ratio``.
        residual_factor: a frame whose mean residual (after the cold re-solve
            of jumped pixels) exceeds this many times the running level, and 2 %
            of its mean grey value, is rejected (the first frame: 50 %).
        jump_factor: warm-started pixels whose residual exceeds this many times
            both their own residual in the last accepted frame and the running
            mean residual (and 0.1 % of the mean grey value) are re-solved cold
            within the frame (``redo_starts`` starts of ``redo_iterations``).
        redo_starts, redo_iterations: the cold re-solve of jumped pixels (as the
            first frame's by default).  Mean MAEN over 120 frames of the moving
            64^2 scene of ``perf/_common.moving_bumps`` on the CPU: 0.07 deg with
            these, 0.11 with 4 starts of 20 iterations, 3.3 deg (4.6 over the
            last 10 frames) without any re-solve (``check=False``).
        material: ``"known"``: the material passed to :class:`Stream` is used as
            it is (no extra work); ``"estimate"`` (full mode): its scene parameters
            are estimated from the frames, RON's alternation (seed 4.1.10,
            Algorithm 2) spread over the stream (:mod:`gpps.pipeline.stream_material`);
            the material passed is the starting guess and fixes the model.
        estimate: the parameters to estimate (names of
            :data:`gpps.names.LOBE_PARAMETERS` for the model); empty: all of them.
        refine_every: once the search has settled, one batch of candidates is
            scored every this many frames (k), which follows a drifting material.
        material_samples: pixels of the material sample (RON's 2000; half of them each scored
            frame's brightest pixel per tile, half fixed random mask pixels).
        material_candidates: most candidates per launch (one launch a scoring
            frame): the first frame scores a grid of ``floor(K^(1/d))`` points per
            parameter (5 x 5 for K = 25, d = 2), later frames ``3^d + 1`` (a
            stencil and its quadratic model's minimiser).  At least ``3^d + 1``.
        material_starts: starts per sample pixel of the material fit (RON's).
        material_trim: fraction of the largest squared sample residuals left out
            of a candidate's energy (RON's).
        material_tol: the search settles when its steps in every log parameter
            are below this (1e-3: 0.1 %, the tolerance of RON's later material
            fits, ``gpps.flows.ron._XATOL``).  The normals follow the material
            closely: 64^2 Cook-Torrance bumps, 24 frames, a settled estimate 0.3 %
            off the truth gave 0.056 deg MAEN where the offline reconstruct, 0.03 %
            off, gave 0.023; with 1e-3 the stream's estimate is within 0.01 %.
        dgmc: full mode, first frame: DGMC start normals (4.16-4.18) on the
            highlight pixels (:class:`gpps.pipeline.dgmc.DeviceDGMC`), one warm
            solve from them, the lower residual kept per pixel.
        refresh_rows: a rolling cold re-solve: on every warm frame the mask rows
            ``i = frame (mod refresh_rows)`` are solved again cold (``redo_starts``
            starts of ``redo_iterations``) and keep that solution where its
            residual is lower, so each pixel gets a multi-start solve every
            ``refresh_rows`` frames.  It repairs pixels that a warm start carried
            into another local minimum, which the jump test does not see (their
            residual grows slowly): on a moving object, and after the estimated
            material moved.  Moving 128^2 Cook-Torrance bumps on the CPU, material
            known: 0.16 deg at the cold first frame, 0.4-0.6 deg later without it.
            Cost: at most ``redo_starts * redo_iterations / (3 * refresh_rows)``
            warm solves a frame (the cold solves stop early on convergence).
            0 (default): off (``retry_rows`` re-solves the misfits alone).
        retry_rows: the rolling cold re-solve of misfits: on every warm frame the
            pixels of the mask rows ``i = frame (mod retry_rows)`` whose residual
            exceeds the jump test's level (``jump_factor`` times the running mean
            residual, and 0.1 % of the mean grey value) are solved again cold and
            keep that solution where its residual is lower (frames where
            ``refresh_rows`` or the full mode's sweep re-solve whole rows do not
            run it).  The jump test re-solves a pixel only when its residual
            *rises*; a pixel that a warm start carried into a wrong basin and that
            stays there (a moving object's highlights, a frame solved under a
            search's early material) keeps a high residual and is never re-solved
            by it.  Moving 64^2 Cook-Torrance bumps (a pixel a frame, CPU), known
            material: 0.028 deg MAEN over the last 12 of 36 frames without it,
            0.022 with it; full mode, where the search's early materials leave
            misfits, 0.15 without it and 0.044 with it (the last 12 of 72 frames).
            Cost: the misfits' cold solves, a ``retry_rows``-th of them a frame;
            a misfit whose cold solve found nothing better is retried again only
            once its residual exceeds :data:`gpps.kernels.stream.RETRY_FLOOR_FACTOR`
            times the one it kept then (a static scene's misfits are not solved
            again every ``retry_rows`` frames for nothing).
            0, or ``check=False`` (no level to compare with): off.
        sweep_rows: full mode: after each change of the estimated material the
            rolling cold re-solve runs with period ``sweep_rows`` (whatever
            ``refresh_rows`` is) until ``sweep_rows`` frames have passed without a
            change, so every pixel gets one multi-start solve with the new
            material: a warm start keeps the basin the old material put a normal
            in (64^2 Cook-Torrance bumps solved first with the first frame's grid
            estimate stayed near 3 deg MAEN without it, offline 1.3 deg).  An
            under-determined pixel (fewer than 3 usable observations, e.g. one
            clipped) takes the sweep's solve: its residual cannot rank the two.
            0: off.
        neighbour_radius: pixels with fewer than 3 usable observations (a clipped
            highlight leaves many with 2) cannot fix normal and albedo together.
            The cold solves (the first frame, the re-solves of jumps, the retries
            and the sweeps) give them the albedo of the nearest well-determined
            pixels (:attr:`gpps.SolverConfig.neighbour_radius`, read from the
            whole mask); the warm frames hold the albedo such a pixel has
            (:attr:`gpps.SolverConfig.warm_albedo`), one read where the neighbour
            pass searches rings of pixels (at 1024^2 the pass cost 96 ms a frame).
            Without either a warm solve moves the normal along its curve of exact
            fits: moving 64^2 Cook-Torrance bumps (a pixel a frame, CPU), material
            known, 2.2 deg MAEN on those pixels.  The held albedo is the pixel's,
            not the moving surface point's: on a *textured* moving object it lags
            (the same scene with a smooth random texture: 0.45 deg MAEN over the
            last frames, 0.28 with the pass in every warm frame, 0.67 with
            neither).  None: the solver's default (32 pixels); 0: off (free
            albedo, as above).
    """

    solver: StreamSolver = "lm"
    iterations: int = 3
    first_starts: int = 10
    first_iterations: int = 50
    integrate: bool = True
    integration_iterations: int = 1
    first_tol: float = 1e-4
    reference_depth: float | None = None
    graph: GraphName = "auto"
    capture_after: int = 2
    output: Output = "device"
    ring: int = 2
    saturation: float | None = 1.0
    check: bool = True
    min_lit_fraction: float = 0.05
    max_saturated_fraction: float = 0.5
    max_noise_ratio: float = 0.1
    noise_factor: float = 3.0
    residual_factor: float = 4.0
    jump_factor: float = 8.0
    redo_starts: int = 10
    redo_iterations: int = 50
    material: MaterialMode = "known"
    estimate: tuple[str, ...] = ()
    refine_every: int = 8
    material_samples: int = 2000
    material_candidates: int = 25
    material_starts: int = 4
    material_trim: float = 0.02
    material_tol: float = 1e-3
    dgmc: bool = True
    refresh_rows: int = 0
    retry_rows: int = 8
    sweep_rows: int = 8
    neighbour_radius: int | None = None

    def __post_init__(self):
        check_choices(self)
        check_bool("integrate", self.integrate)
        check_number("iterations", self.iterations, lo=1, integer=True)
        check_number("first_starts", self.first_starts, lo=1, integer=True)
        check_number("first_iterations", self.first_iterations, lo=1, integer=True)
        check_number("integration_iterations", self.integration_iterations, lo=0, integer=True)
        check_number("first_tol", self.first_tol, lo=0.0, hi=1.0, lo_open=True)
        check_number("capture_after", self.capture_after, lo=1, integer=True)
        check_number("ring", self.ring, lo=1, hi=64, integer=True)
        if self.reference_depth is not None:
            check_number("reference_depth", self.reference_depth, lo=0.0, lo_open=True)
        if self.saturation is not None:
            check_number("saturation", self.saturation, lo=0.0, hi=1.0, lo_open=True)
        check_bool("check", self.check)
        check_number("min_lit_fraction", self.min_lit_fraction, lo=0.0, hi=1.0)
        check_number("max_saturated_fraction", self.max_saturated_fraction, lo=0.0, hi=1.0)
        check_number("max_noise_ratio", self.max_noise_ratio, lo=0.0, lo_open=True)
        for name in ("noise_factor", "residual_factor", "jump_factor"):
            check_number(name, getattr(self, name), lo=1.0)
        check_number("redo_starts", self.redo_starts, lo=1, integer=True)
        check_number("redo_iterations", self.redo_iterations, lo=1, integer=True)
        if not isinstance(self.estimate, (tuple, list)) or not all(isinstance(e, str) for e in self.estimate):
            raise TypeError(f"estimate: expected a tuple of parameter names, got {self.estimate!r}")
        object.__setattr__(self, "estimate", tuple(self.estimate))
        bad = [e for e in self.estimate if e not in LOBE_RANGES]
        if bad:
            raise ValueError(f"estimate: expected names from {sorted(LOBE_RANGES)}, got {bad}")
        if self.estimate and self.material == "known":
            raise ValueError(f"estimate: expected no names with material='known', got {self.estimate}")
        check_number("refine_every", self.refine_every, lo=1, integer=True)
        check_number("material_samples", self.material_samples, lo=16, integer=True)
        check_number("material_candidates", self.material_candidates, lo=4, hi=81, integer=True)
        check_number("material_starts", self.material_starts, lo=1, integer=True)
        check_number("material_trim", self.material_trim, lo=0.0, hi=0.5)
        check_number("material_tol", self.material_tol, lo=0.0, lo_open=True)
        check_bool("dgmc", self.dgmc)
        check_number("refresh_rows", self.refresh_rows, lo=0, integer=True)
        check_number("retry_rows", self.retry_rows, lo=0, integer=True)
        check_number("sweep_rows", self.sweep_rows, lo=0, integer=True)
        if self.neighbour_radius is not None:
            check_number("neighbour_radius", self.neighbour_radius, lo=0, hi=256, integer=True)


@dataclass
class StreamResult:
    """One frame's output.

    Attributes:
        index: position of the frame in the stream (0-based).
        normals: (H, W, 3) unit normals (gpps frame), 0 outside the mask.
        albedo: (H, W, 3) RGB albedo.
        depth: (H, W) depth (> 0 inside the mask for perspective / point
            lights; see :class:`StreamConfig.reference_depth`), None without integration.
        error: None, or why the frame was rejected (then the arrays are None).
        seconds: host wall time of :meth:`Stream.process` for this frame.
        checks: the frame's sanity statistics (``lit_fraction``,
            ``saturated_fraction``, ``noise_ratio``, ``residual`` (mean over the
            pixels the solve determined), ``determined_fraction`` (of the mask's
            pixels, with 3 or more valid observations), ``redone`` pixels), when
            the check ran.
        material: the stream's material after this frame: the known one, or in
            full mode the current estimate (what the next frame is solved with).
    """

    index: int
    normals: Any = None
    albedo: Any = None
    depth: Any = None
    error: str | None = None
    seconds: float = 0.0
    checks: dict | None = None
    material: Material | None = None

    @property
    def ok(self) -> bool:
        return self.error is None

    def numpy(self) -> "StreamResult":
        """A copy with numpy arrays owned by the caller (never views of the stream's buffers)."""
        return StreamResult(self.index, _copy(self.normals), _copy(self.albedo), _copy(self.depth), self.error,
                            self.seconds, None if self.checks is None else dict(self.checks), self.material)


def _copy(a):
    """A numpy copy of a Warp or numpy array (Warp's ``numpy()`` on the CPU is a view of the live buffer)."""
    if a is None:
        return None
    if hasattr(a, "numpy") and not isinstance(a, np.ndarray):
        a = a.numpy()
    return np.array(a, copy=True)


class _BadFrame(Exception):
    """A frame that failed the sanity check (internal: becomes an error result)."""


class Stream(Stage):
    """Photometric stereo on a stream of N-image frames, buffers allocated once.

    Args:
        shape: (H, W) frame size.
        camera: :class:`Orthographic` or :class:`Perspective`.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N, one per image of a frame).
        material: :class:`Material` (reflectance model and parameters).
        mask: (H, W) bool pixels to reconstruct (None: all).
        config: :class:`StreamConfig`.
        device: Warp device (None: CUDA if present).

    A stage (:mod:`gpps.pipeline.stage`): ``run(frame)`` reconstructs one frame (:meth:`upload`,
    :meth:`step`, :meth:`fetch`); :meth:`iterate` goes over any iterable of frames (it prefetches the
    next frame's upload while the current one computes).
    Each frame is an (N, H, W) or (N, H, W, 3) uint8 / uint16 / float32 array
    (numpy, or a Warp array already on the device); float32 is taken as
    0..1, integers as 0..full scale.
    """

    def __init__(self, shape, camera, lights, material: Material, mask=None, config: StreamConfig | None = None,
                 device=None):
        wp = warp()

        self._ks = ks
        self.config = config if config is not None else StreamConfig()
        if not isinstance(self.config, StreamConfig):
            raise TypeError(f"config: expected StreamConfig, got {type(self.config).__name__}")
        h, w = check_shape("shape", shape, "HW", lo=2)  # (16.5 is a TypeError, not 16)
        if not isinstance(lights, (DirectionalLights, PointLights)):
            raise TypeError(f"lights: expected DirectionalLights or PointLights, got {type(lights).__name__}")
        if not isinstance(camera, (Orthographic, Perspective)):
            raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
        if not isinstance(material, Material):
            raise TypeError(f"material: expected gpps.material.Material, got {type(material).__name__}")
        cfg = self.config
        self.point = isinstance(lights, PointLights)
        if self.point and (cfg.reference_depth is None or not cfg.integrate):
            raise ValueError("config: point lights need reference_depth (metric depth for 1/r^2) and integrate=True")
        self.device = resolve_device(device)
        self.is_cuda = self.device.startswith("cuda")
        n = len(lights)
        check_model_images((material.brdf,), n)
        self.n, self.shape = n, (h, w)
        self.mask = np.ones((h, w), bool) if mask is None else as_mask("mask", mask, (h, w))
        self.camera, self.lights, self.material = camera, lights, material
        # unit-intensity lights for the solver; intensities go into the conversion gain
        inten = np.asarray(lights.intensities, np.float64).reshape(n, 3)
        if np.any(inten <= 0):
            raise ValueError("lights: expected intensities > 0 for every light and channel")
        self._inten = inten
        unit = DirectionalLights(lights.directions) if not self.point else PointLights(
            lights.positions, axes=getattr(lights, "axes", None), mu=getattr(lights, "mu", None))
        radius = cfg.neighbour_radius
        if radius is None:
            radius = SolverConfig().neighbour_radius
        # warm frames hold an under-determined pixel's albedo (warm_albedo: one read, where the neighbour pass
        # searches rings of pixels, 96 ms a frame at 1024^2); the cold solves (first frame, re-solves of jumps,
        # retries and sweeps) run the neighbour pass, which gives it
        self._warm_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.iterations, starts=1, warm_start=True,
                                      early_exit=False, neighbour_radius=0, warm_albedo=bool(radius))
        self._cold_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.first_iterations, starts=cfg.first_starts,
                                      neighbour_radius=int(radius))
        self._redo_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.redo_iterations, starts=cfg.redo_starts,
                                      neighbour_radius=int(radius))
        self.solver = PixelSolver((n, h, w), camera, unit, material, self._cold_cfg, device=self.device)
        d = self.device
        self._gain = {}
        self._raw = {}  # (dtype, channels) -> [device buffers] (two slots)
        self._staging = {}
        self._slot = 0
        self._pending = None
        self._graphs: dict = {}
        self._count = wp.zeros(2, dtype=wp.int32, device=d)
        self.index = 0
        self._started = self._done = None  # the frame between upload, step and fetch
        self.frames_done = 0
        self._warm_frames = 0
        self.solver.mask.assign(self.mask.astype(np.uint8))
        self.solver.valid.fill_(1)
        dep0 = float(cfg.reference_depth) if cfg.reference_depth is not None else 1.0
        self.solver.depth.fill_(dep0)
        self.depth = wp.zeros((h, w), dtype=wp.float32, device=d)
        self.integrator = None
        if cfg.integrate:
            self.integrator = StreamIntegrator(self.mask, camera, device=_taichi.taichi_device(self.device))
            if self.is_cuda:
                if importlib.util.find_spec("torch") is None:
                    raise ImportError("the stream's integration on CUDA needs PyTorch for zero-copy views of the "
                                      "Warp buffers: pip install 'gpps[cuda]' (or StreamConfig(integrate=False))")
                self._nrm_view = wp.to_torch(self.solver.normals)
                self._dep_view = wp.to_torch(self.depth)
            else:
                self._nrm_view = self.solver.normals.numpy()
                self._dep_view = self.depth.numpy()
        self._ring = [
            (wp.zeros((h, w), dtype=wp.vec3, device=d), wp.zeros((h, w), dtype=wp.vec3, device=d),
             wp.zeros((h, w), dtype=wp.float32, device=d))
            for _ in range(cfg.ring if cfg.output == "device" else 0)
        ]
        self._upload_stream = wp.Stream(d) if self.is_cuda else None
        self.stats = {"frames": 0, "errors": 0, "seconds": 0.0, "redone_pixels": 0}
        # sanity check: per-frame sums, the running residual level (read by mark_jumps on the device),
        # the pixels to re-solve cold, and the last accepted frame's normals (restored after a bad frame)
        self._fstats = wp.zeros((ks.STAT_SLOTS, ks.N_STATS), dtype=wp.float32, device=d)
        self._inten_dev = wp.array(inten.astype(np.float32), dtype=wp.float32, device=d)
        self._level = wp.zeros(1, dtype=wp.float32, device=d)
        self._redo = wp.zeros((h, w), dtype=wp.uint8, device=d)
        self._kept = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self._kept_albedo = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self._kept_res = wp.zeros((h, w), dtype=wp.float32, device=d)
        self._mask_n = float(self.mask.sum())
        self._levels: dict | None = None  # running lit share, saturated share, noise ratio, residual
        self._reset_residual = False  # the material changed: the next accepted frame sets the residual level
        self._cmds: dict = {}
        # full mode: the material search (None with a known material: nothing of it runs)
        self.estimator = None
        if cfg.material == "estimate":
            self.estimator = StreamMaterial(
                self.solver, self.mask, material, lobe_names(material.brdf, cfg.estimate),
                samples=cfg.material_samples, candidates=cfg.material_candidates, starts=cfg.material_starts,
                iterations=cfg.first_iterations, trim=cfg.material_trim, tol=cfg.material_tol,
                refine_every=cfg.refine_every, point=self.point, device=d)
            self._dgmc_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.first_iterations, starts=1,
                                          warm_start=True, neighbour_radius=0)
            self.stats.update({"material_batches": 0, "material_changes": 0, "dgmc_pixels": 0})
        self._refresh = int(cfg.refresh_rows)  # the period of the rolling cold re-solve on this frame (0: none)
        self._sweep_left = 0  # full mode: frames the re-solve still runs with period sweep_rows
        self._sweeping = False  # this frame's re-solve is the sweep's (under-determined pixels take it)
        self._retry = int(cfg.retry_rows) if cfg.check else 0  # the misfit retries' period (0: none)
        if cfg.refresh_rows or self._retry or (self.estimator is not None and cfg.sweep_rows):
            # the rolling cold re-solve: this frame's rows, its phase, the warm solution it competes with
            self._refresh_mask = wp.zeros((h, w), dtype=wp.uint8, device=d)
            self._phase = wp.zeros(1, dtype=wp.int32, device=d)
            self._saved = (wp.zeros((h, w), dtype=wp.vec3, device=d), wp.zeros((h, w), dtype=wp.vec3, device=d),
                           wp.zeros((h, w), dtype=wp.float32, device=d), wp.zeros((h, w), dtype=wp.int32, device=d))
            # the residual each pixel kept after its last cold re-solve (0: none since the material or a rejected
            # frame last changed what residuals mean): a misfit is retried when it rises above it
            self._floor = wp.zeros((h, w), dtype=wp.float32, device=d)

    # ------------------------------------------------------------------ frames

    def _check(self, frame):
        """(dtype, channels, host array or device array) of a valid frame, or raise ValueError."""
        wp = warp()
        n, (h, w) = self.n, self.shape
        if isinstance(frame, wp.array):
            dt = np.dtype(wp.dtype_to_numpy(frame.dtype)) if frame.dtype in (wp.uint8, wp.uint16, wp.float32) else None
            shp = tuple(frame.shape)
        else:
            frame = np.asarray(frame)
            dt = frame.dtype
            shp = frame.shape
        if dt not in _DTYPES:
            raise ValueError(f"frame: expected dtype uint8, uint16 or float32 (integers by full scale, floats "
                             f"with 1 = full scale), got {dt}")
        if shp == (n, h, w):
            c = 1
        elif shp == (n, h, w, 3):
            c = 3
        elif shp == (n, h, w, 1):
            c = 1
        else:
            raise ValueError(f"frame: expected shape ({n}, {h}, {w}) or ({n}, {h}, {w}, 3), got {shp}")
        if dt == np.float32 and not isinstance(frame, wp.array):
            if not np.isfinite(frame).all():
                raise ValueError("frame: expected finite values, got NaN or inf")
            if (frame < 0).any():
                raise ValueError("frame: expected values >= 0, got negative values")
        return dt, c, frame

    def _buffers(self, dt, c):
        wp = warp()
        key = (dt, c)
        if key not in self._raw:
            wdt = {np.dtype(np.uint8): wp.uint8, np.dtype(np.uint16): wp.uint16, np.dtype(np.float32): wp.float32}[dt]
            shp = (self.n, *self.shape, c)
            self._raw[key] = [wp.zeros(shp, dtype=wdt, device=self.device) for _ in range(2)]
            if self.is_cuda:
                try:  # page-locked host staging: asynchronous copies on the upload stream
                    self._staging[key] = [wp.zeros(shp, dtype=wdt, device="cpu", pinned=True) for _ in range(2)]
                except Exception:  # a Warp build without a CPU device: synchronous uploads
                    self._staging[key] = None
            g = 1.0 / (_DTYPES[dt] * self._inten)
            self._gain[key] = wp.array(g.astype(np.float32), dtype=wp.float32, device=self.device)
        return self._raw[key]

    def _upload(self, frame):
        """Start the upload of a checked frame into the next slot; returns (key, slot, event)."""
        wp = warp()
        dt, c, arr = self._check(frame)
        raw = self._buffers(dt, c)
        slot = self._slot
        self._slot ^= 1
        key = (dt, c)
        if isinstance(arr, wp.array):
            if dt == np.float32:
                self._count.zero_()
                wp.launch(self._ks.count_invalid, dim=(self.n, *self.shape),
                          inputs=[arr.reshape((self.n, *self.shape, c))], outputs=[self._count], device=self.device)
                bad = self._count.numpy()
                if int(bad[0]) > 0:
                    raise ValueError("frame: expected finite values, got NaN or inf")
                if int(bad[1]) > 0:
                    raise ValueError("frame: expected values >= 0, got negative values")
            wp.copy(raw[slot], arr.reshape((self.n, *self.shape, c)))
            return key, slot, None
        host = arr.reshape((self.n, *self.shape, c))
        if self.is_cuda and self._staging.get(key) is not None:
            st = self._staging[key][slot]
            np.copyto(st.numpy(), host)
            wp.copy(raw[slot], st, stream=self._upload_stream)
            ev = self._upload_stream.record_event()
            return key, slot, ev
        raw[slot].assign(host)
        return key, slot, None

    # ------------------------------------------------------------------ compute

    def _launch_solve(self, key, slot, warm: bool, score: bool = False):
        """Convert, check and solve one frame on the device (graph-capturable: no host sync); with ``score``
        (full mode) also gather the material sample from it and score the search's batch."""
        self._launch_convert(key, slot)
        self._launch_fit(warm)
        if score:
            self.estimator.upload()
            self.estimator.step()

    def _launch_convert(self, key, slot):
        """The raw frame to the solver's images, and the frame statistics (graph-capturable)."""
        wp = warp()
        ks = self._ks
        raw = self._raw[key][slot]
        kern = {np.dtype(np.uint8): ks.convert_uint8, np.dtype(np.uint16): ks.convert_uint16,
                np.dtype(np.float32): ks.convert_float32}[key[0]]
        sat = 0.0 if self.config.saturation is None else float(self.config.saturation) * _DTYPES[key[0]]
        wp.launch(kern, dim=(self.n, *self.shape), inputs=[raw, self._gain[key], sat],
                  outputs=[self.solver.images, self.solver.valid], device=self.device)
        if self.config.check:
            self._fstats.zero_()
            self._cmd("stats", key).launch()

    def _launch_fit(self, warm: bool):
        """The per-pixel solve of the converted frame, the cold re-solve of jumped pixels and the residual sum
        (graph-capturable)."""
        check = self.config.check
        self.solver.step()
        if check:
            if warm:  # pixels whose warm start failed (scene change, bad start): cold, multi-start, in this frame
                self._cmd("jumps").launch()
                self.solver.step_subset(self._redo, self._redo_cfg)
        if warm and (self._refresh or self._retry):
            self._launch_refresh()
        if check:
            self._cmd("residual").launch()

    def _launch_refresh(self):
        """This frame's rows of the rolling cold re-solve, the lower residual kept per pixel; the phase advances
        on the device (graph-capturable).  Every pixel of the rows with period ``refresh_rows`` (or the full
        mode's sweep); otherwise only the rows' misfits (residual above the jump test's level and above
        :data:`gpps.kernels.stream.RETRY_FLOOR_FACTOR` times the residual the pixel kept after its last cold
        re-solve), period ``retry_rows``."""
        wp = warp()
        s, d = self.solver, self.device
        saved = self._saved
        period = self._refresh or self._retry
        misfits = int(not self._refresh)
        wp.launch(self._ks.refresh_rows, dim=self.shape,
                  inputs=[s.mask, self._phase, period, s.residual, self._level, misfits, self._floor],
                  outputs=[self._refresh_mask], device=d)
        wp.launch(self._ks.save_rows, dim=self.shape,
                  inputs=[self._refresh_mask, s.normals, s.albedo, s.residual, s.flags], outputs=list(saved), device=d)
        s.step_subset(self._refresh_mask, self._redo_cfg)
        wp.launch(self._ks.keep_better, dim=self.shape,
                  inputs=[self._refresh_mask, *saved, int(FLAG_FEW_OBSERVATIONS), int(self._sweeping)],
                  outputs=[s.normals, s.albedo, s.residual, s.flags, self._floor], device=d)
        wp.launch(self._ks.advance_phase, dim=1, inputs=[self._phase, period, 1], device=d)

    def _cmd(self, name, key=None):
        """The recorded launch of a check kernel (arguments packed once; the buffers never change)."""
        wp = warp()
        ks = self._ks
        cmd = self._cmds.get((name, key))
        if cmd is None:
            if name == "stats":
                args = dict(kernel=ks.frame_stats, dim=(self.shape[0], -(-self.shape[1] // ks.STAT_CHUNK)),
                            inputs=[self.solver.images, self.solver.mask, self._inten_dev, 1e-3,
                                    1.0 if key[0] == np.float32 else 0.999])
            elif name == "jumps":
                args = dict(kernel=ks.mark_jumps, dim=self.shape,
                            inputs=[self.solver.residual, self._kept_res, self.solver.mask, self._level,
                                    float(self.config.jump_factor)], outputs=[self._redo])
            else:
                args = dict(kernel=ks.residual_sum, dim=(self.shape[0], -(-self.shape[1] // ks.STAT_CHUNK)),
                            inputs=[self.solver.residual, self.solver.mask, self.solver.flags])
            args["outputs"] = [*args.get("outputs", []), self._fstats]
            cmd = wp.launch(**args, device=self.device, record_cmd=True)
            self._cmds[(name, key)] = cmd
        return cmd

    def _judge(self, cold: bool) -> dict:
        """The frame's statistics (one small read-back); raises :class:`_BadFrame` when it fails the check."""
        ks = self._ks
        s = self._fstats.numpy().astype(np.float64).sum(axis=0)  # add up the slots
        nobs = self.n * self._mask_n
        grey = s[ks.STAT_GREY] / max(nobs, 1.0)
        got = {
            "lit_fraction": s[ks.STAT_LIT] / max(nobs, 1.0),
            "saturated_fraction": s[ks.STAT_SATURATED] / max(nobs, 1.0),
            "noise_ratio": s[ks.STAT_HF] / (6.0 * s[ks.STAT_HF_GREY]) if s[ks.STAT_HF_GREY] > 0 else 0.0,
            # (per determined pixel: an under-determined one's residual is no evidence of a misfit)
            "residual": s[ks.STAT_RESIDUAL] / max(s[ks.STAT_DETERMINED], 1.0),
            "determined_fraction": s[ks.STAT_DETERMINED] / max(self._mask_n, 1.0),
            "grey": grey,
            "redone": int(s[ks.STAT_REDONE]),
        }
        c, lv = self.config, self._levels
        lit, sat, hf, res = got["lit_fraction"], got["saturated_fraction"], got["noise_ratio"], got["residual"]
        why = None
        if lit < c.min_lit_fraction or (lv is not None and lit < 0.5 * lv["lit_fraction"]):
            why = f"only {100 * lit:.1f}% of the observations are lit (a dark frame, or lights that did not fire)"
        elif sat > c.max_saturated_fraction or (lv is not None and sat > lv["saturated_fraction"] + 0.25):
            # (before the determined pixels: saturated observations are dropped from the fit, so an over-exposed
            # frame also leaves no pixel determined, and the exposure is the cause to report)
            why = f"{100 * sat:.1f}% of the observations are saturated (over-exposed)"
        elif got["determined_fraction"] == 0.0:
            why = "no pixel has 3 lit observations (lights that did not fire, or a frame of shadows)"
        elif hf > c.max_noise_ratio or (lv is not None and hf > max(c.noise_factor * lv["noise_ratio"], 0.05)):
            why = f"the frame is mostly noise (high-frequency ratio {hf:.3f})"
        elif res > (0.5 if lv is None else 0.02) * grey and (lv is None or res > c.residual_factor * lv["residual"]):
            why = f"the model does not fit the frame (mean residual {res:.3g}, {100 * res / max(grey, 1e-30):.0f}% of the signal)"
        if why is not None:
            raise _BadFrame(f"frame: rejected by the sanity check: {why}")
        return got

    def _accept(self, got: dict) -> None:
        """Fold an accepted frame's statistics into the running levels (exponential, 1/10)."""
        if self._levels is None:
            self._levels = {k: got[k] for k in ("lit_fraction", "saturated_fraction", "noise_ratio", "residual", "grey")}
        else:
            for k in self._levels:
                self._levels[k] = 0.9 * self._levels[k] + 0.1 * got[k]
            if self._reset_residual:
                self._levels["residual"] = got["residual"]
        self._reset_residual = False
        # re-solve a warm pixel cold when its residual jumps above jump_factor x its own last residual and
        # x the running mean residual (and 0.1 % of the mean signal: noiseless renders fit to ~1e-6, where
        # quantisation alone would trip it)
        lv = self._levels
        thr = max(self.config.jump_factor * lv["residual"], 1e-3 * lv["grey"])
        self._level.assign(np.array([thr], np.float32))
        self.stats["redone_pixels"] += got["redone"]

    def _compute(self, key, slot, ev):
        wp = warp()
        cfg = self.config
        cold = self.frames_done == 0
        est = self.estimator
        score = False
        if ev is not None:
            wp.get_stream(self.device).wait_event(ev)
        if cold:
            self.solver.set_config(self._cold_cfg)
            if est is None:
                self._launch_solve(key, slot, warm=False)
            else:
                self._first_full(key, slot)
        else:
            if self.solver.config is not self._warm_cfg:
                self.solver.set_config(self._warm_cfg)
            if est is not None:
                score = est.scoring()
                self._sweeping = self._sweep_left > 0  # (its re-solve gives the under-determined pixels a cold start)
                self._refresh = cfg.sweep_rows if self._sweeping else cfg.refresh_rows
                self._sweep_left = max(self._sweep_left - 1, 0)
            use_graph = self.is_cuda and cfg.graph == "auto" and self._warm_frames >= cfg.capture_after
            if use_graph:
                gkey = (key, slot) if est is None else (key, slot, score, self._refresh, self._sweeping)
                g = self._graphs.get(gkey)
                if g is None:
                    wp.capture_begin(device=self.device)
                    try:
                        self._launch_solve(key, slot, warm=True, score=score)
                    finally:
                        g = wp.capture_end(device=self.device)
                    self._graphs[gkey] = g
                wp.capture_launch(g)
            else:
                self._launch_solve(key, slot, warm=True, score=score)
            self._warm_frames += 1
        checks = None
        if cfg.check:
            try:
                checks = self._judge(cold)
            except _BadFrame:
                if not cold:  # the next frame warm-starts from the last accepted one
                    wp.copy(self.solver.normals, self._kept)
                    wp.copy(self.solver.albedo, self._kept_albedo)
                    period = self._refresh or self._retry
                    if period:  # and re-solves the rows this one would have had (with no floor: the rejected
                        # frame's re-solves kept residuals of data that failed the check)
                        wp.launch(self._ks.advance_phase, dim=1, inputs=[self._phase, period, period - 1],
                                  device=self.device)
                        self._floor.zero_()
                elif est is not None:  # the first frame's grid scores are not trusted: start the search over
                    est.reset()
                    self._set_material(est.material)
                raise
        if self.integrator is not None:
            if self.is_cuda:
                wp.synchronize_device(self.device)
            ref = cfg.reference_depth
            if cold:
                self.integrator.reset()
                self.integrator.step(self._nrm_view, self._dep_view, tol=cfg.first_tol, reference=ref)
            else:
                self.integrator.step(self._nrm_view, self._dep_view, iterations=cfg.integration_iterations,
                                          reference=ref)
            if self.is_cuda:
                _taichi.ti.sync()
            if self.point:
                # the next frame's per-pixel light directions and fall-off come from this depth
                wp.copy(self.solver.depth, self.depth)
        if cfg.check:
            wp.copy(self._kept, self.solver.normals)
            wp.copy(self._kept_albedo, self.solver.albedo)
            wp.copy(self._kept_res, self.solver.residual)
            self._accept(checks)
        if score:  # after the frame's synchronisation: one step of the material search (step 4)
            self.stats["material_batches"] += 1
            new = est.fetch()
            if new is not None:
                self._set_material(new)
        self.frames_done += 1
        return checks

    def _set_material(self, material: Material) -> None:
        """Solve the next frames with ``material``: the solver re-records its launches, the captured graphs
        (which baked the old material's struct) are dropped and captured again after ``capture_after`` eager
        frames (a search that moves every frame never pays for a capture it would use once)."""
        if material == self.material:
            return
        self.material = material
        self.solver.set_material(material)
        self._graphs.clear()
        self._warm_frames = 0
        self.stats["material_changes"] += 1
        self._sweep_left = self.config.sweep_rows
        # residuals under the old material are no level for the new one's: the next accepted frame sets it
        # again (kept, it held the jump test's and the misfit retry's threshold above the misfits a search's
        # early, wrong materials left: 64^2 moving bumps stayed at 0.3 deg against 0.03 with a known material)
        self._reset_residual = True
        if self.__dict__.get("_floor") is not None:  # (the retries' floors were residuals under the old material)
            self._floor.zero_()

    def _first_full(self, key, slot) -> None:
        """The first frame in full mode (it is a cold one already: its extra waits do not touch later frames).

        1. convert; score the search's grid on the frame's sample (one launch) and wait for it: the frame is
           then solved with the grid's best material, not the guess;
        2. the cold multi-start solve (its starts include the brightest observation's half vector,
           :func:`gpps.kernels.solve_common.start_normal`);
        3. with ``config.dgmc``: DGMC start normals (4.16-4.18) for the highlight pixels, one warm solve from
           them, the lower residual kept (:meth:`_dgmc_starts`).
        """
        est = self.estimator
        self._launch_convert(key, slot)
        est.upload()
        est.step()
        self.stats["material_batches"] += 1
        new = est.fetch()
        if new is not None:
            self._set_material(new)
        self._launch_fit(warm=False)
        if self.config.dgmc:
            self.stats["dgmc_pixels"] += self._dgmc_starts()

    def _dgmc_starts(self) -> int:
        """DGMC on the first frame (seed 4.1.9, 4.16-4.18, on the device: :class:`gpps.pipeline.dgmc.DeviceDGMC`).

        The highlight test is the ``"lambertian"`` rule; with 3 lights it tests one observation per pixel
        against the mask's reference albedo (:func:`gpps.host.dgmc.detect_highlights`), so it applies to
        triples.  Each highlight pixel with a reachable boundary starts from the solved normal of the boundary
        pixel whose curvatures match (4.17-4.18, the seed's ``"boundary"`` sources: the cold solve's normals
        are the solved front); one warm solve from it, kept where its residual is lower
        (:func:`gpps.host.merge.ranks_better`).  Host round trips: this frame only.

        Returns:
            the number of pixels whose DGMC-started solve won.
        """
        s = self.solver
        m = self.mask
        names = ("normals", "albedo", "residual", "flags", "iterations")
        cold = s.fetch(names)
        nrm = cold["normals"].astype(np.float64)
        ok = m & (np.abs(np.linalg.norm(nrm, axis=-1) - 1.0) < 1e-3)
        nrm[~ok] = (0.0, 0.0, 1.0)
        if not (m & ok).any():
            return 0
        pts = None
        if self.point:
            pts = self.camera.backproject(np.full(self.shape, float(self.config.reference_depth), np.float32))
        with DeviceDGMC(s.shape, config=DGMCConfig(start="boundary"), device=self.device) as stage:
            stage.upload(s.images, m & ok, nrm, lights=s.lights, points=pts)
            stage.step()
            dg = stage.fetch()
        hl = dg.highlight & ok & (dg.source[..., 0] >= 0)
        if not hl.any():
            return 0
        s.normals.assign(np.where(hl[..., None], dg.normals, cold["normals"]).astype(np.float32))
        self._redo.assign(hl.astype(np.uint8))
        s.step_subset(self._redo, self._dgmc_cfg)
        warm = s.fetch(names)
        better = hl & ranks_better(warm["residual"], warm["flags"], cold["residual"])
        for k in names[:4]:
            sel = better.reshape(better.shape + (1,) * (cold[k].ndim - 2))
            getattr(s, k).assign(np.where(sel, warm[k], cold[k]))
        return int(better.sum())

    def _result(self, index, t0, checks=None):
        wp = warp()
        cfg = self.config
        dep = self.depth if self.integrator is not None else None
        if cfg.output == "numpy":  # copies: on the CPU Warp's numpy() is a view of the live buffer
            res = StreamResult(index, _copy(self.solver.normals), _copy(self.solver.albedo), _copy(dep))
        else:
            nr, ab, dp = self._ring[index % len(self._ring)]
            wp.copy(nr, self.solver.normals)
            wp.copy(ab, self.solver.albedo)
            if dep is not None:
                wp.copy(dp, dep)
            res = StreamResult(index, nr, ab, dp if dep is not None else None)
        res.checks = checks
        res.material = self.material
        res.seconds = time.perf_counter() - t0
        self.stats["frames"] += 1
        self.stats["seconds"] += res.seconds
        return res

    def close(self) -> None:
        """Release the device state: the solver's buffers (back to the pool), the integrator's fields, the
        material estimator's, the captured graphs; a closed stream refuses frames (ValueError).  Also on
        leaving a ``with`` block.  Closing twice does nothing."""
        if self.__dict__.get("_closed", False):
            return
        self._closed = True
        self._graphs.clear()
        for name in ("estimator", "integrator", "solver"):
            stage = getattr(self, name, None)
            if stage is not None:
                stage.close()
        self._release_buffers()

    def _start(self, frame):
        """Number the frame and start its upload: ``(index, t0, (key, slot, event) or None, error or None)``."""
        self._check_open()  # (raised: not a bad frame of an open stream)
        t0 = time.perf_counter()
        idx = self.index
        self.index += 1
        try:
            return idx, t0, self._upload(frame), None
        except ValueError as e:
            return idx, t0, None, str(e)

    def _finish(self, started) -> StreamResult:
        """Compute a started frame (or report its error) and return its result."""
        self._started = started
        self.step()
        return self.fetch()

    def upload(self, frame) -> None:
        """Number one frame and start its upload (checked; a bad frame is reported by :meth:`fetch`)."""
        self._started = self._start(frame)
        self._done = None

    def step(self) -> None:
        """Solve, check and integrate the uploaded frame on the device (a bad frame is kept as an error)."""
        self._check_open()
        if self._started is None:
            raise ValueError("frame: expected upload(frame) before step(), got nothing uploaded")
        idx, t0, up, err = self._started
        self._started = None
        checks = None
        if err is None:
            try:
                checks = self._compute(*up)
            except _BadFrame as e:
                err = str(e)
        self._done = (idx, t0, checks, err)

    def fetch(self) -> StreamResult:
        """The last stepped frame's :class:`StreamResult` (an error result for a bad frame)."""
        if self._done is None:
            raise ValueError("frame: expected upload(frame) and step() before fetch(), got no frame")
        idx, t0, checks, err = self._done
        if err is not None:
            self.stats["errors"] += 1
            return StreamResult(idx, error=err, seconds=time.perf_counter() - t0)
        return self._result(idx, t0, checks)

    def iterate(self, frames: Iterable) -> Iterator[StreamResult]:
        """Yield one :class:`StreamResult` per frame of ``frames``, in order.

        The next frame's upload is started before the current frame computes
        (on CUDA it runs on a separate stream and overlaps the compute; the two
        upload slots alternate, so it never overwrites the frame in use).
        """
        it = iter(frames)
        cur = None
        for fr in it:
            cur = self._start(fr)
            break
        while cur is not None:
            nxt = None
            for fr in it:
                nxt = self._start(fr)
                break
            yield self._finish(cur)
            cur = nxt
