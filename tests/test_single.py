"""Issue 8: the shipped network (numpy inference against an independent reference, loads without
PyTorch), the photometric objective against numpy, light estimation, and ``gpps single`` end to end."""

import json
import subprocess
import sys

import numpy as np
import pytest

from gpps.nn.model import ARCH, DEFAULT_WIDTHS, WEIGHTS_PATH, SingleNet, arch, conv3x3, layers, load_weights, prepare_input


# --------------------------------------------------------------------------- independent numpy reference


def _conv_ref(x, w, b):
    """3x3 cross-correlation, zero padding 1, by sliding windows + einsum (not the shifted matmuls)."""
    xp = np.pad(x.astype(np.float64), ((0, 0), (1, 1), (1, 1)))
    win = np.lib.stride_tricks.sliding_window_view(xp, (3, 3), axis=(1, 2))  # (C, H, W, 3, 3)
    return np.einsum("chwij,ocij->ohw", win, w.astype(np.float64)) + b[:, None, None]


def _forward_ref(p, x, widths=DEFAULT_WIDTHS):
    enc, dec, _, _ = layers(widths)
    relu = lambda a: np.maximum(a, 0.0)  # noqa: E731
    block = lambda name, a: relu(_conv_ref(relu(_conv_ref(a, p[f"{name}.conv1.weight"], p[f"{name}.conv1.bias"])),  # noqa: E731
                                           p[f"{name}.conv2.weight"], p[f"{name}.conv2.bias"]))
    skips = []
    per = [im.astype(np.float64) for im in (x[None] if x.ndim == 3 else x)]  # K images: fused by their maximum
    for k, (name, _, _) in enumerate(enc):
        for i, a in enumerate(per):
            if k:
                c, h, w = a.shape
                a = a.reshape(c, h // 2, 2, w // 2, 2).mean((2, 4))
            per[i] = block(name, a)
        skips.append(np.maximum.reduce(per))
    a = skips[-1]
    g = relu(p["glob.fc1.weight"] @ a.mean((1, 2)) + p["glob.fc1.bias"])
    g = p["glob.fc2.weight"] @ g + p["glob.fc2.bias"]
    a = relu(a + g[:, None, None])
    for (name, _, _), s in zip(dec, skips[-2::-1]):
        up = np.kron(a, np.ones((1, 2, 2)))
        a = block(name, np.concatenate([up, s], 0))
    return _conv_ref(a, p["head.weight"], p["head.bias"])


def test_conv3x3_against_reference():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(5, 7, 9)).astype(np.float32)
    w = rng.normal(size=(4, 5, 3, 3)).astype(np.float32)
    b = rng.normal(size=4).astype(np.float32)
    np.testing.assert_allclose(conv3x3(x, w, b), _conv_ref(x, w, b), rtol=1e-4, atol=1e-4)
    # one explicit pixel: out[o, i, j] = b + sum w[o, c, di, dj] x[c, i + di - 1, j + dj - 1]
    o, i, j = 2, 0, 4
    v = b[o] + sum(w[o, c, di, dj] * x[c, i + di - 1, j + dj - 1]
                   for c in range(5) for di in range(3) for dj in range(3) if 0 <= i + di - 1 < 7)
    assert conv3x3(x, w, b)[o, i, j] == pytest.approx(v, rel=1e-4)


def test_forward_against_reference_random_weights():
    rng = np.random.default_rng(1)
    params = {k: (rng.normal(size=s) * (0.5 / np.sqrt(np.prod(s[1:])) if len(s) > 1 else 0.1)).astype(np.float32)
              for k, s in ARCH.items()}
    net = SingleNet(params, {"size": 32})
    x = rng.uniform(0, 1, (4, 32, 48)).astype(np.float32)
    np.testing.assert_allclose(net.forward(x), _forward_ref(params, x), rtol=1e-3, atol=1e-4)
    with pytest.raises(ValueError, match="multiples of 16"):
        net.forward(x[:, :30])


