"""The per-pixel solve of a large frame in tiles: the pieces a distributed engine maps over blocks.

:func:`gpps.flows.photometric.solve_normals` solves every pixel on its own except for two frame-wide
inputs and one neighbourhood pass, which is what a tiled solve must reproduce to equal the untiled one:

* the per-image noise levels (:func:`gpps.pipeline.solver.estimate_noise`, a median over the whole
  frame): estimated once on the frame (:func:`prepare`) and handed to every tile
  (``PixelSolver.upload(noise=...)``);
* the degenerate-input check (:func:`gpps.flows.photometric.check_observations`): once, on the frame;
* the second pass for pixels with fewer than 3 lit observations reads the first-pass results of
  well-determined pixels up to ``neighbour_radius`` away: each tile is solved with a halo of
  :func:`halo` pixels on every side (a block of the frame's packed inputs, :func:`pack`), and only
  its core is kept.  The smoothness term (``smoothness > 0``) couples all pixels through its sweeps
  and is refused.

Each tile's camera is the frame's, shifted to the tile's origin (:func:`crop_camera`), so every pixel
sees the same ray.  :func:`solve_block` solves one packed block (its origin is in the block itself,
two index channels, so a block needs no side information); :func:`unpack` turns the assembled
outputs into a :class:`gpps.flows.photometric.PSResult`.  The engine that maps the blocks lives above
the flows (:mod:`gpps.batch`, dask.array ``map_overlap``).
"""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np

from gpps._check import GppsWarning, as_flags
from gpps.camera import Orthographic, Perspective
from gpps.flows.photometric import (
    PSResult,
    check_inputs,
    check_observations,
    detect_clipping,
    input_saturation,
)
from gpps.lights import PointLights
from gpps.material import Material
from gpps.pipeline.solver import PixelSolver, SolverConfig, estimate_noise, rgb_images

__all__ = ["halo", "crop_camera", "prepare", "pack", "solve_block", "unpack", "output_channels"]


def halo(config: SolverConfig) -> int:
    """Pixels of context a tile needs on each side: the neighbour pass's radius (0 when it is off).

    Raises:
        ValueError: ``smoothness > 0`` (its sweeps couple every pixel of the frame).
    """
    if config.smoothness > 0.0 and config.smoothing_sweeps > 0:
        raise ValueError("config: expected smoothness 0 for a tiled solve (the smoothness sweeps couple the whole frame), "
                         f"got {config.smoothness}")
    return int(config.neighbour_radius)


def crop_camera(camera, shape: tuple[int, int], y0: int, x0: int):
    """The camera of the window of a (H, W) frame whose first pixel is row ``y0``, column ``x0``: the same
    rays (principal point / orthographic centre shifted by the origin)."""
    cx, cy = camera.principal_point(shape)
    if isinstance(camera, Perspective):
        K = np.array(camera.K, np.float64)
        K[0, 2], K[1, 2] = cx - x0, cy - y0
        return Perspective(K)
    if isinstance(camera, Orthographic):
        return Orthographic(camera.pixel_size, center=(cx - x0, cy - y0))
    raise TypeError(f"camera: expected Orthographic or Perspective, got {type(camera).__name__}")


def prepare(images, mask, lights, *, camera=None, config: SolverConfig, valid=None, depth=None) -> dict:
    """The frame-wide part of a tiled solve, on the whole frame: checks, noise levels, the packed inputs.

    Returns:
        ``{"packed": (H, W, C) float32 (:func:`pack`), "noise": (N,) float32, "determined": (H, W) bool,
        "warnings": [...], "camera", "shape": (N, H, W), "halo", "config", "has_valid"}``: ``config`` the solver config the
        tiles take (``config`` with ``saturation`` at the full scale of uint8 / uint16 input, as
        :func:`gpps.flows.photometric.solve_normals` sets it); float input given with neither ``saturation`` nor
        ``valid`` has its clipping plateaus left out of ``packed``'s valid flags (with a warning), as there;
        ``has_valid``: whether ``packed`` carries valid flags (:func:`solve_block`'s argument).
    """
    img, m, lights, camera = check_inputs(images, mask, lights, camera)
    n, h, w = img.shape[:3]
    notes: list[str] = []
    ref = None if depth is None else float(np.mean(np.asarray(depth, np.float64)[m]))
    if valid is not None:
        valid = as_flags("valid", valid, (n, h, w))
    if config.saturation is None and input_saturation(images) is not None:
        # uint8 / uint16 input: the full scale dropped from the fit, as solve_normals drops it
        config = replace(config, saturation=input_saturation(images))
    # float input without saturation or valid: the clipping plateaus left out, as solve_normals leaves them out
    valid, clipped = detect_clipping(images, img, m, saturation=config.saturation, valid=valid, sink=notes)
    determined = check_observations(img, m, lights, valid=valid, saturation=input_saturation(images, config.saturation),
                                    reference_depth=ref, sink=notes, clipped=clipped)
    rgb = rgb_images(img, (n, h, w))
    noise = estimate_noise(rgb, m) if config.noise_level is None else np.full(n, config.noise_level, np.float32)
    if isinstance(lights, PointLights) and depth is None:
        raise ValueError("depth: expected an (H, W) depth estimate for point lights (2.30-2.31), got None")
    return {"packed": pack(rgb, m, valid=valid, depth=depth), "noise": np.asarray(noise, np.float32),
            "determined": determined, "warnings": notes, "camera": camera, "shape": (n, h, w), "halo": halo(config),
            "config": config, "has_valid": valid is not None}


