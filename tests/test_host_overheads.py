"""The cheaper host-side paths of issue 20 against straightforward references: the same values, bit for bit,
the same errors and warnings.

* reading: the threaded :func:`gpps.io.capture.read_capture` and the float32 scaling of 8/16-bit images
  against the sequential float64 route it replaced;
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

import gpps.io.capture as capture
from gpps.io import save_png, save_txt
from gpps.io.formats import RawImage, read_image_file, srgb_to_linear


def _bits(a: np.ndarray) -> np.ndarray:
    """The bit patterns of a float32 array (NaN == NaN, -0 != +0)."""
    a = np.ascontiguousarray(a)
    assert a.dtype == np.float32
    return a.view(np.uint32)


def _same(a, b) -> bool:
    return a.shape == b.shape and np.array_equal(_bits(a), _bits(b))


# ---------------------------------------------------------------------------------------------------- reading


@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.uint16, np.int16])
def test_float32_scaling_of_small_integers_is_the_float64_quotient(dtype):
    """Every value of the type: float32(x) / float32(s) == float32(float64(x) / s) (innocuous double rounding)."""
    info = np.iinfo(dtype)
    x = np.arange(info.min, info.max + 1).astype(dtype).reshape(1, -1, 1)
    scale = float(info.max)
    ref = (x.astype(np.float64) / scale).astype(np.float32)
    raw = RawImage(x, scale, False, {})
    assert _same(raw.to_float(), ref)
    out = np.empty(x.shape[:2] + (3,), np.float32)  # a grey image broadcast into 3 channels
    raw.to_float(out=out)
    assert _same(out, np.repeat(ref, 3, axis=-1))


def _float64_route(data, scale, decode, dtype=np.float32):
    """read_image_file's scaling before issue 20: float64 quotient, sRGB decoding, cast."""
    out = data.astype(np.float64) / scale
    if decode:
        out = srgb_to_linear(np.clip(out, 0.0, 1.0))
    return out.astype(dtype)


def test_read_image_file_matches_the_float64_route(tmp_path):
    rng = np.random.default_rng(0)
    rgb16 = rng.integers(0, 65536, (7, 9, 3), dtype=np.uint16)
    grey8 = rng.integers(0, 256, (7, 9), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb16[..., ::-1])
    cv2.imwrite(str(tmp_path / "grey8.png"), grey8)
    cv2.imwrite(str(tmp_path / "rgb8.jpg"), rng.integers(0, 256, (7, 9, 3), dtype=np.uint8))
    f32 = rng.random((7, 9, 3)).astype(np.float32)
    f32[0, 0, 0] = -0.0
    tifffile.imwrite(tmp_path / "f32.tif", f32, photometric="rgb")
    tifffile.imwrite(tmp_path / "i16.tif", rng.integers(-32768, 32768, (7, 9), dtype=np.int16))
    tifffile.imwrite(tmp_path / "u32.tif", rng.integers(0, 2**32, (7, 9), dtype=np.uint32))
    jpg = cv2.imread(str(tmp_path / "rgb8.jpg"), cv2.IMREAD_UNCHANGED)[..., ::-1]
    cases = [
        ("rgb16.png", "auto", rgb16, 65535.0, False),
        ("rgb16.png", "srgb", rgb16, 65535.0, True),
        ("grey8.png", "auto", grey8[..., None], 255.0, False),
        ("rgb8.jpg", "auto", jpg, 255.0, True),
        ("rgb8.jpg", "linear", jpg, 255.0, False),
        ("f32.tif", "auto", f32, 1.0, False),
        ("i16.tif", "auto", tifffile.imread(tmp_path / "i16.tif")[..., None], 32767.0, False),
        ("u32.tif", "auto", tifffile.imread(tmp_path / "u32.tif")[..., None], float(2**32 - 1), False),
    ]
    for name, transfer, data, scale, decode in cases:
        img, info = read_image_file(tmp_path / name, transfer=transfer)
        assert _same(img, _float64_route(data, scale, decode)), (name, transfer)
        img64, _ = read_image_file(tmp_path / name, transfer=transfer, dtype=np.float64)
        np.testing.assert_array_equal(img64, _float64_route(data, scale, decode, np.float64))
        assert info["transfer"] == ("srgb-decoded" if decode else "linear")


def _reference_capture_images(root, names, *, ambient=None, li=None):
    """The image stack of read_capture before issue 20: sequential reads, np.stack, copies."""
    imgs = [read_image_file(root / nm)[0] for nm in names]
    chans = {im.shape[2] for im in imgs}
    imgs = [np.repeat(im, 3, axis=-1) if im.shape[2] == 1 and chans != {1} else im for im in imgs]
    images = np.stack(imgs)
    if images.shape[-1] == 1:
        images = np.repeat(images, 3, axis=-1)
    if ambient is not None:
        a, _ = read_image_file(root / ambient)
        images = np.clip(images - a[None], 0.0, None).astype(np.float32)
    if li is not None:
        images = (images / li[:, None, None, :].astype(np.float32)).astype(np.float32)
    return images


