"""Streaming stage: warm-started frames equal the batch solve, bad frames are reported, state stays put."""

import numpy as np
import pytest

from gpps.host.metrics import normal_errors


def _scene(size=48, camera="perspective"):
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene("bumps", size, camera)
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", 3)
    img = render(sc, mat, L, bits=16)
    frame = np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16)
    return sc, mat, L, img, frame


def test_stream_matches_batch_and_reports_bad_frames(device):
    from gpps.lights import DirectionalLights
    from gpps.pipeline.integration import Integrator, IntegratorConfig
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, img, frame = _scene()
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=sc.mask, config=StreamConfig(output="numpy"), device=device)
    bad_nan = (frame.astype(np.float32) / 65535).copy()
    bad_nan[0, 3, 3] = np.nan
    frames = [frame, frame, bad_nan, frame[:2], frame.astype(np.int32), frame, frame.astype(np.float32) / 65535, frame]
    out = list(st.iterate(frames))
    assert [r.index for r in out] == list(range(len(frames)))
    assert [r.ok for r in out] == [True, True, False, False, False, True, True, True]
    assert "NaN" in out[2].error and "shape" in out[3].error and "dtype" in out[4].error
    # batch reference: gpps.reconstruct on the same (quantised) frame, the material known (nothing to estimate)
    import gpps

    from gpps.flows.ron import RONConfig

    same = RONConfig(integrator=IntegratorConfig(tol=1e-5, weighting="uniform"))  # the stream's plain Poisson integration
    rec = gpps.reconstruct(frame.astype(np.float32) / 65535 / np.asarray(L.intensities, np.float32)[:, None, None, :],
                           sc.mask, DirectionalLights(L.directions), camera=sc.camera, material=mat, config=same,
                           device=device)
    assert rec.rounds == 1 and rec.estimated == {}
    m = sc.mask
    for r in (out[0], out[-1]):  # the cold first frame and a warm-started later one
        ang = np.degrees(np.arccos(np.clip((r.normals * rec.normals).sum(-1), -1, 1)))[m]
        assert np.percentile(ang, 99) < 0.05, np.percentile(ang, 99)
        # albedo: a handful of rim pixels may settle in another local minimum (reconstruct adds DGMC starts)
        assert np.percentile(np.abs(r.albedo[m] - rec.albedo[m]).max(-1), 99.5) < 2e-3
        d = r.depth * np.exp(np.mean(np.log(rec.depth[m])) - np.mean(np.log(r.depth[m])))  # same scale
        dd = np.abs(d - rec.depth)[m] / np.ptp(rec.depth[m])
        # both integrate to a tolerance (reconstruct: relative residual 1e-5): ~2e-4 of the range apart
        assert dd.mean() < 1e-3 and dd.max() < 5e-3, (dd.mean(), dd.max())
    last = out[-1]
    assert normal_errors(last.normals, sc.normals, sc.mask)["mean"] < 0.1
    dref = Integrator(sc.mask, sc.camera, IntegratorConfig(solver="direct")).run(last.normals).depth
    d = last.depth * np.exp(np.mean(np.log(dref[m])) - np.mean(np.log(last.depth[m])))
    assert np.abs(d - dref)[m].max() < 1e-3 * np.ptp(dref[m])
    # the rejected frames left the state alone: a process() after them is as good as before
    again = st.run(frame)
    assert again.ok and np.abs(again.depth - last.depth)[m].max() < 1e-3 * np.ptp(last.depth[m])
    assert st.stats["errors"] == 3


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "float32"])
@pytest.mark.parametrize("channels", [3, 1])
def test_convert_drops_observations_at_full_scale(device, dtype, channels):
    """The frame conversion against numpy: images = raw / (full scale * intensity), and the observations with a
    channel at or above ``saturation`` of full scale marked invalid (default 1.0: the camera's clip); None keeps all."""
    from gpps.camera import Orthographic
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig

    full = {"uint8": 255.0, "uint16": 65535.0, "float32": 1.0}[dtype]
    rng = np.random.default_rng(3)
    n, h, w = 3, 12, 10
    raw = rng.uniform(0.2, 1.0, (n, h, w, channels)) * full
    raw[rng.random((n, h, w, channels)) < 0.15] = full  # clipped channels
    raw = raw.astype(dtype) if dtype != "float32" else raw.astype(np.float32)
    inten = np.array([[0.8, 0.9, 1.0], [1.0, 1.0, 1.0], [0.5, 0.6, 0.7]])
    d = np.array([[0.3, 0.2, 0.93], [-0.3, 0.25, 0.92], [0.0, -0.35, 0.94]])
    L = DirectionalLights(d / np.linalg.norm(d, axis=1, keepdims=True), intensities=inten)
    for sat, want in ((1.0, ~(raw.astype(np.float64) >= full).any(-1)), (0.9, ~(raw.astype(np.float64) >= 0.9 * full).any(-1)),
                      (None, np.ones((n, h, w), bool))):
        st = Stream((h, w), Orthographic(1.0 / w), L, Material.default_for("lambertian"), mask=np.ones((h, w), bool),
                    config=StreamConfig(output="numpy", saturation=sat, integrate=False, check=False), device=device)
        try:
            key, slot, ev = st._upload(raw if channels == 3 else raw[..., 0])
            if ev is not None:
                import warp as wp
                wp.get_stream(st.device).wait_event(ev)
            st._launch_convert(key, slot)
            got = st.solver.valid.numpy().astype(bool)
            img = st.solver.images.numpy()
        finally:
            st.close()
        assert np.array_equal(got, want), (sat, int((got != want).sum()))
        ref = raw.astype(np.float64) / full
        ref = np.repeat(ref, 3, axis=-1) if channels == 1 else ref
        assert np.allclose(img, ref / inten[:, None, None, :], rtol=1e-6, atol=0)


