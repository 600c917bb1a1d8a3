"""The integrator's system assembled and solved on the device, from a normal map already there.

:class:`DeviceSystem` is a second front end of one :class:`gpps.pipeline.integration.Integrator`: it
builds the system ``Integrator.upload`` builds on the host (same checks, steps, ``"uniform"`` or
``"normal"`` (BiNI's ``N_z^2``) weighting, perspective log-depth) in the integrator's own Taichi
fields (:mod:`gpps.kernels.poisson_weighted`), with the multigrid hierarchy for those weights
(``coarse_alpha``: 1/2 for uniform weights, 2/3 for weighted ones, as ``Integrator._upload_levels``)
and the coarsest level's exact pseudo-inverse (its at most 2 x 16 x 16 edge weights read back: the
host's numpy pseudo-inverse, ``Integrator.set_coarsest``, ~1 ms, where one serial GPU task took 15 ms),
then runs the integrator's own
multigrid-preconditioned CG (``Integrator._iterate``, same tolerance, one float64 scalar read every
``check_every`` iterations) from ``u = 0`` (as RON's host rounds), and writes the depth (mean 0 per
component, ``exp``, mean ``reference_depth`` per component: ``Integrator.fetch``; dropped pixels filled
by the mean depth: RON's ``_fill_depth``) into a float32 (H, W) array on the device.

The normals and the output are read and written in place: numpy views of CPU Warp arrays, or on CUDA
torch views of Warp arrays (``wp.to_torch``, zero-copy; torch is the ``gpps[cuda]`` extra, as for the
stream).  Only scalars come back: the invalid-pixel count, the CG residual checks, the fill value.

Component constants use the connected components of the mask, labelled once; a normal map with
invalid pixels (NaN, zero or back-facing inside the mask, dropped as the host drops them), whose
valid pixels may split into other components, has them labelled on the device
(:func:`gpps.kernels.poisson_weighted.label_hook`).  The host path's fields are shared: its cached
levels are marked stale after each device solve.
"""

from __future__ import annotations

import threading

import numpy as np
from scipy import ndimage

from gpps import _taichi
from gpps.kernels import poisson_weighted as KW
from gpps.pipeline.integration import Integrator, IntegratorConfig, coarse_alpha
from gpps.pipeline.stage import Stage

__all__ = ["DeviceSystem"]

# fields of closed device systems, by (Taichi device, H, W, the coarsest level's shape): Taichi compiles
# the kernels for each set of fields (as the integrator's own pool, gpps.pipeline.integration._POOL)
_POOL: dict = {}
_POOL_LOCK = threading.Lock()