def _mixed_folder(root, n=7):
    """16-bit RGB and 8-bit grey PNGs, an ambient image, light intensities, directions and a mask."""
    rng = np.random.default_rng(1)
    for k in range(n):
        if k % 3 == 1:
            save_png(root / f"img{k + 1}.png", rng.integers(0, 256, (12, 10), dtype=np.uint8))
        else:
            save_png(root / f"img{k + 1}.png", rng.integers(0, 65536, (12, 10, 3), dtype=np.uint16))
    save_png(root / "ambient.png", rng.integers(0, 4000, (12, 10, 3), dtype=np.uint16))
    mask = np.zeros((12, 10), np.uint8)
    mask[2:10, 2:8] = 255
    save_png(root / "mask.png", mask)
    li = rng.uniform(0.5, 2.0, (n, 3))
    save_txt(root / "light_intensities.txt", li)
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 1.0
    save_txt(root / "light_directions.txt", d / np.linalg.norm(d, axis=1, keepdims=True))
    return [f"img{k + 1}.png" for k in range(n)], np.loadtxt(root / "light_intensities.txt")


@pytest.mark.parametrize("threads", [1, 2, 5])
def test_read_capture_threads_equal_the_sequential_read(tmp_path, monkeypatch, threads):
    monkeypatch.setattr(capture, "_read_threads", lambda: threads)
    names, li = _mixed_folder(tmp_path)
    seen = []
    cap = capture.read_capture(tmp_path, progress=lambda k, n, msg: seen.append((k, n, msg)))
    assert seen == [(k + 1, len(names), f"read {nm}") for k, nm in enumerate(names)]
    ds = cap.dataset
    assert ds.images.flags.c_contiguous and ds.normalised and cap.ambient == "ambient.png"
    assert _same(ds.images, _reference_capture_images(tmp_path, names, ambient="ambient.png", li=li))
    assert cap.formats == [{"format": "png", "bits": 16, "transfer": "linear", "images": 5},
                           {"format": "png", "bits": 8, "transfer": "linear", "images": 2}]
    raw = capture.read_capture(tmp_path, ambient=None, normalise=False)
    assert _same(raw.dataset.images, _reference_capture_images(tmp_path, names))
    grey = tmp_path / "grey"
    grey.mkdir()
    for k in range(4):
        save_png(grey / f"g{k}.png", np.full((5, 6), 40 * k + 3, np.uint8))
    assert _same(capture.read_capture(grey, mask="none").dataset.images,
                 _reference_capture_images(grey, [f"g{k}.png" for k in range(4)]))


@pytest.mark.parametrize("threads", [1, 4])
def test_read_capture_errors_in_file_order(tmp_path, monkeypatch, threads):
    """The first bad file in the list is the error, after the progress of the files before it (as sequentially)."""
    monkeypatch.setattr(capture, "_read_threads", lambda: threads)
    for k in range(6):
        save_png(tmp_path / f"{k}.png", np.full((4, 4), 0.5), bits=8)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    (tmp_path / "filenames.txt").write_text("0.png\n1.png\nbad.png\n2.png\nmissing.png\n3.png\n")
    seen = []
    with pytest.raises(ValueError, match=r"bad\.png: not a readable image"):
        capture.read_capture(tmp_path, progress=lambda k, n, msg: seen.append(msg))
    assert seen == ["read 0.png", "read 1.png"]
    (tmp_path / "filenames.txt").write_text("0.png\n1.png\nmissing.png\nbad.png\n")
    with pytest.raises(FileNotFoundError, match=r"image not found: .*missing\.png"):
        capture.read_capture(tmp_path)
    save_png(tmp_path / "4.png", np.zeros((5, 4)), bits=8)
    (tmp_path / "filenames.txt").write_text("0.png\n4.png\n1.png\n")
    with pytest.raises(ValueError, match=r"expected images of one size, got \[\(4, 4\), \(5, 4\)\]"):
        capture.read_capture(tmp_path)
    with pytest.raises(ValueError, match="transfer"):
        capture.read_capture(tmp_path, transfer="gamma")


@pytest.mark.parametrize("name", ["ball", "bear"])
def test_read_capture_diligent_equals_the_sequential_read(data_root, name):
    root = data_root / "diligent" / name
    if not root.is_dir():
        pytest.skip(f"no {root}")
    cap = capture.read_capture(root)
    ds = cap.dataset
    li = np.loadtxt(root / "light_intensities.txt")
    assert _same(ds.images, _reference_capture_images(root, ds.filenames, li=li))


# ------------------------------------------------------------------------------------------- estimate_noise


