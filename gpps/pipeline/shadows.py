"""Cast-shadow masks from a depth map, on the device: the stage :class:`CastShadows`.

Once a depth exists (RON's integrated depth, a solver's ``depth`` buffer) each light's visibility is found by
marching from every mask pixel toward the light over the depth map (:mod:`gpps.kernels.shadows` has the rule,
the sampling and the tolerance).  The result is an (N, H, W) uint8 buffer, 1 = lit, like
:attr:`gpps.pipeline.solver.PixelSolver.valid`; :meth:`CastShadows.apply` ANDs it into such a buffer on the
device so that the next solve drops the shadowed observations.  The depth and the mask can come from the host
(:meth:`CastShadows.upload`) or stay on the device (``step(depth=solver.depth, mask=solver.mask)``: no copy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps._check import as_array, as_mask, check_number
from gpps._runtime import resolve_device, warp
from gpps.kernels import shadows as sk
from gpps.lights import DirectionalLights, PointLights
from gpps.pipeline.params import camera_params, light_params
from gpps.pipeline.stage import Stage

__all__ = ["ShadowConfig", "CastShadows"]


@dataclass(frozen=True)
class ShadowConfig:
    """Settings of the march (:mod:`gpps.kernels.shadows`).

    Attributes:
        tolerance_px: ``tau``, the tolerance in pixel widths (the side of a pixel on the surface): an
            observation is shadowed where the depth map lies in front of the ray by more than ``tau`` pixel
            widths.  1.0 (chosen in tests/test_shadows.py: with depth noise of 0.3 pixel widths rms the
            analytic scenes keep IoU >= 0.95 from tau = 1; the shadow of an occluder of height ``h`` loses
            ``tau / h`` of its length, 2.5 % for ``h`` = 40 pixel widths).
        step_px: distance between samples along the ray's image, pixels (> 0, <= 2).
        max_steps: the most samples of one ray (then lit); None: ``2 (H + W) / step_px``, enough to cross
            the image.
    """

    tolerance_px: float = 1.0
    step_px: float = 1.0
    max_steps: int | None = None

    def __post_init__(self):
        check_number("tolerance_px", self.tolerance_px, lo=0.0)
        check_number("step_px", self.step_px, lo=0.0, hi=2.0, lo_open=True)
        if self.max_steps is not None:
            check_number("max_steps", self.max_steps, lo=1, integer=True)


def _shape(shape, lights) -> tuple[int, int, int]:
    try:
        n, h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise TypeError(f"shape: expected (N, H, W) integers, got {shape!r}") from None
    if n < 1 or h < 1 or w < 1 or tuple(shape) != (n, h, w):
        raise ValueError(f"shape: expected (N, H, W) positive integers, got {shape!r}")
    if not isinstance(lights, (DirectionalLights, PointLights)):
        raise TypeError(f"lights: expected DirectionalLights or PointLights, got {type(lights).__name__}")
    if len(lights) != n:
        raise ValueError(f"lights: expected {n} lights (shape[0]), got {len(lights)}")
    return n, h, w


class CastShadows(Stage):
    """Each light's cast-shadow mask of one (H, W) depth map; buffers allocated once.

    Args:
        shape: (N, H, W): lights and image size.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        lights: :class:`gpps.lights.DirectionalLights` or :class:`gpps.lights.PointLights` (N).
        config: :class:`ShadowConfig`.
        device: Warp device (None: CUDA if present, else CPU).

    ``upload(depth, mask)`` (host arrays), ``step(depth=None, mask=None)`` (the uploaded buffers, or (H, W)
    float32 / uint8 Warp arrays on this device, read in place), ``fetch()`` -> (N, H, W) bool, 1 = lit;
    ``apply(valid)`` ANDs the visibility into an (N, H, W) uint8 Warp array (``PixelSolver.valid``).
    Off the mask the visibility is 1 (so ``apply`` leaves it alone); an empty mask gives all ones.
    """

    Config = ShadowConfig

    def __init__(self, shape, camera, lights, config: ShadowConfig | None = None, device=None):
        wp = warp()
        n, h, w = _shape(shape, lights)
        self.config = ShadowConfig() if config is None else config
        if not isinstance(self.config, ShadowConfig):
            raise TypeError(f"config: expected CastShadows.Config, got {type(self.config).__name__}")
        self.device = resolve_device(device)
        self.shape = (n, h, w)
        self.cam = camera_params(camera, (h, w))
        self.lights = lights
        self.lp = light_params(lights, self.device)
        d = self.device
        self.depth = wp.ones((h, w), dtype=wp.float32, device=d)
        self.mask = wp.zeros((h, w), dtype=wp.uint8, device=d)
        self.visible = wp.ones((n, h, w), dtype=wp.uint8, device=d)
        self.dmin = wp.zeros(1, dtype=wp.float32, device=d)
        c = self.config
        self.max_steps = int(c.max_steps) if c.max_steps is not None else int(np.ceil(2 * (h + w) / c.step_px))
        self._closed = False

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("CastShadows: the stage is closed")

    def _device_array(self, name, a, shape, dtype):
        wp = warp()
        if not isinstance(a, wp.array):
            raise TypeError(f"{name}: expected a Warp array, got {type(a).__name__}")
        if tuple(a.shape) != shape or a.dtype != dtype:
            raise ValueError(f"{name}: expected a {shape} {wp.types.type_repr(dtype)} Warp array, got shape "
                             f"{tuple(a.shape)} {wp.types.type_repr(a.dtype)}")
        if str(a.device) != self.device:
            raise ValueError(f"{name}: expected an array on {self.device}, got one on {a.device}")
        return a

    def upload(self, depth, mask) -> None:
        """Copy a depth map and its mask into the stage's buffers.

        Args:
            depth: (H, W) depth (scene units), finite and > 0 inside the mask (ignored outside).
            mask: (H, W) bool: the object (may be empty).
        """
        self._check_open()
        n, h, w = self.shape
        m = as_mask("mask", mask, (h, w), allow_empty=True)
        dep = as_array("depth", depth, shape=(h, w), finite=False)
        if not np.all(np.isfinite(dep[m])) or np.any(dep[m] <= 0):
            raise ValueError("depth: expected finite values > 0 inside the mask")
        self.depth.assign(np.where(m, dep, 1.0).astype(np.float32))
        self.mask.assign(m.astype(np.uint8))

    def step(self, depth=None, mask=None) -> None:
        """Launch the march on the device (nothing is copied; the host does not wait).

        Args:
            depth: None (the uploaded depth) or an (H, W) float32 Warp array on this device, > 0 in the mask
                (the caller guarantees it, as for :meth:`gpps.pipeline.solver.PixelSolver.set_depth_device`).
            mask: None (the uploaded mask) or an (H, W) uint8 Warp array on this device.
        """
        wp = warp()
        self._check_open()
        n, h, w = self.shape
        dep = self.depth if depth is None else self._device_array("depth", depth, (h, w), wp.float32)
        m = self.mask if mask is None else self._device_array("mask", mask, (h, w), wp.uint8)
        self.dmin.fill_(float(sk.BIG))
        wp.launch(sk.min_depth_kernel, dim=(h, w), inputs=[dep, m, self.dmin], device=self.device)
        c = self.config
        wp.launch(sk.cast_shadow_kernel, dim=(n, h, w),
                  inputs=[dep, m, self.cam, self.lp, self.dmin, float(c.tolerance_px), float(c.step_px),
                          self.max_steps, self.visible], device=self.device)

    def apply(self, valid) -> None:
        """``valid &= visible`` on the device: drop the shadowed observations from an (N, H, W) uint8 Warp
        array on this device (e.g. :attr:`gpps.pipeline.solver.PixelSolver.valid`)."""
        wp = warp()
        self._check_open()
        v = self._device_array("valid", valid, self.shape, wp.uint8)
        wp.launch(sk.and_visible_kernel, dim=self.shape, inputs=[self.visible, v], device=self.device)

    def fetch(self) -> np.ndarray:
        """(N, H, W) bool visibility, True = lit (off the mask True)."""
        self._check_open()
        return self.visible.numpy().astype(bool)

    def close(self) -> None:
        for name in ("depth", "mask", "visible", "dmin", "lp"):
            self.__dict__.pop(name, None)
        self._closed = True
