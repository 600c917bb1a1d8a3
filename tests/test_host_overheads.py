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
