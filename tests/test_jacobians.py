"""Analytic Jacobians of the per-pixel models against float64 central differences
of an independent numpy implementation (tests/kernels_for_tests.py)."""

import numpy as np
import pytest

from gpps._runtime import warp
from gpps.material import Material
from gpps.pipeline.params import material_params

MATERIALS = {
    "lambertian": Material("lambertian", ks=0.0),
    "phong": Material("phong", ks=0.5, shininess=30.0),
    "blinn-phong": Material("blinn-phong", ks=0.5, shininess=40.0),
    "cook-torrance": Material("cook-torrance", ks=0.6, roughness=0.25, f0=0.5),
    "ashikhmin-shirley": Material("ashikhmin-shirley", ks=0.8, eta_u=10.0, eta_v=60.0, f0=0.5),
    "plastic": Material.from_ior("plastic", 1.5, ks=1.0, roughness=0.25),
    "conductor": Material("conductor", roughness=0.25, f0=0.6),
}
M = 400  # random samples per model
H = 1e-6  # central-difference step (float64)
RTOL = 1e-4


def _pdict(m):
    return dict(shininess=m.shininess, roughness=m.roughness, f0=m.f0, eta_u=m.eta_u, eta_v=m.eta_v)


def _random_unit(rng, m, zmin):
    out = []
    while len(out) < m:
        a = rng.normal(size=3)
        a /= np.linalg.norm(a)
        if a[2] > zmin:
            out.append(a)
    return np.array(out)


def _samples(brdf, mat, rng):
    """Random (n0, t1, t2, x, l, v) away from the models' kinks (so that differences are meaningful)."""
    from kernels_for_tests import np_chart, np_normalize, np_tangent_t1

    p = _pdict(mat)
    rows = []
    while len(rows) < M:
        n0 = _random_unit(rng, 1, 0.3)[0]
        t1 = np_tangent_t1(n0)
        t2 = np.cross(n0, t1)
        x = rng.uniform(-0.3, 0.3, 2)
        n = np_chart(n0, t1, t2, x)
        v = _random_unit(rng, 1, 0.5)[0]
        # lights near the mirror direction so that the lobes are not negligible
        r = np_normalize(2 * np.dot(n, v) * n - v)
        l = np_normalize(r + rng.normal(scale=0.35, size=3))
        nl, nv = np.dot(n, l), np.dot(n, v)
        h = np_normalize(l + v)
        nh, vh = np.dot(n, h), np.dot(v, h)
        if nl < 0.05 or nv < 0.05 or vh < 0.05 or nh < 0.05 or abs(nl - nv) < 1e-3 or abs(n[0]) > 0.88:
            continue
        if brdf == "phong" and np.dot(2 * nl * n - l, v) < 0.05:
            continue
        if brdf in ("cook-torrance", "plastic"):
            g1, g2 = 2 * nh * nv / vh, 2 * nh * nl / vh
            if abs(g1 - g2) < 1e-3 or abs(min(g1, g2) - 1) < 1e-3:
                continue
        rows.append((n0, t1, t2, x, l, v))
    return [np.array(c) for c in zip(*rows)], p


@pytest.mark.parametrize("brdf", list(MATERIALS))
def test_model_jacobians_match_central_differences(device, brdf):
    from kernels_for_tests import np_chart, np_terms, terms_grad_kernel

    wp = warp()
    mat = MATERIALS[brdf]
    rng = np.random.default_rng(7)
    (n0, t1, t2, x, l, v), p = _samples(brdf, mat, rng)
    arrs = [wp.array(a.astype(np.float32), dtype=wp.vec3 if a.shape[1] == 3 else wp.vec2, device=device) for a in (n0, t1, t2, x, l, v)]
    out = wp.zeros((M, 6), dtype=wp.float32, device=device)
    wp.launch(terms_grad_kernel, dim=M, inputs=arrs + [material_params(mat)], outputs=[out], device=device)
    got = out.numpy().astype(np.float64)

    def f(xx):
        return np.stack(np_terms(brdf, np_chart(n0, t1, t2, xx), l, v, p), -1)  # (M, 2)

    val = f(x)
    fd = np.zeros((M, 2, 2))  # [sample, term, coordinate]
    for c in range(2):
        e = np.zeros(2)
        e[c] = H
        fd[:, :, c] = (f(x + e) - f(x - e)) / (2 * H)
    np.testing.assert_allclose(got[:, :2], val, rtol=2e-5, atol=1e-7)
    ana = got[:, 2:].reshape(M, 2, 2)
    scale = np.linalg.norm(fd, axis=2, keepdims=True)  # per term: |grad|
    err = np.abs(ana - fd)
    rel = np.where(scale > 1e-6, err / np.maximum(scale, 1e-30), err)
    assert rel.max() <= RTOL, f"{brdf}: worst relative error {rel.max():.3g} at sample {np.unravel_index(rel.argmax(), rel.shape)}"
    if brdf != "lambertian":  # the lobe was actually exercised (the conductor's is its first term)
        assert np.count_nonzero(val[:, 0 if brdf == "conductor" else 1] > 1e-3) > M // 4


