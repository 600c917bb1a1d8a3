"""Mitsuba 3 captures (training/mitsuba_scenes.py): gpps's frame and units, the folder they are written to,
their ground truth, determinism and quantisation.  Skipped without mitsuba (``pip install gpps[render]``)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

mi = pytest.importorskip("mitsuba")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/mitsuba_scenes.py

from gpps.host.scenes import UNIFORM_ALBEDO, default_camera, make_scene  # noqa: E402
from gpps.io import read_capture  # noqa: E402
from gpps.io.formats import decode_image_file  # noqa: E402
from gpps.lights import DirectionalLights, PointLights  # noqa: E402
from gpps.material import Material  # noqa: E402
from mitsuba_scenes import (  # noqa: E402
    MIN_FACING,
    SHAPES,
    CaptureSpec,
    light_rig,
    make_capture,
    render_capture,
    render_scene,
)


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_lambertian_sphere_agrees_with_gpps_render(kind):
    """The same Lambertian sphere, camera and lights rendered by Mitsuba and by gpps.render: the frame (x right,
    y up, camera looking down -z), K and the light units (gpps intensity I = Mitsuba pi I) agree."""
    from gpps.flows.synthetic import render

    size = 48
    sc = make_scene("sphere", size, "perspective")
    lights = light_rig(kind, 3, seed=1)
    bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(UNIFORM_ALBEDO)}}
    lin, mask, normals, depth, _ = render_scene({"s": {"type": "sphere", "center": [0, 0, -10], "radius": 2.0, "bsdf": bsdf}},
                                                lights, sc.camera.K, size, spp=32, max_depth=2)
    ref = render(sc, Material("lambertian", ks=0.0), lights, device="cpu")
    both = mask & sc.mask
    assert np.mean(mask == sc.mask) > 0.99  # silhouette pixels only (n . v <= MIN_FACING)
    cos_n = np.sum(normals * sc.normals, -1)[both]
    assert np.degrees(np.arccos(np.clip(cos_n.min(), -1, 1))) < 0.1
    np.testing.assert_allclose(depth[both], sc.depth[both], atol=1e-4)
    inner = binary_erosion(sc.mask, iterations=2)
    for k in range(3):
        if kind == "directional":
            cos = sc.normals @ lights.directions[k]
        else:
            d = lights.positions[k] - sc.points
            cos = np.sum(sc.normals * d / np.linalg.norm(d, axis=-1, keepdims=True), -1)
        sel = inner & (cos > 0.15)  # away from the terminator (the pixel-area average differs from the centre there)
        r = lin[k][sel] / ref[k][sel]
        assert abs(np.median(r) - 1.0) < 0.01, (k, np.median(r))
        assert np.percentile(np.abs(r - 1.0), 99) < 0.03, (k, np.percentile(np.abs(r - 1.0), 99))
    # and a mirror test of the frame: light from +x brightens the sphere's right half (columns > cx)
    lit = render_scene({"s": {"type": "sphere", "center": [0, 0, -10], "radius": 2.0, "bsdf": bsdf}},
                       DirectionalLights([[1.0, 0.0, 0.0]]), sc.camera.K, size, spp=4, max_depth=2)[0][0, ..., 0]
    assert lit[:, size // 2 + 2:].sum() > 0 and lit[:, : size // 2 - 2].sum() == 0


def test_capture_reads_back_through_gpps_io(tmp_path):
    spec = CaptureSpec(shape="sphere_on_plane", material="roughplastic", light_kind="point", n_lights=3, size=32, spp=8)
    folder = make_capture(spec, tmp_path)
    assert folder == tmp_path / spec.name
    cap = read_capture(folder)
    ds = cap.dataset
    assert ds.images.shape == (3, 32, 32, 3) and ds.images.dtype == np.float32
    assert cap.calibrated and cap.mask_source == "mask.png" and ds.light_directions is None
    rig = light_rig("point", 3, spec.seed)
    np.testing.assert_allclose(ds.light_positions, rig.positions, rtol=1e-8)
    info = json.loads((folder / "scene.json").read_text())
    np.testing.assert_allclose(ds.light_intensities, info["exposure"] * rig.intensities, rtol=1e-8)
    np.testing.assert_allclose(ds.K, default_camera("perspective", 32).K, rtol=1e-8)  # K.txt: 9 digits
    assert ds.normal_gt.shape == (32, 32, 3) and ds.depth_gt.shape == (32, 32)
    assert [f["bits"] for f in cap.formats] == [16]
    again = render_capture(spec)
    np.testing.assert_array_equal(ds.mask, again.mask)
    np.testing.assert_allclose(ds.normal_gt, again.normals)
    # the reader divides by exposure x intensity: the files hold the quantised images exactly
    np.testing.assert_allclose(ds.images * ds.light_intensities[:, None, None, :].astype(np.float32), again.images, atol=2e-7)
    # rendered once: the second call finds the folder with the same spec
    mtime = (folder / "001.png").stat().st_mtime_ns
    assert make_capture(spec, tmp_path) == folder and (folder / "001.png").stat().st_mtime_ns == mtime


@pytest.mark.parametrize("shape", SHAPES)
def test_ground_truth_normals_are_unit_and_face_the_camera(shape):
    spec = CaptureSpec(shape=shape, material="diffuse", n_lights=1, size=32, spp=2, texture=shape == "bumps")
    cap = render_capture(spec)
    m = cap.mask
    assert m.mean() > 0.1, m.mean()
    n = cap.normals
    np.testing.assert_allclose(np.linalg.norm(n[m], axis=-1), 1.0, atol=1e-5)
    assert not n[~m].any() and not cap.depth[~m].any()
    points = default_camera("perspective", 32).backproject(cap.depth)[m]
    view = -points / np.linalg.norm(points, axis=-1, keepdims=True)
    assert np.sum(n[m] * view, -1).min() > MIN_FACING
    assert np.all((cap.depth[m] > 8.0) & (cap.depth[m] < 12.0))
    assert cap.images[0][m].max() > 0.5  # exposed: the bright end near exposure_level


def test_same_seed_same_images_other_seed_other_images():
    spec = CaptureSpec(shape="bumps", material="roughplastic", n_lights=2, size=24, spp=4, texture=True)
    a, b = render_capture(spec), render_capture(spec)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.linear, b.linear)
    c = render_capture(CaptureSpec(**{**spec.__dict__, "seed": 1}))
    assert not np.array_equal(a.images, c.images)
    assert isinstance(light_rig("point", 12, 0), PointLights) and not np.allclose(light_rig("directional", 3, 0).directions,
                                                                                  light_rig("directional", 3, 1).directions)


def test_8bit_quantisation_is_what_it_says(tmp_path):
    spec = CaptureSpec(shape="steps", material="diffuse", n_lights=2, size=24, spp=4, bits=8, read_noise=0.0, full_well=0.0)
    folder = make_capture(spec, tmp_path)
    raw = decode_image_file(folder / "001.png")
    assert raw.data.dtype == np.uint8 and raw.info["bits"] == 8
    cap = render_capture(spec)
    q = cap.images * 255.0
    np.testing.assert_allclose(q, np.round(q), atol=1e-4)
    np.testing.assert_array_equal(raw.data.astype(np.float32) / 255.0, cap.images[0])
    # no noise: the image is the exposed render rounded to 8 bits (clipped at full scale)
    expected = np.round(np.clip(cap.linear * cap.exposure, 0, 1) * 255) / 255
    np.testing.assert_allclose(cap.images, expected, atol=1e-6)
    assert read_capture(folder).formats[0]["bits"] == 8


def test_spec_checks_its_arguments():
    with pytest.raises(ValueError, match="shape"):
        CaptureSpec(shape="teapot")
    with pytest.raises(ValueError, match="bits"):
        CaptureSpec(bits=12)
    with pytest.raises(ValueError, match="max_depth"):
        CaptureSpec(max_depth=1)
