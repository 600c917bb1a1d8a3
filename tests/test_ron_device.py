"""RON's rounds on the device (gpps.pipeline.ron_rounds, gpps.pipeline.integration_rounds) against the host
rounds they replace: the integrator's system assembled and solved on the device against the host
Integrator, the round scalars against the host formulas, whole point-light reconstructions against
``RONConfig(device_rounds=False)``, and a count of host<->device copies per round.
"""

import numpy as np
import pytest

from gpps._runtime import warp
from gpps._taichi import taichi_device
from gpps.flows.ron import RON, RONConfig, normal_change_deg
from gpps.host.poisson import level_shapes
from gpps.flows.synthetic import default_lights, render
from gpps.host.metrics import angular_error
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.integration import Integrator, IntegratorConfig
from gpps.pipeline.integration_rounds import DeviceSystem
from gpps.pipeline.ron_rounds import DeviceRounds
from gpps.pipeline.solver import PixelSolver

MAT = Material("blinn-phong", ks=0.7, shininess=60.0)


def _views(device, normals, out):
    """Warp arrays of ``normals`` and ``out`` on ``device`` and the views DeviceSystem reads (as DeviceRounds)."""
    wp = warp()
    n = wp.array(normals, dtype=wp.vec3, device=device)
    o = wp.array(out, dtype=wp.float32, device=device)
    if device.startswith("cuda"):
        pytest.importorskip("torch")
        return n, o, wp.to_torch(n), wp.to_torch(o)
    return n, o, n.numpy(), o.numpy()


def _host_round_depth(integ, normals, ref):
    """The host rounds' depth: Integrator.run, then RON's _fill_depth, then the solver's 1.0 outside the mask."""
    r = integ.run(normals, reference_depth=ref)
    fill = float(np.mean(r.depth[r.mask]))
    d = np.where(r.mask & (r.depth > 0), r.depth, fill)
    return np.where(integ.mask, d, 1.0).astype(np.float32), r.iterations


