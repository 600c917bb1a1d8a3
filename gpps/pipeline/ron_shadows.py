"""RON's cast-shadow pass (issue 25): each round's visibility from the round's depth, into the solver's ``valid``.

:class:`RoundShadows` wraps :class:`gpps.pipeline.shadows.CastShadows` for one :class:`PixelSolver`:

* :meth:`RoundShadows.capture` keeps a device copy of the solver's ``valid`` as uploaded (the caller's
  observation mask): the **original** observations;
* :meth:`RoundShadows.step` marches over a depth map (a device buffer: the device rounds' integrated depth,
  no host copy; or a host array, uploaded) and writes ``valid = original & not cast-shadowed`` into the
  solver's ``valid`` (:data:`gpps.kernels.shadows.shadowed_valid_kernel`; cast-shadowed: hidden from the light
  and facing it, by the solver's current normals, :data:`FACING_MIN`): recomputed from the original every round, so
  an observation wrongly shadowed by one round's depth comes back when the next depth lights it;
* a pixel the shadows would leave with fewer than 3 valid observations either keeps its original ones
  (``few="keep"``) or loses them (``few="flag"``: the solver flags it ``FLAG_FEW_OBSERVATIONS``, as every
  pixel with fewer than 3 lit observations, and gives it its neighbour pass); counted either way;
* :meth:`RoundShadows.fetch` reads three counters (observations dropped, pixels kept, pixels left with
  fewer than 3); :meth:`RoundShadows.valid_host` / :meth:`RoundShadows.shadowed` copy the masks to the
  host (the material fit's sample, the result).
"""

from __future__ import annotations

import numpy as np

from gpps._runtime import warp
from gpps.kernels.shadows import shadowed_valid_kernel
from gpps.pipeline.shadows import CastShadows, ShadowConfig
from gpps.pipeline.solver import PixelSolver
from gpps.pipeline.stage import Stage

__all__ = ["RoundShadows", "FEW_RULES"]

#: the rules for a pixel the shadows would leave with fewer than 3 valid observations
FEW_RULES = ("flag", "keep")
#: an observation the march finds hidden is dropped only where the round's normal faces its light (n . l above
#: this): behind the terminator the ray enters the object's own surface, an attached shadow that the image model
#: already explains (shading 0), whose dark observations constrain the normal.  Measured on DiLiGenT ball (96
#: images, no cast shadows; only a final check): without this test the pass dropped ~100,000 observations a round,
#: MAEN 1.7876 -> 1.7961 deg
FACING_MIN = 0.0


class RoundShadows(Stage):
    """The cast-shadow pass of RON's rounds for one solver and mask.

    Args:
        solver: the :class:`PixelSolver` whose ``valid`` the pass rewrites (its camera, lights, device).
        mask: (H, W) bool, RON's mask (the pixels that occlude and whose observations are tested).
        config: :class:`ShadowConfig` of the march.
        few: ``"keep"`` or ``"flag"`` (module docstring).
    """

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches (:meth:`gpps.flows.ron.RON.kernel_plan`)."""
        return [shadowed_valid_kernel.module]

    def __init__(self, solver: PixelSolver, mask, config: ShadowConfig | None = None, few: str = "keep"):
        wp = warp()
        if few not in FEW_RULES:
            raise ValueError(f"few: expected one of {list(FEW_RULES)}, got {few!r}")
        self.solver = solver
        self.device = solver.device
        self._settle(*self.kernel_modules())
        n, h, w = solver.shape
        m = np.asarray(mask, bool)
        if m.shape != (h, w):
            raise ValueError(f"mask: expected shape ({h}, {w}), got {m.shape}")
        self.shape = (n, h, w)
        self.few = few
        self.march = CastShadows(self.shape, solver.camera, solver.lights, config, device=self.device)
        self.mask = self._buffer((h, w), wp.uint8, self.device)
        self.mask.assign(m.astype(np.uint8))
        self._mask_host = m.copy()
        self.valid0 = self._buffer((n, h, w), wp.uint8, self.device, fill=1)
        self.counts = self._buffer(3, wp.int32, self.device)
        self.steps = 0

    def capture(self) -> None:
        """The solver's ``valid`` as it is now (right after its upload) becomes the original observations."""
        warp().copy(self.valid0, self.solver.valid)
        self.steps = 0

    def upload(self, depth) -> None:
        """A host depth map (H, W) (> 0 in the mask) for the next :meth:`step` without a device depth."""
        self.march.upload(depth, self._mask_host)

    def step(self, depth=None) -> None:
        """The visibility of every light from ``depth`` (an (H, W) float32 Warp array on the solver's device,
        > 0 in the mask; None: the uploaded one), then the solver's ``valid`` from the original observations;
        the counters are reset first.  No host sync."""
        wp = warp()
        self.march.step(depth=depth, mask=self.mask)
        self.counts.zero_()
        m = self.march
        wp.launch(shadowed_valid_kernel, dim=self.shape[1:],
                  inputs=[self.valid0, m.visible, self.mask, self.solver.normals, m.depth if depth is None else depth,
                          m.cam, m.lp, FACING_MIN, 3 if self.few == "keep" else 0, self.solver.valid, self.counts],
                  device=self.device)
        self.steps += 1

    def restore(self) -> None:
        """The solver's ``valid`` back to the original observations."""
        warp().copy(self.solver.valid, self.valid0)

    def fetch(self) -> dict:
        """The last :meth:`step`'s counts: ``dropped`` observations, ``kept_pixels`` (pixels that kept their
        original observations, ``few="keep"``), ``few_pixels`` (pixels left with fewer than 3)."""
        d, k, f = (int(v) for v in self.counts.numpy())
        return {"dropped": d, "kept_pixels": k, "few_pixels": f}

    def valid_host(self) -> np.ndarray:
        """(N, H, W) bool copy of the solver's ``valid`` (after the last :meth:`step`)."""
        return self.solver.valid.numpy().astype(bool)

    def shadowed(self) -> np.ndarray:
        """(N, H, W) bool: the observations the last :meth:`step` dropped (original and no longer valid)."""
        return self.valid0.numpy().astype(bool) & ~self.solver.valid.numpy().astype(bool)

    def close(self) -> None:
        self.march.close()
        self._release_buffers()  # (the pool's: a later RON of this size takes them)
        for name in ("mask", "valid0", "counts"):
            self.__dict__.pop(name, None)
