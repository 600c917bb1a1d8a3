"""Normal integration stage: normals to depth by variational (Poisson) integration.

Minimises (4.20), ``F(u) = sum over mask edges of w_e (u_b - u_a - t_e)^2``,
whose normal equations are the masked 5-point Laplacian with natural (Neumann)
boundary conditions, ``A u = b = -div(t)``, the discrete ``Laplace(u) = div(g)``.

* Orthographic camera: ``u`` is the depth ``d`` (scene units); per-pixel steps
  ``du/dj = s n_x/n_z``, ``du/di = -s n_y/n_z`` (``s`` = pixel size; rows go
  down, ``d = -z``).
* Perspective camera (PPN, (3.2)-(3.3), as BiNI): ``u = log d``; with
  ``m = n . ((j-cx)/fx, -(i-cy)/fy, -1)`` (< 0 for visible normals),
  ``du/dj = -n_x/(fx m)`` and ``du/di = n_y/(fy m)``.  Depth ``exp(u)`` is
  known up to one scale factor per connected component.

An edge between pixels ``a`` and ``b = a + step`` collects the one-sided
terms of both pixels as in BiNI (Cao et al., ECCV 2022): weight
``w_e = c_a w+_a + c_b w-_b``, target ``t_e = (c_a w+_a g_a + c_b w-_b g_b)/w_e``.
Plain Poisson integration has ``c = 1``, ``w+- = 1/2`` (``w_e = 1``, ``t_e`` the
mean step).  ``weighting="normal"`` takes BiNI's ``c = N_z^2``.
``bilateral=True`` is BiNI itself, run on the device by
:class:`gpps.pipeline.integration_bini.BilateralIntegrator` (iteratively
reweighted least squares with BiNI's inner Jacobi-PCG and stopping rule):
the mode for measured normal maps, which have depth discontinuities.

Each connected component (4-neighbourhood) of the valid mask is integrated up
to a constant, fixed afterwards: mean 0 (orthographic depth / perspective
log-depth) or, with ``reference_depth``, mean depth = ``reference_depth``.

Solvers: ``multigrid`` (Taichi; conjugate gradient preconditioned by a
geometric multigrid V-cycle on coarsened masks), ``jacobi`` (Taichi, damped
Jacobi, the reference and smoother), ``direct`` (scipy sparse LU, pinned per
component) and ``dct`` (scipy, Simchony et al.'s DCT solution, full
rectangles with uniform weights only).

Length: the config (its modes documented in place), the result and one stage with its four solvers; the
scipy solvers and the system algebra live in :mod:`gpps.host.poisson`, BiNI in
:mod:`gpps.pipeline.integration_bini`; what is left is one solve's state, kept together.
"""

from __future__ import annotations

import math
import threading
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Literal

import numpy as np
from scipy import ndimage

from gpps import _taichi
from gpps._check import GppsWarning, _source, as_array, check_bool, check_choices, check_number
from gpps.camera import Orthographic, Perspective
from gpps.host.creases import stitch_cut_pieces
from gpps.host.poisson import (
    build_levels,
    coarsest_pinv,
    component_means,
    component_means_at,
    curl_edge_weights,
    diagonal,
    divergence_rhs,
    edge_system,
    level_shapes,
    normal_equation_residual,
    pixel_gradients,
    robust_edge_weights,
    solve_dct,
    solve_direct,
)
from gpps.kernels import poisson as K
from gpps.kernels import poisson_persistent as KP
from gpps.names import CutStitchName, LaunchName
from gpps.pipeline.integration_bini import BilateralIntegrator, BiniConfig, check_cuts
from gpps.pipeline.stage import Stage

# the largest log-depth range within one part of a perspective depth before Integrator.fetch warns: a depth ratio of
# e^14 ~ 1.2e6 (a photometric-stereo object spans a ratio of a few; beyond this the normals were not integrable, e.g.
# a fit gone astray; the Mitsuba dev set's ridges_roughconductor under the plastic model overflowed exp at e^709)
_MAX_LOG_SPAN = 14.0

def warn_log_depth_span(span: float) -> None:
    """A :class:`GppsWarning` naming the depth when a perspective depth's log-depth ``span`` within one part (its
    largest ``max - min``) is beyond :data:`_MAX_LOG_SPAN` or not finite (the host path and the device one)."""
    if not np.isfinite(span) or span > _MAX_LOG_SPAN:
        warnings.warn(f"depth: the integrated depth spans a factor of e^{span:.3g} within one part: the normals are "
                      f"not integrable there (expected a ratio below e^{_MAX_LOG_SPAN:g}); the depth is unreliable",
                      GppsWarning, stacklevel=3)


#: ``|r|^2 / |b|^2`` below which a float32 multigrid CG is at its precision floor (a relative residual of 1e-4, a
#: few times float32's epsilon times sqrt(pixels) at the sizes gpps solves): there a check that does not cut
#: ``|r|^2`` by 20 % stops the CG.  On CUDA the float32 V-cycle is not the same operator from one application to
#: the next (the order of its atomic sums), and CG at the floor can be thrown back up by orders of magnitude
#: before it comes down again (256^2 perspective, n_z^2 weights: 1.3e-5 at 14 iterations, 7.7e-3 at 20, 5.7e-6 at
#: 30; perf/probe_pcg_floor.py): that rise stops it too, with the iterate of the lowest residual checked.
_FLOOR_RR = 1e-8

# device fields of closed integrators, by (Taichi device, H, W, coarsest, dtype): Taichi compiles its
# kernels for each set of fields, so reusing them skips the compilation (BiNI's stage pools likewise)
_POOL: dict = {}
_POOL_LOCK = threading.Lock()

__all__ = ["IntegratorConfig", "IntegrationResult", "Integrator", "Solver"]

Solver = Literal["multigrid", "jacobi", "direct", "dct"]
Weighting = Literal["uniform", "normal"]
Robust = Literal["none", "cauchy", "curl"]
DType = Literal["float32", "float64"]
CgSums = Literal["auto", "block", "atomic"]
Launch = Literal["auto", "persistent", "fused", "per-level"]
Progress = Callable[[float, float, str], None]


# the coarse levels' edge weights over the Galerkin sums of piecewise-constant aggregation (coarse_alpha)
_WEIGHTED_ALPHA = 2.0 / 3.0


