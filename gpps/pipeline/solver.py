"""The per-pixel photometric-stereo solver stage: N images -> normals, albedo, diagnostics.

One Warp launch solves every pixel (the iteration loop, the multi-start and
the IRLS rounds all run inside the kernel, see :mod:`gpps.kernels.solve`), so
a solve needs no host synchronisation and :meth:`PixelSolver.step` can be
captured in a CUDA graph.  Buffers are allocated once for ``(N, H, W)``.

Length: the config (every setting documented in place, about 150 lines), the noise and light checks the
stages share, and one stage whose frame buffers serve its solve, re-solves of the uploaded frame
(``set_mask`` / ``select_pixels`` / ``set_start`` / ``set_depth``) and the device merge (``save`` / ``merge_saved``).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np

from gpps._check import (
    GppsWarning,
    as_array,
    as_flags,
    as_images,
    as_mask,
    check_bool,
    check_choices,
    check_number,
    check_shape,
)
from gpps._runtime import block_lanes, resolve_device, warp
from gpps.host.observations import masked_grey, noise_selection
from gpps.kernels import front as fk
from gpps.kernels import merge as mk
from gpps.kernels import solve as sk
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.names import (
    FLAG_ALBEDO_FROM_NEIGHBOURS,
    FLAG_FEW_OBSERVATIONS,
    FLAG_ILL_CONDITIONED,
    FLAG_NOT_CONVERGED,
    FLAG_UNFOUNDED,
    FLAG_WOODHAM_FALLBACK,
    LIGHT_LANES,
    ROBUST_NAMES,
    SOLVER_CMD_SETS,
    SOLVER_NAMES,
    SUBSET_BLOCKS_PER_SM,
    ParallelName,
    RobustName,
    SolverName,
)
from gpps.names import ROBUST_TAG as _ROBUST_TAG
from gpps.names import SOLVER_TAG as _SOLVER_TAG
from gpps.pipeline.cpu_threads import balanced_bounds, cpu_threads, load_first, run_all, run_reporting
from gpps.pipeline.noise import DeviceNoise, noise_on_device
from gpps.pipeline.prefetch import is_loaded
from gpps.pipeline.params import camera_params, light_params, material_params, resolve_parallel, uses_lanes
from gpps.pipeline.stage import Stage

AlbedoMode = Literal["rgb", "grey"]

__all__ = [
    "PixelSolver",
    "SolverConfig",
    "SOLVER_NAMES",
    "ROBUST_NAMES",
    "FLAG_ILL_CONDITIONED",
    "FLAG_FEW_OBSERVATIONS",
    "FLAG_NOT_CONVERGED",
    "FLAG_WOODHAM_FALLBACK",
    "FLAG_ALBEDO_FROM_NEIGHBOURS",
    "FLAG_UNFOUNDED",
    "check_light_configuration",
    "estimate_noise",
    "solver_params",
    "robust_code",
    "solver_kernels",
]


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :class:`PixelSolver`.

    Attributes:
        solver: ``"lm"`` Levenberg-Marquardt (Algorithm 4), ``"dogleg"`` Powell's
            dog leg (Algorithm 5), ``"bfgs"`` quasi-Newton BFGS (Algorithm 3), or
            ``"none"``: only the Lambertian least-squares (Woodham) solution.
        max_iters: cap on cost evaluations per start and per IRLS round.
        starts: starts per pixel (best final cost wins): the least-squares
            normal, the view direction, then the least-squares normal tilted
            toward ``starts - 2`` evenly spread azimuths, alternately by
            ``start_angle_deg`` and twice that.
            Several starts beat the multimodality of 3-image specular fits.
        start_angle_deg: tilt of the extra starts (degrees).
        tol_step: stop when a step is shorter than this (radians).
        tol_grad: stop when ``|J^T W r|_inf`` is at most this.
        robust: robust loss by iteratively reweighted least squares (IRLS).
        robust_scale: the loss's scale, relative to the pixel's brightest grey value.
        irls_rounds: reweighting rounds (used when ``robust != "none"``).
        shadow_threshold: drop observations whose grey value is below this
            fraction of the pixel's brightest (0 keeps all).
        shadow_relative: the cast-shadow refit (used when ``robust != "none"``;
            0 disables it).  An observation darker than this fraction of the
            pixel's lit level (the grey value that a quarter of its
            observations reach) which the robust fit predicts at least
            ``gpps.names.CAST_CONFLICT`` times that level, or one at the lit
            level or above which it predicts below that fraction of its value,
            contradicts the fit: a cast shadow darkens an observation at any
            normal, and a tilted normal (or a low albedo under which the lit
            observations become the outliers) can win the fit (a backdrop seen
            through a hole, shadowed for half of the lights).  So does a fit
            that misses the lit observations (at or above the dark level) by
            more than the dark level, RMS over their channels, while the pixel
            has a dark one whose light the fit turned the surface from (its n.l
            below that factor times the lit observations' mean): the normal
            was tilted until a shadowed light grazed it.  Such a pixel is solved again
            with every observation that dark set aside, from the lit
            observations' least squares, the fit's normal and the view
            direction; the reweighting rounds then take an observation back, as
            a one-sided term, where the new fit predicts it dark too (an
            attached shadow, the dark flank of a specular lobe), so only the
            ones it predicts bright stay out.  Pixels without a contradiction
            keep the first fit.  Set-aside observations carry the weight
            ``gpps.names.ASIDE_WEIGHT`` in ``weights``.
        saturation: drop observations with a channel >= this value (None: keep).
        albedo: ``"rgb"`` (3 channels) or ``"grey"`` (one value for all channels).
        cond_threshold: flag pixels whose valid light directions' Gram matrix
            has a Frobenius condition number above this (lighting sensitivity, 3.13).
        early_exit: stop each solve on convergence; False always runs
            ``max_iters`` evaluations (uniform work, e.g. for timing).
        neighbour_radius: pixels with fewer than 3 lit observations (attached
            shadows) cannot fix normal and albedo together; a second pass holds
            their albedo at the geometric median of the albedos of the nearest
            well-determined pixels (square rings searched until 16 are found, then
            2 rings more, at most this radius in pixels) and re-solves the normal
            with a weak tie-breaking prior toward the first-order (affine, least
            absolute deviations) extrapolation of their normals.  The robust fits
            ignore the few rim pixels that noise on a shadowed observation made
            look determined.  A fit whose albedo the data do not fix
            (``FLAG_UNFOUNDED``: every kept observation explained with a
            diffuse shading below :data:`gpps.names.UNFOUNDED_SHADING`, e.g. a
            normal grazing to the view, where plastic's diffuse term vanishes,
            with an albedo of 1e5) is flagged ``FLAG_FEW_OBSERVATIONS`` too and
            takes the same pass.  0 disables the pass.
        held_dark_refit: in the neighbour pass (without reweighting rounds), a
            pixel with unlit observations is fitted again with them set aside
            (from its neighbours' prior start), and that fit is kept when it
            predicts one of them lit and the first fit paid for them (a misfit,
            or the other of the two normals its 2 lit observations allow,
            clearly farther from the neighbours'): a cast shadow, dark at any
            normal, rather than an attached one (the rule and its measurements:
            ``held_dark_refit`` of :func:`gpps.kernels.solve_methods.solve_pixel_for`).
            The refinement (:class:`gpps.pipeline.depth_refine.DepthRefiner`)
            leaves the set-aside observations out too.  False: the unlit
            observations always stay in the fit (before session 35).
        lit_threshold: an observation counts as lit (informative) when its grey
            value exceeds this fraction of the pixel's brightest and
            ``lit_sigmas`` times the image's noise level; pixels with fewer than
            3 lit observations get the neighbour pass above.  Unlit observations
            stay in the fit (unless ``shadow_threshold`` drops them); the dark
            ones as the one-sided terms of ``lit_sigmas``.
        warm_start: start from the normals passed to :meth:`PixelSolver.upload`
            (one start per pixel) instead of the least-squares solution.
        warm_albedo: with ``warm_start``, a pixel with fewer than 3 lit
            observations holds the albedo its ``albedo`` buffer has (the last
            solve's: a stream's previous frame) instead of fitting it, and is
            flagged ``FLAG_ALBEDO_FROM_NEIGHBOURS``; two observations cannot fix
            normal and albedo together, and the neighbour pass that gives such a
            pixel an albedo searches rings of pixels (one read here).  A pixel
            whose buffer holds no albedo yet (zeros) fits it as before.
        lm_tau: initial LM damping ``tau * max(diag J^T J)`` (Algorithm 4).
        dogleg_radius: initial trust radius of the dog leg (radians).
        smoothness: weight of a first-order smoothness term
            ``smoothness * s^2 / 2 * sum_(p~q) |n_p - n_q|^2`` (4-neighbours in the
            mask) added to the per-pixel costs after the pixelwise solve, where
            ``s`` is the 99th percentile of the grey observations in the mask
            (so the weight does not depend on the image scale).  0 (default)
            keeps every pixel independent.  With noisy images and few lights,
            0.1-1 suppresses the noise amplification of grazing and shadowed
            pixels; as a MAP estimate it is ``sigma^2 / (s^2 tau^2)`` for image
            noise ``sigma`` and a neighbour normal difference of about ``tau``.
            With 3 images and 1 % noise, 1 keeps every case of
            ``perf/synthetic_calibrated.py`` (256^2) at or below 0.9 deg MAEN
            (1.4-3.8 deg pixelwise); it stays opt-in: each sweep is a launch and
            a warm-started solve of every pixel.
        smoothing_sweeps: red-black Gauss-Seidel sweeps of that regularised fit
            (each pixel one warm-started solve per sweep).
        noise_level: standard deviation of the image noise (grey values, image
            units as passed); None (default): estimated per image from each
            frame by :func:`estimate_noise` in :meth:`PixelSolver.upload`.
            A frame written straight into the buffers (the stream) keeps the
            last value of :attr:`PixelSolver.noise` (zeros at first: no noise test).
        lit_sigmas: the noise test of ``lit_threshold``: a shadowed observation's
            noise passes ``lit_threshold`` of a dim grazing pixel (whose
            brightest value is small) often, ``lit_sigmas`` noise levels rarely
            (0.13 % at 3).  Observations at or below it are *dark*: a one-sided
            term (weight -1 in ``weights``) that only penalises a model brighter
            than them (see :mod:`gpps.kernels.solve`).  0: no noise test, and
            only exact zeros are dark.
        parallel: how the pixelwise solve is spread over GPU threads: ``"pixels"`` one thread a
            pixel; ``"lights"`` one block of :data:`gpps.names.LIGHT_LANES` threads a pixel with
            the lights split over the lanes (equal up to the order of the light sums);
            ``"auto"``: "lights" on CUDA with :data:`gpps.names.LIGHTS_PARALLEL_MIN` images or
            more for a solve of at most ``LIGHTS_PARALLEL_PAIRS_PER_IMAGE x N`` mask pixels
            (latency-bound launches, measured in :mod:`gpps.names`), else "pixels".  A
            "lights" solve on the CPU runs as one launch on one thread (and one lane unless
            ``warp.config.enable_cpu_blocks``): a testing aid.
        split_starts: cold solves of one thread a pixel run each of the ``starts`` in a thread of its
            own (:mod:`gpps.kernels.solve_split`: a prelude, the starts, the pick of the best in start
            order and the IRLS rounds; three launches), and so does the neighbour pass after them
            (``neighbour_radius``; :func:`gpps.kernels.solve_split.split_under_kernels_for`); the same
            results (bitwise on the CPU).  A GPU launch costs its slowest thread, which runs ``starts``
            solves one after another in the one-kernel form.  None (default): on CUDA when
            ``starts > 1``; the CPU keeps the one kernel (its launches run the threads one after another
            anyway; True there is for tests).
            Also the default of :class:`gpps.pipeline.material.MaterialScorer`'s ``split_starts``.
            A :meth:`PixelSolver.step_subset` re-solve runs them only when True: its subset is
            usually a few pixels or none, and over a whole 1024^2 grid the three launches cost more
            than the one-thread kernel when it holds none (the stream's known-material frame on an
            H200: 2.03 against 1.87 ms), less when it holds hard pixels (~70 misfits a frame,
            each start up to 50 iterations: 0.16 against 0.34 ms a launch;
            perf/results/s26/README.md).
    """

    solver: SolverName = "lm"
    max_iters: int = 50
    starts: int = 10
    start_angle_deg: float = 20.0
    tol_step: float = 1e-6
    tol_grad: float = 1e-14
    robust: RobustName = "none"
    robust_scale: float = 0.1
    irls_rounds: int = 3
    shadow_threshold: float = 0.0
    saturation: float | None = None
    albedo: AlbedoMode = "rgb"
    cond_threshold: float = 1e3
    early_exit: bool = True
    neighbour_radius: int = 32
    lit_threshold: float = 0.05
    warm_start: bool = False
    lm_tau: float = 1e-3
    dogleg_radius: float = 0.3
    smoothness: float = 0.0
    smoothing_sweeps: int = 20
    noise_level: float | None = None  # (after the older fields: positional construction keeps working)
    lit_sigmas: float = 3.0
    parallel: ParallelName = "auto"
    split_starts: bool | None = None
    shadow_relative: float = 0.0
    warm_albedo: bool = False
    held_dark_refit: bool = True

    def __post_init__(self):
        check_choices(self)
        check_bool("early_exit", self.early_exit)
        check_bool("warm_start", self.warm_start)
        check_bool("warm_albedo", self.warm_albedo)
        check_bool("held_dark_refit", self.held_dark_refit)
        check_number("max_iters", self.max_iters, lo=1, integer=True)
        check_number("starts", self.starts, lo=1, integer=True)
        check_number("irls_rounds", self.irls_rounds, lo=0, integer=True)
        check_number("neighbour_radius", self.neighbour_radius, lo=0, hi=256, integer=True)
        check_number("start_angle_deg", self.start_angle_deg, lo=0.0, hi=45.0)
        check_number("tol_step", self.tol_step, lo=0.0)
        check_number("tol_grad", self.tol_grad, lo=0.0)
        check_number("robust_scale", self.robust_scale, lo=0.0, lo_open=True)
        check_number("shadow_threshold", self.shadow_threshold, lo=0.0, hi=1.0)
        check_number("shadow_relative", self.shadow_relative, lo=0.0, hi=1.0)
        if self.saturation is not None:
            check_number("saturation", self.saturation, lo=0.0, lo_open=True)
        check_number("lit_threshold", self.lit_threshold, lo=0.0, hi=1.0)
        if self.noise_level is not None:
            check_number("noise_level", self.noise_level, lo=0.0)
        check_number("lit_sigmas", self.lit_sigmas, lo=0.0)
        if self.split_starts is not None:
            check_bool("split_starts", self.split_starts)
        check_number("cond_threshold", self.cond_threshold, lo=1.0)
        check_number("lm_tau", self.lm_tau, lo=0.0, lo_open=True)
        check_number("dogleg_radius", self.dogleg_radius, lo=0.0, lo_open=True)
        check_number("smoothness", self.smoothness, lo=0.0)
        check_number("smoothing_sweeps", self.smoothing_sweeps, lo=0, integer=True)
        if self.smoothness > 0.0 and self.solver == "none":
            raise ValueError("smoothness: expected 0 with solver 'none' (the smoothness term needs a nonlinear solver)")


