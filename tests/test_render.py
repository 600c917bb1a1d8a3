"""Renderer, synthetic scenes, DiLiGenT-style folders, CLI render, bad input."""

import json

import numpy as np
import pytest

from gpps.camera import Orthographic, Perspective
from gpps.io import read_dataset, write_dataset
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.render import Renderer, quantise
from gpps.host.scenes import make_scene
from gpps.flows.synthetic import default_lights, render, render_dataset


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
@pytest.mark.parametrize("kind", ["directional", "point"])
def test_render_roundtrip_16bit(tmp_path, device, camera, kind):
    scene = make_scene("bumps", 64, camera, albedo="texture")
    mat = Material.default_for("cook-torrance")
    lights = default_lights(kind, 4)
    ds = render_dataset(scene, mat, lights, bits=None, device=device)
    write_dataset(tmp_path / "cap", ds, bits=16)
    back = read_dataset(tmp_path / "cap", normalise=False)
    want = quantise(ds.images, 16)
    assert np.max(np.abs(back.images - want)) <= 0.5 / 65535
    assert np.array_equal(back.mask, scene.mask)
    np.testing.assert_array_equal(back.normal_gt, scene.normals)
    np.testing.assert_allclose(back.depth_gt, scene.depth)
    assert (back.K is not None) == (camera == "perspective")
    assert (back.light_positions is not None) == (kind == "point")
    assert Material.from_dict(back.material) == mat
    # normalised read divides by the intensities
    normed = read_dataset(tmp_path / "cap")
    np.testing.assert_allclose(normed.images, back.images / lights.intensities[:, None, None, :].astype(np.float32), rtol=1e-6)
    # the images carry signal where the object is and none outside
    assert back.images[:, scene.mask].mean() > 0.05
    assert np.all(back.images[:, ~scene.mask] == 0)


def test_point_light_inverse_square(device):
    """A fronto-parallel Lambertian plane under one point light above a pixel: I = kd I0 cos / r^2."""
    h = w = 33
    cam = Perspective(np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]))
    depth = np.full((h, w), 10.0, np.float32)
    mask = np.ones((h, w), bool)
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1
    mat = Material("lambertian", ks=0)
    pts = cam.backproject(depth)
    vals = []
    for zl in (0.0, -4.0, -7.0):
        lights = PointLights([[0.0, 0.0, zl]], [[100.0, 100.0, 100.0]])
        img = Renderer((h, w), cam, lights, mat, device=device).run(depth, mask, 0.5, normals=normals)[0, ..., 0]
        d = np.array([0.0, 0.0, zl]) - pts
        r = np.linalg.norm(d, axis=-1)
        want = 0.5 * 100.0 * (d[..., 2] / r) / r**2
        np.testing.assert_allclose(img, want, rtol=2e-6)
        vals.append(img[16, 16])
    r = np.array([10.0, 6.0, 3.0])
    np.testing.assert_allclose(np.array(vals) / vals[0], (r[0] / r) ** 2, rtol=1e-6)


def test_led_anisotropy(device):
    """An LED with mu = 2 aimed along -z dims off-axis pixels by cos(angle)^2."""
    cam = Orthographic(pixel_size=0.5)
    depth = np.full((21, 21), 5.0, np.float32)
    mask = np.ones((21, 21), bool)
    nrm = np.zeros((21, 21, 3), np.float32)
    nrm[..., 2] = 1
    mat = Material("lambertian", ks=0)
    iso = Renderer((21, 21), cam, PointLights([[0, 0, 0]]), mat, device=device).run(depth, mask, 1.0, nrm)[0, ..., 0]
    led = Renderer((21, 21), cam, PointLights([[0, 0, 0]], axes=[[0, 0, -1]], mu=[2.0]), mat, device=device).run(depth, mask, 1.0, nrm)[0, ..., 0]
    p = cam.backproject(depth)
    cosang = 5.0 / np.linalg.norm(p, axis=-1)
    np.testing.assert_allclose(led, iso * cosang**2, rtol=1e-5)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_normals_from_depth_match_exact(device, camera):
    scene = make_scene("sphere", 128, camera)
    r = Renderer(scene.shape, scene.camera, default_lights("directional", 3), Material(), device=device)
    n = r.normals_from_depth(scene.depth, scene.mask)
    inner = scene.mask.copy()
    for ax in (0, 1):
        for s in (1, -1):
            inner &= np.roll(scene.mask, s, ax)
    inner &= scene.normals[..., 2] > 0.5  # away from the silhouette, where differences are poor
    ang = np.degrees(np.arccos(np.clip(np.sum(n * scene.normals, -1), -1, 1)))[inner]
    assert np.median(ang) < 0.05 and ang.max() < 0.5


