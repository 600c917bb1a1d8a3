"""Depth map to triangle mesh, mesh files and an off-screen rendered view.

Vertices are the back-projected pixel centres (``camera.backproject``, gpps
frame: x right, y up, z toward the camera, ``z = -depth``); each 2x2 block of
valid pixels gives two triangles, wound so their normals face the camera.
Mesh export (PLY/OBJ) goes through pyvista and needs no OpenGL.
:func:`render_view` renders off-screen with EGL (no X server); when that is
impossible it falls back to a numpy-shaded normal view written with OpenCV
and says so in its return value.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from gpps.camera import Orthographic
from gpps.io.files import atomic_write

__all__ = ["depth_to_mesh", "save_mesh", "render_view"]


def _pyvista():
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv  # lazy: 1.17 s to import (measured), needed only for view.png; VTK reads the variable above

    return pv


def _mesh_arrays(depth, mask, camera):
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth: expected (H, W), got shape {depth.shape}")
    if mask is None:
        mask = np.isfinite(depth) & (depth != 0)
    mask = np.asarray(mask, dtype=bool)
    if mask.shape != depth.shape:
        raise ValueError(f"mask: expected shape {depth.shape} matching depth, got {mask.shape}")
    mask = mask & np.isfinite(depth)
    if camera is None:
        camera = Orthographic(1.0)
    if camera.is_perspective and np.any(depth[mask] <= 0):
        raise ValueError("depth: expected depth > 0 inside the mask for a perspective camera")
    pts = camera.backproject(np.where(mask, depth, 0.0))
    h, w = depth.shape
    idx = -np.ones((h, w), dtype=np.int64)
    idx[mask] = np.arange(int(mask.sum()))
    a, b = idx[:-1, :-1], idx[:-1, 1:]
    c, d = idx[1:, :-1], idx[1:, 1:]
    tris = []
    # (i,j)->(i+1,j)->(i,j+1) is counter-clockwise seen from the camera (rows go down, y up)
    for t in ((a, c, b), (b, c, d)):
        ok = (t[0] >= 0) & (t[1] >= 0) & (t[2] >= 0)
        tris.append(np.stack([t[0][ok], t[1][ok], t[2][ok]], axis=1))
    faces = np.concatenate(tris, axis=0)
    return pts[mask], faces


def depth_to_mesh(depth, mask=None, camera=None):
    """Triangulated surface in camera space.

    Args:
        depth: (H, W) depth ``d = -z`` (scene units; > 0 for perspective).
        mask: (H, W) bool pixels to use (``None``: finite, non-zero depth).
        camera: :class:`gpps.camera.Orthographic` (default, pixel size 1) or
            :class:`gpps.camera.Perspective`.

    Returns:
        ``pyvista.PolyData`` with one vertex per masked pixel (gpps frame)
        and triangles over 2x2 blocks of masked pixels.
    """
    pts, faces = _mesh_arrays(depth, mask, camera)
    pv = _pyvista()
    cells = np.hstack([np.full((faces.shape[0], 1), 3, dtype=np.int64), faces]).ravel()
    return pv.PolyData(pts, cells) if faces.size else pv.PolyData(pts)


def save_mesh(mesh, path) -> Path:
    """Write a mesh to ``.ply`` (binary), ``.obj`` or ``.vtk`` atomically.

    Args:
        mesh: ``pyvista.PolyData``.
        path: target file; the extension picks the format.
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".ply", ".obj", ".vtk", ".stl"):
        raise ValueError(f"path: expected a .ply, .obj, .vtk or .stl file name, got {str(path)!r}")

    with atomic_write(path) as tmp:
        mesh.save(str(tmp))
    return path


def _shaded_fallback(depth, mask, camera, size):
    """Lambertian shading of the mesh normals, head-on light, as an (H, W, 3) uint8 image."""
    if camera is None:
        camera = Orthographic(1.0)
    pts = camera.backproject(np.where(mask, depth, 0.0))
    du = np.gradient(pts, axis=1)
    dv = np.gradient(pts, axis=0)
    n = np.cross(dv, du)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    n *= np.sign(n[..., 2:3] + 1e-12)
    light = np.array([0.3, 0.4, 1.0])
    light /= np.linalg.norm(light)
    shade = np.clip(n @ light, 0, 1) * 0.85 + 0.15
    img = np.where(mask, shade * 255, 255).astype(np.uint8)
    img = np.repeat(img[..., None], 3, axis=2)
    if size is not None:
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return img


def render_view(depth, mask=None, camera=None, path=None, *, size=(800, 800)) -> dict:
    """Render the depth map's mesh off-screen to a PNG.

    Args:
        depth, mask, camera: as in :func:`depth_to_mesh`.
        path: PNG file to write (``None``: only return the image).
        size: ``(width, height)`` in pixels.

    Returns:
        dict with ``image`` ((h, w, 3) uint8 RGB), ``method`` (``"egl"`` or
        ``"numpy-shaded"``), ``path`` and, on fallback, ``reason``.  Never
        raises for a rendering failure.
    """
    depth = np.asarray(depth, dtype=np.float64)
    if mask is None:
        mask = np.isfinite(depth) & (depth != 0)
    mask = np.asarray(mask, bool)
    out = {"path": None if path is None else str(path)}
    try:
        pv = _pyvista()
        mesh = depth_to_mesh(depth, mask, camera)
        if mesh.n_cells == 0:
            raise RuntimeError("no triangles to render")
        pl = pv.Plotter(off_screen=True, window_size=list(size))
        pl.set_background("white")
        pl.add_mesh(mesh.compute_normals(auto_orient_normals=False, consistent_normals=False),
                    color="lightgray", smooth_shading=True, specular=0.2)
        pl.camera_position = "xy"  # look down -z, y up: the gpps camera's view
        img = pl.screenshot(None, return_img=True)
        pl.close()
        out.update(image=np.asarray(img)[..., :3].astype(np.uint8), method="egl")
    except Exception as e:  # no EGL/GL here: shaded normals instead, never crash
        out.update(image=_shaded_fallback(depth, mask, camera, size), method="numpy-shaded",
                   reason=f"{type(e).__name__}: {e}")
    if path is not None:
        with atomic_write(path) as tmp:
            if not cv2.imwrite(str(tmp), out["image"][..., ::-1]):
                raise OSError(f"path: could not write PNG {str(path)!r}")
    return out