def coarse_alpha(uniform: bool, reweighted: bool) -> float:
    """``alpha`` of :func:`gpps.host.poisson.build_levels`: each coarse level's edge weights are ``alpha`` times the
    sums of the fine weights that cross its edges (``alpha = 1``: the Galerkin operator of piecewise-constant
    aggregation).  That Galerkin coarse correction is too weak for smooth error (aggregation's coarse operator is
    about twice too stiff), so the correction is scaled by ``1 / alpha``:

    * uniform weights: ``1/2``, the Laplacian rediscretised at twice the spacing;
    * weighted systems (BiNI's ``N_z^2`` weighting, RON's perspective rounds): ``2/3``, a correction scaled by 1.5.
      A two-grid correction scaled by ``w`` keeps the preconditioner positive definite for ``w < 2``; at ``w = 2``
      (``1/2``) the ``N_z^2``-weighted perspective sphere, figure and rims diverged (256^2 / 128^2, float32), at 1.5
      none of the 12 surfaces of the smooth and discontinuity suites did, and the multigrid CG took 12-16
      iterations instead of 24-34 for the same solution (1e-6 of the depth range);
    * re-weighted solves (``robust`` IRLS): ``1``: their result follows every inner solve's path (a 1.5 scale
      moved the Cauchy solutions of the discontinuity suite by up to 0.3 of the range) and saved few iterations.
    """
    if uniform:
        return 0.5
    return 1.0 if reweighted else _WEIGHTED_ALPHA


