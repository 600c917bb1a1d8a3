"""Diffuse interreflections over a depth map (gpps.kernels.interreflection, gpps.pipeline.interreflection,
gpps.flows.interreflection) on every device.

* The gather against numpy float64 from the radiosity kernel (``F = cos_r cos_s A_s / (pi d^2)``, no occlusion)
  on a perspective surface with random radiance.
* Analytic: inside a sphere every patch sees the element ``dA`` with the form factor ``dA / (4 pi R^2)``
  (whatever its place), so under uniform radiance a spherical cap of half-angle 60 degrees (area ``pi R^2``)
  gathers ``1/4`` of it at every one of its pixels, and nothing on the concave cap hides anything (the march must
  not occlude).
* Visibility: a V-groove split by a wall; the walls facing each other across the wall see nothing of each other.
* The compensation on a self-consistent synthetic capture: a Lambertian concave surface whose images hold the
  exact multi-bounce indirect light of the same discretisation; the normals of a least-squares solve get better
  with it and the images' indirect light comes back.
"""

import numpy as np
import pytest

from gpps.camera import Orthographic, Perspective
from gpps.pipeline.interreflection import InterreflectionConfig, Interreflections, source_pixels


def _cap(size=64, R=26.0, half=60.0, dc=100.0):
    """Orthographic spherical cap (concave, seen from inside): mask, depth, normals; pixel 1 unit."""
    ii, jj = np.mgrid[0:size, 0:size].astype(float)
    c = (size - 1) / 2
    x, y = jj - c, -(ii - c)
    r2 = x * x + y * y
    m = r2 < (R * np.sin(np.radians(half))) ** 2
    zz = np.sqrt(np.clip(R * R - r2, 0, None))
    depth = np.where(m, dc + zz, 1.0).astype(np.float32)
    n = np.where(m[..., None], np.stack([-x, -y, zz], -1) / R, (0.0, 0.0, 1.0)).astype(np.float32)
    return m, depth, n


def test_cap_gathers_a_quarter(device):
    m, depth, n = _cap()
    st = Interreflections((1,) + m.shape, Orthographic(1.0), InterreflectionConfig(max_sources=4096), device=device)
    S = st.run(depth, m, n, np.ones((1,) + m.shape + (3,), np.float32))
    st.close()
    v = S[0][m]
    assert st.stride == 1
    np.testing.assert_allclose(v.mean(), 0.25, rtol=0.02)  # (the staircase rim loses ~1 %)
    np.testing.assert_allclose(v, 0.25, rtol=0.04)
    assert np.all(S[0][~m] == 0)


def test_sources_on_a_stride_keep_the_sum(device):
    m, depth, n = _cap()
    full = Interreflections((1,) + m.shape, Orthographic(1.0), InterreflectionConfig(max_sources=4096), device=device)
    few = Interreflections((1,) + m.shape, Orthographic(1.0), InterreflectionConfig(max_sources=300), device=device)
    rad = np.ones((1,) + m.shape + (3,), np.float32)
    a, b = full.run(depth, m, n, rad), few.run(depth, m, n, rad)
    assert few.stride >= 2 and few.sources <= 300
    np.testing.assert_allclose(b[0][m].mean(), a[0][m].mean(), rtol=0.03)


def _surface(size=20):
    """A perspective bumpy concave surface (depth, normals from the depth's gradient), pinhole 60 px."""
    cam = Perspective(np.array([[60.0, 0, (size - 1) / 2], [0, 60.0, (size - 1) / 2], [0, 0, 1]]))
    ii, jj = np.mgrid[0:size, 0:size].astype(float)
    u, v = (jj - (size - 1) / 2) / size, (ii - (size - 1) / 2) / size
    depth = 10.0 + 3.0 * (u * u + v * v) * -1.0 + 0.3 * np.sin(6 * u) * np.cos(5 * v)
    m = np.ones((size, size), bool)
    m[:2, :3] = False
    pts = cam.backproject(depth)
    du = np.gradient(pts, axis=1)
    dv = np.gradient(pts, axis=0)
    nrm = np.cross(du, dv)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    nrm *= np.sign(nrm[..., 2:3])  # toward the camera
    return cam, m, depth.astype(np.float32), nrm.astype(np.float32), pts


def _form_factors(cam, m, depth, nrm, src, area_scale):
    """numpy float64 form factors without occlusion (module docstring of gpps.kernels.interreflection): the
    receivers (R, 2), their points and normals (R, 3), the sources' normals (S, 3), the unit directions receiver ->
    source (R, S, 3), the receivers' cosines (R, S) and ``F`` (R, S)."""
    pts = cam.backproject(depth).astype(np.float64)
    recv = np.argwhere(m)
    pr, nr = pts[recv[:, 0], recv[:, 1]], nrm[recv[:, 0], recv[:, 1]].astype(np.float64)
    ps, ns = pts[src[:, 0], src[:, 1]], nrm[src[:, 0], src[:, 1]].astype(np.float64)
    w = ps[None] - pr[:, None]
    d = np.linalg.norm(w, axis=-1)
    om = w / np.maximum(d, 1e-30)[..., None]
    cr = np.einsum("rc,rsc->rs", nr, om)
    cs = -np.einsum("sc,rsc->rs", ns, om)
    dist = np.linalg.norm(ps, axis=-1)
    cos_a = -ps[:, 2] / dist
    view = -ps / dist[:, None]
    area = dist**2 * cos_a**3 / (cam.fx * cam.fy * np.maximum((ns * view).sum(-1), 0.1))
    F = np.where((cr > 0) & (cs > 0), cr * cs * area_scale * area[None] / (np.pi * np.maximum(d, 1e-30) ** 2), 0.0)
    sep = np.hypot(*(recv[:, None, :] - src[None, :, :]).transpose(2, 0, 1))
    F[sep < 1.5] = 0.0
    return recv, pr, nr, ns, om, cr, F