def test_other_widths_forward_and_load(tmp_path):
    """A network of other widths and depth (four scales): its layer table, forward against the reference, the
    input multiple, and a weights file naming its widths loads (one of the wrong shapes does not)."""
    widths = (6, 10, 12, 20)
    enc, dec, glob, head = layers(widths)
    assert [c for _, _, c in enc] == list(widths) and enc[0][1] == 4
    assert [(n, i, o) for n, i, o in dec] == [("dec2", 32, 12), ("dec1", 22, 10), ("dec0", 16, 6)]
    assert glob == [("glob.fc1", 20, 20), ("glob.fc2", 20, 20)] and head == ("head", 6, 4)
    rng = np.random.default_rng(3)
    params = {k: (rng.normal(size=s) * (0.5 / np.sqrt(np.prod(s[1:])) if len(s) > 1 else 0.1)).astype(np.float32)
              for k, s in arch(widths).items()}
    net = SingleNet(params, {"size": 16, "widths": list(widths)})
    assert net.multiple == 8
    x = rng.uniform(0, 1, (4, 16, 24)).astype(np.float32)
    np.testing.assert_allclose(net.forward(x), _forward_ref(params, x, widths), rtol=1e-3, atol=1e-4)
    with pytest.raises(ValueError, match="multiples of 8"):
        net.forward(x[:, :12])
    n, h = net.predict(rng.uniform(0, 1, (21, 30, 3)).astype(np.float32))
    assert n.shape == (21, 30, 3) and h.shape == (21, 30)
    path = tmp_path / "w.npz"
    np.savez(path, meta=np.array(json.dumps({"size": 16, "widths": list(widths)})), **params)
    loaded = SingleNet.load(path)
    assert loaded.widths == widths and np.array_equal(loaded.forward(x), net.forward(x))
    np.savez(path, meta=np.array(json.dumps({"size": 16})), **params)  # no widths: the default's shapes
    with pytest.raises(ValueError, match="expected shape"):
        load_weights(path)
    for bad in ((16,), (16, 0), "ab", (8, 2.5)):
        with pytest.raises(ValueError, match="widths"):
            layers(bad)


