"""The stream's accuracy on rendered scenes: grey and RGB frames against the offline solve and the truth.

Issue 20: ``perf/bench.py`` reported 5.96-5.98 deg for the stream at every size while RGB frames of the
same scene gave 0.007 deg.  The bench averaged its Blinn-Phong renders to grey frames; with 3 lights a
grey frame gives each pixel 3 observations for 3 unknowns (2 for the normal, the albedo), and the
specular lobe makes the system have other exact roots, which the stream and the offline solve both
find (the stream's grey path is right: it matches the offline solve wherever the data determine the
normal, tested here with 4 lights).  These tests pin the three facts down.
"""

import sys
from pathlib import Path

import numpy as np

from gpps.host.metrics import normal_errors

SIZE = 40


def _angles(a, b, mask):
    """Per-pixel angle (deg) between two (H, W, 3) normal maps inside ``mask``."""
    return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1.0, 1.0)))[mask]


def _render(n_lights, device):
    """Bumps, perspective, Blinn-Phong, ``n_lights`` directional lights: (scene, material, lights, float RGB)."""
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.scenes import make_scene
    from gpps.material import Material

    sc = make_scene("bumps", SIZE, "perspective")
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", n_lights)
    return sc, mat, L, render(sc, mat, L, device=device)


def _stream(sc, mat, L, frame, device):
    from gpps.pipeline.stream import Stream, StreamConfig

    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=sc.mask, config=StreamConfig(output="numpy"), device=device)
    r = st.run(frame)
    assert r.ok, r.error
    return st, r


def _grey16(img):
    """A grey camera's uint16 frame of RGB renders (the channel mean, clipped and rounded)."""
    return np.round(np.clip(img.mean(-1), 0, 1) * 65535).astype(np.uint16)


def test_grey_frames_match_rgb_and_offline(device):
    """4 lights (a grey frame determines the normal): grey stream = offline solve of the same data = truth."""
    from gpps.flows.photometric import solve_normals
    from gpps.lights import DirectionalLights

    sc, mat, L, img = _render(4, device)
    m = sc.mask
    grey = _grey16(img)
    st, rg = _stream(sc, mat, L, grey, device)
    # the grey conversion: each grey value in all three channels, divided by full scale and the intensities
    inten = np.asarray(L.intensities, np.float32)
    ref = grey[..., None].astype(np.float32) / 65535 / inten[:, None, None, :]
    np.testing.assert_allclose(st.solver.images.numpy(), np.broadcast_to(ref, (*grey.shape, 3)), rtol=1e-6, atol=0)
    _, rc = _stream(sc, mat, L, np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), device)
    off = solve_normals(grey.astype(np.float32) / 65535 / inten[:, :1, None], m, DirectionalLights(L.directions),
                        camera=sc.camera, material=mat, device=device)
    # 16-bit quantisation (1.5e-5 of full scale) moves a normal by hundredths of a degree at most.  Measured
    # on the CPU at 40^2: MAEN 0.0010 deg (grey stream and offline alike, RGB stream 0.0005), 99th
    # percentile of the angle grey stream vs offline grey solve and vs RGB stream 0.028 deg, albedo 6e-5.
    # The bounds keep a 3.5x margin or more (for CUDA's other float rounding) and sit 60x below the
    # 6 deg that grey 3-light frames give (test below)
    assert normal_errors(rg.normals, sc.normals, m)["mean"] < 0.01
    assert np.percentile(_angles(rg.normals, off.normals, m), 99) < 0.1
    assert np.percentile(_angles(rg.normals, rc.normals, m), 99) < 0.1
    # a grey frame fits a grey albedo: the channel mean of the true one (uniform (0.6, 0.5, 0.4))
    assert np.percentile(np.abs(rg.albedo[m] - sc.albedo[m].mean(-1, keepdims=True)).max(-1), 99) < 5e-4


def test_bench_frames_give_the_offline_accuracy(device):
    """The frame the bench times and scores (perf/_common.bumps_frame): the stream's MAEN equals the offline one.

    The offline reference is the solve of the float (unquantised) RGB render, so a frame construction
    that loses information (issue 20's grey mean: 5.96 deg) fails here, not only a wrong stream.
    """
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "perf"))
    from _common import bumps_frame

    from gpps.flows.photometric import solve_normals
    from gpps.lights import DirectionalLights

    sc, mat, L, frame = bumps_frame(SIZE, device)
    _, r = _stream(sc, mat, L, frame, device)
    _, _, _, img = _render(3, device)
    off = solve_normals(img / np.asarray(L.intensities, np.float32)[:, None, None, :], sc.mask,
                        DirectionalLights(L.directions), camera=sc.camera, material=mat, device=device)
    e_stream = normal_errors(r.normals, sc.normals, sc.mask)["mean"]
    e_off = normal_errors(off.normals, sc.normals, sc.mask)["mean"]
    # measured on the CPU at 40^2: stream 0.0164 deg, offline 0.0156 (a few rim pixels in the same local
    # minimum carry most of it); the grey frames of issue 20 gave 6.0 deg here
    assert e_off < 0.05 and e_stream < 0.05, (e_stream, e_off)
    assert abs(e_stream - e_off) < 0.02, (e_stream, e_off)


def test_three_grey_observations_have_spurious_exact_roots(device):
    """Why the bench was wrong: a 3-light grey frame of this scene does not determine the normal.

    The stream's solution fits the grey frame as well as the truth does (re-rendered independently by
    the Renderer), yet a large share of its normals is degrees away from the truth: both are exact
    roots of the 3 equations.  The same scene as RGB frames is solved to < 0.05 deg.
    """
    from gpps.lights import DirectionalLights
    from gpps.pipeline.render import Renderer

    sc, mat, L, img = _render(3, device)
    m = sc.mask
    grey = _grey16(img)
    _, r = _stream(sc, mat, L, grey, device)
    ang = _angles(r.normals, sc.normals, m)
    rd = Renderer(sc.mask.shape, sc.camera, DirectionalLights(L.directions), mat, device=device)
    fit = rd.run(sc.depth, m, np.ascontiguousarray(r.albedo, np.float32),
                 normals=np.ascontiguousarray(r.normals, np.float32))
    data = grey.astype(np.float32) / 65535 / np.asarray(L.intensities, np.float32)[:, :1, None]
    truth = rd.run(sc.depth, m, np.ascontiguousarray(np.repeat(sc.albedo.mean(-1, keepdims=True), 3, -1)),
                   normals=np.ascontiguousarray(sc.normals, np.float32))
    off_root = ang > 1.0
    dev_fit = np.abs(fit.mean(-1) - data)[:, m].max(0)
    dev_truth = np.abs(truth.mean(-1) - data)[:, m].max(0)
    # measured on the CPU at 40^2: 32 % of the pixels > 1 deg off (MAEN 6.0 deg), and they fit the frame to
    # 2.0e-6 while the truth fits it to 9.6e-6 (its 16-bit rounding: half a step is 1/65535/2/0.8 = 9.5e-6)
    # of a mean signal 0.45.  Bound: within 5e-5 (2.6 steps of 16 bits), as the truth is
    assert off_root.mean() > 0.1, off_root.mean()
    assert dev_truth.max() < 5e-5 and dev_fit[off_root].max() < 5e-5, (dev_truth.max(), dev_fit[off_root].max())
    assert normal_errors(r.normals, sc.normals, m)["mean"] > 1.0
    _, rc = _stream(sc, mat, L, np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), device)
    assert normal_errors(rc.normals, sc.normals, m)["mean"] < 0.05
