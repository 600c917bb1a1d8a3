"""Photometric-stereo folders as users have them.

:func:`read_capture` reads a folder of images taken by a fixed camera under
different lights, in any format :mod:`gpps.io.formats` reads (PNG 8/16, PGM/PPM,
JPEG, TIFF 8/16/32f, EXR, camera RAW), with whatever of the DiLiGenT-style
side files is present:
* ``filenames.txt``: the images, in order; without it, every image file of a
  supported format in the folder, sorted by name (natural order: ``img2`` before
  ``img10``), except the side images below.
* ``light_directions.txt`` / ``light_positions.txt`` (N x 3, gpps frame),
  ``light_intensities.txt`` (N x 3 RGB or N x 1): the lights; none of them
  means uncalibrated.
* ``mask.png`` (any supported format named ``mask.*``): the object; without
  it an automatic mask (:func:`gpps.host.automask.automatic_mask`).
* ``K.txt``: perspective camera (pixels), else orthographic.
* an image named ``*ambient*`` (or ``ambient=`` a file): the scene with every
  light off; it is subtracted from every image (negative values clipped to 0).
* ``normal_gt.npy``, ``depth_gt.npy``, ``material.json``: optional.

``max_size`` downscales images whose longer side exceeds it (area averaging;
the mask by nearest neighbour; ``K`` scaled with the pixel grid: pixel
centres at integers, so ``c' = (c + 0.5) s - 0.5``).
"""

from __future__ import annotations

import json
import os
import re
from concurrent.futures import ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from gpps._check import as_path, warn
from gpps.host.automask import automatic_mask
from gpps.io import Dataset, read_K, read_matrix, read_npy
from gpps.io.formats import IMAGE_EXTENSIONS, Transfer, decode_image_file, read_image_file

__all__ = ["Capture", "read_capture", "list_images", "find_side_file", "SIDE_IMAGE_STEMS"]

#: image files that are not captures (compared on the lower-case stem)
SIDE_IMAGE_STEMS = ("mask", "normal_gt", "normals", "albedo", "depth", "view", "normal", "chrome_mask", "matte_mask", "sphere_mask", "card_mask")


#: at most this many threads decode and scale the images (OpenCV, tifffile and numpy release the GIL)
MAX_READ_THREADS = 8


def _read_threads() -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_READ_THREADS))


def _imap(fn, items):
    """``fn`` over ``items`` on a bounded thread pool: a generator of the results in order (each exception
    raised at its item, as a sequential loop would; close the generator to drop the items not started)."""
    items = list(items)
    threads = min(_read_threads(), len(items))
    if threads <= 1:
        yield from map(fn, items)
        return
    with ThreadPoolExecutor(threads, thread_name_prefix="gpps-read") as pool:
        futures = [pool.submit(fn, x) for x in items]
        try:
            for f in futures:
                yield f.result()
        finally:
            for f in futures:
                f.cancel()


def _each(fn, items) -> None:
    """``fn`` over ``items`` on the thread pool of :func:`_imap`; returns when all are done."""
    with closing(_imap(fn, items)) as results:
        for _ in results:
            pass


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _is_ambient(name: str) -> bool:
    return "ambient" in Path(name).stem.lower()


def list_images(root) -> list[str]:
    """The capture images of a folder, in natural sorted order (no side images, no ambient image)."""
    root = Path(root)
    names = []
    for p in root.iterdir():
        if not p.is_file() or p.name.startswith("."):
            continue
        if p.suffix.lower() not in IMAGE_EXTENSIONS:
            continue
        stem = p.stem.lower()
        if stem in SIDE_IMAGE_STEMS or stem.endswith("_gt") or _is_ambient(p.name):
            continue
        names.append(p.name)
    return sorted(names, key=_natural_key)


@dataclass
class Capture:
    """A folder read by :func:`read_capture`.

    Attributes:
        dataset: :class:`gpps.io.Dataset` (images divided by the light
            intensities when those are given; ``light_intensities`` as read).
        mask_source: "mask.png" (the file's name), "automatic" or "given".
        automask: the automatic mask's info, when one was made.
        formats: the image formats, bit depths and transfer curves seen.
        ambient: the ambient image's file name, when one was subtracted.
        scale: downscaling factor applied (1: none).
        calibrated: whether the folder gives light directions or positions.
    """

    dataset: Dataset
    mask_source: str
    automask: dict | None = None
    formats: list = field(default_factory=list)
    ambient: str | None = None
    scale: float = 1.0
    calibrated: bool = True


def find_side_file(root, stem: str) -> Path | None:
    """The side image ``<stem>.<ext>`` in folder ``root`` (any extension :mod:`gpps.io.formats` reads, lower or upper case).

    Args:
        root: the folder.
        stem: the file name without extension, e.g. ``"mask"`` or ``"chrome_mask"``.

    Returns:
        The first existing file, in the order of :data:`gpps.io.formats.IMAGE_EXTENSIONS`; None if there is none.
    """
    root = Path(root)
    for ext in IMAGE_EXTENSIONS:
        for cand in (root / f"{stem}{ext}", root / f"{stem}{ext.upper()}"):
            if cand.is_file():
                return cand
    return None


