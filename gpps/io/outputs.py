"""The output set every command writes, and the one depth convention they share.

Files (:func:`write_outputs`, into a folder the caller writes atomically):
================  ==================================================================
normals.npy       (H, W, 3) float32 unit normals, gpps frame, 0 outside the mask
normals.png       16-bit RGB, ``(n + 1) / 2`` (black outside the mask)
albedo.npy        (H, W, 3) float32 RGB albedo, linear, as estimated (not rescaled)
albedo.png        8-bit preview: albedo / its 99th percentile, sRGB-encoded
depth.npy         (H, W) float32 depth ``d = -z`` (see below), NaN outside the mask
depth.tiff        the same, float32 TIFF (tifffile)
depth.exr         the same, float32 OpenEXR, channel "Z"
mesh.ply          binary PLY, one vertex per pixel (gpps frame), albedo as vertex colours
mesh.obj          the same mesh as OBJ (``v x y z r g b``)
view.png          off-screen view of the mesh
mask.png          the mask used (always; automatic when the input had none)
flags.npy         (H, W) int32 the per-pixel solver's flag bits (gpps.names.FLAG_NAMES: e.g. 32 "unfounded",
                  a fit whose albedo the data do not fix), 0 outside the mask; only where a per-pixel solver ran
================  ==================================================================

Depth convention (:func:`depth_convention`), stated in ``report.json`` under
``"depth"`` with its ``unit``, ``scale`` and ``source``:
* **metric** when the scale is known: the depth is in the unit of what gave
  it (light positions, a reference depth given by the user, the ground truth's
  depth): ``scale = "metric"``, ``unit`` names it.
* **relative** otherwise: with a perspective camera the shape is known up to
  one factor, and the depth is divided so that its mean over the mask is 1
  (``unit = "mean object distance"``); with an orthographic camera x, y and
  depth are in pixels (``unit = "pixel"``, times ``pixel_size`` when one is
  given) and the depth, known up to an offset, has mean 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gpps.io.files import save_npy, save_png
from gpps.io.formats import linear_to_srgb, save_exr, save_float_tiff, save_mesh_file
from gpps.io.mesh import _mesh_arrays, render_view

__all__ = ["depth_convention", "apply_depth_convention", "write_outputs", "OUTPUT_FILES"]

OUTPUT_FILES = ("normals.npy", "normals.png", "albedo.npy", "albedo.png", "depth.npy", "depth.tiff", "depth.exr",
                "mesh.ply", "mesh.obj", "view.png", "mask.png")


def depth_convention(camera, *, known_scale: str | None = None, unit: str | None = None) -> dict:
    """The report's ``"depth"`` entry.

    Args:
        camera: the camera the depth belongs to.
        known_scale: where a metric scale came from (e.g. "light_positions.txt",
            "--reference-depth"), or None when it is unknown.
        unit: the unit's name when the scale is known (default "scene units of <source>").
    """
    base = {"definition": "d = -z: distance along the optical axis (gpps frame: x right, y up, z toward the camera)",
            "camera": "perspective" if camera.is_perspective else "orthographic"}
    if known_scale is not None:
        return {**base, "scale": "metric", "unit": unit or f"scene units of {known_scale}", "source": known_scale}
    if camera.is_perspective:
        return {**base, "scale": "relative", "unit": "mean object distance",
                "source": "unknown scale: depth divided by its mean over the mask (shape right up to one factor)"}
    px = getattr(camera, "pixel_size", 1.0)
    return {**base, "scale": "relative" if px == 1.0 else "metric", "unit": "pixel" if px == 1.0 else f"pixel_size units ({px:g} per pixel)",
            "source": "orthographic: x, y and depth in pixel widths; depth known up to an offset, mean 0 over the mask"}


def apply_depth_convention(depth, mask, convention: dict) -> np.ndarray:
    """Rescale / shift a depth map to the convention; NaN outside ``mask``."""
    d = np.asarray(depth, np.float64)
    m = np.asarray(mask, bool) & np.isfinite(d)
    if m.any() and convention["scale"] == "relative":
        if convention["camera"] == "perspective":
            mean = float(d[m].mean())
            if mean > 0:
                d = d / mean
        else:
            d = d - float(d[m].mean())
    elif m.any() and convention["camera"] == "orthographic" and convention["scale"] == "metric" and "pixel_size" in convention["unit"]:
        d = d - float(d[m].mean())
    return np.where(m, d, np.nan).astype(np.float32)


def _albedo_colors(albedo, mask):
    a = np.asarray(albedo, np.float64)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, -1)
    ok = np.asarray(mask, bool) & np.all(np.isfinite(a), -1)
    top = float(np.percentile(a[ok], 99)) if ok.any() else 1.0
    a = np.clip(np.nan_to_num(a / max(top, 1e-12)), 0.0, 1.0)

    return linear_to_srgb(a)


def write_outputs(folder, *, normals, albedo, mask, depth=None, depth_mask=None, camera=None, depth_info=None,
                  view: bool = True, flags=None) -> dict:
    """Write the output set into ``folder`` (which the caller creates and renames atomically).

    Args:
        folder: target folder (exists).
        normals: (H, W, 3) unit normals.
        albedo: (H, W, 3) or (H, W) linear albedo, or None.
        mask: (H, W) bool.
        depth: (H, W) depth already in the convention (:func:`apply_depth_convention`), or None.
        depth_mask: (H, W) bool pixels with depth (default: finite depth in ``mask``).
        camera: the camera (mesh back-projection).
        depth_info: the convention (only checked for presence with depth).
        view: render ``view.png``.
        flags: (H, W) int the per-pixel solver's flags (``flags.npy``), or None (not written).

    Returns:
        dict: ``files`` written and ``view`` (the renderer used, or why none).
    """

    folder = Path(folder)
    mask = np.asarray(mask, bool)
    n = np.where(mask[..., None], np.asarray(normals, np.float32), 0.0).astype(np.float32)
    files = []
    save_npy(folder / "normals.npy", n)
    save_png(folder / "normals.png", np.where(mask[..., None], (n + 1.0) / 2.0, 0.0), bits=16)
    save_png(folder / "mask.png", mask.astype(np.uint8) * 255)
    files += ["normals.npy", "normals.png", "mask.png"]
    colors = None
    if albedo is not None:
        a = np.asarray(albedo, np.float32)
        if a.ndim == 2:
            a = np.repeat(a[..., None], 3, -1)
        a = np.where(mask[..., None], a, 0.0).astype(np.float32)
        save_npy(folder / "albedo.npy", a)
        colors = _albedo_colors(a, mask)
        save_png(folder / "albedo.png", np.where(mask[..., None], colors, 0.0), bits=8)
        files += ["albedo.npy", "albedo.png"]
    if flags is not None:
        f = np.asarray(flags)
        if f.shape != mask.shape or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"flags: expected {mask.shape} integers, got {f.shape} {f.dtype}")
        save_npy(folder / "flags.npy", np.where(mask, f, 0).astype(np.int32))
        files.append("flags.npy")
    out = {"files": files}
    if depth is not None:
        if depth_info is None:
            raise ValueError("depth_info: expected the depth convention (gpps.io.outputs.depth_convention) with a depth map")
        d = np.asarray(depth, np.float32)
        dm = (mask & np.isfinite(d)) if depth_mask is None else (np.asarray(depth_mask, bool) & np.isfinite(d))
        d = np.where(dm, d, np.nan).astype(np.float32)
        save_npy(folder / "depth.npy", d)
        save_float_tiff(folder / "depth.tiff", d)
        save_exr(folder / "depth.exr", d, channels="Z")
        files += ["depth.npy", "depth.tiff", "depth.exr"]

        pts, faces = _mesh_arrays(np.where(dm, d, 0.0), dm, camera)
        vcol = None if colors is None else colors[dm]
        save_mesh_file(folder / "mesh.ply", pts, faces, vcol)
        save_mesh_file(folder / "mesh.obj", pts, faces, vcol)
        files += ["mesh.ply", "mesh.obj"]
        if view:
            v = render_view(np.where(dm, d, 0.0), dm, camera, folder / "view.png")
            files.append("view.png")
            out["view"] = v["method"]
            if "reason" in v:
                out["view_fallback_reason"] = v["reason"]
    return out
