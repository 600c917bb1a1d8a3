"""The cheaper host-side paths of issue 20 against straightforward references: the same values, bit for bit,
the same errors and warnings.

* reading: the threaded :func:`gpps.io.capture.read_capture` and the float32 scaling of 8/16-bit images
  against the sequential float64 route it replaced;
* :func:`gpps.pipeline.solver.estimate_noise` against its plain 3x3 loop;
* :func:`gpps.flows.photometric.check_observations`, :func:`gpps.flows.folder._saturation` and
  :func:`gpps._check.as_images` against their whole-stack numpy formulas.
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
    # the automatic mask and the downscaling read the undivided images: divided after them, as before
    from gpps.host.automask import automatic_mask

    undivided = _reference_capture_images(tmp_path, names, ambient="ambient.png")
    auto = capture.read_capture(tmp_path, mask="auto")
    assert auto.mask_source == "automatic"
    np.testing.assert_array_equal(auto.dataset.mask, automatic_mask(undivided, None)[0])
    assert _same(auto.dataset.images, _reference_capture_images(tmp_path, names, ambient="ambient.png", li=li))
    small = capture.read_capture(tmp_path, max_size=8)
    ref = np.stack([capture._resize(im, (7, 8)) for im in undivided]).astype(np.float32)
    assert small.scale < 1 and _same(small.dataset.images, (ref / li[:, None, None, :].astype(np.float32)).astype(np.float32))
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
    (tmp_path / "filenames.txt").write_text("0.png\n1.png\n2.png\n")
    with pytest.raises(FileNotFoundError, match=r"ambient: file not found: .*none\.png"):
        capture.read_capture(tmp_path, ambient="none.png", mask="bad mask path")  # the ambient first, as before
    with pytest.raises(ValueError, match=r"ambient: expected shape \(4, 4\), got \(5, 4\)"):
        capture.read_capture(tmp_path, ambient="4.png")
    with pytest.raises(ValueError, match=r"mask: expected shape \(4, 4\), got \(5, 4\)"):
        capture.read_capture(tmp_path, mask=np.ones((5, 4), bool))


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


# ------------------------------------------------------------------- check_observations, _saturation, as_images


def _check_observations_reference(images, mask, lights, *, valid=None, saturation=None, reference_depth=None,
                                  sink=None):
    """check_observations before issue 20 (whole-stack means, maxima and gathers)."""
    from gpps._check import warn
    from gpps.flows.photometric import MIN_DETERMINED, UNLIT_FRACTION, WARN_DETERMINED
    from gpps.lights import DirectionalLights

    img = images if images.ndim == 4 else images[..., None]
    grey = img.mean(axis=-1)[:, mask]
    scale = float(np.percentile(grey, 99.9)) if grey.size else 0.0
    if not scale > 0.0:
        outside = img.mean(axis=-1)[:, ~mask]
        where = (" while pixels outside it are lit: the mask lies outside the lit area"
                 if outside.size and float(outside.max()) > 0 else "")
        raise ValueError(f"images: every observation inside the mask is black (0){where}; nothing is lit")
    lit = grey > UNLIT_FRACTION * scale
    sat = np.zeros_like(lit)
    if saturation is not None:
        sat |= img.max(axis=-1)[:, mask] >= saturation
    if valid is not None:
        sat |= ~np.asarray(valid, bool)[:, mask]
    determined = np.zeros(mask.shape, bool)
    determined[mask] = np.count_nonzero(lit & ~sat, axis=0) >= 3
    frac = float(determined[mask].mean())
    if frac < MIN_DETERMINED:
        if sat.mean() > 0.5:
            cause = f"{100 * sat.mean():.0f}% of the observations are saturated (over-exposed)"
        elif lit.mean() < 0.5:
            cause = (f"{100 * (1 - lit.mean()):.0f}% of the observations are dark: under-exposed images, lights "
                     "that missed the object, or a mask outside the lit area")
        else:
            cause = "too few lights reach each pixel"
        raise ValueError(f"images: only {100 * frac:.1f}% of the mask pixels have 3 or more usable (lit, "
                         f"unsaturated) observations; {cause}")
    if frac < WARN_DETERMINED:
        warn(f"images: {100 * (1 - frac):.0f}% of the mask pixels have fewer than 3 usable (lit, unsaturated) "
             "observations; their normals rest on neighbours and priors", sink)
    if isinstance(lights, DirectionalLights):
        behind = np.nonzero(np.asarray(lights.directions)[:, 2] <= 0.0)[0]
        if behind.size:
            warn(f"lights: {behind.size} of {len(lights)} directional lights point away from the camera side "
                 f"(z <= 0; lights {(behind + 1).tolist()[:8]}): they light only surfaces facing away from the camera",
                 sink)
    elif reference_depth is not None:
        behind = np.nonzero(np.asarray(lights.positions)[:, 2] <= -float(reference_depth))[0]
        if behind.size:
            warn(f"lights: {behind.size} of {len(lights)} point lights are at or beyond the object's mean depth "
                 f"{float(reference_depth):g} (lights {(behind + 1).tolist()[:8]}): they light it from behind", sink)
    return determined


def _outcome(fn, *args, **kwargs):
    """(determined, warnings' messages, error) of one call."""
    import warnings

    sink = []
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        try:
            det = fn(*args, sink=sink, **kwargs)
        except ValueError as e:
            return None, sink, [str(w.message) for w in rec], str(e)
    return det, sink, [str(w.message) for w in rec], None


def test_masked_grey_is_numpys_channel_mean():
    """The per-image (a0 + a1) + a2, / 3 of check_observations is numpy's mean over the channel axis."""
    from gpps.flows.photometric import _masked_statistics

    a = np.array([[1, 4e-8, 4e-8], [4e-8, 4e-8, 1], [3e-8, 1, 3e-8]], np.float32)  # the order shows
    img = np.broadcast_to(a[None, None], (2, 3, 3, 3)).copy()
    mask = np.ones((3, 3), bool)
    grey, bad, peak = _masked_statistics(img, mask, None, None)
    assert bad is None and _same(grey, img.mean(axis=-1)[:, mask])
    np.testing.assert_array_equal(peak, img.max(axis=-1)[:, mask])
    from gpps.host.observations import masked_grey  # (PixelSolver.upload's and this function's)

    assert _same(masked_grey(img, mask), img.mean(axis=-1)[:, mask])
    rng = np.random.default_rng(6)
    frame = rng.random((3, 17, 13, 3)).astype(np.float32) ** 3
    m = rng.random((17, 13)) > 0.5
    np.testing.assert_array_equal(masked_grey(frame, m), frame[:, m].mean(-1))
    g, p = masked_grey(frame, m, peak=True)
    np.testing.assert_array_equal(g, frame[:, m].mean(-1))
    np.testing.assert_array_equal(p, frame[:, m].max(-1))
    from gpps.host.observations import gather_masked, grey_peak  # (the flows' checks: the gather shared)

    idx = np.flatnonzero(m)
    x = gather_masked(frame, idx)
    np.testing.assert_array_equal(x, frame[:, m].transpose(0, 2, 1))
    g2, p2 = grey_peak(x)
    assert _same(g2, g) and _same(p2, p)
    assert _same(grey_peak(gather_masked(img, np.flatnonzero(mask)))[0], img.mean(axis=-1)[:, mask])
    for valid, sat in ((None, None), (rng.random((3, 17, 13)) > 0.2, 0.5)):
        a = _masked_statistics(frame, m, valid, sat)
        b = _masked_statistics(frame, m, valid, sat, (idx, x))
        for u, v in zip(a, b):
            assert (u is None and v is None) or (np.array_equal(u, v) if u.dtype == bool else _same(u, v))
    rng = np.random.default_rng(5)
    for dtype in (np.float32, np.float64):
        img = rng.random((4, 9, 11, 3)).astype(dtype) ** 3
        mask = rng.random((9, 11)) > 0.4
        grey, bad, peak = _masked_statistics(img, mask, None, 0.5)
        np.testing.assert_array_equal(grey, img.mean(axis=-1)[:, mask])
        np.testing.assert_array_equal(peak, img.max(axis=-1)[:, mask])
        np.testing.assert_array_equal(bad, img.max(axis=-1)[:, mask] >= 0.5)
        assert grey.dtype == dtype
        view = np.moveaxis(np.ascontiguousarray(np.moveaxis(img, -1, 1)), 1, -1)  # channels the slowest axis
        np.testing.assert_array_equal(_masked_statistics(view, mask, None, None)[0], img.mean(axis=-1)[:, mask])


def _observation_cases():
    from gpps.lights import DirectionalLights, PointLights

    rng = np.random.default_rng(7)
    n, h, w = 9, 13, 17
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.5
    d[2, 2] = -0.3  # one light behind: a warning
    dl = DirectionalLights(d / np.linalg.norm(d, axis=1, keepdims=True))
    pl = PointLights(np.c_[rng.normal(size=(n, 2)), rng.uniform(-3.0, 2.0, n)])
    mask = np.zeros((h, w), bool)
    mask[2:11, 3:15] = True
    base = (rng.random((n, h, w, 3)) * 0.9).astype(np.float32)
    cases = []
    for name, img in [("rgb", base), ("grey", base.mean(axis=-1)), ("rgb64", base.astype(np.float64)),
                      ("one channel", base[..., :1])]:
        cases.append((name, img, mask, dl, {}))
        cases.append((name + " saturation", img, mask, dl, {"saturation": 0.6}))
        cases.append((name + " valid", img, mask, pl, {"valid": rng.random((n, h, w)) > 0.3, "reference_depth": 1.0}))
        cases.append((name + " both", img, mask, dl, {"valid": rng.random((n, h, w)) > 0.2, "saturation": 0.8}))
    dark = base.copy()
    dark[:, ~mask] = 0.0
    dark[:7] = 0.0
    cases.append(("dark: error", dark, mask, dl, {}))
    half = base.copy()
    half[:7, 2:8] *= 1e-5  # 2 lit images on two thirds of the mask: a third determined
    cases.append(("half dark: warning", half, mask, dl, {}))
    cases.append(("saturated: error", base, mask, dl, {"saturation": 0.05}))
    few = base.copy()
    few[6:] *= 1e-5
    inval = np.ones((n, h, w), bool)
    inval[:4] = False
    cases.append(("few lights: error", few, mask, dl, {"valid": inval}))  # 6 lit, 4 of them invalid: 2 usable
    cases.append(("invalid: error", base, mask, dl, {"valid": np.zeros((n, h, w), np.uint8)}))
    black = base.copy()
    black[:, mask] = 0.0
    cases.append(("black inside: error", black, mask, dl, {}))
    cases.append(("black everywhere: error", np.zeros_like(base), mask, dl, {}))
    cases.append(("empty mask: error", base, np.zeros((h, w), bool), dl, {}))
    return cases


@pytest.mark.parametrize("case", _observation_cases(), ids=lambda c: c[0])
def test_check_observations_equals_the_whole_stack_formula(case):
    from gpps.flows.photometric import check_observations

    _, img, mask, lights, kw = case
    got = _outcome(check_observations, img, mask, lights, **kw)
    ref = _outcome(_check_observations_reference, img, mask, lights, **kw)
    assert got[1:] == ref[1:]
    assert (got[0] is None) == (ref[0] is None)
    if ref[0] is not None:
        np.testing.assert_array_equal(got[0], ref[0])
    if case[0].endswith("error"):
        assert ref[3] is not None
    if case[0].endswith("warning"):
        assert any("fewer than 3 usable" in m for m in ref[1])


def test_check_observations_diligent_equals_the_whole_stack_formula(data_root):
    from gpps.flows.folder import _saturation
    from gpps.flows.photometric import check_observations
    from gpps.lights import DirectionalLights

    root = data_root / "diligent" / "bear"
    if not root.is_dir():
        pytest.skip(f"no {root}")
    cap = capture.read_capture(root)
    ds = cap.dataset
    lights = DirectionalLights(ds.light_directions)
    valid = _saturation(cap)
    for kw in ({"valid": valid}, {}, {"saturation": 0.5}):
        got = _outcome(check_observations, ds.images, ds.mask, lights, **kw)
        ref = _outcome(_check_observations_reference, ds.images, ds.mask, lights, **kw)
        assert got[1:] == ref[1:] and ref[3] is None
        np.testing.assert_array_equal(got[0], ref[0])


def _saturation_reference(cap):
    """folder._saturation before issue 20: the whole stack times the intensities, any over the channels."""
    ds = cap.dataset
    integer_input = all(f["format"] not in ("exr",) and not (f["format"] == "tiff" and f["bits"] == 32) for f in cap.formats)
    if not integer_input:
        return None
    raw = ds.images
    if ds.light_intensities is not None and ds.normalised:
        raw = ds.images * np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
    return ~np.any(raw >= 0.995, axis=-1)


def test_saturation_equals_the_whole_stack_formula(tmp_path):
    from gpps.flows.folder import _saturation
    from gpps.io import Dataset

    rng = np.random.default_rng(11)
    n, h, w = 6, 8, 9
    li = rng.uniform(0.5, 2.0, (n, 3))
    raw = rng.integers(60000, 65536, (n, h, w, 3)).astype(np.float32) / np.float32(65535)
    raw[0, 0, 0] = (np.float32(0.995), 0.0, 0.0)  # exactly at the level, in one channel
    raw[1, 0, 0] = (0.0, 0.0, np.nextafter(np.float32(0.995), np.float32(0)))  # just below
    images = (raw / li[:, None, None, :].astype(np.float32)).astype(np.float32)
    images[2, 1, 1] = (np.nan, 1.0, 0.0)  # NaN in one channel: any() and fmax() agree
    images[2, 1, 2] = (np.nan, np.nan, np.nan)
    png = [{"format": "png", "bits": 16, "transfer": "linear", "images": n}]
    for normalised, intens in ((True, li), (False, li), (True, None)):
        ds = Dataset(images=images, mask=np.ones((h, w), bool), light_intensities=intens, normalised=normalised)
        cap = capture.Capture(dataset=ds, mask_source="given", formats=png)
        got, ref = _saturation(cap), _saturation_reference(cap)
        assert got.dtype == bool and got.shape == (n, h, w)
        np.testing.assert_array_equal(got, ref)
        assert 0 < np.count_nonzero(~got) < got.size
    exr = capture.Capture(dataset=ds, mask_source="given", formats=[{"format": "exr", "bits": 32, "transfer": "linear", "images": n}])
    assert _saturation(exr) is None


def test_saturation_diligent_equals_the_whole_stack_formula(data_root):
    from gpps.flows.folder import _saturation

    for name in ("ball", "bear"):
        root = data_root / "diligent" / name
        if not root.is_dir():
            pytest.skip(f"no {root}")
        cap = capture.read_capture(root)
        np.testing.assert_array_equal(_saturation(cap), _saturation_reference(cap))


def test_as_images_errors_and_no_copy():
    from gpps._check import as_array, as_images

    a = np.random.default_rng(2).random((3, 4, 5, 3)).astype(np.float32)
    assert as_images("images", a) is a  # the right dtype: no copy
    assert as_array("depth", a[0, ..., 0]).base is a
    for bad, msg in [(np.nan, "finite"), (np.inf, "finite"), (-np.inf, "finite"), (-0.25, "minimum of -0.25")]:
        b = a.copy()
        b[1, 2, 3, 1] = bad
        with pytest.raises(ValueError, match=msg):
            as_images("images", b)
        if msg == "finite":
            with pytest.raises(ValueError, match="depth: expected finite"):
                as_array("depth", b)
    b = a.copy()
    b[0, 0, 0] = (-0.0, np.nan, -1.0)  # NaN before negatives, as before
    with pytest.raises(ValueError, match="finite"):
        as_images("images", b)
    b[0, 0, 0, 1] = 0.0
    b[0, 0, 0, 2] = -0.0  # -0 is >= 0
    assert as_images("images", b) is b
    assert as_images("images", np.zeros((0, 4, 3))).shape == (0, 4, 3)
    for dtype in (np.uint8, np.uint16):
        info = np.iinfo(dtype)
        x = np.arange(info.max + 1, dtype=dtype).reshape(-1, 256)
        got = as_images("images", x)
        assert got.dtype == np.float32 and _same(got, x.astype(np.float32) / np.float32(info.max))
        np.testing.assert_array_equal(as_images("images", x, dtype=np.float64), x.astype(np.float64) / info.max)
    with pytest.raises(TypeError, match="int32"):
        as_images("images", np.zeros(3, np.int32))


@pytest.mark.parametrize("channels", [3, 1, None])
def test_working_scale_equals_the_strided_mean_formula(channels):
    """working_scale gathers its strided grid by flat index and sums the channels in float64 left to right: the
    scales equal those of ``img[:, ::step, ::step][:, sub].mean(axis=-1, dtype=np.float64)`` exactly."""
    from gpps.flows.photometric import SCALE_SAMPLE, working_scale
    from gpps.lights import DirectionalLights, ring_directions

    rng = np.random.default_rng(11)
    for n, h, w in ((3, 97, 131), (5, 256, 200), (4, 40, 33)):
        shape = (n, h, w) + (() if channels is None else (channels,))
        img = (rng.random(shape) ** 3 * 7.0).astype(np.float32)
        mask = rng.random((h, w)) > 0.3
        lights = DirectionalLights(ring_directions(n), intensities=rng.uniform(0.5, 2.0, (n, 3)))
        got = working_scale(img, mask, lights)
        x = img if img.ndim == 4 else img[..., None]
        step = max(1, int(np.sqrt(np.count_nonzero(mask) / max(SCALE_SAMPLE // n, 1024))))
        grey = x[:, ::step, ::step][:, mask[::step, ::step]].mean(axis=-1, dtype=np.float64)
        per = 1.0 / np.asarray(lights.intensities, np.float64).mean(axis=1)
        assert got["image_scale"] == float(np.percentile(grey, 99.9))
        assert got["albedo_scale"] == float(np.percentile(grey * per[:, None], 99.9))