def test_stream_device_output_ring_and_config_errors(device):
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, img, frame = _scene(size=24, camera="orthographic")
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=sc.mask, config=StreamConfig(ring=2, integrate=False), device=device)
    a = st.run(frame)
    b = st.run(frame)
    assert a.depth is None and a.normals is not b.normals  # two ring slots
    assert np.allclose(a.numpy().normals, b.numpy().normals, atol=1e-4)
    with pytest.raises(ValueError, match="iterations"):
        StreamConfig(iterations=0)
    with pytest.raises(ValueError, match="output"):
        StreamConfig(output="gpu")
    with pytest.raises(ValueError, match="neighbour_radius"):
        StreamConfig(neighbour_radius=-1)
    from gpps.flows.synthetic import default_lights

    with pytest.raises(ValueError, match="reference_depth"):
        Stream(sc.mask.shape, sc.camera, default_lights("point", 3), mat, mask=sc.mask, device=device)
    with pytest.raises(ValueError, match="shape"):
        Stream((0, 5), sc.camera, L, mat, device=device)


def test_stream_memory_stays_flat(device):
    """Many frames through one stream allocate nothing per frame (Python heap and Warp buffers)."""
    import tracemalloc

    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, img, frame = _scene(size=16, camera="orthographic")
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=sc.mask, config=StreamConfig(integration_iterations=1), device=device)
    tracemalloc.start()
    # Python keeps up to 2000 freed tuples per size in free lists, which tracemalloc counts as allocated:
    # the first ~2000 frames fill them (a few hundred kB, bounded); after that nothing may grow
    for r in st.iterate([frame] * 2400):
        assert r.ok
    base = tracemalloc.get_traced_memory()[0]
    for r in st.iterate([frame] * 400):
        pass
    grown = tracemalloc.get_traced_memory()[0] - base
    tracemalloc.stop()
    assert grown < 20_000, grown