def _reference(cam, m, depth, nrm, rad, src, area_scale):
    """numpy float64 of F @ x without occlusion (module docstring of gpps.kernels.interreflection)."""
    recv, *_, F = _form_factors(cam, m, depth, nrm, src, area_scale)
    n = rad.shape[0]
    x = rad[:, src[:, 0], src[:, 1], :].transpose(1, 0, 2).reshape(len(src), 3 * n).astype(np.float64)
    out = np.zeros(rad.shape)
    out[:, recv[:, 0], recv[:, 1], :] = (F @ x).reshape(len(recv), n, 3).transpose(1, 0, 2)
    return out


@pytest.mark.parametrize("max_sources", [4096, 60])
def test_gather_matches_numpy(device, max_sources):
    cam, m, depth, nrm, _ = _surface()
    rad = np.random.default_rng(3).uniform(0, 1, (2,) + m.shape + (3,)).astype(np.float32)
    cfg = InterreflectionConfig(max_sources=max_sources, visibility=False, max_rows=97)  # (blocks of 97 receivers)
    with Interreflections((2,) + m.shape, cam, cfg, device=device) as st:
        got = st.run(depth, m, nrm, rad)
        stride = st.stride
    src, s2 = source_pixels(m, max_sources)
    assert s2 == stride
    ref = _reference(cam, m, depth, nrm, rad, src, float(stride**2))
    assert ref[:, m].max() > 1e-3  # (the surface is concave enough to gather something)
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=1e-6)


def _groove(size=48, wall=True):
    """Orthographic V-groove along the columns (walls at 45 degrees facing each other), optionally split by a
    vertical wall 3 px wide and 30 units tall along its bottom: (mask, depth, normals, left, right)."""
    ii, jj = np.mgrid[0:size, 0:size].astype(float)
    c = (size - 1) / 2
    x = jj - c
    depth = 100.0 + (20.0 - np.abs(x))  # the bottom (x = 0) deepest
    n = np.stack([-np.sign(x), np.zeros_like(x), np.ones_like(x)], -1) / np.sqrt(2)
    if wall:
        top = np.abs(x) <= 1.5
        depth = np.where(top, 100.0 - 10.0, depth)
        n = np.where(top[..., None], (0.0, 0.0, 1.0), n)
    m = np.ones((size, size), bool)
    return m, depth.astype(np.float32), n.astype(np.float32), x < -2, x > 2


def test_wall_hides_the_other_side(device):
    m, depth, n, left, right = _groove()
    rad = np.zeros((1,) + m.shape + (3,), np.float32)
    rad[0][right] = 1.0  # only the right wall shines
    out = {}
    for vis in (True, False):
        cfg = InterreflectionConfig(max_sources=4096, visibility=vis)
        with Interreflections((1,) + m.shape, Orthographic(1.0), cfg, device=device) as st:
            out[vis] = st.run(depth, m, n, rad)[0, ..., 0]
    assert out[False][left].mean() > 0.05  # facing walls exchange light ...
    assert out[True][left].max() < 1e-6  # ... unless the wall stands between them


def test_open_groove_sees_across(device):
    m, depth, n, left, right = _groove(wall=False)
    rad = np.zeros((1,) + m.shape + (3,), np.float32)
    rad[0][right] = 1.0
    with Interreflections((1,) + m.shape, Orthographic(1.0), InterreflectionConfig(max_sources=4096), device=device) as st:
        vis = st.run(depth, m, n, rad)[0, ..., 0]
    with Interreflections((1,) + m.shape, Orthographic(1.0), InterreflectionConfig(max_sources=4096, visibility=False),
                          device=device) as st:
        free = st.run(depth, m, n, rad)[0, ..., 0]
    # (a 90-degree groove: every pair of the two walls sees each other; the march must agree)
    np.testing.assert_allclose(vis[left], free[left], rtol=0.02, atol=1e-4)


def test_checks(device):
    with pytest.raises(ValueError, match="max_sources"):
        InterreflectionConfig(max_sources=0)
    with pytest.raises(TypeError, match="visibility"):
        InterreflectionConfig(visibility=1)
    with pytest.raises(ValueError, match="step_px"):
        InterreflectionConfig(step_px=5.0)
    with pytest.raises(TypeError, match="config"):
        Interreflections((1, 8, 8), Orthographic(1.0), config={"max_sources": 3}, device=device)
    m, depth, n = _cap(size=16, R=6.0)
    st = Interreflections((2, 16, 16), Orthographic(1.0), device=device)
    with pytest.raises(ValueError, match="images"):
        st.upload(depth, m, n, np.ones((3, 16, 16, 3), np.float32))
    with pytest.raises(ValueError, match="depth"):
        st.upload(np.where(m, -1.0, 1.0), m, n, np.ones((2, 16, 16, 3), np.float32))
    with pytest.raises(ValueError, match="upload"):
        st.step()
    st.close()
    with pytest.raises(ValueError, match="closed"):
        st.upload(depth, m, n, np.ones((2, 16, 16, 3), np.float32))


