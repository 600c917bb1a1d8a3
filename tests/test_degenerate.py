"""Degenerate and doubtful input: clear errors, warnings in results, report.json and stderr; types at the boundary."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import gpps
from gpps import GppsWarning
from gpps.cli import main
from gpps.io import Dataset, write_dataset
from gpps.flows.photometric import solve_normals
from gpps.host.scenes import make_scene
from gpps.flows.synthetic import default_lights, render


@pytest.fixture(scope="module")
def sphere():
    sc = make_scene("sphere", 24, "orthographic")
    L = default_lights("directional", 3)
    img = render(sc, gpps.Material("lambertian", ks=0.0), L, bits=16) / L.intensities[:, None, None, :]
    return sc, gpps.DirectionalLights(L.directions), img.astype(np.float32)


def _capture(root, images, sc, lights):
    write_dataset(root, Dataset(images=images, mask=sc.mask, light_directions=lights.directions,
                                normal_gt=sc.normals))
    return root


# ------------------------------------------------------------------ errors


def test_all_black_is_an_error(sphere, device):
    sc, L, img = sphere
    with pytest.raises(ValueError, match="images: every observation inside the mask is black"):
        solve_normals(np.zeros_like(img), sc.mask, L, device=device)
    with pytest.raises(ValueError, match="images: every observation inside the mask is black"):
        gpps.reconstruct(np.zeros_like(img), sc.mask, L, device=device)


def test_all_saturated_is_an_error(sphere, device):
    sc, L, img = sphere
    full = np.full(img.shape, 65535, np.uint16)  # integer images: full scale is saturated
    with pytest.raises(ValueError, match="saturated"):
        solve_normals(full, sc.mask, L, device=device)
    with pytest.raises(ValueError, match="saturated"):
        gpps.reconstruct(np.ones_like(img), sc.mask, L, saturation=1.0, device=device)


def test_mask_outside_the_lit_area(sphere, device):
    sc, L, img = sphere
    outside = ~sc.mask
    with pytest.raises(ValueError, match="mask lies outside the lit area"):
        solve_normals(img, outside, L, device=device)


@pytest.mark.parametrize("kind", ["black", "saturated"])
def test_cli_refuses_degenerate_captures(sphere, tmp_path, capsys, kind, device):
    sc, L, img = sphere
    images = np.zeros_like(img) if kind == "black" else np.ones_like(img)
    cap = _capture(tmp_path / "cap", images, sc, L)
    rc = main(["--device", device, "reconstruct", str(cap), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert ("black" if kind == "black" else "saturated") in err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ warnings


def test_lights_behind_the_object_warn(sphere, tmp_path, capsys, device):
    sc, L, img = sphere
    d = L.directions.copy()
    d[0, 2] = -abs(d[0, 2])  # light 1 behind the object
    behind = gpps.DirectionalLights(d / np.linalg.norm(d, axis=1, keepdims=True))
    lit = render(sc, gpps.Material("lambertian", ks=0.0), default_lights("directional", 3), bits=16)
    with pytest.warns(GppsWarning, match="point away from the camera"):
        res = solve_normals(lit, sc.mask, behind, device=device)
    assert any("away from the camera" in w for w in res.warnings)
    cap = _capture(tmp_path / "cap", lit, sc, behind)
    assert main(["--device", device, "reconstruct", str(cap), "--method", "ppn", "--no-integrate",
                 "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert "warning: lights: 1 of 3 directional lights point away" in err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert any("away from the camera" in w for w in report["warnings"])


def test_point_light_behind_warns(sphere, device):
    sc, _, img = sphere
    pos = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, -20.0]])
    with pytest.warns(GppsWarning, match="beyond the object's mean depth"):
        solve_normals(img, sc.mask, gpps.PointLights(pos), depth=np.full(sc.mask.shape, 10.0), device=device)


def test_estimate_on_its_bound_and_unconverged_rounds_warn(sphere, device):
    sc, L, img = sphere  # a matte sphere: a specular lobe cannot be estimated, ks goes to its lower bound
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rec = gpps.reconstruct(img, sc.mask, L, material="blinn-phong", device=device,
                               config=gpps.RONConfig(rounds=2))
    msgs = [str(w.message) for w in caught if issubclass(w.category, GppsWarning)]
    assert msgs == rec.warnings
    assert any("estimated ks" in m and "bound of its search range" in m for m in msgs), msgs
    if not rec.converged:
        assert any("RON stopped at its cap of 2 rounds" in m for m in msgs)
    from gpps.flows.ron import estimate_on_bound

    assert estimate_on_bound("shininess", 500.0) is not None and estimate_on_bound("shininess", 40.0) is None


def test_many_undetermined_pixels_warn(sphere, device):
    sc, L, img = sphere
    half = img.copy()
    half[:, :, : sc.mask.shape[1] // 2] = 0.0  # the left half unlit in every image
    with pytest.warns(GppsWarning, match="fewer than 3 usable"):
        solve_normals(half, sc.mask, L, device=device)


def test_clean_input_gives_no_warning(sphere, device):
    sc, L, img = sphere
    with warnings.catch_warnings():
        warnings.simplefilter("error", GppsWarning)
        res = solve_normals(img, sc.mask, L, device=device)
    assert res.warnings == [] and res.determined[sc.mask].mean() > 0.5


# ------------------------------------------------------------------ types at the boundary


@pytest.mark.parametrize("bad", ["complex", "bool", "object", "int32", "str"])
def test_image_types_refused(sphere, bad, device):
    sc, L, img = sphere
    arr = {"complex": img.astype(np.complex64), "bool": img > 0.5, "object": img.astype(object),
           "int32": (img * 1000).astype(np.int32), "str": img.astype(str)}[bad]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning: refused before any cast
        with pytest.raises(TypeError, match="images"):
            solve_normals(arr, sc.mask, L, device=device)
        with pytest.raises(TypeError, match="images"):
            gpps.reconstruct(arr, sc.mask, L, device=device)


def test_integer_images_by_full_scale(sphere, device):
    sc, L, img = sphere
    u16 = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
    u8 = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    ref = solve_normals(u16.astype(np.float32) / 65535, sc.mask, L, solver="none", device=device)
    a = solve_normals(u16, sc.mask, L, solver="none", device=device)
    b = solve_normals(u8, sc.mask, L, solver="none", device=device)
    np.testing.assert_allclose(a.albedo[sc.mask], ref.albedo[sc.mask], rtol=1e-5)
    np.testing.assert_allclose(b.albedo[sc.mask], ref.albedo[sc.mask], rtol=0.05, atol=0.01)
    assert a.albedo[sc.mask].max() < 2.0  # 0..1 images, not 0..65535


def test_negative_images_refused(sphere, device):
    sc, L, img = sphere
    with pytest.raises(ValueError, match="images: expected values >= 0"):
        solve_normals(img - 0.5, sc.mask, L, device=device)


def test_float_images_saturated_everywhere_are_an_error(sphere, device):
    """Float images at their full scale (1.0) everywhere with no saturation level given (nothing flags them):
    refused before any solve; one value below full scale everywhere (a flat target under a ring of lights gives
    that) is a valid capture."""
    sc, L, img = sphere
    with pytest.raises(ValueError, match=r"images: 100% of the observations inside the mask are at 1, the full "
                                         r"scale: everything is saturated"):
        gpps.reconstruct(np.ones_like(img), sc.mask, L, device=device)
    d = np.array([[np.sin(0.5) * np.cos(a), np.sin(0.5) * np.sin(a), np.cos(0.5)] for a in (0.0, 2.1, 4.2)])
    flat = solve_normals(np.full_like(img, 0.5), sc.mask, gpps.DirectionalLights(d), solver="none", device=device)
    np.testing.assert_allclose(flat.normals[sc.mask], np.tile([0.0, 0.0, 1.0], (int(sc.mask.sum()), 1)), atol=1e-5)


def test_clipped_float_images_warn(sphere, device):
    """Float images clipped at 1.0 (~8 % of the observations): the clipping plateaus are found and left out of the
    fit with a warning (gpps.host.clipping), as a given saturation=1 leaves them out without one."""
    sc, L, img = sphere
    peak = img.max(axis=-1)[:, sc.mask]
    clipped = np.minimum(img / np.percentile(peak, 92), 1.0).astype(np.float32)  # ~8% of the observations at 1.0
    with pytest.warns(GppsWarning, match=r"plateau of one value at the image's maximum \(1, 1, 1\) and were left "
                                         r"out as clipped"):
        res = solve_normals(clipped, sc.mask, L, device=device)
    assert any("left out as clipped" in w for w in res.warnings)
    assert not any("Pass saturation=" in w for w in res.warnings)  # (not told twice)
    with warnings.catch_warnings(record=True) as caught:  # a saturation level given: the fit drops them
        warnings.simplefilter("always")
        given = solve_normals(clipped, sc.mask, L, saturation=1.0, device=device)
    assert not any("clipped" in str(w.message) for w in caught) and not any("clipped" in w for w in given.warnings)
    assert np.array_equal(res.normals, given.normals)  # the same observations left out


def test_float_mask_with_nan_is_refused(sphere, device):
    sc, L, img = sphere
    bad = np.where(sc.mask, np.nan, 0.0)  # NaN > 0 is False: it would read as an empty mask
    with pytest.raises(ValueError, match=r"^mask: expected finite values"):
        gpps.reconstruct(img, bad, L, device=device)
    ok = solve_normals(img, sc.mask.astype(np.float32), L, solver="none", device=device)  # finite floats: > 0 inside
    assert ok.normals[sc.mask].any()


def test_single_image_saturated_or_clipped():
    """The single-image flow checks clipping as the calibrated ones do (gpps.names.CLIP_LEVELS): an over-exposed
    8-bit photograph (255 everywhere) is refused before the network runs; one with 5 % or more of its observations
    at the full scale warns; an unclipped one does not."""
    from gpps.host.single import prepare_images

    sc = make_scene("sphere", 32, "orthographic")
    L = default_lights("directional", 1)
    img = render(sc, gpps.Material("lambertian", ks=0.0), L, bits=16)[0]  # (H, W, 3) in [0, 1]
    white = np.full(img.shape, 255, np.uint8)
    with pytest.raises(ValueError, match=r"images: 100% of the object's observations are at 1, the full scale: "
                                         r"everything is saturated"):
        prepare_images(white, sc.mask)
    with pytest.raises(ValueError, match="everything is saturated"):
        gpps.reconstruct_single(white, sc.mask)
    peak = img.max(axis=-1)[sc.mask]
    clipped = np.round(255 * np.minimum(img / np.percentile(peak, 90), 1.0)).astype(np.uint8)  # ~10 % at 255
    with pytest.warns(GppsWarning, match=r"observations sit at 1, the full scale: clipped"):
        prepare_images(clipped, sc.mask)
    with warnings.catch_warnings():
        warnings.simplefilter("error", GppsWarning)
        prepare_images(np.round(200 * img / peak.max()).astype(np.uint8), sc.mask)