@pytest.mark.parametrize("camera,weighting", [("perspective", "normal"), ("orthographic", "uniform")])
def test_device_system_matches_host_integrator(camera, weighting, device):
    """Same system, same multigrid-preconditioned CG (equal iteration counts), depth within 1e-5 of its range
    (both solve to a relative residual of 1e-5 in float32; the assembly orders its float64 sums differently)."""
    sc = make_scene("sphere", 64, camera)
    ref = float(sc.depth[sc.mask].mean())
    rng = np.random.default_rng(1)
    n = sc.normals + 0.03 * rng.standard_normal(sc.normals.shape)  # (some rim normals turn back-facing)
    n = (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)
    n[~sc.mask] = 0.0
    integ = Integrator(sc.mask, camera=sc.camera, config=IntegratorConfig(tol=1e-5, weighting=weighting),
                       device=taichi_device(device))
    try:
        host, its = _host_round_depth(integ, n, ref)
        n_bad = integ.fetch().n_invalid
        ds = DeviceSystem(integ)
        wn, wo, vn, vo = _views(device, n, np.zeros(sc.mask.shape, np.float32))
        assert ds.step(vn, vo, reference_depth=ref)
        got = ds.fetch()
        dev = wo.numpy()
        m = sc.mask
        span = float(host[m].max() - host[m].min())
        assert np.abs(dev - host)[m].max() <= 1e-5 * span + 1e-6 * ref, np.abs(dev - host)[m].max() / span
        assert np.all(dev[~m] == 1.0)
        assert got["invalid"] == n_bad and abs(got["iterations"] - its) <= 1 and got["residual"] <= 1e-5
        assert got["fill"] == pytest.approx(float(np.mean(host[m])), rel=1e-6)
        # the host path after a device solve rebuilds its own levels (shared fields)
        again, its2 = _host_round_depth(integ, n, ref)
        np.testing.assert_array_equal(again, host)
        # invalid normals (back-facing, NaN, zero) cutting the object in two: dropped, the two parts integrated
        # as separate components (labelled on the device), the dropped pixels filled, as on the host
        bad = n.copy()
        rows = np.flatnonzero(m.any(1))
        mid = rows[len(rows) // 2]
        bad[mid] = -bad[mid]
        bad[mid, ::3] = np.nan
        bad[mid, 1::3] = 0.0
        host2, _ = _host_round_depth(integ, bad, ref)
        assert integ.fetch().n_components >= 2
        wn.assign(bad)
        assert ds.step(vn, vo, reference_depth=ref)
        got = ds.fetch()
        assert got["invalid"] == integ.fetch().n_invalid >= int(m[mid].sum())
        dev = wo.numpy()
        span = float(host2[m].max() - host2[m].min())
        assert np.abs(dev - host2)[m].max() <= 1e-5 * span + 1e-6 * ref
        # fewer than 2 valid normals: nothing written, the host path raises its error
        wn.assign(np.full_like(n, np.nan))
        wo.fill_(-7.0)
        assert not ds.step(vn, vo, reference_depth=ref)
        assert np.all(wo.numpy() == -7.0)
        ds.close()
    finally:
        integ.close()


def test_device_round_sums_equal_host_formulas(device):
    """Energy (mean squared residual over the mask) and mean normal change (degrees, zero vectors 90) of
    DeviceRounds equal RON's host formulas to float64 rounding; prev becomes the solver's normals."""
    wp = warp()
    h, w = 24, 31
    sc = make_scene("sphere", 32, "perspective")
    lights = default_lights("point", 3)
    s = PixelSolver((3, h, w), sc.camera, PointLights(lights.positions), MAT, device=device)
    rng = np.random.default_rng(2)
    mask = rng.random((h, w)) < 0.7
    a = rng.standard_normal((h, w, 3)).astype(np.float32)
    b = a + 1e-3 * rng.standard_normal((h, w, 3)).astype(np.float32)  # small angles: where arccos(float32) fails
    b[3, :5] = 0.0
    res = rng.random((h, w)).astype(np.float32)
    s.normals.assign(a)
    s.residual.assign(res)
    dr = DeviceRounds(s, mask)
    dr.upload(b)
    dr.step()
    got = dr.fetch()
    assert got["energy"] == pytest.approx(float(np.mean(res[mask].astype(np.float64) ** 2)), rel=1e-12)
    assert got["change_deg"] == pytest.approx(normal_change_deg(a, b, mask), rel=1e-12)
    np.testing.assert_array_equal(dr.prev.numpy(), a)
    # the host formula itself: exact small angles (float32 arccos reads them as 0 or ~0.02 deg)
    u = np.array([[[0.0, 0.0, 1.0]]], np.float32)
    t = 1e-4
    v = np.array([[[np.sin(t), 0.0, np.cos(t)]]], np.float32)
    assert normal_change_deg(v, u, np.ones((1, 1), bool)) == pytest.approx(np.degrees(t), rel=1e-3)
    dr.close()
    with pytest.raises(ValueError, match="integrator"):
        dr.integrate(1.0)
    with pytest.raises(ValueError, match="depth"):
        s.set_depth_device(wp.zeros((h, w + 1), dtype=wp.float32, device=device))


def _scene(camera, size):
    sc = make_scene("sphere", size, camera)
    L = default_lights("point", 3)
    raw = render(sc, MAT, L, bits=16, noise=0.0)
    img = raw / np.asarray(L.intensities, np.float32)[:, None, None, :]
    return img, PointLights(L.positions), sc, float(sc.depth[sc.mask].mean())


def _run(img, lights, sc, ref, device, *, device_rounds, rounds):
    cfg = RONConfig(rounds=rounds, tol=0.0, tol_normals_deg=0.0, device_rounds=device_rounds)
    ron = RON(img.shape[:3], sc.camera, lights, MAT, sc.mask, cfg, device=device)
    try:
        return ron.run(img, reference_depth=ref)
    finally:
        ron.close()


@pytest.mark.parametrize("camera", ["perspective", "orthographic"])
def test_device_rounds_match_host_rounds(camera, device, monkeypatch):
    """Point lights, known material, 4 rounds.  Each device round's depth (as handed to the solver) within
    2e-5 of its range of the host rounds' integration of the same round's normals (RON's integrator and
    _fill_depth; both solve to a relative residual of 1e-5 in float32).  Against a whole host run (whose
    rounds see their own depths: the difference feeds back through the lights): depths within 5e-4 of the
    range, round 1's energy and change equal to float64 rounding (same normals), later ones within 1e-4
    relative / 1e-3 degrees, the final normals within 0.05 degrees (0.005 on average)."""
    img, lights, sc, ref = _scene(camera, 64)
    m = sc.mask
    got = {"host": [], "device": []}
    key = ["host"]
    set_depth, set_dev, integrate = PixelSolver.set_depth, PixelSolver.set_depth_device, DeviceRounds.integrate
    wt = "normal" if sc.camera.is_perspective else "uniform"
    ref_integ = Integrator(m, camera=sc.camera, config=IntegratorConfig(tol=1e-5, weighting=wt),
                           device=taichi_device(device))
    same = []

    def spy_host(self, depth, mask=None):
        got[key[0]].append(np.where(m, np.asarray(depth, np.float32), 1.0))
        return set_depth(self, depth, mask)

    def spy_dev(self, depth):
        got[key[0]].append(np.array(depth.numpy()))
        return set_dev(self, depth)

    def spy_integrate(self, reference_depth, **kw):
        want, _ = _host_round_depth(ref_integ, self.solver.normals.numpy().copy(), reference_depth)
        ok = integrate(self, reference_depth, **kw)
        assert ok
        dev = self.depth.numpy()
        same.append(np.abs(dev - want)[m].max() / float(want[m].max() - want[m].min()))
        np.testing.assert_array_equal(dev[~m], want[~m])
        return ok

    monkeypatch.setattr(PixelSolver, "set_depth", spy_host)
    monkeypatch.setattr(PixelSolver, "set_depth_device", spy_dev)
    monkeypatch.setattr(DeviceRounds, "integrate", spy_integrate)
    try:
        h = _run(img, lights, sc, ref, device, device_rounds=False, rounds=4)
        key[0] = "device"
        d = _run(img, lights, sc, ref, device, device_rounds=True, rounds=4)
    finally:
        ref_integ.close()
    # rounds 1-3 integrate (not the last): 3 depths handed to the solver; the device run's final depth
    # is integrated on the device too (a 4th integrate, not handed to the solver)
    assert len(got["host"]) == len(got["device"]) == 3 and len(same) == 4
    assert max(same) <= 2e-5, same
    for a, b in zip(got["host"], got["device"]):
        span = float(a[m].max() - a[m].min())
        assert np.abs(a - b)[m].max() <= 5e-4 * span, np.abs(a - b)[m].max() / span
        np.testing.assert_array_equal(a[~m], b[~m])
    assert d.energy[0] == pytest.approx(h.energy[0], rel=1e-12)
    assert d.normal_change_deg[0] == pytest.approx(h.normal_change_deg[0], rel=1e-12)
    # (an absolute floor of 1e-6 of round 1's energy: once the fit is exact the energy is float32 rounding of the
    # depth fed to the point lights, 7e-12 against 8e-8 in the orthographic case, where 1e-4 relative is noise)
    np.testing.assert_allclose(d.energy, h.energy, rtol=1e-4, atol=1e-6 * h.energy[0])
    np.testing.assert_allclose(d.normal_change_deg, h.normal_change_deg, atol=1e-3)
    a, b = h.normals[m].astype(np.float64), d.normals[m].astype(np.float64)
    ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))
    assert ang.max() <= 0.05 and ang.mean() <= 0.005, (ang.max(), ang.mean())
    e_h = angular_error(h.normals, sc.normals, m)[m].mean()
    e_d = angular_error(d.normals, sc.normals, m)[m].mean()
    assert abs(e_h - e_d) <= 1e-3, (e_h, e_d)
    np.testing.assert_array_equal(h.depth_mask, d.depth_mask)  # (invalid normals dropped by the host's rule)
    span = float(h.depth[h.depth_mask].max() - h.depth[h.depth_mask].min())
    assert np.abs(h.depth - d.depth)[h.depth_mask].max() <= 1e-4 * span
    for k in ("albedo", "residual"):
        np.testing.assert_allclose(d.__dict__[k][m], h.__dict__[k][m], rtol=1e-2, atol=1e-4)