@dataclass(frozen=True)
class IntegratorConfig:
    """Options of :class:`Integrator`.

    Attributes:
        solver: see the module docstring.
        tol: relative residual ``|b - A u| / |b|`` of the normal equations to stop at.
        max_iter: conjugate-gradient iterations (multigrid) or Jacobi sweeps;
            ``None`` = 500 / 200000.
        weighting: ``"uniform"`` (plain Poisson) or ``"normal"`` (BiNI's N_z^2 confidence).
        bilateral: bilateral normal integration (BiNI, Cao et al. ECCV 2022) on
            the device (:mod:`gpps.pipeline.integration_bini`): BiNI's
            multiplied one-sided equations, IRLS weights ``sigmoid(k ...)``,
            inner Jacobi-PCG to ``bilateral_inner_tol`` warm-started across
            iterations, stop on the relative energy change.  ``solver``,
            ``tol``, ``max_iter``, ``weighting``, ``min_nz``, ``dtype`` and the
            multigrid options apply to the plain Poisson solve only (BiNI runs in
            float64 with its own equations); ``robust`` must be ``"none"``.
        bilateral_k: BiNI's sigmoid sharpness ``k`` (BiNI's default 2).
        bilateral_max_iter: IRLS iterations at most (BiNI's default 150).
        bilateral_tol: relative energy change that stops the IRLS (BiNI's 1e-4).
        bilateral_inner_tol: relative residual of each inner CG solve (BiNI's 1e-3).
        bilateral_cg_max_iter: CG iterations per inner solve at most (BiNI's 5000).
        bilateral_launch: how BiNI's IRLS iterations are launched (:class:`BiniConfig`'s ``launch``):
            ``"auto"`` (one persistent task an iteration on CUDA, tasks on the CPU), ``"tasks"`` or
            ``"persistent"``; the same iterations either way.
        cut_stitch: with ``run(cuts=...)``: how the cut pieces get their constants, ``"mid"`` (mid-normal
            continuity) or ``"bini"`` (BiNI's bilateral energy of the cut edges, with ``bilateral_k`` and
            ``bilateral_tol``; :func:`gpps.host.creases.stitch_cut_pieces`).
        robust: ``"cauchy"``: a robust loss on the edge residuals of (4.20)
            by iteratively reweighted least squares: each edge's weight is
            multiplied by ``1 / (1 + (r / sigma)^2)``, ``r = u_q - u_p - t`` from
            the previous solution, ``sigma = robust_scale * 1.4826 * MAD(r)``
            re-estimated every round, so that a few wrong normals (grazing
            rims, rendering or acquisition artefacts, small depth jumps) stop
            bending the whole surface as they do under the plain quadratic
            loss.  Combines with ``weighting`` (not with ``bilateral``).
            ``"curl"``: each edge is weighted by a Cauchy function of the
            integrability defect (curl) of the targets around its two 2x2
            pixel loops (:func:`curl_edge_weights`): a wrong normal or a
            depth jump makes the loops through its edges fail to close, a
            smooth surface closes them to discretisation order.  The weights
            come from the data alone, so the problem stays convex and is one
            weighted solve (no IRLS, no local minima).  It scored within 1.2x
            of BiNI on the six shared DiLiGenT maps but 7x on a held-back one
            with many depth discontinuities: for measured normal maps use
            ``bilateral`` (perf/integration_diligent.py compares the modes).
            ``"none"``: plain least squares.
        robust_scale: ``sigma`` in robust standard deviations (``1.4826 MAD``)
            of the edge residuals (``"cauchy"``) or of the loop curls (``"curl"``).
        robust_iterations: re-weighted solves after the first (``"cauchy"``).
        min_nz: floor on ``n_z`` (orthographic) or ``-m`` (perspective) that
            bounds the slopes of grazing normals.
        dtype: device precision of the Taichi solvers.
        smooth_pairs: Jacobi sweep pairs before and after each coarse correction.
        omega: Jacobi damping.
        check_every: iterations between residual checks (the only host syncs).
        coarsest: coarsen while ``max(h, w) > coarsest``.
        cg_sums: how the multigrid CG's float64 dot products are summed on the device
            (:mod:`gpps.kernels.poisson`): ``"block"`` tree-reduces each sum per CUDA block in shared
            memory with one atomic a block (CUDA only); ``"atomic"`` adds every pixel's term into the
            scalar (Taichi's CPU threads keep these sums thread-local, but on CUDA it is one float64
            atomic a pixel on one address, serialised); ``"auto"``: ``"block"`` on CUDA, ``"atomic"``
            on the CPU.  Both give the same CG up to the order of the float64 additions.
        launch: how the multigrid PCG is launched: ``"persistent"``: the start, every iteration and the
            stopping test in one launch of one persistent task whose phases meet at grid barriers
            (:mod:`gpps.kernels.poisson_persistent`; the host reads the result once; on the CPU it runs as one
            thread, for tests); ``"fused"``: one Taichi launch an iteration (cg_step, the V-cycle over every
            level, cg_direction; :func:`gpps.kernels.poisson.pcg_iteration`) and one for the start, the host
            reading ``|r|^2`` every ``check_every`` iterations; ``"per-level"``: one launch per step and level
            (~13 an iteration); ``"auto"``: persistent on CUDA (``persistent_blocks`` resident blocks of
            128 threads per multiprocessor; a GPU that cannot hold them falls back to fused with a
            warning), fused on the CPU.  The same arithmetic in the same order (the persistent task sums
            its dot products in another order); fused saves Taichi's host time per launch (60-100 us a call
            on an H100's host, more than the GPU's 0.6 ms iteration at 256^2 spends in 13 calls), the
            persistent task its host time per task (about 40 a fused iteration).  Measured on an H200
            (perf/results/s24): a 256^2 solve of 14 iterations took 1.9 ms persistent against 6.1 ms for the
            fused launches, but inside ``gpps.reconstruct`` the integration stage gained 0.7 ms and the whole
            call nothing measurable, while the persistent kernel costs a new frame size's first call 7.7 s
            more compilation: so ``"fused"`` stays the default, ``"persistent"`` is for many solves of one
            size where the host's launches are the cost.
        persistent_blocks: resident blocks per multiprocessor of the persistent launch (halved down to 1
            when the GPU cannot hold them, then fused).
    """

    solver: Solver = "multigrid"
    tol: float = 1e-5
    max_iter: int | None = None
    weighting: Weighting = "uniform"
    bilateral: bool = False
    bilateral_k: float = 2.0
    bilateral_max_iter: int = 150
    bilateral_tol: float = 1e-4
    bilateral_inner_tol: float = 1e-3
    bilateral_cg_max_iter: int = 5000
    bilateral_launch: LaunchName = "auto"
    cut_stitch: CutStitchName = "mid"
    robust: Robust = "none"
    robust_scale: float = 2.0
    robust_iterations: int = 8
    min_nz: float = 1e-3
    dtype: DType = "float32"
    smooth_pairs: int = 1
    omega: float = 0.8
    check_every: int = 2
    coarsest: int = 8
    cg_sums: CgSums = "auto"
    launch: Launch = "fused"
    persistent_blocks: int = 4

    def __post_init__(self):
        check_choices(self)
        if not (isinstance(self.tol, (int, float)) and 0 < self.tol < 1):
            raise ValueError(f"tol: expected a number in (0, 1), got {self.tol!r}")
        if self.max_iter is not None and (not isinstance(self.max_iter, int) or self.max_iter < 1):
            raise ValueError(f"max_iter: expected an integer >= 1 or None, got {self.max_iter!r}")
        check_bool("bilateral", self.bilateral)
        check_number("omega", self.omega, lo=0.0, hi=1.0, lo_open=True)
        check_number("min_nz", self.min_nz, lo=0.0, hi=1.0, lo_open=True)
        if self.min_nz >= 1:
            raise ValueError(f"min_nz: expected 0 < min_nz < 1, got {self.min_nz!r}")
        if not (isinstance(self.robust_scale, (int, float)) and not isinstance(self.robust_scale, bool)
                and 0 < self.robust_scale < float("inf")):
            raise ValueError(f"robust_scale: expected a finite number > 0, got {self.robust_scale!r}")
        if not isinstance(self.robust_iterations, int) or isinstance(self.robust_iterations, bool) \
                or self.robust_iterations < 0:
            raise ValueError(f"robust_iterations: expected an integer >= 0, got {self.robust_iterations!r}")
        for name in ("smooth_pairs", "check_every", "bilateral_max_iter", "bilateral_cg_max_iter", "coarsest",
                     "persistent_blocks"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected an integer >= 1, got {v!r}")
        if self.coarsest > 16:
            raise ValueError(f"coarsest: expected <= 16, got {self.coarsest}")
        check_number("bilateral_k", self.bilateral_k, lo=0.0, lo_open=True)
        for name in ("bilateral_tol", "bilateral_inner_tol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < v < 1):
                raise ValueError(f"{name}: expected a number in (0, 1), got {v!r}")
        if not isinstance(self.bilateral, bool):
            raise ValueError(f"bilateral: expected True or False, got {self.bilateral!r}")
        if self.bilateral and self.robust != "none":
            raise ValueError(f"robust: expected 'none' with bilateral=True (BiNI's own weights handle "
                             f"discontinuities), got {self.robust!r}")

    @property
    def iterations_cap(self) -> int:
        if self.max_iter is not None:
            return self.max_iter
        return 200000 if self.solver == "jacobi" else 500


@dataclass
class IntegrationResult:
    """Output of an integration.

    Attributes:
        depth: (H, W) float32 depth ``d = -z > 0`` (orthographic without a
            reference: relative depth with mean 0 per component), 0 outside ``mask``.
        mask: (H, W) bool, pixels that were integrated (input mask minus invalid normals).
        iterations: solver iterations (bilateral: CG iterations summed over the IRLS iterations).
        residual: final relative residual ``|b - A u| / |b|`` of the normal
            equations, recomputed on the host in float64 from the returned
            solution (in float32 this has a floor near ``1e-7 |u| / |b|``).
        converged: whether the solver's own residual reached ``tol``.
        n_invalid: mask pixels dropped for NaN, zero-length or back-facing normals.
        n_components: connected components integrated independently.
        outer_iterations: bilateral re-weighting iterations (0 without ``bilateral``).
        energy: bilateral only: BiNI's energy after each IRLS iteration.
        timings: seconds: ``setup``, ``rhs``, ``solve``, ``post``, ``total``.
        solver: the solver used.
        log_depth: perspective only: (H, W) float64 ``log d`` before scaling (0 outside).
        solver_residual: the residual the solver itself measured (device
            precision; the CG recurrence for ``multigrid``).
    """

    depth: np.ndarray
    mask: np.ndarray
    iterations: int
    residual: float
    converged: bool
    n_invalid: int
    n_components: int
    outer_iterations: int = 0
    timings: dict = field(default_factory=dict)
    solver: str = "multigrid"
    log_depth: np.ndarray | None = None
    solver_residual: float = float("nan")
    energy: list | None = None


# ============================================================================ numpy assembly


# ============================================================================ the stage


class Integrator(Stage):
    """Integrates normal maps over one mask with one camera.

    Configured once (mask, camera, options); Taichi fields are allocated once
    at the first Taichi solve and reused by every later call, so a stream of
    normal maps (with the previous depth as a warm start) costs only the solve.

    Args:
        mask: (H, W) bool (or 0/nonzero) pixels to integrate; at least 2.
        camera: :class:`gpps.camera.Orthographic` or
            :class:`gpps.camera.Perspective`; ``None`` = orthographic, pixel size 1.
        config: :class:`IntegratorConfig` (``None`` = defaults).
        device: ``"auto"``, ``"cpu"`` or ``"cuda:0"`` for the Taichi solvers.
    """

    def __init__(self, mask, camera=None, config: IntegratorConfig | None = None, device: str | None = "auto"):
        m = np.asarray(mask)
        if m.ndim != 2:
            raise ValueError(f"mask: expected (H, W), got shape {m.shape}")
        if m.dtype != bool:
            if not np.issubdtype(m.dtype, np.number):
                raise ValueError(f"mask: expected a boolean or numeric (H, W) array, got dtype {m.dtype}")
            m = np.nan_to_num(m.astype(np.float64)) != 0
        if min(m.shape) < 1 or m.sum() < 2:
            raise ValueError(f"mask: expected at least 2 pixels set, got {int(m.sum())} of shape {m.shape}")
        self.mask = m.copy()
        self.shape = m.shape
        if camera is None:
            camera = Orthographic(1.0)
        if not isinstance(camera, (Orthographic, Perspective)):
            raise TypeError(f"camera: expected gpps.camera.Orthographic or Perspective, got {type(camera).__name__}")
        self.camera = camera
        self.config = config if config is not None else IntegratorConfig()
        if not isinstance(self.config, IntegratorConfig):
            raise TypeError(f"config: expected IntegratorConfig, got {type(self.config).__name__}")
        self.device = device
        self._dev = None  # Taichi state, created lazily
        self._bini_stage = None  # device BiNI stage (bilateral), created lazily
        self._bini_key = None
        self._levels_key = None
        self._labels_key = None
        self._mask_ij = None  # the mask's (rows, columns), computed on first use
        self._job = None  # the uploaded normal map's system, then its solution

    # ------------------------------------------------------------------ checks

    def _check_normals(self, normals):
        """``(unit normals (H, W, 3) float64, valid (H, W) bool, invalid count)``: the normals normalised inside
        the mask (0 outside it, and at the non-finite or zero-length ones), ``valid`` the mask's finite, non-zero,
        camera-facing normals.  The arithmetic runs on the mask's pixels only (a masked map is often a small part
        of its frame)."""
        n = _source("normals", normals)  # (complex, bool, object, strings: a TypeError, never cast)
        h, w = self.shape
        if n.ndim != 3 or n.shape != (h, w, 3):
            raise ValueError(f"normals: expected shape (H, W, 3) = ({h}, {w}, 3) matching the mask, got {n.shape}")
        ii, jj = self._mask_pixels()
        v = n[ii, jj].astype(np.float64)
        with np.errstate(all="ignore"):
            norm = np.linalg.norm(v, axis=-1)
            ok = np.isfinite(norm) & (norm > 1e-6)
            v = np.where(ok[:, None], v / np.where(ok, norm, 1.0)[:, None], 0.0)
        if self.camera.is_perspective:
            cx, cy = self.camera.principal_point(self.shape)
            facing = (v[:, 0] * (jj.astype(np.float64) - cx) / self.camera.fx
                      - v[:, 1] * (ii.astype(np.float64) - cy) / self.camera.fy - v[:, 2] < 0)
        else:
            facing = v[:, 2] > 0
        out = np.zeros((h, w, 3))
        out[ii, jj] = v
        valid = np.zeros((h, w), bool)
        valid[ii, jj] = ok & facing
        n_valid = int(np.count_nonzero(valid))
        n_invalid = int(ii.size - n_valid)
        if n_valid < 2:
            raise ValueError(
                f"normals: expected at least 2 finite, non-zero, camera-facing normals inside the mask, "
                f"got {n_valid} ({n_invalid} of {ii.size} invalid)"
            )
        return out, valid, n_invalid

    def _mask_pixels(self):
        """The mask's (rows, columns), row-major (computed once)."""
        if self._mask_ij is None:
            self._mask_ij = np.nonzero(self.mask)
        return self._mask_ij

    def _check_warm(self, warm_start):
        if warm_start is None:
            return None
        d = as_array("warm_start", warm_start, dtype=np.float64, finite=False)  # (NaN: left out, as documented)
        if d.shape != self.shape:
            raise ValueError(f"warm_start: expected depth of shape (H, W) = {self.shape}, got {d.shape}")
        return d

    # ------------------------------------------------------------------ components

    def _components(self, valid):
        key = valid.tobytes()
        if self._labels_key != key:
            lab, n = ndimage.label(valid)
            self._labels, self._ncomp, self._labels_key = lab, n, key
        return self._labels, self._ncomp

    def _comp_mean(self, a, valid):
        return component_means(a, valid, *self._components(valid))

    # ------------------------------------------------------------------ main entry

    def upload(self, normals, warm_start=None, *, reference_depth: float | None = None, cuts=None) -> None:
        """Check one normal map and set up its system (gradients, weights, warm start) for :meth:`step`.

        Args:
            normals: (H, W, 3) normals in the gpps frame (need not be unit; NaN,
                zero-length and back-facing ones inside the mask are dropped and
                counted in ``n_invalid``).
            warm_start: optional (H, W) depth to start from (e.g. the previous
                frame's); only its shape up to a constant per component matters.
            reference_depth: if given (> 0), each component's mean depth is set
                to it; otherwise orthographic depth has mean 0 and perspective
                log-depth has mean 0 (depth ~ 1) per component.
            cuts: bilateral only: optional ``(cut_x, cut_y)`` (H, W) bool edges to cut
                (:class:`~gpps.pipeline.integration_bini.BilateralIntegrator`); BiNI then
                integrates the pieces they separate with the cut edges as missing
                neighbours, and the pieces' constants are set from the cut edges'
                mid-normal targets (:func:`gpps.host.creases.stitch_cut_pieces`).
                ``None`` or nothing cut: BiNI unchanged.

        ``run(normals, warm_start, reference_depth=..., progress=...)`` integrates and returns the
        :class:`IntegrationResult` in one call.
        """
        self._check_open()
        t0 = time.perf_counter()
        cfg = self.config
        if reference_depth is not None:
            reference_depth = check_number("reference_depth", reference_depth)  # (a string or an array: TypeError)
            if not reference_depth > 0:
                raise ValueError(f"reference_depth: expected a finite number > 0, got {reference_depth!r}")
        n, valid, n_invalid = self._check_normals(normals)
        warm = self._check_warm(warm_start)
        if cuts is not None:
            if not cfg.bilateral:
                raise ValueError("cuts: expected None without bilateral=True (only BiNI takes cut edges), got cuts")
            cuts = check_cuts(cuts, self.shape)
        system = None
        if not cfg.bilateral:  # (BiNI forms its own system from the normals on the device)
            gj, gi, nzj, nzi = pixel_gradients(n, valid, self.camera, cfg.min_nz)
            cj = ci = None
            if cfg.weighting == "normal":
                scale = float(np.mean(nzj[valid] ** 2))
                cj, ci = nzj ** 2 / scale, nzi ** 2 / scale
            system = (gj, gi, nzj, nzi, cj, ci)
        u0 = None
        if warm is not None:
            if self.camera.is_perspective:
                with np.errstate(all="ignore"):
                    u0 = np.where(valid & (warm > 0) & np.isfinite(warm), np.log(np.abs(warm) + 1e-300), 0.0)
            else:
                u0 = np.where(valid & np.isfinite(warm), warm, 0.0)
            u0 = np.where(valid, u0 - self._comp_mean(u0, valid), 0.0)
        timings = {"setup": time.perf_counter() - t0}
        self._job = {"t0": t0, "n": n, "valid": valid, "n_invalid": n_invalid, "u0": u0, "timings": timings,
                     "reference_depth": reference_depth, "system": system, "cuts": cuts}

    def step(self, progress: Progress | None = None) -> None:
        """Solve the uploaded system (BiNI's IRLS on the device, or the plain Poisson solve).

        Args:
            progress: optional ``progress(done, total, message)``.
        """
        self._check_open()
        job = self._job
        if job is None:
            raise ValueError("normals: expected upload(normals) before step(), got nothing uploaded")
        cfg = self.config
        n, valid, u0, timings = job["n"], job["valid"], job["u0"], job["timings"]
        outer = 0
        total_it = 0
        energy_log = None
        if cfg.bilateral:
            cuts = job["cuts"]
            bres = self._bini(valid, cuts).run(n, u0, progress=progress)
            u = bres.u
            if cuts is not None:
                t_s = time.perf_counter()
                u, _, _ = stitch_cut_pieces(u, n, valid, self.camera, *cuts, min_nz=cfg.min_nz, mode=cfg.cut_stitch,
                                            k=float(cfg.bilateral_k), tol=cfg.bilateral_tol)
                timings["stitch"] = time.perf_counter() - t_s
            total_it, outer, energy_log = bres.cg_iterations, bres.outer_iterations, bres.energy
            true_res = solver_res = bres.residual
            converged = bres.converged
            for key, v in bres.timings.items():
                timings[key] = timings.get(key, 0.0) + v
        else:
            u, total_it, outer, true_res, solver_res = self._poisson(n, valid, *job["system"], u0, timings, progress)
            converged = bool(solver_res <= cfg.tol)
        job.update(u=u, total_it=total_it, outer=outer, energy=energy_log, true_res=true_res, solver_res=solver_res,
                   converged=converged, progress=progress)

    def fetch(self) -> IntegrationResult:
        """The depth of the last :meth:`step` with its diagnostics (:class:`IntegrationResult`)."""
        self._check_open()
        job = self._job
        if job is None or "u" not in job:
            raise ValueError("normals: expected upload(normals) and step() before fetch(), got no solve")
        cfg = self.config
        valid, timings, reference_depth, t0 = job["valid"], job["timings"], job["reference_depth"], job["t0"]
        u, true_res = job["u"], job["true_res"]
        t2 = time.perf_counter()
        # on the valid pixels only (row-major, as the full-frame sums: the same values bit for bit)
        labels, ncomp = self._components(valid)
        vi, vj = np.nonzero(valid)
        lab = labels[vi, vj]
        uv = u[vi, vj]
        uv = uv - component_means_at(uv, lab, ncomp)
        u = np.zeros(self.shape)
        u[vi, vj] = uv
        log_depth = None
        if self.camera.is_perspective:
            log_depth = u
            top = np.full(ncomp + 1, -np.inf)
            np.maximum.at(top, lab, uv)
            top = top[lab]
            warn_log_depth_span(float(np.max(top - uv)) if uv.size else 0.0)
            if reference_depth is not None:
                # exp(u - max per part), scaled to the reference mean: no overflow whatever the log-depth's range
                dv = np.exp(uv - top)
                dv = dv * (reference_depth / component_means_at(dv, lab, ncomp))
            else:
                with np.errstate(over="ignore"):
                    dv = np.exp(uv)
        else:
            dv = uv + (reference_depth if reference_depth is not None else 0.0)
        depth = np.zeros(self.shape, np.float32)
        depth[vi, vj] = dv
        timings["post"] = time.perf_counter() - t2
        timings["total"] = time.perf_counter() - t0
        if job["progress"] is not None:
            job["progress"](1, 1, f"residual {true_res:.2e}")
        return IntegrationResult(
            depth=depth, mask=valid, iterations=job["total_it"], residual=true_res, solver_residual=job["solver_res"],
            converged=job["converged"], n_invalid=job["n_invalid"], n_components=int(ncomp),
            outer_iterations=job["outer"], timings=timings, solver="bini" if cfg.bilateral else cfg.solver,
            log_depth=log_depth, energy=job["energy"],
        )

    def run(self, normals, warm_start=None, *, reference_depth: float | None = None,
            progress: Progress | None = None, cuts=None) -> IntegrationResult:
        """:meth:`upload` (with ``cuts``), :meth:`step` (with ``progress``) and :meth:`fetch`: one normal map to
        depth."""
        self.upload(normals, warm_start, reference_depth=reference_depth, cuts=cuts)
        self.step(progress)
        return self.fetch()

    # ------------------------------------------------------------------ solvers

    def _bini(self, valid, cuts=None):
        """The device BiNI stage for ``valid`` and ``cuts`` (kept while both stay the same)."""

        key = valid.tobytes() + (b"" if cuts is None else b"cuts" + cuts[0].tobytes() + cuts[1].tobytes())
        if getattr(self, "_bini_key", None) != key:
            if getattr(self, "_bini_stage", None) is not None:
                self._bini_stage.close()
            cfg = self.config
            bcfg = BiniConfig(k=float(cfg.bilateral_k), max_iter=cfg.bilateral_max_iter, tol=cfg.bilateral_tol,
                              cg_tol=cfg.bilateral_inner_tol, cg_max_iter=cfg.bilateral_cg_max_iter,
                              launch=cfg.bilateral_launch)
            self._bini_stage = BilateralIntegrator(valid, self.camera, bcfg, device=self.device, cuts=cuts)
            self._bini_key = key
        return self._bini_stage

    def _poisson(self, n, valid, gj, gi, nzj, nzi, cj, ci, u0, timings, progress):
        """The plain (optionally robust) least-squares solve of (4.20)."""
        cfg = self.config
        total_it = 0
        outer = 0
        u = u0
        inner_tol = cfg.tol

        def solve(wx, wy, tx, ty, u, prog, tol):
            nonlocal total_it
            u, its, res, tim = self._solve(n, valid, wx, wy, tx, ty, u, prog, tol)
            total_it += its
            for key, v in tim.items():
                timings[key] = timings.get(key, 0.0) + v
            return u, res

        rob = cfg.robust == "cauchy"
        rwx = rwy = None
        nout = 1 + cfg.robust_iterations if rob else 1
        for k in range(nout):
            wx, wy, tx, ty = edge_system(valid, gj, gi, cj, ci)
            ex, ey = wx > 0, wy > 0
            if cfg.robust == "curl" and rwx is None:
                # fixed, data-only weights from the first system's targets
                rwx, rwy, _ = curl_edge_weights(ex, ey, tx, ty, cfg.robust_scale)
            if rwx is not None:
                wx, wy = wx * rwx, wy * rwy
            u, res = solve(wx, wy, tx, ty, u, None if rob else progress, inner_tol)
            if rob and k < nout - 1:
                rwx, rwy, _ = robust_edge_weights(u, ex, ey, tx, ty, cfg.robust_scale)
            outer = k + 1 if rob else 0
            if rob and progress is not None:
                progress(k + 1, nout, "robust re-weighting")
        # final residual of the last system (float64, host)
        b = divergence_rhs(wx, wy, tx, ty)
        true_res = normal_equation_residual(np.where(valid, u, 0.0), wx, wy, b)
        solver_res = true_res if res is None else res
        return u, total_it, outer, true_res, solver_res

    def _solve(self, n, valid, wx, wy, tx, ty, u0, progress, tol):
        cfg = self.config
        if cfg.solver == "direct":
            return solve_direct(valid, wx, wy, tx, ty, self._components(valid)[0])
        if cfg.solver == "dct":
            return solve_dct(valid, wx, wy, tx, ty)
        return self._solve_taichi(n, valid, wx, wy, tx, ty, u0, progress, tol)

    # ------------------------------------------------------------------ Taichi

    def _ensure_device(self):
        if self._dev is not None:
            return self._dev
        ti = _taichi.init(self.device)
        cfg = self.config
        h, w = self.shape
        key = (_taichi.current_device(), h, w, cfg.coarsest, cfg.dtype)
        with _POOL_LOCK:
            free = _POOL.get(key)
            if free:
                self._dev = free.pop()
                return self._dev
        shapes = level_shapes(h, w, cfg.coarsest)
        offs = np.concatenate([[0], np.cumsum([s[1] for s in shapes])]).astype(int)
        wp_ = int(offs[-1])
        ft = ti.f32 if cfg.dtype == "float32" else ti.f64
        ncmax = shapes[-1][0] * shapes[-1][1]
        fb = ti.FieldsBuilder()
        d = {}
        for name in ("wx", "wy", "dg", "e", "f", "t"):
            d[name] = ti.field(ft)
            fb.dense(ti.ij, (h, wp_)).place(d[name])
        for name in ("z", "b", "r", "p", "q", "gj", "gi"):
            d[name] = ti.field(ft)
            fb.dense(ti.ij, (h, w)).place(d[name])
        d["sc"] = ti.field(ti.f64)  # CG scalars: float64 accumulators whatever the precision
        fb.dense(ti.i, 8).place(d["sc"])
        d["pinv"] = ti.field(ft)
        fb.dense(ti.ij, (ncmax, ncmax)).place(d["pinv"])
        d["cidx"] = ti.field(ti.i32)
        fb.dense(ti.ij, (ncmax, 2)).place(d["cidx"])
        # the persistent solve's accumulators, barrier counters and the start it restores after a failed launch
        d["acc"] = ti.field(ti.f64)
        fb.dense(ti.i, 16).place(d["acc"])
        d["bar"] = ti.field(ti.i32)
        fb.dense(ti.i, 2).place(d["bar"])
        d["z0"] = ti.field(ft)
        fb.dense(ti.ij, (h, w)).place(d["z0"])
        d["geo"] = ti.field(ti.i32)  # the level layout (off, h, w) per level, for the persistent solve
        fb.dense(ti.ij, (len(shapes), 3)).place(d["geo"])
        d["tree"] = fb.finalize()
        d["geo"].from_numpy(np.array([(o, hh, ww) for o, (hh, ww) in zip(offs, shapes)], np.int32))
        d["shapes"], d["offs"], d["wp"], d["np_dtype"] = shapes, offs, wp_, np.dtype(cfg.dtype)
        d["key"] = key
        d["persistent"] = {}  # the persistent solve's kernels, by geometry, grid and smoother (kept with the fields)
        self._dev = d
        return d

    def close(self) -> None:
        """Give the Taichi fields back to the pool of this process (the next integrator of the same size
        takes them, with the kernels Taichi compiled for them: a new set of fields costs 0.8-1.6 s of
        compilation on this CPU, about 2.4 s a reconstruction on the H100); the integrator then refuses work
        (:meth:`Stage._check_open`: its fields may belong to another integrator by then)."""
        self._closed = True
        if getattr(self, "_bini_stage", None) is not None:
            self._bini_stage.close()
            self._bini_stage = self._bini_key = None
        if self._dev is not None:
            d, self._dev = self._dev, None
            with _POOL_LOCK:
                _POOL.setdefault(d["key"], []).append(d)

    def _upload_levels(self, valid, wx, wy):
        d = self._dev
        key = (wx.tobytes(), wy.tobytes())
        if self._levels_key == key:
            return
        cfg = self.config
        uniform = bool(np.all((wx == 0) | (wx == 1)) and np.all((wy == 0) | (wy == 1)))
        levels = build_levels(wx, wy, cfg.coarsest, alpha=coarse_alpha(uniform, cfg.robust != "none"))
        h = self.shape[0]
        P = {k: np.zeros((h, d["wp"]), dtype=d["np_dtype"]) for k in ("wx", "wy", "dg")}
        for k, ((lx, ly), (hh, ww)) in enumerate(zip(levels, d["shapes"])):
            o = d["offs"][k]
            P["wx"][:hh, o:o + ww] = lx
            P["wy"][:hh, o:o + ww] = ly
            P["dg"][:hh, o:o + ww] = diagonal(lx, ly)
        for k in ("wx", "wy", "dg"):
            d[k].from_numpy(P[k])
        # exact pseudo-inverse on the coarsest level
        lx, ly = levels[-1]
        self.set_coarsest(lx, ly)
        self._levels_key = key

    def set_coarsest(self, lx, ly) -> None:
        """The coarsest level's exact solve (:func:`gpps.host.poisson.coarsest_pinv`) from its edge weights
        (hc, wc), into the device fields (the host path, and :class:`DeviceSystem` with weights coarsened on
        the device: the at most ``coarsest^2`` cells' pseudo-inverse costs ~1 ms in numpy, 15 ms as one serial
        GPU task)."""
        d = self._dev
        ncmax = d["pinv"].shape[0]
        off = int(d["offs"][len(d["shapes"]) - 1])
        lx, ly = np.asarray(lx), np.asarray(ly)
        # the fields already hold this level's solve (the rounds' systems and the calls of a kept Reconstructor
        # on one mask coarsen to the same weights): skip the pseudo-inverse and its upload (2.6 ms of a 256^2
        # call's host time on the H200's host); the key lives with the fields, which the pool hands on
        key = (lx.shape, lx.dtype.str, lx.tobytes(), ly.tobytes(), off)
        if d.get("coarsest_key") == key:
            return
        d["coarsest_key"] = None
        pinv, cidx, nc = coarsest_pinv(lx, ly, ncmax, off, d["np_dtype"])
        d["pinv"].from_numpy(pinv)
        d["cidx"].from_numpy(cidx)
        d["nc"] = nc
        d["coarsest_key"] = key

    def _geometry(self) -> tuple:
        """The level layout ``((off, h, w), ...)``, finest first, as the fused kernels' compile-time tuple."""
        d = self._dev
        return tuple((int(o), int(hh), int(ww)) for o, (hh, ww) in zip(d["offs"], d["shapes"]))

    def _vcycle(self):
        d, cfg = self._dev, self.config
        sh, of = d["shapes"], d["offs"]
        L = len(sh)
        args = (d["e"], d["f"], d["t"], d["wx"], d["wy"], d["dg"])
        for k in range(L - 1):
            K.down(*args, int(of[k]), sh[k][0], sh[k][1], int(of[k + 1]), sh[k + 1][0], sh[k + 1][1],
                   cfg.omega, cfg.smooth_pairs)
        K.coarse_exact(d["e"], d["f"], d["cidx"], d["pinv"], d["nc"])
        for k in range(L - 2, -1, -1):
            K.up(*args, int(of[k]), sh[k][0], sh[k][1], int(of[k + 1]), cfg.omega, cfg.smooth_pairs)

    def _solve_taichi(self, n, valid, wx, wy, tx, ty, u0, progress, tol):
        cfg = self.config
        t0 = time.perf_counter()
        d = self._ensure_device()
        self._upload_levels(valid, wx, wy)
        h, w = self.shape
        uniform = cfg.weighting == "uniform" and not cfg.bilateral and cfg.robust == "none"
        if uniform:
            # right-hand side computed on the device (the streaming path)
            cam = self.camera
            if cam.is_perspective:
                cx, cy = cam.principal_point(self.shape)
                pars = (1, cam.fx, cam.fy, cx, cy, 1.0)
            else:
                cx, cy = cam.principal_point(self.shape)
                pars = (0, 1.0, 1.0, cx, cy, cam.pixel_size)
            K.gradients_uniform(np.ascontiguousarray(n, dtype=d["np_dtype"]), d["gj"], d["gi"], d["dg"], *pars,
                                cfg.min_nz, h, w)
            K.rhs_uniform(d["gj"], d["gi"], d["wx"], d["wy"], d["b"], h, w)
        else:
            d["b"].from_numpy(divergence_rhs(wx, wy, tx, ty).astype(d["np_dtype"]))
        if u0 is not None:
            d["z"].from_numpy(np.where(valid, u0, 0.0).astype(d["np_dtype"]))
        else:
            d["z"].fill(0)
        t1 = time.perf_counter()
        its, res = self._iterate(progress, tol)
        u = d["z"].to_numpy().astype(np.float64)
        t2 = time.perf_counter()
        return u, its, res, {"rhs": t1 - t0, "solve": t2 - t1}

    def _block_sums(self) -> bool:
        """Whether the CG sums run in the block build (``IntegratorConfig.cg_sums``)."""
        mode = self.config.cg_sums
        cuda = _taichi.current_device().startswith("cuda")
        if mode == "block" and not cuda:
            raise ValueError(f"cg_sums: 'block' needs Taichi on CUDA (shared arrays are CUDA-only), "
                             f"got device {_taichi.current_device()!r}")
        return mode == "block" or (mode == "auto" and cuda)

    def _pcg_launches(self, blk: bool):
        """``(start, iteration)`` closures of the multigrid PCG (``IntegratorConfig.launch``).

        ``start``: r = b - A z, sc[RR] = |r|^2, the first V-cycle and direction (sc[RZ]); ``iteration``:
        cg_step (sc[RR] = the new |r|^2), the V-cycle, the new direction.  Stopping after ``iteration``
        leaves the solution of stopping after its cg_step (the V-cycle and cg_direction do not touch z
        or sc[RR]); the per-level form runs ``start``'s V-cycle and ``iteration``'s after cg_step in the
        same order, so both launch forms compute the same sequence.
        """
        d, cfg = self._dev, self.config
        h, w = self.shape
        if self._launch() != "per-level":  # (fused; also a persistent launch's fallback)
            geom = self._geometry()
            lv = (d["wx"], d["wy"], d["dg"], d["sc"], d["cidx"], d["pinv"], d["nc"], geom, cfg.omega,
                  cfg.smooth_pairs, blk)

            def start():
                K.pcg_start(d["z"], d["b"], d["r"], d["e"], d["f"], d["t"], d["p"], *lv)

            def iteration():
                K.pcg_iteration(d["z"], d["r"], d["p"], d["q"], d["e"], d["f"], d["t"], *lv)

            return start, iteration
        args = (d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)

        def start():
            K.cg_start(d["z"], d["b"], d["r"], d["e"], d["f"], *args)
            self._vcycle()
            K.cg_first_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk)

        def iteration():
            K.cg_step(d["z"], d["r"], d["p"], d["q"], d["e"], d["f"], *args)
            self._vcycle()
            K.cg_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk)

        return start, iteration

    def _launch(self) -> str:
        """The PCG's launch form here (``IntegratorConfig.launch``; ``"auto"``: persistent on CUDA, fused on the
        CPU; ``"fused"`` after a persistent launch the GPU could not hold)."""
        mode = self.config.launch
        if mode == "auto":
            mode = "persistent" if _taichi.current_device().startswith("cuda") else "fused"
        if mode == "persistent" and getattr(self, "_persistent_off", False):
            mode = "fused"
        return mode

    def _persistent_grid(self) -> tuple[int, int]:
        """(blocks, threads per block) of the persistent solve: ``persistent_blocks`` (or what the GPU held)
        blocks of :data:`gpps.kernels.block_sum.BLOCK` threads per multiprocessor, no more than the image's
        pixels need; off CUDA one thread."""
        if not _taichi.current_device().startswith("cuda"):
            return 1, 1
        from gpps._runtime import warp
        from gpps.kernels.block_sum import BLOCK

        bps = getattr(self, "_bps", self.config.persistent_blocks)
        sms = int(warp().get_device("cuda:0").sm_count)
        h, w = self.shape
        return max(1, min(sms * bps, -(-(h * w) // BLOCK))), BLOCK

    def _iterate_persistent(self, tol) -> tuple[int, float] | None:
        """:meth:`_iterate`'s multigrid PCG as one persistent launch (:mod:`gpps.kernels.poisson_persistent`) and
        one read of its accumulators; None when the GPU cannot hold the task's blocks even at one a
        multiprocessor (the start restored: the caller runs the fused launches)."""
        d, cfg = self._dev, self.config
        while True:
            grid = self._persistent_grid()
            cuda = grid[1] > 1
            key = (self._geometry(), grid, float(cfg.omega), int(cfg.smooth_pairs))
            kern = d["persistent"].get(key)
            first = kern is None
            if first:
                kern = d["persistent"][key] = KP.make_pcg_persistent(d, key[0], cfg.omega, cfg.smooth_pairs, *grid,
                                                                     cuda=cuda)
                if cuda:
                    d["z0"].copy_from(d["z"])
            kern(int(d["nc"]), float(tol), int(cfg.iterations_cap), int(cfg.check_every),
                 int(cfg.dtype == "float32"))
            if not (first and cuda) or int(d["bar"][1]) == 0:
                break
            # a block never became resident (the barrier timed out): the start again, half the blocks
            d["z"].copy_from(d["z0"])
            del d["persistent"][key]
            bps = getattr(self, "_bps", cfg.persistent_blocks)
            if bps <= 1:
                warnings.warn("integrator: the GPU cannot hold the persistent solve's blocks; using one launch an "
                              "iteration (launch='fused')", RuntimeWarning, stacklevel=4)
                self._persistent_off = True
                return None
            self._bps = bps // 2
        acc = d["acc"].to_numpy()  # (the one read)
        bb, rr = float(acc[KP.A_BB]), float(acc[KP.A_RES])
        return int(acc[KP.A_ITS]), (0.0 if bb == 0.0 else math.sqrt(max(rr, 0.0) / bb))

    def _iterate(self, progress, tol) -> tuple[int, float]:
        """Solve the system in the fields (``b``, the levels, the start in ``z``) to ``tol``: Jacobi or
        multigrid-preconditioned CG, reading one float64 scalar every ``check_every`` iterations.
        Returns ``(iterations, relative residual)``; the solution is left in ``z``."""
        d, cfg = self._dev, self.config
        h, w = self.shape
        if cfg.solver != "jacobi" and self._launch() == "persistent":
            got = self._iterate_persistent(tol)
            if got is not None:
                if progress is not None:
                    progress(got[0], cfg.iterations_cap, f"residual {got[1]:.2e}")
                return got
        blk = self._block_sums()
        # |b|^2
        d["r"].fill(0)
        K.residual_norm(d["r"], d["b"], d["q"], d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)
        bb = float(d["sc"][K.RR])
        tol2 = (tol ** 2) * bb
        cap = cfg.iterations_cap
        its = 0
        if bb == 0.0:
            res = 0.0
        elif cfg.solver == "jacobi":
            pairs = 8
            K.residual_norm(d["z"], d["b"], d["r"], d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)
            rr = float(d["sc"][K.RR])
            while rr > tol2 and its < cap:
                K.smooth(d["z"], d["b"], d["t"], d["wx"], d["wy"], d["dg"], 0, h, w, cfg.omega, pairs)
                its += 2 * pairs
                if its % (2 * pairs * cfg.check_every) == 0 or its >= cap:
                    K.residual_norm(d["z"], d["b"], d["r"], d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)
                    rr = float(d["sc"][K.RR])
                    if progress is not None:
                        progress(min(its, cap), cap, f"jacobi residual {math.sqrt(rr / bb):.2e}")
            res = math.sqrt(rr / bb)
        else:
            start, iteration = self._pcg_launches(blk)
            start()
            rr = float(d["sc"][K.RR])
            f32 = cfg.dtype == "float32"
            best = math.inf  # the lowest |r|^2 checked at the float32 floor, its iterate kept in z0
            if rr > tol2:
                while its < cap:
                    iteration()
                    its += 1
                    if its % cfg.check_every == 0 or its >= cap:
                        rr_prev, rr = rr, float(d["sc"][K.RR])  # the only host sync
                        if progress is not None:
                            progress(its, cap, f"residual {math.sqrt(rr / bb):.2e}")
                        if rr <= tol2:
                            break
                        if f32 and rr > 0.8 * rr_prev and min(rr, rr_prev) < _FLOOR_RR * bb:
                            # the float32 precision floor (_FLOOR_RR): stalled, or thrown back up from it
                            if best < rr:
                                d["z"].copy_from(d["z0"])
                                rr = best
                            break
                        if f32 and rr < _FLOOR_RR * bb and rr < best:
                            d["z0"].copy_from(d["z"])  # (at most a check or two: one device copy each)
                            best = rr
            res = math.sqrt(rr / bb)
        return its, res
