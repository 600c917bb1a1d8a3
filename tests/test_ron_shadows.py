"""RON's cast-shadow pass (RONConfig.cast_shadows, gpps.pipeline.ron_shadows.RoundShadows), on every device.

The scene with cast shadows is tests/ron_shadow_scenes.py's Gaussian bump on a plane (64^2, 12-degree pinhole,
Blinn-Phong, noise 0.002): images rendered by gpps's renderer times the exact visibility of each light, found by a
3D march against the analytic height field (not by the depth-map march under test).  Measured on the CPU
(perf/ron_shadows.py has the table): with 12 lights the MAEN over the pixels with a cast shadow falls from 1.86 to
0.17 deg (directional) and from 1.45 to 0.13 deg (point); the observations dropped match the analytic cast shadows
with IoU 0.92 / 0.95 at RON's default tolerance of 0.5 pixel widths (0.84 / 0.86 at the stage's default 1).
"""

import numpy as np
import pytest
from ron_shadow_scenes import bump_case, solid_case
from shadow_reference import box_scene, iou, perspective

from gpps.flows.ron import RON, RONConfig
from gpps.host.metrics import normal_errors
from gpps.lights import DirectionalLights
from gpps.material import Material
from gpps.names import FLAG_FEW_OBSERVATIONS
from gpps.pipeline.ron_shadows import RoundShadows
from gpps.pipeline.shadows import ShadowConfig
from gpps.pipeline.solver import PixelSolver, SolverConfig

BUMP = ((0.25, 0.0, 0.0, 0.09),)
_CASES = {}


def _case(kind, n):
    key = (kind, n)
    if key not in _CASES:
        c = bump_case(kind, n, 64, bumps=BUMP, slant=70.0)
        c["facing"] = c["scene"].facing(c["lights"])
        _CASES[key] = c
    return _CASES[key]


def _ron(device, case, **cfg):
    n = len(case["lights"])
    ron = RON((n,) + case["mask"].shape, case["camera"], case["lights"], case["material"], case["mask"],
              RONConfig(**cfg), device=device)
    try:
        ref = case["reference_depth"] if case["lights"].__class__.__name__ == "PointLights" else None
        return ron.run(case["images"], reference_depth=ref, valid=case.get("valid"))
    finally:
        ron.close()


def _maen(res, case, where):
    return normal_errors(res.normals, case["normals"], where)["mean"]


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_cast_shadows_lower_the_error_where_shadowed(device, kind):
    """12 lights: the pass cuts the MAEN on the shadowed pixels to under a third (1.86 -> 0.17 directional,
    1.45 -> 0.13 point measured; 0.37 / 0.30 at tolerance 1) and lowers it over the whole mask (0.49 -> 0.07,
    0.50 -> 0.07); the dropped observations are the analytic cast shadows (IoU 0.92 / 0.95 measured at the
    default tolerance of 0.5 pixel widths, 0.84 / 0.86 at 1)."""
    case = _case(kind, 12)
    where = case["shadow"].any(0)
    off = _ron(device, case, cast_shadows=False)
    on = _ron(device, case, cast_shadows=True)
    loose = _ron(device, case, cast_shadows=True, shadow_config=ShadowConfig(tolerance_px=1.0))
    e_off, e_on, e_loose = _maen(off, case, where), _maen(on, case, where), _maen(loose, case, where)
    print(f"\n{kind}: shadowed-pixel MAEN off {e_off:.3f} on {e_on:.3f} tau 1 {e_loose:.3f}; whole "
          f"{_maen(off, case, case['mask']):.3f} / {_maen(on, case, case['mask']):.3f}")
    assert off.shadows == [] and off.shadowed is None and off.timings["shadows"] == 0.0
    assert e_off > 1.2 and e_on < e_off / 3 and e_loose < 0.5 * e_off
    assert _maen(on, case, case["mask"]) < 0.5 * _maen(off, case, case["mask"])
    assert on.timings["shadows"] > 0.0 and len(on.shadows) == on.rounds - 1
    assert on.shadows[-1]["dropped"] == int(on.shadowed.sum()) and on.shadows[-1]["few_pixels"] == 0
    cast = case["shadow"]
    j_on, j_loose = iou(cast, on.shadowed & case["facing"]), iou(cast, loose.shadowed & case["facing"])
    print(f"  IoU of the dropped cast shadows: default (tau 0.5) {j_on:.3f}, tau 1 {j_loose:.3f}")
    assert j_on >= 0.9 and j_loose >= 0.8