def test_folder_config_checks():
    import gpps

    with pytest.raises(ValueError, match="interreflections"):
        gpps.FolderConfig(interreflections="subtract", method="ppn")
    with pytest.raises(ValueError, match="interreflections"):
        gpps.FolderConfig(interreflections="subtract", integrate=False)
    with pytest.raises(ValueError, match="interreflections"):
        gpps.FolderConfig(interreflections="bounce")
    with pytest.raises(ValueError, match="albedo_scale"):
        gpps.FolderConfig(albedo_scale=0.0)
    with pytest.raises(ValueError, match="interreflection_rounds"):
        gpps.FolderConfig(interreflection_rounds=0)


def _self_lit(device, kd=0.8):
    """A Lambertian concave cap under 8 directional lights with the exact multi-bounce indirect light of the same
    discretisation: (mask, depth, normals, lights, camera, direct, images)."""
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.render import Renderer

    m, depth, n = _cap(size=40, R=16.0)
    az = np.radians(np.arange(8) * 45.0)
    el = np.radians(np.array([80, 65] * 4, float))
    lights = DirectionalLights(np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1))
    cam = Orthographic(1.0)
    with Renderer(m.shape, cam, lights, Material("lambertian"), device=device) as rd:
        direct = rd.run(depth, m, np.full(m.shape + (3,), kd, np.float32), n)
    images = direct.copy()
    with Interreflections((8,) + m.shape, cam, InterreflectionConfig(max_sources=4096), device=device) as st:
        for _ in range(8):
            images = direct + kd * st.run(depth, m, n, images)
    return m, depth, n, lights, cam, direct, images


def _least_squares_solver(m, lights, depth):
    """``solve(images)`` for :func:`gpps.flows.interreflection.reconstruct_subtracting`: Lambertian least squares on
    the grey images of mask ``m`` with the true ``depth`` (a stand-in for the pipeline's reconstruction)."""
    from types import SimpleNamespace

    from gpps.material import Material

    L = lights.directions

    def solve(imgs):
        g = imgs.mean(-1)[:, m]  # (N, P)
        b = np.linalg.lstsq(L, g, rcond=None)[0].T  # (P, 3)
        rho = np.linalg.norm(b, axis=-1)
        nn = np.zeros(m.shape + (3,), np.float32)
        nn[m] = b / rho[:, None]
        nn[~m] = (0, 0, 1)
        alb = np.zeros(m.shape + (3,), np.float32)
        alb[m] = rho[:, None]
        return SimpleNamespace(normals=nn, albedo=alb, depth=depth, depth_mask=m, material=Material("lambertian"))
    return solve


