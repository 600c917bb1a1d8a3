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

Bad frames (wrong shape or dtype, NaN/inf) yield a :class:`StreamResult` with
``error`` set and leave the state (warm starts) untouched; the stream goes on.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Iterable, Iterator, Literal, get_args

import numpy as np

from gpps._check import as_mask, check_number
from gpps._runtime import resolve_device, warp
from gpps.camera import Orthographic, Perspective
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.solver import PixelSolver, SolverConfig

__all__ = ["StreamConfig", "StreamResult", "Stream"]

Output = Literal["device", "numpy"]
StreamSolver = Literal["lm", "dogleg", "bfgs"]
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
        first_tol: relative residual of the first frame's integration.
        reference_depth: mean depth per mask component (scene units); required
            for point lights (their 1/r^2 needs metric depth), optional otherwise
            (perspective default: mean log-depth 0; orthographic: mean depth 0).
        graph: ``"auto"`` captures CUDA graphs on CUDA, ``"off"`` never.
        capture_after: frames run eagerly before the capture.
        output: ``"device"`` results are Warp arrays (views of a ring of
            ``ring`` output slots, valid for that many frames); ``"numpy"`` copies.
        ring: output slots (device output).
        saturation: raw observations at or above this fraction of full scale
            are dropped from the fit (None: keep all).
    """

    solver: StreamSolver = "lm"
    iterations: int = 3
    first_starts: int = 10
    first_iterations: int = 50
    integrate: bool = True
    integration_iterations: int = 1
    first_tol: float = 1e-4
    reference_depth: float | None = None
    graph: Literal["auto", "off"] = "auto"
    capture_after: int = 2
    output: Output = "device"
    ring: int = 2
    saturation: float | None = None

    def __post_init__(self):
        if self.solver not in get_args(StreamSolver):
            raise ValueError(f"solver: expected one of {get_args(StreamSolver)}, got {self.solver!r}")
        if self.graph not in ("auto", "off"):
            raise ValueError(f"graph: expected 'auto' or 'off', got {self.graph!r}")
        if self.output not in get_args(Output):
            raise ValueError(f"output: expected one of {get_args(Output)}, got {self.output!r}")
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
    """

    index: int
    normals: Any = None
    albedo: Any = None
    depth: Any = None
    error: str | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.error is None

    def numpy(self) -> "StreamResult":
        """A copy with numpy arrays (a no-op for numpy results)."""
        cv = lambda a: a.numpy() if hasattr(a, "numpy") and not isinstance(a, np.ndarray) else a  # noqa: E731
        return StreamResult(self.index, cv(self.normals), cv(self.albedo), cv(self.depth), self.error, self.seconds)


