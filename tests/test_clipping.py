"""Clipped observations at any level (gpps.host.clipping), against renders whose clipped set is known exactly.

Raw images clip at the sensor's full scale (gpps.render with ``bits`` clips at 1 and quantises); divided by the
lights' intensities the clipped observations sit at 1 / intensity (1.25 for the default lights), which no full-scale
rule knows.  The ground truth is the render itself: an observation is clipped when a channel of the raw image is at
1.0.  Checked here: the detection finds exactly those (8- and 16-bit, RGB and grey), finds nothing in unclipped
renders, in noise-free float renders or on a flat, uniformly lit plane at the image maximum, and gpps.reconstruct,
gpps.Reconstructor and solve_normals leave them out (issue 20's benchmark capture: 1.17 deg -> 0.016 deg) unless the
caller passes ``saturation=`` or ``valid=``; bad inputs raise as before.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

import gpps
from gpps import GppsWarning
from gpps.flows.photometric import solve_normals
from gpps.host.clipping import clipped_observations
from gpps.host.observations import gather_masked

from conftest import RENDER_DEVICE

CT = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
MATERIALS = {
    "cook-torrance": CT,
    "blinn-phong": gpps.Material("blinn-phong", ks=0.5, shininess=40.0),
    "lambertian": gpps.Material("lambertian", ks=0.0),
}
DETECTED = "left out as clipped"


def _render(scene, material, lights, *, exposure=None, gain=1.0, bits=16):
    """``(raw, images, lights)``: the raw render (clipped and quantised with ``bits``), the images divided by the
    intensities (float32) and the lights.  ``exposure``: the lights scaled so that the unclipped brightest value is
    ``exposure``; else the intensities times ``gain``."""
    if exposure is not None:
        top = float(gpps.render(scene, material, lights, device=RENDER_DEVICE)[:, scene.mask].max())
        gain = exposure / top
    lit = gpps.DirectionalLights(lights.directions, np.asarray(lights.intensities) * gain)
    raw = gpps.render(scene, material, lit, bits=bits, device=RENDER_DEVICE)
    img = (raw / np.asarray(lit.intensities)[:, None, None, :]).astype(np.float32)
    return raw, img, lit


def _detected(img, mask, **kw):
    """``(out, keep, info)``: the (N, H, W) bool observations the detection leaves out (all False when it finds
    nothing), and its own answer."""
    keep, info = clipped_observations(img, mask, **kw)
    out = np.zeros(img.shape[:3], bool) if keep is None else ~keep
    return out, keep, info


# ---------------------------------------------------------------------------------------- the detection itself


@pytest.mark.parametrize("grey", [False, True], ids=["rgb", "grey"])
@pytest.mark.parametrize("bits", [8, 16])
@pytest.mark.parametrize("gain", [1.0, 1.6, 2.5])
def test_detects_exactly_the_clipped_observations(bits, grey, gain):
    sc = gpps.make_scene("bumps", 64, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    raw, img, lit = _render(sc, CT, L, gain=gain, bits=bits)
    if grey:  # a mono sensor: one channel, divided by that channel's intensity
        raw, img = raw[..., 0], img[..., 0]
        truth = raw >= 1.0
    else:
        truth = (raw >= 1.0).any(axis=-1)
    truth &= sc.mask
    assert truth.sum() >= 100  # (the case clips: 2-4 % of the observations at the default intensities)
    got, keep, info = _detected(img, sc.mask)
    assert keep is not None and keep.shape == img.shape[:3] and keep.dtype == bool
    assert not got[:, ~sc.mask].any()  # never outside the mask
    assert not (got & ~truth).any()  # no false positive
    assert (got & truth).sum() / (got | truth).sum() >= 0.99
    assert info["observations"] == int(got.sum())
    assert info["clipped_images"] == [k for k in range(3) if got[k].any()]
    for k in info["clipped_images"]:  # the plateau's value: the clip level over the image's intensity
        im = info["images"][k]
        assert im["clipped"] and im["reason"] is None and im["observations"] == int(got[k].sum())
        assert im["value"] == pytest.approx(1.0 / float(lit.intensities[k][0]), rel=1e-6)


@pytest.mark.parametrize("bits", [8, 16, None])
@pytest.mark.parametrize("exposure", [0.5, 0.7, 0.9])
@pytest.mark.parametrize("scene, camera, material, n", [
    ("bumps", "perspective", "cook-torrance", 3), ("bumps", "orthographic", "blinn-phong", 3),
    ("bumps", "perspective", "lambertian", 8), ("sphere", "orthographic", "cook-torrance", 8),
    ("sphere", "perspective", "blinn-phong", 3)])
def test_unclipped_renders_have_no_plateau(scene, camera, material, n, exposure, bits):
    """Quantised (8- and 16-bit) and float renders whose brightest value is below the full scale: nothing taken."""
    sc = gpps.make_scene(scene, 64, camera)
    L = gpps.default_lights("directional", n, layout="ring" if n <= 4 else "spiral")
    raw, img, _ = _render(sc, MATERIALS[material], L, exposure=exposure, bits=bits)
    assert raw[:, sc.mask].max() < 1.0
    keep, info = clipped_observations(img, sc.mask)
    assert keep is None and info["observations"] == 0 and info["clipped_images"] == []


@pytest.mark.parametrize("gain", [1.0, 3.0])
def test_float_renders_have_no_plateau(gain):
    """Noise-free float renders (no clipping, no quantisation), also far above 1: no plateau of equal values."""
    for name, camera in (("bumps", "perspective"), ("sphere", "orthographic")):
        sc = gpps.make_scene(name, 64, camera)
        L = gpps.default_lights("directional", 3, layout="ring")
        for material in MATERIALS.values():
            raw, img, _ = _render(sc, material, L, gain=gain, bits=None)
            keep, _ = clipped_observations(img, sc.mask)
            assert keep is None, (name, material.brdf)


def _plane_and_bumps():
    """Bumps (albedo 0.3) with their top 24 rows replaced by a fronto-parallel plane of albedo 0.9: under
    directional lights the plane has one value in every image, the brightest of each image-channel."""
    sc = gpps.make_scene("bumps", 64, "orthographic")
    normals, albedo = sc.normals.copy(), np.where(sc.mask[..., None], np.float32(0.3), np.float32(0.0))
    albedo = np.repeat(albedo, 3, axis=-1)
    plane = sc.mask.copy()
    plane[24:] = False
    normals[plane] = (0.0, 0.0, 1.0)
    albedo[plane] = 0.9
    return dataclasses.replace(sc, normals=normals, albedo=albedo), plane


@pytest.mark.parametrize("bits", [8, 16, None])
def test_a_flat_plane_at_the_maximum_is_not_a_clip(bits):
    sc, plane = _plane_and_bumps()
    L = gpps.default_lights("directional", 3, layout="ring")
    raw, img, _ = _render(sc, MATERIALS["lambertian"], L, bits=bits)
    assert raw[:, sc.mask].max() < 1.0
    for k in range(3):  # (the plane is the plateau at every image-channel's maximum: a pile-up, not a clip)
        top = img[k][sc.mask].max(axis=0)
        np.testing.assert_array_equal(img[k][plane], np.broadcast_to(top, (int(plane.sum()), 3)))
    keep, info = clipped_observations(img, sc.mask)
    assert keep is None
    assert all("flat" in ch["reason"] for im in info["images"] for ch in im["channels"])


def test_valid_observations_alone_count():
    """``valid``: observations out of use take no part, and stay out of the result."""
    sc = gpps.make_scene("bumps", 64, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    raw, img, _ = _render(sc, CT, L)
    truth = (raw >= 1.0).any(-1) & sc.mask
    valid = np.ones(img.shape[:3], bool)
    valid[0] = ~truth[0]  # the plateau of image 1 already out of use: nothing left to find there
    valid[1, :8] = False
    keep, info = clipped_observations(img, sc.mask, valid=valid)
    assert info["clipped_images"] == [1, 2] and not info["images"][0]["clipped"]
    np.testing.assert_array_equal(keep, valid & ~truth)
    # the observations gathered by the caller (gpps.flows.reconstruction._prepare): the same result, theirs untouched
    idx = np.flatnonzero(sc.mask)
    x = gather_masked(img, idx)
    before = x.copy()
    for v in (valid, None):
        k2, i2 = clipped_observations(img, sc.mask, valid=v, gathered=(idx, x))
        k1, i1 = clipped_observations(img, sc.mask, valid=v)
        np.testing.assert_array_equal(k2, k1)
        assert i2 == i1
    np.testing.assert_array_equal(x, before)
    with pytest.raises(ValueError, match="gathered"):
        clipped_observations(img, sc.mask, gathered=(idx[1:], x))


def test_no_mask_pixels_or_black_images():
    img = np.zeros((3, 16, 16, 3), np.float32)
    mask = np.ones((16, 16), bool)
    keep, info = clipped_observations(img, mask)
    assert keep is None and {ch["reason"] for im in info["images"] for ch in im["channels"]} == {"black"}
    keep, info = clipped_observations(img[..., 0] + 1.0, np.zeros((16, 16), bool))
    assert keep is None and info["observations"] == 0


def _levels_below_rule(rows, plateau_lo, count, levels):
    """gpps.host.clipping._levels_below as the rule reads, two passes over the whole rows a level (the clipping
    module's form before session 38)."""
    from gpps.host.clipping import _TOL

    m = rows.shape[0]
    values = np.full((m, levels), -np.inf)
    counts = np.zeros((m, levels), np.int64)
    lo, above = plateau_lo, count
    for i in range(levels):
        v = np.max(rows, axis=-1, where=rows < lo[:, None], initial=-np.inf)  # (M,) the next lower value
        if not np.isfinite(v).any():
            break
        lo = v - np.abs(v) * rows.dtype.type(_TOL)
        at_or_above = np.count_nonzero(rows >= lo[:, None], axis=-1)
        values[:, i] = v
        counts[:, i] = np.where(np.isfinite(v), at_or_above - above, 0)
        above = at_or_above
    return values, counts


@pytest.mark.parametrize("levels_of", ["8-bit", "16-bit", "float", "few", "ties"])
def test_levels_below_equal_the_rule(levels_of, monkeypatch):
    """The pile-up's levels from the rows' largest values (np.partition, more when they do not hold the levels)
    equal the rule level by level over whole rows: 8- and 16-bit quantised data, float data, rows with fewer levels
    than asked, out-of-use (-inf) values and a plateau with exact ties at its edge; with the default first selection
    and with one of a single value beyond the plateau (every row then needs the larger selections)."""
    from gpps.host import clipping
    from gpps.host.clipping import _TOL, _levels_below

    rng = np.random.default_rng(7)
    p = 5000
    rows = {
        "8-bit": np.round(rng.beta(5, 2, (6, p)) * 255) / 255 * 1.25,
        "16-bit": np.round(rng.beta(5, 2, (6, p)) * 65535) / 65535 * 1.25,
        "float": rng.random((6, p)).astype(np.float32),
        "few": np.where(rng.random((6, p)) < 0.5, 1.0, np.where(rng.random((6, p)) < 0.5, 0.5, -np.inf)),
        "ties": np.round(rng.random((6, p)) * 40) / 40,
    }[levels_of]
    rows[:, :700] = rows.max()  # a plateau piled up at the maximum (more than the first selection's margin)
    rows[1, 900:1400] = -np.inf  # out of use
    rows[2] = -np.inf
    rows[2, :3] = (1.0, 0.5, 0.25)
    top = rows.max(axis=-1)
    lo = top - np.abs(top) * rows.dtype.type(_TOL)
    count = np.count_nonzero(rows >= lo[:, None], axis=-1)
    for margin in (clipping._TOP_MARGIN, 1):
        monkeypatch.setattr(clipping, "_TOP_MARGIN", margin)
        for levels in (1, 4, 9):
            got, want = _levels_below(rows, lo, count, levels), _levels_below_rule(rows, lo, count, levels)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
            assert got[1].sum() > 0


def test_largest_equals_a_partition():
    """``_largest`` (a sampled threshold, then a sort of what passes it) returns a full partition's k largest values,
    sorted, on uniform, quantised (ties), sorted and partly out-of-use rows, including dense tops the sample
    misses (the partition then runs)."""
    from gpps.host.clipping import _largest

    rng = np.random.default_rng(3)
    for trial in range(600):
        p = int(rng.integers(1, 6000))
        k = int(rng.integers(1, p + 1))
        row = {0: lambda: rng.random(p),
               1: lambda: np.round(rng.random(p) * int(rng.integers(1, 50))),
               2: lambda: np.sort(rng.random(p)),
               3: lambda: np.where(rng.random(p) < 0.3, -np.inf, rng.random(p))}[trial % 4]().astype(np.float32)
        if trial % 7 == 0:
            row[rng.integers(0, p, max(1, p // 5))] = row.max()  # a tie-heavy top
        want = np.sort(row) if k >= p else np.sort(np.partition(row, p - k)[p - k:])
        np.testing.assert_array_equal(_largest(row, k), want)


# ---------------------------------------------------------------------------------------------- in the flows


@pytest.fixture(scope="module")
def issue20():
    """Issue 20's benchmark capture at 64^2 (perf/_common.py reconstruct_inputs): 16-bit, divided by the
    intensities, 2-4 % of the observations clipped at 1.25."""
    sc = gpps.make_scene("bumps", 64, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    raw = gpps.render(sc, CT, L, bits=16, device=RENDER_DEVICE)
    img = raw / L.intensities[:, None, None, :]
    return sc, gpps.DirectionalLights(L.directions), img, ~(raw >= 1.0).any(-1)


def _maen(normals, sc):
    return float(gpps.normal_errors(normals, sc.normals, sc.mask)["mean"])


def _quiet_detection(monkeypatch):
    """Make the detection fail loudly should it run."""
    import gpps.flows.photometric as ph

    def boom(*a, **k):
        raise AssertionError("the clipping detection ran")
    monkeypatch.setattr(ph, "clipped_observations", boom)


def test_reconstruct_leaves_clipped_observations_out(issue20, device, monkeypatch):
    sc, lights, img, truth_valid = issue20
    kw = dict(camera=sc.camera, material="cook-torrance", device=device)
    with pytest.warns(GppsWarning, match=r"213 observations \(2\.6%\) in images \[1, 2, 3\] sat on a plateau of "
                                         r"one value at the image's maximum \(1\.25, 1\.25, 1\.25\) and were left "
                                         r"out as clipped"):
        rec = gpps.reconstruct(img, sc.mask, lights, **kw)
    assert _maen(rec.normals, sc) < 0.1  # (1.17 deg with the clipped observations in the fit)
    assert rec.estimated["ks"] == pytest.approx(0.8, rel=0.02)
    assert rec.estimated["roughness"] == pytest.approx(0.2, rel=0.02)
    assert sum(DETECTED in w for w in rec.warnings) == 1
    assert not any("Pass saturation" in w for w in rec.warnings)

    # the caller decides: valid= (here the detected set itself, so the same result) or saturation=; no detection
    _quiet_detection(monkeypatch)
    keep = truth_valid | ~sc.mask[None]
    with warnings.catch_warnings():
        warnings.simplefilter("error", GppsWarning)
        explicit = gpps.reconstruct(img, sc.mask, lights, valid=keep, **kw)
    np.testing.assert_array_equal(explicit.normals, rec.normals)
    np.testing.assert_array_equal(explicit.albedo, rec.albedo)
    assert explicit.estimated == rec.estimated
    assert not any(DETECTED in w for w in explicit.warnings)
    sat = gpps.reconstruct(img, sc.mask, lights, saturation=1.2, **kw)
    assert not any(DETECTED in w for w in sat.warnings)
    assert _maen(sat.normals, sc) < 0.1


def test_reconstructor_leaves_clipped_observations_out(issue20, device):
    sc, lights, img, _ = issue20
    kw = dict(camera=sc.camera, material="cook-torrance", device=device)
    with pytest.warns(GppsWarning, match=DETECTED):
        fresh = gpps.reconstruct(img, sc.mask, lights, **kw)
    with gpps.Reconstructor(sc.mask, lights, **kw) as rc:
        with pytest.warns(GppsWarning, match=DETECTED):
            kept = rc(img)
    np.testing.assert_array_equal(kept.normals, fresh.normals)
    assert kept.warnings == fresh.warnings
    assert _maen(kept.normals, sc) < 0.1


def test_solve_normals_leaves_clipped_observations_out(issue20, device, monkeypatch):
    sc, lights, img, truth_valid = issue20
    kw = dict(camera=sc.camera, material=CT, device=device)
    with pytest.warns(GppsWarning, match=DETECTED):
        res = solve_normals(img, sc.mask, lights, **kw)
    assert _maen(res.normals, sc) < 0.05
    assert not (res.weights[~truth_valid & sc.mask[None]] > 0).any()  # (dropped: weight 0)
    _quiet_detection(monkeypatch)
    keep = truth_valid | ~sc.mask[None]
    explicit = solve_normals(img, sc.mask, lights, valid=keep, **kw)
    np.testing.assert_array_equal(explicit.normals, res.normals)
    assert not any(DETECTED in w for w in explicit.warnings)
    inside = solve_normals(img, sc.mask, lights, valid=np.ones(img.shape[:3], bool), **kw)  # the caller's choice
    assert _maen(inside.normals, sc) > 10 * _maen(res.normals, sc)  # (0.19 deg against 0.005 with them out)
    assert not any(DETECTED in w for w in inside.warnings)
    sat = solve_normals(img, sc.mask, lights, saturation=1.2, **kw)
    assert not any(DETECTED in w for w in sat.warnings)


def test_tiled_prepare_leaves_them_out_as_solve_normals(issue20):
    """The tiled flow's frame-wide part (gpps.flows.tiled.prepare) leaves out what solve_normals leaves out: float
    input's clipping plateaus as the tiles' valid flags, uint16 input's full scale as the tiles' saturation."""
    from gpps.flows import tiled
    from gpps.pipeline.solver import SolverConfig

    sc, lights, img, truth_valid = issue20
    cfg = SolverConfig()
    with pytest.warns(GppsWarning, match=DETECTED):
        prep = tiled.prepare(img, sc.mask, lights, camera=sc.camera, config=cfg)
    assert prep["has_valid"] and prep["config"].saturation is None
    n = img.shape[0]
    flags = np.moveaxis(prep["packed"][..., 3 * n + 3:4 * n + 3], 2, 0) > 0.5  # (pack: RGB, mask, row, column, valid)
    np.testing.assert_array_equal(flags & sc.mask[None], truth_valid & sc.mask[None])
    raw16 = np.round(np.clip(img * 0.8, 0, 1) * 65535).astype(np.uint16)  # the camera's frame (intensity 0.8)
    with warnings.catch_warnings():
        warnings.simplefilter("error", GppsWarning)  # (nothing detected on integer input: its full scale is known)
        prep16 = tiled.prepare(raw16, sc.mask, lights, camera=sc.camera, config=cfg)
    assert not prep16["has_valid"] and prep16["config"].saturation == 1.0
    given = tiled.prepare(raw16, sc.mask, lights, camera=sc.camera, config=dataclasses.replace(cfg, saturation=0.9))
    assert given["config"].saturation == 0.9


def test_full_scale_plateau_warns_once(device, monkeypatch):
    """Float images clipped at 1.0 (not divided): the detection leaves the plateau out and says so; the full-scale
    warning does not ask for saturation=1 as well.  uint16 images keep their rule (saturated at full scale)."""
    sc = gpps.make_scene("bumps", 48, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    raw, _, lit = _render(sc, CT, L, gain=1.4)
    share = float((raw >= 1.0).any(-1)[:, sc.mask].mean())
    assert share > 0.05  # (enough for check_observations' full-scale warning)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = solve_normals(raw, sc.mask, lit, camera=sc.camera, solver="none", device=device)
    messages = [str(w.message) for w in caught if issubclass(w.category, GppsWarning)]
    assert sum(DETECTED in m for m in messages) == 1 and not any("Pass saturation" in m for m in messages)
    assert messages == res.warnings
    _quiet_detection(monkeypatch)  # (integer images: saturated at their full scale, nothing to detect)
    ints = np.round(raw * 65535).astype(np.uint16)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        solve_normals(ints, sc.mask, lit, camera=sc.camera, solver="none", device=device)
        gpps.reconstruct(ints, sc.mask, lit, camera=sc.camera, material=CT, device=device,
                         config=gpps.RONConfig(rounds=1))
    assert not any(DETECTED in str(w.message) or "Pass saturation" in str(w.message) for w in caught)


def test_too_many_clipped_observations_is_the_usual_error(device):
    """Heavily clipped images: leaving the plateaus out leaves too few determined pixels; the error says so and
    names the way out."""
    sc = gpps.make_scene("sphere", 48, "orthographic")
    L = gpps.default_lights("directional", 3, layout="ring")
    raw, img, lit = _render(sc, MATERIALS["lambertian"], L, exposure=2.2)
    with pytest.raises(ValueError, match=r"images: only .*% of the mask pixels have 3 or more usable .*taken as "
                                         r"clipped and left out \(pass saturation= or valid= to decide\)"):
        with pytest.warns(GppsWarning, match=DETECTED):
            gpps.reconstruct(img, sc.mask, gpps.DirectionalLights(lit.directions), device=device)
    ok = solve_normals(img, sc.mask, gpps.DirectionalLights(lit.directions), valid=np.ones(img.shape[:3], bool),
                       solver="none", device=device)  # (the caller's valid: no detection, no error)
    assert ok.normals[sc.mask].any()


# ---------------------------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize("bad, error, match", [
    (lambda img: img * np.nan, ValueError, r"^images: expected finite values"),
    (lambda img: img - 2.0, ValueError, r"^images: expected values >= 0"),
    (lambda img: (img * 1000).astype(np.int32), TypeError, r"^images: expected uint8, uint16"),
    (lambda img: img[:2], ValueError, r"^images: expected at least 3 images"),
    (lambda img: np.zeros_like(img), ValueError, r"^images: every observation inside the mask is black"),
    (lambda img: np.ones_like(img), ValueError, r"images: 100% of the observations inside the mask are at 1, the "
                                                r"full scale: everything is saturated"),
    (lambda img: np.full_like(img, 1.25), ValueError, None),  # (a plateau everywhere: not a clip, see below)
])
def test_bad_inputs_raise_as_before(issue20, bad, error, match, device):
    sc, lights, img, _ = issue20
    arg = bad(np.asarray(img, np.float32))
    if match is None:  # one value everywhere is a valid (flat) capture: solved, nothing detected
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = solve_normals(arg, sc.mask, lights, solver="none", device=device)
        assert not any(DETECTED in str(w.message) for w in caught) and res.normals[sc.mask].any()
        return
    lights_n = lights if len(arg) == len(lights) else gpps.DirectionalLights(lights.directions[: len(arg)])
    with pytest.raises(error, match=match):
        solve_normals(arg, sc.mask, lights_n, solver="none", device=device)
    with pytest.raises(error, match=match):
        gpps.reconstruct(arg, sc.mask, lights_n, camera=sc.camera, device=device)


def test_bad_valid_and_saturation_raise_as_before(issue20, device):
    sc, lights, img, _ = issue20
    with pytest.raises(ValueError, match=r"^valid: expected shape \(3, 64, 64\)"):
        gpps.reconstruct(img, sc.mask, lights, valid=np.ones((3, 64, 63), bool), device=device)
    with pytest.raises(ValueError, match=r"^valid: expected finite values"):
        solve_normals(img, sc.mask, lights, valid=np.full((3, 64, 64), np.nan), device=device)
    with pytest.raises(TypeError, match=r"^saturation: "):
        gpps.reconstruct(img, sc.mask, lights, saturation="1", device=device)
    with pytest.raises(ValueError, match=r"^saturation: "):
        gpps.reconstruct(img, sc.mask, lights, saturation=0.0, device=device)