def test_compensation_recovers_a_self_lit_cap(device):
    """Images of a Lambertian concave cap with the exact multi-bounce indirect light of the same discretisation
    (``I = D + kd F I`` iterated): least squares tilts the normals toward the bright walls; with the
    interreflections taken out (the true depth given, the albedo estimated) they come back."""
    from types import SimpleNamespace

    from gpps.flows.interreflection import reconstruct_subtracting
    from gpps.material import Material

    kd = 0.8
    m, depth, n, lights, cam, direct, images = _self_lit(device, kd)
    solve = _least_squares_solver(m, lights, depth)

    def maen(nn):
        return np.degrees(np.arccos(np.clip((nn[m] * n[m]).sum(-1), -1, 1))).mean()

    before = maen(solve(images).normals)
    calls = []
    rec, info = reconstruct_subtracting(solve, images, m, lights, cam, rounds=2, albedo_scale=1.0, device=device,
                                        progress=lambda d, t, msg: calls.append((d, t, msg)))
    after = maen(rec.normals)
    assert before > 2.0
    assert after < 0.2 * before, (before, after)
    assert info["tau"] == [1.0, 1.0] and info["sources"] == int(m.sum())
    assert not info["lowered"] and not info["skipped"]
    assert [c[:2] for c in calls] == [(0, 2), (1, 2)] and "round 2 of 2" in calls[1][2]
    np.testing.assert_allclose(rec.albedo[m].mean(), kd, rtol=0.03)

    # a pixel the solver could not fit (negative or NaN albedo) reflects nothing and stops nothing
    def broken(imgs):
        r = solve(imgs)
        r.albedo[m.nonzero()[0][:5], m.nonzero()[1][:5]] = -0.5
        r.albedo[m.nonzero()[0][5:9], m.nonzero()[1][5:9]] = np.nan
        return r

    rec3, _ = reconstruct_subtracting(broken, images, m, lights, cam, rounds=1, albedo_scale=1.0, device=device)
    assert maen(rec3.normals) < 0.3 * before

    # a pixel fitted with an absurd albedo (a pixel no light reaches: any albedo times a vanishing shading; 10^5
    # and more on our Mitsuba captures) is a receiver of at most a white albedo: the indirect light taken out of
    # the images stays what the others' terms give, the share stays a share
    from gpps.flows.interreflection import interreflection_terms

    base = solve(images)
    wild = solve(images)
    bad = (m.nonzero()[0][::211], m.nonzero()[1][::211])  # (a few, spread over the cap: fewer than 1 %)
    assert 3 <= bad[0].size < 0.01 * m.sum()
    wild.albedo[bad] = 6.7e5
    t_base = interreflection_terms(images, m, lights, cam, base, max_albedo=1.0, device=device)
    t_wild = interreflection_terms(images, m, lights, cam, wild, max_albedo=1.0, device=device)
    S = t_base["B"] / np.maximum(base.albedo[None], 1e-12)  # (the gathered radiance per unit albedo)
    np.testing.assert_allclose(t_wild["B"][:, bad[0], bad[1]], S[:, bad[0], bad[1]], rtol=1e-5, atol=1e-7)
    keep = m.copy()
    keep[bad] = False
    np.testing.assert_array_equal(t_wild["B"][:, keep], t_base["B"][:, keep])
    unclipped = interreflection_terms(images, m, lights, cam, wild, device=device)["B"]
    assert unclipped[:, m].sum() > 100 * images[:, m].sum()  # (what the compensation took out before the clip)
    _, info5 = reconstruct_subtracting(lambda im: wild if im is images else solve(im), images, m, lights, cam,
                                       rounds=1, albedo_scale=1.0, device=device)
    assert not info5["skipped"]
    assert info["indirect_share"][0] <= info5["indirect_share"][0] < 1.1 * info["indirect_share"][0]

    # a scale that makes the albedo exceed 1 is lowered to the brightest pixels' white ...
    _, info = reconstruct_subtracting(solve, images, m, lights, cam, rounds=1, albedo_scale=1.3, device=device)
    assert info["lowered"] and 1.0 < info["tau"][0] < 1.3
    # ... and far beyond what a self-lit matte surface shows nothing is taken out, with a warning
    import gpps

    with pytest.warns(gpps.GppsWarning, match="left in"):
        rec2, info = reconstruct_subtracting(solve, images, m, lights, cam, albedo_scale=3.0, device=device)
    assert info["skipped"] and info["tau"] == [] and info["apparent_albedo"] > 1.5
    np.testing.assert_allclose(maen(rec2.normals), before, rtol=1e-6)

    # a metal (the conductor model chosen) has no diffuse albedo to send light on: nothing taken out, with a warning
    def metal(imgs):
        return SimpleNamespace(**dict(vars(solve(imgs)), material=Material("conductor")))

    with pytest.warns(gpps.GppsWarning, match="conductor"):
        rec4, info = reconstruct_subtracting(metal, images, m, lights, cam, device=device)
    assert info["skipped"] and info["tau"] == []
    np.testing.assert_allclose(maen(rec4.normals), before, rtol=1e-6)


def test_convex_surface_is_not_reconstructed_again(device):
    """A convex surface sends itself no light: the first gather's share is below ``NEGLIGIBLE_SHARE`` and the
    compensation returns the first reconstruction without solving again."""
    from types import SimpleNamespace

    from gpps.flows.interreflection import NEGLIGIBLE_SHARE, reconstruct_subtracting
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    size, R = 40, 16.0
    ii, jj = np.mgrid[0:size, 0:size].astype(float)
    x, y = jj - (size - 1) / 2, -(ii - (size - 1) / 2)
    m = x * x + y * y < (0.9 * R) ** 2
    zz = np.sqrt(np.clip(R * R - x * x - y * y, 0, None))
    depth = np.where(m, 100.0 - zz, 1.0).astype(np.float32)  # (a sphere seen from outside)
    n = np.where(m[..., None], np.stack([x, y, zz], -1) / R, (0.0, 0.0, 1.0)).astype(np.float32)
    dirs = np.array([[0.3, 0.2, 0.93], [-0.4, 0.1, 0.91], [0.0, -0.5, 0.87]])
    lights = DirectionalLights(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True))
    images = np.repeat(np.clip(np.einsum("kc,hwc->khw", lights.directions, n), 0, None)[..., None], 3, -1)
    images = (0.7 * images * m[None, ..., None]).astype(np.float32)
    calls = []

    def solve(imgs):
        calls.append(imgs)
        return SimpleNamespace(normals=n, albedo=np.full(m.shape + (3,), 0.7, np.float32), depth=depth,
                               depth_mask=m, material=Material("lambertian"))

    rec, info = reconstruct_subtracting(solve, images, m, lights, Orthographic(1.0), rounds=2, device=device)
    assert len(calls) == 1 and info["negligible"] and not info["skipped"]
    rs = info["round_seconds"]
    assert len(rs["gather"]) == 1 and rs["solve"] == [] and rs["first"] >= 0 and rs["gather"][0] > 0
    assert len(info["indirect_share"]) == 1 and info["indirect_share"][0] < NEGLIGIBLE_SHARE


