"""Reading and writing images, arrays and DiLiGenT-style folders.

Every writer goes through :func:`atomic_write`: the data is written to a
temporary name in the target folder and renamed into place, so a crash never
leaves a half-written file.  Folders are written the same way (a temporary
sibling folder renamed at the end).

16-bit RGB PNGs are read with OpenCV (``IMREAD_UNCHANGED``; imageio and Pillow
silently return 8 bits) and converted from OpenCV's BGR order to RGB.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import tifffile

from gpps._version import __version__

__all__ = [
    "MARKER",
    "OutputError",
    "check_output_dir",
    "read_marker",
    "atomic_write",
    "atomic_dir",
    "save_npy",
    "read_npy",
    "save_json",
    "json_default",
    "save_txt",
    "save_png",
    "save_tiff",
    "read_image",
    "read_mask",
    "read_K",
    "read_matrix",
    "Dataset",
    "read_dataset",
    "write_dataset",
]


def _cv2():
    return cv2


MARKER = ".gpps-output.json"
"""Name of the marker file that gpps writes into every output folder (its manifest)."""


class OutputError(ValueError):
    """An output path gpps refuses to write (it would lose a user's data); raised before any computing."""


def _umask() -> int:
    """The process's umask, read without changing it where the platform allows."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    old = os.umask(0o022)  # no /proc: set and restore (not thread-safe, rarely reached)
    os.umask(old)
    return old


def _chmod_default(path: Path, directory: bool) -> None:
    """Give a temporary file (0600) or folder (0700) the permissions a plain ``open``/``mkdir`` would."""
    with contextlib.suppress(OSError):
        os.chmod(path, (0o777 if directory else 0o666) & ~_umask())


def read_marker(path) -> dict | None:
    """The manifest of a folder gpps wrote (``{"gpps": version, "files": [...]}``), or None."""
    f = Path(path) / MARKER
    if not f.is_file():
        return None
    try:
        d = json.loads(f.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(d, dict) or not isinstance(d.get("files"), list):
        return None
    return d


def check_output_dir(path, *, inputs=(), overwrite: bool = False, name: str = "--out") -> Path:
    """Check an output folder before any computing; return its resolved path.

    gpps writes a whole output folder at once (a temporary sibling renamed into
    place) and never deletes or overwrites what it did not write.  Refused, with
    an :class:`OutputError` naming ``name``:
    * a path that is an existing file, or whose parent is a file;
    * one of ``inputs``, or a folder containing one of them;
    * a non-empty folder without gpps's marker (:data:`MARKER`), or one with the
      marker that also holds files gpps did not write;
    * an earlier gpps output folder unless ``overwrite`` is True;
    * a place whose first existing parent is not writable.

    Args:
        path: the output folder.
        inputs: paths (files or folders) the command reads.
        overwrite: allow replacing an earlier gpps output folder (only that).
        name: the argument's name in messages.

    Raises:
        OutputError: as above.
    """
    if path is None or str(path) == "":
        raise OutputError(f"{name}: expected a folder path, got {path!r}")
    p = Path(path).expanduser()
    real = p.resolve()
    for anc in (real, *real.parents):
        if anc.exists() or anc.is_symlink():
            if not anc.is_dir():
                what = "is an existing file" if anc == real else f"has a parent that is a file ({anc})"
                raise OutputError(f"{name}: {p} {what}; expected a folder (new, empty, or an earlier gpps output)")
            if not os.access(anc, os.W_OK | os.X_OK):
                raise OutputError(f"{name}: cannot write in {anc} (permission denied)")
            break
    if real.parent == real:
        raise OutputError(f"{name}: expected a folder below the file-system root, got {p}")
    for inp in inputs:
        if inp is None:
            continue
        r = Path(inp).expanduser().resolve()
        if r == real:
            raise OutputError(f"{name}: {p} is an input of this command; choose another output folder")
        if real in r.parents:
            raise OutputError(f"{name}: {p} contains an input of this command ({inp}); choose another output folder")
    if real.is_dir():
        entries = sorted(e.name for e in real.iterdir())
        if entries:
            manifest = read_marker(real)
            if manifest is None:
                raise OutputError(
                    f"{name}: {p} is a non-empty folder that gpps did not write; expected a new or empty folder "
                    "or an earlier gpps output (gpps never replaces other files)")
            foreign = sorted(set(entries) - set(manifest["files"]) - {MARKER})
            if foreign:
                shown = ", ".join(foreign[:3]) + (" ..." if len(foreign) > 3 else "")
                raise OutputError(f"{name}: {p} is an earlier gpps output but also holds files gpps did not write "
                                  f"({shown}); gpps will not replace it")
            if not overwrite:
                raise OutputError(f"{name}: {p} holds an earlier gpps output; pass --overwrite to replace it")
    return real


@contextlib.contextmanager
def atomic_write(path, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    The file gets the permissions of a plain ``open`` (``0666`` less the umask).

    Args:
        path: final file name.
        suffix: extension of the temporary name (defaults to that of ``path``,
            so that writers that look at the extension, like OpenCV, work).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = path.suffix if suffix is None else suffix
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".tmp" + suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        _chmod_default(Path(tmp), directory=False)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


@contextlib.contextmanager
def atomic_dir(path, *, overwrite: bool = False, inputs=(), name: str = "out"):
    """Yield a temporary folder beside ``path``; on success it becomes ``path``.

    The target is checked first (:func:`check_output_dir`: never a file, an
    input, or a folder gpps did not write; an earlier gpps output only with
    ``overwrite``).  On success the manifest (:data:`MARKER`) is written, the
    folder gets the permissions of a plain ``mkdir`` (``0777`` less the umask)
    and is renamed into place; an earlier output is moved aside first and then
    removed, so readers never see a mix of old and new files.  On any failure,
    ``KeyboardInterrupt`` included, the temporary folder is removed and the
    target is left as it was.

    Args:
        path: the output folder.
        overwrite: replace an earlier gpps output folder.
        inputs: paths the computation read (refused as targets).
        name: the argument's name in messages.
    """
    real = check_output_dir(path, inputs=inputs, overwrite=overwrite, name=name)
    real.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{real.name}.", suffix=".tmp", dir=real.parent))
    old = None
    try:
        yield tmp
        files = sorted(e.name for e in tmp.iterdir() if e.name != MARKER)

        (tmp / MARKER).write_text(json.dumps({"gpps": __version__, "files": files}, indent=1) + "\n")
        _chmod_default(tmp, directory=True)
        # the target may have changed while we computed: check again just before the rename
        check_output_dir(real, inputs=inputs, overwrite=overwrite, name=name)
        if real.is_dir():
            old = Path(tempfile.mkdtemp(prefix=f".{real.name}.", suffix=".old", dir=real.parent))
            _swap_into(tmp, real, old)
        else:
            os.replace(tmp, real)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def _swap_into(tmp: Path, real: Path, old: Path) -> None:
    """Replace the contents of the existing folder ``real`` by those of ``tmp``, keeping ``real`` itself.

    The folder is kept (it may be a shell's working directory, ``--out .``):
    its entries (the marker first) move aside into ``old``, then the new ones
    move in (the marker last, so a reader sees a complete output or none).  On
    failure the earlier entries are put back.
    """
    def entries(d, marker_first):
        names = sorted(e.name for e in d.iterdir())
        if MARKER in names:
            names.remove(MARKER)
            names = [MARKER, *names] if marker_first else [*names, MARKER]
        return names

    out_old, in_new = [], []
    try:
        for nm in entries(real, marker_first=True):
            os.replace(real / nm, old / nm)
            out_old.append(nm)
        for nm in entries(tmp, marker_first=False):
            os.replace(tmp / nm, real / nm)
            in_new.append(nm)
    except BaseException:
        for nm in reversed(in_new):
            with contextlib.suppress(OSError):
                os.replace(real / nm, tmp / nm)
        for nm in reversed(out_old):
            with contextlib.suppress(OSError):
                os.replace(old / nm, real / nm)
        raise
    tmp.rmdir()


def save_npy(path, array) -> None:
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(array))


def save_json(path, obj) -> None:
    with atomic_write(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False, default=json_default) + "\n")


def json_default(o):
    """The ``default=`` of :func:`json.dump` for gpps reports: numpy scalars and arrays as numbers and lists, paths as strings.

    Raises:
        TypeError: anything else (``json.dumps`` reports it with the key's value).
    """
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def save_txt(path, array, fmt: str = "%.9g") -> None:
    with atomic_write(path) as tmp:
        np.savetxt(tmp, np.atleast_2d(np.asarray(array, dtype=np.float64)), fmt=fmt)


def save_png(path, image, bits: int = 16) -> None:
    """Write an image in [0, 1] (float) or an integer image as PNG.

    Args:
        path: file name.
        image: (H, W) or (H, W, 3) RGB; floats are clipped to [0, 1] and scaled
            to ``2**bits - 1``; integer arrays are written as they are.
        bits: 8 or 16 (for float input).
    """
    img = np.asarray(image)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
        raise ValueError(f"image: expected (H, W) or (H, W, 3), got shape {img.shape}")
    if bits not in (8, 16):
        raise ValueError(f"bits: expected 8 or 16, got {bits!r}")
    if np.issubdtype(img.dtype, np.floating):
        if not np.all(np.isfinite(img)):
            raise ValueError("image: expected finite values, got NaN or inf")
        scale = 2**bits - 1
        img = np.round(np.clip(img, 0.0, 1.0) * scale).astype(np.uint16 if bits == 16 else np.uint8)
    elif img.dtype not in (np.uint8, np.uint16):
        raise TypeError(f"image: expected float, uint8 or uint16, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]  # RGB -> BGR for OpenCV
    cv2 = _cv2()
    with atomic_write(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise OSError(f"could not write PNG {path}")


def save_tiff(path, array) -> None:
    """Write a float32 array (e.g. depth) as a single-channel TIFF."""

    with atomic_write(path) as tmp:
        tifffile.imwrite(tmp, np.asarray(array, dtype=np.float32))


def read_image(path, *, dtype=np.float32) -> np.ndarray:
    """Read an 8/16-bit grey or RGB image as floats in [0, 1].

    Returns:
        (H, W, C) array, C = 1 for grey and 3 for colour (RGB order).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    cv2 = _cv2()
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if img.dtype == np.uint8:
        scale = 255.0
    elif img.dtype == np.uint16:
        scale = 65535.0
    else:
        scale = 1.0
    if img.ndim == 2:
        img = img[..., None]
    elif img.shape[2] == 4:
        img = img[..., 2::-1]
    elif img.shape[2] == 3:
        img = img[..., ::-1]
    return (img.astype(np.float64) / scale).astype(dtype)


def read_mask(path) -> np.ndarray:
    """Read a mask image: (H, W) bool, True where any channel is > half range."""
    m = read_image(path)
    return np.any(m > 0.5, axis=-1)


def read_npy(path, *, name: str | None = None) -> np.ndarray:
    """Read a ``.npy`` array (no pickled objects); a file that is not one is a ValueError naming ``name``
    (numpy's own messages say neither which argument nor, for a text file, what is wrong)."""
    path = Path(path)
    name = name or path.name
    if not path.is_file():
        raise FileNotFoundError(f"{name}: file not found: {path}")
    try:
        a = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise ValueError(f"{name}: expected a numeric .npy array, could not read {path} ({e})") from None
    if not isinstance(a, np.ndarray):  # (an .npz archive: np.load opened it)
        a.close()
        raise ValueError(f"{name}: expected a numeric .npy array, got an .npz archive in {path}")
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{name}: expected a numeric .npy array, got {a.dtype} in {path}")
    return a


def read_matrix(path, *, shape=None, name: str | None = None) -> np.ndarray:
    """Read a whitespace/comma separated numeric text matrix (float64)."""
    path = Path(path)
    name = name or path.name
    if not path.is_file():
        raise FileNotFoundError(f"{name}: file not found: {path}")
    text = path.read_text().replace(",", " ")
    rows = [r.split() for r in text.splitlines() if r.strip() and not r.lstrip().startswith("#")]
    try:
        m = np.array([[float(v) for v in r] for r in rows], dtype=np.float64)
    except ValueError:
        raise ValueError(f"{name}: expected numbers, could not parse {path}") from None
    if m.ndim != 2:
        raise ValueError(f"{name}: expected a matrix with equal row lengths in {path}")
    if shape is not None:
        for want, got in zip(shape, m.shape):
            if want is not None and want != got:
                raise ValueError(f"{name}: expected shape {shape}, got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{name}: expected finite numbers, got NaN or inf")
    return m


def read_K(path) -> np.ndarray:
    """Read a 3x3 intrinsic matrix from text (DiLiGenT ``K.txt``)."""
    return read_matrix(path, shape=(3, 3), name="K")


@dataclass
class Dataset:
    """A photometric-stereo capture: images, lights, mask and optional camera/ground truth.

    Attributes:
        images: (N, H, W, C) float32, already divided by the light intensities
            when ``normalised`` is True.
        mask: (H, W) bool.
        light_directions: (N, 3) unit vectors toward the lights, or None.
        light_positions: (N, 3) point-light positions (scene units), or None.
        light_intensities: (N, 3) RGB intensities as read (ones if absent).
        K: (3, 3) intrinsics or None (orthographic).
        normal_gt: (H, W, 3) float32 or None.
        depth_gt: (H, W) float or None.
        material: dict from ``material.json`` or None.
        filenames: image file names in order.
    """

    images: np.ndarray
    mask: np.ndarray
    light_directions: np.ndarray | None = None
    light_positions: np.ndarray | None = None
    light_intensities: np.ndarray | None = None
    K: np.ndarray | None = None
    normal_gt: np.ndarray | None = None
    depth_gt: np.ndarray | None = None
    material: dict | None = None
    filenames: list[str] = field(default_factory=list)
    normalised: bool = True
    extra: dict = field(default_factory=dict)


def read_dataset(root, *, normalise: bool = True, indices=None) -> Dataset:
    """Read a DiLiGenT-style folder.

    Layout: ``filenames.txt`` (else ``*.png`` sorted), ``light_directions.txt``
    and/or ``light_positions.txt`` (N x 3), ``light_intensities.txt`` (N x 3),
    ``mask.png`` (else all pixels), ``K.txt`` (optional), ``normal_gt.npy`` /
    ``Normal_gt.mat``-free ground truth, ``depth_gt.npy``, ``material.json``.

    Args:
        root: folder.
        normalise: divide each image by its row of ``light_intensities.txt``.
        indices: optional subset of image indices (0-based) to read.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {root}")
    fn_file = root / "filenames.txt"
    if fn_file.is_file():
        names = [s.strip() for s in fn_file.read_text().splitlines() if s.strip()]
    else:
        names = sorted(p.name for p in root.glob("*.png") if p.name[0].isdigit())
    if not names:
        raise ValueError(f"{root}: no images (filenames.txt or numbered *.png)")
    n = len(names)
    sel = list(range(n)) if indices is None else [int(i) for i in indices]
    for i in sel:
        if not 0 <= i < n:
            raise ValueError(f"indices: expected values in [0, {n}), got {i}")

    def opt(name, shape):
        p = root / name
        return read_matrix(p, shape=shape, name=name) if p.is_file() else None

    ld = opt("light_directions.txt", (n, 3))
    lp = opt("light_positions.txt", (n, 3))
    li = opt("light_intensities.txt", (n, 3))
    K = read_K(root / "K.txt") if (root / "K.txt").is_file() else None
    imgs = [read_image(root / names[i]) for i in sel]
    shapes = {im.shape for im in imgs}
    if len(shapes) != 1:
        raise ValueError(f"{root}: images differ in shape: {sorted(shapes)}")
    images = np.stack(imgs)
    if images.shape[-1] == 1:
        images = np.repeat(images, 3, axis=-1)
    h, w = images.shape[1:3]
    mask = read_mask(root / "mask.png") if (root / "mask.png").is_file() else np.ones((h, w), bool)
    if mask.shape != (h, w):
        raise ValueError(f"mask.png: expected shape {(h, w)}, got {mask.shape}")
    li_sel = None if li is None else li[sel]
    if normalise and li_sel is not None:
        if np.any(li_sel <= 0):
            raise ValueError("light_intensities.txt: expected positive intensities")
        images = (images / li_sel[:, None, None, :].astype(np.float32)).astype(np.float32)
    ngt = read_npy(root / "normal_gt.npy").astype(np.float32) if (root / "normal_gt.npy").is_file() else None
    dgt = read_npy(root / "depth_gt.npy") if (root / "depth_gt.npy").is_file() else None
    mat = json.loads((root / "material.json").read_text()) if (root / "material.json").is_file() else None
    return Dataset(
        images=images,
        mask=mask,
        light_directions=None if ld is None else ld[sel],
        light_positions=None if lp is None else lp[sel],
        light_intensities=li_sel,
        K=K,
        normal_gt=ngt,
        depth_gt=dgt,
        material=mat,
        filenames=[names[i] for i in sel],
        normalised=normalise and li_sel is not None,
    )


def write_dataset(root, ds: Dataset, *, bits: int = 16, overwrite: bool = False) -> Path:
    """Write a :class:`Dataset` as a DiLiGenT-style folder, atomically.

    Images are written as they are (they should already be in [0, 1]); the
    light intensities are written to ``light_intensities.txt`` so that a
    reader divides by them.  ``root`` follows :func:`check_output_dir` (new,
    empty, or an earlier gpps output with ``overwrite``).
    """
    root = Path(root)
    images = np.asarray(ds.images)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected (N, H, W, 3), got shape {images.shape}")
    n = images.shape[0]
    names = ds.filenames or [f"{i + 1:03d}.png" for i in range(n)]
    with atomic_dir(root, overwrite=overwrite, name="root") as tmp:
        for name, img in zip(names, images):
            save_png(tmp / name, img, bits=bits)
        (tmp / "filenames.txt").write_text("\n".join(names) + "\n")
        if ds.light_directions is not None:
            save_txt(tmp / "light_directions.txt", ds.light_directions)
        if ds.light_positions is not None:
            save_txt(tmp / "light_positions.txt", ds.light_positions)
        li = ds.light_intensities if ds.light_intensities is not None else np.ones((n, 3))
        save_txt(tmp / "light_intensities.txt", li)
        save_png(tmp / "mask.png", ds.mask.astype(np.uint8) * 255)
        if ds.K is not None:
            save_txt(tmp / "K.txt", ds.K)
        if ds.material is not None:
            save_json(tmp / "material.json", ds.material)
        if ds.normal_gt is not None:
            save_npy(tmp / "normal_gt.npy", np.asarray(ds.normal_gt, dtype=np.float32))
        if ds.depth_gt is not None:
            save_npy(tmp / "depth_gt.npy", np.asarray(ds.depth_gt, dtype=np.float32))
        for k, v in ds.extra.items():
            save_npy(tmp / f"{k}.npy", v)
    return root
