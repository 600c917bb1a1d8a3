"""RON's rounds on the device: normals, depth and the round's scalars stay where the solver put them.

:class:`DeviceRounds` owns what a RON round (:mod:`gpps.flows.ron`, seed Algorithm 2) needs beside
the pixel solver and the integrator, on the solver's device:

* the previous round's normals (the warm start of the next solve and the reference of the normal
  change), copied device to device from the solver's buffer;
* the round's energy (mean squared residual over the mask) and mean normal change (degrees), as
  float64 device sums (:data:`gpps.kernels.ron.round_sums_kernel`): three scalars come back;
* step 3: the solver's normals integrated by :class:`gpps.pipeline.integration_rounds.DeviceSystem`
  (the integrator's system, assembled and solved on the device) into a depth buffer, handed to the
  solver with :meth:`PixelSolver.set_depth_device` (point lights move with it).

Warp and Taichi share the buffers without copies: numpy views of the CPU Warp arrays, or on CUDA
``wp.to_torch`` views (torch: the ``gpps[cuda]`` extra, as for the stream), with a device
synchronisation at each hand-over.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np

from gpps import _taichi
from gpps._runtime import warp
from gpps.kernels.ron import ROUND_CHUNK, round_sums_kernel
from gpps.pipeline.integration import Integrator
from gpps.pipeline.integration_rounds import DeviceSystem
from gpps.pipeline.solver import PixelSolver
from gpps.pipeline.stage import Stage

__all__ = ["DeviceRounds"]


class DeviceRounds(Stage):
    """The device side of RON's rounds for one solver, mask and (optional) integrator.

    Args:
        solver: the RON's :class:`PixelSolver` (its ``normals``, ``residual`` and ``depth`` buffers).
        mask: (H, W) bool, RON's mask.
        integrator: the rounds' :class:`Integrator` (None, or a config :meth:`DeviceSystem.supports`
            rejects: no device integration, :attr:`integrates` False).
    """

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches (:meth:`gpps.flows.ron.RON.kernel_plan`)."""
        return [round_sums_kernel.module]

    def __init__(self, solver: PixelSolver, mask, integrator: Integrator | None = None):
        wp = warp()
        self.solver = solver
        self.device = solver.device
        # (settled at the first step, not here: RON builds this stage at a run's start and steps it after round
        # 1's solve; settling here took a first run's queued compile of it off the helper, to be built later on
        # the run's own thread: 1.5 s of DiLiGenT ball's first run on the 2-core CPU, perf/results/s43)
        self._settled = False
        n, h, w = solver.shape
        m = np.asarray(mask, bool)
        if m.shape != (h, w):
            raise ValueError(f"mask: expected shape ({h}, {w}), got {m.shape}")
        self.mask = wp.array(m.astype(np.uint8), dtype=wp.uint8, device=self.device)
        self.prev = wp.zeros((h, w), dtype=wp.vec3, device=self.device)
        self.depth = wp.ones((h, w), dtype=wp.float32, device=self.device)
        self.sums = wp.zeros(3, dtype=wp.float64, device=self.device)
        self.system = None
        self._views = None
        if integrator is not None and DeviceSystem.supports(integrator.config):
            self.system = DeviceSystem(integrator)
        self.last = {}

    @property
    def integrates(self) -> bool:
        """Whether :meth:`integrate` runs on the device."""
        return self.system is not None

    def _view(self):
        """Zero-copy views for Taichi of the solver's normals, this depth buffer and :attr:`prev` (made once)."""
        if self._views is None:
            wp = warp()
            if self.device.startswith("cuda"):
                if importlib.util.find_spec("torch") is None:
                    raise ImportError("RON's device rounds on CUDA need PyTorch for zero-copy views of the Warp "
                                      "buffers: pip install 'gpps[cuda]' (or RONConfig(device_rounds=False))")
                self._views = (wp.to_torch(self.solver.normals), wp.to_torch(self.depth), wp.to_torch(self.prev))
            else:
                self._views = (self.solver.normals.numpy(), self.depth.numpy(), self.prev.numpy())
        return self._views

    def upload(self, prev) -> None:
        """The previous normals (H, W, 3) from the host (round 1's start, or a round solved on the host)."""
        n, h, w = self.solver.shape
        a = np.ascontiguousarray(prev, dtype=np.float32)
        if a.shape != (h, w, 3):
            raise ValueError(f"prev: expected shape ({h}, {w}, 3), got {a.shape}")
        self.prev.assign(a)

    def step(self) -> None:
        """The round's sums (squared residuals, normal changes against :attr:`prev`, pixels), then
        :attr:`prev` = the solver's normals; no host sync."""
        wp = warp()
        if not self._settled:
            self._settle(*self.kernel_modules())
            self._settled = True
        s = self.solver
        self.sums.zero_()
        h, w = s.shape[1:]
        wp.launch(round_sums_kernel, dim=(h, (w + ROUND_CHUNK - 1) // ROUND_CHUNK),
                  inputs=[self.mask, s.residual, s.normals, self.prev, self.sums], device=self.device)
        wp.copy(self.prev, s.normals)

    def fetch(self) -> dict:
        """``energy`` (mean squared residual over the mask) and ``change_deg`` (mean angle between the
        round's and the previous normals, degrees) of the last :meth:`step`: three float64 scalars read."""
        se, sa, cnt = (float(v) for v in self.sums.numpy())
        cnt = max(cnt, 1.0)
        return {"energy": se / cnt, "change_deg": math.degrees(sa / cnt)}

    def integrate(self, reference_depth: float | None, *, into_solver: bool = True, normals=None) -> bool:
        """Step 3 on the device: the solver's normals to :attr:`depth` (filled, mean ``reference_depth``);
        with ``into_solver`` copied into the solver's depth buffer.  False: fewer than 2 normals were
        valid (nothing written; integrate on the host).  ``reference_depth`` None (the final depth of a
        run without one; not ``into_solver``): normalised as :meth:`DeviceSystem.step` says.

        ``normals``: (H, W, 3) host normals to integrate instead of the solver's (RON's final depth after
        a round solved on the host): copied into :attr:`prev` (one upload), which the rounds no longer
        need then."""
        if self.system is None:
            raise ValueError("integrator: expected one the device path supports, got none")
        if reference_depth is None and into_solver:
            raise ValueError("reference_depth: expected a depth (> 0) for a depth the solver uses, got None")
        nrm, dep, prev = self._view()
        if normals is not None:
            self.upload(normals)
            nrm = prev
        if self.device.startswith("cuda"):
            warp().synchronize_device(self.device)
        ok = self.system.step(nrm, dep, reference_depth=reference_depth)
        if self.device.startswith("cuda"):
            _taichi.ti.sync()
        self.last = self.system.fetch()
        if ok:
            if reference_depth is not None and not self.last["fill"] > 0:
                raise ValueError(f"depth: expected a positive integrated depth, got mean {self.last['fill']:g}")
            if into_solver:
                self.solver.set_depth_device(self.depth)
        return ok

    def depth_host(self) -> np.ndarray:
        """A host copy of the last integrated depth (H, W) (for host rules that need it)."""
        return np.array(self.depth.numpy(), copy=True)

    def close(self) -> None:
        """Free the device integration's own fields and the views."""
        self._views = None
        if self.system is not None:
            self.system.close()
            self.system = None