def test_folder_flow_subtracts(tmp_path, device):
    """``gpps.reconstruct_folder`` with ``interreflections="subtract"`` on the self-lit cap written as a capture
    folder (16-bit, orthographic): the report carries the rounds' record and the normals beat the default's."""
    import gpps
    from gpps.host.metrics import normal_errors
    from gpps.io import Dataset, write_dataset

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    ds = Dataset(images=images, mask=m, light_directions=lights.directions, light_intensities=np.ones((8, 3), np.float32),
                 normal_gt=n, filenames=[f"{i:03d}.png" for i in range(1, 9)])
    folder = write_dataset(tmp_path / "cap", ds, bits=16)
    off = gpps.reconstruct_folder(folder, gpps.FolderConfig(brdf="lambertian", interreflections="off"), device=device)
    on = gpps.reconstruct_folder(folder, gpps.FolderConfig(brdf="lambertian", interreflections="subtract",
                                                           albedo_scale=1.0), device=device)
    ir = on.report["interreflections"]
    assert off.report["interreflections"] == {"skipped": True, "why": "turned off"}
    assert ir["tau"] == [1.0] and not ir["skipped"] and ir["indirect_share"][0] > 0.05 and ir["why"] == "asked"
    a = normal_errors(off.normals, n, m)["mean"]
    b = normal_errors(on.normals, n, m)["mean"]
    assert b < 0.5 * a, (a, b)


def test_folder_flow_keeps_the_first_model(tmp_path, device, monkeypatch):
    """With models compared (the default from 5 images), the compensation's later reconstructions keep the material
    the first one estimated on the observed images (no second comparison, no estimation), start every pixel warm
    from the last reconstruction's normals and solve the frame the first one uploaded, as changed on the device (no
    upload after the first reconstruction's); the report keeps the first comparison."""
    import gpps
    import gpps.flows.reconstruction as fr
    from gpps.flows.ron import _RESIDENT, RON
    from gpps.io import Dataset, write_dataset
    from gpps.pipeline.solver import PixelSolver

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    ds = Dataset(images=images, mask=m, light_directions=lights.directions, light_intensities=np.ones((8, 3), np.float32),
                 normal_gt=n, filenames=[f"{i:03d}.png" for i in range(1, 9)])
    folder = write_dataset(tmp_path / "cap", ds, bits=16)
    runs, recs, uploads = [], [], []
    real_run, real_again, real_upload = RON.run, fr.ResidentFrame.again, PixelSolver.upload

    def run(self, images, **kw):
        runs.append((images is _RESIDENT, self.config.models, self.config.estimate, self.material, kw.get("start"),
                     len(uploads)))
        return real_run(self, images, **kw)

    def again(self, start, **kw):
        r = real_again(self, start, **kw)
        recs.append((start, r))
        return r

    def upload(self, *a, **kw):
        uploads.append(1)
        return real_upload(self, *a, **kw)

    monkeypatch.setattr(RON, "run", run)
    monkeypatch.setattr(fr.ResidentFrame, "again", again)
    monkeypatch.setattr(PixelSolver, "upload", upload)
    on = gpps.reconstruct_folder(folder, gpps.FolderConfig(interreflections="subtract", interreflection_rounds=2),
                                 device=device)
    assert on.report["interreflections"]["resident"] is True
    assert len(runs) == 3 and len(recs) == 2
    resident, models, estimate, material, start, _ = runs[0]
    assert not resident and set(models) == {"conductor", "plastic"} and material.brdf == "blinn-phong" and start is None
    first_uploads = runs[1][5]
    assert first_uploads >= 1 and len(uploads) == first_uploads  # (nothing uploaded after the first reconstruction)
    chosen = recs[0][0].material  # (the first reconstruction's, in the caller's scale)
    for k, (resident, models, estimate, material, start, _) in enumerate(runs[1:]):  # (the material kept, warm)
        assert resident and models == () and estimate == ()
        assert material.brdf == chosen.brdf and recs[k][1].material == chosen
        np.testing.assert_array_equal(start[0], recs[k][0].normals)  # (the last reconstruction's normals)
    assert recs[1][0] is recs[0][1]
    assert set(on.report["model_energies"]) == {"blinn-phong", "conductor", "plastic"}
    assert on.report["material"]["brdf"] == chosen.brdf
    # (report.json's stage times are the whole call's: the three reconstructions' summed, the gathers a stage)
    t, ir = on.report["timings"], on.report["interreflections"]
    every = [recs[0][0].timings] + [r.timings for _, r in recs]
    for stage in ("least_squares", "dgmc", "normals", "material"):
        assert t[stage] == pytest.approx(sum(x[stage] for x in every), rel=1e-9, abs=1e-12)
    assert t["normals"] > recs[1][1].timings["normals"] > 0
    assert t["interreflections"] == pytest.approx(sum(ir["round_seconds"]["gather"])) and t["interreflections"] > 0
    assert t["total"] == ir["seconds"] >= sum(x["total"] for x in every) + t["interreflections"] - 1e-6


