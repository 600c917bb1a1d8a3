"""Image formats in, every output format out and read back; capture folders as users have them; the automatic mask."""


import numpy as np
import pytest

from gpps.io.formats import (linear_to_srgb, read_exr, read_image_file, read_mesh_file, read_tiff, save_exr,
                          save_float_tiff, save_mesh_file, srgb_to_linear)


def _rgb(h=12, w=17, seed=0):
    return np.random.default_rng(seed).random((h, w, 3))


def test_srgb_round_trip():
    x = np.linspace(0, 1, 101)
    assert np.allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=1e-12)
    assert srgb_to_linear(0.5) == pytest.approx(0.21404, abs=1e-5)  # IEC 61966-2-1


@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("channels", [1, 3])
def test_png_and_pgm(tmp_path, bits, channels):
    import cv2

    img = _rgb()[..., :channels]
    dt = np.uint8 if bits == 8 else np.uint16
    q = np.round(img * (2**bits - 1)).astype(dt)
    ext = ".png" if channels == 3 else ".pgm"
    cv2.imwrite(str(tmp_path / f"a{ext}"), q[..., ::-1] if channels == 3 else q[..., 0])
    got, info = read_image_file(tmp_path / f"a{ext}")
    assert info["bits"] == bits and info["transfer"] == "linear" and got.shape == img.shape
    assert np.allclose(got, q / (2**bits - 1), atol=1e-6)  # RGB order, exact scale


def test_jpeg_is_srgb_decoded(tmp_path):
    import cv2

    lin = np.full((16, 16, 3), 0.2)
    lin[..., 1] = 0.05
    enc = np.round(linear_to_srgb(lin) * 255).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "a.jpg"), enc[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 100])
    got, info = read_image_file(tmp_path / "a.jpg")
    assert info["format"] == "jpeg" and info["transfer"] == "srgb-decoded"
    assert np.allclose(got, lin, atol=0.004)
    raw, info2 = read_image_file(tmp_path / "a.jpg", transfer="linear")
    assert info2["transfer"] == "linear" and np.allclose(raw, enc / 255.0, atol=0.01)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.float32])
def test_tiff(tmp_path, dtype):
    import tifffile

    img = _rgb()
    data = img.astype(np.float32) if dtype == np.float32 else np.round(img * np.iinfo(dtype).max).astype(dtype)
    tifffile.imwrite(tmp_path / "a.tif", data, photometric="rgb")
    got, info = read_image_file(tmp_path / "a.tif")
    assert info["format"] == "tiff" and info["bits"] == 8 * np.dtype(dtype).itemsize
    scale = 1.0 if dtype == np.float32 else np.iinfo(dtype).max
    assert np.allclose(got, data / scale, atol=1e-6)


def test_exr_and_float_tiff_round_trip(tmp_path):
    d = np.random.default_rng(1).random((9, 11)).astype(np.float32) * 100
    d[0, 0] = np.nan
    save_exr(tmp_path / "d.exr", d)
    save_float_tiff(tmp_path / "d.tiff", d)
    for got in (read_exr(tmp_path / "d.exr")[..., 0], read_tiff(tmp_path / "d.tiff")[..., 0]):
        assert np.array_equal(np.isnan(got), np.isnan(d)) and np.allclose(got[1:], d[1:], rtol=0, atol=0)
    rgb = _rgb().astype(np.float32) * 4  # HDR values above 1 survive
    save_exr(tmp_path / "c.exr", rgb)
    got, info = read_image_file(tmp_path / "c.exr")
    assert info["format"] == "exr" and np.array_equal(got, rgb)


@pytest.mark.parametrize("ext", [".ply", ".obj"])
def test_mesh_with_vertex_colours(tmp_path, ext):
    rng = np.random.default_rng(2)
    v = rng.random((30, 3))
    f = rng.integers(0, 30, (40, 3))
    c = rng.random((30, 3))
    save_mesh_file(tmp_path / f"m{ext}", v, f, c)
    vv, ff, cc = read_mesh_file(tmp_path / f"m{ext}")
    assert np.allclose(vv, v, atol=1e-6) and np.array_equal(ff, f)
    assert np.array_equal(cc, np.round(c * 255).astype(np.uint8))


