"""Device-resident normal integration for streams: one mask, many normal maps, no host round trip.

:class:`StreamIntegrator` is the per-frame form of
:class:`gpps.pipeline.integration.Integrator` (uniform Poisson weights, 4.20):
the mask, the multigrid hierarchy, the coarsest-level pseudo-inverse and the
connected components are set up once; each frame then costs a few fused
Taichi launches (:mod:`gpps.kernels.poisson_fused`): with a fixed count of
multigrid cycles (the streaming mode) one launch for the whole frame, whose
small levels run in one persistent task with software grid barriers on CUDA
(``StreamIntegratorConfig.launch``); with a tolerance, or PCG, a launch per
iteration; the depth is written straight into the caller's buffer.  The normals are read in place (a numpy
array, or on CUDA a Warp array through ``wp.to_torch``, zero-copy), and the
previous solution stays in the fields as the next frame's warm start.

Two stopping modes: ``integrate(..., iterations=k)`` runs exactly ``k``
iterations with no host synchronisation (the streaming mode); ``tol=...``
checks the residual every ``check_every`` iterations (one 8-byte read each).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy import ndimage

from gpps import _taichi
from gpps._check import check_choices, check_number
from gpps._runtime import warp
from gpps._taichi import DirectLaunch
from gpps.camera import Orthographic, Perspective
from gpps.host.poisson import build_levels, diagonal, laplacian, level_shapes
from gpps.kernels.poisson_fused import make_fused
from gpps.names import STALL_CHECKS, LaunchName
from gpps.pipeline.stage import Stage

__all__ = ["StreamIntegratorConfig", "StreamIntegrator"]

DType = Literal["float32", "float64"]
Method = Literal["pcg", "multigrid"]
Launch = LaunchName
_BLOCK = 256  # threads per block of the persistent frame kernel
_FUSED_MAX = 4  # multigrid cycles fused into the one-launch frame kernel (the streaming and cold counts)


@dataclass(frozen=True)
class StreamIntegratorConfig:
    """Options of :class:`StreamIntegrator`.

    Attributes:
        coarsest: coarsen while ``max(h, w) > coarsest``; the coarsest level is
            solved exactly by a dense pseudo-inverse (at most ``coarsest^2``
            cells).  Each level costs a few parallel tasks (about 6 us each on
            an H100, launch-bound at the small levels), the dense solve grows
            as ``coarsest^4``: 16 was the faster of 16 and 32 at 1024^2.
        smooth_pairs: Jacobi sweep pairs before and after each coarse
            correction.
        omega: Jacobi damping.
        min_nz: floor on ``n_z`` (orthographic) or ``-m`` (perspective).
        dtype: field precision.
        check_every: iterations between residual checks in the ``tol`` mode.
        method: ``"multigrid"`` (default): plain V-cycle corrections
            ``u += M (b - A u)``; with a fixed iteration count the whole frame
            (right-hand side, corrections, depth) is one Taichi launch.
            ``"pcg"``: conjugate gradients preconditioned by one V-cycle per
            iteration (two level-0 passes and reductions more per iteration,
            and a restart per frame).  On an H100 at 1024^2
            (``perf/integration_device_speed.py``) the multigrid form reaches
            1e-4 of the depth range cold in 3 cycles and warm in 1, PCG in 2
            and 1, each PCG iteration costing about 1.3 cycles.
        launch: how a multigrid frame with a fixed cycle count runs on the
            device.  ``"tasks"``: one Taichi launch of about 30 parallel tasks
            (one per phase; each task costs an H100 about 3 us of device time
            and 5 us of host time).  ``"persistent"``: the levels no larger
            than ``persistent_size`` run as one task whose phases are
            separated by software grid barriers (about 2 us each), its blocks
            all resident at once; the larger levels stay one task per phase,
            where full occupancy pays (:func:`gpps.kernels.poisson_fused.make_fused`,
            ``hybrid`` and ``persistent``).  ``"auto"``: persistent on CUDA,
            tasks on CPU.  On the CPU ``"persistent"`` runs its task as one
            thread, phase after phase (slow: it exists to test the arithmetic).
        blocks_per_sm: resident blocks of 256 threads per multiprocessor of the
            persistent task; if the GPU cannot hold them (the first frame's
            barrier check), it halves them down to 1, then falls back to tasks.
        persistent_size: levels whose larger side is at most this run in the
            persistent task (an image no larger runs whole in it).  On an H100
            at 1024^2 (``perf/integration_device_speed.py``, before the fused
            right-hand side and the warp sums) a warm one-cycle frame cost the
            device 0.186 ms this way against 0.196 as tasks, and the host
            0.27-0.34 ms against 0.41 (14 tasks instead of 30); the whole frame
            in the persistent task cost 0.293 ms (level 0 at 2 blocks per SM is
            latency-bound).  Now a frame is 11 tasks: 0.199 ms of device time
            and 0.09 ms of host time; 512 (7 tasks) gave 0.210 and 0.06.
        direct_launch: launch the per-frame kernel through
            :class:`gpps._taichi.DirectLaunch` (Taichi's argument handling
            skipped while the normals and output arrays are the same objects
            as the previous frame's, as in a stream; the last four sets of
            arrays are remembered, for buffers used in turn).  On an H100 at
            1024^2 with torch tensors an isolated warm frame took 0.283 ms this
            way against 0.403 with Taichi's plain call, a streamed one 0.196
            against 0.312 (``perf/integration_device_speed.py``).  False:
            Taichi's plain call.
    """

    coarsest: int = 16
    smooth_pairs: int = 1
    omega: float = 0.8
    min_nz: float = 1e-3
    dtype: DType = "float32"
    check_every: int = 2
    method: Method = "multigrid"
    launch: Launch = "auto"
    blocks_per_sm: int = 2
    persistent_size: int = 256
    direct_launch: bool = True

    def __post_init__(self):
        check_choices(self)
        check_number("blocks_per_sm", self.blocks_per_sm, lo=1, hi=8, integer=True)
        check_number("persistent_size", self.persistent_size, lo=1, integer=True)
        check_number("coarsest", self.coarsest, lo=2, hi=48, integer=True)
        check_number("smooth_pairs", self.smooth_pairs, lo=1, hi=8, integer=True)
        check_number("omega", self.omega, lo=0.0, hi=1.0, lo_open=True)
        check_number("min_nz", self.min_nz, lo=0.0, hi=1.0, lo_open=True)
        check_number("check_every", self.check_every, lo=1, integer=True)
        if not isinstance(self.direct_launch, bool):
            raise TypeError(f"direct_launch: expected bool, got {type(self.direct_launch).__name__}")


class StreamIntegrator(Stage):
    """Integrate many normal maps over one fixed mask on the Taichi device.

    Args:
        mask: (H, W) bool, at least 2 pixels.
        camera: :class:`Orthographic` or :class:`Perspective` (None: orthographic, pixel size 1).
        config: :class:`StreamIntegratorConfig`.
        device: ``"auto"``, ``"cpu"`` or ``"cuda:0"`` (Taichi's device).

    The unknown is the depth (orthographic) or the log-depth (perspective,
    PPN 3.2-3.3); each 4-connected component of the mask gets its own
    constant (mean 0, or mean depth ``reference``).
    """

    def __init__(self, mask, camera=None, config: StreamIntegratorConfig | None = None, device: str | None = "auto"):
        m = np.asarray(mask)
        if m.ndim != 2:
            raise ValueError(f"mask: expected (H, W), got shape {m.shape}")
        m = m.astype(bool)
        if m.sum() < 2:
            raise ValueError(f"mask: expected at least 2 pixels set, got {int(m.sum())}")
        camera = Orthographic(1.0) if camera is None else camera
        if not isinstance(camera, (Orthographic, Perspective)):
            raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
        self.config = config if config is not None else StreamIntegratorConfig()
        if not isinstance(self.config, StreamIntegratorConfig):
            raise TypeError(f"config: expected StreamIntegratorConfig, got {type(self.config).__name__}")
        self.mask, self.camera, self.shape = m, camera, m.shape
        ti = _taichi.init(device)
        self.device = _taichi.current_device()
        cfg = self.config
        h, w = self.shape
        # uniform edge weights of the mask: an edge exists where both pixels are in the mask
        wx = np.zeros((h, w))
        wy = np.zeros((h, w))
        wx[:, :-1] = (m[:, :-1] & m[:, 1:]).astype(float)
        wy[:-1, :] = (m[:-1, :] & m[1:, :]).astype(float)
        # pixels with no edge cannot be integrated: drop them from the mask
        dgl = diagonal(wx, wy)
        valid = m & (dgl > 0)
        if valid.sum() < 2:
            raise ValueError("mask: expected at least 2 pixels with a 4-neighbour in the mask")
        self.valid = valid
        lab, ncomp = ndimage.label(valid)
        self.n_components = int(ncomp)
        shapes = level_shapes(h, w, cfg.coarsest)
        offs = np.concatenate([[0], np.cumsum([s[1] for s in shapes])]).astype(int)
        wpk = int(offs[-1])
        ft = ti.f32 if cfg.dtype == "float32" else ti.f64
        npd = np.dtype(cfg.dtype)
        levels = build_levels(wx, wy, cfg.coarsest)
        lx, ly = levels[-1]
        dgc = diagonal(lx, ly)
        act = np.argwhere(dgc > 0)
        nc = len(act)
        fb = ti.FieldsBuilder()
        F = {}
        for name in ("wx", "wy", "dg", "e", "f", "t"):
            F[name] = ti.field(ft)
            fb.dense(ti.ij, (h, wpk)).place(F[name])
        for name in ("z", "b", "r", "p", "q"):
            F[name] = ti.field(ft)
            fb.dense(ti.ij, (h, w)).place(F[name])
        F["red"] = ti.field(ft)
        fb.dense(ti.ij, (h, w)).place(F["red"])
        for name in ("part", "part2"):
            F[name] = ti.field(ti.f64)
            fb.dense(ti.ij, ((h + 7) // 8, w)).place(F[name])  # chunks of poisson_fused's CH rows
        F["sc"] = ti.field(ti.f64)
        fb.dense(ti.i, 10).place(F["sc"])
        F["slot"] = ti.field(ti.f64)  # per-warp totals of the last z update (CUDA, one component)
        fb.dense(ti.ij, (2, 32)).place(F["slot"])
        F["wcnt"] = ti.field(ti.i32)  # warps of that update arrived
        fb.dense(ti.i, 1).place(F["wcnt"])
        F["bar"] = ti.field(ti.i32)  # grid-barrier arrivals, timeout flag (persistent kernel)
        fb.dense(ti.i, 2).place(F["bar"])
        F["geo"] = ti.field(ti.i32)  # (offset, height, width) per level
        fb.dense(ti.ij, (len(shapes), 3)).place(F["geo"])
        F["cmap"] = ti.field(ti.i32)  # coarsest cell -> index into cidx, -1 if inactive
        fb.dense(ti.ij, shapes[-1]).place(F["cmap"])
        F["fcv"] = ti.field(ft)  # the coarsest right-hand side, gathered
        fb.dense(ti.i, max(nc, 1)).place(F["fcv"])
        F["pinv"] = ti.field(ft)
        fb.dense(ti.ij, (max(nc, 1), max(nc, 1))).place(F["pinv"])
        F["cidx"] = ti.field(ti.i32)
        fb.dense(ti.ij, (max(nc, 1), 2)).place(F["cidx"])
        F["lab"] = ti.field(ti.i32)
        fb.dense(ti.ij, (h, w)).place(F["lab"])
        for name in ("csum", "cden", "ccnt"):
            F[name] = ti.field(ti.f64)
            fb.dense(ti.i, max(ncomp, 1)).place(F[name])
        self._tree = fb.finalize()
        P = {k: np.zeros((h, wpk), dtype=npd) for k in ("wx", "wy", "dg")}
        for k, ((ax, ay), (hh, ww)) in enumerate(zip(levels, shapes)):
            o = offs[k]
            P["wx"][:hh, o:o + ww] = ax
            P["wy"][:hh, o:o + ww] = ay
            P["dg"][:hh, o:o + ww] = diagonal(ax, ay)
        for k in ("wx", "wy", "dg"):
            F[k].from_numpy(P[k])
        pinv = np.zeros((max(nc, 1), max(nc, 1)), dtype=npd)
        cidx = np.zeros((max(nc, 1), 2), dtype=np.int32)
        if nc:
            A, _ = laplacian(lx, ly, dgc > 0)
            pinv[:nc, :nc] = np.linalg.pinv(A.toarray(), hermitian=True)
            cidx[:nc, 0] = act[:, 0]
            cidx[:nc, 1] = act[:, 1] + offs[len(levels) - 1]
        F["pinv"].from_numpy(pinv)
        F["cidx"].from_numpy(cidx)
        cmap = -np.ones(shapes[-1], dtype=np.int32)
        if nc:
            cmap[act[:, 0], act[:, 1]] = np.arange(nc, dtype=np.int32)
        F["cmap"].from_numpy(cmap)
        F["geo"].from_numpy(np.array([[offs[k], s[0], s[1]] for k, s in enumerate(shapes)], dtype=np.int32))
        F["bar"].fill(0)
        F["slot"].fill(0)
        F["wcnt"].fill(0)
        F["lab"].from_numpy((lab - 1).astype(np.int32))
        F["ccnt"].from_numpy(np.bincount(lab.ravel(), minlength=ncomp + 1)[1:].astype(np.float64).reshape(max(ncomp, 1)))
        for k in ("z", "e", "f", "t"):
            F[k].fill(0)
        self._F = F
        self.levels = [(int(offs[k]), s[0], s[1]) for k, s in enumerate(shapes)]

        self._K = make_fused(F, self.levels, cfg.smooth_pairs, cfg.omega, nc, camera.is_perspective)
        if camera.is_perspective:
            cx, cy = camera.principal_point(self.shape)
            self._cam = (float(camera.fx), float(camera.fy), float(cx), float(cy), 1.0)
        else:
            self._cam = (1.0, 1.0, 0.0, 0.0, float(camera.pixel_size))
        self.last_iterations = 0
        self.last_residual = float("nan")
        persistent = cfg.launch == "persistent" or (cfg.launch == "auto" and self.device.startswith("cuda"))
        # the first level in the persistent task (0: all of them)
        self._top = next(k for k, (hh, ww) in enumerate(shapes) if max(hh, ww) <= cfg.persistent_size or k == len(shapes) - 1)
        if len(shapes) < 3 or self._top == len(shapes) - 1:
            persistent = False  # nothing but the coarsest level would be in it
        #: "persistent" or "tasks": how fixed-count multigrid frames run (see ``StreamIntegratorConfig.launch``)
        self.launch = "persistent" if persistent and cfg.method == "multigrid" else "tasks"
        self._bps = cfg.blocks_per_sm
        self._ready = {}  # cycles -> (launcher, extra arguments) of a persistent frame whose barrier passed
        self._frames = {}  # cycles -> launcher of the task frame kernel
        self._io = (None, None)  # the (normals, out) objects last checked

    # ------------------------------------------------------------------ persistent kernel

    def _grid(self) -> tuple[int, int]:
        """(blocks, threads per block) of the persistent task: on CUDA, ``blocks_per_sm``
        per multiprocessor (no more than its largest level needs); on the CPU one thread."""
        if not self.device.startswith("cuda"):
            return 1, 1

        sms = int(warp().get_device("cuda:0").sm_count)
        _, hh, ww = self.levels[self._top]
        return max(1, min(sms * self._bps, -(-hh * ww // _BLOCK))), _BLOCK

    def _persistent_kernel(self, cycles: int):
        """(kernel, extra arguments) of a frame of ``cycles`` corrections, or None (tasks)."""
        if self._top == 0:
            return self._K["persistent"](*self._grid()), (int(cycles),)
        if cycles > _FUSED_MAX:
            return None
        return self._K["hybrid"](int(cycles), self._top, *self._grid()), ()

    def _persistent(self, normals, out, cycles: int, ref: float) -> bool:
        """Run a frame with the persistent task; False if this frame is for the tasks path (more
        cycles than a fused frame holds, or a GPU that cannot hold the persistent blocks at all).

        Each kernel's first frame checks the barrier's timeout flag (one host read) and, if some
        block never became resident, restores the warm start and retries with half the
        blocks per multiprocessor, down to 1.
        """
        ready = self._ready.get(cycles)
        if ready is not None:  # the streaming path: one launch
            ready[0](normals, out, *self._cam, self.config.min_nz, ref, *ready[1])
            return True
        F = self._F
        while True:
            got = self._persistent_kernel(cycles)
            if got is None:
                return False
            kern, extra = got
            F["p"].copy_from(F["z"])
            F["bar"].fill(0)
            kern(normals, out, *self._cam, self.config.min_nz, ref, *extra)
            if int(F["bar"][1]) == 0:
                self._ready[cycles] = (self._launcher(kern), extra)
                return True
            F["z"].copy_from(F["p"])
            F["bar"].fill(0)
            self._ready.clear()  # kernels of other cycle counts were checked with these blocks too
            if self._bps == 1:
                warnings.warn("StreamIntegrator: the GPU cannot hold the persistent kernel's blocks; "
                              "using one task per phase", RuntimeWarning, stacklevel=3)
                self.launch = "tasks"
                return False
            self._bps //= 2

    def _launcher(self, kern):
        """The per-frame call of ``kern``: direct (see ``StreamIntegratorConfig.direct_launch``) or plain."""
        if not self.config.direct_launch:
            return kern

        return DirectLaunch(kern)

    def _check_io(self, normals, out) -> None:
        """Shapes every frame; types and dtypes when the arrays are not the previous frame's."""
        h, w = self.shape
        if tuple(getattr(normals, "shape", ())) != (h, w, 3):
            raise ValueError(f"normals: expected shape ({h}, {w}, 3), got {tuple(getattr(normals, 'shape', ()))}")
        if tuple(getattr(out, "shape", ())) != (h, w):
            raise ValueError(f"out: expected shape ({h}, {w}), got {tuple(getattr(out, 'shape', ()))}")
        if normals is self._io[0] and out is self._io[1]:
            return
        for name, arr, ok in (("normals", normals, ("float32", "float64")), ("out", out, ("float32",))):
            dt = str(getattr(arr, "dtype", "")).replace("torch.", "")
            dt = {"f32": "float32", "f64": "float64"}.get(dt, dt)
            if dt not in ok:
                raise ValueError(f"{name}: expected a {' or '.join(ok)} array (numpy, torch or Taichi ndarray), "
                                 f"got {type(arr).__name__} of dtype {dt or 'none'}")
        self._io = (normals, out)

    # ------------------------------------------------------------------ per frame

    def upload(self, depth) -> None:
        """Warm start from a depth map (H, W) (numpy, or a CUDA tensor Taichi accepts).

        The normal maps themselves are not copied: :meth:`step` reads them where they are (another
        stage's device buffer)."""
        self._K["load"](depth)

    def reset(self) -> None:
        """Forget the previous solution (the next frame starts from u = 0)."""
        self._F["z"].fill(0)

    def step(self, normals, out, *, iterations: int | None = None, tol: float | None = None,
             max_iterations: int = 200, reference: float | None = None) -> None:
        """Integrate one normal map into ``out``, warm-started from the previous frame.

        Args:
            normals: (H, W, 3) float32 or float64 unit normals (numpy, a Taichi
                ndarray, or on CUDA a torch tensor view of a Warp array); read
                where the mask is set.
            out: (H, W) float32 array (same kinds) written with the depth (0
                outside the mask).
            iterations: run exactly this many iterations (no host sync): PCG
                iterations or V-cycle corrections (``config.method``).
            tol: else iterate until ``|b - A u| <= tol |b|`` (checked every
                ``config.check_every`` iterations) or ``max_iterations``, or,
                in float32, until the residual stops falling: :data:`gpps.names.STALL_CHECKS`
                checks in a row without halving the best ``|r|^2`` so far (the
                arithmetic's floor: on the bumps scene the relative residual
                stays at 3.3e-4 from the 6th iteration at 512^2 and 1.0e-3 at
                1024^2, so ``tol=1e-4`` ran the 200 iterations for the same
                depth: 52 ms instead of about 3 on an H200 at 1024^2).
                :attr:`last_residual` then says where it stopped.
            reference: mean depth per component, >= 0 (None or 0: orthographic
                mean 0, perspective mean log-depth 0).

        Raises:
            ValueError: arrays of another shape or dtype, a negative or
                non-finite ``reference``, bad ``iterations``/``tol``.
        """
        if (iterations is None) == (tol is None):
            raise ValueError("iterations, tol: expected exactly one of them")
        if iterations is not None:
            check_number("iterations", iterations, lo=0, integer=True)
        else:
            check_number("tol", tol, lo=0.0, hi=1.0, lo_open=True)
        self._check_io(normals, out)
        K = self._K
        mg = self.config.method == "multigrid"
        ref = check_number("reference", reference, lo=0.0) if reference is not None else 0.0
        if mg and iterations is not None and iterations >= 1 and self.launch == "persistent":
            if self._persistent(normals, out, int(iterations), ref):
                self.last_iterations = int(iterations)
                return
        if mg and iterations is not None and iterations <= _FUSED_MAX:
            # the whole frame in one launch (right-hand side, corrections, depth); longer
            # runs launch per cycle (one kernel per count would compile a long unrolled chain)
            run = self._frames.get(int(iterations))
            if run is None:
                run = self._frames[int(iterations)] = self._launcher(K["frame"](int(iterations)))
            run(normals, out, *self._cam, self.config.min_nz, ref)
            self.last_iterations = int(iterations)
            return
        if mg:
            K["rhs_only"](normals, *self._cam, self.config.min_nz)
            step = K["mg_step"]
        else:
            K["rhs_begin"](normals, *self._cam, self.config.min_nz)
            step = K["pcg_iteration"]
        if iterations is not None:
            for _ in range(iterations):
                step()
            self.last_iterations = int(iterations)
        else:
            sc = K["scalars"]()  # one read: |b|^2 and (CG) |r|^2
            bb = float(sc[7])
            its = 0
            rr = float(sc[2]) if not mg else bb
            rr_min = rr
            stalled = 0
            f32 = self.config.dtype == "float32"
            while bb > 0 and rr > tol * tol * bb and its < max_iterations:
                step()
                its += 1
                if its % self.config.check_every == 0:
                    if mg:
                        K["residual"]()  # mg_step computes no norm
                    rr = float(K["scalars"]()[2])
                    if f32 and rr > 4.0 * rr_min and rr_min < 1e-8 * bb:
                        break  # past the float32 floor the CG recurrence wanders: stop
                    # a multigrid iteration cuts |r| several times over while it converges; checks that do not
                    # halve the best |r|^2 are rounding noise at the float32 floor, which may lie above tol
                    stalled = 0 if rr < 0.5 * rr_min else stalled + 1
                    rr_min = min(rr_min, rr)
                    if f32 and stalled >= STALL_CHECKS:
                        break
            K["residual"]()
            rr = float(K["scalars"]()[2])
            self.last_iterations = its
            self.last_residual = float(np.sqrt(rr / bb)) if bb > 0 else 0.0
        K["finish"](out, ref)

    def fetch(self) -> dict:
        """``iterations`` of the last :meth:`step` and the ``residual`` ``|b - A u| / |b|`` of the current
        solution (a host sync); the depth itself is in the ``out`` array the step wrote."""
        return {"iterations": int(self.last_iterations), "residual": self.residual()}

    def run(self, normals, out, **kwargs) -> dict:
        """:meth:`step` then :meth:`fetch` (the normals are read in place: nothing to upload)."""
        self.step(normals, out, **kwargs)
        return self.fetch()

    def residual(self) -> float:
        """Relative residual ``|b - A u| / |b|`` of the current solution (host sync)."""
        self._K["residual"]()
        sc = self._K["scalars"]()
        bb = float(sc[7])
        return float(np.sqrt(float(sc[2]) / bb)) if bb > 0 else 0.0

    def close(self) -> None:
        """Free the fields and the per-frame launchers (which hold the last frames' arrays)."""
        self._ready.clear()
        self._frames.clear()
        if self._tree is not None:
            self._tree.destroy()
            self._tree = None