def rgb_images(images, shape) -> np.ndarray:
    """Checked images of an ``(N, H, W)`` problem as (N, H, W, 3): RGB as given, grey (N, H, W) or (N, H, W, 1)
    repeated over the channels (:func:`gpps._check.as_images` rules).  Raises ValueError for another shape."""
    n, h, w = shape
    arr = as_images("images", images)
    if arr.shape == (n, h, w):
        arr = np.repeat(arr[..., None], 3, axis=-1)
    elif arr.shape == (n, h, w, 1):
        arr = np.repeat(arr, 3, axis=-1)
    if arr.shape != (n, h, w, 3):
        raise ValueError(f"images: expected shape ({n}, {h}, {w}, 3) or ({n}, {h}, {w}), got {arr.shape}")
    return arr


def check_problem(shape, lights) -> tuple[int, int, int]:
    """``(N, H, W)`` of a per-pixel problem, checked against its lights (one per image).

    Raises:
        ValueError: a shape that is not three positive sizes, or a light count other than N.
        TypeError: lights that are not :class:`DirectionalLights` or :class:`PointLights`.
    """
    n, h, w = check_shape("shape", shape, "NHW")  # (16.5 is a TypeError, not 16)
    if not isinstance(lights, (DirectionalLights, PointLights)):
        raise TypeError(f"lights: expected DirectionalLights or PointLights, got {type(lights).__name__}")
    if len(lights) != n:
        raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
    return n, h, w