def test_cli_stream_synthetic(tmp_path, device):
    import json

    from gpps.cli import main

    rc = main(["--device", device, "stream", "--synthetic", "--frames", "5", "--size", "32", "--save-every", "2",
               "--out", str(tmp_path)])
    assert rc == 0
    rep = json.loads((tmp_path / "report.json").read_text())
    assert rep["frames"] == 5 and rep["errors"] == []
    n = np.load(tmp_path / "frame_000004" / "normals.npy")
    assert n.shape == (32, 32, 3) and np.isfinite(n).all()
    assert main(["--device", device, "stream", "--out", str(tmp_path)]) == 2  # neither SOURCE nor --synthetic


def test_cli_stream_folder_without_a_mask(tmp_path, device, capsys):
    """A folder of frame triples with no mask.png (every pixel) of an object on a black background: its frames
    pass (they were all rejected as a misfit); a folder whose every frame is rejected exits 2, naming the first
    reason, and keeps report.json with every frame's."""
    import json

    import cv2

    import gpps
    from gpps.cli import main

    sc = gpps.make_scene("sphere", 32, "orthographic")
    L = gpps.default_lights("directional", 3)
    img = (np.clip(gpps.render(sc, gpps.Material("lambertian"), L, bits=16), 0, 1) * 65535).astype(np.uint16)
    src = tmp_path / "src"
    src.mkdir()
    np.savetxt(src / "light_directions.txt", L.directions)
    (src / "material.json").write_text('{"brdf": "lambertian"}')
    for f in range(3):
        for k in range(3):
            cv2.imwrite(str(src / f"{f:03d}_{k}.png"), img[k][..., ::-1])
    assert main(["--device", device, "stream", str(src), "--out", str(tmp_path / "a")]) == 0
    rep = json.loads((tmp_path / "a" / "report.json").read_text())
    assert rep["frames"] == 3 and rep["errors"] == []
    (src / "001_1.png").unlink()  # a frame the folder cannot give says which file is missing
    assert main(["--device", device, "stream", str(src), "--out", str(tmp_path / "c")]) == 0
    rep = json.loads((tmp_path / "c" / "report.json").read_text())
    assert rep["errors"] == [{"index": 1, "error": "frame 001: missing or unreadable 001_1.png"}]
    cv2.imwrite(str(src / "001_1.png"), img[1][..., ::-1])
    for f in range(3):  # lights that did not fire: the third image black in every frame
        cv2.imwrite(str(src / f"{f:03d}_2.png"), np.zeros_like(img[2]))
    capsys.readouterr()
    assert main(["--device", device, "stream", str(src), "--out", str(tmp_path / "b")]) == 2
    assert "every frame (3) was rejected; the first: frame: rejected" in capsys.readouterr().err
    rep = json.loads((tmp_path / "b" / "report.json").read_text())
    assert rep["frames"] == 3 and len(rep["errors"]) == 3


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_stream_integrator_several_components_matches_direct(camera):
    """Each mask component gets its own constant (mean depth = reference), as the direct solver gives."""
    from gpps.pipeline.integration import Integrator, IntegratorConfig
    from gpps.pipeline.integration_device import StreamIntegrator
    from gpps.host.scenes import make_scene

    sc = make_scene("bumps", 64, camera)
    m = sc.mask.copy()
    m[:, 28:31] = False
    si = StreamIntegrator(m, sc.camera)
    assert si.n_components == 2
    out = np.zeros(m.shape, np.float32)
    si.step(np.ascontiguousarray(sc.normals, np.float32), out, tol=1e-5, reference=10.0)
    ref = Integrator(m, sc.camera, IntegratorConfig(solver="direct")).run(sc.normals, reference_depth=10.0)
    assert np.abs(out - ref.depth)[m].max() < 1e-4 * np.ptp(ref.depth[m])
    assert np.all(out[~m] == 0)


