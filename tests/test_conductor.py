"""The rough conductor (a metal: GGX microfacets, no diffuse term, gpps.kernels.brdf): its lobe against Mitsuba 3's
``roughconductor`` and against Walter et al.'s equations (tests/reference_models.py, tests/test_models.py; the
Jacobians in tests/test_jacobians.py), per-pixel solves on conductor-rendered scenes, RON's roughness fit and the
choice of the model by residual, and the Material / CLI settings.
"""

import numpy as np
import pytest

import gpps
from gpps.host.metrics import normal_errors
from gpps.material import Material
from gpps.names import LOBE_PARAMETERS

TRUE = Material("conductor", roughness=0.3)


@pytest.mark.parametrize("alpha", [0.1, 0.25, 0.5])
def test_lobe_equals_mitsuba_roughconductor_ggx(device, alpha):
    """An independent implementation: Mitsuba 3's ``roughconductor`` (GGX, Smith's separable G, ``material`` "none":
    a perfect reflector, F = 1) is ``D G / (4 n.v)`` in its ``eval`` (the cosine of l included); gpps's lobe with
    f0 = 1 is pi times it (gpps's units, see gpps.kernels.brdf), everywhere, grazing directions included
    (measured: within 1e-6)."""
    from test_models import eval_kernel
    from test_plastic import _mitsuba_eval, _near_mirror

    n, v, l = _near_mirror(np.random.default_rng(int(alpha * 100)), 300, 1.5 * alpha, 0.05)
    got = eval_kernel(device, Material("conductor", roughness=alpha), n, l, v)
    ref = np.pi * _mitsuba_eval({"type": "roughconductor", "distribution": "ggx", "alpha": alpha, "material": "none"}, v, l)
    assert np.all(got[:, 1] == 0.0)  # no second (ks-weighted) term
    big = ref > 1e-3 * ref.max()
    assert big.sum() > 250
    np.testing.assert_allclose(got[big, 0], ref[big], rtol=2e-5)  # both float32


def test_fresnel_rise_is_schlick_relative_to_normal_incidence(device):
    """With f0 < 1 the lobe is the f0 = 1 lobe times ``(f0 + (1 - f0)(1 - h.v)^5) / f0``: 1 at normal incidence,
    rising toward grazing (the albedo map stays the metal's colour at normal incidence)."""
    from test_models import eval_kernel, random_geometry

    n, l, v = random_geometry(np.random.default_rng(3), 500)
    one = eval_kernel(device, Material("conductor", roughness=0.3), n, l, v)[:, 0]
    f0 = 0.6
    got = eval_kernel(device, Material("conductor", roughness=0.3, f0=f0), n, l, v)[:, 0]
    h = (l + v) / np.linalg.norm(l + v, axis=-1, keepdims=True)
    vh = np.sum(v * h, -1)
    np.testing.assert_allclose(got, one * (f0 + (1 - f0) * (1 - vh) ** 5) / f0, rtol=2e-6, atol=1e-9)
    assert np.count_nonzero(one > 1e-2) > 100


def _case(scene="bumps", n_lights=12, kind="directional", size=48, noise=0.0, material=TRUE):
    """tests/test_plastic.py's rendered case (16-bit, divided by the intensities) with the metal's defaults."""
    from test_plastic import _case as rendered_case

    return rendered_case(scene, n_lights, kind, size, noise, material)


@pytest.mark.parametrize("scene,kind", [("bumps", "directional"), ("sphere", "point")])
@pytest.mark.parametrize("n_lights", [5, 6, 12])
def test_solve_recovers_normals_noise_free(device, scene, kind, n_lights):
    """Known material, perspective, 16-bit: the normals and the metal's colour back from
    :data:`gpps.names.CONDUCTOR_MIN_IMAGES` (5) lights on.  Measured at 48^2: MAEN 0.0004-0.004 deg with 6 and 12
    lights; with 5 0.01 (bumps) and 0.11 (the sphere under point lights: a few rim pixels see only 3 of the lights
    inside the lobe).  (With 3 lights a pixel has three equations for its normal and its colour's scale: the normals
    are not determined, 4-10 deg; with 4, 0.4-2.1 deg; not asserted.)"""
    from gpps.flows.photometric import solve_normals

    img, L, sc, sat = _case(scene, n_lights, kind)
    depth = sc.depth if kind == "point" else None
    r = solve_normals(img, sc.mask, L, camera=sc.camera, material=TRUE, depth=depth, saturation=sat, device=device)
    e = normal_errors(r.normals, sc.normals, sc.mask)
    assert e["mean"] <= (0.25 if n_lights == 5 else 0.05), e
    assert e["median"] <= 0.01, e
    ok = sc.mask & ((r.flags & 2) == 0)
    assert np.median(np.abs(r.albedo[ok] - sc.albedo[ok])) < 1e-3


def test_residual_chooses_the_conductor_and_fits_its_roughness(device):
    """``material=("blinn-phong", "conductor")``: on a metal the conductor is chosen and its GGX alpha estimated
    (measured 0.298 against 0.3 at 64^2 with noise 0.002); on a plastic scene it is not chosen."""
    img, L, sc, sat = _case(noise=0.002)
    rec = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("blinn-phong", "conductor"), saturation=sat,
                           device=device)
    assert rec.material.brdf == "conductor"
    assert rec.estimated["roughness"] == pytest.approx(TRUE.roughness, rel=0.05)
    assert normal_errors(rec.normals, sc.normals, sc.mask)["median"] <= 0.5
    plastic = Material.from_ior("plastic", 1.5, ks=1.2, roughness=0.15)
    img, L, sc, sat = _case(noise=0.002, material=plastic)
    rec = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=("blinn-phong", "conductor"), saturation=sat,
                           device=device)
    assert rec.material.brdf == "blinn-phong"