def estimate_noise(images, mask, *, max_pixels: int = 1 << 16) -> np.ndarray:
    """Noise standard deviation of each image's grey values: (N,) float32.

    Immerkaer's estimator (J. Immerkaer, "Fast noise variance estimation",
    CVIU 64(2), 1996): the 3x3 kernel ``K = [[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``
    cancels a locally linear (and nearly cancels a smooth) signal and has gain
    ``|K|_2 = 6`` on white noise.  Here in its robust form,
    ``sigma = median |I * K| / (0.6745 * 6)``, over the pixels whose 3x3
    neighbourhood lies in ``mask`` and is positive in that image (shadows clip
    the noise at 0; edges, texture and highlights are outvoted by the median),
    about ``max_pixels`` of them (every few rows).  0 (unknown) for an
    image with fewer than 64 such pixels.  Dense high-frequency texture or
    geometry inflates the estimate (it is signal to the kernel); that only
    makes more dim observations count as unlit.

    Args:
        images: (N, H, W, 3) or (N, H, W) observations.
        mask: (H, W) bool.
        max_pixels: cap on the pixels used per image.

    Cost: image by image (the blocks stay in cache), only the rows and the column range of the chosen
    pixels, one grey value per pixel (not once per kernel row), in float32 without a copy of the frame.
    The kernel sums its 9 terms in the same order as a plain 3x3 loop and the median is np.median's, so
    the estimate is the same bit for bit (tests/test_host_overheads.py pins it to that loop).
    """
    img = np.asarray(images)
    n = img.shape[0]
    out = np.zeros(n, np.float32)
    got = noise_selection(mask, max_pixels=max_pixels)
    if got is None:
        return out
    rows, sel, c0, c1 = got
    wc = c1 - c0

    def rows_of(idx):
        """The index of ``a[idx]`` rows: a slice (a view) when ``idx`` (increasing) is an arithmetic progression
        (worked out once: the loop below takes the same rows 19 times an image)."""
        d = np.diff(idx)
        if idx.size == 1 or np.all(d == d[0]):
            return slice(int(idx[0]), int(idx[-1]) + 1, int(d[0]) if idx.size > 1 else 1)
        return idx

    used = np.unique(np.concatenate([rows, rows + 1, rows + 2]))  # the image rows above, at and below
    at = [rows_of(np.searchsorted(used, rows + 1 + di)) for di in (-1, 0, 1)]
    used_rows = rows_of(used)
    taps = [(di, dj, (1 + (di == 0)) * (1 + (dj == 0)) * (-1) ** (di + dj)) for di in (-1, 0, 1) for dj in (-1, 0, 1)]
    grey = np.empty((used.size, wc), np.float32)
    lit = np.empty(grey.shape, bool)
    lap = np.empty((rows.size, wc - 2), np.float32)
    tmp = np.empty_like(lap)
    pos = np.empty(lap.shape, bool)
    mid = np.empty(2, np.float32)
    for k in range(n):  # one image at a time: the (U, Wc) blocks stay in cache
        blk = img[k, :, c0:c1][used_rows]
        if blk.ndim == 3:  # (U, Wc, C): the mean of R, G, B in float32, summed left to right
            blk = blk.astype(np.float32, copy=False)
            np.add(blk[..., 0], blk[..., 1], out=grey)
            grey += blk[..., 2]
            grey /= 3.0
        else:
            grey[...] = blk
        np.greater(grey, 0.0, out=lit)
        pos[...] = sel
        for i, (di, dj, kk) in enumerate(taps):  # lap = sum of K[di, dj] I[r + di, c + dj] in this order
            sh = grey[at[di + 1]][:, 1 + dj : wc - 1 + dj]
            pos &= lit[at[di + 1]][:, 1 + dj : wc - 1 + dj]
            if i == 0:  # 0 + 1 sh: sh (bit for bit where it counts: sh > 0 there)
                lap[...] = sh
            elif kk == 1:
                lap += sh
            elif kk == -1:
                lap -= sh
            else:
                np.multiply(sh, kk, out=tmp)
                lap += tmp
        v = np.abs(lap[pos])
        if v.size < 64:
            continue
        if np.isnan(v).any():  # pragma: no cover - inf in the images; np.median's NaN rule
            med = np.median(v)
        else:
            # the median as np.median takes it: the middle order statistic, or the float32 mean of the two;
            # |values| >= +0 sort as their bit patterns (one partition, no float compare)
            j = (v.size - 1) // 2
            part = np.partition(v.view(np.uint32), j).view(np.float32)
            if v.size % 2:
                med = part[j]
            else:
                mid[0], mid[1] = part[j], part[j + 1 :].min()
                med = np.mean(mid)
        out[k] = float(med) / (0.6745 * 6.0)
    return out


def _directions_at(lights, point: np.ndarray) -> np.ndarray:
    if isinstance(lights, DirectionalLights):
        return np.asarray(lights.directions, np.float64)
    d = np.asarray(lights.positions, np.float64) - point[None]
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def check_light_configuration(lights, point=None, *, tol: float = 1e-3) -> float:
    """Raise ValueError when the lights cannot determine normals; return the condition number.

    Needs at least 3 lights whose directions (at ``point`` for point lights)
    span 3D: collinear or coplanar directions leave a normal component
    undetermined (the non-singularity condition behind 3.13).

    Returns:
        The 2-norm condition number of the (N, 3) direction matrix.
    """
    n = len(lights)
    if n < 3:
        raise ValueError(f"lights: expected at least 3 lights to determine normals, got {n}")
    p = np.zeros(3) if point is None else np.asarray(point, np.float64)
    with np.errstate(all="ignore"):
        d = _directions_at(lights, p)
    if not np.all(np.isfinite(d)):  # (a point light at the point itself: no direction, and the SVD fails on NaN)
        k = np.nonzero(~np.all(np.isfinite(d), axis=1))[0]
        raise ValueError(f"lights: point light(s) {(k + 1).tolist()[:8]} lie at the object's centre "
                         f"{np.round(p, 6).tolist()}: expected lights away from the object")
    if point is not None and isinstance(lights, PointLights) and np.any(lights.mu > 0):
        # an LED (mu > 0) whose axis points away from the object sends it no light: max(cos, 0)^mu = 0
        facing = np.einsum("nc,nc->n", lights.axes, p[None] - lights.positions)
        away = np.nonzero((lights.mu > 0) & (facing <= 0))[0]
        if away.size:
            warnings.warn(f"lights: {away.size} of {n} point lights have axes pointing away from the object's centre "
                          f"{np.round(p, 6).tolist()} (lights {(away + 1).tolist()[:8]}): with mu > 0 they send it "
                          f"no light (check the axes' sign: from the LED into the scene)", GppsWarning, stacklevel=3)
    s = np.linalg.svd(d, compute_uv=False)
    if s[0] <= 0 or s[-1] / s[0] < tol:
        what = "collinear" if (s[0] > 0 and s[1] / s[0] < tol) else "coplanar"
        raise ValueError(
            f"lights: the {n} light directions are {what} (singular values {np.round(s, 6).tolist()}); "
            "photometric stereo needs 3 non-coplanar directions"
        )
    return float(s[0] / s[-1])


def solver_params(c: SolverConfig):
    """The device parameter struct (:class:`gpps.kernels.solve.SolverParams`) of a config: what
    :class:`PixelSolver` launches with (``keep_unmasked`` 0), shared with :class:`gpps.pipeline.material.MaterialScorer`."""
    p = sk.SolverParams()
    p.method = _SOLVER_TAG[c.solver]
    p.max_iters = int(c.max_iters)
    p.starts = int(c.starts)
    p.start_angle = float(np.deg2rad(c.start_angle_deg))
    p.tol_step = float(c.tol_step)
    p.tol_grad = float(c.tol_grad)
    p.robust = _ROBUST_TAG[c.robust]
    p.robust_scale = float(c.robust_scale)
    p.irls_rounds = int(c.irls_rounds) if c.robust != "none" else 0
    p.shadow_threshold = float(c.shadow_threshold)
    p.shadow_relative = float(c.shadow_relative)
    p.held_dark = int(bool(c.held_dark_refit))
    p.saturation = float(c.saturation) if c.saturation is not None else 0.0
    p.warm_start = int(bool(c.warm_start))
    p.warm_albedo = int(bool(c.warm_albedo))
    p.grey_albedo = int(c.albedo == "grey")
    p.cond_threshold = float(c.cond_threshold)
    p.early_exit = int(bool(c.early_exit))
    p.lm_tau = float(c.lm_tau)
    p.dogleg_radius = float(c.dogleg_radius)
    p.lit_threshold = float(c.lit_threshold)
    p.lit_sigmas = float(c.lit_sigmas)
    p.keep_unmasked = 0
    p.row0 = 0
    return p