def test_assumed_scale_follows_the_rule(device):
    """With the light's scale unknown (``albedo_scale=None``) ``tau`` makes the brightest pixels' albedo
    ``ASSUMED_BRIGHT_ALBEDO``, once, from the first reconstruction (later rounds keep it); the light left in then
    scales as ``|kd - a|``: a cap of albedo ``a`` comes back as with its true scale, one of albedo ``a / 2`` (the
    rule's break-even) no better and no worse by much, and a darker one gets at most the error of an uncompensated
    cap of albedo ``a``."""
    from gpps.flows.interreflection import reconstruct_subtracting, tau_bound
    from gpps.names import ASSUMED_BRIGHT_ALBEDO as A

    def run(kd, scale, rounds=1):
        m, depth, n, lights, cam, direct, images = _self_lit(device, kd)
        solve = _least_squares_solver(m, lights, depth)

        def maen(nn):
            return float(np.degrees(np.arccos(np.clip((nn[m] * n[m]).sum(-1), -1, 1))).mean())

        first = solve(images)
        rec, info = reconstruct_subtracting(solve, images, m, lights, cam, rounds=rounds, albedo_scale=scale,
                                            device=device)
        return maen(first.normals), maen(rec.normals), info, tau_bound(first.albedo, m)

    before, after, info, bound = run(0.8, None, rounds=2)
    assert info["scale"] == "assumed" and info["albedo_scale"] is None and not info["skipped"]
    assert info["tau"] == [A * bound, A * bound]  # (set once: the second round's albedo does not move it)
    true_before, true_after, _, _ = run(0.8, 1.0, rounds=2)
    assert true_before == before and true_after < after < 0.7 * before  # (|0.8 - 0.5| of 0.8 left in)
    # albedo a: as the true scale
    b, a_assumed, _, _ = run(A, None)
    _, a_true, _, _ = run(A, 1.0)
    assert a_assumed < 0.3 * b and abs(a_assumed - a_true) < 0.1 * b
    # albedo a / 2: the break-even, as much taken out too much as was in
    b, half, _, _ = run(A / 2, None)
    assert 0.5 * b < half < 1.5 * b
    # a dark cap: at most what an uncompensated cap of albedo a shows
    b, dark, _, _ = run(A / 8, None)
    assert dark < before * A / 0.8 and dark < run(A, None)[0]


def test_automatic_policy(tmp_path, device):
    """``interreflections="auto"`` (the default) subtracts from ``INTERREFLECTION_MIN_IMAGES`` images on, with RON's
    integrated depth; the report says which rule decided."""
    import gpps
    from gpps.flows.folder import automatic_interreflections
    from gpps.io import Dataset, write_dataset
    from gpps.names import INTERREFLECTION_MIN_IMAGES as K

    cfg = gpps.FolderConfig()
    assert cfg.interreflections == "auto" and cfg.albedo_scale is None
    assert automatic_interreflections(K - 1, cfg) == (False, f"automatic: off with {K - 1} images (on from {K})")
    assert automatic_interreflections(K, cfg) == (True, f"automatic: on from {K} images")
    assert automatic_interreflections(96, gpps.FolderConfig(method="ppn"))[0] is False
    assert automatic_interreflections(96, gpps.FolderConfig(integrate=False))[0] is False
    assert automatic_interreflections(3, gpps.FolderConfig(interreflections="subtract")) == (True, "asked")
    assert automatic_interreflections(96, gpps.FolderConfig(interreflections="off")) == (False, "turned off")

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    ds = Dataset(images=images, mask=m, light_directions=lights.directions, light_intensities=np.ones((8, 3), np.float32),
                 normal_gt=n, filenames=[f"{i:03d}.png" for i in range(1, 9)])
    folder = write_dataset(tmp_path / "cap", ds, bits=16)
    res = gpps.reconstruct_folder(folder, gpps.FolderConfig(brdf="lambertian"), device=device)
    ir = res.report["interreflections"]
    assert ir["why"] == f"automatic: on from {K} images" and ir["scale"] == "assumed" and len(ir["tau"]) == 1
    assert ir["indirect_share"][0] > 0.02
    few = write_dataset(tmp_path / "few", Dataset(images=images[:4], mask=m, light_directions=lights.directions[:4],
                                                  light_intensities=np.ones((4, 3), np.float32), normal_gt=n,
                                                  filenames=[f"{i:03d}.png" for i in range(1, 5)]), bits=16)
    res4 = gpps.reconstruct_folder(few, gpps.FolderConfig(brdf="lambertian"), device=device)
    assert res4.report["interreflections"] == {"skipped": True, "why": f"automatic: off with 4 images (on from {K})"}


def test_cli_options():
    """``gpps reconstruct --interreflections subtract --albedo-scale .. --interreflection-rounds ..`` set the
    FolderConfig; errors name the options."""
    import argparse

    import gpps
    from gpps.cli.reconstruct import add_reconstruct_options, folder_config

    p = argparse.ArgumentParser()
    add_reconstruct_options(p)
    cfg = folder_config(p.parse_args(["--interreflections", "subtract", "--albedo-scale", "0.5",
                                      "--interreflection-rounds", "3"]))
    assert (cfg.interreflections, cfg.albedo_scale, cfg.interreflection_rounds) == ("subtract", 0.5, 3)
    default = folder_config(p.parse_args([]))
    assert (default.interreflections, default.albedo_scale, default.interreflection_rounds) == ("auto", None, 1)
    assert default == gpps.FolderConfig()
    with pytest.raises(ValueError, match="^--albedo-scale"):
        folder_config(p.parse_args(["--albedo-scale", "-1"]))
    with pytest.raises(ValueError, match="^--interreflections"):
        folder_config(p.parse_args(["--interreflections", "subtract", "--method", "ppn"]))