def test_material_settings_and_errors(tmp_path):
    import json

    from gpps.cli import main

    m = Material("conductor")
    assert m.f0 == 1.0 and "conductor" in gpps.BRDF_NAMES
    assert LOBE_PARAMETERS["conductor"] == ("roughness",)  # its albedo map weighs the lobe: no ks
    assert Material.default_for("conductor") == Material("conductor", ks=0.0, roughness=0.5)  # peak 1: in range
    assert Material.from_dict(m.to_dict()) == m
    with pytest.raises(ValueError, match="f0: the conductor needs f0 in"):
        Material("conductor", f0=0.0)
    out = tmp_path / "cap"
    assert main(["render", "--scene", "sphere", "--brdf", "conductor", "--size", "16", "--out", str(out)]) == 0
    assert json.loads((out / "material.json").read_text())["brdf"] == "conductor"


def test_lights_parallel_and_split_starts_builds_equal_the_one_thread_solve(device):
    """The conductor's lights-parallel build (one block of lanes a pixel) and starts-parallel build give the
    one-thread solve's results (bitwise on the CPU, where a block runs as one lane; close on CUDA), as plastic's
    (tests/test_plastic.py's solve_three_builds)."""
    from test_plastic import solve_three_builds

    out, sc = solve_three_builds(TRUE, device)
    assert normal_errors(out["normals"], sc.normals, sc.mask)["median"] < 2.5  # measured 1.22 (1 % noise on a metal)


def test_folder_flow_compares_the_conductor_from_five_images(tmp_path, device):
    """``gpps reconstruct``'s default (``FolderConfig(models=None)``): the conductor (and plastic) are fitted beside
    Blinn-Phong from :data:`CONDUCTOR_IMAGES` images on, and the conductor is chosen on a metal with the evidence
    test passed; with 3 images, or ``models=()`` / ``--compare-models none``, nothing is compared; the report says
    which rule decided."""
    import argparse

    from gpps.cli import main
    from gpps.cli.reconstruct import add_reconstruct_options, folder_config
    from gpps.flows.folder import CONDUCTOR_IMAGES, FolderConfig, automatic_models

    assert CONDUCTOR_IMAGES == 5
    assert automatic_models(4, FolderConfig()) == ((), "automatic: none with 4 images (the conductor and plastic "
                                                       "from 5)")
    assert automatic_models(5, FolderConfig())[0] == ("conductor", "plastic")
    assert automatic_models(96, FolderConfig(models=())) == ((), "turned off")
    assert automatic_models(96, FolderConfig(models=("plastic",))) == (("plastic",), "asked")
    with pytest.raises(TypeError, match="models: expected None or a tuple"):
        FolderConfig(models="conductor")
    out = tmp_path / "metal"
    assert main(["render", "--scene", "sphere", "--brdf", "conductor", "--n-lights", "8", "--size", "32",
                 "--camera", "perspective", "--out", str(out)]) == 0
    (out / "material.json").unlink()  # the material unknown to the reconstruction
    rec = gpps.reconstruct_folder(out, device=device)
    assert rec.report["models"]["compared"] == ["conductor", "plastic"]
    assert rec.report["models"]["why"].startswith("automatic")
    assert rec.report["model_evidence"]["conductor"]["significant"]
    assert rec.report["material"]["brdf"] == "conductor"
    p = argparse.ArgumentParser()
    add_reconstruct_options(p)
    assert folder_config(p.parse_args(["--compare-models", "none"])).models == ()
    assert folder_config(p.parse_args([])).models is None
    assert folder_config(p.parse_args(["--compare-models", "plastic,conductor"])).models == ("plastic", "conductor")


def test_fewer_than_five_images_of_a_metal_warn(device):
    """A metal's normals are not determined by fewer than :data:`gpps.names.CONDUCTOR_MIN_IMAGES` images (3 lights:
    4-10 deg off with the material known, 4 lights 0.4-2.1, tests above): the array API, the per-pixel solve and the
    stream say so; with 5 they do not."""
    import warnings

    from gpps.flows.photometric import solve_normals
    from gpps.material import check_model_images
    from gpps.names import CONDUCTOR_MIN_IMAGES
    from gpps.pipeline.stream import Stream, StreamConfig

    assert CONDUCTOR_MIN_IMAGES == 5
    sink: list = []
    with pytest.warns(gpps.GppsWarning, match="does not determine the normals from 4 images"):
        check_model_images(("blinn-phong", "conductor"), 4, sink)
    assert len(sink) == 1 and "5 or more images" in sink[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error", gpps.GppsWarning)
        check_model_images(("blinn-phong", "conductor"), 5)
        check_model_images(("blinn-phong", "plastic"), 3)
    img, L, sc, sat = _case("sphere", 3, size=24)
    with pytest.warns(gpps.GppsWarning, match="conductor"):
        r = solve_normals(img, sc.mask, L, camera=sc.camera, material=TRUE, saturation=sat, device=device)
    assert any("does not determine the normals" in w for w in r.warnings)
    with pytest.warns(gpps.GppsWarning, match="conductor"):
        Stream(sc.mask.shape, sc.camera, L, TRUE, mask=sc.mask, config=StreamConfig(output="numpy"), device=device).close()