@pytest.mark.parametrize("method", ["multigrid", "pcg"])
def test_stream_integrator_tolerance_stops_at_the_float32_floor(method):
    """A tolerance below what float32 reaches stops once the residual stops falling (gpps.names.STALL_CHECKS
    checks without halving the best |r|^2) instead of running ``max_iterations``.  The floor grows with the map:
    the bumps scene's relative residual stays at about 1e-5 at 64^2, 3.3e-4 at 512^2 and 1.0e-3 at 1024^2, where
    the stream's first frame (``first_tol=1e-4``) ran all 200 iterations for the depth of 6; here ``tol=1e-7``
    at 64^2.  The depth is as good as a longer run's."""
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig
    from gpps.host.scenes import make_scene

    sc = make_scene("bumps", 64, "perspective")
    m = sc.mask
    nrm = np.ascontiguousarray(sc.normals, np.float32)
    si = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(method=method, dtype="float32"))
    out = np.zeros(m.shape, np.float32)

    def err():  # mean |error| / range after the scale (the perspective depth's unknown)
        d = out[m].astype(np.float64)
        d = d * np.exp(np.mean(np.log(sc.depth[m])) - np.mean(np.log(d)))
        return float(np.abs(d - sc.depth[m]).mean() / np.ptp(sc.depth[m]))

    si.reset()
    si.step(nrm, out, tol=1e-7)
    its, res, e = si.last_iterations, si.last_residual, err()
    assert its <= 30, its
    assert 1e-7 < res < 1e-4, res  # stopped at the floor, which lies above tol
    si.reset()
    si.step(nrm, out, iterations=40)
    assert si.residual() > 0.5 * res  # forty iterations do not get much lower
    assert e <= 1.05 * err() + 1e-7, (e, err())


@pytest.mark.parametrize("method, camera", [("multigrid", "orthographic"), ("multigrid", "perspective"),
                                            ("pcg", "perspective")])
def test_stream_integrator_fixed_iterations_converge_and_warm_start(method, camera):
    """The fixed-count mode (for multigrid: the one-launch frame kernel) converges to the direct
    solution, and one iteration from a perturbed previous depth removes most of the perturbation."""
    from gpps.pipeline.integration import Integrator, IntegratorConfig
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig
    from gpps.host.scenes import make_scene

    sc = make_scene("bumps", 64, camera)
    m = sc.mask
    nrm = np.ascontiguousarray(sc.normals, np.float32)
    ref = Integrator(m, sc.camera, IntegratorConfig(solver="direct")).run(sc.normals, reference_depth=10.0).depth
    rng = np.ptp(ref[m])
    si = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(method=method))
    out = np.zeros(m.shape, np.float32)

    def err():
        return float(np.abs(out - ref)[m].mean() / rng)

    errs = []
    for k in (1, 10):  # fused frame kernel (multigrid) and per-cycle launches
        si.reset()
        si.step(nrm, out, iterations=k, reference=10.0)
        errs.append(err())
        assert np.all(out[~m] == 0) and np.isfinite(out).all()
    assert errs[1] < 1e-4 and errs[1] < 0.05 * errs[0], errs
    assert si.last_iterations == 10
    # warm start: the previous depth with a smooth 1 % perturbation
    yy, xx = np.mgrid[0:64, 0:64] / 64.0
    prev = np.where(m, ref * (1.0 + 0.01 * np.sin(2 * np.pi * xx) * np.cos(np.pi * yy)), 0.0).astype(np.float32)
    out[...] = prev
    e0 = err()
    si.upload(prev)
    si.step(nrm, out, iterations=1, reference=10.0)
    assert err() < 0.2 * e0, (err(), e0)


