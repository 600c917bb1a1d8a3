"""The stream rejects bad frames (never a warm start), heals a bad start within a frame, and never hands out
views of its live buffers."""

from __future__ import annotations

import numpy as np
import pytest

from gpps.host.metrics import angular_error, normal_errors
from gpps.names import FLAG_FEW_OBSERVATIONS


def _frames(size=32, n=6, seed=0):
    """A slowly moving perspective Blinn-Phong scene as uint16 RGB frames, with ground truth."""
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene("bumps", size, "perspective")
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", 3)
    frames, truth = [], []
    for f in range(n):
        s = f // 2
        moved = type(sc)(**{k: (np.roll(v, s, axis=1) if isinstance(v, np.ndarray) and v.ndim >= 2 else v)
                            for k, v in sc.__dict__.items()})
        frames.append(np.round(np.clip(render(moved, mat, L, bits=16), 0, 1) * 65535).astype(np.uint16))
        truth.append(moved.normals)
    mask = sc.mask.copy()
    for s in range(n // 2 + 1):
        mask &= np.roll(sc.mask, s, axis=1)
    return sc, mat, L, mask, frames, truth


def _bad(kind, frame, rng):
    f = frame.astype(np.float32) / 65535
    if kind == "black":
        return np.zeros_like(frame)
    if kind == "noise":
        return rng.integers(0, 65536, frame.shape).astype(np.uint16)
    if kind == "grey-noise":
        return rng.integers(0, 65536, frame.shape[:3]).astype(np.uint16)
    if kind == "saturated":
        return np.full_like(frame, 65535)
    if kind == "negative":
        return f - 0.5
    if kind == "nan":
        f[0, 1, 1, 0] = np.nan
        return f
    if kind == "shape":
        return frame[:, :-1]
    if kind == "dtype":
        return frame.astype(np.int64)
    raise AssertionError(kind)


KINDS = ["black", "noise", "grey-noise", "saturated", "negative", "nan", "shape", "dtype"]


def test_bad_frames_are_reported_and_never_warm_start(device):
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, mask, frames, truth = _frames()
    rng = np.random.default_rng(1)
    cfg = StreamConfig(output="numpy")
    clean = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=cfg, device=device)
    dirty = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=cfg, device=device)
    seq = [frames[0]]
    for k, kind in enumerate(KINDS):  # every kind of bad frame between two good ones
        seq += [_bad(kind, frames[0], rng), frames[1 + k % (len(frames) - 1)]]
    good = [f for f in seq if f.dtype == np.uint16 and f.shape == frames[0].shape and f.any() and
            any(f is g for g in frames)]
    ref = [r for r in clean.iterate(good)]
    out = list(dirty.iterate(seq))
    errs = [r for r in out if not r.ok]
    assert len(errs) == len(KINDS), [r.error for r in out]
    for r, kind in zip(errs, KINDS):
        assert r.error.startswith("frame:"), r.error
        want = {"black": "lit", "noise": "noise", "grey-noise": "noise", "saturated": "saturated",
                "negative": ">= 0", "nan": "NaN", "shape": "shape", "dtype": "dtype"}[kind]
        assert want in r.error, (kind, r.error)
    oks = [r for r in out if r.ok]
    assert len(oks) == len(ref)
    for a, b in zip(oks, ref):
        ang = angular_error(a.normals, b.normals, mask)[mask]
        assert ang.max() < 1e-3, ang.max()  # identical to the stream that never saw the bad frames
        assert np.allclose(a.depth[mask], b.depth[mask], rtol=1e-5, atol=1e-6)
    assert dirty.stats["errors"] == len(KINDS)


def test_a_bad_first_frame_leaves_the_next_one_cold(device):
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, mask, frames, truth = _frames(n=2)
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="numpy"), device=device)
    out = list(st.iterate([np.zeros_like(frames[0]), frames[0], frames[1]]))
    assert [r.ok for r in out] == [False, True, True]
    assert normal_errors(out[1].normals, truth[0], mask)["mean"] < 0.1
    assert normal_errors(out[2].normals, truth[1], mask)["mean"] < 0.1


def test_a_scene_change_heals_within_the_frame(device):
    """A warm start from another scene: the pixels whose residual jumps are re-solved cold in the same frame."""
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, mask, frames, truth = _frames(n=2)
    other = np.ascontiguousarray(frames[0][:, ::-1])  # the frame upside down: another scene, most normals change
    both = mask & mask[::-1]
    cold = Stream(sc.mask.shape, sc.camera, L, mat, mask=both, config=StreamConfig(output="numpy"), device=device)
    ref = cold.run(other)  # a cold (multi-start) solve of the new scene
    for check in (True, False):
        st = Stream(sc.mask.shape, sc.camera, L, mat, mask=both, config=StreamConfig(output="numpy", check=check),
                    device=device)
        st.run(frames[0])
        st.run(frames[0])
        r = st.run(other)
        assert r.ok
        off = angular_error(r.normals, ref.normals, both)[both]
        if check:
            assert r.checks["redone"] > 0.2 * both.sum()
            assert np.percentile(off, 95) < 0.5, np.percentile(off, 95)
        else:  # without the re-solve, 3 warm iterations from the wrong scene stay wrong on many pixels
            assert np.percentile(off, 95) > 2.0, np.percentile(off, 95)


