"""Bilateral normal integration (BiNI) on the device: the stage that owns its buffers.

Cao, Santo, Shi, Okura and Matsushita, "Bilateral Normal Integration", ECCV
2022.  Each valid pixel contributes four one-sided equations (forward and
backward along j and i) in BiNI's multiplied form ``N (u_q - u_p) - m`` (no
division by ``N``, so grazing normals only lose weight):

* orthographic (pixel size ``s``): ``u`` = depth, ``N = n_z / s``, ``m_j = n_x``,
  ``m_i = -n_y`` (rows go down);
* perspective (BiNI's log-depth form): ``u = log d``, with ``B = n_x (j - c_x) -
  n_y (i - c_y)``: ``N_j = f_x n_z - B``, ``N_i = f_y n_z - B``, ``m_j = n_x``,
  ``m_i = -n_y``; ``N > 0`` for a normal facing the camera.  ``N D = m`` is the
  PPN constraint (3.2)-(3.3), ``D`` the one-sided difference.

The energy ``E(u, w) = sum_p w_j (N_j D_right - m_j)^2 + (1 - w_j) (N_j D_left -
m_j)^2 + (same along i)`` is minimised by BiNI's iteratively reweighted least
squares, exactly as its reference implementation (whose defaults are the
defaults here):

1. ``w = 1/2`` everywhere, ``u = 0`` (or the warm start), ``E_0 = E(u, 1/2)``;
2. solve the normal equations for ``u`` with fixed ``w`` by Jacobi-preconditioned
   CG to relative residual ``cg_tol`` (1e-3), warm-started from the previous ``u``
   (at most ``cg_max_iter`` = 5000 iterations, at least one);
3. ``w_j = sigmoid(k ((N_j D_left)^2 - (N_j D_right)^2))`` (k = 2), the same
   along i: the side with the smaller jump keeps the weight, a depth
   discontinuity is cut;
4. ``E_t = E(u, w)``; stop when ``|E_t - E_{t-1}| / E_{t-1} < tol`` (1e-4) or after
   ``max_iter`` (150) iterations, else go to 2.

The inner solver is part of the method: BiNI's reported accuracy is that of
this warm-started, loosely converged Jacobi-PCG trajectory (its authors'
optimisation log records that exact or multigrid-class inner solves move the
non-convex IRLS to other, on DiLiGenT worse, local minima; so did gpps's
earlier multigrid variant: bear 1.48x, cow 1.21x of BiNI's error).  Every
step runs on the device (Taichi, float64): buffers are uploaded once, the
host reads a few scalars per IRLS iteration and one per launch of 6 CG
iterations, and the depth is fetched at the end.

Speed (perf/integration_bini.py, results in perf/results/integration_bini_*.json):
on this project's 2-core CPU the six DiLiGenT maps take 5.6 s against 11.7 s
for BiNI's reference code in the same process (identical iteration counts and
errors); on an H100 a map takes 0.4-1.7 s (5.7 s for the six) against dbini-torch's 0.8-1.8 s (8.3 s):
the Jacobi-PCG needs thousands of iterations (2400-6800 per map, about 13 000
on a 256^2 map and growing with the side), each a few small launches, so the
faithful method is far from real time on large maps.
"""

from __future__ import annotations

import threading
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from gpps import _taichi
from gpps._check import check_choices, check_number
from gpps._runtime import warp
from gpps._taichi import ti
from gpps.kernels import bini as K
from gpps.names import LaunchName
from gpps.pipeline.stage import Stage

__all__ = ["BiniConfig", "BiniResult", "BilateralIntegrator", "bini_coefficients", "check_cuts"]