def _model_reference(cam, m, depth, nrm, albedo, material, dirs, intens, visible, src, area_scale):
    """numpy float64 of :func:`gpps.kernels.interreflection.model_gather_kernel` (its docstring's sum, no
    occlusion between patches), directional lights ``dirs`` (N, 3) of RGB radiance ``intens`` (N, 3)."""
    from reference_models import terms

    recv, pr, nr, ns, om, cr, F = _form_factors(cam, m, depth, nrm, src, area_scale)
    ar, as_ = albedo[recv[:, 0], recv[:, 1]].astype(np.float64), albedo[src[:, 0], src[:, 1]].astype(np.float64)
    vr = -pr / np.linalg.norm(pr, axis=-1, keepdims=True)
    R, S = F.shape
    n_r = np.broadcast_to(nr[:, None], (R, S, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        t0r, t1r = terms(material, n_r, om, np.broadcast_to(vr[:, None], (R, S, 3)))  # the receiver, lit from omega
    T = ar[:, None] * t0r[..., None] + material.ks * t1r[..., None]  # (R, S, 3)
    out = np.zeros((len(dirs),) + m.shape + (3,))
    for k, (l, e) in enumerate(zip(dirs, intens)):
        lk = np.broadcast_to(l, (R, S, 3))
        with np.errstate(divide="ignore", invalid="ignore"):  # (pairs the reference's np.where leaves out)
            t0s, t1s = terms(material, np.broadcast_to(ns[None], (R, S, 3)), lk, -om)  # the source toward r
        Ls = e * (as_[None] * t0s[..., None] + material.ks * t1s[..., None]) * visible[k, src[:, 0], src[:, 1]][None, :, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            g = np.where(F > 0, F / cr, 0.0)
        out[k, recv[:, 0], recv[:, 1]] = np.einsum("rs,rsc->rc", g, T * Ls)
    return out


@pytest.mark.parametrize("brdf", ["lambertian", "blinn-phong", "conductor", "plastic"])
def test_model_gather_matches_numpy(device, brdf):
    """The one-bounce gather under the reflectance model at both ends against numpy float64 from its formula, on a
    perspective concave surface (no occlusion between patches), one light cast-shadowed at some sources."""
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    cam, m, depth, nrm, _ = _surface()
    mat = {"lambertian": Material("lambertian"), "blinn-phong": Material("blinn-phong", ks=0.6, shininess=12.0),
           "conductor": Material("conductor", roughness=0.3, f0=0.8),
           "plastic": Material("plastic", ks=0.5, roughness=0.25, f0=0.04)}[brdf]
    rng = np.random.default_rng(5)
    albedo = rng.uniform(0.3, 0.9, m.shape + (3,)).astype(np.float32)
    dirs = np.array([[0.3, 0.2, 0.93], [-0.5, 0.1, 0.86]])
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    intens = np.array([[1.0, 0.9, 0.8], [0.7, 0.7, 0.7]])
    lights = DirectionalLights(dirs, intens)
    visible = np.ones((2,) + m.shape, bool)
    visible[1, ::2, :] = False
    cfg = InterreflectionConfig(max_sources=120, visibility=False, max_rows=97)
    with Interreflections((2,) + m.shape, cam, cfg, device=device) as st:
        st.upload(depth, m, nrm, np.zeros((2,) + m.shape + (3,), np.float32))
        got = st.gather_model(albedo, mat, lights, visible)
        stride = st.stride
    src, _ = source_pixels(m, 120)
    ref = _model_reference(cam, m, depth, nrm, albedo, mat, dirs, intens, visible, src, float(stride**2))
    assert ref[:, m].max() > 1e-3 and np.all(got[:, ~m] == 0)
    np.testing.assert_allclose(got, ref, rtol=2e-3, atol=2e-6)
    if brdf == "lambertian":  # a matte source's radiance is its image: the diffuse gather times the albedo
        with Interreflections((2,) + m.shape, cam, cfg, device=device) as st:
            img = (albedo[None] * np.clip(np.einsum("kc,hwc->khw", dirs, nrm), 0, None)[..., None]
                   * intens[:, None, None, :] * visible[..., None]).astype(np.float32)
            S = st.run(depth, m, nrm, img)
        np.testing.assert_allclose(got, albedo[None] * S, rtol=1e-4, atol=1e-6)


def test_model_gather_checks(device):
    from gpps.lights import DirectionalLights
    from gpps.material import Material

    cam, m, depth, nrm, _ = _surface(12)
    lights = DirectionalLights(np.array([[0.0, 0.0, 1.0]]))
    with Interreflections((1,) + m.shape, cam, device=device) as st:
        with pytest.raises(ValueError, match="upload"):
            st.gather_model(np.ones(m.shape + (3,)), Material("conductor"), lights)
        st.upload(depth, m, nrm, np.zeros((1,) + m.shape + (3,), np.float32))
        with pytest.raises(ValueError, match="albedo"):
            st.gather_model(np.ones(m.shape), Material("conductor"), lights)
        with pytest.raises(ValueError, match="lights"):
            st.gather_model(np.ones(m.shape + (3,)), Material("conductor"),
                            DirectionalLights(np.array([[0.0, 0.0, 1.0], [0.0, 0.6, 0.8]])))
        with pytest.raises(ValueError, match="visible"):
            st.gather_model(np.ones(m.shape + (3,)), Material("conductor"), lights, np.ones((2,) + m.shape, bool))
        with pytest.raises(TypeError, match="material"):
            st.gather_model(np.ones(m.shape + (3,)), "conductor", lights)


def test_glossy_terms_of_a_matte_surface_are_the_diffuse_ones(device):
    """``interreflection_terms(glossy=True)`` sends on the model's direct radiance (cast shadows from the depth);
    for a Lambertian surface whose images are exactly that radiance, it equals the diffuse gather of the images
    times the albedo (both with the receivers' albedo clipped at ``max_albedo``)."""
    from types import SimpleNamespace

    from gpps.flows.interreflection import interreflection_terms
    from gpps.lights import DirectionalLights
    from gpps.material import Material
    from gpps.pipeline.render import Renderer
    from gpps.pipeline.shadows import CastShadows

    cam, m, depth, nrm, _ = _surface(24)
    dirs = np.array([[0.95, 0.1, 0.3], [-0.2, -0.9, 0.4], [0.0, 0.0, 1.0]])
    lights = DirectionalLights(dirs / np.linalg.norm(dirs, axis=-1, keepdims=True))
    albedo = np.random.default_rng(2).uniform(0.2, 0.9, m.shape + (3,)).astype(np.float32)
    albedo[5, 7] = 40.0  # (a wild fit: clipped at max_albedo, as a receiver and as a source of modelled light)
    mat = Material("lambertian")
    with Renderer(m.shape, cam, lights, mat, device=device) as rd:
        direct = rd.run(depth, m, np.minimum(albedo, 1.0), nrm)
    with CastShadows((3,) + m.shape, cam, lights, device=device) as cs:
        cs.upload(depth, m)
        cs.step()
        vis = cs.fetch()
    assert not vis[:, m].all()  # (the concave surface shadows itself under the oblique lights)
    images = (direct * vis[..., None]).astype(np.float32)
    rec = SimpleNamespace(normals=nrm, depth=depth, depth_mask=m, albedo=albedo, material=mat)
    cfg = InterreflectionConfig(max_sources=150)
    g = interreflection_terms(images, m, lights, cam, rec, config=cfg, max_albedo=1.0, glossy=True, device=device)
    d = interreflection_terms(images, m, lights, cam, rec, config=cfg, max_albedo=1.0, device=device)
    assert g["stride"] == d["stride"] and g["sources"] == d["sources"]
    assert d["B"][:, m].max() > 1e-3
    np.testing.assert_allclose(g["B"], d["B"], rtol=2e-4, atol=1e-6)


@pytest.mark.parametrize("brdf", ["blinn-phong", "plastic"])
def test_sources_less_specular_match_the_renders(device, brdf):
    """``upload(..., less_specular=(material, lights))``: the sources' radiance is the images less the model's
    specular part, evaluated at the sources only; it equals the images less (the render less its render with
    ks = 0) there, clipped at 0 (what the flow computed with two full renders before)."""
    from dataclasses import replace

    from gpps.lights import PointLights
    from gpps.material import Material
    from gpps.pipeline.render import Renderer

    cam, m, depth, nrm, pts = _surface(24)
    mat = {"blinn-phong": Material("blinn-phong", ks=0.7, shininess=15.0),
           "plastic": Material("plastic", ks=0.5, roughness=0.2, f0=0.04)}[brdf]
    lights = PointLights(np.array([[2.0, 1.0, 0.0], [-1.5, 0.5, 1.0], [0.0, -2.0, -1.0]]),
                         np.full((3, 3), 100.0))  # (the surface is ~10 units away)
    albedo = np.random.default_rng(4).uniform(0.2, 0.9, m.shape + (3,)).astype(np.float32)
    images = np.random.default_rng(5).uniform(0.0, 0.3, (3,) + m.shape + (3,)).astype(np.float32)
    with Renderer(m.shape, cam, lights, mat, device=device) as rd:
        full = rd.run(depth, m, albedo, nrm)
    with Renderer(m.shape, cam, lights, replace(mat, ks=0.0), device=device) as rd:
        diffuse = rd.run(depth, m, albedo, nrm)
    cfg = InterreflectionConfig(max_sources=100)
    with Interreflections((3,) + m.shape, cam, cfg, device=device) as st:
        st.upload(depth, m, nrm, images + full, less_specular=(mat, lights))
        got = st.radiance.numpy()
        with pytest.raises(ValueError, match="less_specular"):
            st.upload(depth, m, nrm, images, less_specular=(mat, PointLights(np.ones((2, 3)))))
    src, _ = source_pixels(m, 100)
    ref = np.clip(images + full - (full - diffuse), 0.0, None)[:, src[:, 0], src[:, 1], :]
    ref = ref.transpose(1, 0, 2).reshape(len(src), 9)
    assert (full - diffuse)[:, src[:, 0], src[:, 1]].max() > 0.05  # (the sources do show a specular part)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-6)
