"""The frame's noise levels on the device: :func:`gpps.pipeline.solver.estimate_noise` where the images already are.

On CUDA the flows' preparation estimated the noise on the host (numpy, about 2 ms for 256^2 x 3 on the GPU
machine's host, on a pool thread whose numpy calls contend for the GIL with the input checks'), and then uploaded
the images.  :class:`DeviceNoise` reads the uploaded images instead: one launch writes every selected pixel's
``|I * K|`` of each image (:mod:`gpps.kernels.noise`), one sort an image, one launch takes the medians into the
solver's noise buffer.  The host's selection of the pixels (:func:`gpps.host.observations.noise_selection`, the
mask's alone) is kept for the mask it was made for.  The same bits as the host's estimate.
"""

from __future__ import annotations

import numpy as np

from gpps._runtime import resolve_device, warp
from gpps.host.observations import noise_selection
from gpps.kernels import noise as nk
from gpps.pipeline.stage import Stage

__all__ = ["DeviceNoise", "noise_on_device"]


def noise_on_device(device) -> bool:
    """Whether the frame's noise levels are estimated on ``device`` (:class:`DeviceNoise`, by
    :meth:`gpps.pipeline.solver.PixelSolver.upload`) rather than on the host: on CUDA, where the images are uploaded
    anyway and the host's numpy estimate would hold the host; on the CPU the host's estimate (numpy, vectorised) is
    faster than one Warp thread's."""
    return str(resolve_device(device)).startswith("cuda")


class DeviceNoise(Stage):
    """:func:`gpps.pipeline.solver.estimate_noise` of images on the device, into a device array.

    Args:
        shape: ``(N, H, W)`` of the images it reads.
        device: Warp device.
        max_pixels: as :func:`~gpps.pipeline.solver.estimate_noise`'s.

    ``upload(mask)`` selects the pixels (host, the mask only; again only for another mask), ``step(images, out)``
    launches the estimate of ``images`` ((N, H, W) ``wp.vec3`` on the device) into ``out`` ((N,) float32 on the
    device) without a host wait, ``fetch()`` returns the last estimate ((N,) float32).  The scratch (the values,
    a row of twice the selection's pixels an image, as the sort needs, and their counts) is allocated for the
    largest selection seen.
    """

    def __init__(self, shape, device=None, *, max_pixels: int = 1 << 16):
        self.shape = tuple(int(s) for s in shape)
        self.device = resolve_device(device)
        self.max_pixels = int(max_pixels)
        self._settle(nk.noise_values_kernel, nk.noise_median_kernel)
        wp = warp()
        n = self.shape[0]
        self.counts = self._buffer(n, wp.int32, self.device)
        self.keys = self._buffer((n, 2), wp.float32, self.device)  # (grown by upload to the selection's size)
        self.vals = self._buffer(2, wp.int32, self.device)
        self.out = None
        self._mask = None
        self._sel = None  # (rows, sel, c0) on the device, or None: no pixel selected
        self._size = 0  # pixels a row of the selection times its rows

    def upload(self, mask) -> None:
        """The selection of ``mask`` ((H, W) bool): made again only when the mask differs from the last one."""
        self._check_open()
        m = np.asarray(mask, bool)
        if m.shape != self.shape[1:]:
            raise ValueError(f"mask: expected shape {self.shape[1:]}, got {m.shape}")
        if self._mask is not None and np.array_equal(m, self._mask):
            return
        wp = warp()
        got = noise_selection(m, max_pixels=self.max_pixels)
        self._mask = m.copy()
        if got is None:
            self._sel, self._size = None, 0
            return
        rows, sel, c0, _ = got
        size = int(sel.size)
        if self.keys.shape[1] < 2 * size:
            self.keys = self._buffer((self.shape[0], 2 * size), wp.float32, self.device)
            self.vals = self._buffer(2 * size, wp.int32, self.device)
        self._sel = (wp.array(rows.astype(np.int32), dtype=wp.int32, device=self.device),
                     wp.array(sel.astype(np.uint8), dtype=wp.uint8, device=self.device), int(c0))
        self._size = size

    def step(self, images, out) -> None:
        """Launch the estimate of ``images`` into ``out`` (no host wait)."""
        self._check_open()
        wp = warp()
        n, h, w = self.shape
        if tuple(images.shape) != (n, h, w) or images.dtype != wp.vec3:
            raise ValueError(f"images: expected ({n}, {h}, {w}) wp.vec3, got {tuple(images.shape)} {images.dtype}")
        if tuple(out.shape) != (n,) or out.dtype != wp.float32:
            raise ValueError(f"out: expected ({n},) float32, got {tuple(out.shape)} {out.dtype}")
        if self._mask is None:
            raise ValueError("mask: expected an upload(mask) before step")
        self.out = out
        self.counts.zero_()
        if self._sel is not None:
            rows, sel, c0 = self._sel
            wp.launch(nk.noise_values_kernel, dim=(n, sel.shape[0], sel.shape[1]),
                      inputs=[images, rows, sel, c0, self.keys, self.counts], device=self.device)
            for k in range(n):
                wp.utils.radix_sort_pairs(self.keys[k], self.vals, self._size)
        wp.launch(nk.noise_median_kernel, dim=n, inputs=[self.keys, self.counts, out], device=self.device)

    def fetch(self) -> np.ndarray:
        """The last estimate, (N,) float32 (a host copy)."""
        if self.out is None:
            raise ValueError("DeviceNoise: expected a step before fetch")
        return self.out.numpy().copy()

    def close(self) -> None:
        self._release_buffers()
        self._sel = self.keys = self.vals = self.out = None
        self._closed = True