class Stream:
    """Photometric stereo on a stream of N-image frames, buffers allocated once.

    Args:
        shape: (H, W) frame size.
        camera: :class:`Orthographic` or :class:`Perspective`.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N, one per image of a frame).
        material: :class:`Material` (reflectance model and parameters).
        mask: (H, W) bool pixels to reconstruct (None: all).
        config: :class:`StreamConfig`.
        device: Warp device (None: CUDA if present).

    Use :meth:`process` per frame, or :meth:`run` over any iterable of frames
    (it prefetches the next frame's upload while the current one computes).
    Each frame is an (N, H, W) or (N, H, W, 3) uint8 / uint16 / float32 array
    (numpy, or a Warp array already on the device); float32 is taken as
    0..1, integers as 0..full scale.
    """

    def __init__(self, shape, camera, lights, material: Material, mask=None, config: StreamConfig | None = None,
                 device=None):
        wp = warp()
        from gpps.kernels import stream as ks

        self._ks = ks
        self.config = config if config is not None else StreamConfig()
        if not isinstance(self.config, StreamConfig):
            raise TypeError(f"config: expected StreamConfig, got {type(self.config).__name__}")
        try:
            h, w = (int(s) for s in shape)
        except (TypeError, ValueError):
            raise ValueError(f"shape: expected (H, W), got {shape!r}") from None
        if h < 2 or w < 2:
            raise ValueError(f"shape: expected (H, W) with sizes >= 2, got {shape!r}")
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
        self._warm_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.iterations, starts=1, warm_start=True,
                                      early_exit=False, neighbour_radius=0)
        self._cold_cfg = SolverConfig(solver=cfg.solver, max_iters=cfg.first_iterations, starts=cfg.first_starts)
        self.solver = PixelSolver((n, h, w), camera, unit, material, self._cold_cfg, device=self.device)
        d = self.device
        self._gain = {}
        self._raw = {}  # (dtype, channels) -> [device buffers] (two slots)
        self._staging = {}
        self._slot = 0
        self._pending = None
        self._graphs: dict = {}
        self._count = wp.zeros(1, dtype=wp.int32, device=d)
        self.index = 0
        self.frames_done = 0
        self._warm_frames = 0
        self.solver.mask.assign(self.mask.astype(np.uint8))
        self.solver.valid.fill_(1)
        dep0 = float(cfg.reference_depth) if cfg.reference_depth is not None else 1.0
        self.solver.depth.fill_(dep0)
        self.depth = wp.zeros((h, w), dtype=wp.float32, device=d)
        self.integrator = None
        if cfg.integrate:
            from gpps.pipeline.integration_device import StreamIntegrator

            self.integrator = StreamIntegrator(self.mask, camera, device=self._taichi_device())
            if self.is_cuda:
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
        self.stats = {"frames": 0, "errors": 0, "seconds": 0.0}

    def _taichi_device(self):
        return "cuda:0" if self.is_cuda else "cpu"

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
            raise ValueError(f"frame: expected dtype uint8, uint16 or float32, got {dt}")
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
                wp.launch(self._ks.count_nonfinite, dim=(self.n, *self.shape),
                          inputs=[arr.reshape((self.n, *self.shape, c))], outputs=[self._count], device=self.device)
                if int(self._count.numpy()[0]) > 0:
                    raise ValueError("frame: expected finite values, got NaN or inf")
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

    def _launch_solve(self, key, slot):
        wp = warp()
        raw = self._raw[key][slot]
        kern = {np.dtype(np.uint8): self._ks.convert_uint8, np.dtype(np.uint16): self._ks.convert_uint16,
                np.dtype(np.float32): self._ks.convert_float32}[key[0]]
        wp.launch(kern, dim=(self.n, *self.shape), inputs=[raw, self._gain[key]], outputs=[self.solver.images],
                  device=self.device)
        self.solver.launch()

    def _compute(self, key, slot, ev):
        wp = warp()
        cfg = self.config
        cold = self.frames_done == 0
        if ev is not None:
            wp.get_stream(self.device).wait_event(ev)
        if cold:
            self.solver.set_config(self._cold_cfg)
            self._launch_solve(key, slot)
        else:
            if self._warm_frames == 0:
                self.solver.set_config(self._warm_cfg)
            use_graph = self.is_cuda and cfg.graph == "auto" and self._warm_frames >= cfg.capture_after
            if use_graph:
                g = self._graphs.get((key, slot))
                if g is None:
                    wp.capture_begin(device=self.device)
                    try:
                        self._launch_solve(key, slot)
                    finally:
                        g = wp.capture_end(device=self.device)
                    self._graphs[(key, slot)] = g
                wp.capture_launch(g)
            else:
                self._launch_solve(key, slot)
            self._warm_frames += 1
        if self.integrator is not None:
            if self.is_cuda:
                wp.synchronize_device(self.device)
            ref = cfg.reference_depth
            if cold:
                self.integrator.reset()
                self.integrator.integrate(self._nrm_view, self._dep_view, tol=cfg.first_tol, reference=ref)
            else:
                self.integrator.integrate(self._nrm_view, self._dep_view, iterations=cfg.integration_iterations,
                                          reference=ref)
            if self.is_cuda:
                from gpps import _taichi

                _taichi.ti.sync()
            if self.point:
                # the next frame's per-pixel light directions and fall-off come from this depth
                wp.copy(self.solver.depth, self.depth)
        self.frames_done += 1

    def _result(self, index, t0):
        wp = warp()
        cfg = self.config
        dep = self.depth if self.integrator is not None else None
        if cfg.output == "numpy":
            res = StreamResult(index, self.solver.normals.numpy(), self.solver.albedo.numpy(),
                               None if dep is None else dep.numpy())
        else:
            nr, ab, dp = self._ring[index % len(self._ring)]
            wp.copy(nr, self.solver.normals)
            wp.copy(ab, self.solver.albedo)
            if dep is not None:
                wp.copy(dp, dep)
            res = StreamResult(index, nr, ab, dp if dep is not None else None)
        res.seconds = time.perf_counter() - t0
        self.stats["frames"] += 1
        self.stats["seconds"] += res.seconds
        return res

    def _start(self, frame):
        """Number the frame and start its upload: ``(index, t0, (key, slot, event) or None, error or None)``."""
        t0 = time.perf_counter()
        idx = self.index
        self.index += 1
        try:
            return idx, t0, self._upload(frame), None
        except ValueError as e:
            return idx, t0, None, str(e)

    def _finish(self, started) -> StreamResult:
        """Compute a started frame (or report its error) and return its result."""
        idx, t0, up, err = started
        if err is not None:
            self.stats["errors"] += 1
            return StreamResult(idx, error=err, seconds=time.perf_counter() - t0)
        self._compute(*up)
        return self._result(idx, t0)

    def process(self, frame) -> StreamResult:
        """Reconstruct one frame (normals, albedo, depth); a bad frame gives an error result."""
        return self._finish(self._start(frame))

    def run(self, frames: Iterable) -> Iterator[StreamResult]:
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