def test_textured_frames_pass_and_noise_does_not(device):
    """Albedo texture down to single pixels cancels in the shading ratios; noise does not."""
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    sc = make_scene("bumps", 48, "perspective")
    checker = np.where((np.indices(sc.mask.shape).sum(0) % 2) == 0, 0.15, 0.95)
    sc.albedo[:] = checker[..., None] * np.array([1.0, 0.8, 0.6])
    mat = Material.default_for("lambertian")
    L = default_lights("directional", 3)
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=sc.mask, config=StreamConfig(output="numpy"), device=device)
    for bits in (8, 16):
        full = 2**bits - 1
        f = np.round(np.clip(render(sc, mat, L, bits=bits), 0, 1) * full).astype(np.uint8 if bits == 8 else np.uint16)
        r = st.run(f)
        assert r.ok, r.error
        assert r.checks["noise_ratio"] < 0.03, r.checks
    rng = np.random.default_rng(0)
    r = st.run(rng.integers(0, 65536, f.shape[:3]).astype(np.uint16))
    assert not r.ok and "noise" in r.error


def test_numpy_output_is_a_copy(device):
    from gpps.pipeline.stream import Stream, StreamConfig

    sc, mat, L, mask, frames, truth = _frames(n=4)
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="numpy"), device=device)
    first = st.run(frames[0])
    kept = first.normals.copy()
    st.run(frames[3])
    np.testing.assert_array_equal(first.normals, kept)
    dev = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="device", ring=1),
                 device=device)
    r0 = dev.run(frames[0]).numpy()
    kept = r0.normals.copy()
    dev.run(frames[3])
    np.testing.assert_array_equal(r0.normals, kept)


def test_negative_device_frame_is_an_error(device):
    from gpps._runtime import warp
    from gpps.pipeline.stream import Stream, StreamConfig

    wp = warp()
    sc, mat, L, mask, frames, truth = _frames(n=1)
    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(output="numpy"), device=device)
    f = frames[0].astype(np.float32) / 65535 - 0.25
    r = st.run(wp.array(f, dtype=wp.float32, device=device))
    assert not r.ok and ">= 0" in r.error
    assert st.run(frames[0]).ok


def _numpy_stats(images, mask, inten, lit_level, saturation):
    """The frame statistics from their definitions (gpps.kernels.stream.frame_stats)."""
    from gpps.kernels import stream as ks

    raw = images * inten[:, None, None, :]
    m = mask.astype(bool)
    n = images.shape[0]
    lit = (raw.mean(-1) > lit_level)[:, m].sum()
    sat = (raw.max(-1) >= saturation)[:, m].sum()
    grey = images.mean(-1)
    tot = grey.sum(0)
    K = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float64)
    h, w = m.shape
    hf = hfg = 0.0
    for i in range(1, h - 1):
        for j in range(1, w - 1):
            win = (slice(i - 1, i + 2), slice(j - 1, j + 2))
            if i % ks.HF_STEP_I == 0 and j % ks.HF_STEP_J == 0 and m[win].all() and (tot[win] > lit_level * n).all():
                r = n * grey[:, win[0], win[1]] / tot[win]  # shading ratios: the albedo cancels
                wgt = tot[i, j] / n
                hf += wgt * np.abs((r * K).sum(axis=(1, 2))).sum()
                hfg += wgt * n
    return {"lit": lit, "sat": sat, "grey": grey[:, m].sum(), "hf": hf, "hf_grey": hfg}