def _resize(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    out = cv2.resize(np.ascontiguousarray(img), size, interpolation=cv2.INTER_AREA)
    return out[..., None] if out.ndim == 2 else out


def _decode_images(root: Path, names: list[str], transfer, step) -> tuple[list, dict]:
    """The files decoded on the thread pool (:func:`decode_image_file`), progress and errors in file order.

    Returns:
        ``(raws, formats)``: the :class:`gpps.io.formats.RawImage` of each file and a count of each
        ``(format, bits, transfer)``.

    Raises:
        ValueError: images of different sizes (after every file was read), or what a file's decoding raised.
    """
    n = len(names)
    formats, raws = {}, []
    with closing(_imap(lambda nm: decode_image_file(root / nm, transfer=transfer), names)) as decoded:
        for k, (name, raw) in enumerate(zip(names, decoded)):
            raws.append(raw)
            info = raw.info
            formats[(info["format"], info["bits"], info["transfer"])] = formats.get((info["format"], info["bits"], info["transfer"]), 0) + 1
            step(k + 1, n, f"read {name}")
    shapes = {r.data.shape[:2] for r in raws}
    if len(shapes) != 1:
        raise ValueError(f"dir: expected images of one size, got {sorted(shapes)} in {root}")
    return raws, formats


def _ambient_path(root: Path, names: list[str], ambient) -> Path | None:
    """The ambient image to subtract: ``"auto"``: the first ``*ambient*`` image that is no capture; a name: that
    file (FileNotFoundError when missing); None: none."""
    if ambient is None:
        return None
    if ambient == "auto":
        cands = [p for p in sorted(root.iterdir()) if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS and _is_ambient(p.name) and p.name not in names]
        return cands[0] if cands else None
    amb_path = Path(ambient) if Path(ambient).is_absolute() else root / ambient
    if not amb_path.is_file():
        raise FileNotFoundError(f"ambient: file not found: {amb_path}")
    return amb_path


def _ground_truth(path: Path, shape: tuple, scale: float) -> np.ndarray | None:
    """A ground-truth side file (``normal_gt.npy`` (H, W, 3), ``depth_gt.npy`` (H, W)) of the images' ``shape``,
    or None: absent, the images were downscaled (``scale`` != 1: it no longer matches), or of another shape
    (a :class:`~gpps.GppsWarning` names the file and both shapes; the reconstruction does not need it, only
    the report's errors)."""
    if not path.is_file() or scale != 1.0:
        return None
    a = read_npy(path)
    if a.shape != tuple(shape):
        warn(f"{path.name}: expected shape {tuple(shape)} (the images' size), got {a.shape} in {path}; ignored "
             "(no errors against it in the report)")
        return None
    return a


def _material_file(path: Path) -> dict | None:
    """``material.json`` as a dict (None when absent); a file that is not a JSON object is a ValueError naming it."""
    if not path.is_file():
        return None
    try:
        mat = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"material.json: expected a JSON object such as {{\"brdf\": \"blinn-phong\", "
                         f"\"shininess\": 40}}, could not parse {path} ({e})") from None
    if not isinstance(mat, dict):
        raise ValueError(f"material.json: expected a JSON object (the material's name and parameters), got a "
                         f"{type(mat).__name__} in {path}")
    return mat


