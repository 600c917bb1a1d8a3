"""gpps.Reconstructor: the stages kept between calls give gpps.reconstruct's results, bit for bit."""

import numpy as np
import pytest

import gpps


def _captures(device, size=40):
    """Two captures of one set-up (perspective bumps, 3 directional lights) with different materials, and the
    lights without their intensities (the images divided by them)."""
    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    out = []
    for ks, rough in ((0.8, 0.2), (0.3, 0.45)):
        true = gpps.Material("cook-torrance", ks=ks, roughness=rough, f0=0.5)
        img = gpps.render(sc, true, L, bits=16, device=device) / L.intensities[:, None, None, :]
        out.append(np.ascontiguousarray(img, np.float32))
    return sc, gpps.DirectionalLights(L.directions), out


def _same(a, b, *, depth_bits: bool = True):
    for k in ("normals", "albedo", "depth", "residual", "flags", "highlight", "depth_mask"):
        if k == "depth" and not depth_bits:
            # (the persistent CG's dot products summed in another order: the depth's last bits)
            np.testing.assert_allclose(a.depth, b.depth, rtol=1e-5, atol=0, err_msg=k)
            continue
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k)
    assert a.estimated == b.estimated
    assert a.rounds == b.rounds
    # the rounds' energies are device reductions (float64 atomic sums on CUDA: their order, so the last bit, varies
    # from run to run, a fresh reconstruct against another included)
    np.testing.assert_allclose(a.energy, b.energy, rtol=1e-12)
    assert a.warnings == b.warnings


@pytest.mark.parametrize("config", ["default", "given"])
def test_reconstructor_equals_reconstruct(device, config):
    """Bit for bit, but for the depth's last bits on CUDA without a config (the kept stages' persistent CG:
    gpps.flows.reconstruction.kept_stages_config); the directional lights' normals do not depend on the depth."""
    from gpps.flows.reconstruction import kept_stages_config

    sc, lights, caps = _captures(device)
    kw = dict(camera=sc.camera, material="cook-torrance", device=device)
    given = {} if config == "default" else {"config": gpps.RONConfig()}
    fresh = [gpps.reconstruct(img, sc.mask, lights, **kw, **given) for img in caps]
    with gpps.Reconstructor(sc.mask, lights, **kw, **given) as rc:
        kept = [rc(img) for img in caps + caps[:1]]
        assert rc.builds == 1  # (the same working scale: one set of stages for all three)
        launch = rc._ron.integrator.config.launch
    kept_launch = kept_stages_config(gpps.RONConfig(), sc.camera).integrator.launch
    assert launch == (kept_launch if config == "default" else "fused")
    bits = config == "given" or not device.startswith("cuda")
    _same(kept[0], fresh[0], depth_bits=bits)
    _same(kept[1], fresh[1], depth_bits=bits)
    _same(kept[2], fresh[0], depth_bits=bits)  # (nothing of the second capture left behind)
    # the two materials were told apart: the kept stages did not carry the first capture's estimate over
    assert abs(kept[0].estimated["roughness"] - 0.2) < 0.05
    assert abs(kept[1].estimated["roughness"] - 0.45) < 0.1


def test_reconstructor_rebuilds_on_a_new_scale_and_keeps_inputs(device):
    sc, lights, caps = _captures(device, size=32)
    kw = dict(camera=sc.camera, material="cook-torrance", device=device)
    big = caps[0] * np.float32(1000.0)  # (outside the working range: solved at another scale)
    before = big.copy()
    with gpps.Reconstructor(sc.mask, lights, **kw) as rc:
        a = rc(caps[0])
        b = rc(big)
        assert rc.builds == 2
        c = rc(caps[0])
        assert rc.builds == 3
    np.testing.assert_array_equal(big, before)  # the caller's images are not touched
    _same(b, gpps.reconstruct(big, sc.mask, lights, **kw))
    _same(a, c)


def test_reconstructor_checks(device):
    sc, lights, caps = _captures(device, size=24)
    with pytest.raises(TypeError, match="lights"):
        gpps.Reconstructor(sc.mask, "not lights")
    with pytest.raises(ValueError, match="material"):
        gpps.Reconstructor(sc.mask, lights, material="no-such-model")
    with pytest.raises(TypeError, match="config"):
        gpps.Reconstructor(sc.mask, lights, config={"rounds": 2})
    rc = gpps.Reconstructor(sc.mask, lights, camera=sc.camera, material="cook-torrance", device=device)
    with pytest.raises(ValueError, match="images"):
        rc(caps[0][:2])  # (two images for three lights)
    with pytest.raises(ValueError, match="mask"):
        rc(caps[0][:, :20])  # (another frame size)
    rc.close()
    with pytest.raises(RuntimeError, match="closed"):
        rc(caps[0])


def test_reconstructor_drops_stages_after_a_failed_call(device):
    sc, lights, caps = _captures(device, size=24)
    kw = dict(camera=sc.camera, material="cook-torrance", device=device)

    def stop(done, total, msg):
        if "round 1" in msg:
            raise KeyboardInterrupt  # (the user stopping a run)

    with gpps.Reconstructor(sc.mask, lights, **kw) as rc:
        with pytest.raises(KeyboardInterrupt):
            rc(caps[0], progress=stop)
        got = rc(caps[0])
        assert rc.builds == 2  # (the interrupted run's stages were not kept)
    _same(got, gpps.reconstruct(caps[0], sc.mask, lights, **kw))


def test_noise_estimated_beside_the_checks(device):
    """The call's checks estimate the noise levels on the shared CPU pool (gpps.flows.reconstruction._prepare): the
    solver's own estimate of the images it gets, bit for bit, and RON run with them gives the same result as RON
    estimating them in its upload; at a working scale other than 1 none is passed (the solver estimates them on the
    scaled images)."""
    from gpps.flows.reconstruction import _prepare
    from gpps.flows.ron import RON
    from gpps.pipeline.solver import estimate_noise

    sc, lights, caps = _captures(device)
    args = (sc.mask, lights, sc.camera, "cook-torrance", "auto", None, None, None, None, None)
    prep = _prepare(caps[0], *args)
    assert prep.noise is not None and prep.noise.shape == (3,) and np.all(prep.noise > 0)
    np.testing.assert_array_equal(prep.noise, estimate_noise(prep.images, prep.mask))
    got = []
    for noise in (prep.noise, None):
        ron = RON(prep.shape, prep.camera, prep.lights, prep.material, prep.mask, prep.config, device=device)
        try:
            got.append(ron.run(prep.images, valid=prep.valid, noise=noise))
            np.testing.assert_array_equal(ron.solver.noise_level, prep.noise)
        finally:
            ron.close()
    for k in ("normals", "albedo", "residual", "flags"):
        np.testing.assert_array_equal(getattr(got[0], k), getattr(got[1], k), err_msg=k)
    with pytest.warns(gpps.GppsWarning, match="working"):
        assert _prepare(caps[0] * 4096.0, *args).noise is None
    # where the solver's upload estimates them on the device (CUDA: gpps.pipeline.noise.noise_on_device) the checks
    # leave them out; the device's estimate is the same (ron.solver.noise_level above, with noise None)
    assert _prepare(caps[0], *args, host_noise=False).noise is None