class DeviceSystem(Stage):
    """Device assembly and solve of an :class:`Integrator`'s system (plain multigrid only).

    Args:
        integrator: the integrator whose fields, levels and CG are used (its mask, camera and config).

    Raises:
        ValueError: a config the device path does not build (see :meth:`supports`).
    """

    def __init__(self, integrator: Integrator):
        if not isinstance(integrator, Integrator):
            raise TypeError(f"integrator: expected gpps.pipeline.integration.Integrator, got {type(integrator).__name__}")
        if not self.supports(integrator.config):
            raise ValueError("integrator: expected config with solver='multigrid', robust='none', bilateral=False "
                             f"(the device assembly builds the plain Poisson system), got {integrator.config}")
        self.integrator = integrator
        ti = _taichi.init(integrator.device)
        d = integrator._ensure_device()
        h, w = self.shape = integrator.shape
        cam = integrator.camera
        cx, cy = cam.principal_point(self.shape)
        if cam.is_perspective:
            self._cam = (1, float(cam.fx), float(cam.fy), float(cx), float(cy), 1.0)
        else:
            self._cam = (0, 1.0, 1.0, float(cx), float(cy), float(cam.pixel_size))
        self._weighted = int(integrator.config.weighting == "normal")
        lab, ncomp = ndimage.label(integrator.mask)
        hc, wc = d["shapes"][-1]
        self._key = (_taichi.current_device(), h, w, hc, wc)
        with _POOL_LOCK:
            free = _POOL.get(self._key)
            F = free.pop() if free else None
        if F is None:
            F = self._allocate(ti, h, w, hc, wc)
        F["mask"].from_numpy(integrator.mask.astype(np.int32))
        # a component's label: its first pixel's flat index (as the device labelling's roots)
        first = np.full(ncomp + 1, h * w, np.int64)
        flat = lab.ravel()
        idx = np.flatnonzero(flat)
        np.minimum.at(first, flat[idx], idx)
        F["lab_mask"].from_numpy(np.where(lab > 0, first[lab], -1).astype(np.int32))
        self._F = F
        self.last = {}

    @staticmethod
    def _allocate(ti, h, w, hc, wc) -> dict:
        fb = ti.FieldsBuilder()
        F = {}
        for name, dt in (("mask", ti.i32), ("lab", ti.i32), ("lab_mask", ti.i32), ("gj", ti.f64), ("gi", ti.f64), ("cj", ti.f64),
                         ("ci", ti.f64)):
            F[name] = ti.field(dt)
            fb.dense(ti.ij, (h, w)).place(F[name])
        F["st"] = ti.field(ti.f64)
        fb.dense(ti.i, 8).place(F["st"])
        for name in ("csum", "ccnt", "cden", "cmax", "cmin"):
            F[name] = ti.field(ti.f64)
            fb.dense(ti.i, h * w).place(F[name])  # indexed by a component's root pixel
        F["lvl"] = ti.field(ti.f64)  # the coarsest level's edge weights (gather_level)
        fb.dense(ti.ijk, (2, hc, wc)).place(F["lvl"])
        F["tree"] = fb.finalize()
        return F

    @staticmethod
    def supports(config: IntegratorConfig) -> bool:
        """Whether the device path builds ``config``'s system: the plain (non-robust, non-bilateral)
        multigrid solve with ``"uniform"`` or ``"normal"`` weighting."""
        return (config.solver == "multigrid" and config.robust == "none" and not config.bilateral
                and config.weighting in ("uniform", "normal"))

    def upload(self, *args, **kwargs) -> None:
        """Nothing to copy: :meth:`step` reads the normals where they are (another stage's buffer)."""

    def step(self, normals, out, *, reference_depth: float | None, outside: float = 1.0) -> bool:
        """Integrate ``normals`` into ``out`` on the device.

        Args:
            normals: (H, W, 3) float32 normals (a numpy view of a CPU Warp array, or a CUDA torch view).
            out: (H, W) float32 array of the same kind: the depth (valid pixels), the mean depth
                (dropped mask pixels), ``outside`` (outside the mask).
            reference_depth: mean depth per component (> 0); None: none, the depth as
                :meth:`gpps.pipeline.integration.Integrator.fetch` normalises it without one (perspective ``exp`` of a
                log-depth of mean 0 per component, orthographic a depth of mean 0 per component).
            outside: the value outside the mask.

        Returns:
            False (nothing solved, ``out`` untouched) when fewer than 2 normals are valid: the caller
            integrates on the host (which raises the host's error).
        """
        integ, F = self.integrator, self._F
        if F is None:
            raise ValueError("DeviceSystem: expected an open stage, got a closed one")
        cfg = integ.config
        h, w = self.shape
        persp = self._cam[0]
        F["st"].fill(0)
        KW.assemble_pixels(normals, F["mask"], F["gj"], F["gi"], F["cj"], F["ci"], F["st"], persp, self._weighted,
                           *self._cam[1:], float(cfg.min_nz), h, w)
        return self._solve_assembled(out, reference_depth, outside, self._weighted)

    def step_increment(self, steps, conf, base, out, wplus=None, tol: float | None = None) -> bool:
        """Solve the weighted system of per-pixel step *increments* and confidences and move ``base`` by its
        solution into ``out``, on the device: :class:`gpps.pipeline.depth_refine.DepthRefiner`'s Gauss-Newton
        step (:mod:`gpps.kernels.depth_refine`).  Increments, not targets: with zero increments the solution
        is zero and ``out = base`` (a target system would also pull ``base``'s edge differences toward the
        average of its pixels' steps, a smoothing move no damping removes).

        Args:
            steps: (H, W, 2) float32 increments of the steps ``(du/dj, du/di)`` (views as :meth:`step` takes).
            conf: (H, W, 2) float32 confidences (> 0: the pixel is in the system; divided by their mean,
                as ``"normal"`` weighting does).
            base: (H, W) float32 depth to move.
            out: (H, W) float32: ``u(out) = u(base) + du`` with ``du`` of mean 0 per component (``u``: the
                log-depth under perspective, the depth otherwise); ``base`` where a pixel is not in the system.
            wplus: optional (H, W, 2) float32 forward shares of each pixel's term along j and i (BiNI's ``w+``;
                None: 1/2, the central split).
            tol: the CG's relative residual (None: the integrator's ``config.tol``).

        Returns:
            False when fewer than 2 pixels have positive confidences (nothing written).
        """
        integ, F = self.integrator, self._F
        if F is None:
            raise ValueError("DeviceSystem: expected an open stage, got a closed one")
        h, w = self.shape
        F["st"].fill(0)
        KW.assemble_targets(steps, conf, F["mask"], F["gj"], F["gi"], F["cj"], F["ci"], F["st"], h, w)
        # (alpha 1: the refinement's Levenberg-Marquardt steps were validated with the Galerkin levels)
        if not self._solve_system(1, wplus, alpha=1.0, tol=tol):
            return False
        d = integ._ensure_device()
        KW.component_sums(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], F["cmax"], F["cmin"], F["st"], h, w)
        KW.depth_add(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], base, out, self._cam[0], h, w)
        return True

    def _solve_system(self, weighted: int, wplus=None, alpha: float | None = None, tol: float | None = None) -> bool:
        """Edges, levels, the coarsest pseudo-inverse and the CG from ``z = 0`` once ``gj, gi, cj, ci`` and the
        statistics are assembled; False (``last`` holds the invalid count) when fewer than 2 pixels are valid.
        ``alpha``: the coarse levels' scale (None: :func:`gpps.pipeline.integration.coarse_alpha` of the system,
        as the host path's); ``tol``: the CG's relative residual (None: the integrator's ``config.tol``)."""
        integ, F = self.integrator, self._F
        d = integ._ensure_device()
        cfg = integ.config
        h, w = self.shape
        st = F["st"].to_numpy()  # (one read of the 8 statistics)
        invalid = int(st[KW.N_INVALID])
        if st[KW.N_VALID] < 2:
            self.last = {"invalid": invalid}
            return False
        if invalid:
            self._label(h, w)
        else:
            F["lab"].copy_from(F["lab_mask"])
        if wplus is None:
            KW.assemble_edges(F["gj"], F["gi"], F["cj"], F["ci"], F["st"], weighted, d["wx"], d["wy"], d["dg"],
                              d["b"], h, w)
        else:
            KW.assemble_edges_split(F["gj"], F["gi"], F["cj"], F["ci"], wplus, F["st"], d["wx"], d["wy"], d["dg"],
                                    d["b"], h, w)
        sh, of = d["shapes"], d["offs"]
        if alpha is None:
            alpha = coarse_alpha(not weighted, False)  # (Integrator._upload_levels' rule; no IRLS here)
        for k in range(len(sh) - 1):
            KW.coarsen(d["wx"], d["wy"], d["dg"], int(of[k]), sh[k][0], sh[k][1], int(of[k + 1]), sh[k + 1][0],
                       sh[k + 1][1], alpha)
        hc, wc = sh[-1]
        KW.gather_level(d["wx"], d["wy"], int(of[len(sh) - 1]), hc, wc, F["lvl"])
        lvl = F["lvl"].to_numpy()  # (2 x at most 16 x 16 values)
        integ.set_coarsest(lvl[0], lvl[1])
        integ._levels_key = None  # the host path must upload its own levels again
        d["z"].fill(0)
        its, res = integ._iterate(None, cfg.tol if tol is None else float(tol))
        self.last = {"invalid": invalid, "iterations": int(its), "residual": float(res)}
        return True

    def _solve_assembled(self, out, reference_depth, outside, weighted: int) -> bool:
        """The rest of :meth:`step` once ``gj, gi, cj, ci`` and the statistics are assembled."""
        if not self._solve_system(weighted):
            return False
        integ, F = self.integrator, self._F
        d = integ._ensure_device()
        h, w = self.shape
        persp = self._cam[0]
        KW.component_sums(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], F["cmax"], F["cmin"], F["st"], h, w)
        referenced = reference_depth is not None
        if persp and referenced:
            KW.depth_exp(d["z"], F["cj"], F["lab"], F["cmax"], F["cden"], h, w)
        ref = float(reference_depth) if referenced else 0.0  # (unreferenced orthographic: u + 0)
        KW.depth_write(d["z"], F["cj"], F["lab"], F["csum"], F["ccnt"], F["cmax"], F["cden"], F["st"], out, persp, ref,
                       int(referenced), h, w)
        KW.depth_fill(F["cj"], F["lab"], F["mask"], F["st"], out, ref, float(outside), int(referenced), h, w)
        return True

    def _label(self, h, w) -> None:
        """The components of the valid pixels into ``lab`` (one flag read a hooking pass)."""
        F = self._F
        KW.label_init(F["cj"], F["lab"], h, w)
        while True:
            F["st"][KW.CHANGED] = 0.0
            KW.label_hook(F["lab"], F["st"], h, w)
            KW.label_compress(F["lab"], h, w)
            if F["st"][KW.CHANGED] == 0.0:
                break

    def fetch(self) -> dict:
        """The last :meth:`step`'s scalars: ``invalid`` (mask pixels with invalid normals), and after a
        solve ``iterations``, ``residual`` (the CG's relative residual), ``fill`` (the mean depth of
        the valid pixels) and ``span`` (the largest range of the solution within a component: the log-depth's
        under perspective; one read of the statistics)."""
        out = dict(self.last)
        if "iterations" in out:
            st = self._F["st"].to_numpy()  # (one read of the 8 statistics)
            n = float(st[KW.FILL_N])
            out["fill"] = float(st[KW.FILL_SUM]) / n if n > 0 else float("nan")
            out["span"] = float(st[KW.SPAN])
        return out

    def close(self) -> None:
        """Give this path's own fields back to the pool of this process (the integrator's stay with it)."""
        if self._F is not None:
            F, self._F = self._F, None
            with _POOL_LOCK:
                _POOL.setdefault(self._key, []).append(F)