#: The range of the brightest observations (a high percentile of the grey values inside the mask) the float32
#: solver takes: far outside it its squares overflow (residual NaN above ~1e19) or its absolute tolerances swallow
#: the signal (normals left at the start below ~1e-25; 1.7 deg errors from 1e-8 down).  The flows refuse frames
#: outside it (:func:`gpps.flows.photometric.check_observations`); :meth:`PixelSolver.upload` refuses the overflow.
SCALE_RANGE = (1e-12, 1e12)



def check_scale(scale: float, *, low: bool = True) -> None:
    """ValueError when the brightest observations ``scale`` lie outside :data:`SCALE_RANGE` (``low=False``: only
    above it; a dark tile of a larger frame is fine, the flows check the whole frame's scale)."""
    if scale > SCALE_RANGE[1] or (low and scale < SCALE_RANGE[0]):
        span = f"between {SCALE_RANGE[0]:g} and {SCALE_RANGE[1]:g}" if low else f"up to {SCALE_RANGE[1]:g}"
        raise ValueError(f"images: expected linear values {span} (1 = full scale; beyond them the float32 solver's "
                         f"squares overflow or its tolerances swallow the signal), got the brightest observations "
                         f"inside the mask at {scale:.3g}; rescale the images (and the lights' intensities with them)")


def _intensity_scale(grey) -> float:
    """The smoothness term's intensity scale: the 99th percentile of the mask's (N, P) grey values (>= 1e-12)."""
    return float(max(np.percentile(grey, 99.0), 1e-12))


#: The outputs :meth:`PixelSolver.fetch` copies.
OUTPUTS = ("normals", "albedo", "residual", "iterations", "flags", "cond", "weights")


def robust_code(c: SolverConfig) -> str:
    """The robust loss the kernels of ``c`` are specialised for (the stages' one rule): ``c.robust``, or ``"none"``
    without a reweighting round (no IRLS code is emitted)."""
    return c.robust if c.irls_rounds > 0 else "none"


def _split_starts(c: SolverConfig, device: str) -> bool:
    """Whether a whole-image solve with ``c`` runs the starts-parallel kernels (``SolverConfig.split_starts``)."""
    on = c.split_starts if c.split_starts is not None else str(device).startswith("cuda")
    return bool(on) and c.starts > 1 and not c.warm_start and c.solver != "none"


def solver_kernels(config: SolverConfig, brdf: str, device: str, lights: int, *, split: bool | None = None) -> list:
    """The kernels a :class:`PixelSolver` with ``config`` and the model ``brdf`` launches for a whole-image solve
    of ``lights`` images on ``device`` (the specialisations :meth:`PixelSolver.load` loads), with the modules of
    its merge and subset scatter; the lights-parallel build, when the config may launch it, as ``(kernel,
    block_dim)`` (launched with a block of its own size: another module variant).  For
    :mod:`gpps.pipeline.prefetch`'s plans.

    Args:
        split: whether the solve runs the starts-parallel kernels (None: as :meth:`PixelSolver` decides for a cold
            whole-image solve with this config).
    """
    robust = robust_code(config)
    solve, under, smooth = sk.get_solve_kernels(config.solver, brdf, robust, cache=sk.term_cache_size(device, lights),
                                                with_batched=sk.batched_in_solve_module(device))
    wp = warp()
    kernels = [k for k in (solve, under, smooth) if k is not None]
    kernels += [wp.get_module(mk.__name__), wp.get_module(fk.__name__)]  # (the device merge, a subset's scatter)
    if config.solver != "none" and resolve_parallel(config.parallel, device, lights) != "pixels":
        # (the lights-parallel build: launched with a block of LIGHT_LANES threads, its own module variant)
        kernels.append((sk.get_solve_kernel_lanes(config.solver, brdf, robust), block_lanes(device, LIGHT_LANES)))
    if split if split is not None else _split_starts(config, device):
        kernels += list(sk.get_split_kernels(config.solver, brdf, robust))
        if config.neighbour_radius > 0:
            kernels += list(sk.get_split_under_kernels(config.solver, brdf, robust))
    return kernels