def _numpy_vcycle(levels, f0, omega, keep, pairs=1):
    """One V(2p, 2p)-cycle (``p = pairs``) from zero on ``A u = f0``, written from the definitions (independent of the
    Taichi kernels): damped Jacobi ``x <- keep x + omega (f + sum_b w_ab x_b) / dg`` (``keep = 1 -
    omega``), restriction = sum of the 2x2 block's residuals, prolongation = injection, the coarsest
    level solved by the pseudo-inverse."""
    from gpps.host.poisson import diagonal, apply_laplacian, laplacian

    def jacobi(x, f, wx, wy, d):
        nb = d * x - apply_laplacian(x, wx, wy)
        return np.where(d > 0, keep * x + omega * (f + nb) / np.where(d > 0, d, 1), 0.0)

    def solve(k, f):
        wx, wy = levels[k]
        d = diagonal(wx, wy)
        if k == len(levels) - 1:
            A, idx = laplacian(wx, wy, d > 0)
            x = np.zeros(f.size)
            x[idx] = np.linalg.pinv(A.toarray(), hermitian=True) @ f.ravel()[idx]
            return x.reshape(f.shape)
        x = np.zeros_like(f)
        for _ in range(2 * pairs):
            x = jacobi(x, f, wx, wy, d)
        r = f - apply_laplacian(x, wx, wy)
        r = np.where(d > 0, r, 0.0)
        hc, wc = levels[k + 1][0].shape
        rp = np.zeros((2 * hc, 2 * wc))
        rp[:f.shape[0], :f.shape[1]] = r
        fc = rp[0::2, 0::2] + rp[0::2, 1::2] + rp[1::2, 0::2] + rp[1::2, 1::2]
        ec = solve(k + 1, fc)
        x = np.where(d > 0, x + np.repeat(np.repeat(ec, 2, 0), 2, 1)[:f.shape[0], :f.shape[1]], 0.0)
        for _ in range(2 * pairs):
            x = jacobi(x, f, wx, wy, d)
        return x

    return solve(0, f0)


