"""The Warp reflectance models, lights and camera against independent numpy references."""

import numpy as np
import pytest

import reference_models as ref
from gpps._runtime import warp
from gpps.material import BRDF_NAMES, Material
from gpps.pipeline.params import camera_params, light_params, material_params

RTOL = 1e-5  # float32 kernels vs float64 numpy on the same (float32) inputs
ATOL = 1e-7  # below float32 resolution of the O(1) terms


def _unit(rng, n):
    return ref.normalize(rng.normal(size=(n, 3)))


def random_geometry(rng, n, min_cos=0.05):
    """Unit n, l, v with n.l, n.v >= min_cos (lit and visible), rounded to float32."""
    out_n, out_l, out_v = [], [], []
    while sum(len(a) for a in out_n) < n:
        nn = _unit(rng, 4 * n)
        nn[:, 2] = np.abs(nn[:, 2])
        ll = _unit(rng, 4 * n)
        vv = _unit(rng, 4 * n)
        ok = (ref.dot(nn, ll) > min_cos) & (ref.dot(nn, vv) > min_cos)
        out_n.append(nn[ok]), out_l.append(ll[ok]), out_v.append(vv[ok])
    f = lambda a: np.concatenate(a)[:n].astype(np.float32).astype(np.float64)  # noqa: E731
    n_, l_, v_ = f(out_n), f(out_l), f(out_v)
    return n_, l_, v_


def random_material(rng, brdf):
    return Material(
        brdf,
        ks=rng.uniform(0.1, 1.0),
        shininess=rng.uniform(1.0, 60.0),
        roughness=rng.uniform(0.1, 0.6),
        f0=rng.uniform(0.02, 0.95) if brdf != "conductor" else rng.uniform(0.5, 1.0),
        eta_u=rng.uniform(1.0, 60.0),
        eta_v=rng.uniform(1.0, 60.0),
    )


def eval_kernel(device, mat, n, l, v):
    wp = warp()
    import _brdf_kernels as tk

    arr = lambda a: wp.array(a.astype(np.float32), dtype=wp.vec3, device=device)  # noqa: E731
    out = wp.zeros(len(n), dtype=wp.vec2, device=device)
    wp.launch(tk.eval_brdf_terms, dim=len(n), inputs=[arr(n), arr(l), arr(v), material_params(mat)], outputs=[out], device=device)
    return out.numpy().astype(np.float64)


@pytest.mark.parametrize("brdf", BRDF_NAMES)
def test_models_match_numpy(device, brdf):
    rng = np.random.default_rng(1234)
    worst = 0.0
    for trial in range(8):  # 8 random parameter sets x 2000 random geometries
        mat = random_material(rng, brdf)
        n, l, v = random_geometry(rng, 2000)
        got = eval_kernel(device, mat, n, l, v)
        cos, s = ref.terms(mat, n, l, v)
        np.testing.assert_allclose(got[:, 0], cos, rtol=RTOL, atol=ATOL)
        np.testing.assert_allclose(got[:, 1], s, rtol=RTOL, atol=ATOL, err_msg=f"{brdf} {mat}")
        big = np.abs(s) > 1e-3
        if big.any():
            worst = max(worst, float(np.max(np.abs(got[big, 1] - s[big]) / np.abs(s[big]))))
    assert worst < RTOL


def test_specular_lobes_are_not_trivial(device):
    """The mirror configuration gives each lobe its peak (guards against a zero model passing)."""
    n = np.array([[0.0, 0.0, 1.0]])
    l = ref.normalize(np.array([[0.3, 0.0, 1.0]]))
    v = l * [-1, -1, 1]  # mirror of l about n: h = n, R = v
    for brdf in BRDF_NAMES:
        mat = Material.default_for(brdf)
        got = eval_kernel(device, mat, n, l, v)[0]
        off = eval_kernel(device, mat, n, l, ref.normalize(np.array([[0.0, 0.8, 0.6]])))[0]
        if brdf == "conductor":  # its lobe is the albedo-weighted term, and it has no other
            # (its default's lobe is broad, alpha 0.5, so that it stays in range: a narrower one for the peak test)
            mat = Material("conductor", roughness=0.2)
            got = eval_kernel(device, mat, n, l, v)[0]
            off = eval_kernel(device, mat, n, l, ref.normalize(np.array([[0.0, 0.8, 0.6]])))[0]
            assert got[1] == 0.0 and off[1] == 0.0
            assert got[0] > 0.1 and got[0] > 5 * off[0]
            continue
        # the diffuse cosine (plastic: less what the coating reflects on the way in and out)
        assert got[0] == pytest.approx(ref.terms(mat, n, l, v)[0][0] if brdf == "plastic" else l[0, 2], rel=1e-6)
        if brdf == "lambertian":
            assert got[1] == 0.0
        else:
            assert got[1] > 0.1 and got[1] > 5 * off[1]