def test_no_change_without_cast_shadows(device):
    """A scene without cast shadows (the bump lit from near the view axis: slants up to 25 degrees) keeps its
    MAEN within 0.01 deg with the pass (it only drops attached-shadow observations near the terminator)."""
    case = bump_case("directional", 12, 64, bumps=BUMP, slant=25.0)
    assert not case["shadow"].any()
    off = _ron(device, case, cast_shadows=False)
    on = _ron(device, case, cast_shadows=True)
    e_off, e_on = _maen(off, case, case["mask"]), _maen(on, case, case["mask"])
    print(f"\nno cast shadows: MAEN off {e_off:.4f} on {e_on:.4f}")
    assert abs(e_on - e_off) < 0.01
    # 3 lights: every pixel the march shadows would keep its observations (shadow_few="keep"), so there is no
    # pass: a known material under directional lights stays one round, equal to the run without the pass
    case = bump_case("directional", 3, 64, bumps=BUMP, slant=25.0)
    off = _ron(device, case, cast_shadows=False)
    on = _ron(device, case, cast_shadows=True)
    assert on.rounds == off.rounds == 1 and on.converged and on.shadows == [] and on.shadowed is None
    np.testing.assert_array_equal(on.normals, off.normals)


@pytest.mark.parametrize("scene", ["bump-perspective-point", "hemisphere-orthographic-directional"])
def test_host_and_device_rounds_give_the_same_masks(device, scene, monkeypatch):
    """The device rounds (the depth integrated and marched on the device) and the host rounds (integrated on
    the host, uploaded) drop the same observations but at most 0.05 % of them (float32 integration order);
    measured: none differ.  Both cameras: the orthographic directional case integrates the rounds' depth at
    RON's stand-in mean depth (no reference depth given)."""
    if scene.startswith("bump"):
        case = _case("point", 12)
    else:
        case = solid_case("hemisphere", "directional", 12, 64, camera="orthographic")
    uploads = []
    orig = RoundShadows.upload
    monkeypatch.setattr(RoundShadows, "upload", lambda self, depth: (uploads.append(1), orig(self, depth))[1])
    dev = _ron(device, case, cast_shadows=True, device_rounds=True)
    # the device rounds march their own depth buffer; only round 1 may run on the host (the DGMC front's
    # merge is there) and upload its depth
    assert len(uploads) <= 1 < len(dev.shadows)
    uploads.clear()
    host = _ron(device, case, cast_shadows=True, device_rounds=False)
    assert len(uploads) == len(host.shadows)
    diff = np.count_nonzero(dev.shadowed != host.shadowed)
    print(f"\nhost/device rounds: {diff} of {dev.shadowed.size} differ; dropped {[s['dropped'] for s in dev.shadows]} / "
          f"{[s['dropped'] for s in host.shadows]}")
    assert dev.shadowed.sum() > 1000
    assert diff <= 5e-4 * dev.shadowed.size
    assert dev.rounds == host.rounds


def test_recomputed_not_accumulated(device):
    """Each pass starts from the original observations: a box's shadows, then a flat depth (no shadows) gives
    back every observation but those the caller marked invalid; the caller's invalid ones stay invalid."""
    wp_dev = device
    cam = perspective(300.0, (64, 64))
    sc = box_scene(cam, shape=(64, 64), plane_depth=300.0, box=(-12.0, 8.0, -8.0, 10.0, 20.0))
    d = np.array([[0.6, 0.3, 0.74], [-0.5, 0.5, 0.71], [0.1, -0.7, 0.71], [0.0, 0.0, 1.0]])
    lights = DirectionalLights(d / np.linalg.norm(d, axis=1, keepdims=True))
    n = len(lights)
    solver = PixelSolver((n, 64, 64), cam, lights, Material.default_for("lambertian"), SolverConfig(solver="none"),
                         device=wp_dev)
    valid0 = np.ones((n, 64, 64), bool)
    valid0[1, :, :8] = False
    try:
        solver.upload(np.full((n, 64, 64, 3), 0.5, np.float32), sc.mask, depth=sc.depth, valid=valid0)
        # the round's normals (the pass drops an observation only where the surface faces the light)
        solver.normals.assign(np.ascontiguousarray(sc.normals, np.float32))
        with pytest.raises(ValueError, match="few"):
            RoundShadows(solver, sc.mask, few="drop")
        with pytest.raises(ValueError, match="mask"):
            RoundShadows(solver, sc.mask[:, :10])
        with RoundShadows(solver, sc.mask, few="flag") as rs:
            rs.capture()
            rs.upload(sc.depth)
            rs.step()
            first = rs.fetch()
            v1 = solver.valid.numpy().astype(bool)
            assert first["dropped"] > 200 and np.array_equal(v1, valid0 & ~rs.shadowed())
            assert np.array_equal(rs.shadowed(), valid0 & ~v1)
            rs.upload(np.full((64, 64), 300.0))
            rs.step()
            assert rs.fetch()["dropped"] == 0
            assert np.array_equal(solver.valid.numpy().astype(bool), valid0)
            rs.upload(sc.depth)  # the same shadows again, not fewer or more
            rs.step()
            assert rs.fetch() == first and np.array_equal(solver.valid.numpy().astype(bool), v1)
            rs.restore()
            assert np.array_equal(solver.valid.numpy().astype(bool), valid0)
        with RoundShadows(solver, sc.mask, few="keep") as rs:  # the same pass, keeping pixels left below 3
            rs.capture()
            rs.upload(sc.depth)
            rs.step()
            got = rs.fetch()
            v2 = solver.valid.numpy().astype(bool)
            lost = valid0 & ~v1  # flag's drops
            below = lost.any(0) & (v1.sum(0) < 3)
            assert got["kept_pixels"] == int(below.sum()) and got["few_pixels"] == 0
            assert got["dropped"] == int(lost[:, ~below].sum())
            assert np.array_equal(v2[:, below], valid0[:, below]) and np.array_equal(v2[:, ~below], v1[:, ~below])
    finally:
        solver.close()