@pytest.mark.parametrize("name", ["sphere", "bumps", "microprint"])
@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_scene_ground_truth_is_consistent(name, camera):
    """Exact normals agree with the normals implied by the exact surface points."""
    scene = make_scene(name, 96, camera)
    assert scene.mask.mean() > 0.3
    n = scene.normals[scene.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-6)
    assert np.all(n[:, 2] > 0)
    # tangent vectors from neighbouring points are orthogonal to the normals
    P = scene.points
    m = scene.mask[:, :-1] & scene.mask[:, 1:]
    du = (P[:, 1:] - P[:, :-1])[m]
    navg = (scene.normals[:, 1:] + scene.normals[:, :-1])[m]
    navg /= np.linalg.norm(navg, axis=-1, keepdims=True)
    cosang = np.abs(np.sum(du * navg, -1)) / np.linalg.norm(du, axis=-1)
    assert np.median(cosang) < 2e-3
    if camera == "perspective":  # the points project back onto their pixels
        uv = scene.camera.project(P[scene.mask])
        ii, jj = np.nonzero(scene.mask)
        np.testing.assert_allclose(uv, np.stack([jj, ii], -1), atol=1e-6)


def test_microprint_has_relief():
    s = make_scene("microprint", 128, "orthographic")
    tilt = np.degrees(np.arccos(s.normals[s.mask][:, 2]))
    assert 0.05 < (tilt > 5).mean() < 0.6  # text strokes tilt the normals; the background is flat
    assert tilt.max() < 60


def test_noise_and_quantisation(device):
    scene = make_scene("sphere", 48, "orthographic")
    lights = default_lights("directional", 3)
    clean = render(scene, Material(), lights, device=device)
    noisy = render(scene, Material(), lights, noise=0.01, seed=3, device=device)
    d = (noisy - clean)[:, scene.mask]
    assert abs(d.std() - 0.01) < 0.001 and abs(d.mean()) < 0.001
    q8 = render(scene, Material(), lights, bits=8, device=device)
    assert np.allclose(q8 * 255, np.round(q8 * 255), atol=1e-4) and q8.max() <= 1.0
    again = render(scene, Material(), lights, noise=0.01, seed=3, device=device)
    np.testing.assert_array_equal(again, noisy)


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_value_errors(device):
    cam = Perspective(np.array([[100.0, 0, 8], [0, 100.0, 8], [0, 0, 1]]))
    lights = default_lights("directional", 3)
    r = Renderer((16, 16), cam, lights, Material(), device=device)
    depth = np.full((16, 16), 10.0)
    mask = np.ones((16, 16), bool)
    nrm = np.zeros((16, 16, 3))
    nrm[..., 2] = 1
    with pytest.raises(ValueError, match="depth: expected shape"):
        r.run(depth[:8], mask, 0.5, nrm)
    bad = depth.copy()
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="depth: expected finite"):
        r.run(bad, mask, 0.5, nrm)
    with pytest.raises(ValueError, match="depth: expected values > 0"):
        r.run(-depth, mask, 0.5, nrm)
    with pytest.raises(ValueError, match="mask: expected at least one pixel"):
        r.run(depth, np.zeros((16, 16), bool), 0.5, nrm)
    with pytest.raises(ValueError, match="normals: expected unit"):
        r.run(depth, mask, 0.5, nrm * 2)
    with pytest.raises(ValueError, match="normals: expected shape"):
        r.run(depth, mask, 0.5, nrm[..., :2])
    with pytest.raises(ValueError, match="albedo"):
        r.run(depth, mask, np.ones((3, 3)), nrm)
    with pytest.raises(ValueError, match="albedo: expected values >= 0"):
        r.run(depth, mask, -1.0, nrm)