@pytest.mark.parametrize("camera", ["perspective", "orthographic"])
@pytest.mark.parametrize("with_ref", [True, False])
def test_final_depth_on_device_matches_host(camera, with_ref, device, monkeypatch):
    """Directional lights (the rounds' depth does not feed back): the device run integrates only the final
    depth, once, on the device, from the solver's buffer (not handed to the solver); it equals the host
    run's final depth within 1e-4 of the range (both to a relative residual of 1e-5 in float32, on normals
    that agree to float rounding), with the same depth mask; without a reference depth the host's
    normalisation (log-depth or depth of mean 0 per component, as Integrator.fetch without one, on the device)."""
    sc = make_scene("sphere", 64, camera)
    L = default_lights("directional", 3)
    img = render(sc, MAT, L, bits=16, noise=0.0) / np.asarray(L.intensities, np.float32)[:, None, None, :]
    lights = DirectionalLights(L.directions)
    ref = float(sc.depth[sc.mask].mean())
    calls = []
    integrate = DeviceRounds.integrate

    def spy(self, reference_depth, **kw):
        calls.append(kw.get("into_solver", True))
        return integrate(self, reference_depth, **kw)

    monkeypatch.setattr(DeviceRounds, "integrate", spy)
    h = _run(img, lights, sc, ref if with_ref else None, device, device_rounds=False, rounds=3)
    assert calls == []
    d = _run(img, lights, sc, ref if with_ref else None, device, device_rounds=True, rounds=3)
    assert calls == [False]
    np.testing.assert_array_equal(h.depth_mask, d.depth_mask)
    m = h.depth_mask
    span = float(h.depth[m].max() - h.depth[m].min())
    assert np.abs(h.depth - d.depth)[m].max() <= 1e-4 * span, np.abs(h.depth - d.depth)[m].max() / span
    assert np.all(d.depth[~m] == 0.0)
    if with_ref or sc.camera.is_perspective:
        assert np.all(d.depth[m] > 0.0)
    assert d.integration_residual <= 1e-5