def test_unknown_extension(tmp_path):
    (tmp_path / "a.xyz").write_text("x")
    with pytest.raises(ValueError, match="extensions"):
        read_image_file(tmp_path / "a.xyz")
    with pytest.raises(FileNotFoundError):
        read_image_file(tmp_path / "missing.png")
    with pytest.raises(ValueError, match="transfer"):
        read_image_file(tmp_path / "a.xyz", transfer="gamma")


def test_write_outputs_every_format_read_back(tmp_path):
    """Every file of the output set is written and read back to what was given."""
    import cv2

    from gpps.camera import Perspective
    from gpps.io.outputs import OUTPUT_FILES, apply_depth_convention, depth_convention, write_outputs
    from gpps.host.scenes import make_scene

    sc = make_scene("sphere", 32, "perspective")
    m = sc.mask
    alb = np.where(m[..., None], np.random.default_rng(3).random((32, 32, 3)), 0).astype(np.float32)
    conv = depth_convention(sc.camera)
    assert conv["scale"] == "relative" and conv["unit"] == "mean object distance"
    d = apply_depth_convention(sc.depth * 7.0, m, conv)  # any scale: relative depth has mean 1
    assert abs(np.nanmean(d[m]) - 1) < 1e-6 and np.all(np.isnan(d[~m]))
    info = write_outputs(tmp_path, normals=sc.normals, albedo=alb, mask=m, depth=d, camera=sc.camera, depth_info=conv)
    assert set(OUTPUT_FILES) <= set(info["files"])
    n = np.load(tmp_path / "normals.npy")
    assert n.dtype == np.float32 and np.allclose(n[m], sc.normals[m], atol=1e-6)
    png = cv2.imread(str(tmp_path / "normals.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    assert np.allclose(png[..., ::-1][m] / 65535.0 * 2 - 1, sc.normals[m], atol=2e-5)
    a = np.load(tmp_path / "albedo.npy")
    assert a.dtype == np.float32 and np.array_equal(a, alb)
    assert cv2.imread(str(tmp_path / "albedo.png")).dtype == np.uint8
    for got in (np.load(tmp_path / "depth.npy"), read_tiff(tmp_path / "depth.tiff")[..., 0], read_exr(tmp_path / "depth.exr")[..., 0]):
        assert np.array_equal(np.isnan(got), ~m) and np.array_equal(got[m], d[m])
    assert np.array_equal(cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_UNCHANGED) > 0, m)
    pts = Perspective(sc.camera.K).backproject(np.where(m, d, 0.0))[m]
    from gpps.io.outputs import _albedo_colors

    cols = np.round(_albedo_colors(alb, m)[m] * 255).astype(np.uint8)
    for name in ("mesh.ply", "mesh.obj"):
        v, f, c = read_mesh_file(tmp_path / name)
        assert np.allclose(v, pts, atol=1e-5) and len(f) > 0 and np.array_equal(c, cols)
        assert f.max() < len(v)
    assert (tmp_path / "view.png").is_file()


def test_depth_convention_orthographic_and_metric():
    from gpps.camera import Orthographic
    from gpps.io.outputs import apply_depth_convention, depth_convention

    m = np.ones((4, 4), bool)
    d = np.arange(16.0).reshape(4, 4) + 100
    c = depth_convention(Orthographic())
    assert c["scale"] == "relative" and c["unit"] == "pixel"
    assert abs(apply_depth_convention(d, m, c).mean()) < 1e-5
    c = depth_convention(Orthographic(), known_scale="light_positions.txt")
    assert c["scale"] == "metric" and c["source"] == "light_positions.txt"
    assert np.array_equal(apply_depth_convention(d, m, c), d.astype(np.float32))


# --------------------------------------------------------------------------- capture folders


def _scene_images(n=8, size=48, camera="orthographic"):
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene("sphere", size, camera)
    lights = default_lights("directional", n)
    imgs = render(sc, Material("lambertian"), lights, device="cpu")
    return sc, lights, np.clip(imgs, 0, 1)


def test_read_capture_sorted_names_ambient_automask_max_size(tmp_path):
    from gpps.io.capture import list_images, read_capture
    from gpps.io import save_png, save_txt

    sc, lights, imgs = _scene_images(n=10)
    amb = np.full(imgs.shape[1:], 0.02)
    for k, im in enumerate(imgs):  # img1 .. img10: natural order, not 1, 10, 2
        save_png(tmp_path / f"img{k + 1}.png", np.clip(im + amb, 0, 1), bits=16)
    save_png(tmp_path / "scene_ambient.png", amb, bits=16)
    save_txt(tmp_path / "light_directions.txt", lights.directions)
    K = np.array([[100.0, 0, 23.5], [0, 100.0, 23.5], [0, 0, 1]])
    save_txt(tmp_path / "K.txt", K)
    assert list_images(tmp_path) == [f"img{k}.png" for k in range(1, 11)]
    cap = read_capture(tmp_path)
    assert cap.ambient == "scene_ambient.png" and cap.mask_source == "automatic" and cap.calibrated
    assert np.allclose(cap.dataset.images, imgs, atol=2e-4)
    inter = (cap.dataset.mask & sc.mask).sum()
    assert inter / (cap.dataset.mask | sc.mask).sum() > 0.95
    small = read_capture(tmp_path, max_size=24)
    assert small.dataset.images.shape[1:3] == (24, 24) and small.scale == 0.5
    assert np.allclose(small.dataset.K[0], [50, 0, 11.5]) and np.allclose(small.dataset.K[1], [0, 50, 11.5])
    with pytest.raises(ValueError, match="max_size"):
        read_capture(tmp_path, max_size=3)


def test_read_capture_errors(tmp_path):
    from gpps.io.capture import read_capture
    from gpps.io import save_png

    with pytest.raises(FileNotFoundError):
        read_capture(tmp_path / "missing")
    with pytest.raises(ValueError, match="expected images"):
        read_capture(tmp_path)
    save_png(tmp_path / "a.png", np.zeros((4, 4)), bits=8)
    save_png(tmp_path / "b.png", np.zeros((5, 4)), bits=8)
    with pytest.raises(ValueError, match="one size"):
        read_capture(tmp_path)


def test_read_capture_side_files(tmp_path):
    """material.json that is not a JSON object is a ValueError naming it (before any image is decoded); a
    ground-truth file of another size than the images is a GppsWarning naming it, and is left out."""
    from gpps import GppsWarning
    from gpps.io import save_png, save_txt
    from gpps.io.capture import read_capture

    sc, lights, imgs = _scene_images(n=4, size=16)
    for k, im in enumerate(imgs):
        save_png(tmp_path / f"{k:02d}.png", im, bits=16)
    save_txt(tmp_path / "light_directions.txt", lights.directions)
    np.save(tmp_path / "normal_gt.npy", sc.normals.astype(np.float32))
    np.save(tmp_path / "depth_gt.npy", np.ones((10, 16)))
    with pytest.warns(GppsWarning, match=r"depth_gt.npy: expected shape \(16, 16\).*got \(10, 16\)"):
        cap = read_capture(tmp_path)
    assert cap.dataset.depth_gt is None and cap.dataset.normal_gt.shape == (16, 16, 3)
    (tmp_path / "depth_gt.npy").unlink()
    for text, match in (("{brdf: phong", "could not parse"), ("[1, 2]", "got a list"),
                        (b"\xff\xfe\x00", "could not parse")):
        if isinstance(text, bytes):
            (tmp_path / "material.json").write_bytes(text)
        else:
            (tmp_path / "material.json").write_text(text)
        with pytest.raises(ValueError, match=f"material.json: expected a JSON object.*{match}"):
            read_capture(tmp_path)
    (tmp_path / "material.json").write_text('{"brdf": "blinn-phong", "shininess": 40}')
    assert read_capture(tmp_path).dataset.material == {"brdf": "blinn-phong", "shininess": 40}



def test_read_npy_names_the_argument(tmp_path):
    """A .npy that is text, pickled objects or not numeric: a ValueError naming the argument (no unpickling)."""
    from gpps.cli import main
    from gpps.io import read_npy

    good = np.arange(6, dtype=np.float32).reshape(2, 3)
    np.save(tmp_path / "good.npy", good)
    np.testing.assert_array_equal(read_npy(tmp_path / "good.npy"), good)
    (tmp_path / "text.npy").write_text("hello")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(tmp_path / "str.npy", np.array(["a", "b"]))
    np.savez(tmp_path / "arch.npz", a=good)
    (tmp_path / "arch.npz").rename(tmp_path / "arch.npy")
    for f in ("text.npy", "obj.npy", "str.npy", "arch.npy"):
        with pytest.raises(ValueError, match="normals: expected a numeric .npy array"):
            read_npy(tmp_path / f, name="normals")
    with pytest.raises(FileNotFoundError, match="normals: file not found"):
        read_npy(tmp_path / "missing.npy", name="normals")
    import cv2

    cv2.imwrite(str(tmp_path / "mask.png"), np.full((4, 4), 255, np.uint8))
    assert main(["--device", "cpu", "integrate", str(tmp_path / "text.npy"), "--mask", str(tmp_path / "mask.png"),
                 "--out", str(tmp_path / "out")]) == 2
    assert not (tmp_path / "out").exists()

def test_automatic_mask_fills_holes_and_drops_speckle():
    from gpps.host.automask import AutoMaskConfig, automatic_mask

    h = w = 40
    yy, xx = np.mgrid[:h, :w]
    obj = (yy - 20) ** 2 + (xx - 20) ** 2 < 12**2
    imgs = np.zeros((6, h, w))
    rng = np.random.default_rng(0)
    for k in range(6):
        imgs[k][obj] = 0.3 + 0.5 * rng.random(obj.sum())
    imgs[:, 20, 20] = 0.0  # a dark pupil: a hole
    imgs[:, 2, 2] = 1.0  # a hot pixel: speckle
    m, info = automatic_mask(imgs)
    assert np.array_equal(m, obj) and info["components"] == 1
    with pytest.raises(ValueError, match="level"):
        AutoMaskConfig(level=0)
    with pytest.raises(ValueError, match="lit in enough"):
        automatic_mask(np.zeros((3, 8, 8)))


def test_raw_goes_through_rawpy_linear(tmp_path, monkeypatch):
    """Camera RAW: rawpy's demosaic with gamma 1, no auto-brightening, 16 bits (a stand-in for rawpy.imread:
    no RAW file can be written here)."""
    rawpy = pytest.importorskip("rawpy")
    seen = {}
    data = np.random.default_rng(0).integers(0, 65535, (6, 7, 3)).astype(np.uint16)

    class Fake:
        def __enter__(self):
            return self

        def __exit__(self, *a):
            return False

        def postprocess(self, **kw):
            seen.update(kw)
            return data

    monkeypatch.setattr(rawpy, "imread", lambda path: Fake())
    (tmp_path / "a.dng").write_bytes(b"x")
    got, info = read_image_file(tmp_path / "a.dng")
    assert info == {"format": "raw", "bits": 16, "transfer": "linear"}
    assert seen["gamma"] == (1, 1) and seen["no_auto_bright"] and seen["output_bps"] == 16
    assert np.allclose(got, data / 65535.0, atol=1e-7)