def read_capture(root, *, transfer: Transfer = "auto", max_size: int | None = None, ambient: str | None = "auto",
                 mask=None, automask=None, normalise: bool = True, lights=None, progress=None) -> Capture:
    """Read a photometric-stereo folder as users have it.

    Args:
        root: the folder.
        transfer: image transfer curve ("auto": sRGB decoded for JPEG only; see
            :func:`gpps.io.formats.read_image_file`).
        max_size: downscale so that the longer side is at most this (None: no).
        ambient: "auto" (subtract an image named ``*ambient*`` if there is one),
            None (never), or a file name (relative to ``root`` or absolute).
        mask: None (``mask.*`` in the folder, else automatic), "auto" (always
            automatic), "none" (every pixel), or an (H, W) bool array / a mask file path.
        automask: :class:`gpps.host.automask.AutoMaskConfig` for the automatic mask.
        normalise: divide each image by its row of ``light_intensities.txt``.
        lights: another folder to read the light files from (e.g. the output of
            ``gpps calibrate-lights``); its rows must be in the images' order.
        progress: optional ``progress(done, total, message)`` while reading.

    Returns:
        :class:`Capture`.

    Raises:
        FileNotFoundError: no folder, or a named file is missing.
        ValueError: no images, images of different sizes, side files of the
            wrong shape, ``max_size`` < 8.
    """
    root = as_path("dir", root)
    if not root.is_dir():
        raise FileNotFoundError(f"dir: folder not found: {root}")
    if max_size is not None and (int(max_size) != max_size or max_size < 8):
        raise ValueError(f"max_size: expected an integer >= 8 or None, got {max_size!r}")
    fn_file = root / "filenames.txt"
    if fn_file.is_file():
        names = [s.strip() for s in fn_file.read_text().splitlines() if s.strip() and not s.lstrip().startswith("#")]
    else:
        names = list_images(root)
    if not names:
        raise ValueError(f"dir: expected images ({', '.join(e[1:] for e in IMAGE_EXTENSIONS[:9])}, ...) or filenames.txt in {root}, found none")
    n = len(names)
    step = progress or (lambda *a, **k: None)

    lroot = root
    if lights is not None:
        lroot = Path(lights)
        if not lroot.is_dir():
            raise FileNotFoundError(f"lights: folder not found: {lroot}")
        if not any((lroot / f).is_file() for f in ("light_directions.txt", "light_positions.txt")):
            raise ValueError(f"lights: expected light_directions.txt or light_positions.txt in {lroot}")

    def opt(name, shape):
        p = lroot / name
        return read_matrix(p, shape=shape, name=str(p)) if p.is_file() else None

    ld = opt("light_directions.txt", (n, 3))
    lp = opt("light_positions.txt", (n, 3))
    li = opt("light_intensities.txt", (n, None))
    if li is not None:
        if li.shape[1] == 1:
            li = np.repeat(li, 3, axis=1)
        elif li.shape[1] != 3:
            raise ValueError(f"light_intensities.txt: expected {n} rows of 1 or 3 values, got shape {li.shape}")
    K = read_K(root / "K.txt") if (root / "K.txt").is_file() else None
    mat = _material_file(root / "material.json")  # (before the images are decoded: a bad file fails at once)
    raws, formats = _decode_images(root, names, transfer, step)
    h, w = raws[0].data.shape[:2]
    amb_path = _ambient_path(root, names, ambient)
    amb = None
    if amb_path is not None:
        amb, _ = read_image_file(amb_path, transfer=transfer)
        if amb.shape[:2] != (h, w):
            raise ValueError(f"ambient: expected shape {(h, w)}, got {amb.shape[:2]} in {amb_path}")
    # one (N, H, W, 3) float32 stack, each image scaled into its slot (grey images repeated over the
    # channels), minus the ambient image and clipped at 0 in place
    images = np.empty((n, h, w, 3), np.float32)

    def fill(k):
        im = raws[k].to_float(np.float32, out=images[k])
        if amb is not None:
            np.subtract(im, amb, out=im)
            np.clip(im, 0.0, None, out=im)

    _each(fill, range(n))
    raws.clear()  # the decoded files, no longer needed
    amb_name = None if amb_path is None else amb_path.name
    mask_source = "given"
    if mask is None:
        mp = find_side_file(root, "mask")
        if mp is not None:
            m_img, _ = read_image_file(mp, transfer="linear")
            m = np.any(m_img > 0.5, axis=-1)
            mask_source = mp.name
        else:
            m = None
    elif isinstance(mask, str) and mask == "auto":
        m = None
    elif isinstance(mask, str) and mask == "none":
        m = np.ones((h, w), bool)
        mask_source = "none"
    elif isinstance(mask, (str, Path)):
        m_img, _ = read_image_file(mask, transfer="linear")
        m = np.any(m_img > 0.5, axis=-1)
        mask_source = str(mask)
    else:
        m = np.asarray(mask, bool)
    if m is not None and m.shape != (h, w):
        raise ValueError(f"mask: expected shape {(h, w)}, got {m.shape}")
    scale = 1.0
    if max_size is not None and max(h, w) > max_size:
        scale = max_size / max(h, w)
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        images = np.stack([_resize(im, size) for im in images]).astype(np.float32)
        if m is not None:
            m = cv2.resize(m.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
        sx, sy = size[0] / w, size[1] / h
        if K is not None:
            K = K.copy()
            K[0, 0] *= sx
            K[1, 1] *= sy
            K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
            K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        h, w = size[1], size[0]
    am_info = None
    if m is None:
        m, am_info = automatic_mask(images, automask)
        mask_source = "automatic"
    normalised = False
    if normalise and li is not None:
        if np.any(li <= 0):
            raise ValueError("light_intensities.txt: expected positive intensities")
        li32 = li.astype(np.float32)
        _each(lambda k: np.divide(images[k], li32[k], out=images[k]), range(n))
        normalised = True
    ngt = _ground_truth(root / "normal_gt.npy", (h, w, 3), scale)
    dgt = _ground_truth(root / "depth_gt.npy", (h, w), scale)
    ngt = None if ngt is None else ngt.astype(np.float32)
    ds = Dataset(images=images.astype(np.float32, copy=False), mask=m, light_directions=ld, light_positions=lp, light_intensities=li,
                 K=K, normal_gt=ngt, depth_gt=dgt, material=mat, filenames=list(names), normalised=normalised)
    fmts = [{"format": f, "bits": b, "transfer": t, "images": c} for (f, b, t), c in formats.items()]
    return Capture(dataset=ds, mask_source=mask_source, automask=am_info, formats=fmts, ambient=amb_name, scale=scale,
                   calibrated=ld is not None or lp is not None)
