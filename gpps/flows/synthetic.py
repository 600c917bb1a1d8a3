"""Rendering synthetic photometric-stereo captures (thin API over :class:`gpps.pipeline.render.Renderer`)."""

from __future__ import annotations

from typing import Literal

import numpy as np

from gpps._check import check_number, warn
from gpps.host.scenes import D0, Scene
from gpps.io import Dataset
from gpps.lights import (
    DirectionalLights,
    PointLights,
    ring_directions,
    ring_positions,
    spiral_directions,
)
from gpps.material import Material
from gpps.pipeline.render import Renderer, add_noise, quantise

__all__ = ["default_lights", "render", "render_dataset"]

LIGHT_INTENSITY = 0.8


def default_lights(kind: Literal["directional", "point"] = "directional", n: int = 3, *, slant_deg: float = 35.0, d0: float = D0, layout: Literal["ring", "spiral"] = "ring"):
    """``n`` lights spread around the view axis (``slant_deg`` in [0, 89], ``d0`` > 0).

    Directional: ``layout="ring"``: evenly in azimuth at slant ``slant_deg``
    from the view axis; ``"spiral"``: a golden-angle spiral with slants from 15
    to 50 deg.  Point: on the camera plane z = 0 at the positions that give
    those directions at the object's centre (depth ``d0``), with intensities
    scaled so that the radiance there is about ``LIGHT_INTENSITY``.
    """
    if layout not in ("ring", "spiral"):
        raise ValueError(f"layout: expected 'ring' or 'spiral', got {layout!r}")
    slant_deg = check_number("slant_deg", slant_deg, lo=0.0, hi=89.0)  # (90 and beyond: no light on the front)
    d0 = check_number("d0", d0, lo=0.0, lo_open=True)
    dirs = ring_directions(n, slant_deg) if layout == "ring" else spiral_directions(n)
    if kind == "directional":
        return DirectionalLights(dirs, np.full((n, 3), LIGHT_INTENSITY))
    if kind == "point":
        if layout == "spiral":
            pos = dirs / dirs[:, 2:3] * d0 + [0.0, 0.0, -d0]
            pos[:, 2] = 0.0
            r2 = np.sum(pos[:, :2] ** 2, 1)
            return PointLights(pos, np.repeat((0.65 * LIGHT_INTENSITY * (r2 + d0 * d0))[:, None], 3, 1))
        r = d0 * np.tan(np.deg2rad(slant_deg))
        # the sphere's front is nearer than d0: keep its highlights in range
        return PointLights(ring_positions(n, r, 0.0), np.full((n, 3), 0.65 * LIGHT_INTENSITY * (r * r + d0 * d0)))
    raise ValueError(f"lights: expected 'directional' or 'point', got {kind!r}")


def render(scene: Scene, material: Material, lights, *, noise: float = 0.0, bits: int | None = None, seed: int = 0, device=None) -> np.ndarray:
    """Render ``scene`` under ``lights``: (N, H, W, 3) float32.

    Args:
        scene: a :class:`gpps.host.scenes.Scene` (exact normals are used).
        material: reflectance model and parameters.
        lights: :class:`DirectionalLights` or :class:`PointLights`.
        noise: standard deviation of additive Gaussian noise (image units, 1 = white).
        bits: None keeps floats; 8 or 16 clips to [0, 1] and quantises (after the noise).
        seed: noise seed.
        device: Warp device (None: CUDA when present).
    """
    if not all(hasattr(scene, k) for k in ("shape", "camera", "depth", "mask", "albedo", "normals")):
        raise TypeError(f"scene: expected a gpps.host.scenes.Scene (gpps.make_scene), got {type(scene).__name__}")
    r = Renderer(scene.shape, scene.camera, lights, material, device=device)
    img = r.run(scene.depth, scene.mask, scene.albedo, normals=scene.normals)
    # (before the noise: the lights' own doing, e.g. behind the object or of zero intensity)
    dark = np.nonzero(~np.any(img[:, scene.mask] > 0, axis=(1, 2)))[0]
    if dark.size:
        warn(f"images: {dark.size} of {len(img)} rendered images are black inside the mask (lights "
             f"{(dark + 1).tolist()[:8]}): lights behind the object, of zero intensity or facing away")
    img = add_noise(img, noise, seed)
    img[:, ~scene.mask] = 0.0
    return quantise(img, bits)


def render_dataset(scene: Scene, material: Material, lights, **kw) -> Dataset:
    """Render and package as a :class:`gpps.io.Dataset` with ground truth.

    Images are stored already divided by the light intensities' ... no: they are
    stored as rendered, and ``light_intensities`` holds the lights' RGB
    intensities (a reader divides by them, as for DiLiGenT).
    """
    images = render(scene, material, lights, **kw)
    ds = Dataset(
        images=images,
        mask=scene.mask,
        light_directions=lights.directions if isinstance(lights, DirectionalLights) else None,
        light_positions=lights.positions if isinstance(lights, PointLights) else None,
        light_intensities=np.asarray(lights.intensities),
        K=np.asarray(scene.camera.K) if scene.camera.is_perspective else None,
        normal_gt=scene.normals,
        depth_gt=scene.depth,
        material=material.to_dict(),
        normalised=False,
        extra={"albedo_gt": scene.albedo},
    )
    return ds