def _copy_spy(monkeypatch, more_than: int = 16):
    """Counts host<->device transfers of more than ``more_than`` values: Warp's numpy/list/assign and arrays
    built from host data, Taichi fields' to_numpy/from_numpy.  Small reads (the round's scalars, CG residual
    checks) are not counted."""
    import importlib

    wp = warp()
    tf = importlib.import_module("taichi.lang.field")
    count = [0]

    def big(x):
        return int(np.size(x)) > more_than

    def wrap(cls, name, size_of):
        orig = getattr(cls, name)

        def spy(self, *args, **kwargs):
            if size_of(self, args, kwargs):
                count[0] += 1
            return orig(self, *args, **kwargs)

        monkeypatch.setattr(cls, name, spy)

    wrap(wp.array, "numpy", lambda self, a, k: self.size > more_than)
    wrap(wp.array, "list", lambda self, a, k: self.size > more_than)
    wrap(wp.array, "assign", lambda self, a, k: self.size > more_than)
    wrap(wp.array, "__init__", lambda self, a, k: isinstance(k.get("data", a[0] if a else None), np.ndarray)
         and big(k.get("data", a[0] if a else None)))
    for cls in (tf.Field, tf.ScalarField):
        wrap(cls, "to_numpy", lambda self, a, k: int(np.prod(self.shape)) > more_than)
        wrap(cls, "from_numpy", lambda self, a, k: big(a[0] if a else k.get("arr")))
    return count


def test_device_rounds_copy_nothing_per_round(device, monkeypatch):
    """Copies over a whole run with 2 and with 4 rounds: the device rounds add none per round larger than
    the coarsest multigrid level's (its edge weights read, its pseudo-inverse written: at most (hc wc)^2
    values whatever the image size; 6 x 6 cells here, against 48^2 pixels); the host rounds add several:
    the outputs fetched, the start normals and the depth copied in, the integrator's system uploaded and its
    solution fetched."""
    img, lights, sc, ref = _scene("perspective", 48)
    _run(img, lights, sc, ref, device, device_rounds=True, rounds=2)  # compile outside the count
    hc, wc = level_shapes(48, 48, IntegratorConfig().coarsest)[-1]
    assert (hc * wc) ** 2 < 48 * 48
    count = _copy_spy(monkeypatch, more_than=(hc * wc) ** 2)
    per = {}
    for dr in (True, False):
        n = []
        for rounds in (2, 4):
            count[0] = 0
            res = _run(img, lights, sc, ref, device, device_rounds=dr, rounds=rounds)
            assert res.rounds == rounds
            n.append(count[0])
        per[dr] = (n[1] - n[0]) / 2
    assert per[True] == 0, per
    assert per[False] >= 5, per