def _estimate_noise_reference(images, mask, *, max_pixels: int = 1 << 16) -> np.ndarray:
    """estimate_noise before issue 20: the whole frame in float32, the kernel's rows tripled, a plain 3x3 loop."""
    img = np.asarray(images, np.float32)
    m = np.asarray(mask, bool)
    n, h, w = img.shape[:3]
    out = np.zeros(n, np.float32)
    if h < 3 or w < 3:
        return out
    inner = m[1:-1, 1:-1].copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            inner &= m[1 + di : h - 1 + di, 1 + dj : w - 1 + dj]
    rows = np.nonzero(inner.any(axis=1))[0]
    if rows.size == 0:
        return out
    st = max(1, int(np.ceil(inner[rows].sum() / max_pixels)))
    rows = rows[::st]
    sel = inner[rows]
    blk = img[:, np.stack([rows, rows + 1, rows + 2])]
    if blk.ndim == 5:
        blk = (blk[..., 0] + blk[..., 1] + blk[..., 2]) / 3.0
    lap = np.zeros((n, rows.size, w - 2), np.float32)
    pos = np.broadcast_to(sel, lap.shape).copy()
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            sh = blk[:, 1 + di, :, 1 + dj : w - 1 + dj]
            lap += (1 + (di == 0)) * (1 + (dj == 0)) * (-1) ** (di + dj) * sh
            pos &= sh > 0.0
    lap = lap.reshape(n, -1)
    pos = pos.reshape(n, -1)
    for k in range(n):
        if pos[k].sum() >= 64:
            out[k] = float(np.median(np.abs(lap[k, pos[k]]))) / (0.6745 * 6.0)
    return out


def _blob_mask(h, w, rng, holes=True):
    yy, xx = np.mgrid[:h, :w]
    m = (yy - h / 2) ** 2 / (0.4 * h) ** 2 + (xx - w / 2) ** 2 / (0.35 * w) ** 2 < 1.0
    if holes:  # rows without inner pixels and a second component: rows that are no arithmetic progression
        m[h // 2 - 2 : h // 2 + 2] = False
        m[2:5, 1:6] = True
        m &= rng.random((h, w)) > 0.002
    return m


@pytest.mark.parametrize("max_pixels", [1 << 16, 500, 120, 37])
@pytest.mark.parametrize("kind", ["rgb", "grey", "rgb64", "uint16"])
def test_estimate_noise_equals_the_plain_loop(kind, max_pixels):
    from gpps.pipeline.solver import estimate_noise

    rng = np.random.default_rng(3)
    n, h, w = 5, 41, 53
    smooth = np.linspace(0.1, 0.9, w)[None, None, :] * np.linspace(0.5, 1.0, h)[None, :, None]
    img = smooth[..., None] + rng.normal(0, [0.01, 0.02, 0.005, 0.03, 0.0][:n], (h, w, 3, n)).transpose(3, 0, 1, 2)
    img[1, :, : w // 3] = 0.0  # a shadow: the kernel must see positive neighbourhoods only
    img[2, 10:14, 10:20] = -0.01
    if kind == "grey":
        img = img.mean(axis=-1).astype(np.float32)
    elif kind == "rgb":
        img = img.astype(np.float32)
    elif kind == "uint16":
        img = np.clip(img * 60000, 0, 65535).astype(np.uint16)
    for holes in (False, True):
        m = _blob_mask(h, w, rng, holes)
        got = estimate_noise(img, m, max_pixels=max_pixels)
        ref = _estimate_noise_reference(img, m, max_pixels=max_pixels)
        assert got.dtype == np.float32 and _same(got, ref), (got, ref)
    assert np.any(ref > 0) or max_pixels < 64  # (fewer than 64 pixels: unknown, 0)
    assert _same(estimate_noise(img, np.zeros((h, w), bool)), np.zeros(n, np.float32))
    assert _same(estimate_noise(img[:, :2], np.ones((2, w), bool)), np.zeros(n, np.float32))
    one = np.zeros((h, w), bool)
    one[10:13, 20:23] = True  # a single inner pixel: fewer than 64, unknown
    assert _same(estimate_noise(img, one), np.zeros(n, np.float32))


@pytest.mark.parametrize("name", ["ball", "bear"])
def test_estimate_noise_diligent_equals_the_plain_loop(data_root, name):
    from gpps.pipeline.solver import estimate_noise

    root = data_root / "diligent" / name
    if not root.is_dir():
        pytest.skip(f"no {root}")
    ds = capture.read_capture(root).dataset
    for mp in (1 << 16, 5000):
        assert _same(estimate_noise(ds.images, ds.mask, max_pixels=mp),
                     _estimate_noise_reference(ds.images, ds.mask, max_pixels=mp))
    assert np.all(estimate_noise(ds.images, ds.mask) > 0)
