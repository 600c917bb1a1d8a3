"""RON started warm from an earlier reconstruction (``gpps.reconstruct(..., start=...)``: the interreflection
compensation's later reconstructions): no least squares, no DGMC, no cold starts, and the result of a cold run on
images that moved by a little."""

import numpy as np
import pytest

import gpps


def _capture(device, size=48, n=6):
    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", n, layout="spiral")
    true = gpps.Material("blinn-phong", ks=0.5, shininess=40.0)
    img = gpps.render(sc, true, L, bits=16, device=device) / L.intensities[:, None, None, :]
    return sc, gpps.DirectionalLights(L.directions), np.ascontiguousarray(img, np.float32), true


def _angle(a, b, m):
    return np.degrees(np.arccos(np.clip((a[m] * b[m]).sum(-1), -1.0, 1.0)))


def test_warm_start_skips_the_cold_stages_and_keeps_the_result(device):
    sc, lights, img, true = _capture(device)
    kw = dict(camera=sc.camera, device=device)
    cold = gpps.reconstruct(img, sc.mask, lights, material=true, estimate=(), **kw)
    assert cold.timings["least_squares"] > 0 and cold.highlight.any()
    warm = gpps.reconstruct(img, sc.mask, lights, material=true, estimate=(), start=cold, **kw)
    assert warm.timings["least_squares"] == 0 and warm.timings["dgmc"] == 0
    np.testing.assert_array_equal(warm.highlight, cold.highlight)
    m = sc.mask & (cold.flags == 0)
    assert np.percentile(_angle(warm.normals, cold.normals, m), 99) < 0.01  # (the same images: its fixed point)

    # images that moved by a little (as light bounced from elsewhere: the same 3 % of the pixel's brightest value
    # added under every light): warm from the old normals, the same result as a cold run on the new images
    moved = img + np.float32(0.03) * img.max(0, keepdims=True)
    again = gpps.reconstruct(moved, sc.mask, lights, material=true, estimate=(), **kw)
    warm2 = gpps.reconstruct(moved, sc.mask, lights, material=true, estimate=(), start=cold, **kw)
    m2 = m & (again.flags == 0)
    assert _angle(warm2.normals, again.normals, m2).mean() < 0.02
    assert _angle(again.normals, cold.normals, m2).mean() > 0.2  # (the images did move the normals)
    # a tuple (normals, highlight) as well
    warm3 = gpps.reconstruct(moved, sc.mask, lights, material=true, estimate=(), start=(cold.normals, None), **kw)
    assert not warm3.highlight.any()
    np.testing.assert_allclose(warm3.normals[m2], warm2.normals[m2], atol=1e-5)


def test_warm_start_checks(device):
    sc, lights, img, true = _capture(device, size=24, n=4)
    kw = dict(camera=sc.camera, material=true, estimate=(), device=device)
    with pytest.raises(ValueError, match="^start: expected .* normals, got shape"):
        gpps.reconstruct(img, sc.mask, lights, start=(np.zeros((3, 3, 3)), None), **kw)
    bad = np.zeros(sc.mask.shape + (3,), np.float32)
    bad[sc.mask] = np.nan
    with pytest.raises(ValueError, match="^start: expected finite normals"):
        gpps.reconstruct(img, sc.mask, lights, start=(bad, None), **kw)
    with pytest.raises(TypeError, match="^start: expected a Reconstruction or"):
        gpps.reconstruct(img, sc.mask, lights, start=np.zeros(sc.mask.shape + (3,)), **kw)
    with pytest.raises(ValueError, match="^start: expected \\(normals, highlight\\), got 3 items"):
        gpps.reconstruct(img, sc.mask, lights, start=(bad, None, None), **kw)
    # a pixel the earlier solve left without a normal (zero) starts facing the camera: the solve still runs
    zero = np.tile(np.float32([0.0, 0.0, 1.0]), sc.mask.shape + (1,))
    zero[sc.mask.nonzero()[0][:5], sc.mask.nonzero()[1][:5]] = 0.0
    rec = gpps.reconstruct(img, sc.mask, lights, start=(zero, None), **kw)
    assert np.all(np.isfinite(rec.normals[sc.mask]))
    with pytest.raises(ValueError, match="^start: expected an .* highlight mask"):
        gpps.reconstruct(img, sc.mask, lights, start=(np.tile([0, 0, 1.0], sc.mask.shape + (1,)), np.zeros(3, bool)),
                         **kw)