@pytest.mark.parametrize("brdf", list(MATERIALS))
@pytest.mark.parametrize("grey", [False, True])
def test_reduced_cost_gradient_and_gauss_newton_matrix(device, brdf, grey):
    """Variable projection: J^T W r and J^T W J of the reduced residual against central differences."""
    from kernels_for_tests import evaluate_kernel, np_chart, np_normalize, np_reduced_cost, np_tangent_t1

    from gpps.lights import DirectionalLights
    from gpps.pipeline.params import light_params

    wp = warp()
    mat = MATERIALS[brdf]
    p = _pdict(mat)
    rng = np.random.default_rng(11 + grey)
    nl_ = 6
    checked = 0
    for trial in range(40):
        n0 = _random_unit(rng, 1, 0.5)[0]
        t1 = np_tangent_t1(n0)
        t2 = np.cross(n0, t1)
        x = rng.uniform(-0.2, 0.2, 2)
        n = np_chart(n0, t1, t2, x)
        v = np_normalize(np.array([0.05, -0.03, 1.0]))
        dirs = np_normalize(n + rng.normal(scale=0.5, size=(nl_, 3)))
        if np.any(dirs @ n < 0.05) or np.any(np.abs(dirs @ n - n @ v) < 1e-3):
            continue
        rad = rng.uniform(0.5, 1.5, (nl_, 3))
        obs = rng.uniform(0.05, 0.9, (nl_, 3))
        w = rng.uniform(0.2, 1.0, nl_)
        lights = DirectionalLights(dirs, rad)
        lp = light_params(lights, device)
        images = wp.array(obs.astype(np.float32).reshape(nl_, 1, 1, 3), dtype=wp.vec3, device=device)
        weights = wp.array(w.astype(np.float32).reshape(nl_, 1, 1), dtype=wp.float32, device=device)
        out = wp.zeros(9, dtype=wp.float32, device=device)
        wp.launch(
            evaluate_kernel,
            dim=1,
            inputs=[wp.vec3(*n0), wp.vec3(*t1), wp.vec3(*t2), wp.vec2(*x), images, weights, lp, material_params(mat), wp.vec3(*v), int(grey)],
            outputs=[out],
            device=device,
        )
        got = out.numpy().astype(np.float64)

        def cost(xx):
            return np_reduced_cost(brdf, np_chart(n0, t1, t2, xx), dirs, rad, obs, w, v, p, mat.ks, grey)

        c0, kd0, r0 = cost(x)
        if np.any((kd0 > 0) & (kd0 < 1e-3)):  # too close to the kd >= 0 clamp
            continue
        g = np.zeros(2)
        jac = np.zeros((r0.size, 2))
        for c in range(2):
            e = np.zeros(2)
            e[c] = H
            cp, _, rp = cost(x + e)
            cm, _, rm = cost(x - e)
            g[c] = (cp - cm) / (2 * H)
            jac[:, c] = (rp - rm) / (2 * H)
        jtj = jac.T @ jac
        np.testing.assert_allclose(got[0], c0, rtol=1e-4)
        np.testing.assert_allclose(got[6:9], kd0, rtol=1e-4, atol=1e-6)
        gs = max(np.linalg.norm(g), 1e-6)
        assert np.max(np.abs(got[1:3] - g)) / gs <= RTOL, (brdf, got[1:3], g)
        js = max(np.abs(jtj).max(), 1e-8)
        assert np.max(np.abs(got[[3, 4, 5]] - jtj[[0, 0, 1], [0, 1, 1]])) / js <= RTOL, (brdf, got[3:6], jtj)
        checked += 1
        if checked >= 8:
            break
    assert checked >= 4