def test_attached_shadow_and_backfacing(device):
    n = np.array([[0.0, 0.0, 1.0]] * 3)
    l = np.array([[0.0, 0.6, -0.8], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    v = np.array([[0.0, 0.0, 1.0], [0.0, 0.6, -0.8], [0.0, 0.0, 1.0]])
    for brdf in BRDF_NAMES:
        got = eval_kernel(device, Material.default_for(brdf), n, l, v)
        assert np.all(got[0] == 0.0)  # light behind the surface
        assert got[1, 1] == 0.0  # viewer behind the surface: no specular
        assert np.all(got[2] == 0.0)  # grazing light: n.l = 0


def test_ashikhmin_shirley_isotropic_equals_blinn_shape(device):
    """With eta_u = eta_v = e, zeta = e: the lobe is (n.h)^e times smooth factors (5.2)."""
    rng = np.random.default_rng(5)
    n, l, v = random_geometry(rng, 500)
    mat = Material("ashikhmin-shirley", ks=1.0, eta_u=25.0, eta_v=25.0, f0=1.0)
    got = eval_kernel(device, mat, n, l, v)[:, 1]
    h = ref.normalize(l + v)
    nh, nl, nv, vh = ref.dot(n, h), ref.dot(n, l), ref.dot(n, v), ref.dot(v, h)
    want = 26.0 / (8 * np.pi) * nh**25 / (vh * np.maximum(nl, nv)) * nl
    np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("kind", ["directional", "point"])
def test_lights_match_numpy(device, kind):
    from gpps.lights import DirectionalLights, PointLights

    wp = warp()
    import _brdf_kernels as tk

    rng = np.random.default_rng(7)
    p = np.column_stack([rng.uniform(-2, 2, 300), rng.uniform(-2, 2, 300), rng.uniform(-12, -8, 300)]).astype(np.float32)
    if kind == "directional":
        lights = DirectionalLights(ref.normalize(rng.normal(size=(5, 3)) + [0, 0, 3]), rng.uniform(0.2, 2.0, (5, 3)))
    else:
        axes = ref.normalize(rng.normal(size=(5, 3)) * 0.2 + [0, 0, -1])
        lights = PointLights(rng.uniform(-5, 5, (5, 3)) * [1, 1, 0.2], rng.uniform(10, 100, (5, 3)), axes, mu=[0, 1, 2.5, 0, 4])
    lp = light_params(lights, device)
    dirs = wp.zeros((5, 300), dtype=wp.vec3, device=device)
    rad = wp.zeros((5, 300), dtype=wp.vec3, device=device)
    wp.launch(tk.eval_lights, dim=300, inputs=[wp.array(p, dtype=wp.vec3, device=device), lp], outputs=[dirs, rad], device=device)
    P = p.astype(np.float64)
    if kind == "directional":
        want_d = np.broadcast_to(lights.directions[:, None], (5, 300, 3))
        want_r = np.broadcast_to(lights.intensities[:, None], (5, 300, 3))
    else:
        diff = lights.positions[:, None] - P[None]  # (5, 300, 3) from point to light
        r = np.linalg.norm(diff, axis=-1)
        want_d = diff / r[..., None]
        cosang = np.maximum(ref.dot(-want_d, lights.axes[:, None]), 0.0)
        lobe = np.where(lights.mu[:, None] > 0, cosang ** lights.mu[:, None], 1.0)
        want_r = lights.intensities[:, None] / r[..., None] ** 2 * lobe[..., None]
    np.testing.assert_allclose(dirs.numpy(), want_d, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(rad.numpy(), want_r, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("cam", ["orthographic", "perspective"])
def test_pixel_points_match_camera(device, cam):
    from gpps.host.scenes import default_camera

    wp = warp()
    import _brdf_kernels as tk

    camera = default_camera(cam, (24, 32))
    rng = np.random.default_rng(0)
    depth = rng.uniform(5, 15, (24, 32)).astype(np.float32)
    out = wp.zeros((24, 32), dtype=wp.vec3, device=device)
    wp.launch(tk.eval_pixel_points, dim=(24, 32), inputs=[wp.array(depth, device=device), camera_params(camera, (24, 32))], outputs=[out], device=device)
    np.testing.assert_allclose(out.numpy(), camera.backproject(depth), rtol=1e-5, atol=1e-5)
    if cam == "perspective":  # projecting back lands on the pixel centres
        uv = camera.project(camera.backproject(depth))
        jj, ii = np.meshgrid(np.arange(32), np.arange(24))
        np.testing.assert_allclose(uv[..., 0], jj, atol=1e-9)
        np.testing.assert_allclose(uv[..., 1], ii, atol=1e-9)
