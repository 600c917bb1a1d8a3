"""A battery of bad inputs through the public API: each a clear ValueError / TypeError naming the argument
(never a numpy, OpenCV or LinAlg error from deep inside), each degenerate input an error or a GppsWarning.

One row per defect found by probing the value types, the array entry points and the stages; every call fails
before any solve (tiny sizes), so the file runs in seconds.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import gpps
from conftest import DEVICES
from gpps import GppsWarning

#: every call fails (or warns) on the host before any solve; the first test device runs it (the GPU machine has no
#: Warp CPU device)
DEV = DEVICES[0]

K_OK = [[100.0, 0.0, 8.0], [0.0, 100.0, 8.0], [0.0, 0.0, 1.0]]
DIRS = [[0.0, 0.0, 1.0], [0.5, 0.0, 0.866], [0.0, 0.5, 0.866]]


@pytest.fixture(scope="module")
def capture():
    """A 16 x 16 Lambertian sphere under 4 unit directional lights: (scene, images, lights)."""
    sc = gpps.make_scene("sphere", 16, "orthographic")
    lights = gpps.default_lights("directional", 4)
    img = gpps.render(sc, gpps.Material("lambertian", ks=0.0), lights, device=DEV) / 0.8
    return sc, img.astype(np.float32), gpps.DirectionalLights(lights.directions)


def _raises(exc, match, fn):
    with pytest.raises(exc, match=match):
        fn()


# ------------------------------------------------------------------ value types

VALUE_TYPES = {
    # strings, bools and complex numbers were cast to floats (np.asarray(K, float64) in camera_from_K)
    "K strings": (lambda: gpps.camera_from_K([["100", "0", "8"], ["0", "100", "8"], ["0", "0", "1"]]), TypeError, "^K: "),
    "K complex": (lambda: gpps.camera_from_K(np.array(K_OK) * (1 + 1j)), TypeError, "^K: "),
    "K bool": (lambda: gpps.camera_from_K(np.eye(3, dtype=bool)), TypeError, "^K: "),
    "K a string": (lambda: gpps.camera_from_K("abc"), TypeError, "^K: "),
    "Perspective K strings": (lambda: gpps.Perspective([["1", "0", "0"], ["0", "1", "0"], ["0", "0", "1"]]),
                              TypeError, "^K: "),
    # float("1") and float(True) were taken as pixel sizes
    "pixel_size string": (lambda: gpps.Orthographic("1"), TypeError, "^pixel_size: "),
    "pixel_size bool": (lambda: gpps.Orthographic(True), TypeError, "^pixel_size: "),
    "center strings": (lambda: gpps.Orthographic(1.0, ("1", "2")), TypeError, "^center: "),
    "center bools": (lambda: gpps.Orthographic(1.0, (True, False)), TypeError, "^center: "),
    # lights: strings and bools were cast, an empty set of lights was accepted
    "directions strings": (lambda: gpps.DirectionalLights([["0", "0", "1"]]), TypeError, "^directions: "),
    "directions bool": (lambda: gpps.DirectionalLights(np.array([[False, False, True]])), TypeError, "^directions: "),
    "intensities bool": (lambda: gpps.DirectionalLights(DIRS, [True, True, True]), TypeError, "^intensities: "),
    "positions bool": (lambda: gpps.PointLights(np.array([[True, False, True]])), TypeError, "^positions: "),
    "mu bool": (lambda: gpps.PointLights([[10.0, 0.0, 0.0]], mu=True), TypeError, "^mu: "),
    "no directions": (lambda: gpps.DirectionalLights(np.zeros((0, 3))), ValueError, r"^directions: .*N >= 1"),
    "no positions": (lambda: gpps.PointLights(np.zeros((0, 3))), ValueError, r"^positions: .*N >= 1"),
    # subset: IndexError from numpy
    "subset out of range": (lambda: gpps.DirectionalLights(DIRS).subset([5]), ValueError, "^idx: "),
    "subset empty": (lambda: gpps.DirectionalLights(DIRS).subset([]), ValueError, "^idx: "),
    "subset floats": (lambda: gpps.PointLights(DIRS).subset([0.5]), TypeError, "^idx: "),
    # default_lights: numpy's TypeError for a bool, int()'s message for NaN
    "default_lights n bool": (lambda: gpps.default_lights("directional", True), ValueError, "^n: "),
    "default_lights n nan": (lambda: gpps.default_lights("directional", float("nan")), ValueError, "^n: "),
}


@pytest.mark.parametrize("case", list(VALUE_TYPES))
def test_value_types_refuse_bad_input(case):
    fn, exc, match = VALUE_TYPES[case]
    _raises(exc, match, fn)


def test_subset_keeps_working():
    lights = gpps.DirectionalLights(DIRS)
    assert len(lights.subset([True, False, True])) == 2
    assert len(lights.subset(1)) == 1
    assert len(lights.subset([-1, 0])) == 2


# ------------------------------------------------------------------ solve_normals / reconstruct


def test_lights_of_zero_intensity_are_an_error(capture):
    sc, img, lights = capture
    dark = gpps.DirectionalLights(lights.directions, np.zeros((4, 3)))
    two = gpps.DirectionalLights(lights.directions, [[1, 1, 1], [1, 1, 1], [0, 0, 0], [0, 0, 0]])
    for entry in (gpps.solve_normals, gpps.reconstruct):
        for lt in (dark, two):  # (a garbage result with 45 deg errors before, flags only)
            with pytest.raises(ValueError, match="^lights: expected at least 3 lights with an intensity > 0"):
                entry(img, sc.mask, lt, device=DEV)


@pytest.mark.parametrize("scale", [1e30, 1e-30, 1e-40])
def test_images_outside_the_float32_range_are_an_error(capture, scale):
    # 1e30: residual NaN and zero normals without a word; 1e-30 and 1e-40: normals left at the start (45 deg)
    sc, img, lights = capture
    for entry in (gpps.solve_normals, gpps.reconstruct):
        with pytest.raises(ValueError, match="^images: expected linear values between"):
            entry(img * np.float32(scale), sc.mask, lights, device=DEV)


def test_light_intensity_far_from_the_images_is_an_error(capture):
    sc, img, lights = capture
    faint = gpps.DirectionalLights(lights.directions, np.full((4, 3), 1e-11))  # (albedo 0 came out)
    with pytest.raises(ValueError, match="^lights: expected intensities of the images' order"):
        gpps.solve_normals(img, sc.mask, faint, device=DEV)


def test_pixel_solver_refuses_overflowing_images(capture):
    sc, img, lights = capture
    ps = gpps.PixelSolver((4, 16, 16), gpps.Orthographic(), lights, gpps.Material("lambertian", ks=0.0), device=DEV)
    try:
        with pytest.raises(ValueError, match="^images: expected linear values up to"):
            ps.upload(img * np.float32(1e30), sc.mask)
    finally:
        ps.close()


def test_pixel_solver_warns_when_nothing_is_lit(capture):
    """All-black images (or no valid observation) gave every pixel the view direction and albedo 0 without a
    word; the flows refuse such frames, the stage warns (a dark tile of a tiled frame stays quiet: the flow checks
    the frame)."""
    sc, img, lights = capture
    ps = gpps.PixelSolver((4, 16, 16), gpps.Orthographic(), lights, gpps.Material("lambertian", ks=0.0), device=DEV)
    try:
        with pytest.warns(GppsWarning, match="^images: no observation inside the mask is lit: no normal"):
            ps.upload(np.zeros_like(img), sc.mask)
        with pytest.warns(GppsWarning, match="^images: no observation inside the mask is lit and valid"):
            ps.upload(img, sc.mask, valid=np.zeros(img.shape[:3], bool))
        with warnings.catch_warnings():
            warnings.simplefilter("error", GppsWarning)
            ps.upload(img, sc.mask)  # (a lit frame: no warning)
    finally:
        ps.close()


def test_led_axes_pointing_away_warn():
    """Point lights with mu > 0 whose axes point away from the object light nothing; they passed without a word."""
    sc = gpps.make_scene("sphere", 16, "perspective")
    pos = np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, -0.5, 0.0]])
    img = np.full((4, 16, 16, 3), 0.5, np.float32)
    for sign, warns in ((-1.0, False), (1.0, True)):  # the default axes (0, 0, -1) face the scene
        lights = gpps.PointLights(pos, axes=np.tile([0.0, 0.0, sign], (4, 1)), mu=1.0)
        ps = gpps.PixelSolver((4, 16, 16), sc.camera, lights, gpps.Material("lambertian", ks=0.0), device=DEV)
        try:
            with warnings.catch_warnings(record=True) as rec:
                warnings.simplefilter("always")
                ps.upload(img, sc.mask, depth=sc.depth)
            hits = [w for w in rec if "axes pointing away from the object" in str(w.message)]
            assert len(hits) == int(warns), [str(w.message) for w in rec]
            if warns:
                assert issubclass(hits[0].category, GppsWarning) and "lights [1, 2, 3, 4]" in str(hits[0].message)
        finally:
            ps.close()


def test_no_images_names_the_images(capture):
    sc, img, lights = capture  # (said "lights: expected 0 lights (one per image), got 4")
    with pytest.raises(ValueError, match="^images: expected at least 3 images, got 0"):
        gpps.solve_normals(img[:0], sc.mask, lights, device=DEV)


@pytest.mark.parametrize("bad,exc", [(np.nan, ValueError), ("x", TypeError)])
def test_valid_is_checked(capture, bad, exc):
    # NaN was True (np.asarray(valid, bool)); strings were numpy's UFuncTypeError without the argument's name
    sc, img, lights = capture
    valid = np.full(img.shape[:3], bad)
    for entry in (gpps.solve_normals, gpps.reconstruct):
        with pytest.raises(exc, match="^valid: "):
            entry(img, sc.mask, lights, valid=valid, device=DEV)
    ps = gpps.PixelSolver((4, 16, 16), gpps.Orthographic(), lights, gpps.Material("lambertian", ks=0.0), device=DEV)
    try:
        with pytest.raises(exc, match="^valid: "):
            ps.upload(img, sc.mask, valid=valid)
    finally:
        ps.close()


def test_point_light_at_the_object_is_an_error(capture):
    sc, img, _ = capture  # (numpy's LinAlgError "SVD did not converge" before)
    at = gpps.PointLights([[0.0, 0.0, -5.0]] * 4)
    with pytest.raises(ValueError, match=r"^lights: point light\(s\) \[1, 2, 3, 4\] lie at the object's centre"):
        gpps.solve_normals(img, sc.mask, at, depth=np.full(sc.shape, 5.0), device=DEV)


def test_reconstruct_checks_saturation_and_estimate(capture):
    sc, img, lights = capture
    with pytest.raises(TypeError, match="^saturation: "):  # (float("1") before)
        gpps.reconstruct(img, sc.mask, lights, saturation="1", device=DEV)
    with pytest.raises(TypeError, match="^estimate: "):  # ("'int' object is not iterable" before)
        gpps.reconstruct(img, sc.mask, lights, material="blinn-phong", estimate=3, device=DEV)


# ------------------------------------------------------------------ stages


SHAPES = {
    "Renderer": lambda L: gpps.Renderer((16.5, 16), gpps.Orthographic(), L, gpps.Material(), device=DEV),
    "PixelSolver": lambda L: gpps.PixelSolver((4, 16.5, 16), gpps.Orthographic(), L, gpps.Material(), device=DEV),
    "Stream": lambda L: gpps.Stream((16.5, 16), gpps.Orthographic(), L, gpps.Material(), device=DEV),
}


@pytest.mark.parametrize("stage", list(SHAPES))
def test_stage_shapes_are_integers(capture, stage):
    _, _, lights = capture  # (int(16.5) made a 16-pixel stage without a word)
    with pytest.raises(TypeError, match=r"^shape: expected \(.*\) integers"):
        SHAPES[stage](lights)


def test_renderer_names_missing_lights():
    with pytest.raises(TypeError, match="^lights: "):  # ("object of type 'NoneType' has no len()")
        gpps.Renderer((16, 16), gpps.Orthographic(), None, gpps.Material(), device=DEV)


def test_pixel_solver_checks_its_arguments(capture):
    sc, img, lights = capture
    ps = gpps.PixelSolver((4, 16, 16), gpps.Orthographic(), lights, gpps.Material("lambertian", ks=0.0), device=DEV)
    try:
        with pytest.raises(ValueError, match="^noise: "):  # (negative noise levels were taken)
            ps.upload(img, sc.mask, noise=[-1.0] * 4)
        with pytest.raises(ValueError, match="^names: "):  # (AttributeError before)
            ps.fetch(names=("foo",))
        with pytest.raises(TypeError, match="^mask: "):  # (AttributeError before)
            ps.step_subset("x", ps.config)
    finally:
        ps.close()


# ------------------------------------------------------------------ integration


def test_integrator_checks_its_arguments(capture):
    sc = capture[0]
    n, m = sc.normals, sc.mask
    with pytest.raises(TypeError, match="^normals: "):  # (complex: cast with numpy's ComplexWarning)
        gpps.integrate_normals(n.astype(np.complex64), m, device=DEV)
    with pytest.raises(TypeError, match="^reference_depth: "):  # (float("3") before)
        gpps.integrate_normals(n, m, reference_depth="3", device=DEV)
    with pytest.raises(TypeError, match="^reference_depth: "):  # (numpy's "only 0-dimensional arrays ...")
        gpps.integrate_normals(n, m, reference_depth=np.ones(3), device=DEV)
    with pytest.raises(TypeError, match="^warm_start: "):  # ("could not convert string to float")
        gpps.integrate_normals(n, m, warm_start="x", device=DEV)


# ------------------------------------------------------------------ metrics


def test_normal_errors_checks_the_slant_threshold(capture):
    sc = capture[0]
    with pytest.raises(ValueError, match="^tilt_min_slant_deg: "):  # (NaN: every tilt left out silently)
        gpps.normal_errors(sc.normals, sc.normals, sc.mask, tilt_min_slant_deg=np.nan)
    with pytest.raises(TypeError, match="^tilt_min_slant_deg: "):  # (numpy's UFuncTypeError)
        gpps.normal_errors(sc.normals, sc.normals, sc.mask, tilt_min_slant_deg="1")


def test_depth_error_checks_its_arguments(capture):
    sc = capture[0]
    m = sc.mask
    psc = gpps.make_scene("sphere", 16, "perspective")
    one = m & (np.arange(m.size).reshape(m.shape) == np.flatnonzero(m)[0])
    cases = [
        (lambda: gpps.depth_error(sc.depth, m, None), TypeError, "^scene: "),  # AttributeError
        (lambda: gpps.depth_error(sc.depth, np.zeros_like(m), sc), ValueError, "^depth_mask: "),  # numpy's max
        (lambda: gpps.depth_error(np.full(m.shape, np.nan), m, sc), ValueError, "^depth: "),  # NaN result
        (lambda: gpps.depth_error(sc.depth, one, sc), ValueError, "^scene.depth: "),  # NaN (0 / 0)
        (lambda: gpps.depth_error(sc.depth[:-1], m, sc), ValueError, "^depth: "),  # broadcasting error
        (lambda: gpps.depth_error(np.zeros_like(psc.depth), psc.mask, psc), ValueError, "^depth: "),  # NaN
        (lambda: gpps.depth_error(-psc.depth, psc.mask, psc), ValueError, "^depth: "),  # plausible number
    ]
    for fn, exc, match in cases:
        _raises(exc, match, fn)
    # a float or list mask works as everywhere else (the float mask was numpy's bitwise_and TypeError)
    assert gpps.depth_error(sc.depth, m.astype(float), sc) == pytest.approx(0.0, abs=1e-6)
    assert gpps.depth_error(sc.depth.tolist(), m.tolist(), sc) == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------------ synthetic scenes and rendering

SCENES = {
    "size inf": (dict(size=float("inf")), ValueError, "^size: "),  # OverflowError
    "size nan": (dict(size=float("nan")), ValueError, "^size: "),  # int()'s message
    "size None": (dict(size=None), ValueError, "^size: "),  # "'NoneType' object is not iterable"
    "size (16, 16, 3)": (dict(size=(16, 16, 3)), ValueError, "^size: "),  # "too many values to unpack"
    "size 10**9": (dict(size=10**9), ValueError, "^size: expected at most"),  # MemoryError
    "seed string": (dict(albedo="texture", seed="x"), TypeError, "^seed: "),  # numpy's SeedSequence
    "seed negative": (dict(albedo="texture", seed=-1), ValueError, "^seed: "),
    "text empty": (dict(name="microprint", text=""), ValueError, "^text: "),  # IndexError
    "text int": (dict(name="microprint", text=5), TypeError, "^text: "),  # cv2.error
}


@pytest.mark.parametrize("case", list(SCENES))
def test_make_scene_checks_its_arguments(case):
    kw, exc, match = SCENES[case]
    kw = {"name": "sphere", "size": 16, "camera": "orthographic", **kw}
    with pytest.raises(exc, match=match):
        gpps.make_scene(kw.pop("name"), kw.pop("size"), kw.pop("camera"), **kw)


def test_render_checks_its_arguments(capture):
    sc, _, lights = capture
    mat = gpps.Material("lambertian", ks=0.0)
    cases = [
        (lambda: gpps.render(None, mat, lights, device=DEV), TypeError, "^scene: "),  # AttributeError
        (lambda: gpps.render(sc, mat, None, device=DEV), TypeError, "^lights: "),  # len(None)
        (lambda: gpps.render(sc, mat, lights, noise="0.1", device=DEV), TypeError, "^noise: "),  # float("0.1")
        (lambda: gpps.render(sc, mat, lights, noise=0.1, seed="x", device=DEV), TypeError, "^seed: "),
        (lambda: gpps.render(sc, mat, lights, noise=0.1, seed=-1, device=DEV), ValueError, "^seed: "),
        (lambda: gpps.render(sc, mat, lights, noise=0.1, seed=1.5, device=DEV), TypeError, "^seed: "),
    ]
    for fn, exc, match in cases:
        _raises(exc, match, fn)


def test_render_warns_about_black_images(capture):
    sc = capture[0]
    behind = gpps.DirectionalLights([[0.0, 0.0, -1.0]] * 3)  # (three black images without a word before)
    with pytest.warns(GppsWarning, match=r"^images: 3 of 3 rendered images are black inside the mask"):
        img = gpps.render(sc, gpps.Material("lambertian", ks=0.0), behind, device=DEV)
    assert not img.any()
    dark = gpps.DirectionalLights(gpps.default_lights("directional", 3).directions, [[1, 1, 1], [0, 0, 0], [1, 1, 1]])
    with pytest.warns(GppsWarning, match=r"1 of 3 rendered images .*lights \[2\]"):
        gpps.render(sc, gpps.Material("lambertian", ks=0.0), dark, device=DEV)


# ------------------------------------------------------------------ uncalibrated, single image


def test_uncalibrated_and_single_check_their_arguments(capture):
    sc, img, _ = capture
    with pytest.raises(TypeError, match="^config: "):  # AttributeError: 'str' object has no attribute 'dark_fraction'
        gpps.solve_uncalibrated(img, sc.mask, config="x", device=DEV)
    with pytest.raises(TypeError, match="^net: "):  # AttributeError: 'str' object has no attribute 'predict'
        gpps.reconstruct_single(img[0], sc.mask, net="x", device=DEV)
    with pytest.raises(ValueError, match="^mask: "):  # (NaN was True)
        gpps.reconstruct_single(img[0], np.where(sc.mask, np.nan, 0.0), device=DEV)


def test_single_image_with_an_alpha_channel_is_an_error():
    """An (H, W, 4) RGBA image was read as H grey images 4 pixels wide (normals of shape (16, 4, 3))."""
    rgba = np.random.default_rng(0).random((16, 16, 4)).astype(np.float32)
    for img in (rgba, rgba[..., :2]):
        with pytest.raises(ValueError, match=r"^images: expected \(H, W\), .* an image with an alpha channel"):
            gpps.reconstruct_single(img)


def test_single_image_scale_is_free(capture):
    """reconstruct_single takes "any positive scale": 1e-30 images were divided by max(p99, 1e-12) and came out
    near 1e-18 (a black input to the network and the search)."""
    from gpps.host.single import prepare_images

    sc, img, _ = capture
    a, _ = prepare_images(img[0], sc.mask)
    b, _ = prepare_images(img[0] * np.float32(1e-30), sc.mask)
    np.testing.assert_allclose(b, a, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------ image scale (session 18)


def test_working_scale_is_one_in_its_band_and_a_power_of_two_outside():
    from gpps.flows.photometric import WORKING_ALBEDO, WORKING_IMAGES, working_scale

    sc = gpps.make_scene("sphere", 24, "orthographic")
    lights = gpps.DirectionalLights(DIRS)
    img = gpps.render(sc, gpps.Material("lambertian", ks=0.0), lights, device=DEV).astype(np.float32)
    base = working_scale(img, sc.mask, lights)
    assert base["images"] == base["lights"] == 1.0
    assert WORKING_ALBEDO[0] <= base["albedo_scale"] <= WORKING_ALBEDO[1]
    assert WORKING_IMAGES[0] <= base["image_scale"] <= WORKING_IMAGES[1]
    for s in (1e3, 2.0 ** -9, 1e7):  # images alone: the albedo scale moves (and from 1e7 on the images' too)
        ws = working_scale(img * np.float32(s), sc.mask, lights)
        assert ws["images"] == (1.0 if s < WORKING_IMAGES[1] else 2.0 ** round(np.log2(1.0 / ws["image_scale"])))
        f = ws["images"] / ws["lights"]  # (the working albedo over the caller's)
        assert f == 2.0 ** round(np.log2(f))  # a power of two: exact
        assert 2.0 ** -0.5 <= ws["albedo_scale"] * f <= 2.0 ** 0.5  # brought near 1
    # images and radiance together: the albedo scale stays, the images are brought near 1
    ws = working_scale(img * np.float32(1e-8), sc.mask,
                       gpps.DirectionalLights(DIRS, np.full((len(DIRS), 3), 1e-8)))
    assert ws["images"] == 2.0 ** round(np.log2(1.0 / ws["image_scale"]))
    assert 0.5 <= ws["image_scale"] * ws["images"] <= 2.0
    assert ws["albedo_scale"] * ws["images"] / ws["lights"] == pytest.approx(base["albedo_scale"], rel=1e-3)


def test_point_lights_albedo_scale_counts_the_falloff():
    """Point lights 5 units away: the images are 1/25 of the albedo's order; the albedo scale undoes the falloff."""
    from gpps.flows.photometric import working_scale

    pos = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, -1.0, 0.0]])
    lights = gpps.PointLights(pos)
    img = np.full((4, 8, 8, 3), 0.5 / 25.0, np.float32)
    mask = np.ones((8, 8), bool)
    ws = working_scale(img, mask, lights, reference_depth=5.0)
    assert ws["albedo_scale"] == pytest.approx(0.5 * 27.0 / 25.0, rel=1e-3)  # (r^2 from 25 to 27: the brightest 27)
    assert ws["images"] == ws["lights"] == 1.0
    assert working_scale(img, mask, lights)["albedo_scale"] == pytest.approx(0.02, rel=1e-5)  # (no depth: I / E)


