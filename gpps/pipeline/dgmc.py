"""DGMC on the device (seed 4.1.9, 4.16-4.18): the stage that owns the buffers and launches the kernels of
:mod:`gpps.kernels.dgmc` and :mod:`gpps.kernels.dgmc_geodesic`.

:class:`DeviceDGMC` runs the whole of :func:`gpps.host.dgmc.dgmc_start` on a Warp device: the highlight test
(O(N) per pixel and flagging round instead of the host's O(N^2) leave-one-out refits), the regions' labels and
outer boundaries, the ``K`` nearest boundary pixels of each highlight pixel by geodesic distance (min-plus
relaxation sweeps instead of a host Dijkstra per boundary pixel), the curvatures (4.16) and the
curvature-similarity start search (4.17-4.18).  Where the parallel forms differ from the host's and why the
results agree is written in :mod:`gpps.kernels.dgmc`.  :func:`dgmc_start_device` has the signature and result of
:func:`gpps.host.dgmc.dgmc_start` (plus ``device``), so a caller swaps it in with one line.

The only host work left is the mask's fill-index map (a Euclidean distance transform of the mask, once per upload)
and scipy's Gaussian-derivative weights (a few numbers per ``sigma``); the sorts behind the reference albedo (a
median) and the percentile rule run on the device (:func:`warp.utils.radix_sort_pairs`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps._check import as_array, as_mask, check_unit
from gpps._runtime import resolve_device, warp
from gpps.host.dgmc import (
    DGMCConfig,
    DGMCResult,
    Highlights,
    fill_indices,
    gaussian_derivative_weights,
)
from gpps.kernels import dgmc as dk
from gpps.kernels import dgmc_geodesic as dg
from gpps.lights import DirectionalLights, PointLights
from gpps.pipeline.cpu_threads import balanced_bounds, cpu_threads, load_first, run_all
from gpps.pipeline.stage import Stage

__all__ = ["DeviceDGMC", "DGMCStart", "dgmc_start_device"]

# sweeps between two convergence checks of the geodesic relaxation (each check waits for the device)
CHECK_EVERY = 8
# min-label steps between two convergence checks of the region labelling (~20 steps on a 256^2 frame)
LABEL_CHECK = 4


class DeviceDGMC(Stage):
    """DGMC start normals on a Warp device; buffers allocated once for one (N, H, W) and ``config.k_nearest``.

    Args:
        shape: (N, H, W): images and their size.
        config: :class:`gpps.host.dgmc.DGMCConfig` (default settings when None).
        device: Warp device (None: CUDA if present, else CPU).

    ``upload(images, mask, normals, lights=..., points=...)``, ``step()``, ``fetch()`` -> :class:`DGMCResult`
    (the host's fields; ``highlights.predicted`` and the maps included).  ``sweeps`` holds the number of
    geodesic relaxation sweeps of the last step.
    """

    def __init__(self, shape, *, config: DGMCConfig | None = None, device=None):
        wp = warp()
        cfg = DGMCConfig() if config is None else config
        if not isinstance(cfg, DGMCConfig):
            raise TypeError(f"config: expected DGMCConfig, got {type(cfg).__name__}")
        if len(tuple(shape)) != 3 or any(int(v) < 1 for v in shape):
            raise ValueError(f"shape: expected (N, H, W) with positive sizes, got {shape!r}")
        n, h, w = (int(v) for v in shape)
        if h * w > 1 << dg.SRC_BITS:
            raise ValueError(f"shape: expected H W <= 2^{dg.SRC_BITS} pixels (the geodesic merge keeps a flat pixel "
                             f"index in {dg.SRC_BITS} bits), got {h} x {w}")
        if cfg.rule == "lambertian" and n < 3:
            raise ValueError(f"shape: expected N >= 3 images for rule='lambertian', got N = {n}")
        self.config = cfg
        self.shape = (n, h, w)
        self.device = resolve_device(device)
        self._settle(*self.kernel_modules())
        d = self.device
        k = int(cfg.k_nearest)
        f64, i32, u8 = wp.float64, wp.int32, wp.uint8
        self.images = self._buffer((n, h, w), wp.vec3, d)
        self.mask = self._buffer((h, w), u8, d)
        self.normals = self._buffer((h, w), wp.vec3d, d)
        self.points = self._buffer((h, w), wp.vec3d, d)
        self.lvec = self._buffer(n, wp.vec3d, d)
        self.laxis = self._buffer(n, wp.vec3d, d)
        self.lmu = self._buffer(n, f64, d)
        self.lint = self._buffer(n, f64, d)
        self.fill = self._buffer((h, w, 2), i32, d)
        self.sort_keys = self._buffer(2 * h * w, f64, d)
        self.sort_vals = self._buffer(2 * h * w, i32, d)
        self.rho = self._buffer(1, f64, d)
        self.levels = self._buffer(n, f64, d)
        self.flags = self._buffer((n, h, w), u8, d)
        self.saturated = self._buffer((n, h, w), u8, d)
        self.predicted = self._buffer((n, h, w), wp.float32, d)
        self.region = self._buffer((h, w), u8, d)
        self.labels = self._buffer((h, w), i32, d)
        self.roots = self._buffer(h * w, i32, d)
        self.numbers = self._buffer(h * w, i32, d)
        self.boundary = self._buffer((h, w), i32, d)
        self.counter = self._buffer(1, i32, d)
        # the geodesic sweeps' change counts, one slot per CPU thread (gpps.pipeline.cpu_threads)
        self.sweep_count = self._buffer(max(1, cpu_threads()), i32, d)
        self.keys = [self._buffer((h, w, k), i32, d) for _ in range(2)]
        self.srcs = [self._buffer((h, w, k), i32, d) for _ in range(2)]
        self.changed = [self._buffer((h, w), i32, d) for _ in range(2)]
        self.slots = self._buffer((h, w), i32, d)
        self.f = [self._buffer((h, w), f64, d) for _ in range(2)]
        self.tmp = self._buffer((h, w), f64, d)
        self.deriv = [self._buffer((h, w), f64, d) for _ in range(4)]
        self.gc = self._buffer((h, w), f64, d)
        self.mc = self._buffer((h, w), f64, d)
        self.weights = [wp.array(gaussian_derivative_weights(cfg.sigma, o), dtype=f64, device=d) for o in range(3)]
        self.out_normals = self._buffer((h, w), wp.vec3, d)
        self.source = self._buffer((h, w, 2), i32, d)
        self.distance = self._buffer((h, w), wp.float32, d)
        self.rank = self._buffer((h, w), i32, d)
        self.tol_used = self._buffer((h, w), wp.float32, d)
        self.channels = 3
        self.light_kind = 0
        self.count = 0
        self._mask_host = None  # (the mask whose device copies the buffers hold)
        self.sweeps = 0
        self._starts = True
        self._uploaded = False
        self._closed = False

    # ------------------------------------------------------------------ upload

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches (:meth:`gpps.flows.ron.RON.kernel_plan`)."""
        wp = warp()
        return [wp.get_module(dk.__name__), wp.get_module(dg.__name__)]

    def upload(self, images, mask, normals, *, lights=None, points=None) -> None:
        """Copy a frame into the stage's buffers.

        Args:
            images: (N, H, W) grey or (N, H, W, 3) RGB numpy images >= 0, or a Warp (N, H, W) vec3 array on the
                stage's device (copied on the device; not checked for values).
            mask: (H, W) bool object mask, not empty.
            normals: (H, W, 3) unit normals inside the mask (numpy; e.g. the least-squares solution), a Warp
                (H, W) vec3d array on the stage's device (copied as it is), or a Warp (H, W) vec3 (float32) array
                there, a solve's output such as :attr:`gpps.pipeline.solver.PixelSolver.normals` (converted on the
                device, :func:`gpps.kernels.dgmc.start_normals_kernel`: a pixel whose normal is not unit within
                1e-3, one the solve left undetermined, starts from (0, 0, 1), as do the pixels outside the mask;
                no copy to the host).
            lights: DirectionalLights, PointLights (needs ``points``) or (N, 3) directions; needed for
                ``config.rule="lambertian"``.
            points: (H, W, 3) surface points (scene units) for point lights.
        """
        self._check_open()
        wp = warp()
        n, h, w = self.shape
        self._upload_images(images)
        m = as_mask("mask", mask, (h, w))
        if self._mask_host is None or not np.array_equal(self._mask_host, m):
            # (a kept stage sees one mask frame after frame: its device copies are made once)
            self.mask.assign(m.astype(np.uint8))
            self.count = int(m.sum())
            self.fill.assign(fill_indices(m))
            self._mask_host = m.copy()
        if isinstance(normals, wp.array):
            if (normals.shape != (h, w) or normals.dtype not in (wp.vec3d, wp.vec3)
                    or normals.device != self.device):
                raise ValueError(f"normals: expected a ({h}, {w}) vec3d or vec3 array on {self.device}, "
                                 f"got {normals.shape} {normals.dtype} on {normals.device}")
            if normals.dtype == wp.vec3d:
                wp.copy(self.normals, normals)
            else:
                self._launch(dk.start_normals_kernel, (h, w), [normals, self.mask, self.normals])
        else:
            nrm = np.asarray(normals)
            if nrm.shape != (h, w, 3):
                raise ValueError(f"normals: expected (H, W, 3) = ({h}, {w}, 3), got {nrm.shape}")
            nrm = as_array("normals", nrm, dtype=np.float64)
            check_unit("normals", nrm[m])
            self.normals.assign(np.ascontiguousarray(nrm))
        self._upload_lights(lights, points)
        self._uploaded = True

    def _upload_images(self, images) -> None:
        wp = warp()
        n, h, w = self.shape
        if isinstance(images, wp.array):
            if images.shape != (n, h, w) or images.dtype != wp.vec3 or images.device != self.device:
                raise ValueError(f"images: expected a ({n}, {h}, {w}) vec3 array on {self.device}, "
                                 f"got {images.shape} {images.dtype} on {images.device}")
            wp.copy(self.images, images)
            self.channels = 3
            return
        arr = np.asarray(images)
        if arr.ndim not in (3, 4) or (arr.ndim == 4 and arr.shape[-1] not in (1, 3)):
            raise ValueError(f"images: expected (N, H, W) or (N, H, W, 3), got {arr.shape}")
        if arr.shape[:3] != (n, h, w):
            raise ValueError(f"images: expected (N, H, W) = ({n}, {h}, {w}) leading axes, got {arr.shape}")
        arr = as_array("images", arr, dtype=np.float32)
        if np.any(arr < 0):
            raise ValueError("images: expected values >= 0")
        if arr.ndim == 3 or arr.shape[-1] == 1:
            arr = arr.reshape(n, h, w, 1)
            self.channels = 1
            arr = np.concatenate([arr, np.zeros((n, h, w, 2), np.float32)], -1)
        else:
            self.channels = 3
        self.images.assign(np.ascontiguousarray(arr))

    def _upload_lights(self, lights, points) -> None:
        n, h, w = self.shape
        if lights is None:
            if self.config.rule == "lambertian":
                raise ValueError("lights: expected DirectionalLights, PointLights or (N, 3) directions for "
                                 "rule='lambertian', got None")
            return
        if isinstance(lights, (DirectionalLights, PointLights)) and len(lights) != n:
            raise ValueError(f"lights: expected {n} lights (one per image), got {len(lights)}")
        if isinstance(lights, DirectionalLights):
            e = np.asarray(lights.intensities, np.float64).mean(1)
            self.lvec.assign(np.asarray(lights.directions, np.float64) * e[:, None])
            self.light_kind = 0
        elif isinstance(lights, PointLights):
            if points is None:
                raise ValueError("points: expected (H, W, 3) surface points for point lights (2.30-2.31), got None")
            self.points.assign(np.ascontiguousarray(as_array("points", points, shape=(h, w, 3), dtype=np.float64)))
            self.lvec.assign(np.asarray(lights.positions, np.float64))
            self.laxis.assign(np.asarray(lights.axes, np.float64))
            self.lmu.assign(np.asarray(lights.mu, np.float64))
            self.lint.assign(np.asarray(lights.intensities, np.float64).mean(1))
            self.light_kind = 1
        else:
            arr = as_array("lights", lights, dtype=np.float64)
            if arr.shape != (n, 3):
                raise ValueError(f"lights: expected DirectionalLights, PointLights or an ({n}, 3) direction array, "
                                 f"got {arr.shape}")
            self.lvec.assign(arr)
            self.light_kind = 0

    # ------------------------------------------------------------------ step

    def step(self, *, starts: bool = True) -> None:
        """Highlights, regions, boundaries, geodesic candidates, curvatures and the start search, on the device.

        Args:
            starts: False: the highlights and the curvatures only (4.16), what DGMC's solved front
                (``DGMCConfig.start="front"``, :mod:`gpps.pipeline.front`) reads: the front picks each ring
                pixel's source among its solved neighbours itself (4.17-4.18), so the regions, the geodesic
                candidates and the boundary start search (the ``"boundary"`` mode's starts) are skipped;
                :meth:`fetch_start` then returns no start normals and :meth:`fetch` refuses.
        """
        self._check_open()
        if not self._uploaded:
            raise RuntimeError("step: upload() a frame first")
        self._highlights()
        self._curvatures()
        if starts:
            self._regions()
            self._geodesics()
            self._select()
        self._starts = bool(starts)

    def _launch(self, kernel, dim, inputs) -> None:
        warp().launch(kernel, dim=dim, inputs=inputs, device=self.device)

    def _sorted_median(self, slot_out, slot) -> None:
        wp = warp()
        hw = self.shape[1] * self.shape[2]
        wp.utils.radix_sort_pairs(self.sort_keys, self.sort_vals, hw)
        self._launch(dk.median_kernel, 1, [self.sort_keys, self.count, slot_out, slot])

    def _highlights(self) -> None:
        wp = warp()
        cfg = self.config
        n, h, w = self.shape
        light = [self.light_kind, self.lvec, self.laxis, self.lmu, self.lint, self.points]
        if cfg.rule == "lambertian":
            self._launch(dk.albedo_sample_kernel, (h, w),
                         [self.images, self.channels, self.mask, *light, self.sort_keys, self.sort_vals])
            self._sorted_median(self.rho, 0)
            self._launch(dk.highlight_kernel, (h, w),
                         [self.images, self.channels, self.mask, *light, self.rho, float(cfg.ratio),
                          float(cfg.margin), self.flags, self.predicted])
        else:
            q = float(np.true_divide(cfg.percentile, 100))
            for k in range(n):
                self._launch(dk.grey_keys_kernel, (h, w),
                             [self.images, self.channels, self.mask, k, self.sort_keys, self.sort_vals])
                wp.utils.radix_sort_pairs(self.sort_keys, self.sort_vals, h * w)
                self._launch(dk.percentile_kernel, 1, [self.sort_keys, self.count, q, self.levels, k])
            self._launch(dk.percentile_rule_kernel, (n, h, w),
                         [self.images, self.channels, self.mask, self.levels, float(cfg.ratio), float(cfg.margin),
                          self.flags, self.predicted])
        sat = cfg.saturation
        self._launch(dk.saturation_kernel, (h, w),
                     [self.images, self.channels, self.mask, 0.0 if sat is None else float(sat),
                      0 if sat is None else 1, self.flags, self.saturated, self.region])

    def _regions(self) -> None:
        """Connected regions by in-place min-label propagation, numbered 1..n in raster order of their first
        pixels (scipy.ndimage.label's numbering), and the outer boundary labelled with the smallest region."""
        wp = warp()
        _, h, w = self.shape
        conn = int(self.config.connectivity)
        self._launch(dg.label_init_kernel, (h, w), [self.region, self.labels])
        # the changes are read every LABEL_CHECK steps (one host wait each): a step at the fixed point changes
        # nothing (labels only decrease), so the steps after it leave the labels as they are
        for it in range(0, h * w + 1, LABEL_CHECK):
            self.counter.zero_()
            for _ in range(LABEL_CHECK):
                self._launch(dg.label_min_kernel, (h, w), [self.region, conn, self.labels, self.counter])
            if int(self.counter.numpy()[0]) == 0:
                break
        self._launch(dg.roots_kernel, (h, w), [self.labels, self.roots])
        wp.utils.array_scan(self.roots, self.numbers, inclusive=True)
        self._launch(dg.label_number_kernel, (h, w), [self.numbers, self.labels])
        self._launch(dg.boundary_kernel, (h, w), [self.mask, self.region, self.labels, conn, self.boundary])

    def _geodesics(self) -> None:
        """K-lists by Jacobi min-plus sweeps until a whole check interval changes nothing.

        The two list buffers swap roles every sweep (ping-pong, no copy: :func:`geodesic_relax_kernel`); once a
        sweep changes nothing both hold the converged lists, so ``keys[0]`` / ``srcs[0]`` are the result
        whichever was written last."""
        _, h, w = self.shape
        k = int(self.config.k_nearest)
        conn = int(self.config.connectivity)
        for b in range(2):
            self._launch(dg.list_reset_kernel, (h, w, k), [self.keys[b], self.srcs[b], self.changed[b]])
        self._launch(dg.geodesic_slots_kernel, (h, w), [self.mask, self.region, self.labels, conn, self.slots])
        old, new = 0, 1
        # CPU: the rows split across threads (Jacobi: a sweep reads only the last sweep's lists), balanced by
        # the region's pixels; each part counts its changes in its own slot
        parts = [(0, h)]
        if not self.device.startswith("cuda") and self.sweep_count.shape[0] > 1:
            parts = balanced_bounds(self.region.numpy().sum(axis=1), self.sweep_count.shape[0]) or [(0, h)]
        wp = warp()
        if len(parts) > 1:
            load_first(dg.geodesic_relax_kernel, self.device)
        count = self.sweep_count
        count.zero_()
        sweeps = 0
        # the change count is read every CHECK_EVERY sweeps on CUDA (a read is a device synchronisation),
        # after every sweep on the CPU (a memory read: no sweep past the converged one)
        every = CHECK_EVERY if self.device.startswith("cuda") else 1
        limit = h * w + CHECK_EVERY + 1  # Bellman-Ford: at most (region pixels + 1) sweeps change anything
        # recorded launches (the arguments packed once): sweep 0, then the two ping-pong directions
        cmds = {}

        def sweep_cmds(first, old, new):
            key = (first, old)
            if key not in cmds:
                ins = [self.slots, first, self.keys[old], self.srcs[old], self.changed[old], self.keys[new],
                       self.srcs[new], self.changed[new], count]
                cmds[key] = [wp.launch(dg.geodesic_relax_kernel, dim=(b - a, w), inputs=ins + [a, q],
                                       device=self.device, record_cmd=True) for q, (a, b) in enumerate(parts)]
            return cmds[key]

        while True:
            first = 1 if sweeps == 0 else 0
            run_all([c.launch for c in sweep_cmds(first, old, new)])
            old, new = new, old
            sweeps += 1
            if sweeps % every == 0:
                if int(count.numpy().sum()) == 0:
                    break
                count.zero_()
            if sweeps > limit:  # pragma: no cover - would be a bug in the kernel
                raise RuntimeError(f"geodesic relaxation did not converge in {sweeps} sweeps")
        self.sweeps = sweeps

    def _curvatures(self) -> None:
        """GC and MC (4.16): the host's Gaussian-derivative filters as separable device passes."""
        _, h, w = self.shape
        kind = 0 if self.config.curvature_field == "intensity" else 1
        self._launch(dk.field_kernel, (h, w), [self.images, self.channels, self.normals, kind, self.fill,
                                               self.f[0], self.f[1]])
        wt = self.weights
        if kind == 0:
            # f_ii: order (2, 0); f_ij: (1, 1); f_jj: (0, 2)
            plan = [(self.f[0], 2, 0), (self.f[0], 1, 1), (self.f[0], 0, 2)]
        else:
            # q_i: (1, 0) of q; p_i: (1, 0) of p; q_j: (0, 1) of q; p_j: (0, 1) of p
            plan = [(self.f[1], 1, 0), (self.f[0], 1, 0), (self.f[1], 0, 1), (self.f[0], 0, 1)]
        for out, (src, o0, o1) in zip(self.deriv, plan):
            self._launch(dk.correlate_kernel, (h, w), [src, wt[o0], 0, self.tmp])
            self._launch(dk.correlate_kernel, (h, w), [self.tmp, wt[o1], 1, out])
        d = self.deriv
        self._launch(dk.curvature_kernel, (h, w), [self.mask, kind, d[0], d[1], d[2], d[3], self.gc, self.mc])

    def _select(self) -> None:
        _, h, w = self.shape
        cfg = self.config
        self._launch(dk.select_kernel, (h, w),
                     [self.mask, self.region, self.keys[0], self.srcs[0], self.gc, self.mc, self.normals,
                      float(cfg.tolerance), float(cfg.widen_factor), int(cfg.widen_steps), self.out_normals,
                      self.source, self.distance, self.rank, self.tol_used])

    # ------------------------------------------------------------------ fetch

    def candidates(self) -> tuple[np.ndarray, np.ndarray]:
        """The converged lists: ``(sources (H, W, K) int32 flat indices, -1 past the end; distances (H, W, K)
        float64, inf past the end)``, nearest first (the device form of :func:`gpps.host.dgmc.geodesic_candidates`)."""
        if not self._starts:
            raise RuntimeError("candidates: the last step ran with starts=False (no geodesic candidates)")
        wp = warp()
        _, h, w = self.shape
        k = int(self.config.k_nearest)
        dist = wp.zeros((h, w, k), dtype=wp.float64, device=self.device)
        self._launch(dg.key_distance_kernel, (h, w, k), [self.keys[0], self.srcs[0], dist])
        return self.srcs[0].numpy(), dist.numpy()

    def fetch(self) -> DGMCResult:
        """The result of the last step, as :func:`gpps.host.dgmc.dgmc_start` returns it."""
        self._check_open()
        if not self._starts:
            raise RuntimeError("fetch: the last step ran with starts=False (no regions, candidates or starts); "
                               "use fetch_start(), or step() with starts=True")
        m = self.mask.numpy().astype(bool)
        flags = self.flags.numpy().astype(bool)
        labels = self.labels.numpy()
        hl = Highlights(
            maps=flags,
            saturated=self.saturated.numpy().astype(bool),
            region=self.region.numpy().astype(bool),
            labels=labels,
            n_regions=int(labels.max()) if labels.size else 0,
            boundary=self.boundary.numpy(),
            predicted=self.predicted.numpy(),
        )
        return DGMCResult(
            normals=self.out_normals.numpy().reshape(m.shape + (3,)),
            highlight=hl.region,
            source=self.source.numpy(),
            distance=self.distance.numpy(),
            rank=self.rank.numpy(),
            tolerance=self.tol_used.numpy(),
            gaussian=self.gc.numpy().astype(np.float32),
            mean=self.mc.numpy().astype(np.float32),
            highlights=hl,
            config=self.config,
        )

    def fetch_start(self, *, curvatures: bool = True) -> "DGMCStart":
        """The part of the last step a reconstruction reads (:class:`DGMCStart`): four (H, W) maps come back
        instead of :meth:`fetch`'s fourteen (RON's start, its front's curvature similarity); three after a step
        with ``starts=False`` (``normals`` None).

        ``curvatures=False``: ``gaussian`` and ``mean`` stay on the device (None in the result): a caller whose
        next stage reads them there (:meth:`gpps.pipeline.front.DeviceFront.upload` takes :attr:`gc` and
        :attr:`mc`) fetches only the highlights (and the start normals)."""
        self._check_open()
        _, h, w = self.shape
        nrm = self.out_normals.numpy().reshape(h, w, 3) if self._starts else None
        gc = self.gc.numpy().astype(np.float32) if curvatures else None
        mc = self.mc.numpy().astype(np.float32) if curvatures else None
        return DGMCStart(normals=nrm, highlight=self.region.numpy().astype(bool), gaussian=gc, mean=mc)

    def close(self) -> None:
        """Give the device buffers back to the process's pool (:mod:`gpps.pipeline.buffers`)."""
        self._release_buffers()
        for name in list(vars(self)):
            if name not in ("config", "shape", "device", "_closed"):
                setattr(self, name, None)
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("DeviceDGMC: the stage is closed")


@dataclass(frozen=True)
class DGMCStart:
    """What :meth:`DeviceDGMC.fetch_start` returns (the fields of :class:`gpps.host.dgmc.DGMCResult` of the same
    names): ``normals`` (H, W, 3) float32 start normals (None after :meth:`DeviceDGMC.step` with
    ``starts=False``), ``highlight`` (H, W) bool region, ``gaussian`` and ``mean`` (H, W) float32 curvatures (4.16;
    None from ``fetch_start(curvatures=False)``)."""

    normals: np.ndarray | None
    highlight: np.ndarray
    gaussian: np.ndarray | None
    mean: np.ndarray | None


def dgmc_start_device(images, mask, normals, *, lights=None, config: DGMCConfig | None = None, points=None,
                      device=None) -> DGMCResult:
    """:func:`gpps.host.dgmc.dgmc_start` on a Warp device (same arguments and result; see :class:`DeviceDGMC`).

    Args:
        images: (N, H, W) grey or (N, H, W, 3) RGB images >= 0 (numpy; float32 on the device).
        mask: (H, W) bool object mask, not empty.
        normals: (H, W, 3) unit normals inside the mask.
        lights: lights for ``config.rule="lambertian"``.
        config: :class:`DGMCConfig`.
        points: (H, W, 3) surface points, for point lights.
        device: Warp device (None: CUDA if present, else CPU).

    Returns:
        :class:`gpps.host.dgmc.DGMCResult`.
    """
    arr = np.asarray(images)
    if arr.ndim not in (3, 4):
        raise ValueError(f"images: expected (N, H, W) or (N, H, W, 3), got {arr.shape}")
    with DeviceDGMC(arr.shape[:3], config=config, device=device) as stage:
        return stage.run(arr, mask, normals, lights=lights, points=points)