@pytest.mark.parametrize("launch, psize", [("tasks", 256), ("persistent", 256), ("persistent", 40)])
@pytest.mark.parametrize("shape, smooth_pairs", [((75, 90), 1), ((128, 128), 1), ((75, 90), 2)])
def test_stream_integrator_vcycle_matches_numpy_reference(shape, smooth_pairs, launch, psize):
    """The fused frame kernel (right-hand side with the first residual, the V-cycle with level 0's
    last sweep folded into the depth update, the one-component finish) equals a numpy V-cycle
    written from the definitions: one frame from u = 0 gives u = M b, centred (float64 fields,
    orthographic); odd sizes, a hole, and extra smoothing pairs.  Every launch form: one task per
    phase; the whole frame in the persistent task (on CUDA its blocks meet at grid barriers, on
    the CPU it runs as one thread); the levels of at most 40 pixels a side in it, the larger ones
    as tasks."""
    from gpps.camera import Orthographic
    from gpps.host.poisson import diagonal, build_levels, divergence_rhs, edge_system, pixel_gradients
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig

    h, w = shape
    ii, jj = np.mgrid[0:h, 0:w]
    m = np.hypot(ii - h / 2, jj - w / 2) < 0.45 * min(h, w)
    m &= np.hypot(ii - h / 2 - 5, jj - w / 2 + 7) > 6  # a hole
    x, y = (jj - w / 2) / w, (ii - h / 2) / h
    hx, hy = 0.6 * np.cos(3 * x) * np.cos(2 * y) + 0.2, -0.4 * np.sin(3 * x) * np.sin(2 * y)
    n = np.stack([-hx, -hy, np.ones_like(hx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    cam = Orthographic(1.0)
    cfg = StreamIntegratorConfig(dtype="float64", smooth_pairs=smooth_pairs, launch=launch, persistent_size=psize)
    si = StreamIntegrator(m, cam, cfg)
    assert si.launch == launch and (launch == "tasks" or si._top == (0 if psize == 256 else 2))
    si.reset()
    out = np.zeros(shape, np.float32)
    si.step(np.ascontiguousarray(n), out, iterations=1)
    got = si._F["z"].to_numpy()
    # the reference, with the integrator's own mask (pixels with a 4-neighbour) and level weights
    v = si.valid
    gj, gi, _, _ = pixel_gradients(n, v, cam, cfg.min_nz)
    wx, wy, tx, ty = edge_system(v, gj, gi)
    b = divergence_rhs(wx, wy, tx, ty)
    # omega and 1 - omega enter the kernels as literals of Taichi's default (float32) precision
    want = _numpy_vcycle(build_levels(wx, wy, cfg.coarsest), b, float(np.float32(cfg.omega)),
                         float(np.float32(1 - cfg.omega)), smooth_pairs)
    want = np.where(v, want - want[v].mean(), 0.0)
    assert len(si.levels) >= 3
    scale = np.abs(want[v]).max()
    np.testing.assert_allclose(got[v], want[v], rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(out[v], want[v], rtol=0, atol=2e-6 * scale)  # float32 depth
    assert diagonal(wx, wy)[v].min() > 0


def _two_component_case(camera, size=64):
    from gpps.host.scenes import make_scene

    sc = make_scene("bumps", size, camera)
    m = sc.mask.copy()
    m[:, 28:31] = False  # two components
    m[40:44, 10:20] = False  # a hole
    return sc, m, np.ascontiguousarray(sc.normals, np.float32)


@pytest.mark.parametrize("camera, psize", [("orthographic", 256), ("perspective", 256), ("perspective", 40)])
def test_stream_integrator_persistent_kernel_equals_task_frame(camera, psize):
    """The persistent task (grid barriers between phases: the whole frame, or the levels of at most
    40 pixels a side) gives the task-per-phase frame's depth and warm start: two mask components
    and a hole, 1 and 3 cycles, a reference depth, and a second (warm) frame from each one's own
    previous solution."""
    from gpps import _taichi
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig

    _taichi.init("auto")
    if (camera, psize) == ("perspective", 256) and not _taichi.current_device().startswith("cuda"):
        # (the CPU's suite time: the whole-frame task is orthographic-256's, the perspective system perspective-40's)
        pytest.skip("the perspective whole-frame case runs on CUDA")
    sc, m, nrm = _two_component_case(camera)
    a = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch="tasks"))
    b = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch="persistent", persistent_size=psize))
    assert a.n_components == b.n_components == 2 and b._top == (0 if psize == 256 else 1)
    oa = np.zeros(m.shape, np.float32)
    ob = np.zeros(m.shape, np.float32)
    for cycles in (1, 3):
        a.reset()
        b.reset()
        for _ in range(2):
            a.step(nrm, oa, iterations=cycles, reference=10.0)
            b.step(nrm, ob, iterations=cycles, reference=10.0)
            scale = np.abs(oa).max()
            np.testing.assert_allclose(ob, oa, rtol=0, atol=2e-6 * scale)
            za, zb = a._F["z"].to_numpy(), b._F["z"].to_numpy()
            np.testing.assert_allclose(zb, za, rtol=0, atol=2e-6 * max(np.abs(za).max(), 1e-3))
    assert b.launch == "persistent" and np.all(ob[~m] == 0)


def test_stream_integrator_persistent_falls_back_when_blocks_do_not_fit():
    """Asking for more resident blocks than a multiprocessor holds (8 of 256 threads: 2048 threads
    at most 32 registers each) trips the barrier's timeout on the first frame: the integrator
    restores the warm start, halves the blocks until they fit (or falls back to tasks) and still
    returns the right depth, without hanging."""
    from gpps import _taichi
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig

    _taichi.init("auto")
    if not _taichi.current_device().startswith("cuda"):
        pytest.skip("block residency is a CUDA matter")
    sc, m, nrm = _two_component_case("orthographic", size=640)  # 1600 blocks wanted: 8 per SM on a 132-SM H100
    a = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch="tasks"))
    b = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch="persistent", blocks_per_sm=8,
                                                                            persistent_size=1024))
    oa = np.zeros(m.shape, np.float32)
    ob = np.zeros(m.shape, np.float32)
    for _ in range(2):
        a.step(nrm, oa, iterations=2)
        b.step(nrm, ob, iterations=2)
    np.testing.assert_allclose(ob, oa, rtol=0, atol=2e-6 * np.abs(oa).max())
    print(f"blocks per SM used: {b._bps}, launch {b.launch}")