def test_few_observations_rule(device):
    """3 lights: every shadowed pixel would keep 2 observations.  ``shadow_few="keep"`` could drop nothing, so
    RON runs no pass (as without cast_shadows); 4 lights: pixels shadowed by two lights keep their 4 (counted),
    the others lose theirs; ``"flag"`` drops the shadowed one and the solver flags each such pixel
    FLAG_FEW_OBSERVATIONS (never silently under-determined)."""
    case = _case("directional", 3)
    keep = _ron(device, case, cast_shadows=True, shadow_few="keep")
    assert keep.shadows == [] and keep.shadowed is None
    four = _ron(device, _case("directional", 4), cast_shadows=True, shadow_few="keep")
    assert all(s["few_pixels"] == 0 for s in four.shadows) and max(s["dropped"] for s in four.shadows) > 0
    assert np.all(four.shadowed.sum(0) <= 1)  # (4 images: a pixel may lose one and keep 3)
    flag = _ron(device, case, cast_shadows=True, shadow_few="flag")
    last = flag.shadows[-1]
    few = flag.shadowed.any(0)
    assert last["few_pixels"] == int(few.sum()) > 50 and last["kept_pixels"] == 0
    assert np.all(flag.flags[few] & FLAG_FEW_OBSERVATIONS)


def test_no_pass_without_integration(device):
    """``integrate=False``: no depth, no pass (the default cast_shadows=True does not make it an error)."""
    case = _case("directional", 12)
    res = _ron(device, case, integrate=False)
    assert res.shadows == [] and res.shadowed is None and res.rounds == 1 and res.depth is None


def test_caller_valid_is_the_original(device):
    """Observations the caller marked invalid stay out and are not counted as dropped by the shadows."""
    case = dict(_case("directional", 12))
    valid = np.ones(case["images"].shape[:3], bool)
    valid[:, :, :20] = False
    case["valid"] = valid
    res = _ron(device, case, cast_shadows=True)
    assert res.shadowed.sum() > 100 and not (res.shadowed & ~valid).any()


def test_material_fit_sample_leaves_the_shadows_out(device, monkeypatch):
    """With estimated parameters the fit's sample is uploaded with each pass's observations: the first fit
    (after round 1's pass) already without the shadowed ones.  Measured (true ks 0.4, shininess 40): with the
    pass 0.400 / 40.00, without it 0.389 / 35.8 (directional; point 0.398 / 36.9)."""
    from gpps.pipeline.material import MaterialScorer

    case = _case("directional", 12)
    seen = []
    orig = MaterialScorer.upload

    def spy(self, images, sample, **kw):
        seen.append(None if kw.get("valid") is None else np.asarray(kw["valid"], bool).copy())
        return orig(self, images, sample, **kw)

    monkeypatch.setattr(MaterialScorer, "upload", spy)
    res = _ron(device, case, estimate=("ks", "shininess"), cast_shadows=True)
    assert seen and all(v is not None for v in seen) and len(res.shadows) >= 2
    first = res.shadows[0]["dropped"]
    assert first > 1000 and int((~seen[0]).sum()) == first
    monkeypatch.setattr(MaterialScorer, "upload", orig)
    off = _ron(device, case, estimate=("ks", "shininess"), cast_shadows=False)
    print(f"\nks, shininess with the pass {res.estimated}, without {off.estimated}; {len(seen)} sample uploads")
    assert res.estimated["shininess"] == pytest.approx(40.0, rel=0.01)
    assert res.estimated["ks"] == pytest.approx(0.4, rel=0.01)
    assert abs(off.estimated["shininess"] - 40.0) > 2.0


def test_bad_config_names_the_argument():
    with pytest.raises(TypeError, match="cast_shadows"):
        RONConfig(cast_shadows=1)
    with pytest.raises(TypeError, match="shadow_config"):
        RONConfig(shadow_config={"tolerance_px": 1.0})
    with pytest.raises(ValueError, match="shadow_few"):
        RONConfig(shadow_few="drop")
    with pytest.raises(ValueError, match="tolerance_px"):
        RONConfig(shadow_config=ShadowConfig(tolerance_px=-1.0))