@pytest.mark.parametrize("shape", [(3, 13, 21), (4, 9, 8)])
def test_frame_stats_kernel_matches_numpy(device, shape):
    from gpps._runtime import warp
    from gpps.kernels import stream as ks

    wp = warp()
    rng = np.random.default_rng(3)
    n, h, w = shape
    images = rng.uniform(0, 1.2, (n, h, w, 3)).astype(np.float32)
    images[0, :3] = 0.0  # unlit
    mask = (rng.random((h, w)) > 0.15).astype(np.uint8)
    inten = rng.uniform(0.5, 1.5, (n, 3)).astype(np.float32)
    stats = wp.zeros((ks.STAT_SLOTS, ks.N_STATS), dtype=wp.float32, device=device)
    wp.launch(ks.frame_stats, dim=(h, -(-w // ks.STAT_CHUNK)),
              inputs=[wp.array(images, dtype=wp.vec3, device=device), wp.array(mask, dtype=wp.uint8, device=device),
                      wp.array(inten, dtype=wp.float32, device=device), 0.05, 0.999],
              outputs=[stats], device=device)
    got = stats.numpy().astype(np.float64).sum(axis=0)
    ref = _numpy_stats(images.astype(np.float64), mask, inten.astype(np.float64), 0.05, 0.999)
    assert got[ks.STAT_LIT] == ref["lit"] and got[ks.STAT_SATURATED] == ref["sat"]
    for slot, key in ((ks.STAT_GREY, "grey"), (ks.STAT_HF, "hf"), (ks.STAT_HF_GREY, "hf_grey")):
        np.testing.assert_allclose(got[slot], ref[key], rtol=1e-5)
    # the residual sum and the jump marks
    res = rng.uniform(0, 1, (h, w)).astype(np.float32)
    prev = rng.uniform(0, 0.2, (h, w)).astype(np.float32)
    thr, factor = 0.3, 3.0
    stats.zero_()
    redo = wp.zeros((h, w), dtype=wp.uint8, device=device)
    r_d, m_d = wp.array(res, device=device), wp.array(mask, dtype=wp.uint8, device=device)
    flags = rng.integers(0, 32, (h, w)).astype(np.int32)  # (FLAG_FEW_OBSERVATIONS = 2: left out of the sum)
    wp.launch(ks.residual_sum, dim=(h, -(-w // ks.STAT_CHUNK)), inputs=[r_d, m_d, wp.array(flags, dtype=wp.int32, device=device)],
              outputs=[stats], device=device)
    wp.launch(ks.mark_jumps, dim=(h, w), inputs=[r_d, wp.array(prev, device=device), m_d,
                                                wp.array([thr], dtype=wp.float32, device=device), factor],
              outputs=[redo, stats], device=device)
    got = stats.numpy().astype(np.float64).sum(axis=0)
    want = (mask > 0) & (res > np.maximum(thr, factor * prev))
    det = (mask > 0) & ((flags & FLAG_FEW_OBSERVATIONS) == 0)
    np.testing.assert_allclose(got[ks.STAT_RESIDUAL], res[det].sum(), rtol=1e-5)
    assert got[ks.STAT_DETERMINED] == det.sum() and 0 < det.sum() < (mask > 0).sum()
    np.testing.assert_array_equal(redo.numpy() > 0, want)
    assert got[ks.STAT_REDONE] == want.sum()


def test_stream_without_a_mask_on_a_dark_background(device):
    """A stream given no mask (every pixel) of an object on a black background accepts its frames: the pixels
    with no lit observation borrow their neighbours' albedo and misfit their black observations, which said
    nothing about the model but, counted in the residual check, rejected every frame ("the model does not fit
    the frame, 152% of the signal").  The object's normals are those of the masked stream."""
    import gpps

    sc = gpps.make_scene("sphere", 32, "orthographic")
    L = gpps.default_lights("directional", 3)
    frame = (np.clip(gpps.render(sc, gpps.Material("lambertian"), L, bits=16), 0, 1) * 65535).astype(np.uint16)
    lights = gpps.DirectionalLights(L.directions)
    got = {}
    for name, mask in (("all", None), ("object", sc.mask)):
        st = gpps.Stream((32, 32), sc.camera, lights, gpps.Material("lambertian"), mask=mask,
                         config=gpps.StreamConfig(output="numpy", integrate=False), device=device)
        rs = [st.run(frame) for _ in range(3)]
        assert all(r.ok for r in rs), [r.error for r in rs]
        assert 0.3 < rs[-1].checks["determined_fraction"] < 1.0  # (the background, attached shadows)
        got[name] = rs[-1].normals
        st.close()
    det = sc.mask & (frame.astype(np.float64).mean(-1) > 100).all(0)  # the object's pixels lit by all 3 lights
    assert normal_errors(got["all"], sc.normals, det)["mean"] < 0.5
    assert angular_error(got["all"], got["object"], det).max() < 0.1
    # a frame of which no pixel has 3 lit observations is refused by name
    dark = frame.copy()
    dark[2] = 0
    st = gpps.Stream((32, 32), sc.camera, lights, gpps.Material("lambertian"), config=gpps.StreamConfig(output="numpy", integrate=False),
                     device=device)
    r = st.run(dark)
    assert not r.ok and "3 lit observations" in r.error, r.error


def test_a_closed_stream_refuses_frames(device):
    """close() releases the solver's buffers (back to the pool), the integrator's fields and the graphs, as the
    stage protocol says; the stream then refuses frames by name instead of computing into released buffers
    (before, close() released nothing and the stream kept running)."""
    import gpps

    sc = gpps.make_scene("sphere", 16, "orthographic")
    L = gpps.default_lights("directional", 3)
    frame = (np.clip(gpps.render(sc, gpps.Material("lambertian"), L, bits=16), 0, 1) * 65535).astype(np.uint16)
    with gpps.Stream((16, 16), sc.camera, gpps.DirectionalLights(L.directions), gpps.Material("lambertian"),
                     mask=sc.mask, config=gpps.StreamConfig(output="numpy"), device=device) as st:
        assert st.run(frame).ok
        solver = st.solver
    with pytest.raises(ValueError, match="Stream: closed"):
        st.run(frame)
    with pytest.raises(ValueError, match="Stream: closed"):
        next(st.iterate([frame]))
    with pytest.raises(ValueError, match="PixelSolver: closed"):
        solver.step()
    st.close()  # (twice: nothing)