def test_fused_images_forward_and_predict_many():
    """K images of one object: the numpy forward against the reference (per-image encoder, elementwise maximum
    at every scale), the order of the images free, one image the plain network; the flow uses the fused
    answer when the network was trained so (meta "fusion")."""
    widths = (6, 10, 12, 20)
    rng = np.random.default_rng(4)
    params = {k: (rng.normal(size=s) * (0.5 / np.sqrt(np.prod(s[1:])) if len(s) > 1 else 0.1)).astype(np.float32)
              for k, s in arch(widths).items()}
    net = SingleNet(params, {"size": 16, "widths": list(widths), "fusion": "max"})
    assert net.fusion and not SingleNet(params, {"widths": list(widths)}).fusion
    x = rng.uniform(0, 1, (3, 4, 16, 24)).astype(np.float32)
    out = net.forward(x)
    np.testing.assert_allclose(out, _forward_ref(params, x, widths), rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(net.forward(x[[2, 0, 1]]), out, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(net.forward(x[:1]), net.forward(x[0]))
    with pytest.raises(ValueError, match="K, 4, H, W"):
        net.forward(x[:, :3])
    imgs = rng.uniform(0, 1, (3, 21, 30, 3)).astype(np.float32)
    m = np.ones((21, 30), bool)
    m[:3] = False
    n3, h3 = net.predict_many(imgs, m, tta="flips")
    assert n3.shape == (21, 30, 3) and np.allclose(np.linalg.norm(n3[m], axis=-1), 1, atol=1e-4) and np.all(n3[~m] == 0)
    np.testing.assert_allclose(net.predict_many(imgs[::-1], m, tta="flips")[0], n3, atol=1e-5)
    np.testing.assert_array_equal(net.predict_many(imgs[:1], m)[0], net.predict(imgs[0], m)[0])
    with pytest.raises(ValueError, match="images"):
        net.predict_many([imgs[0], imgs[1][:20]], m)
    from gpps.flows.single import SingleConfig, reconstruct_single

    res = reconstruct_single(imgs, m, config=SingleConfig(rounds=0, integrate=False, tta="none"), net=net)
    np.testing.assert_allclose(res.normals_net, net.predict_many(imgs, m)[0], atol=1e-6)
    plain = SingleNet(params, {"size": 16, "widths": list(widths)})  # not trained to fuse: the mean of one-image answers
    res = reconstruct_single(imgs, m, config=SingleConfig(rounds=0, integrate=False, tta="none"), net=plain)
    mean = sum(plain.predict(im, m)[0] for im in imgs)
    mean[m] /= np.linalg.norm(mean[m], axis=-1, keepdims=True)
    np.testing.assert_allclose(res.normals_net, mean, atol=1e-5)


def test_shipped_weights_and_their_size():
    params, meta = load_weights()
    assert WEIGHTS_PATH.stat().st_size < 20e6
    assert set(arch(meta.get("widths", DEFAULT_WIDTHS))) == set(params)
    assert meta["size"] == 128 and meta["steps"] > 1000
    assert meta["numpy_vs_torch_max_abs"] < 1e-2  # measured at export, on the training machine


def test_weights_load_without_torch_or_network(tmp_path):
    code = (
        "import sys, socket\n"
        "sys.modules['torch'] = None\n"  # any import of torch now raises ImportError
        "def _no_net(*a, **k):\n    raise RuntimeError('network access')\n"
        "socket.socket.connect = _no_net\n"
        "import numpy as np\n"
        "from gpps.nn.model import SingleNet\n"
        "net = SingleNet.load()\n"
        "img = np.random.default_rng(0).uniform(0, 1, (40, 52, 3)).astype(np.float32)\n"
        "n, h = net.predict(img)\n"
        "assert n.shape == (40, 52, 3) and h.shape == (40, 52)\n"
        "assert np.allclose(np.linalg.norm(n, axis=-1), 1, atol=1e-4) and np.all(n[..., 2] > 0)\n"
        "assert 'torch' not in sys.modules or sys.modules['torch'] is None\n"
        "print('ok')\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("ok")


def test_prepare_input_scale_free():
    rng = np.random.default_rng(2)
    img = rng.uniform(0, 1, (16, 16, 3))
    m = np.zeros((16, 16), bool)
    m[2:14, 3:15] = True
    a = prepare_input(img, m)
    b = prepare_input(img * 37.0, m)
    np.testing.assert_allclose(a, b, rtol=1e-5)
    assert a.shape == (4, 16, 16) and np.all(a[:3, ~m] == 0) and np.all(a[3] == m)
    with pytest.raises(ValueError, match="mask"):
        prepare_input(img, np.zeros((16, 16), bool))



def test_prepare_images_refuses_empty_input():
    """No image, or images of no pixels: a ValueError naming ``images`` (numpy's reduction error before)."""
    from gpps.host.single import prepare_images

    for shape in ((0, 16, 16, 3), (2, 0, 16, 3), (0, 16, 16)):
        with pytest.raises(ValueError, match="images: expected at least one image"):
            prepare_images(np.zeros(shape, np.float32))
    I, m = prepare_images(np.full((2, 8, 8, 3), 0.5, np.float32))
    assert I.shape == (2, 8, 8, 3) and m.all()

def _sphere_capture(size=64, brdf="lambertian"):
    from gpps.lights import DirectionalLights, ring_directions
    from gpps.material import Material
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import render

    sc = make_scene("sphere", size, "orthographic", albedo="texture", seed=5)
    lights = DirectionalLights(ring_directions(3, 35.0), np.full((3, 3), 0.8))
    mat = Material(brdf, ks=0.0 if brdf == "lambertian" else 0.3, shininess=30.0)
    return sc, lights, render(sc, mat, lights, device=None)  # CUDA where present: the GPU kit has no Warp CPU


def test_network_beats_flat_plane_on_a_sphere():
    from gpps.host.metrics import normal_errors

    sc, _, imgs = _sphere_capture(64)
    n, h = SingleNet.load().predict(imgs[0], sc.mask)
    flat = np.zeros_like(n)
    flat[..., 2] = 1
    e_net = normal_errors(n, sc.normals, sc.mask)["mean"]
    e_flat = normal_errors(flat, sc.normals, sc.mask)["mean"]
    assert e_net < 0.5 * e_flat, (e_net, e_flat)
    # the height is larger at the centre (nearer the camera) than at the rim
    c = h[28:36, 28:36].mean()
    assert c > h[sc.mask].mean()


def test_photometric_objective_against_numpy(device):
    import warp as wp

    from gpps._runtime import warp
    from gpps.kernels import cuckoo as ck

    warp()
    rng = np.random.default_rng(3)
    P, N = 50, 3
    x = np.concatenate([rng.uniform(-0.6, 0.6, (P, 2)), rng.uniform(0.1, 1.0, (P, 3))], 1).astype(np.float32)
    ldir = rng.normal(size=(N, 3)) + [0, 0, 2]
    ldir /= np.linalg.norm(ldir, axis=1, keepdims=True)
    lrgb = rng.uniform(0.5, 1.0, (N, 3))
    I = rng.uniform(0, 1, (N, P, 3)).astype(np.float32)
    prior = rng.normal(size=(P, 3)) + [0, 0, 3]
    prior /= np.linalg.norm(prior, axis=1, keepdims=True)
    view = np.tile([0.0, 0.0, 1.0], (P, 1))
    ks, shin, pw = 0.3, 20.0, 0.05
    # numpy reference
    n = np.stack([x[:, 0], x[:, 1], np.sqrt(1 - x[:, 0] ** 2 - x[:, 1] ** 2)], 1).astype(np.float64)
    ref = np.zeros(P)
    for k in range(N):
        a = n @ ldir[k]
        hv = ldir[k] + view
        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
        s = np.where(a > 0, np.maximum(np.sum(n * hv, 1), 0) ** shin, 0.0)
        model = lrgb[k] * (x[:, 2:] * np.maximum(a, 0)[:, None] + ks * s[:, None])
        ref += np.sum((I[k] - model) ** 2, 1)
    ref += pw * np.sum((n - prior) ** 2, 1)
    d = ck.PhotoData()
    d.images = wp.array(I, dtype=wp.vec3, device=device)
    d.view = wp.array(view.astype(np.float32), dtype=wp.vec3, device=device)
    d.prior = wp.array(prior.astype(np.float32), dtype=wp.vec3, device=device)
    d.light_dir = wp.array(ldir.astype(np.float32), dtype=wp.vec3, device=device)
    d.light_rgb = wp.array(lrgb.astype(np.float32), dtype=wp.vec3, device=device)
    d.weight = wp.array(np.ones(P, np.float32), dtype=wp.float32, device=device)
    d.ks, d.shininess, d.prior_weight, d.albedo_from_normal = ks, shin, pw, 0
    out = wp.zeros(P, dtype=wp.float32, device=device)
    wp.launch(ck.photometric_error_kernel, dim=P, inputs=[wp.array(x, dtype=ck.vec5, device=device), d], outputs=[out],
              device=device)
    np.testing.assert_allclose(out.numpy(), ref, rtol=2e-4, atol=1e-5)


def test_estimate_lights_exact_normals():
    from gpps.host.single import estimate_lights, prepare_images

    sc, lights, imgs = _sphere_capture(48)
    I, m = prepare_images(imgs, sc.mask)
    d, rgb, kd, ks = estimate_lights(I[:, m], sc.normals[m], np.tile([0, 0, 1.0], (int(m.sum()), 1)), specular=False)
    err = np.degrees(np.arccos(np.clip(np.sum(d * lights.directions, 1), -1, 1)))
    assert np.all(err < 1.0), err
    # equal lights: equal intensities up to a colour shared with the albedo (per channel)
    np.testing.assert_allclose(rgb / rgb[:1], 1.0, atol=0.02)


def test_reconstruct_single_refines_and_is_reproducible(device):
    from gpps.host.metrics import normal_errors
    from gpps.pipeline.cuckoo import CuckooConfig
    from gpps.flows.single import SingleConfig, reconstruct_single

    sc, _, imgs = _sphere_capture(48)
    # the search's own refinement (weak fixed prior, every pixel kept): the defaults ("map", min_lit=3) trust the
    # network more and move this sphere by < 0.1 deg (perf/single_dev.py is where they were chosen)
    cfg = SingleConfig(cuckoo=CuckooConfig(nests=8, generations=30, seed=2), integrate=False, prior_weight=0.002,
                       min_lit=0)
    a = reconstruct_single(imgs, sc.mask, config=cfg, device=device)
    b = reconstruct_single(imgs, sc.mask, config=cfg, device=device)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert a.objective[0]["after"] < a.objective[0]["before"]
    e_net = normal_errors(a.normals_net, sc.normals, a.mask)["mean"]
    e_ref = normal_errors(a.normals, sc.normals, a.mask)["mean"]
    assert e_ref < e_net, (e_net, e_ref)
    one = reconstruct_single(imgs[0], sc.mask, config=SingleConfig(rounds=0, integrate=False))
    assert one.normals.shape == sc.normals.shape and one.objective == []


def _gbr_setup(brdf, size=40, lam=0.75, mu=0.06, nu=-0.04):
    """Sphere normals and Blinn-Phong / Lambertian intensities (numpy), and the same normals and lights
    moved along a bas-relief (what a flattening prior and lights fitted to it look like)."""
    from gpps.lights import ring_directions
    from gpps.host.single import through_gbr as _through_gbr

    u = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(u, -u)
    m = x**2 + y**2 < 0.97
    n = np.stack([x[m], y[m], np.sqrt(1 - x[m] ** 2 - y[m] ** 2)], 1)
    L = ring_directions(3, 35.0)
    v = np.tile([0.0, 0.0, 1.0], (len(n), 1))
    kd = np.random.default_rng(4).uniform(0.4, 0.8, (len(n), 3))
    ks = 0.3 if brdf == "blinn-phong" else 0.0
    I = np.stack([kd * np.maximum(n @ l, 0)[:, None] + ks * _bp(n, l, 40.0)[:, None] for l in L])
    G = np.array([[1.0, 0, 0], [0, 1.0, 0], [mu, nu, lam]])
    n_b = _through_gbr(n, G).astype(np.float64)
    gl = L @ G.T
    e = np.linalg.norm(gl, axis=1)
    kd_b = kd * np.linalg.norm(n @ np.linalg.inv(G), axis=1)[:, None] * e.mean()
    rgb_b = np.repeat((e / e.mean())[:, None], 3, 1)
    # the moved normals and lights explain the Lambertian part exactly
    lam_b = np.stack([rgb_b[k] * kd_b * np.maximum(n_b @ (gl[k] / e[k]), 0)[:, None] for k in range(3)])
    lam_t = np.stack([kd * np.maximum(n @ l, 0)[:, None] for l in L])
    np.testing.assert_allclose(lam_b, lam_t, atol=1e-6)
    return I, n, L, v, n_b, gl / e[:, None], rgb_b, kd_b


def _bp(n, l, shininess):
    h = (l + [0, 0, 1.0]) / np.linalg.norm(l + [0, 0, 1.0])
    return np.where(n @ l > 0, np.maximum(n @ h, 0) ** shininess, 0.0)


def _deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def test_fit_highlights_undoes_a_bas_relief():
    from gpps.host.single import fit_highlights

    I, n, L, v, n_b, l_b, rgb_b, kd_b = _gbr_setup("blinn-phong")
    assert _deg(l_b, L).min() > 5 and _deg(n_b, n).mean() > 4  # the start is well off
    fit = fit_highlights(I, n_b, v, l_b, rgb_b, kd_b, prior_deg=10.0)
    assert fit.accepted and fit.info["peak"] == pytest.approx([1, 1, 1], abs=0.05)
    assert np.all(_deg(fit.directions, L) < 1.0), _deg(fit.directions, L)
    assert _deg(fit.normals, n).mean() < 0.5
    assert fit.ks == pytest.approx(0.3, rel=0.1) and fit.shininess == pytest.approx(40, rel=0.1)
    # the Lambertian part of every image is unchanged
    def lam(d, e, a, nn):
        return np.stack([e[k] * a * np.maximum(nn @ d[k], 0)[:, None] for k in range(3)])

    np.testing.assert_allclose(lam(fit.directions, fit.intensities, fit.albedo, fit.normals),
                               lam(l_b, rgb_b, kd_b, n_b), atol=1e-4)


def test_fit_highlights_without_highlights_changes_nothing():
    from gpps.host.single import fit_highlights

    I, _, _, v, n_b, l_b, rgb_b, kd_b = _gbr_setup("lambertian")
    I = I + np.random.default_rng(0).normal(0, 0.01, I.shape)  # shading noise, no highlight
    fit = fit_highlights(I, n_b, v, l_b, rgb_b, kd_b, shininess=30.0)
    assert not fit.accepted and fit.ks == 0.0 and fit.shininess == 30.0
    np.testing.assert_array_equal(fit.gbr, np.eye(3))
    np.testing.assert_allclose(fit.directions, l_b, atol=1e-6)
    np.testing.assert_allclose(fit.normals, n_b, atol=1e-6)
    with pytest.raises(ValueError, match="view"):
        fit_highlights(I, n_b, v[:-1], l_b, rgb_b, kd_b)
    with pytest.raises(ValueError, match="prior_deg"):
        fit_highlights(I, n_b, v, l_b, rgb_b, kd_b, prior_deg=0.0)
    with pytest.raises(ValueError, match="shininess_range"):
        fit_highlights(I, n_b, v, l_b, rgb_b, kd_b, shininess_range=(10.0, 5.0))


def test_refinement_beats_the_network_on_a_blinn_phong_sphere(device):
    """Issue 8 regression: lights fitted to the network's (flattened) normals were ~10 deg too oblique
    and the refinement of a Blinn-Phong sphere ended worse than the network (64^2: 8.2 -> 9.0 deg).  The
    refinement must beat the network by a fifth: the issue-8 network went 8.0 -> 2.9 deg here, the session-30
    network (better on physically based renders, its lights from these three images less exact) 7.5 -> 5.8."""
    from gpps.host.metrics import normal_errors
    from gpps.pipeline.cuckoo import CuckooConfig
    from gpps.pipeline.render import quantise
    from gpps.flows.single import SingleConfig, reconstruct_single
    from gpps.host.single import estimate_lights, prepare_images

    sc, lights, imgs = _sphere_capture(64, "blinn-phong")
    cfg = SingleConfig(cuckoo=CuckooConfig(nests=8, generations=30, seed=2), integrate=False)
    res = reconstruct_single(quantise(imgs, 8), sc.mask, config=cfg, device=device)
    e_net = normal_errors(res.normals_net_first, sc.normals, res.mask)["mean"]
    e_net3 = normal_errors(res.normals_net, sc.normals, res.mask)["mean"]
    e_ref = normal_errors(res.normals, sc.normals, res.mask)["mean"]
    assert e_ref < 0.8 * min(e_net, e_net3), (e_net, e_net3, e_ref)
    assert res.highlights[0]["accepted"] and res.highlights[0]["lam"] > 1.05  # the network's flattening undone
    err = _deg(res.light_directions, lights.directions)
    m = res.mask
    I, _ = prepare_images(imgs, m)
    d_ls = estimate_lights(I[:, m], res.normals_net[m], np.tile([0, 0, 1.0], (int(m.sum()), 1)), specular=False)[0]
    err_ls = _deg(d_ls, lights.directions)
    assert err.max() < 7.0 and err.mean() < 0.5 * err_ls.mean(), (err, err_ls)


def test_single_config_validation():
    from gpps.flows.single import SingleConfig

    with pytest.raises(ValueError, match="albedo"):
        SingleConfig(albedo="guess")
    with pytest.raises(ValueError, match="lights"):
        SingleConfig(lights="magic")
    with pytest.raises(ValueError, match="rounds"):
        SingleConfig(rounds=-1)
    with pytest.raises(TypeError, match="cuckoo"):
        SingleConfig(cuckoo={"nests": 3})
    with pytest.raises(ValueError, match="specular"):
        SingleConfig(specular="estimate-all")
    with pytest.raises(ValueError, match="shininess_range"):
        SingleConfig(shininess_range=(0.0, 10.0))
    with pytest.raises(ValueError, match="shininess_range"):
        SingleConfig(shininess_range=(50.0, 10.0))
    with pytest.raises(ValueError, match="highlight_prior_deg"):
        SingleConfig(highlight_prior_deg=-1.0)
    assert SingleConfig(shininess_range=[2, 100]).shininess_range == (2.0, 100.0)


def test_cli_single(tmp_path, capsys):
    from gpps.cli import main
    from gpps.io import save_png

    sc, _, imgs = _sphere_capture(32)
    paths = []
    for k in range(3):
        p = tmp_path / f"{k}.png"
        save_png(p, np.clip(imgs[k], 0, 1), bits=8)
        paths.append(str(p))
    save_png(tmp_path / "mask.png", sc.mask.astype(np.uint8) * 255)
    out = tmp_path / "out"
    rc = main(["--device", "cpu", "single", *paths, "--mask", str(tmp_path / "mask.png"), "--out", str(out),
               "--generations", "5", "--nests", "4"])
    assert rc == 0
    from gpps.io.outputs import OUTPUT_FILES

    for f in ("report.json", "normals_net.npy", *OUTPUT_FILES):  # the output set every command writes
        assert (out / f).is_file(), f
    rep = json.loads((out / "report.json").read_text())
    assert rep["depth"]["scale"] == "relative" and rep["depth"]["unit"] == "pixel"
    assert rep["pixels"] == int(sc.mask.sum()) and len(rep["light_directions"]) == 3
    assert rep["network"]["weights"] == "shipped"
    assert main(["single", str(tmp_path / "missing.png"), "--out", str(out)]) == 2
    # --weights: another network (here the shipped one, copied), named in the report; a missing file is an error
    import shutil

    shutil.copy(WEIGHTS_PATH, tmp_path / "net.npz")
    rc = main(["--device", "cpu", "single", *paths, "--mask", str(tmp_path / "mask.png"), "--out", str(tmp_path / "out2"),
               "--generations", "5", "--nests", "4", "--weights", str(tmp_path / "net.npz")])
    assert rc == 0
    rep2 = json.loads((tmp_path / "out2" / "report.json").read_text())
    assert rep2["network"]["weights"] == str(tmp_path / "net.npz")
    assert np.array_equal(np.load(tmp_path / "out2" / "normals_net.npy"), np.load(out / "normals_net.npy"))
    assert main(["--device", "cpu", "single", paths[0], "--weights", str(tmp_path / "none.npz"), "--out", str(tmp_path / "o3")]) == 2
    assert "none.npz" in capsys.readouterr().err and not (tmp_path / "o3").exists()
    for opt, val in (("--pc", "1.5"), ("--nests", "0"), ("--rounds", "-1")):  # errors name the options
        assert main(["--device", "cpu", "single", paths[0], opt, val, "--out", str(tmp_path / "bad")]) == 2
        assert f"error: {opt}: expected" in capsys.readouterr().err


def test_explained_fraction_against_the_model():
    # 1 where the observations are the Blinn-Phong model's own images, 1 - |r|^2/|I|^2 otherwise, negative where a
    # lit model meets a dark (cast-shadowed) pixel, 0 for a black pixel
    from gpps.host.single import explained_fraction

    rng = np.random.default_rng(3)
    P = 50
    n = rng.normal(0, 0.3, (P, 3))
    n[:, 2] = 1.0
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    view = np.tile([0.0, 0.0, 1.0], (P, 1))
    L = np.array([[0.3, 0.2, 0.93], [-0.4, 0.1, 0.91], [0.0, -0.5, 0.87]])
    L /= np.linalg.norm(L, axis=1, keepdims=True)
    E = rng.uniform(0.5, 1.0, (3, 3))
    kd = rng.uniform(0.2, 0.9, (P, 3))
    ks, sh = 0.3, 20.0
    I = np.zeros((3, P, 3))
    for k in range(3):
        a = np.maximum(n @ L[k], 0)
        h = L[k] + view
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        s = np.where(a > 0, np.maximum(np.sum(n * h, 1), 0) ** sh, 0)
        I[k] = E[k] * (kd * a[:, None] + ks * s[:, None])
    np.testing.assert_allclose(explained_fraction(I, n, view, L, E, kd, ks, sh), 1.0, atol=1e-12)
    J = I.copy()
    J[1, :5] = 0.0  # light 1 hidden from pixels 0-4: their residual is the model's whole image there
    f = explained_fraction(J, n, view, L, E, kd, ks, sh)
    want = 1 - np.sum(I[1, :5] ** 2, -1) / np.sum(J[:, :5] ** 2, axis=(0, 2))
    np.testing.assert_allclose(f[:5], want, rtol=1e-12)
    np.testing.assert_allclose(f[5:], 1.0, atol=1e-12)
    J[:, 7] = 0.0
    assert explained_fraction(J, n, view, L, E, kd, ks, sh)[7] == 0.0


def test_unexplained_pixels_keep_the_prior(device):
    # a clean Lambertian sphere is explained by the refined model (few pixels keep the prior); a threshold no fit
    # reaches (min_explained=1) keeps the prior everywhere: the result is then the network's normals
    from gpps.flows.single import SingleConfig, reconstruct_single
    from gpps.pipeline.cuckoo import CuckooConfig

    sc, _, imgs = _sphere_capture(32)
    cfg = SingleConfig(cuckoo=CuckooConfig(nests=6, generations=10, seed=1), integrate=False)
    a = reconstruct_single(imgs, sc.mask, config=cfg, device=device)
    assert 0 <= a.kept_network < a.mask.sum() // 2  # a clean Lambertian sphere: the model explains it
    strict = reconstruct_single(imgs, sc.mask, config=SingleConfig(cuckoo=cfg.cuckoo, integrate=False, min_explained=1.0),
                                device=device)
    assert strict.kept_network == strict.mask.sum()
    np.testing.assert_allclose(strict.normals[strict.mask], strict.normals_net[strict.mask], atol=1e-6)
    with pytest.raises(ValueError, match="min_explained"):
        SingleConfig(min_explained=1.5)


@pytest.mark.parametrize("tta", ["flips", "dihedral"])
def test_test_time_augmentation_is_equivariant(tta):
    # the mean over the mirror images (and transposes) makes the prediction exactly equivariant: a mirrored image
    # gives the mirrored normals (n_x negated), a transposed one the transposed normals ((n_x, n_y) -> (-n_y, -n_x))
    sc, _, imgs = _sphere_capture(64)
    img = imgs[0] * (1 + 0.5 * np.arange(64)[None, :, None] / 64)  # break the sphere's own symmetry
    net = SingleNet.load()
    n, h = net.predict(img, sc.mask, size=64, tta=tta)
    nf, hf = net.predict(img[:, ::-1], sc.mask[:, ::-1], size=64, tta=tta)
    want = n[:, ::-1] * np.array([-1.0, 1.0, 1.0])
    np.testing.assert_allclose(nf, want, atol=2e-5)
    np.testing.assert_allclose(hf, h[:, ::-1], atol=2e-5)
    if tta == "dihedral":
        nt, _ = net.predict(img.transpose(1, 0, 2), sc.mask.T, size=64, tta=tta)
        want = n.transpose(1, 0, 2)[..., [1, 0, 2]] * np.array([-1.0, -1.0, 1.0])
        np.testing.assert_allclose(nt, want, atol=2e-5)
    plain, _ = net.predict(img, sc.mask, size=64)
    assert np.degrees(np.arccos(np.clip(np.sum(plain * n, -1), -1, 1)))[sc.mask].mean() < 10  # a mean, not noise
    with pytest.raises(ValueError, match="tta"):
        net.predict(img, sc.mask, tta="rotations")


def test_network_spread_and_the_map_weight(device):
    # the spread: the RMS angle of the per-image predictions about their mean; "map" (the default with three images)
    # searches again with the MAP weights and records them; too few lit observations keep the prior
    from gpps.flows.single import SingleConfig, _spread, reconstruct_single
    from gpps.pipeline.cuckoo import CuckooConfig

    z = np.tile([0.0, 0.0, 1.0], (4, 1))
    t = np.radians(10.0)
    tilted = np.tile([np.sin(t), 0.0, np.cos(t)], (4, 1))
    np.testing.assert_allclose(_spread([z, z, z], z), 0.0, atol=1e-7)
    np.testing.assert_allclose(_spread([z, tilted], z), np.sqrt(t * t / 2), rtol=1e-6)
    sc, _, imgs = _sphere_capture(32)
    ck = CuckooConfig(nests=6, generations=10, seed=1)
    a = reconstruct_single(imgs, sc.mask, config=SingleConfig(cuckoo=ck, integrate=False, min_lit=0), device=device)
    rec = a.objective[0]
    assert rec["prior_weight"] > 0 and rec["sigma"] > 0 and rec["theta_median_deg"] >= 1.0
    b = reconstruct_single(imgs, sc.mask, config=SingleConfig(cuckoo=ck, integrate=False, prior_weight=0.002, min_lit=0),
                           device=device)
    assert "sigma" not in b.objective[0] and b.objective[0]["prior_weight"] == 0.002
    dark = reconstruct_single(imgs, sc.mask, config=SingleConfig(cuckoo=ck, integrate=False, lit_fraction=1.0),
                              device=device)  # nothing counts as lit: every pixel keeps the prior
    assert dark.kept_network == dark.mask.sum()
    for kw in (dict(min_lit=-1), dict(lit_fraction=2.0), dict(min_spread_deg=0.0), dict(prior_weight="mapp")):
        with pytest.raises(ValueError, match=next(iter(kw))):
            SingleConfig(**kw)


def test_cuckoo_data_weight_is_checked():
    from gpps.pipeline.cuckoo import CuckooConfig, PhotometricCuckoo

    st = PhotometricCuckoo(3, 10, config=CuckooConfig(nests=4, generations=1), device="cpu")
    with pytest.raises(ValueError, match="weight"):
        st.upload(weight=np.ones(9))
    st.upload(weight=np.full(10, 2.0))
    assert np.all(st.data.weight.numpy() == 2.0)
    st.close()
