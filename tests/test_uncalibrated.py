"""Uncalibrated PS (seed ch. 5): factorisation, integrability, GBR, refinement, failure modes."""

import numpy as np
import pytest

from gpps.material import Material
from gpps.scenes import make_scene
from gpps.synthetic import default_lights, render
from gpps.uncalibrated import UncalibratedConfig, factorize, gbr, integrability_gbr, light_direction_errors, pca_merge, solve_uncalibrated

FLIP = np.diag([-1.0, -1.0, 1.0])


def _maen(n, gt, mask):
    return float(np.degrees(np.arccos(np.clip(np.sum(n[mask] * gt[mask], -1), -1, 1))).mean())


@pytest.fixture(scope="module")
def lambertian_capture():
    scene = make_scene("bumps", 96, "orthographic", albedo="texture")
    lights = default_lights("directional", 8, layout="spiral")
    images = render(scene, Material("lambertian", ks=0), lights, bits=16)
    return scene, lights, images


def test_factorisation_and_integrability_recover_gbr(lambertian_capture):
    """Exact rank-3 data: B is recovered up to a 3x3 matrix, and integrability leaves only a GBR."""
    scene, lights, images = lambertian_capture
    M = images[:, scene.mask].mean(-1).astype(np.float64)
    L, B, _ = factorize(M, np.ones_like(M), robust_rounds=0)
    assert np.abs(L @ B.T - M).max() < 1e-3  # attached shadows are the only non-rank-3 part at 8 lights
    Bmap = np.zeros(scene.mask.shape + (3,))
    Bmap[scene.mask] = B
    A = integrability_gbr(Bmap, scene.mask)
    Bi = B @ A.T
    # some GBR (and sign) maps the integrable B onto the true b = albedo * n
    true_b = scene.normals[scene.mask] * scene.albedo[scene.mask].mean(-1, keepdims=True)
    X, *_ = np.linalg.lstsq(Bi, true_b, rcond=None)  # b_true ~ Bi X: X^T should be a GBR
    G = X.T / X.T[0, 0]
    np.testing.assert_allclose(G[0, 1], 0, atol=2e-2)
    np.testing.assert_allclose(G[1, 0], 0, atol=2e-2)
    np.testing.assert_allclose(G[1, 1], 1, atol=2e-2)
    np.testing.assert_allclose(G[2, :2], 0, atol=2e-2)


def test_lambertian_uncalibrated_synthetic(lambertian_capture, device):
    scene, lights, images = lambertian_capture
    cfg = UncalibratedConfig(refine="lambertian", highlight_trim=0.0, refine_iterations=100, final_iterations=60)
    res = solve_uncalibrated(images, scene.mask, config=cfg, device=device)
    assert res.flip == "ambiguous" and res.alternative is not None
    cands = [(res.normals, res.light_directions), res.alternative]
    errs = [(_maen(n, scene.normals, scene.mask), light_direction_errors(l, lights.directions).mean()) for n, l in cands]
    maen, lerr = min(errs)  # the only alignment: the convex/concave flip
    assert maen < 2.0 and lerr < 2.0, errs
    assert max(errs)[0] > 10  # the two candidates really differ
    np.testing.assert_allclose(res.light_intensities.mean(), 1.0)
    assert np.all(res.normals[~scene.mask] == 0)


def test_gbr_transforms_consistently():
    rng = np.random.default_rng(0)
    b = rng.normal(size=(50, 3))
    s = rng.normal(size=(6, 3))
    H = gbr(0.3, -0.2, 1.7)
    np.testing.assert_allclose((s @ np.linalg.inv(H)) @ (b @ H.T).T, s @ b.T, atol=1e-12)


def test_pca_merge():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.5
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    np.testing.assert_allclose(pca_merge(np.stack([n, n, n])), n, atol=1e-12)
    noisy = np.stack([n + 0.05 * rng.normal(size=n.shape) for _ in range(5)])
    merged = pca_merge(noisy)
    single = noisy[0] / np.linalg.norm(noisy[0], axis=1, keepdims=True)
    assert np.mean(np.sum(merged * n, 1)) > np.mean(np.sum(single * n, 1))
    with pytest.raises(ValueError, match="normal_sets: expected shape"):
        pca_merge(n)


def test_failure_modes_are_explicit(lambertian_capture):
    scene, lights, images = lambertian_capture
    with pytest.raises(ValueError, match="at least 3 images"):
        solve_uncalibrated(images[:2], scene.mask)
    dark = images.copy()
    dark[2] = 0
    with pytest.raises(ValueError, match=r"image\(s\) \[2\] are all dark"):
        solve_uncalibrated(dark, scene.mask)
    # all lights in one plane through the origin: the data have rank 2
    from gpps.lights import DirectionalLights

    t = np.linspace(0, np.pi / 2, 6)
    coplanar = DirectionalLights(np.stack([np.sin(t) * 0.6, np.zeros(6), np.sqrt(1 - (0.6 * np.sin(t)) ** 2)], 1) / np.linalg.norm(np.stack([np.sin(t) * 0.6, np.zeros(6), np.sqrt(1 - (0.6 * np.sin(t)) ** 2)], 1), axis=1, keepdims=True))
    planar = render(scene, Material("lambertian", ks=0), coplanar)
    with pytest.raises(ValueError, match="rank < 3"):
        solve_uncalibrated(planar, scene.mask)
    with pytest.raises(ValueError, match="images: expected shape"):
        solve_uncalibrated(images[..., :2], scene.mask)
    with pytest.raises(ValueError, match="mask: expected shape"):
        solve_uncalibrated(images, scene.mask[:10])
    with pytest.raises(ValueError, match="cues"):
        UncalibratedConfig(cues=("magic",))
    with pytest.raises(ValueError, match="refine"):
        UncalibratedConfig(refine="phong")
