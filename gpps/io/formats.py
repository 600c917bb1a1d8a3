"""Image, array and mesh files as users have them, through well-kept libraries.

Readers (:func:`read_image_file`) return linear floats ``(H, W, C)`` (C = 1 or
3, RGB order) and what they found (format, bit depth, transfer curve):
========================  ===========================================================
PNG 8/16 bit, PGM/PPM,    OpenCV ``IMREAD_UNCHANGED`` (16-bit RGB stays 16-bit;
BMP, JPEG                 BGR -> RGB); integers divided by 255 or 65535
TIFF 8/16/32f             tifffile; integers divided by their maximum, floats as they are
EXR (half/float)          OpenEXR (R, G, B or Y or the first channel), as they are
camera RAW (.dng, .cr2,   rawpy (optional extra ``gpps[raw]``): demosaiced, camera white
.nef, .arw, ...)          balance, *linear* (gamma 1, no auto-brightening), 16 bit
========================  ===========================================================

Transfer curve: photometric stereo needs intensities proportional to the light.
JPEGs are, by their standard, sRGB-encoded; ``transfer="auto"`` decodes them
(:func:`srgb_to_linear`) and leaves every other format as it is (16-bit PNG /
TIFF, EXR and RAW from scientific captures are linear).  ``"srgb"`` or
``"linear"`` force one choice.

Writers: :func:`save_exr` (OpenEXR, float32 channels), :func:`save_float_tiff`
(tifffile) and :func:`save_mesh_file` (trimesh: binary PLY or OBJ with
per-vertex RGB colours).  Every writer writes to a temporary name and renames
(:func:`gpps.io.atomic_write`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import tifffile

from gpps._check import check_choice
from gpps.io.files import atomic_write

__all__ = [
    "IMAGE_EXTENSIONS",
    "RAW_EXTENSIONS",
    "Transfer",
    "srgb_to_linear",
    "linear_to_srgb",
    "read_image_file",
    "decode_image_file",
    "RawImage",
    "save_exr",
    "read_exr",
    "save_float_tiff",
    "read_tiff",
    "save_mesh_file",
    "read_mesh_file",
]

Transfer = Literal["auto", "linear", "srgb"]

CV2_EXTENSIONS = (".png", ".jpg", ".jpeg", ".pgm", ".ppm", ".pnm", ".pbm", ".bmp")
TIFF_EXTENSIONS = (".tif", ".tiff")
EXR_EXTENSIONS = (".exr",)
RAW_EXTENSIONS = (".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".orf", ".rw2", ".pef", ".srw", ".raw", ".3fr", ".iiq", ".x3f")
JPEG_EXTENSIONS = (".jpg", ".jpeg")
#: every extension :func:`read_image_file` reads (lower case)
IMAGE_EXTENSIONS = CV2_EXTENSIONS + TIFF_EXTENSIONS + EXR_EXTENSIONS + RAW_EXTENSIONS


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1): encoded values in [0, 1] to linear."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """The sRGB encoding curve: linear values in [0, 1] to encoded."""
    x = np.clip(np.asarray(x, np.float64), 0.0, None)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def _channels_last_rgb(img: np.ndarray, bgr: bool) -> np.ndarray:
    if img.ndim == 2:
        return img[..., None]
    if img.ndim != 3:
        raise ValueError(f"expected a 2-D grey or 3-D colour image, got shape {img.shape}")
    c = img.shape[2]
    if c == 1:
        return img
    if c == 2:  # grey + alpha
        return img[..., :1]
    if bgr:
        return img[..., 2::-1]  # BGR(A) -> RGB
    return img[..., :3]  # RGB(A) -> RGB


def _int_scale(dtype) -> float:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return 1.0


def read_image_file(path, *, transfer: Transfer = "auto", dtype=np.float32) -> tuple[np.ndarray, dict]:
    """Read one image of any supported format as linear floats.

    Args:
        path: image file; the extension picks the reader (:data:`IMAGE_EXTENSIONS`).
        transfer: "auto" (decode sRGB for JPEG only), "srgb" or "linear".
        dtype: output dtype.

    Returns:
        ``(image, info)``: image (H, W, C) with C = 1 (grey) or 3 (RGB), integer
        formats scaled to [0, 1], float formats as stored; info: ``format``,
        ``bits`` (8, 16, 32, or 16 for half), ``transfer`` applied.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unknown extension, unreadable file, or ``transfer`` not one of its values.
        ImportError: a RAW file without rawpy installed (``pip install gpps[raw]``).
    """
    raw = decode_image_file(path, transfer=transfer)
    return raw.to_float(dtype), raw.info


@dataclass
class RawImage:
    """An image file as decoded, before the scaling to floats (:func:`decode_image_file`).

    Attributes:
        data: (H, W, C) array as the reader gave it (C = 1 or 3, RGB order; may be a view).
        scale: the integer full scale (1.0 for float formats).
        decode: whether the sRGB curve is to be decoded.
        info: ``format``, ``bits``, ``transfer`` (as :func:`read_image_file` returns them).
    """

    data: np.ndarray
    scale: float
    decode: bool
    info: dict

    def to_float(self, dtype=np.float32, out: np.ndarray | None = None) -> np.ndarray:
        """The image as :func:`read_image_file` returns it: ``data / scale`` (sRGB-decoded when ``decode``).

        8/16-bit integers straight to float32: the same values as the float64 quotient rounded to float32
        (both operands are exact in float32, and double rounding through 53 bits is innocuous for a
        quotient of 24-bit numbers: 53 >= 2 * 24 + 2, Figueroa 1995; checked exhaustively in
        tests/test_host_overheads.py), without the (H, W, C) float64 temporaries.

        Args:
            dtype: output dtype.
            out: optional array of ``dtype`` to write into (``data`` broadcast to its shape, e.g. a grey
                image into 3 channels).
        """
        a = self.data
        dtype = np.dtype(dtype)
        if not self.decode and dtype == np.float32 and a.dtype in _EXACT_IN_FLOAT32:
            if out is None:
                out = a.astype(np.float32)
                out /= np.float32(self.scale)
                return out
            return np.divide(a, np.float32(self.scale), out=out, dtype=np.float32, casting="unsafe")
        if not self.decode and self.scale == 1.0 and a.dtype.kind == "f" and a.dtype.itemsize <= 8:
            res = a.astype(dtype)  # x / 1.0 is x; float16/32/64 -> dtype as the float64 route rounds it
        else:
            res = a.astype(np.float64) / self.scale
            if self.decode:
                res = srgb_to_linear(np.clip(res, 0.0, 1.0))
            res = res.astype(dtype)
        if out is None:
            return res
        out[...] = res
        return out


#: integer types whose values (and full scale) are exact in float32
_EXACT_IN_FLOAT32 = tuple(np.dtype(t) for t in (np.uint8, np.int8, np.uint16, np.int16))


def decode_image_file(path, *, transfer: Transfer = "auto") -> RawImage:
    """Decode one image file of any supported format, without scaling it (:func:`read_image_file`'s first half).

    The same checks and errors as :func:`read_image_file`; :meth:`RawImage.to_float` gives its image.
    Safe to call from several threads (the decoders release the GIL).
    """
    check_choice("transfer", transfer, Transfer)
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    ext = path.suffix.lower()
    if ext in CV2_EXTENSIONS:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"{path}: not a readable image")
        fmt = "jpeg" if ext in JPEG_EXTENSIONS else ext[1:]
        bits = 8 * img.dtype.itemsize
        scale = _int_scale(img.dtype)
        img = _channels_last_rgb(img, bgr=True)
    elif ext in TIFF_EXTENSIONS:
        img, bits, scale = read_tiff(path, with_info=True)
        fmt = "tiff"
    elif ext in EXR_EXTENSIONS:
        img = read_exr(path)
        fmt, bits, scale = "exr", 32, 1.0
    elif ext in RAW_EXTENSIONS:
        try:
            import rawpy  # lazy: the optional 'raw' extra
        except ImportError as e:  # pragma: no cover - depends on the extra
            raise ImportError(f"{path}: camera RAW files need rawpy: pip install 'gpps[raw]'") from e
        with rawpy.imread(str(path)) as raw:
            img = raw.postprocess(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=True, user_flip=0)
        fmt, bits, scale = "raw", 16, 65535.0
        img = _channels_last_rgb(img, bgr=False)
    else:
        raise ValueError(f"{path}: expected an image with one of the extensions {', '.join(IMAGE_EXTENSIONS)}, got {ext!r}")
    decode = transfer == "srgb" or (transfer == "auto" and fmt == "jpeg")
    return RawImage(img, scale, decode, {"format": fmt, "bits": int(bits), "transfer": "srgb-decoded" if decode else "linear"})


def read_tiff(path, *, with_info: bool = False):
    """Read a TIFF (first page/series) with tifffile: (H, W, C) floats; integers divided by their maximum.

    With ``with_info`` returns ``(raw array, bits, scale)`` instead (the caller scales).
    """

    arr = tifffile.imread(str(path))
    if arr.ndim == 3 and arr.shape[0] in (1, 3, 4) and arr.shape[2] not in (1, 3, 4):
        arr = np.moveaxis(arr, 0, -1)  # planar -> channels last
    if arr.ndim > 3:
        arr = arr.reshape(arr.shape[-3:]) if np.prod(arr.shape[:-3]) == 1 else arr[(0,) * (arr.ndim - 3)]
    if arr.dtype == np.bool_:
        arr = arr.astype(np.uint8)
    arr = _channels_last_rgb(arr, bgr=False)
    bits, scale = 8 * arr.dtype.itemsize, _int_scale(arr.dtype)
    if with_info:
        return arr, bits, scale
    return arr.astype(np.float64) / scale


def save_float_tiff(path, array) -> None:
    """Write a float32 (H, W) or (H, W, C) array as a TIFF (tifffile), atomically."""


    a = np.ascontiguousarray(np.asarray(array, dtype=np.float32))
    photometric = "rgb" if a.ndim == 3 and a.shape[2] == 3 else "minisblack"
    with atomic_write(path) as tmp:
        tifffile.imwrite(tmp, a, photometric=photometric)


def save_exr(path, array, *, channels: str | None = None) -> None:
    """Write a float32 array as OpenEXR (ZIP compression), atomically.

    Args:
        path: file name (``.exr``).
        array: (H, W) -> one channel (``channels`` default "Z"), or (H, W, 3) -> "RGB".
        channels: channel name for a single-channel image.
    """

    a = np.ascontiguousarray(np.asarray(array, dtype=np.float32))
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.ndim == 2:
        chans = {channels or "Z": a}
    elif a.ndim == 3 and a.shape[2] == 3:
        chans = {"RGB": a}
    else:
        raise ValueError(f"array: expected (H, W) or (H, W, 3), got shape {a.shape}")
    import OpenEXR  # lazy: only EXR files need it, and the GPU machine's kit has no OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_write(path) as tmp:
        with OpenEXR.File(header, chans) as f:
            f.write(str(tmp))


def read_exr(path) -> np.ndarray:
    """Read an OpenEXR file: (H, W, 3) for R, G, B channels, else (H, W, 1) (Y, Z or the first channel)."""
    import OpenEXR  # lazy: only EXR files need it, and the GPU machine's kit has no OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    if not ch:
        raise ValueError(f"{path}: no channels")
    names = {k.split(".")[-1]: k for k in ch}
    if all(c in names for c in "RGB"):
        return np.stack([ch[names[c]] for c in "RGB"], -1).astype(np.float32)
    for c in ("Y", "Z", "R", "L"):
        if c in names:
            return ch[names[c]].astype(np.float32)[..., None]
    return ch[sorted(ch)[0]].astype(np.float32)[..., None]


def save_mesh_file(path, vertices, faces, colors=None) -> Path:
    """Write a triangle mesh with optional per-vertex RGB colours (trimesh), atomically.

    Args:
        path: ``.ply`` (binary, colours as uchar red/green/blue/alpha) or ``.obj``
            (colours as ``v x y z r g b``).
        vertices: (V, 3) float positions (gpps frame).
        faces: (F, 3) int vertex indices.
        colors: (V, 3) floats in [0, 1] or uint8, or None.
    """
    import trimesh  # lazy: 1.07 s to import (measured), needed only for meshes


    path = Path(path)
    ext = path.suffix.lower()
    if ext not in (".ply", ".obj"):
        raise ValueError(f"path: expected a .ply or .obj file name, got {str(path)!r}")
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    kw = {}
    if colors is not None:
        c = np.asarray(colors)
        if c.shape != (len(v), 3):
            raise ValueError(f"colors: expected shape {(len(v), 3)}, got {c.shape}")
        if np.issubdtype(c.dtype, np.floating):
            c = np.round(np.clip(np.nan_to_num(c), 0.0, 1.0) * 255).astype(np.uint8)
        kw["vertex_colors"] = np.concatenate([c.astype(np.uint8), np.full((len(v), 1), 255, np.uint8)], 1)
    mesh = trimesh.Trimesh(vertices=v, faces=f, process=False, **kw)
    with atomic_write(path) as tmp:
        if ext == ".ply":
            data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False)
            Path(tmp).write_bytes(data)
        else:
            text = trimesh.exchange.obj.export_obj(mesh, include_normals=False, include_color=colors is not None, include_texture=False, header="gpps mesh (gpps frame: x right, y up, z toward the camera)")
            Path(tmp).write_text(text)
    return path


def read_mesh_file(path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Read a PLY/OBJ mesh back: ``(vertices (V, 3), faces (F, 3), colours (V, 3) uint8 or None)``."""
    import trimesh  # lazy: 1.07 s to import (measured), needed only for meshes

    m = trimesh.load(str(path), process=False, force="mesh")
    col = None
    vc = getattr(m.visual, "vertex_colors", None)
    if getattr(m.visual, "kind", None) == "vertex" and vc is not None and len(vc) == len(m.vertices):
        col = np.asarray(vc)[:, :3].astype(np.uint8)
    return np.asarray(m.vertices), np.asarray(m.faces), col
