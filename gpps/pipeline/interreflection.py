"""Diffuse interreflections from a reconstructed surface, on the device: the stage :class:`Interreflections`.

Given a depth map, its normals and the observed images, the stage gathers at every mask pixel (the receiver) the
radiance the other patches of the surface send it (:mod:`gpps.kernels.interreflection`: form factors with
visibility marched over the depth map).  The result ``S`` (N, H, W, 3) is in the images' units per unit albedo: a
Lambertian receiver of albedo ``kd`` shows the indirect light ``kd * S[k]`` in image ``k``.  The sources' radiance
is the pixel value of the images given (the radiance toward the camera: exact for Lambertian sources), less the
model's specular part at the sources with ``upload(..., less_specular=(material, lights))`` (what
:func:`gpps.flows.interreflection.reconstruct_subtracting` asks for, to take the indirect light out of the
images).  :meth:`Interreflections.gather_model` gathers the first bounce under the model at both ends instead.

Cost: ``R * S`` form factors (``R`` mask pixels, ``S <= max_sources`` sources, each a march of up to the pair's
distance in pixels) and ``R * S * 3N`` multiply-adds for the gather (numpy's BLAS on the CPU, a kernel on CUDA).
The (R, S) float32 form-factor matrix is allocated for each mask (its size depends on the mask), in blocks of
``max_rows`` receivers.  Measured: a 128^2 object (about 10^4 receivers, 700-1000 sources) takes 1-4 s on the
2-core CPU (Warp's CPU backend is single-threaded) and well under a second on an H200; the cost grows with the
receivers, so a megapixel object wants the GPU (or ``max_size`` in the folder flow).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gpps._check import as_array, as_mask, check_bool, check_number, check_shape, unit_normals
from gpps._runtime import resolve_device, warp
from gpps.kernels import interreflection as ik
from gpps.kernels import shadows as sk
from gpps.pipeline.params import camera_params
from gpps.pipeline.stage import Stage

__all__ = ["InterreflectionConfig", "Interreflections", "source_pixels"]


@dataclass(frozen=True)
class InterreflectionConfig:
    """Settings of the gather (:mod:`gpps.kernels.interreflection`).

    Attributes:
        max_sources: the most source pixels: the mask pixels on every ``stride``-th row and column, ``stride``
            the smallest that gives at most this many (each then stands for ``stride^2`` pixels).  Indirect
            light is an integral over the surface, smooth where the geometry is: on the spherical cap of
            tests/test_interreflection.py 179 sources (stride 3, ``max_sources=300``) keep the mean gathered
            radiance within 3 % of all 1584 pixels'.
        visibility: march the segment between receiver and source over the depth map (a source hidden behind
            another part of the surface sends nothing); False: every facing pair sees each other.
        tolerance_px: the march's tolerance in pixel widths (as :class:`gpps.pipeline.shadows.ShadowConfig`).
        step_px: the march's step, pixels (> 0, <= 4: a coarser step than the shadows', the sum averages many
            segments).
        max_rows: receivers per launch (bounds the (rows, S) form-factor block in memory).
    """

    max_sources: int = 1024
    visibility: bool = True
    tolerance_px: float = 1.0
    step_px: float = 2.0
    max_rows: int = 65536

    def __post_init__(self):
        check_number("max_sources", self.max_sources, lo=1, integer=True)
        check_bool("visibility", self.visibility)
        check_number("tolerance_px", self.tolerance_px, lo=0.0)
        check_number("step_px", self.step_px, lo=0.0, hi=4.0, lo_open=True)
        check_number("max_rows", self.max_rows, lo=1, integer=True)


def source_pixels(mask: np.ndarray, max_sources: int) -> tuple[np.ndarray, int]:
    """The source pixels of :class:`InterreflectionConfig`: ``((S, 2) int32 rows and columns, stride)``, the mask
    pixels on every ``stride``-th row and column (offset ``stride // 2``), ``stride`` the smallest with ``S <=
    max_sources``."""
    stride = max(1, int(np.floor(np.sqrt(mask.sum() / max_sources))))
    while True:
        o = stride // 2
        sub = np.zeros_like(mask)
        sub[o::stride, o::stride] = mask[o::stride, o::stride]
        if sub.sum() <= max_sources:
            return np.argwhere(sub).astype(np.int32), stride
        stride += 1


class Interreflections(Stage):
    """The radiance each mask pixel gathers from the rest of the surface; see the module docstring.

    Args:
        shape: (N, H, W): images and their size.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        config: :class:`InterreflectionConfig`.
        device: Warp device (None: CUDA if present, else CPU).

    ``upload(depth, mask, normals, images)`` (host arrays), ``step()``, ``fetch()`` -> (N, H, W, 3) float32
    ``S`` (0 off the mask); :attr:`stride` and :attr:`sources` after an upload.
    """

    Config = InterreflectionConfig

    @staticmethod
    def kernel_modules() -> list:
        """The Warp modules this stage launches, the subtraction's included (a flow queues them behind a run's plan:
        :meth:`gpps.flows.ron.RON.compile_ahead`)."""
        from gpps.kernels import interreflection_subtract as isk

        wp = warp()
        return [wp.get_module(ik.__name__), wp.get_module(sk.__name__), wp.get_module(isk.__name__)]

    def __init__(self, shape, camera, config: InterreflectionConfig | None = None, device=None):
        wp = warp()
        n, h, w = check_shape("shape", shape, "NHW")
        self.config = InterreflectionConfig() if config is None else config
        if not isinstance(self.config, InterreflectionConfig):
            raise TypeError(f"config: expected Interreflections.Config, got {type(self.config).__name__}")
        self.device = resolve_device(device)
        self._settle(*self.kernel_modules())
        self.shape = (n, h, w)
        self.cam = camera_params(camera, (h, w))
        d = self.device
        self.depth = self._buffer((h, w), wp.float32, d, fill=1.0)
        self.mask = self._buffer((h, w), wp.uint8, d)
        self.normals = self._buffer((h, w), wp.vec3, d)
        self.dmin = self._buffer(1, wp.float32, d)
        self.max_steps = int(np.ceil(2 * (h + w) / self.config.step_px))
        self._mask_host = None
        self.recv = self.src = self.radiance = self.out = None
        self.stride = None

    @property
    def sources(self) -> int:
        """The number of source pixels of the last upload."""
        return 0 if self.src is None else int(self.src.shape[0])

    def upload(self, depth, mask, normals, images, *, less_specular=None) -> None:
        """Copy the surface and the images into the stage's buffers.

        Args:
            depth: (H, W) depth (scene units), finite and > 0 inside the mask.
            mask: (H, W) bool: the object.
            normals: (H, W, 3) unit normals inside the mask (gpps frame).
            images: (N, H, W, 3) (or (N, H, W)) linear images, the sources' radiance.
            less_specular: optional ``(material, lights)``: the sources' radiance is the images less the model's
                specular part toward the camera (``E ks s``, :func:`gpps.kernels.interreflection.source_specular_kernel`,
                evaluated at the source pixels only), clipped at 0: a glossy source's highlight is sent toward the
                camera, not toward the rest of the surface.
        """
        wp = warp()
        self._check_open()
        n, h, w = self.shape
        m = as_mask("mask", mask, (h, w), allow_empty=True)
        dep = as_array("depth", depth, shape=(h, w), finite=False)
        if not np.all(np.isfinite(dep[m])) or np.any(dep[m] <= 0):
            raise ValueError("depth: expected finite values > 0 inside the mask")
        nrm = unit_normals("normals", np.where(m[..., None], normals, (0.0, 0.0, 1.0)), m)
        img = as_array("images", images, finite=False)
        if img.ndim == 3:
            img = img[..., None]
        if img.shape[:3] != (n, h, w) or img.shape[3] not in (1, 3):
            raise ValueError(f"images: expected ({n}, {h}, {w}, 3) or ({n}, {h}, {w}), got {np.shape(images)}")
        img = np.broadcast_to(img, (n, h, w, 3))
        d = self.device
        self.depth.assign(np.where(m, dep, 1.0).astype(np.float32))
        self.mask.assign(m.astype(np.uint8))
        self.normals.assign(np.where(m[..., None], nrm, 0.0).astype(np.float32))
        src, self.stride = source_pixels(m, self.config.max_sources)
        recv = np.argwhere(m).astype(np.int32)
        self._mask_host = m
        self.recv = wp.array(recv, dtype=wp.vec2i, device=d)
        self.src = wp.array(src, dtype=wp.vec2i, device=d)
        # (S, 3N): the sources' radiance, one column per image and channel
        x = np.ascontiguousarray(img[:, src[:, 0], src[:, 1], :].transpose(1, 0, 2).reshape(len(src), 3 * n))
        if less_specular is not None and len(src):
            from gpps.pipeline.params import light_params, material_params

            material, lights = less_specular
            if len(lights) != n:
                raise ValueError(f"less_specular: expected {n} lights (the stage's shape[0]), got {len(lights)}")
            spec = wp.empty((len(src), n), dtype=wp.vec3, device=d)
            lp = light_params(lights, d)
            wp.launch(ik.source_specular_kernel, dim=(len(src), n),
                      inputs=[self.depth, self.normals, material_params(material), lp, self.cam, self.src, spec],
                      device=d)
            x = np.clip(x - spec.numpy().reshape(len(src), 3 * n), 0.0, None)
        self.radiance = wp.array(np.nan_to_num(x).astype(np.float32), dtype=wp.float32, device=d)
        self.out = wp.zeros((len(recv), 3 * n), dtype=wp.float32, device=d)

    def step(self) -> None:
        """Form factors and the gather, in blocks of ``max_rows`` receivers (the host does not wait on CUDA)."""
        wp = warp()
        self._check_open()
        if self.recv is None:
            raise ValueError("Interreflections: upload a surface first")
        d = self.device
        R, S = int(self.recv.shape[0]), int(self.src.shape[0])
        if R == 0 or S == 0:
            return
        cpu = str(d) == "cpu"
        x_host = self.radiance.numpy() if cpu else None
        out_host = self.out.numpy() if cpu else None  # (a view of the CPU array: written in place)
        for r0, r1, blk in self._form_factor_blocks():
            if cpu:
                out_host[r0:r1] = blk.numpy() @ x_host
            else:
                wp.launch(ik.gather_kernel, dim=(r1 - r0, self.out.shape[1]), inputs=[blk, self.radiance,
                          self.out[r0:r1]], device=d)

    def _form_factor_blocks(self):
        """The form factors of the uploaded surface in blocks of ``max_rows`` receivers: yields ``(r0, r1, F)``
        with ``F`` the (r1 - r0, S) Warp array of receivers ``r0:r1`` (launched, not waited on; the next block
        reuses the buffer, so a caller launches its gather on it before asking for the next)."""
        wp = warp()
        c, d = self.config, self.device
        R, S = int(self.recv.shape[0]), int(self.src.shape[0])
        self.dmin.fill_(float(sk.BIG))
        wp.launch(sk.min_depth_kernel, dim=self.shape[1:], inputs=[self.depth, self.mask, self.dmin], device=d)
        rows = max(1, min(R, int(c.max_rows)))
        F = wp.empty((rows, S), dtype=wp.float32, device=d)
        for r0 in range(0, R, rows):
            r1 = min(R, r0 + rows)
            blk = F if r1 - r0 == rows else wp.empty((r1 - r0, S), dtype=wp.float32, device=d)
            wp.launch(ik.form_factor_kernel, dim=(r1 - r0, S),
                      inputs=[self.depth, self.mask, self.normals, self.cam, self.recv[r0:r1], self.src,
                              float(self.stride**2), self.dmin, float(c.tolerance_px), float(c.step_px),
                              self.max_steps, int(c.visibility), blk], device=d)
            yield r0, r1, blk

    def gather_model(self, albedo, material, lights, visible=None) -> np.ndarray:
        """One bounce of interreflection under the reflectance model at both ends
        (:func:`gpps.kernels.interreflection.model_gather_kernel`), over the uploaded surface.

        The diffuse gather (:meth:`step`) sends on the sources' observed radiance, right for a matte source, and
        reflects it with the receiver's albedo; a glossy source (a metal) sends toward another part of the
        surface what the camera does not see, and a glossy receiver reflects it by its lobe: here both come from
        the fitted model.  Costs ``R * S * N`` pairs of model evaluations (the form factors ``R * S`` once).

        Args:
            albedo: (H, W, 3) albedo (the model's per-pixel weight; finite, clipped by the caller as it sees fit).
            material: :class:`gpps.Material` fitted to the images.
            lights: :class:`gpps.DirectionalLights` or :class:`gpps.PointLights` (N), as the images were fitted.
            visible: (N, H, W) bool, True where light ``k`` reaches the pixel (cast shadows,
                :class:`gpps.pipeline.shadows.CastShadows`); None: every light reaches every pixel.

        Returns:
            (N, H, W, 3) float32 radiance toward the camera per image (0 off the mask).
        """
        from gpps.pipeline.params import light_params, material_params

        wp = warp()
        self._check_open()
        if self.recv is None:
            raise ValueError("Interreflections: upload a surface first")
        n, h, w = self.shape
        alb = as_array("albedo", albedo, shape=(h, w, 3), dtype=np.float32)
        if len(lights) != n:
            raise ValueError(f"lights: expected {n} lights (the stage's shape[0]), got {len(lights)}")
        vis = np.ones((n, h, w), bool) if visible is None else np.asarray(visible)
        if vis.shape != (n, h, w) or vis.dtype != bool:
            raise ValueError(f"visible: expected a ({n}, {h}, {w}) bool array, got {vis.shape} {vis.dtype}")
        d = self.device
        R, S = int(self.recv.shape[0]), int(self.src.shape[0])
        res = np.zeros((n, h, w, 3), np.float32)
        if R == 0 or S == 0:
            return res
        alb_d = wp.array(np.where(self._mask_host[..., None], alb, 0.0), dtype=wp.vec3, device=d)
        vis_d = wp.array(vis.astype(np.uint8), dtype=wp.uint8, device=d)
        mp = material_params(material)
        lp = light_params(lights, d)
        out = wp.zeros((R, n), dtype=wp.vec3, device=d)
        for r0, r1, blk in self._form_factor_blocks():
            wp.launch(ik.model_gather_kernel, dim=(r1 - r0, n),
                      inputs=[blk, self.depth, self.normals, alb_d, vis_d, mp, lp, self.cam, self.recv[r0:r1],
                              self.src, out[r0:r1]], device=d)
        recv = self.recv.numpy()
        res[:, recv[:, 0], recv[:, 1], :] = out.numpy().transpose(1, 0, 2)
        return res

    def indirect_total(self, albedo, max_albedo: float = np.inf) -> float:
        """The indirect light per unit ``tau`` of the last :meth:`step`, summed over the receivers, images and
        channels: ``sum kd * S`` with ``kd`` the albedo clipped to ``[0, max_albedo]`` (NaN: 0), reduced on the
        device (one float per receiver comes back, summed in float64).  Keeps ``kd`` on the device for
        :meth:`subtract_from`.

        Args:
            albedo: (H, W, 3) albedo of the receivers (the reconstruction's, in the images' scale).
            max_albedo: the receivers' albedo is taken as at most this (> 0; ``1 / tau``).
        """
        from gpps.kernels import interreflection_subtract as isk

        wp = warp()
        self._check_open()
        if self.recv is None or self.out is None:
            raise ValueError("Interreflections: upload a surface and step first")
        n, h, w = self.shape
        alb = as_array("albedo", albedo, shape=(h, w, 3), dtype=np.float32, finite=False)
        self._max_albedo = (float(max_albedo) if isinstance(max_albedo, (float, np.floating)) and np.isposinf(max_albedo)
                            else check_number("max_albedo", max_albedo, lo=0.0, lo_open=True))
        d = self.device
        self._albedo = wp.array(alb, dtype=wp.vec3, device=d)
        R = int(self.recv.shape[0])
        if R == 0:
            return 0.0
        sums = wp.empty(R, dtype=wp.float32, device=d)
        wp.launch(isk.indirect_sums_kernel, dim=R,
                  inputs=[self.out, self.recv, self._albedo, float(min(self._max_albedo, 3.0e38)), sums], device=d)
        return float(sums.numpy().sum(dtype=np.float64))

    def subtract_from(self, frame, coef: float, *, observed=None) -> None:
        """The frame less the indirect light, on the device: ``frame = max(observed - coef * kd * S, 0)`` at every
        receiver, the other pixels untouched (:func:`gpps.kernels.interreflection_subtract.subtract_indirect_kernel`;
        ``kd`` as the last :meth:`indirect_total` took it).

        Args:
            frame: (N, H, W) ``wp.vec3`` images on the stage's device (a pixel solver's frame,
                :attr:`gpps.flows.reconstruction.ResidentFrame.images`), written in place.
            coef: ``tau`` times the frame's scale over the images the sources' radiance came from (>= 0).
            observed: the images to subtract from, as ``frame`` (None: ``frame`` itself; a later round subtracts
                from the observed images, kept aside, not from the last round's result).
        """
        from gpps.kernels import interreflection_subtract as isk

        wp = warp()
        self._check_open()
        if getattr(self, "_albedo", None) is None:
            raise ValueError("Interreflections: indirect_total(albedo) first (it sets the receivers' albedo)")
        coef = check_number("coef", coef, lo=0.0)
        n, h, w = self.shape
        src = frame if observed is None else observed
        for name, arr in (("frame", frame), ("observed", src)):
            if not isinstance(arr, wp.array) or arr.dtype != wp.vec3 or tuple(arr.shape) != (n, h, w):
                got = (f"{type(arr).__name__}" if not isinstance(arr, wp.array)
                       else f"shape {tuple(arr.shape)} of {wp.types.type_repr(arr.dtype)}")
                raise ValueError(f"{name}: expected an ({n}, {h}, {w}) wp.vec3 array, got {got}")
            if str(arr.device) != str(self.device):
                raise ValueError(f"{name}: expected an array on {self.device}, got one on {arr.device}")
        R = int(self.recv.shape[0])
        if R == 0:
            return
        wp.launch(isk.subtract_indirect_kernel, dim=(R, n),
                  inputs=[src, self.out, self.recv, self._albedo, float(min(self._max_albedo, 3.0e38)), float(coef),
                          frame], device=self.device)

    def fetch(self) -> np.ndarray:
        """(N, H, W, 3) float32 gathered radiance per unit albedo (0 off the mask)."""
        self._check_open()
        n, h, w = self.shape
        res = np.zeros((n, h, w, 3), np.float32)
        if self.recv is None or self.out is None:
            return res
        recv = self.recv.numpy()
        res[:, recv[:, 0], recv[:, 1], :] = self.out.numpy().reshape(len(recv), n, 3).transpose(1, 0, 2)
        return res

    def close(self) -> None:
        for name in ("recv", "src", "radiance", "out", "_albedo"):
            self.__dict__.pop(name, None)
        self._release_buffers()
        self._closed = True