def test_device_rounds_config():
    with pytest.raises(TypeError, match="device_rounds"):
        RONConfig(device_rounds="yes")


def test_device_rounds_default_by_device(monkeypatch):
    """``device_rounds=None`` (the default): the round's scalars on the device everywhere; step 3 there
    too on the CPU, and on CUDA where torch is installed (its zero-copy views), else on the host; an
    explicit False keeps every round on the host; an explicit True integrates on the device (and
    raises later without torch); one round needs no device rounds."""
    import importlib.util

    from gpps.flows.ron import RON

    assert RONConfig().device_rounds is None

    class Probe:  # only what _device_rounds reads
        point = True
        integrator = object()
        _rounds = None
        _rounds_integ = False

        def __init__(self, device, flag, rounds=5):
            self.device = device
            self.config = RONConfig(device_rounds=flag, rounds=rounds)

    made = []

    class Fake:
        def __init__(self, solver, mask, integrator):
            made.append(integrator)

        def close(self):
            pass

    monkeypatch.setattr("gpps.flows.ron.DeviceRounds", Fake)
    real = importlib.util.find_spec
    for torch in (True, False):
        monkeypatch.setattr(importlib.util, "find_spec",
                            lambda name, *a, t=torch: (object() if t else None) if name == "torch" else real(name, *a))
        for device, flag, rounds, want, integ in (
                ("cpu", None, 5, True, True), ("cuda:0", None, 5, True, torch), ("cuda:0", True, 5, True, True),
                ("cpu", False, 5, False, False), ("cuda:0", False, 5, False, False), ("cpu", None, 1, False, False)):
            p = Probe(device, flag, rounds)
            p.solver = p.mask = None
            made.clear()
            got = RON._device_rounds(p, 1.0, False)
            assert (got is not None) == want, (device, flag, rounds, torch)
            if want:
                assert (made[-1] is not None) == integ, (device, flag, torch)
                assert p._rounds_integ == integ
    # no reference depth: the device integration is still built (the final depth, normalised there as
    # Integrator.fetch does without one); the rounds' step 3 needs a reference (RON.run checks it)
    p = Probe("cpu", None)
    p.solver = p.mask = None
    made.clear()
    assert RON._device_rounds(p, None, False) is not None and made[-1] is p.integrator


def test_device_depth_never_overflows(device, monkeypatch):
    """A solved log-depth whose range would overflow exp (normals that are not integrable) gives a finite depth
    with the reference mean on the device (exp of the log-depth less its maximum per component, as the host's
    Integrator.fetch), and ``fetch()["span"]`` reports the range that RON's final depth warns about.  (Before, exp
    of the log-depth less its mean overflowed to inf.)"""
    sc = make_scene("sphere", 32, "perspective")
    ref = float(sc.depth[sc.mask].mean())
    n = np.where(sc.mask[..., None], sc.normals, 0.0).astype(np.float32)
    integ = Integrator(sc.mask, camera=sc.camera, config=IntegratorConfig(tol=1e-5, weighting="normal"),
                       device=taichi_device(device))
    try:
        ds = DeviceSystem(integ)
        d = integ._ensure_device()
        h, w = sc.mask.shape
        ramp = np.tile(np.linspace(0.0, 2000.0, w), (h, 1)).astype(d["np_dtype"])  # exp(2000) overflows float64

        def fake_iterate(progress, tol):
            d["z"].from_numpy(ramp)
            return 1, 0.0

        monkeypatch.setattr(integ, "_iterate", fake_iterate)
        wn, wo, vn, vo = _views(device, n, np.zeros(sc.mask.shape, np.float32))
        assert ds.step(vn, vo, reference_depth=ref)
        got = ds.fetch()
        dep = wo.numpy()
        m = sc.mask
        # finite everywhere; the valid pixels' depths have the reference mean before the fill (underflowed ones,
        # depth 0, are then filled with that mean, as RON's _fill_depth does on the host)
        assert np.all(np.isfinite(dep[m])) and np.all(dep[m] > 0.0)
        assert got["fill"] == pytest.approx(ref, rel=1e-3)
        assert got["span"] == pytest.approx(float(ramp[m].max() - ramp[m].min()), rel=1e-6)
        ds.close()
    finally:
        integ.close()
