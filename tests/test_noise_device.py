"""The noise estimate on the device (gpps.pipeline.noise.DeviceNoise, gpps/kernels/noise.py) against the plain 3x3
loop of estimate_noise and the host's estimate_noise, bit for bit, on every device; and the solver's upload that
uses it."""

from __future__ import annotations

import numpy as np
import pytest
from cases import make_case
from test_host_overheads import _blob_mask, _estimate_noise_reference, _same

import warp as wp

from gpps.pipeline.noise import DeviceNoise
from gpps.pipeline.solver import PixelSolver, SolverConfig, estimate_noise


def _frames(rng, n, h, w, kind):
    smooth = np.linspace(0.1, 0.9, w)[None, None, :] * np.linspace(0.5, 1.0, h)[None, :, None]
    sig = np.resize([0.01, 0.02, 0.005, 0.03, 0.0], n)
    img = smooth[..., None] + rng.normal(0, sig, (h, w, 3, n)).transpose(3, 0, 1, 2)
    img[1, :, : w // 3] = 0.0  # a shadow: only positive neighbourhoods count
    img[2, 10:14, 10:20] = -0.01
    if kind == "grey":  # (the solver holds grey images as three equal channels)
        img = np.repeat(img.mean(axis=-1, keepdims=True), 3, axis=-1)
    elif kind == "8bit":  # quantised: ties everywhere, the median's two middle values often equal
        img = np.round(np.clip(img, 0, 1) * 255) / 255
    return img.astype(np.float32)


@pytest.mark.parametrize("max_pixels", [1 << 16, 500, 37])
@pytest.mark.parametrize("kind", ["rgb", "grey", "8bit"])
def test_device_noise_equals_the_plain_loop(device, kind, max_pixels):
    rng = np.random.default_rng(4)
    n, h, w = 5, 41, 53
    img = _frames(rng, n, h, w, kind)
    est = DeviceNoise((n, h, w), device, max_pixels=max_pixels)
    images = wp.array(img, dtype=wp.vec3, device=device)
    out = wp.zeros(n, dtype=wp.float32, device=device)
    masks = [_blob_mask(h, w, rng, False), _blob_mask(h, w, rng, True), np.zeros((h, w), bool)]
    one = np.zeros((h, w), bool)
    one[10:13, 20:23] = True  # a single inner pixel: fewer than 64 values, unknown (0)
    for m in masks + [one, masks[0]]:  # (the last: back to a mask seen before, after smaller selections)
        est.upload(m)
        est.step(images, out)
        got = est.fetch()
        ref = _estimate_noise_reference(img, m, max_pixels=max_pixels)
        assert got.dtype == np.float32 and _same(got, ref), (got, ref)
        assert _same(got, estimate_noise(img, m, max_pixels=max_pixels))
    assert np.any(got > 0) or max_pixels < 64
    est.close()


def test_device_noise_refuses_wrong_buffers(device):
    est = DeviceNoise((3, 16, 16), device)
    images = wp.zeros((3, 16, 16), dtype=wp.vec3, device=device)
    out = wp.zeros(3, dtype=wp.float32, device=device)
    with pytest.raises(ValueError, match="upload"):
        est.step(images, out)
    with pytest.raises(ValueError, match="mask: expected shape"):
        est.upload(np.ones((16, 15), bool))
    est.upload(np.ones((16, 16), bool))
    with pytest.raises(ValueError, match="images: expected"):
        est.step(wp.zeros((3, 16, 15), dtype=wp.vec3, device=device), out)
    with pytest.raises(ValueError, match="out: expected"):
        est.step(images, wp.zeros(4, dtype=wp.float32, device=device))
    est.close()
    with pytest.raises(ValueError, match="closed"):
        est.upload(np.ones((16, 16), bool))


def test_solver_upload_estimates_on_the_device(device, monkeypatch):
    """The upload's estimate on the device (CUDA's path; forced here on every device) is the host's, and the
    solve from it the same; a given noise or config.noise_level skip it."""
    img, lights, sc, mat = make_case("sphere", 40, "perspective", "directional", "cook-torrance", noise=0.01,
                                     device=device)
    img = np.clip(img, 0.0, None)
    outs = []
    for on_device in (False, True):
        monkeypatch.setattr(PixelSolver, "_noise_on_device", lambda self, on=on_device: on)
        s = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(starts=2), device=device)
        s.upload(img, sc.mask)
        assert (s._noise_host is None) == on_device  # (not fetched until read)
        assert _same(s.noise_level, estimate_noise(img, sc.mask)) and np.all(s.noise_level > 0)
        s.step()
        outs.append(s.fetch(("normals", "residual", "flags")))
        s.upload(img, sc.mask, noise=np.full(3, 0.5, np.float32))
        assert _same(s.noise.numpy(), np.full(3, 0.5, np.float32))
        s.set_config(SolverConfig(starts=2, noise_level=0.25))
        s.upload(img, sc.mask)
        assert _same(s.noise_level, np.full(3, 0.25, np.float32))
        s.close()
    for k in outs[0]:
        np.testing.assert_array_equal(outs[1][k], outs[0][k], err_msg=k)