def _arrays(kind, nrm, cuda):
    """(normals, out) of one kind: numpy, a Taichi ndarray, or a torch tensor on Taichi's device."""
    from gpps._taichi import ti

    if kind == "numpy":
        return nrm.copy(), np.zeros(nrm.shape[:2], np.float32)
    if kind == "ndarray":
        a, o = ti.ndarray(ti.f32, nrm.shape), ti.ndarray(ti.f32, nrm.shape[:2])
        a.from_numpy(nrm)
        return a, o
    torch = pytest.importorskip("torch")
    dev = "cuda" if cuda else "cpu"
    return torch.from_numpy(nrm.copy()).to(dev), torch.zeros(nrm.shape[:2], dtype=torch.float32, device=dev)


def _host(a):
    return a if isinstance(a, np.ndarray) else (a.to_numpy() if hasattr(a, "to_numpy") else a.cpu().numpy())


@pytest.mark.parametrize("kind", ["numpy", "ndarray", "torch"])
@pytest.mark.parametrize("launch", ["tasks", "persistent"])
def test_stream_integrator_direct_launch_equals_plain_call(kind, launch):
    """Frames launched directly (Taichi's argument handling skipped on the same array objects) give
    the plain call's depth over three frames, new normals written into the same input between them;
    the launcher really took the direct path from the second frame on."""
    from gpps import _taichi
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig

    _taichi.init("auto")
    cuda = _taichi.current_device().startswith("cuda")
    if kind == "numpy" and cuda:
        pytest.skip("Taichi copies numpy arrays to the GPU: those frames take the plain path")
    sc, m, nrm = _two_component_case("perspective")
    shifted = np.ascontiguousarray(np.roll(nrm, 2, axis=1))
    ia, oa = _arrays(kind, nrm, cuda)
    ib, ob = _arrays(kind, nrm, cuda)
    a = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch=launch, direct_launch=False))
    b = StreamIntegrator(m, sc.camera, StreamIntegratorConfig(launch=launch))
    for k in range(3):
        if k == 2:  # a new normal map in the same buffers
            for x in (ia, ib):
                if kind == "numpy":
                    x[:] = shifted
                elif kind == "ndarray":
                    x.from_numpy(shifted)
                else:
                    x.copy_(x.new_tensor(shifted))
        a.step(ia, oa, iterations=1, reference=10.0)
        b.step(ib, ob, iterations=1, reference=10.0)
        da, db = _host(oa), _host(ob)
        np.testing.assert_allclose(db, da, rtol=0, atol=2e-6 * np.abs(da).max())
    assert np.abs(da - _host(oa)).max() == 0 and np.abs(da[m]).min() > 0
    run = b._ready[1][0] if b.launch == "persistent" else b._frames[1]
    assert len(run._plans) == 1 and next(iter(run._plans.values()))[3][0][1] is ib