def test_bad_configuration_raises():
    with pytest.raises(ValueError, match="directions: expected unit vectors, got a zero"):
        DirectionalLights([[0, 0, 0], [0, 0, 1], [0, 1, 0]])
    with pytest.raises(ValueError, match="directions: expected unit vectors, got norm"):
        DirectionalLights([[0, 0, 2.0]])
    with pytest.raises(ValueError, match="directions: expected shape"):
        DirectionalLights(np.ones((3, 2)))
    with pytest.raises(ValueError, match="directions: expected finite"):
        DirectionalLights([[np.nan, 0, 1]])
    with pytest.raises(ValueError, match="intensities"):
        DirectionalLights([[0, 0, 1.0]], [[-1, 1, 1]])
    with pytest.raises(ValueError, match="positions: expected shape"):
        PointLights(np.ones((2, 4)))
    with pytest.raises(ValueError, match="mu"):
        PointLights(np.ones((2, 3)), mu=[-1, 0])
    with pytest.raises(ValueError, match="K: expected focal lengths"):
        Perspective(np.array([[0.0, 0, 1], [0, 1.0, 1], [0, 0, 1]]))
    with pytest.raises(ValueError, match="K: expected focal lengths"):
        Perspective(np.array([[10.0, 0, 1], [0, -1.0, 1], [0, 0, 1]]))
    with pytest.raises(ValueError, match="K: expected shape"):
        Perspective(np.eye(2))
    with pytest.raises(ValueError, match="K: expected finite"):
        Perspective(np.array([[np.nan, 0, 1], [0, 1.0, 1], [0, 0, 1]]))
    with pytest.raises(ValueError, match="pixel_size"):
        Orthographic(pixel_size=0)
    with pytest.raises(ValueError, match="brdf: expected one of"):
        Material("oren-nayar")
    with pytest.raises(ValueError, match="roughness"):
        Material("cook-torrance", roughness=0)
    with pytest.raises(ValueError, match="f0"):
        Material("cook-torrance", f0=1.5)
    with pytest.raises(ValueError, match="scene: expected one of"):
        make_scene("teapot")
    with pytest.raises(ValueError, match="size"):
        make_scene("sphere", 4)
    with pytest.raises(ValueError, match="lights: expected"):
        default_lights("area", 3)


def test_failed_write_leaves_nothing(tmp_path, monkeypatch):
    """A crash while writing a capture leaves neither a half folder nor a changed old one."""
    import gpps.io.files as gio  # write_dataset calls the module's save_png

    scene = make_scene("sphere", 32, "orthographic")
    ds = render_dataset(scene, Material(), default_lights("directional", 3), bits=16)
    out = tmp_path / "cap"
    write_dataset(out, ds)
    before = sorted(p.name for p in out.iterdir())
    calls = {"n": 0}
    real = gio.save_png

    def flaky(path, img, bits=16):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError("disk full")
        return real(path, img, bits)

    monkeypatch.setattr(gio, "save_png", flaky)
    with pytest.raises(OSError, match="disk full"):
        write_dataset(out, ds, overwrite=True)  # replacing an earlier gpps output needs overwrite=True
    assert sorted(p.name for p in out.iterdir()) == before
    assert [p.name for p in tmp_path.iterdir()] == ["cap"]  # no temporary left behind


def test_cli_render(tmp_path):
    from gpps.cli import main

    out = tmp_path / "sphere"
    rc = main(["render", "--scene", "sphere", "--brdf", "cook-torrance", "--lights", "point", "--n-lights", "5", "--camera", "perspective", "--size", "48", "--out", str(out)])
    assert rc == 0
    names = sorted(p.name for p in out.iterdir())
    for want in ["001.png", "005.png", "filenames.txt", "light_positions.txt", "light_intensities.txt", "mask.png", "K.txt", "material.json", "normal_gt.npy", "depth_gt.npy"]:
        assert want in names
    assert "light_directions.txt" not in names
    assert json.loads((out / "material.json").read_text())["brdf"] == "cook-torrance"
    ds = read_dataset(out)
    assert ds.images.shape == (5, 48, 48, 3) and ds.K is not None
    assert main(["render", "--scene", "sphere", "--brdf", "cook-torrance", "--roughness", "-1", "--size", "16", "--out", str(tmp_path / "x")]) == 2
    assert not (tmp_path / "x").exists()
