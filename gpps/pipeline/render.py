"""The forward renderer stage: (depth, normals, mask, albedo) -> N RGB images."""

from __future__ import annotations

import numpy as np

from gpps._check import albedo_map, as_array, as_mask, check_number, check_shape, unit_normals
from gpps.lights import DirectionalLights, PointLights
from gpps._runtime import resolve_device, warp
from gpps.kernels import render as rk
from gpps.pipeline.params import camera_params, light_params, material_params
from gpps.pipeline.stage import Stage


class Renderer(Stage):
    """Renders images of a scene under N lights; buffers are allocated once.

    Args:
        shape: (H, W) image size.
        camera: :class:`gpps.camera.Orthographic` or :class:`gpps.camera.Perspective`.
        lights: :class:`gpps.lights.DirectionalLights` or :class:`gpps.lights.PointLights`.
        material: :class:`gpps.material.Material`.
        device: Warp device (None: CUDA if present, else CPU).

    :meth:`upload` re-checks the shapes of its inputs ("expected ..., got ..."); ``run(depth, mask, albedo,
    normals)`` renders and returns the images (N, H, W, 3).
    """

    def __init__(self, shape, camera, lights, material, device=None):
        wp = warp()

        self._rk = rk
        self.device = resolve_device(device)
        h, w = check_shape("shape", shape, "HW")  # (16.5 is a TypeError, not 16)
        if not isinstance(lights, (DirectionalLights, PointLights)):  # (before len(lights) below)
            raise TypeError(f"lights: expected DirectionalLights or PointLights, got {type(lights).__name__}")
        self.shape = (h, w)
        self.cam = camera_params(camera, self.shape)
        self.camera = camera
        self.set_lights(lights)
        self.set_material(material)
        d = self.device
        self.depth = wp.zeros((h, w), dtype=wp.float32, device=d)
        self.normals = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self.mask = wp.zeros((h, w), dtype=wp.uint8, device=d)
        self.albedo = wp.zeros((h, w), dtype=wp.vec3, device=d)
        self.images = wp.zeros((len(lights), h, w), dtype=wp.vec3, device=d)

    def set_lights(self, lights):
        self.lights = lights
        self.lp = light_params(lights, self.device)
        if hasattr(self, "images") and self.images.shape[0] != len(lights):
            self.images = warp().zeros((len(lights),) + self.shape, dtype=warp().vec3, device=self.device)

    def set_material(self, material):
        self.material = material
        self.mp = material_params(material)

    def normals_from_depth(self, depth, mask) -> np.ndarray:
        """Unit normals (H, W, 3) from ``depth`` by finite differences of back-projected points."""
        wp = warp()
        mask = as_mask("mask", mask, self.shape)
        depth = as_array("depth", depth, shape=self.shape)
        if np.any(depth[mask] <= 0):
            raise ValueError("depth: expected values > 0 inside the mask")
        self.depth.assign(depth)
        self.mask.assign(mask.astype(np.uint8))
        wp.launch(self._rk.normals_from_depth_kernel, dim=self.shape, inputs=[self.depth, self.mask, self.cam], outputs=[self.normals], device=self.device)
        return self.normals.numpy()

    def upload(self, depth, mask, albedo, normals=None) -> None:
        """Check and copy the scene into the device buffers.

        Args:
            depth: (H, W) depth > 0 inside the mask (scene units).
            mask: (H, W) bool, not empty.
            albedo: (H, W, 3), (H, W) or (3,) RGB diffuse colour >= 0.
            normals: (H, W, 3) unit normals in the gpps frame; None derives them
                from ``depth`` (finite differences).
        """
        mask = as_mask("mask", mask, self.shape)
        depth = as_array("depth", depth, shape=self.shape)
        if np.any(depth[mask] <= 0):
            raise ValueError("depth: expected values > 0 inside the mask")
        depth = np.where(mask, depth, 1.0).astype(np.float32)
        if normals is None:
            self.normals_from_depth(depth, mask)
        else:
            self.normals.assign(unit_normals("normals", normals, mask))
        self.depth.assign(depth)
        self.mask.assign(mask.astype(np.uint8))
        self.albedo.assign(albedo_map("albedo", albedo, self.shape))

    def step(self) -> None:
        """Render the N images into :attr:`images`, the device array (N, H, W) of vec3 (RGB)."""
        warp().launch(
            self._rk.render_kernel,
            dim=self.shape,
            inputs=[self.depth, self.normals, self.mask, self.albedo, self.cam, self.lp, self.mp],
            outputs=[self.images],
            device=self.device,
        )

    def fetch(self) -> np.ndarray:
        """The rendered images (N, H, W, 3) float32, a copy owned by the caller."""
        return np.array(self.images.numpy(), copy=True)


def quantise(images: np.ndarray, bits: int | None) -> np.ndarray:
    """Clip to [0, 1] and round to ``bits`` (8 or 16) levels; None leaves floats as they are."""
    if bits is None:
        return images
    if bits not in (8, 16):
        raise ValueError(f"bits: expected 8, 16 or None, got {bits!r}")
    s = float(2**bits - 1)
    return (np.round(np.clip(images, 0.0, 1.0) * s) / s).astype(np.float32)


def add_noise(images: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    """Add zero-mean Gaussian noise of standard deviation ``sigma`` (image units), seeded."""
    sigma = check_number("noise", sigma)  # (a string such as "0.1" is a TypeError, not a number)
    if sigma < 0:
        raise ValueError(f"noise: expected a standard deviation >= 0, got {sigma!r}")
    seed = check_number("seed", seed, lo=0, integer=True)
    if sigma == 0:
        return images
    rng = np.random.default_rng(seed)
    return (images + rng.normal(0.0, sigma, images.shape)).astype(np.float32)
