"""DGMC on the solved front (seed 4.16-4.18), device-resident: the stage :class:`DeviceFront` and
:func:`propagate_front`.

:func:`gpps.host.dgmc.dgmc_start` copies the normal of a boundary pixel ``q`` that may lie tens of pixels from
``p`` (a broad lobe makes large highlight regions); on a curved surface that start is as far from the truth as
``q`` is from ``p``, and it converges no faster than the least-squares start (``perf/dgmc_start.py``).  The front
applies the same rule (4.17-4.18) with the boundary moved inward as pixels get solved: ring 1 is the highlight
pixels next to a solved pixel, ring ``k`` those next to ring ``k - 1``; each ring pixel starts from the *solved*
normal of its source (the nearest solved 8-neighbour, edge ones first, whose curvatures match,
:func:`gpps.kernels.front.front_source_kernel`), with one warm start, and then serves as a source for the next
ring.  A start one pixel away is within the basin of the right minimum where the surface is smooth, so the
highlight pixels converge in fewer cost evaluations and far more often to the right normal.

Device-resident: the rings depend only on the masks, so the host finds them all at once
(:func:`gpps.host.dgmc.front_rings`, a breadth-first walk) and uploads them once, as the list of ring pixels
ring by ring and a level map, with the curvatures and the given solution.  The sources depend only on the rings
and the curvatures: one launch picks them all (:func:`gpps.kernels.front.front_source_kernel`).  Per ring only
the starts depend on the earlier rings' results, and everything runs on the solver's device with no copy: the
solver's mask becomes ring ``k`` (:meth:`gpps.pipeline.solver.PixelSolver.select_pixels`), each ring pixel's
start is gathered from the current normals at its source, the solver steps (:meth:`PixelSolver.step` with
``subset``: the pixels outside the ring are left alone; on the CPU split over rows across threads), and the
ring's solve is merged into the current solution on the device (:mod:`gpps.kernels.front`; every launch but the
solve's is one thread per ring pixel).  The result comes back once, at the end.  Decisions and results are
those of the former host loop over rings (rings and sources picked in numpy per ring, a full start array
uploaded and the full outputs fetched per ring, merged on the host): tests/test_front.py compares the two
exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gpps._check import as_array, as_mask
from gpps._runtime import warp
from gpps.host.dgmc import DGMCConfig, FrontResult, front_rings
from gpps.kernels import front as fk
from gpps.names import FLAG_FEW_OBSERVATIONS
from gpps.pipeline.stage import Stage

__all__ = ["DeviceFront", "propagate_front", "propagate_front_device"]

_SOLUTION = (("normals", 3), ("albedo", 3), ("residual", 0), ("flags", 0))
_UNSOLVED = 1 << 30  # the level of pixels no ring solves (off the mask, unreached highlights)


class DeviceFront(Stage):
    """The front's buffers on a :class:`gpps.pipeline.solver.PixelSolver`'s device, allocated once for its (H, W).

    Args:
        solver: the solver that holds the frame (its last upload) and solves the rings.

    ``upload(mask, highlight, solution, gaussian=..., mean=..., config=...)`` (the rings found on the host, one
    copy of each input), ``step(keep_better=..., progress=...)`` (the sources, then every ring, on the device, no
    copy), ``fetch()`` -> :class:`gpps.host.dgmc.FrontResult`.  The solver's config is replaced for the ring
    solves (``warm_start=True``, ``starts=1``, no neighbour pass, no smoothness) and restored after; its mask is
    left on the last ring, and its outputs hold each ring's solve on that ring (unchanged when there is no ring;
    outside the rings as they were).
    """

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches (:meth:`gpps.flows.ron.RON.kernel_plan`)."""
        return [warp().get_module(fk.__name__)]

    def __init__(self, solver):
        wp = warp()
        self.solver = solver
        self.device = solver.device
        self._settle(*self.kernel_modules())
        h, w = solver.shape[1:]
        d = self.device
        self.pixels = wp.zeros(h * w, dtype=wp.int32, device=d)  # ring pixels (flat), ring by ring
        self.sources = wp.zeros(h * w, dtype=wp.int32, device=d)  # their sources (flat)
        self.level = wp.zeros((h, w), dtype=wp.int32, device=d)  # when each pixel is solved (front_source_kernel)
        self.gc = wp.zeros((h, w), dtype=wp.float64, device=d)
        self.mc = wp.zeros((h, w), dtype=wp.float64, device=d)
        self.normals = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self.albedo = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self.residual = wp.zeros((h, w), dtype=wp.float32, device=d)
        self.flags = wp.zeros((h, w), dtype=wp.int32, device=d)
        self.iterations = wp.zeros((h, w), dtype=wp.int32, device=d)
        self.solve_iterations = wp.zeros((h, w), dtype=wp.int32, device=d)  # the solution's (write_back adds them)
        self.source_normals = wp.zeros(h * w, dtype=wp.vec3, device=d)  # each ring pixel's source's (fetch_sources)
        self.won = wp.zeros((h, w), dtype=wp.uint8, device=d)
        self._plan = None
        self._closed = False

    def upload(self, mask, highlight, solution: dict | None, *, gaussian=None, mean=None,
               config: DGMCConfig | None = None) -> None:
        """Find the rings (:func:`gpps.host.dgmc.front_rings`) and copy them, the curvatures and the solution in.

        Args:
            mask: (H, W) bool object mask.
            highlight: (H, W) bool highlight region (:attr:`gpps.host.dgmc.DGMCResult.highlight`).
            solution: dict with (H, W, 3) ``normals`` and ``albedo`` and (H, W) ``residual`` and ``flags`` of a
                solve of the mask: the sources are its non-highlight pixels; with ``keep_better`` its highlight
                pixels are the alternative each ring's solve must beat.  None: the solver's outputs, as its last
                step left them (copied on the device: no host round trip; :meth:`write_back` returns the merged
                solution there).
            gaussian, mean: (H, W) curvatures (4.16): numpy, or Warp float64 arrays on the solver's device
                (:attr:`gpps.pipeline.dgmc.DeviceDGMC.gc` / ``mc``, read there and rounded to float32 as
                :meth:`gpps.pipeline.dgmc.DeviceDGMC.fetch_start` returns them: the same values, no copy to the
                host); None: the test of 4.17-4.18 is skipped (nearest neighbour).
            config: :class:`gpps.host.dgmc.DGMCConfig` (tolerance, widen_factor, widen_steps).
        """
        self._check_open()
        cfg = DGMCConfig() if config is None else config
        if not isinstance(cfg, DGMCConfig):
            raise TypeError(f"config: expected DGMCConfig, got {type(cfg).__name__}")
        h, w = self.solver.shape[1:]
        m = as_mask("mask", mask, (h, w))
        hl = np.asarray(highlight, bool)
        if hl.shape != (h, w):
            raise ValueError(f"highlight: expected shape ({h}, {w}), got {hl.shape}")
        for k, c in (_SOLUTION if solution is not None else ()):
            shp = (h, w, c) if c else (h, w)
            if k not in solution:
                raise ValueError(f"solution: expected a dict with '{k}', got keys {sorted(solution)}")
            if np.shape(solution[k]) != shp:
                raise ValueError(f"solution['{k}']: expected shape {shp}, got {np.shape(solution[k])}")
        curv = gaussian is not None and mean is not None
        if curv:
            wp = warp()
            for name, a, buf in (("gaussian", gaussian, self.gc), ("mean", mean, self.mc)):
                if isinstance(a, wp.array):
                    if a.shape != (h, w) or a.dtype != wp.float64 or a.device != wp.get_device(self.device):
                        raise ValueError(f"{name}: expected a ({h}, {w}) float64 array on {self.device}, got "
                                         f"{a.shape} {getattr(a.dtype, '__name__', a.dtype)} on {a.device}")
                    wp.launch(fk.curvature_in_kernel, dim=(h, w), inputs=[a], outputs=[buf], device=self.device)
                else:
                    buf.assign(as_array(name, a, shape=(h, w), dtype=np.float64))
        ring, pixels, sizes = front_rings(m, hl)
        n = sizes.size - 1
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        # pixels of each ring per image row (row k: ring k): they balance the solver's CPU row split, and their
        # sum picks its kernel (PixelSolver.select_pixels)
        per = np.repeat(np.arange(n + 1), sizes)
        rows = np.bincount(per * h + pixels // w, minlength=(n + 1) * h).reshape(n + 1, h)
        if pixels.size:
            self.pixels[:pixels.size].assign(pixels.astype(np.int32))
            level = np.where(m & ~hl, 0, np.where(ring > 0, ring, _UNSOLVED)).astype(np.int32)
            self.level.assign(level)
        if solution is None:
            wp = warp()
            s = self.solver
            for k in ("normals", "albedo", "residual", "flags"):
                wp.copy(getattr(self, k), getattr(s, k))
            wp.copy(self.solve_iterations, s.iterations)
        else:
            self.normals.assign(np.asarray(solution["normals"], np.float32))
            self.albedo.assign(np.asarray(solution["albedo"], np.float32))
            self.residual.assign(np.asarray(solution["residual"], np.float32))
            self.flags.assign(np.asarray(solution["flags"], np.int32))
            if "iterations" in solution:
                self.solve_iterations.assign(np.asarray(solution["iterations"], np.int32))
            else:
                self.solve_iterations.zero_()
        self.iterations.zero_()
        self.won.zero_()
        self._plan = (ring, pixels, sizes, starts, rows, curv, cfg)

    def step(self, *, keep_better: bool = True, progress=None) -> None:
        """The sources of every ring pixel, then the rings in order, on the solver's device: per ring the mask, the
        starts, a warm solve and the merge, with no copy between host and device.

        Args:
            keep_better: keep, per highlight pixel, the ring's solve only where its residual is below the
                current solution's and the pixel has 3 lit observations (:func:`gpps.host.merge.ranks_better`:
                an under-determined pixel's residual cannot rank starts); that winner is what later rings start
                from.  False: always the ring's solve.
            progress: optional ``progress(ring, None, message)`` callback, after each ring's launches.
        """
        self._check_open()
        if self._plan is None:
            raise RuntimeError("step: upload() first")
        wp = warp()
        s = self.solver
        w = s.shape[2]
        ring, pixels, sizes, starts, rows, curv, cfg = self._plan
        n = sizes.size - 1
        if n == 0:
            return
        wp.launch(fk.front_source_kernel, dim=pixels.size,
                  inputs=[self.pixels, self.level, self.gc, self.mc, int(curv), float(cfg.tolerance),
                          float(cfg.widen_factor), int(cfg.widen_steps)],
                  outputs=[self.sources], device=self.device)
        # recorded once, then per ring only the slice changes (a launch packs its arguments anew each time)
        start = wp.launch(fk.front_start_kernel, dim=1, inputs=[self.pixels, self.sources, 0, w, self.normals],
                          outputs=[s.normals], device=self.device, record_cmd=True)
        merge = wp.launch(fk.front_merge_kernel, dim=1,
                          inputs=[self.pixels, 0, w, int(bool(keep_better)), int(FLAG_FEW_OBSERVATIONS), s.normals,
                                  s.albedo, s.residual, s.iterations, s.flags],
                          outputs=[self.normals, self.albedo, self.residual, self.flags, self.iterations, self.won],
                          device=self.device, record_cmd=True)
        old = s.config
        s.set_config(replace(old, warm_start=True, starts=1, neighbour_radius=0, smoothness=0.0))
        try:
            for k in range(1, n + 1):
                a, c = int(starts[k]), int(sizes[k])
                s.select_pixels(self.pixels, a, c, rows[k])
                start.set_dim(c)
                start.set_param_at_index(2, a)
                start.launch()
                s.step(subset=True)
                merge.set_dim(c)
                merge.set_param_at_index(1, a)
                merge.launch()
                if progress is not None:
                    progress(k, None, f"DGMC front ring {k}: {c} pixels")
        finally:
            s.set_config(old)

    def write_back(self) -> None:
        """The merged solution into the solver's outputs, on the device (:func:`front_write_back_kernel`): its
        ``normals``, ``albedo``, ``residual`` and ``flags`` become the front's, its ``iterations`` the solution's
        (as uploaded) plus the front solves' (the host path's ``FrontResult`` merge); nothing is copied to the host."""
        self._check_open()
        if self._plan is None:
            raise RuntimeError("write_back: upload() first")
        s = self.solver
        h, w = s.shape[1:]
        warp().launch(fk.front_write_back_kernel, dim=(h, w),
                      inputs=[self.normals, self.albedo, self.residual, self.flags, self.solve_iterations,
                              self.iterations],
                      outputs=[s.normals, s.albedo, s.residual, s.flags, s.iterations], device=self.device)

    def fetch_sources(self) -> tuple[np.ndarray, np.ndarray]:
        """The ring pixels that have a source and their sources' merged normals (one gather on the device, two small
        copies): ``(pixels (M,) int64 flat indices, normals (M, 3) float32)``."""
        self._check_open()
        if self._plan is None:
            raise RuntimeError("fetch_sources: upload() first")
        pixels = self._plan[1]
        if pixels.size == 0:
            return np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
        wp = warp()
        w = self.solver.shape[2]
        wp.launch(fk.front_source_normals_kernel, dim=pixels.size,
                  inputs=[self.pixels, self.sources, w, self.normals], outputs=[self.source_normals],
                  device=self.device)
        src = self.sources[:pixels.size].numpy()  # (only the ring pixels' entries cross)
        nrm = self.source_normals[:pixels.size].numpy()
        has = src >= 0
        return pixels[has].astype(np.int64), nrm[has]

    def fetch(self) -> FrontResult:
        """The merged solution and the front's diagnostics (copies owned by the caller)."""
        self._check_open()
        if self._plan is None:
            raise RuntimeError("fetch: upload() first")
        ring, pixels, sizes = self._plan[:3]
        h, w = ring.shape
        out = {k: np.array(getattr(self, k).numpy(), copy=True)
               for k in ("normals", "albedo", "residual", "flags", "iterations", "won")}
        source = np.full((h, w, 2), -1, np.int32)
        if pixels.size:
            q = self.sources.numpy()[:pixels.size]
            source.reshape(-1, 2)[pixels] = np.stack([q // w, q % w], -1)
        return FrontResult(normals=out["normals"], albedo=out["albedo"], residual=out["residual"],
                           flags=out["flags"], iterations=out["iterations"], ring=ring, source=source,
                           won=out["won"].astype(bool), n_rings=sizes.size - 1)

    def close(self) -> None:
        """Release the device buffers."""
        for name in ("pixels", "sources", "level", "gc", "mc", "normals", "albedo", "residual", "flags",
                     "iterations", "solve_iterations", "source_normals", "won", "_plan"):
            setattr(self, name, None)
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("DeviceFront: the stage is closed")


def propagate_front_device(solver, mask, highlight, *, gaussian=None, mean=None, config: DGMCConfig | None = None,
                           keep_better: bool = True, progress=None, front: DeviceFront | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`propagate_front` from the solver's outputs and back into them, on the device: the solver's last step
    (a solve of the mask) is the solution the rings start from and must beat, and the merged solution replaces it
    there (:meth:`DeviceFront.write_back`), for RON's device rounds; no frame crosses to the host.

    ``front``: a :class:`DeviceFront` on ``solver`` to use (kept by the caller between frames: its buffers are
    allocated once); None: one is built for this call and released after.

    Returns:
        ``(pixels, normals)``: the flat indices (M,) of the ring pixels that had a source, and (M, 3) their sources'
        merged normals (what the host path reads off ``FrontResult.source`` for RON's start normals).
    """
    if front is None:
        with DeviceFront(solver) as own:
            return propagate_front_device(solver, mask, highlight, gaussian=gaussian, mean=mean, config=config,
                                          keep_better=keep_better, progress=progress, front=own)
    if front.solver is not solver:
        raise ValueError("front: expected a DeviceFront on the given solver")
    front.upload(mask, highlight, None, gaussian=gaussian, mean=mean, config=config)
    front.step(keep_better=keep_better, progress=progress)
    front.write_back()
    return front.fetch_sources()


def propagate_front(solver, images, mask, highlight, solution: dict, *, gaussian=None, mean=None, depth=None,
                    valid=None, config: DGMCConfig | None = None, keep_better: bool = True,
                    progress=None) -> FrontResult:
    """DGMC on the solved front: highlight pixels start from their solved neighbours, ring by ring, on the
    solver's device (:class:`DeviceFront`; the rule and why: this module's docstring).

    Args:
        solver: a :class:`gpps.pipeline.solver.PixelSolver` for the frame's shape; its config is replaced for the
            front solves (``warm_start=True``, ``starts=1``, no neighbour pass, no smoothness) and restored after.
        images: (N, H, W) or (N, H, W, 3) the frame (uploaded once), or None when the solver already holds it
            (its last upload; ``depth`` and ``valid`` then unused).
        mask: (H, W) bool object mask.
        highlight: (H, W) bool highlight region (:attr:`gpps.host.dgmc.DGMCResult.highlight`).
        solution: dict with (H, W, 3) ``normals`` and ``albedo`` and (H, W) ``residual`` and ``flags`` of a solve
            of the mask: the sources are its non-highlight pixels; with ``keep_better`` its highlight pixels are
            the alternative each front solve must beat.
        gaussian, mean: (H, W) curvatures (4.16, :attr:`gpps.host.dgmc.DGMCResult.gaussian` / ``mean``); None:
            the test of 4.17-4.18 is skipped (nearest neighbour).
        depth, valid: as :meth:`PixelSolver.upload` (depth needed for point lights).
        config: :class:`gpps.host.dgmc.DGMCConfig` (tolerance, widen_factor, widen_steps).
        keep_better: keep, per highlight pixel, the front solve only where its residual is below the given
            solution's (and the pixel has 3 lit observations: an under-determined pixel's residual cannot rank
            starts); that winner is what later rings start from.  False: always the front solve.
        progress: optional ``progress(ring, None, message)`` callback.

    Returns:
        :class:`gpps.host.dgmc.FrontResult`.
    """
    with DeviceFront(solver) as front:
        front.upload(mask, highlight, solution, gaussian=gaussian, mean=mean, config=config)
        if images is not None:
            m = np.asarray(mask, bool)
            start = np.where(m[..., None], np.asarray(solution["normals"], np.float32), 0.0)
            solver.upload(images, m, depth=depth, valid=valid, init_normals=start)
        front.step(keep_better=keep_better, progress=progress)
        return front.fetch()
