"""The stream's full mode (material unknown, issue 20): the material search spread over frames, its device
sample, its bad-frame handling, and known mode left as it was.

References: the pattern search against an analytic quadratic; the device gather against MaterialScorer's host
upload (same energies); the tile picks against a numpy arg-max; the stream's estimate and MAEN against the
truth and against the offline ``gpps.reconstruct`` (material unknown) of the same frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from gpps.host.metrics import normal_errors

TRUE = dict(brdf="cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
SIZE = 64


def _moving(size=SIZE, shifts=(0, 0, 1, 1, 2, 2, 3, 3), material=None):
    """Cook-Torrance bumps (perspective, 3 directional lights, RGB, 16 bit), moved ``shifts[f]`` pixels right in
    frame f: ``(scene, lights, frames, truth, mask)``, the mask the pixels inside the object in every frame."""
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.material import Material

    mat = Material(**TRUE) if material is None else material
    sc = make_scene("bumps", size, "perspective")
    L = default_lights("directional", 3)
    frames, truth = {}, {}
    mask = sc.mask.copy()
    for s in sorted(set(shifts)):
        moved = type(sc)(**{k: (np.roll(v, s, axis=1) if isinstance(v, np.ndarray) and v.ndim >= 2 else v)
                            for k, v in sc.__dict__.items()})
        frames[s] = np.round(np.clip(render(moved, mat, L, bits=16), 0, 1) * 65535).astype(np.uint16)
        truth[s] = moved.normals
        mask &= moved.mask
    return sc, L, [frames[s] for s in shifts], [truth[s] for s in shifts], mask


def test_pattern_search_minimises_a_valley_one_batch_at_a_time():
    """A rotated quadratic valley (as ks and roughness trade): grid, stencils, settle, refine, discard."""
    from gpps.host.pattern import PatternSearch

    c = np.array([0.3, -1.2])
    a = np.array([[4.0, 3.0], [3.0, 4.0]])  # eigenvalues 1 and 7: a valley across the axes

    def f(x):
        d = np.asarray(x) - c
        return np.einsum("ki,ij,kj->k", d, a, d)

    s = PatternSearch([-2.0, -3.0], [2.0, 0.0], [1.5, -0.2], grid=5, tol=1e-3)
    assert s.max_batch() == 25 and len(s.ask()) == 25
    assert s.ask() is s.ask()  # the same batch until told
    batches = 0
    while not s.settled:
        pts = s.ask()
        assert 1 <= len(pts) <= (25 if batches == 0 else 10)
        s.tell(f(pts))
        batches += 1
        assert batches < 60
    assert np.abs(s.x - c).max() < 5e-3, s.x
    assert len(s.ask()) == 0
    # a refinement at the optimum holds: one batch, settled again, x unchanged
    x = s.x.copy()
    s.refine()
    assert not s.settled
    s.tell(f(s.ask()))
    assert s.settled and np.array_equal(s.x, x)
    # the optimum drifts: a refinement follows it
    c = c + np.array([0.05, 0.0])
    s.refine()
    for _ in range(30):
        if s.settled:
            break
        s.tell(f(s.ask()))
    assert np.abs(s.x - c).max() < 5e-3, (s.x, c)
    # a lost batch is asked again
    s.refine()
    first = s.ask().copy()
    s.discard()
    assert np.array_equal(s.ask(), first)
    with pytest.raises(ValueError, match="values"):
        s.tell(np.zeros(len(first) + 1))
    with pytest.raises(ValueError, match="lo, hi"):
        PatternSearch([0.0], [0.0], [0.0])


def test_upload_device_equals_host_upload(device):
    """The device gather gives the energies of the host upload on the same sample pixels."""
    from gpps._runtime import warp
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.material import MaterialScorer
    from gpps.pipeline.solver import SolverConfig

    wp = warp()
    sc, L, frames, _, mask = _moving(size=32, shifts=(0,))
    img = frames[0].astype(np.float32) / 65535 / np.asarray(L.intensities, np.float32)[:, None, None, :]
    unit = DirectionalLights(L.directions)
    cfg = SolverConfig(starts=4, neighbour_radius=0, warm_start=False, noise_level=0.0)
    rng = np.random.default_rng(3)
    sample = np.zeros(mask.size, bool)
    sample[rng.choice(np.flatnonzero(mask), 150, replace=False)] = True
    sample = sample.reshape(mask.shape)
    cands = [Material(**TRUE), Material("cook-torrance", ks=0.4, roughness=0.3), Material("cook-torrance", ks=1.5)]
    host = MaterialScorer(img.shape[:3], sc.camera, unit, "cook-torrance", cfg, max_samples=200, device=device)
    e_host = host.run(img, sample, cands)
    dev = MaterialScorer(img.shape[:3], sc.camera, unit, "cook-torrance", cfg, max_samples=200, device=device)
    r, c = np.nonzero(sample)
    rows = wp.array(r.astype(np.int32), dtype=wp.int32, device=device)
    cols = wp.array(c.astype(np.int32), dtype=wp.int32, device=device)
    images = wp.array(img, dtype=wp.vec3, device=device)
    dev.set_candidates(cands)
    dev.upload_device(images, rows, cols, len(r))
    dev.launch()
    e_dev = dev.fetch()
    assert dev.rows_host is None
    np.testing.assert_allclose(e_dev, e_host, rtol=1e-5, atol=1e-12)
    assert int(np.argmin(e_dev)) == 0
    with pytest.raises(ValueError, match="images"):
        dev.upload_device(wp.zeros((3, 5, 5), dtype=wp.vec3, device=device), rows, cols, len(r))
    with pytest.raises(ValueError, match="count"):
        dev.upload_device(images, rows, cols, 201)
    with pytest.raises(TypeError, match="rows"):
        dev.upload_device(images, r, cols, len(r))


def test_sample_follows_the_brightest_pixel_of_each_tile(device):
    """The tile half of the sample is each tile's brightest pixel (first in raster order on ties) of the frame the
    stream holds now; the other half are fixed random mask pixels."""
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, L, frames, _, mask = _moving(size=48, shifts=(0, 3))
    st = Stream(mask.shape, sc.camera, L, Material("cook-torrance"), mask=mask, device=device,
                config=StreamConfig(material="estimate", material_samples=128, integrate=False, dgmc=False))
    est = st.estimator
    assert est.tiles > 0 and est.tiles <= 64
    picks = []
    for fr in frames:
        st.run(fr)
        img = st.solver.images.numpy()
        grey = img.mean(-1).max(0)
        est.upload()
        rows, cols = est.scorer.rows.numpy()[:est.samples], est.scorer.cols.numpy()[:est.samples]
        (th, tw), tj = est._tile, est._tiles_j
        i0, j0 = int(est._box[0]), int(est._box[1])
        h, w = mask.shape
        ii, jj = np.mgrid[:h, :w]
        tile = np.where(mask & (ii >= i0) & (jj >= j0), ((ii - i0) // th) * tj + (jj - j0) // tw, -1)
        for t in range(est.tiles):
            inside = tile == t
            if inside.any():
                best = np.flatnonzero((inside & (grey == grey[inside].max())).ravel())[0]
                assert (rows[t], cols[t]) == divmod(best, w), t
        assert mask[rows, cols].all()
        assert len(set(zip(rows[est.tiles:], cols[est.tiles:]))) == est.samples - est.tiles
        picks.append((rows[:est.tiles].copy(), cols[:est.tiles].copy()))
    assert (picks[0][1] != picks[1][1]).any()  # the object moved 3 pixels: the picks moved with it


def test_full_mode_estimates_the_material_and_approaches_offline(device):
    """A wrong guess; the estimate converges to the truth, and the stream's MAEN over the last frames is within
    1.5x of the offline ``gpps.reconstruct`` (material unknown) of the same frames (issue 20's line).

    The frames clip their highlights at full scale (about 2.8 % of the observations).  Both the stream
    (``StreamConfig.saturation``, 1.0: the camera's full scale) and the offline reconstruct (float frames: the
    clipping plateaus of :mod:`gpps.host.clipping`) leave those observations out.  Measured on the CPU (64^2,
    32 frames, a pixel every 4): offline ks 0.8003, roughness 0.2000, MAEN 0.015 / 0.023 deg (a few pixels in a
    wrong basin); stream ks 0.79999, roughness 0.20000, MAEN 0.0011 at both frames (0.0076 on a frame just after
    a move).  What it took (each measured on this scene): leaving the clipped values out (offline 1.26 -> 0.015
    deg, stream 1.71 -> 0.22); the pixels a clip leaves with 2 usable observations held to an albedo (the
    neighbour pass in the cold solves, the held albedo in the warm ones: 2.0 deg there -> 0.012);
    ``material_tol`` 1e-3 (a 0.3 % error in the settled estimate gave 0.056 deg)."""
    import gpps
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig

    shifts = tuple(f // 4 for f in range(32))  # a pixel every 4 frames
    sc, L, frames, truth, mask = _moving(shifts=shifts)
    guess = Material("cook-torrance", ks=0.3, roughness=0.5, f0=0.5)
    st = Stream(mask.shape, sc.camera, L, guess, mask=mask, config=StreamConfig(output="numpy", material="estimate"),
                device=device)
    out = list(st.iterate(frames))
    assert all(r.ok for r in out), [r.error for r in out if not r.ok]
    est = out[-1].material
    assert est.brdf == "cook-torrance" and est.f0 == 0.5
    assert st.estimator.settled and st.stats["material_batches"] < len(frames)
    maen = [normal_errors(r.normals, t, mask)["mean"] for r, t in zip(out, truth)]
    unit = DirectionalLights(L.directions)
    inten = np.asarray(L.intensities, np.float32)[:, None, None, :]
    off_maen, off_est = [], []
    for f in (len(frames) - 5, len(frames) - 1):
        rec = gpps.reconstruct(frames[f].astype(np.float32) / 65535 / inten, mask, unit, camera=sc.camera,
                               material="cook-torrance", device=device)
        off_maen.append(normal_errors(rec.normals, truth[f], mask)["mean"])
        off_est.append(rec.estimated)
    stream_maen = float(np.mean([maen[len(frames) - 5], maen[-1]]))
    assert abs(np.log(est.roughness / TRUE["roughness"])) < 2e-3, est
    assert abs(np.log(est.ks / TRUE["ks"])) < 2e-3, est
    for o in off_est:
        assert abs(np.log(o["roughness"] / TRUE["roughness"])) < 0.01 and abs(np.log(o["ks"] / TRUE["ks"])) < 0.01, o
    assert float(np.mean(off_maen)) < 0.05, off_maen
    assert stream_maen <= 1.5 * float(np.mean(off_maen)), (maen, off_maen)  # issue 20's line
    assert maen[-1] < 0.05 * maen[0]  # the grid's material of the first frame (3.0 deg) is improved on


def test_full_mode_bad_frames_and_config(device):
    """A bad frame (black, noise) is rejected and the search does not take its scores; a black first frame is
    rejected and the search starts over; configs that cannot estimate are refused."""
    from gpps.flows.synthetic import default_lights
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, L, frames, truth, mask = _moving(size=40, shifts=(0, 0, 0, 0))
    cfg = StreamConfig(output="numpy", material="estimate", dgmc=False)
    guess = Material("cook-torrance", ks=0.3, roughness=0.5)
    st = Stream(mask.shape, sc.camera, L, guess, mask=mask, config=cfg, device=device)
    black = np.zeros_like(frames[0])
    noise = np.random.default_rng(0).integers(0, 65536, frames[0].shape).astype(np.uint16)
    r0 = st.run(black)
    assert not r0.ok and "lit" in r0.error
    assert st.estimator.scored == 0 and st.material == guess  # started over
    r1 = st.run(frames[0])
    assert r1.ok and r1.material != guess
    batches = st.stats["material_batches"]
    x = st.estimator.search.x.copy()
    told = st.estimator.search.batches
    for bad in (black, noise):
        r = st.run(bad)
        assert not r.ok
        assert st.estimator.search.batches == told and np.array_equal(st.estimator.search.x, x)
    assert st.stats["material_batches"] == batches  # a rejected frame's scores are never fetched
    r = st.run(frames[1])
    assert r.ok and st.estimator.search.batches == told + 1
    with pytest.raises(ValueError, match="no scene parameters"):
        Stream(mask.shape, sc.camera, L, Material("lambertian"), mask=mask, config=cfg, device=device)
    with pytest.raises(ValueError, match="estimate"):
        Stream(mask.shape, sc.camera, L, guess, mask=mask, device=device,
               config=StreamConfig(material="estimate", estimate=("shininess",)))
    with pytest.raises(ValueError, match="estimate"):
        StreamConfig(material="estimate", estimate=("gloss",))
    with pytest.raises(ValueError, match="estimate"):
        StreamConfig(estimate=("ks",))  # names with a known material
    with pytest.raises(ValueError, match="material"):
        StreamConfig(material="guess")
    with pytest.raises(ValueError, match="material_candidates"):
        Stream(mask.shape, sc.camera, L, guess, mask=mask, device=device,
               config=StreamConfig(material="estimate", material_candidates=9))
    with pytest.raises(ValueError, match="refresh_rows"):
        StreamConfig(refresh_rows=-1)
    with pytest.raises(ValueError, match="retry_rows"):
        StreamConfig(retry_rows=-1)
    with pytest.raises(TypeError, match="retry_rows"):
        StreamConfig(retry_rows=1.5)
    from gpps.pipeline.solver import SolverConfig

    with pytest.raises(TypeError, match="warm_albedo"):
        SolverConfig(warm_albedo="yes")
    del default_lights


def test_known_mode_does_no_material_work(device):
    """Known mode: no estimator, no re-solve rows, the given material reported; one estimated parameter works."""
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, L, frames, truth, mask = _moving(size=32, shifts=(0, 1))
    mat = Material(**TRUE)
    st = Stream(mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="numpy"), device=device)
    assert st.estimator is None and st._refresh == 0  # (no whole-row re-solve: only the misfit retries)
    assert st._retry == StreamConfig().retry_rows
    out = list(st.iterate(frames))
    assert all(r.ok and r.material is mat for r in out)
    assert "material_batches" not in st.stats
    one = Stream(mask.shape, sc.camera, L, Material("cook-torrance", ks=0.8, roughness=0.4), mask=mask, device=device,
                 config=StreamConfig(output="numpy", material="estimate", estimate=("roughness",), dgmc=False))
    r = one.run(frames[0])
    assert r.ok and r.material.ks == 0.8 and r.material.roughness != 0.4
    assert one.estimator.batch == 4 and one.estimator.grid == 9