@dataclass(frozen=True)
class BiniConfig:
    """Options of :class:`BilateralIntegrator` (BiNI's reference defaults).

    Attributes:
        k: sigmoid sharpness (BiNI's ``k``; larger cuts smaller jumps).
        max_iter: IRLS iterations at most.
        tol: relative energy change that stops the IRLS.
        cg_tol: relative residual ``|b - A u| / |b|`` of each inner solve.
        cg_max_iter: CG iterations per inner solve at most.
        check_every: CG iterations per launch, a multiple of 6 (unrolled on the
            device, gated there by the stopping rule, so this never overshoots);
            the host checks once per launch (the ``"tasks"`` launch).
        launch: how an IRLS iteration runs.  ``"tasks"``: a launch for the system,
            launches of ``check_every`` CG iterations (two Taichi tasks each) until
            the host reads the done flag, one for the reweighting.  ``"persistent"``:
            the whole iteration (system, CG to its tolerance, reweighting, energy)
            as one task whose phases meet at software grid barriers
            (:func:`gpps.kernels.bini.make_irls_persistent`; off CUDA one thread, a
            test of its arithmetic).  ``"auto"``: persistent on CUDA, tasks on the CPU.
            Same iterations and stopping rules either way.
        blocks_per_sm: resident blocks of 128 threads per multiprocessor of the
            persistent task (all must be resident at once: a GPU that cannot hold
            them falls back to half as many, then to the tasks).  No more blocks than the
            pixels fill (one pixel a thread).  4: more resident warps hide more of each
            phase's memory and barrier latency (on an H200, DiLiGenT bear's IRLS took
            23.5 ms at 4, 26.8 at 2 and 30.1 at 1; buddha 66.3, 70.6 and 84.0:
            perf/results/bini_persistent_cuda0_H200_s12.json; on all six maps 4 is faster
            than 2 on five and equal on goblet, 6 equal to 4: ..._s12_six.json).
    """

    k: float = 2.0
    max_iter: int = 150
    tol: float = 1e-4
    cg_tol: float = 1e-3
    cg_max_iter: int = 5000
    check_every: int = 6
    launch: LaunchName = "auto"
    blocks_per_sm: int = 4

    def __post_init__(self):
        check_choices(self)
        check_number("blocks_per_sm", self.blocks_per_sm, lo=1, hi=16, integer=True)
        for name in ("k",):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
                raise ValueError(f"{name}: expected a finite number > 0, got {v!r}")
        for name in ("tol", "cg_tol"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < 1:
                raise ValueError(f"{name}: expected a number in (0, 1), got {v!r}")
        for name in ("max_iter", "cg_max_iter", "check_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {v!r}")
        if self.check_every % 6:
            raise ValueError(f"check_every: expected a multiple of 6, got {self.check_every!r}")


@dataclass
class BiniResult:
    """Output of :meth:`BilateralIntegrator.solve`.

    Attributes:
        u: (H, W) float64 solution (depth or log-depth), 0 outside the pixels.
        outer_iterations: IRLS iterations run.
        cg_iterations: CG iterations summed over them.
        energy: BiNI's energy after each IRLS iteration.
        converged: the relative energy change fell below ``tol``.
        residual: relative residual of the last inner solve (device, float64).
        wj, wi: (H, W) final forward weights along j and i (0.5 outside).
        timings: seconds ``upload``, ``solve``, ``fetch``.
    """

    u: np.ndarray
    outer_iterations: int
    cg_iterations: int
    energy: list
    converged: bool
    residual: float
    wj: np.ndarray
    wi: np.ndarray
    timings: dict = field(default_factory=dict)


def bini_coefficients(normals: np.ndarray, valid: np.ndarray, camera):
    """BiNI's per-pixel coefficients ``(N_j, N_i, m_j, m_i)`` (see the module docstring).

    Args:
        normals: (H, W, 3) unit normals, gpps frame.
        valid: (H, W) bool.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.

    Returns:
        four (H, W) float64 arrays, 0 outside ``valid``; ``N D = m`` along each
        axis for the true surface (``D`` the one-sided difference of ``u``).
    """
    v = np.asarray(valid, dtype=bool)
    ii, jj = np.nonzero(v)
    out = []
    for a in bini_coefficients_at(normals, ii, jj, camera, v.shape):
        full = np.zeros(v.shape)
        full[ii, jj] = a
        out.append(full)
    return tuple(out)


def bini_coefficients_at(normals: np.ndarray, ii: np.ndarray, jj: np.ndarray, camera, shape):
    """:func:`bini_coefficients` at the pixels ``(ii, jj)`` only: four (P,) float64 arrays, the same values.

    Args:
        normals: (H, W, 3) unit normals, gpps frame.
        ii, jj: (P,) int rows and columns.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        shape: (H, W) of the image (the principal point's default).
    """
    n = np.asarray(normals)[ii, jj].astype(np.float64)
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    if camera.is_perspective:
        cx, cy = camera.principal_point(tuple(shape))
        base = nx * (jj.astype(np.float64) - cx) - ny * (ii.astype(np.float64) - cy)
        Nj = camera.fx * nz - base
        Ni = camera.fy * nz - base
    else:
        Nj = Ni = nz / camera.pixel_size
    return Nj, Ni, nx, -ny


# ---------------------------------------------------------------------------- the buffer pool
#
# Taichi compiles a kernel per set of fields it closes over; a pool of field sets
# (capacity a power of two, one per (capacity, unroll) in use at a time) keeps
# that to one compilation per size class and process.

_POOL: dict = {}
_POOL_LOCK = threading.Lock()
_NAMES = ("x", "b", "r", "z", "p0", "p1", "q", "Nj", "Ni", "mj", "mi", "wj", "wi", "Wr", "Wd", "Fr", "Fd", "dinv")


def _acquire(n: int, unroll: int) -> dict:

    cap = 1 << max(10, int(n - 1).bit_length())
    key = (cap, unroll)
    with _POOL_LOCK:
        free = _POOL.setdefault(key, [])
        if free:
            return free.pop()
    fb = ti.FieldsBuilder()
    F = {}
    for name in _NAMES:
        F[name] = ti.field(ti.f64)
        fb.dense(ti.i, cap).place(F[name])
    F["nb"] = ti.field(ti.i32)
    fb.dense(ti.ij, (cap, 4)).place(F["nb"])
    F["pix"] = ti.field(ti.i32)
    fb.dense(ti.ij, (cap, 2)).place(F["pix"])
    F["sc"] = ti.field(ti.f64)
    fb.dense(ti.i, K.NSC).place(F["sc"])
    F["acc"] = ti.field(ti.f64)
    fb.dense(ti.i, K.NACC).place(F["acc"])
    F["bar"] = ti.field(ti.i32)
    fb.dense(ti.i, 2).place(F["bar"])
    for name in ("pq", "rr", "rz", "done"):
        F[name] = [ti.field(ti.f64) for _ in range(3)]
        for f in F[name]:
            fb.dense(ti.i, 1).place(f)
    F["tree"] = fb.finalize()
    F["cap"], F["key"], F["unroll"] = cap, key, unroll
    # on the CPU one thread: Taichi's parallel dispatch costs more than it gains at these sizes, the more so
    # on shared cores (bear, 40k pixels, 2 busy cores: 2.1 s on two threads, 1.1 s on one)
    # (CUDA: the CG's sums reduced per block in shared memory: float64 atomics on one address serialise)
    serial = ti.lang.impl.current_cfg().arch == ti.cpu
    F["kernels"] = K.make_bini(F, unroll, serial=serial)
    F["persistent"] = {}  # (nblocks, bd) -> the persistent IRLS kernel, built on first use
    F["verified"] = set()  # the (nblocks, bd) whose grid barrier passed on this GPU
    return F


def _release(F: dict) -> None:
    with _POOL_LOCK:
        _POOL.setdefault(F["key"], []).append(F)


def check_cuts(cuts, shape):
    """``cuts`` checked: ``None``, or a pair of (H, W) bool arrays (copied)."""
    if cuts is None:
        return None
    if not isinstance(cuts, (tuple, list)) or len(cuts) != 2:
        raise ValueError(f"cuts: expected None or a pair (cut_x, cut_y) of {shape} bool arrays, got {type(cuts).__name__}"
                         + (f" of length {len(cuts)}" if isinstance(cuts, (tuple, list)) else ""))
    out = []
    for name, c in zip(("cut_x", "cut_y"), cuts):
        a = np.asarray(c)
        if a.shape != shape or a.dtype != bool:
            raise ValueError(f"cuts: expected {name} an (H, W) = {shape} bool array, got shape {a.shape}, dtype {a.dtype}")
        out.append(a.copy())
    return tuple(out)


def _apply_cuts(nb, ii, jj, cut_x, cut_y):
    """Remove the cut edges from the neighbour table ``nb`` (right, left, down, up) of the pixels ``ii, jj``."""
    h, w = cut_x.shape
    nb[: ii.size, 0][cut_x[ii, jj]] = -1
    left = jj > 0
    nb[: ii.size, 1][left & cut_x[ii, np.maximum(jj - 1, 0)]] = -1
    nb[: ii.size, 2][cut_y[ii, jj]] = -1
    up = ii > 0
    nb[: ii.size, 3][up & cut_y[np.maximum(ii - 1, 0), jj]] = -1


class BilateralIntegrator(Stage):
    """BiNI over one set of valid pixels, with its device buffers.

    Args:
        valid: (H, W) bool pixels to integrate (at least 2).
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        config: :class:`BiniConfig` (``None`` = BiNI's defaults).
        device: ``"auto"``, ``"cpu"`` or ``"cuda:0"`` (Taichi).
        cuts: optional ``(cut_x, cut_y)``, two (H, W) bool arrays: ``cut_x[i, j]`` cuts the edge
            ``(i, j)-(i, j+1)``, ``cut_y[i, j]`` the edge ``(i, j)-(i+1, j)`` (entries on edges that leave the
            image or ``valid`` change nothing).  A cut edge is a missing neighbour on both sides, exactly as
            a mask border (BiNI's own treatment: the one-sided difference across it is 0 and its equation
            carries no coupling).  ``None``, or no edge cut, is BiNI unchanged (bitwise).
    """

    def __init__(self, valid, camera, config: BiniConfig | None = None, device: str | None = "auto", *,
                 cuts=None):
        v = np.asarray(valid, dtype=bool)
        if v.ndim != 2 or v.sum() < 2:
            raise ValueError(f"valid: expected an (H, W) bool mask with at least 2 pixels, got {v.shape}, "
                             f"{int(v.sum()) if v.ndim == 2 else 0} set")
        self.valid = v.copy()
        self.shape = v.shape
        self.camera = camera
        self.config = config if config is not None else BiniConfig()
        if not isinstance(self.config, BiniConfig):
            raise TypeError(f"config: expected BiniConfig, got {type(self.config).__name__}")
        self.device = device
        self.cuts = check_cuts(cuts, v.shape)
        self.n = int(v.sum())
        self._F = None
        self._state = None  # the uploaded map's start energy, then the solve's diagnostics

    # ------------------------------------------------------------------ buffers

    def _ensure(self):
        if self._F is not None:
            return self._F
        _taichi.init(self.device)
        n = self.n
        h, w = self.shape
        F = _acquire(n, self.config.check_every)
        # compact index (row-major) and neighbours, uploaded once per mask
        ii, jj = np.nonzero(self.valid)
        lab = -np.ones((h + 2, w + 2), dtype=np.int32)
        lab[ii + 1, jj + 1] = np.arange(n, dtype=np.int32)
        # one (n, 6) upload: the neighbours (right, left, down, up; -1 none) and the pixel's row, column
        idx = np.empty((n, 6), dtype=np.int32)
        idx[:, 0], idx[:, 1] = lab[ii + 1, jj + 2], lab[ii + 1, jj]
        idx[:, 2], idx[:, 3] = lab[ii + 2, jj + 1], lab[ii, jj + 1]
        if self.cuts is not None:
            _apply_cuts(idx, ii, jj, *self.cuts)
        idx[:, 4], idx[:, 5] = ii, jj
        F["kernels"]["load_index"](n, idx)
        self._ij = (ii, jj)
        self._F = F
        return F

    def close(self) -> None:
        """Give the device buffers back to the pool (they are reused by the next integrator)."""
        if self._F is not None:
            _release(self._F)
            self._F = None

    # ------------------------------------------------------------------ solve

    def upload(self, normals, u0=None) -> None:
        """Upload one normal map's coefficients and the start, and evaluate the start's energy.

        Args:
            normals: (H, W, 3) unit normals in the gpps frame (valid where ``self.valid``).
            u0: optional (H, W) starting ``u`` (depth, or log-depth); ``None`` = 0 as BiNI.
        """
        t0 = time.perf_counter()
        F = self._ensure()
        n = self.n
        ii, jj = self._ij
        # one (n, 5) upload: the coefficients and the start (the kernel also sets BiNI's weights 0.5 and
        # zeroes the scalars)
        a = np.empty((n, 5))
        for k, c in enumerate(bini_coefficients_at(normals, ii, jj, self.camera, self.shape)):
            a[:, k] = c
        a[:, 4] = 0.0 if u0 is None else np.asarray(u0, np.float64)[ii, jj]
        F["kernels"]["load"](n, a)
        F["kernels"]["energy"](n)
        self._state = {"e0": float(F["sc"][K.ENERGY]), "t0": t0, "t1": time.perf_counter()}

    def step(self, progress=None) -> None:
        """BiNI's IRLS from the uploaded start: inner Jacobi-PCG solves on the device, one host check per
        launch, stop on the relative energy change.

        Args:
            progress: optional ``progress(done, total, message)`` per IRLS iteration.
        """
        if self._state is None:
            raise ValueError("normals: expected upload(normals) before step(), got nothing uploaded")
        cfg = self.config
        n = self.n
        e_old = self._state["e0"]
        tol2 = cfg.cg_tol ** 2
        iterate = self._iteration_persistent if self._persistent_launch() else self._iteration_tasks
        energies = []
        converged = False
        outer = 0
        total = 0
        res = float("nan")
        for it in range(cfg.max_iter):
            out = iterate(n, tol2)
            while out is None:  # the persistent grid did not fit (state restored): a smaller one, then the tasks
                iterate = self._iteration_persistent if self._persistent_launch() else self._iteration_tasks
                out = iterate(n, tol2)
            e, rr, bb, its = out
            total += its
            res = float(np.sqrt(rr / bb)) if bb > 0 else 0.0
            energies.append(e)
            outer = it + 1
            rel = abs(e - e_old) / e_old if e_old > 0 else 0.0
            if progress is not None:
                progress(outer, cfg.max_iter, f"BiNI energy {e:.4g}, relative change {rel:.2e}")
            if rel < cfg.tol:
                converged = True
                break
            e_old = e
        self._state.update(energies=energies, converged=converged, outer=outer, res=res, total_cg=total,
                           t2=time.perf_counter())

    def _iteration_tasks(self, n, tol2) -> tuple[float, float, float, int]:
        """One IRLS iteration as per-phase launches (system, CG launches until the done flag, reweighting):
        ``(energy, last |r|^2, |b|^2, CG iterations)``."""
        cfg = self.config
        F = self._F
        kn = F["kernels"]
        last = (F["unroll"] - 1) % 3
        kn["begin"](n)
        while True:
            kn["cg"](n, tol2, cfg.cg_max_iter)
            if F["done"][last][0] != 0:  # the only sync of the inner solve: once per launch
                break
        kn["reweight"](n, float(cfg.k))
        sc = F["sc"].to_numpy()
        its = int(sc[K.ITS])
        return float(sc[K.ENERGY]), float(F["rr"][(its - 1) % 3][0]), float(sc[K.BB]), its

    # ------------------------------------------------------------------ the persistent launch

    def _persistent_launch(self) -> bool:
        """Whether :meth:`step` runs the persistent IRLS kernel (``config.launch``; see :class:`BiniConfig`)."""
        launch = self.config.launch
        if launch == "tasks" or getattr(self, "_bps", 1) == 0:  # (0: the GPU held no persistent grid)
            return False
        return launch == "persistent" or ti.lang.impl.current_cfg().arch == ti.cuda

    def _grid(self) -> tuple[int, int]:
        """(blocks, threads per block) of the persistent task: ``blocks_per_sm`` (or what the GPU held)
        blocks of :data:`gpps.kernels.block_sum.BLOCK` threads per multiprocessor, no more than the pixels
        need; off CUDA one thread."""
        if ti.lang.impl.current_cfg().arch != ti.cuda:
            return 1, 1
        from gpps.kernels.block_sum import BLOCK
        bps = getattr(self, "_bps", self.config.blocks_per_sm)
        sms = int(warp().get_device("cuda:0").sm_count)
        return max(1, min(sms * bps, -(-self.n // BLOCK))), BLOCK

    def _kernel(self, grid):
        F = self._F
        kern = F["persistent"].get(grid)
        if kern is None:
            kern = F["persistent"][grid] = K.make_irls_persistent(F, *grid, cuda=grid[1] > 1)
        return kern

    def _launch_checked(self, n, tol2, maxit, k) -> bool:
        """One persistent IRLS iteration; on its grid's first launch the barrier's timeout flag is read and,
        if some block never became resident, the state is restored and False returned (the caller
        retries with the new grid: half the blocks per multiprocessor, then the tasks)."""
        F = self._F
        grid = self._grid()
        kern = self._kernel(grid)
        if grid in F["verified"] or grid == (1, 1):
            kern(n, tol2, maxit, k)
            return True
        saved = {name: F[name].to_numpy() for name in ("x", "wj", "wi")}
        F["bar"].fill(0)
        kern(n, tol2, maxit, k)
        if int(F["bar"].to_numpy()[1]) == 0:
            F["verified"].add(grid)
            return True
        for name, a in saved.items():
            F[name].from_numpy(a)
        F["bar"].fill(0)
        bps = getattr(self, "_bps", self.config.blocks_per_sm)
        if bps == 1:
            warnings.warn("BilateralIntegrator: the GPU cannot hold the persistent kernel's blocks; using the "
                          "tasks launch", RuntimeWarning, stacklevel=4)
            self._bps = 0
        else:
            self._bps = bps // 2
        return False

    def _iteration_persistent(self, n, tol2) -> tuple[float, float, float, int] | None:
        """One IRLS iteration as one persistent launch and one read of its sums, as
        :meth:`_iteration_tasks` returns it; None when the grid did not fit (see :meth:`_launch_checked`)."""
        cfg = self.config
        if not self._launch_checked(n, tol2, cfg.cg_max_iter, float(cfg.k)):
            return None
        acc = self._F["acc"].to_numpy()
        its = int(acc[K.A_ITS])
        rr = float(acc[K.A_RR + (its - 1) % 3]) if its > 0 else float("nan")
        return float(acc[K.A_E]), rr, float(acc[K.A_BB]), its

    def fetch(self) -> BiniResult:
        """The solution and diagnostics of the last :meth:`step` (:class:`BiniResult`)."""
        st = self._state
        if st is None or "t2" not in st:
            raise ValueError("normals: expected upload(normals) and step() before fetch(), got no solve")
        ii, jj = self._ij
        u = np.zeros(self.shape)
        wjm = np.full(self.shape, 0.5)
        wim = np.full(self.shape, 0.5)
        got = np.empty((self.n, 3))
        self._F["kernels"]["gather"](self.n, got)  # one fetch: x, wj, wi
        u[ii, jj] = got[:, 0]
        wjm[ii, jj] = got[:, 1]
        wim[ii, jj] = got[:, 2]
        t3 = time.perf_counter()
        return BiniResult(u=u, outer_iterations=st["outer"], cg_iterations=st["total_cg"], energy=st["energies"],
                          converged=st["converged"], residual=st["res"], wj=wjm, wi=wim,
                          timings={"upload": st["t1"] - st["t0"], "solve": st["t2"] - st["t1"], "fetch": t3 - st["t2"]})

    def run(self, normals, u0=None, *, progress=None) -> BiniResult:
        """:meth:`upload`, :meth:`step` (with ``progress``) and :meth:`fetch`: BiNI on one normal map."""
        self.upload(normals, u0)
        self.step(progress)
        return self.fetch()