class PixelSolver(Stage):
    """Per-pixel calibrated photometric stereo on N images; buffers allocated once.

    Args:
        shape: (N, H, W): number of images and image size.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        lights: :class:`DirectionalLights` or :class:`PointLights` (N of them);
            the model uses their intensities as the light radiance, so pass
            unit intensities for images already divided by them.
        material: :class:`gpps.material.Material` (model and per-scene ks,
            shininess, roughness, f0, eta); its ``brdf`` selects the model.
        config: :class:`SolverConfig` (default: LM, 8 starts).
        device: Warp device (None: CUDA if present, else CPU).

    Raises:
        ValueError: fewer than 3 lights or degenerate (collinear / coplanar)
            light directions (checked at the scene centre for point lights).

    Besides the per-frame buffers (``images``, ``mask``, ``valid``, ``depth``
    and the outputs), ``noise`` (N,) holds each image's noise level for the
    lit count (set by :meth:`upload`; ``noise_level`` is its host copy).
    """

    Config = SolverConfig

    def __init__(self, shape, camera, lights, material: Material, config: SolverConfig | None = None, device=None):
        wp = warp()

        self._sk = sk
        self.device = resolve_device(device)
        n, h, w = check_problem(shape, lights)
        self.config = config if config is not None else SolverConfig()
        if not isinstance(self.config, SolverConfig):
            raise TypeError(f"config: expected PixelSolver.Config, got {type(self.config).__name__}")
        self.shape = (n, h, w)
        self.camera = camera
        self.cam = camera_params(camera, (h, w))
        self.lights = lights
        if isinstance(lights, DirectionalLights):
            self.light_cond = check_light_configuration(lights)
        self.lp = light_params(lights, self.device)
        self.material = material
        self.mp = material_params(material)
        self.prm = self._params(self.config)
        self._select_kernels()
        self._switch_cmds()  # (the recorded launches of the first config and material: see _switch_cmds)
        d = self.device
        self.images = self._buffer((n, h, w), wp.vec3, d)
        self.mask = self._buffer((h, w), wp.uint8, d)
        self.valid = self._buffer((n, h, w), wp.uint8, d, fill=1)
        self.depth = self._buffer((h, w), wp.float32, d, fill=1)
        self.noise = self._buffer(n, wp.float32, d)
        self.noise_level = np.zeros(n, np.float32)
        self._device_noise = None  # DeviceNoise, on CUDA at the first upload that estimates the noise
        self.weights = self._buffer((n, h, w), wp.float32, d)
        self.normals = self._buffer((h, w), wp.vec3, d)
        self.albedo = self._buffer((h, w), wp.vec3, d)
        self.residual = self._buffer((h, w), wp.float32, d)
        self.iterations = self._buffer((h, w), wp.int32, d)
        self.flags = self._buffer((h, w), wp.int32, d)
        self.cond = self._buffer((h, w), wp.float32, d)
        self.intensity_scale = 1.0  # (None after a checked upload until a config reads it: _ensure_scale)
        self._scale_mask = None  # that upload's mask
        self._row_bounds = None  # CPU: the solve launch's row ranges, one thread each (None: one launch)
        self._mask_rows = None  # mask pixels per row of the last upload (balances the CPU row ranges)

    def _split_rows(self, m: np.ndarray) -> None:
        """On the CPU, split the solve launch by rows over the threads, balanced by the mask's pixels
        (:mod:`gpps.pipeline.cpu_threads`); one launch on CUDA or with one thread."""
        self._split_counts(m.sum(axis=1))

    def _split_counts(self, rows: np.ndarray) -> None:
        """:meth:`_split_rows` from the mask's (H,) pixel counts per row."""
        n = cpu_threads() if not self.device.startswith("cuda") else 1
        self._mask_rows = rows
        bounds = balanced_bounds(self._mask_rows, n) if n > 1 else None
        if bounds is not None and len(bounds) < 2:
            bounds = None
        if bounds != self._row_bounds:
            self._row_bounds = bounds
            for cmds in self.__dict__.get("_cmd_sets", {}).values():
                for k in [k for k in cmds if k[0] == "solve"]:
                    del cmds[k]

    def _params(self, c: SolverConfig):
        return solver_params(c)

    def _params_for(self, c: SolverConfig):
        """The device parameter struct of ``c`` for a subset re-solve (pixels outside the mask keep their
        outputs), built once per config."""
        cache = self.__dict__.setdefault("_prm_cache", {})
        if c not in cache:
            p = self._params(c)
            p.keep_unmasked = 1
            cache[c] = p
        return cache[c]

    def _select_kernels(self) -> None:
        """Pick the kernels specialised for the current solver, reflectance model and robust loss.

        Built once per process and specialisation (:func:`gpps.kernels.solve.get_solve_kernels`);
        compiled on the first launch (or ``wp.load_module(kernel.module)``).
        """
        c = self.config
        robust = robust_code(c)
        self._solve_kernel, self._underdetermined_kernel, self._smooth_kernel = self._sk.get_solve_kernels(
            c.solver, self.material.brdf, robust, cache=self._sk.term_cache_size(self.device, self.shape[0]),
            with_batched=self._sk.batched_in_solve_module(self.device),  # (the scorer's kernel beside them)
        )
        self._parallel = resolve_parallel(c.parallel, self.device, self.shape[0]) if c.solver != "none" else "pixels"
        self._lanes_kernel = (self._sk.get_solve_kernel_lanes(c.solver, self.material.brdf, robust)
                              if self._parallel != "pixels" else None)

    def _uses_lanes(self) -> bool:
        """Whether the next pixelwise solve runs the lights-parallel kernel (``config.parallel``)."""
        pixels = int(self._mask_rows.sum()) if self._mask_rows is not None else self.shape[1] * self.shape[2]
        return uses_lanes(self._parallel, self.shape[0], pixels)

    @property
    def kernels(self) -> tuple:
        """``(solve_kernel, underdetermined_kernel, smooth_kernel)`` that :meth:`step` uses (the last two None for solver "none")."""
        return self._solve_kernel, self._underdetermined_kernel, self._smooth_kernel

    def load(self, progress=None) -> None:
        """Compile (first use in this installation) and load the kernels the current config's :meth:`step` launches
        (and the modules of the device merge and a subset's scatter, :func:`solver_kernels`), now rather than at their
        first launch: a caller reporting progress can say so between the compile and the
        solve (a cold kernel cache costs seconds a module on the CPU, minutes on CUDA).  A no-op for loaded modules.

        Args:
            progress: optional ``progress(seconds, None, message)``, told every second while the modules load
                (they load on a helper thread; the callback is called on this one: :func:`run_reporting`).
        """
        self._check_open()
        key = (self.config, self.material.brdf)
        done = self.__dict__.setdefault("_loaded_for", set())
        if key in done:  # (RON asks before every solve: ~17 us a call saved once its kernels are loaded)
            return
        kernels = solver_kernels(self.config, self.material.brdf, self.device, self.shape[0],
                                 split=self._uses_split())
        # (kernels, modules and (kernel, block_dim) entries: each module variant once, as its launches load it)
        found = {}
        for k in kernels:
            item, dim = k if isinstance(k, tuple) else (k, None)
            module = getattr(item, "module", item)
            found[(id(module), dim)] = (module, dim)
        modules = [(m, dim) for m, dim in found.values() if not self._loaded(m, dim)]

        def task():
            for module, dim in modules:
                load_first(module, self.device, dim)  # (after a helper's compile of it ahead: gpps.pipeline.prefetch)
        report = None if progress is None or not modules else (
            lambda s: progress(s, None, f"loading the solver's kernels ({s:.0f} s)"))
        run_reporting(task, report)
        done.add(key)

    def _loaded(self, module, block_dim: int | None = None) -> bool:
        """Whether ``module``'s variant for launches of ``block_dim`` (None: Warp's default) is loaded on this
        solver's device (:func:`gpps.pipeline.prefetch.is_loaded`; when it cannot tell, :meth:`load` loads it, a
        no-op then)."""
        return is_loaded(module, self.device, block_dim)

    def set_config(self, config: SolverConfig) -> None:
        if not isinstance(config, SolverConfig):
            raise TypeError(f"config: expected PixelSolver.Config, got {type(config).__name__}")
        self.config = config
        self._ensure_scale()
        # (the struct is built once per config: ~0.1 ms of host time each, and RON switches configs ~16 times a
        # call; it is never changed after, so the launches recorded with it stay valid)
        cache = self.__dict__.setdefault("_prm_current", {})
        if config not in cache:
            if len(cache) >= 4 * SOLVER_CMD_SETS:
                cache.clear()
            cache[config] = self._params(config)
        self.prm = cache[config]
        self._select_kernels()
        self._switch_cmds()

    @property
    def noise_level(self) -> np.ndarray:
        """(N,) float32: the host copy of :attr:`noise` (after an upload that estimated it on the device, fetched
        at the first read)."""
        if self._noise_host is None:
            self._noise_host = self.noise.numpy().copy()
        return self._noise_host

    @noise_level.setter
    def noise_level(self, value) -> None:
        self._noise_host = value

    def _noise_on_device(self) -> bool:
        """Whether an upload estimates the noise on the device (:func:`gpps.pipeline.noise.noise_on_device`; the
        same bits as :func:`estimate_noise`)."""
        return noise_on_device(self.device)

    def _ensure_scale(self) -> None:
        """:attr:`intensity_scale` of the uploaded frame when the current config's smoothness term reads it and a
        checked upload left it for later: the frame's images back from the device (once; the upload's mask)."""
        if self.config.smoothness > 0.0 and self.intensity_scale is None:
            self.intensity_scale = _intensity_scale(masked_grey(self.images.numpy(), self._scale_mask))

    def set_material(self, material: Material) -> None:
        self.material = material
        self.mp = material_params(material)
        self._select_kernels()
        self._switch_cmds()

    def _switch_cmds(self) -> None:
        """Make the recorded launches of the current config and material the ones in use (``_cmds``): the set
        recorded the last time this pair was current, else a new one.  The last :data:`gpps.names.SOLVER_CMD_SETS`
        pairs' sets are kept: a recorded launch holds its arguments packed, so it is valid exactly while the
        config (``prm``) and material (``mp``) it was packed from are the current ones again."""
        sets = self.__dict__.setdefault("_cmd_sets", {})
        key = (self.config, self.material)
        cmds = sets.pop(key, None)
        sets[key] = {} if cmds is None else cmds  # (the most recent last)
        while len(sets) > SOLVER_CMD_SETS:
            del sets[next(iter(sets))]
        self._cmds = sets[key]

    # ------------------------------------------------------------------ per frame

    def _images(self, images) -> np.ndarray:
        arr = rgb_images(images, self.shape)  # (as_images: finite and >= 0 checked there)
        return np.ascontiguousarray(arr, dtype=np.float32)

    def upload(self, images, mask, *, depth=None, valid=None, init_normals=None, noise=None,
               checked: bool = False) -> None:
        """Check and copy one frame's inputs into the device buffers.

        Args:
            images: (N, H, W, 3) RGB or (N, H, W) grey observations >= 0.
            mask: (H, W) bool, not empty.
            depth: (H, W) depth estimate (> 0 inside the mask, scene units);
                required for point lights (per-pixel direction and 1/r^2), optional otherwise.
            valid: optional (N, H, W) bool: observations to use (e.g. unsaturated).
            init_normals: (H, W, 3) warm-start normals (with ``config.warm_start``).
            noise: (N,) per-image noise levels to use instead of ``config.noise_level`` / the estimate
                (a tile of a larger frame takes the whole frame's: :mod:`gpps.flows.tiled`).
            checked: the caller ran :func:`gpps.flows.photometric.check_observations` on these images and mask
                (it refuses a frame without enough lit observations and one too bright for the solver): the
                upload's own tests of both are not repeated, and :attr:`intensity_scale` (the grey values'
                99th percentile, which only the smoothness term reads) is computed when a config with that term
                is first set, not here.  Default False: both tested, the scale computed.

        ``run(images, mask, ...)`` (:meth:`Stage.run`) is ``upload``, :meth:`step` and :meth:`fetch` in one.
        Also sets the per-image noise levels (:attr:`noise`, :attr:`noise_level`):
        ``config.noise_level`` or, when that is None, :func:`estimate_noise` of the frame (on CUDA computed on the
        device from the uploaded images, :class:`gpps.pipeline.noise.DeviceNoise`: the same values).
        """
        self._check_open()
        n, h, w = self.shape
        img = self._images(images)
        m = as_mask("mask", mask, (h, w))
        if depth is None:
            if isinstance(self.lights, PointLights):
                raise ValueError("depth: expected an (H, W) depth estimate for point lights (2.30-2.31), got None")
            dep = None  # (ones, filled on the device)
        else:
            dep = as_array("depth", depth, shape=(h, w))
            if np.any(dep[m] <= 0):
                raise ValueError("depth: expected values > 0 inside the mask")
            dep = np.where(m, dep, 1.0).astype(np.float32)
        if valid is None:
            val = None  # (every observation: ones, filled on the device)
        else:
            val = as_flags("valid", valid, (n, h, w)).astype(np.uint8)  # (NaN or strings: an error, not True)
        if self.config.warm_start:
            if init_normals is None:
                raise ValueError("init_normals: expected (H, W, 3) normals for a warm start, got None")
        if init_normals is not None:
            nrm = as_array("init_normals", init_normals, shape=(h, w, 3))
            self.normals.assign(nrm)
        if isinstance(self.lights, PointLights):
            # the configuration must determine normals at the object's centre
            pts = self.camera.backproject(np.where(m, dep, 0.0))
            check_light_configuration(self.lights, np.median(pts[m], axis=0))
        c = self.config
        device_noise = False  # (estimated on the device once the images are there, below)
        if noise is not None:
            self.noise_level = as_array("noise", noise, shape=(n,)).astype(np.float32)
            if np.any(self.noise_level < 0):
                raise ValueError(f"noise: expected {n} noise levels >= 0, got a minimum of {float(self.noise_level.min()):g}")
        elif c.noise_level is not None:
            self.noise_level = np.full(n, c.noise_level, np.float32)
        elif self._noise_on_device():
            device_noise = True
        else:
            self.noise_level = estimate_noise(img, m)
        if not device_noise:
            self.noise.assign(self.noise_level)
        self._scale_mask = None
        if checked and c.smoothness == 0.0:
            # (the caller's checks judged the frame; the scale waits for a config that reads it: _ensure_scale)
            self.intensity_scale, self._scale_mask = None, m.copy()
        else:
            idx = np.flatnonzero(m)
            g = masked_grey(img, m, idx=idx)  # (N, P) = img[:, m].mean(-1) exactly
            self.intensity_scale = _intensity_scale(g)
            check_scale(self.intensity_scale, low=False)
            lit = g > 0 if val is None else (g > 0) & (np.take(val.reshape(n, h * w), idx, axis=1) != 0)
            if not np.any(lit):
                # degenerate: no pixel can be solved (a dark tile of a larger frame is the tiled flow's to judge)
                warnings.warn("images: no observation inside the mask is lit" + ("" if val is None else " and valid")
                              + ": no normal is determined (every pixel is flagged FLAG_FEW_OBSERVATIONS)",
                              GppsWarning, stacklevel=2)
        self.images.assign(img)
        if device_noise:  # (estimate_noise of the uploaded images, there: the host copy fetched when read)
            if self._device_noise is None:
                self._device_noise = DeviceNoise(self.shape, self.device)
            self._device_noise.upload(m)
            self._device_noise.step(self.images, self.noise)
            self._noise_host = None
        self.mask.assign(m.astype(np.uint8))
        self._split_rows(m)
        if dep is None:
            self.depth.fill_(1.0)
        else:
            self.depth.assign(dep)
        if val is None:
            self.valid.fill_(1)
        else:
            self.valid.assign(val)

    def step_subset(self, mask, config: SolverConfig) -> None:
        """The pixelwise solve kernel on another (H, W) uint8 mask buffer and with ``config``'s settings
        (same solver, model and robust loss as the current config: the same compiled kernel), then, when
        ``config.neighbour_radius > 0``, the neighbour pass on that subset's under-determined pixels (their
        neighbours read from the solver's whole mask); pixels outside ``mask`` keep their current outputs.
        Graph-capturable.

        The stream re-solves the pixels whose warm start failed this way, cold, inside the frame.
        """
        if (config.solver, robust_code(config)) != (self.config.solver, robust_code(self.config)):
            raise ValueError("config: expected the current solver and robust loss (the same kernel)")
        if not hasattr(mask, "shape") or not hasattr(mask, "dtype"):
            raise TypeError(f"mask: expected an (H, W) uint8 device array, got {type(mask).__name__}")
        if tuple(mask.shape) != tuple(self.shape[1:]):
            raise ValueError(f"mask: expected shape {self.shape[1:]}, got {tuple(mask.shape)}")
        ins = [self.images, mask, self.valid, self.depth, self.noise, self.cam, self.lp, self.mp]
        outs = [self.weights, self.normals, self.albedo, self.residual, self.iterations, self.flags, self.cond]
        if config.split_starts is True and self._uses_split(config):
            # (only when asked for: SolverConfig.split_starts)
            self._launch_split(ins, outs, config, ("subset", id(mask)))
        else:
            self._recorded(("subset", id(mask), config), self._solve_kernel, ins + [self._params_for(config)],
                           outs).launch()
        # the subset's under-determined pixels take their albedo from the object's determined pixels around
        # them (the solver's mask), not from the subset: without it a cold re-solve of a pixel with 2 usable
        # observations has a free albedo and lands anywhere on its curve of exact fits
        self._launch_underdetermined(mask, config, split=config.split_starts is True and self._uses_split(config))

    def _subset_blocks(self) -> dict:
        """``wp.launch`` keywords of a starts-parallel subset re-solve's launches: on CUDA a grid of
        :data:`gpps.names.SUBSET_BLOCKS_PER_SM` blocks an SM striding over the pixels (few of them in the
        subset), elsewhere none."""
        if not self.device.startswith("cuda"):
            return {}
        return {"max_blocks": int(SUBSET_BLOCKS_PER_SM * warp().get_device(self.device).sm_count)}

    def _recorded(self, key, kernel, inputs, outputs, dim=None, block_dim=None):
        """A recorded launch (``wp.launch(..., record_cmd=True)``) of ``kernel`` over the pixels (or ``dim``),
        kept per ``key`` until the config or material changes: the arguments are packed once (a plain CPU
        launch re-packs its struct arguments every time, and Warp keeps a cache entry per packing: memory
        grows per frame)."""
        cmds = self.__dict__.setdefault("_cmds", {})
        cmd = cmds.get(key)
        if cmd is None:
            extra = {} if block_dim is None else {"block_dim": int(block_dim)}
            cmd = warp().launch(kernel, dim=self.shape[1:] if dim is None else dim, inputs=inputs, outputs=outputs,
                                device=self.device, record_cmd=True, **extra)
            cmds[key] = cmd
        return cmd

    def _launch_solve(self, progress=None, subset: bool = False) -> None:
        """The pixelwise solve over the whole image: one launch, or on the CPU one per row range of
        :meth:`_split_rows`, run on several threads (each with ``row0`` set in its parameter copy).
        With ``progress`` on the CPU: 8 row ranges a thread, run a thread-full at a time, and
        ``progress(done, total, message)`` in mask pixels after each such wave.  ``subset``: pixels
        outside the mask keep their outputs (``keep_unmasked``)."""
        ins = [self.images, self.mask, self.valid, self.depth, self.noise, self.cam, self.lp, self.mp]
        outs = [self.weights, self.normals, self.albedo, self.residual, self.iterations, self.flags, self.cond]
        if self._uses_lanes():
            # one block of lanes a pixel (tiled: the lanes are the last launch dimension); one launch, also on
            # the CPU (Warp's CPU tile code is not safe in concurrent launches)
            h, w = self.shape[1:]
            lanes = block_lanes(self.device, LIGHT_LANES)
            prm = self._params_for(self.config) if subset else self.prm
            self._recorded(("solve_lanes", lanes, subset), self._lanes_kernel, ins + [prm], outs,
                           dim=(h, w, lanes), block_dim=lanes).launch()
            return
        if not subset and self._uses_split():
            self._launch_split(ins, outs)
            return
        bounds = self._row_bounds
        threads = 1 if bounds is None else len(bounds)
        if progress is not None and not self.device.startswith("cuda") and self._mask_rows is not None:
            threads = max(1, cpu_threads())
            bounds = balanced_bounds(self._mask_rows, 8 * threads)
        if bounds is None:
            key, prm = (("solve", "subset"), self._params_for(self.config)) if subset else (("solve",), self.prm)
            self._recorded(key, self._solve_kernel, ins + [prm], outs).launch()
            return
        cmds = []
        for a, b in bounds:
            key = ("solve", a, b, subset)
            if key not in self.__dict__.get("_cmds", {}):
                prm = self._params(self.config)
                prm.row0 = int(a)
                prm.keep_unmasked = int(subset)
                self._recorded(key, self._solve_kernel, ins + [prm], outs, dim=(b - a, self.shape[2]))
            cmds.append(self._cmds[key])
        total = float(self._mask_rows.sum()) if self._mask_rows is not None else 0.0
        for w0 in range(0, len(cmds), threads):
            run_all([c.launch for c in cmds[w0:w0 + threads]])
            if progress is not None:
                done = float(self._mask_rows[:bounds[min(w0 + threads, len(bounds)) - 1][1]].sum())
                progress(done, total, f"normals: {int(done)}/{int(total)} pixels")

    def _uses_split(self, config: SolverConfig | None = None) -> bool:
        """Whether the next whole-image solve (or a :meth:`step_subset` with ``config``) runs the
        starts-parallel kernels (``config.split_starts``)."""
        return _split_starts(self.config if config is None else config, self.device)

    def _launch_split(self, ins, outs, config: SolverConfig | None = None, subset: tuple = ()) -> None:
        """A cold solve as :mod:`gpps.kernels.solve_split`'s three launches (recorded once per config; the
        scratch of the starts, (H, W, S), from the buffer pool, one set per start count).  The whole image
        with the current config, or with ``config`` and ``subset`` (a key naming the subset mask that ``ins``
        carries) a :meth:`step_subset` re-solve: pixels outside the subset keep their outputs."""
        wp = warp()
        c = self.config if config is None else config
        n, h, w = self.shape
        ns = int(c.starts)
        key = ("split", ns, c.solver, self.material.brdf, c.robust, c.irls_rounds) + (
            (subset, c) if config is not None else ())
        cmds = self.__dict__.setdefault("_cmds", {})
        if key not in cmds:
            robust = robust_code(c)
            pre, starts, finish = self._sk.get_split_kernels(c.solver, self.material.brdf, robust)
            sc = self._split_buffers(ns)
            images, mask, valid, depth, noise, cam, lp, mp = ins
            weights, normals, albedo, residual, iterations, flags, cond = outs
            prm = self.prm if config is None else self._params_for(config)
            cap = {} if config is None else self._subset_blocks()
            one = wp.launch(pre, dim=(h, w), inputs=[images, mask, valid, depth, noise, cam, lp, prm],
                            outputs=[weights, normals, albedo, residual, iterations, flags, cond, *sc[:3]],
                            device=self.device, record_cmd=True, **cap)
            two = wp.launch(starts, dim=(h, w, ns), inputs=[images, mask, depth, cam, lp, mp, prm, weights, sc[0]],
                            outputs=list(sc[3:]), device=self.device, record_cmd=True, **cap)
            three = wp.launch(finish, dim=(h, w), inputs=[images, mask, depth, cam, lp, mp, prm, sc[0], sc[1], sc[2],
                                                         *sc[3:]],
                              outputs=[weights, normals, albedo, residual, iterations, flags], device=self.device,
                              record_cmd=True, **cap)
            cmds[key] = (one, two, three)
        for cmd in cmds[key]:
            cmd.launch()

    def _split_buffers(self, ns: int) -> tuple:
        """The starts-parallel launches' scratch (from the buffer pool, kept per start count ``ns``): the start
        normal (H, W) vec3, ``gmax`` (H, W) float32, flags (H, W) int32, then the starts' normals and albedos
        (H, W, ns) vec3, costs float32, evaluations and convergence int32."""
        wp = warp()
        scratch = self.__dict__.setdefault("_split_scratch", {})
        sc = scratch.get(ns)
        if sc is None:
            h, w = self.shape[1:]
            d = self.device
            sc = (self._buffer((h, w), wp.vec3, d), self._buffer((h, w), wp.float32, d),
                  self._buffer((h, w), wp.int32, d)) + tuple(
                self._buffer((h, w, ns), dt, d) for dt in (wp.vec3, wp.vec3, wp.float32, wp.int32, wp.int32))
            scratch[ns] = sc
        return sc

    def _launch_underdetermined(self, solve_mask, config: SolverConfig | None = None, *, split: bool) -> None:
        """The neighbour pass (``config.neighbour_radius > 0``) over ``solve_mask``'s under-determined pixels,
        their neighbours read from the solver's whole mask: ``underdetermined_kernel`` (one thread a pixel), or
        with ``split`` its starts-parallel form (:func:`gpps.kernels.solve_split.split_under_kernels_for`:
        a prelude, one thread a start, the pick and store).  Recorded once per mask and config."""
        c = self.config if config is None else config
        if c.neighbour_radius <= 0 or self._underdetermined_kernel is None:
            return
        prm = self.prm if config is None else self._params_for(config)
        radius, count = int(c.neighbour_radius), int(self._sk.NEIGHBOUR_MIN_COUNT)
        key = ("underdetermined", split) + (() if config is None else (id(solve_mask), config))
        outs = [self.weights, self.normals, self.albedo, self.residual, self.iterations, self.flags]
        if not split:
            self._recorded(key, self._underdetermined_kernel,
                           [self.images, self.mask, solve_mask, self.depth, self.cam, self.lp, self.mp, prm,
                            radius, count], outs).launch()
            return
        cmds = self.__dict__.setdefault("_cmds", {})
        if key not in cmds:
            wp = warp()
            h, w = self.shape[1:]
            ns = int(c.starts)
            robust = robust_code(c)
            pre, starts, finish = self._sk.get_split_under_kernels(c.solver, self.material.brdf, robust)
            sc = self._split_buffers(ns)
            scratch = self.__dict__["_split_scratch"]
            held = scratch.get("held")
            if held is None:
                held = scratch["held"] = (self._buffer((h, w), wp.vec3, self.device),
                                          self._buffer((h, w), wp.vec4, self.device))
            common = [self.images, self.depth, self.cam, self.lp, self.mp, prm]
            one = wp.launch(pre, dim=(h, w), inputs=[self.images, self.mask, solve_mask, self.lp, prm, radius, count,
                                                     self.normals, self.albedo, self.flags, self.depth, self.cam],
                            outputs=[*sc[:3], *held], device=self.device, record_cmd=True)
            two = wp.launch(starts, dim=(h, w, ns), inputs=common + [self.weights, sc[0], sc[2], *held],
                            outputs=list(sc[3:]), device=self.device, record_cmd=True)
            three = wp.launch(finish, dim=(h, w), inputs=common + [sc[0], sc[1], sc[2], *held, *sc[3:]],
                              outputs=outs, device=self.device, record_cmd=True)
            cmds[key] = (one, two, three)
        for cmd in cmds[key]:
            cmd.launch()

    def step(self, progress=None, *, subset: bool = False) -> None:
        """Solve all pixels from the current buffers, no host sync (graph-capturable).

        Two kernel launches (pixelwise solve, under-determined pixels), then
        ``2 * smoothing_sweeps`` red-black half-sweeps when ``smoothness > 0``.
        ``progress(done, total, message)``: on the CPU, told as the solve's row
        ranges finish (:meth:`_launch_solve`; the host waits for them); ignored on CUDA.
        ``subset``: the pixelwise solve leaves the outputs outside the mask as they are
        (default: zeros there), so a re-solve of a few pixels costs little more than
        their solves (the DGMC front's rings, :class:`gpps.pipeline.front.DeviceFront`).
        """
        self._check_open()
        self._launch_solve(progress, subset)
        self._launch_underdetermined(self.mask, split=not subset and self._uses_split())
        c = self.config
        if c.smoothness > 0.0 and c.smoothing_sweeps > 0 and self._smooth_kernel is not None:
            strength = float(c.smoothness * self.intensity_scale**2)
            for _ in range(c.smoothing_sweeps):
                for parity in (0, 1):
                    warp().launch(
                        self._smooth_kernel,
                        dim=self.shape[1:],
                        inputs=[self.images, self.mask, self.depth, self.cam, self.lp, self.mp, self.prm, strength, parity, self.flags],
                        outputs=[self.weights, self.normals, self.albedo, self.residual, self.iterations],
                        device=self.device,
                    )

    # ------------------------------------------------------------------ re-solves of the uploaded frame

    def set_mask(self, mask) -> None:
        """Solve other pixels of the uploaded frame next: (H, W) bool (may be empty), copied to the device."""
        n, h, w = self.shape
        m = as_mask("mask", mask, (h, w), allow_empty=True)
        self.mask.assign(m.astype(np.uint8))
        self._split_rows(m)

    def select_pixels(self, pixels, start: int, count: int, rows=None) -> None:
        """Solve exactly the pixels of a device index list next: the mask is cleared and set on
        ``pixels[start : start + count]`` on the device (kernel :data:`gpps.kernels.front.scatter_mask_kernel`);
        nothing is copied (the DGMC front selects its rings this way, :class:`gpps.pipeline.front.DeviceFront`).

        Args:
            pixels: (P,) int32 Warp array of flat pixel indices ``y * W + x`` on the solver's device.
            start, count: the slice to solve (count may be 0: an empty mask).
            rows: (H,) the selected pixels per image row (host numbers the caller knows): they balance the
                CPU row split (:meth:`_split_rows`), and their sum picks the kernel (``config.parallel``);
                None: ``count`` spread evenly over the rows.
        """
        wp = warp()
        n, h, w = self.shape
        if not isinstance(pixels, wp.array) or pixels.dtype != wp.int32 or pixels.ndim != 1:
            raise ValueError(f"pixels: expected a 1-D int32 Warp array, got {type(pixels).__name__} "
                             f"{getattr(pixels, 'shape', None)} {getattr(pixels, 'dtype', None)}")
        if str(pixels.device) != str(self.mask.device):
            raise ValueError(f"pixels: expected an array on {self.mask.device}, got {pixels.device}")
        start, count = int(start), int(count)
        if start < 0 or count < 0 or start + count > pixels.shape[0]:
            raise ValueError(f"start, count: expected a slice of the {pixels.shape[0]} pixels, got {start}, {count}")
        if rows is None:
            rows = np.full(h, count / h)
        else:
            rows = np.asarray(rows)
            if rows.shape != (h,):
                raise ValueError(f"rows: expected shape ({h},), got {rows.shape}")
        self.mask.zero_()
        if count:
            # recorded once per index list (kept alive with it): later slices change only two numbers
            rec = self.__dict__.get("_scatter")
            if rec is None or rec[0] is not pixels:
                rec = self._scatter = (pixels, wp.launch(fk.scatter_mask_kernel, dim=1, inputs=[pixels, 0, w],
                                                         outputs=[self.mask], device=self.device, record_cmd=True))
            rec[1].set_dim(count)
            rec[1].set_param_at_index(1, start)
            rec[1].launch()
        self._split_counts(rows)

    def set_start(self, normals) -> None:
        """Start normals of the next warm-started step: (H, W, 3), copied into the ``normals`` buffer."""
        n, h, w = self.shape
        self.normals.assign(as_array("normals", normals, shape=(h, w, 3)).astype(np.float32))

    def set_depth(self, depth, mask=None) -> None:
        """Another depth estimate for the uploaded frame (point lights move with it each RON round): (H, W),
        > 0 inside ``mask`` (default: the pixels of the last :meth:`set_mask` / :meth:`upload`)."""
        n, h, w = self.shape
        dep = as_array("depth", depth, shape=(h, w))
        m = self.mask.numpy().astype(bool) if mask is None else as_mask("mask", mask, (h, w), allow_empty=True)
        if np.any(dep[m] <= 0):
            raise ValueError("depth: expected values > 0 inside the mask")
        self.depth.assign(np.where(m, dep, 1.0).astype(np.float32))

    def set_depth_device(self, depth) -> None:
        """Another depth estimate already on this solver's device: an (H, W) float32 Warp array, copied
        device to device (no host round trip; RON's device rounds write their integrated depth there).
        The caller guarantees what :meth:`set_depth` checks: > 0 inside the mask."""
        wp = warp()
        n, h, w = self.shape
        if not isinstance(depth, wp.array) or tuple(depth.shape) != (h, w) or depth.dtype != wp.float32:
            raise ValueError(f"depth: expected a ({h}, {w}) float32 Warp array, got {type(depth).__name__} "
                             f"of shape {tuple(getattr(depth, 'shape', ()))}")
        if str(depth.device) != str(self.depth.device):
            raise ValueError(f"depth: expected an array on {self.depth.device}, got one on {depth.device}")
        wp.copy(self.depth, depth)

    def save(self) -> None:
        """Keep a device copy of the current outputs (``normals`` .. ``cond``) for :meth:`merge_saved`."""
        wp = warp()
        names = ("normals", "albedo", "residual", "iterations", "flags", "cond")
        if "_saved" not in self.__dict__:
            self._saved = {k: self._buffer(getattr(self, k).shape, getattr(self, k).dtype, self.device)
                           for k in names}
        for k in names:
            wp.copy(self._saved[k], getattr(self, k))

    def merge_saved(self) -> None:
        """Merge the last step (a solve of the current mask) into the :meth:`save`'d outputs, on the device:
        the lower residual where it can rank (:func:`gpps.host.merge.ranks_better`, kernel
        :data:`gpps.kernels.merge.merge_saved_kernel`); the saved outputs elsewhere."""
        if "_saved" not in self.__dict__:
            raise ValueError("merge_saved: expected save() first")
        sv = self._saved
        warp().launch(mk.merge_saved_kernel, dim=self.shape[1:],
                      inputs=[self.mask, int(FLAG_FEW_OBSERVATIONS), sv["normals"], sv["albedo"], sv["residual"],
                              sv["iterations"], sv["flags"], sv["cond"]],
                      outputs=[self.normals, self.albedo, self.residual, self.iterations, self.flags, self.cond],
                      device=self.device)

    def run(self, *args, progress=None, **kwargs) -> dict:
        """``upload(*args, **kwargs)``, ``step(progress)`` and ``fetch()`` (:meth:`Stage.run` with progress)."""
        self.upload(*args, **kwargs)
        self.step(progress)
        return self.fetch()

    def resolve(self, mask, init_normals, *, names=("normals", "albedo", "residual", "iterations", "flags")) -> dict:
        """Solve the uploaded frame again on another mask from other start normals.

        The images, depth, observation mask and noise levels of the last
        :meth:`upload` stay; only ``mask`` and the start normals change, so a
        sequence of small solves does not copy the frame each time (the DGMC
        front, :class:`gpps.pipeline.front.DeviceFront`, copies not even masks,
        starts and outputs: :meth:`select_pixels`).  Needs ``config.warm_start``.

        Args:
            mask: (H, W) bool, the pixels to solve (may be empty: nothing runs).
            init_normals: (H, W, 3) start normals (read where ``mask`` is set).
            names: the outputs to return (copies), of those :meth:`fetch` returns.

        Returns:
            dict of numpy arrays, as :meth:`fetch`, restricted to ``names``.
        """
        if not self.config.warm_start:
            raise ValueError("config: expected warm_start=True for resolve (it solves from init_normals)")
        n, h, w = self.shape
        m = as_mask("mask", mask, (h, w), allow_empty=True)
        nrm = as_array("init_normals", init_normals, shape=(h, w, 3))
        self.mask.assign(m.astype(np.uint8))
        self.normals.assign(nrm)
        self._split_rows(m)
        if m.any():
            self.step()
        return self.fetch(names)

    def close(self) -> None:
        """Give the device buffers back to the process's pool (:mod:`gpps.pipeline.buffers`); the solver
        refuses work afterwards (its buffers are gone)."""
        self._release_buffers()
        if self.__dict__.get("_device_noise") is not None:
            self._device_noise.close()
            self._device_noise = None
        for name in ("images", "mask", "valid", "depth", "noise", "weights", "normals", "albedo", "residual",
                     "iterations", "flags", "cond", "_saved", "_cmds", "_cmd_sets", "_split_scratch"):
            self.__dict__.pop(name, None)
        self._closed = True

    def fetch(self, names=("normals", "albedo", "residual", "iterations", "flags", "cond", "weights")) -> dict:
        """The current results as numpy arrays owned by the caller: ``normals`` (H, W, 3), ``albedo``
        (H, W, 3), ``residual`` (H, W), ``iterations`` (H, W), ``flags`` (H, W) (bits of
        :mod:`gpps.names`), ``cond`` (H, W), ``weights`` (N, H, W).

        Copies: on the CPU, Warp's ``numpy()`` is a view of the device buffer,
        which the next solve would overwrite under the caller's feet.

        Args:
            names: the outputs to copy (default: all).
        """
        self._check_open()
        if isinstance(names, str):
            names = (names,)
        bad = [k for k in names if k not in OUTPUTS]
        if bad:
            raise ValueError(f"names: expected some of {list(OUTPUTS)}, got {bad}")
        return {k: np.array(getattr(self, k).numpy(), copy=True) for k in names}