def test_direct_launch_replans_on_new_arrays_and_rejects_resized_ones():
    """DirectLaunch: the first call and a call on new array objects take Taichi's plain call (which
    compiles a specialisation for a new dtype); the same objects take the direct path with the new
    scalars; an array reshaped in place since is refused with a ValueError, not read out of bounds;
    a kernel with a template argument is always called the plain way."""
    from gpps import _taichi
    from gpps._taichi import DirectLaunch

    ti = _taichi.init("auto")
    cuda = _taichi.current_device().startswith("cuda")

    @ti.kernel
    def axpy(x: ti.types.ndarray(), y: ti.types.ndarray(), a: ti.f64, n: ti.i32):
        for i in range(n):
            y[i] = a * x[i] + y[i]

    @ti.kernel
    def scale(x: ti.types.ndarray(), a: ti.template()):
        for i in range(x.shape[0]):
            x[i] *= a

    run = DirectLaunch(axpy)
    if cuda:
        x, y = ti.ndarray(ti.f32, 8), ti.ndarray(ti.f32, 8)
        x.from_numpy(np.arange(8, dtype=np.float32))
        y.fill(1.0)
    else:
        x, y = np.arange(8, dtype=np.float32), np.ones(8, np.float32)
    run(x, y, 2.0, 8)  # plain
    assert len(run._plans) == 1
    plan = next(iter(run._plans.values()))
    run(x, y, 0.5, 4)  # direct: new scalars
    assert list(run._plans.values()) == [plan]
    np.testing.assert_allclose(_host(y), 1 + 2 * np.arange(8) + np.r_[0.5 * np.arange(4), np.zeros(4)])
    x2 = np.arange(8, dtype=np.float64) if not cuda else ti.ndarray(ti.f64, 8)
    if cuda:
        x2.from_numpy(np.arange(8, dtype=np.float64))
    y2 = np.zeros(8) if not cuda else ti.ndarray(ti.f64, 8)
    run(x2, y2, 3.0, 8)  # new objects (float64): plain call, a second plan
    assert len(run._plans) == 2 and list(run._plans.values())[1][3][0][1] is x2
    np.testing.assert_allclose(_host(y2), 3 * np.arange(8))
    run(x, y, 1.0, 8)  # back to the first set: direct
    assert len(run._plans) == 2
    np.testing.assert_allclose(_host(y), 1 + 3 * np.arange(8) + np.r_[0.5 * np.arange(4), np.zeros(4)])
    if not cuda:
        x2.shape = (2, 4)
        with pytest.raises(ValueError, match="resized in place"):
            run(x2, y2, 1.0, 8)
    for _ in range(DirectLaunch.MAX_PLANS):  # new sets push the oldest out
        run(np.arange(8.0) if not cuda else x, np.zeros(8) if not cuda else y, 0.0, 8)
    assert len(run._plans) == (DirectLaunch.MAX_PLANS if not cuda else 2)
    t = DirectLaunch(scale)
    z = np.ones(4, np.float32) if not cuda else ti.ndarray(ti.f32, 4)
    if cuda:
        z.fill(1.0)
    t(z, 2.0)
    t(z, 2.0)
    assert not t._plans
    np.testing.assert_allclose(_host(z), 4.0)


def test_stream_integrator_rejects_bad_frames_arrays():
    from gpps.pipeline.integration_device import StreamIntegrator

    sc, m, nrm = _two_component_case("orthographic", size=32)
    si = StreamIntegrator(m, sc.camera)
    out = np.zeros(m.shape, np.float32)
    with pytest.raises(ValueError, match=r"normals: expected shape \(32, 32, 3\)"):
        si.step(nrm[:, :, :2].copy(), out, iterations=1)
    with pytest.raises(ValueError, match=r"out: expected shape \(32, 32\)"):
        si.step(nrm, out[:5], iterations=1)
    with pytest.raises(ValueError, match="out: expected a float32 array"):
        si.step(nrm, np.zeros(m.shape), iterations=1)
    with pytest.raises(ValueError, match="normals: expected a float32 or float64"):
        si.step(nrm.astype(np.int32), out, iterations=1)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="reference"):
            si.step(nrm, out, iterations=1, reference=bad)
    si.step(nrm, out, iterations=2)
    assert np.isfinite(out).all() and np.abs(out[m]).max() > 0