def pack(images, mask, *, valid=None, depth=None) -> np.ndarray:
    """The per-pixel inputs as one (H, W, C) float32 array, channels: the N RGB images (3N), the mask, the
    row and column index, then the N valid flags (when given) and the depth (when given)."""
    n, h, w = images.shape[:3]
    parts = [np.moveaxis(np.asarray(images, np.float32), 0, 2).reshape(h, w, 3 * n), mask[..., None]]
    ii, jj = np.meshgrid(np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32), indexing="ij")
    parts += [ii[..., None], jj[..., None]]
    if valid is not None:
        parts.append(np.moveaxis(np.asarray(valid, np.float32), 0, 2))
    if depth is not None:
        parts.append(np.asarray(depth, np.float32)[..., None])
    return np.concatenate([np.asarray(p, np.float32) for p in parts], axis=2)


def output_channels(n: int) -> int:
    """Channels of a solved block: normals 3, albedo 3, residual, iterations, flags, cond, then N weights."""
    return 10 + n


def solve_block(block: np.ndarray, *, n: int, shape: tuple[int, int], lights, camera, material: Material,
                config: SolverConfig, noise, has_valid: bool, has_depth: bool, device=None) -> np.ndarray:
    """Solve one packed block (:func:`pack`'s channels, halo included) with :class:`PixelSolver`.

    Args:
        block: (h, w, C) float32 window of the packed frame.
        n: images; shape: the frame's (H, W); lights, material, config: the frame's.
        camera: the frame's camera (shifted here to the block's origin).
        noise: (N,) the frame's noise levels.

    Returns:
        (h, w, :func:`output_channels`) float32: zeros where the block holds no mask pixel.
    """
    h, w = block.shape[:2]
    out = np.zeros((h, w, output_channels(n)), np.float32)
    m = block[..., 3 * n] > 0.5
    if not m.any():
        return out
    y0, x0 = int(block[0, 0, 3 * n + 1]), int(block[0, 0, 3 * n + 2])
    images = np.moveaxis(block[..., :3 * n].reshape(h, w, n, 3), 2, 0)
    c = 3 * n + 3
    valid = None
    if has_valid:
        valid = np.moveaxis(block[..., c:c + n], 2, 0) > 0.5
        c += n
    depth = np.where(m, block[..., c], 1.0) if has_depth else None
    ps = PixelSolver((n, h, w), crop_camera(camera, shape, y0, x0), lights, material, config, device=device)
    with warnings.catch_warnings():
        # a tile with nothing lit is part of a frame the flow has checked as a whole (check_observations)
        warnings.filterwarnings("ignore", message="images: no observation inside the mask is lit", category=GppsWarning)
        ps.upload(images, m, depth=depth, valid=valid, noise=noise)
    ps.step()
    r = ps.fetch()
    out[..., 0:3], out[..., 3:6] = r["normals"], r["albedo"]
    out[..., 6], out[..., 7], out[..., 8], out[..., 9] = r["residual"], r["iterations"], r["flags"], r["cond"]
    out[..., 10:] = np.moveaxis(r["weights"], 0, 2)
    return out


def unpack(solved: np.ndarray, prep: dict, mask, *, config: SolverConfig, material: Material, timings: dict) -> PSResult:
    """A :class:`PSResult` from the assembled (H, W, K) outputs of :func:`solve_block`."""
    return PSResult(
        normals=np.ascontiguousarray(solved[..., 0:3]), albedo=np.ascontiguousarray(solved[..., 3:6]),
        residual=np.ascontiguousarray(solved[..., 6]), iterations=solved[..., 7].astype(np.int32),
        flags=solved[..., 8].astype(np.int32), cond=np.ascontiguousarray(solved[..., 9]),
        weights=np.ascontiguousarray(np.moveaxis(solved[..., 10:], 2, 0)), mask=np.asarray(mask, bool),
        timings=timings, config=config, material=material, determined=prep["determined"], warnings=prep["warnings"])