def test_reconstruct_is_scale_free():
    """Raw counts with unit intensities (images x 1000), and images and radiance both x 1e-8: before, the
    estimated ks sat on a bound of its range and the normals were 5-25 deg off (the search ranges and tolerances
    are absolute); now the same normals, and albedo, ks and residuals in the caller's scale, with a warning that
    says what was done.  Blinn-Phong bumps, 6 directional lights, 32^2, material unknown."""
    sc = gpps.make_scene("bumps", 32, "perspective")
    L = gpps.default_lights("directional", 6)
    img = gpps.render(sc, gpps.Material("blinn-phong", ks=0.4, shininess=30.0), L, bits=16, device=DEV)
    img = (img / L.intensities[:, None, None, :]).astype(np.float32)
    unit = gpps.DirectionalLights(L.directions)
    ref = gpps.reconstruct(img, sc.mask, unit, camera=sc.camera, material="blinn-phong", device=DEV)
    e0 = gpps.normal_errors(ref.normals, sc.normals, sc.mask)["mean"]
    assert e0 < 0.5 and not any("albedo scale" in w for w in ref.warnings)
    m = sc.mask
    for s, lights in ((1e3, unit), (1e-8, gpps.DirectionalLights(L.directions, np.full((6, 3), 1e-8)))):
        with pytest.warns(gpps.GppsWarning, match="albedo scale"):
            r = gpps.reconstruct(img * np.float32(s), m, lights, camera=sc.camera, material="blinn-phong", device=DEV)
        e = gpps.normal_errors(r.normals, sc.normals, m)["mean"]
        f = s / float(np.asarray(lights.intensities).mean())  # (the albedo's factor)
        print(f"\nscale {s:g}: MAEN {e:.4f} (unit scale {e0:.4f}), ks {r.material.ks:.4g} (unit {ref.material.ks:.4g})")
        assert e < e0 + 0.05
        assert r.material.ks == pytest.approx(ref.material.ks * f, rel=0.05)
        assert np.median(r.albedo[m][:, 0]) == pytest.approx(np.median(ref.albedo[m][:, 0]) * f, rel=0.05)
        assert np.median(r.residual[m]) == pytest.approx(np.median(ref.residual[m]) * s, rel=0.5)
        # the converged round's energy, in the caller's scale: a scale error would be off by the working scale's
        # power of two (2^10 or more here).  Each run stops at its own fixed point (normals and material within
        # their resolutions: RON._material_settled), and near zero energy (16-bit, no noise) such a round's energy
        # can still fall 2.5x in a round that moves the normals 0.002 deg: unit scale stops at 1.57e-10 (MAEN
        # 0.00187 deg; a fifth round would give 6.2e-11 and 0.00189), the x1000 run at 6.6e-11 (x1000^2)
        assert 1 / 3 < r.energy[-1] / (ref.energy[-1] * s * s) < 3
        assert any("albedo scale" in w for w in r.warnings)
