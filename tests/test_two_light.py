"""The two-light start of RON's refinement (gpps.host.two_light, RONConfig.refine_two_light) and the refiner's
likelihood (gpps.pipeline.depth_refine.cauchy_likelihood).

References independent of the code under test: gpps.host.perspective.gradient_to_normals for the affine normal;
analytic planes (exact depth, Lambertian shading written here) for the two-light equations; scipy.stats.cauchy's
maximum-likelihood fit for the likelihood; tests/ron_shadow_scenes.py's box and hemisphere on a plane with exact
3D visibility for RON.
"""

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parent))
from ron_shadow_scenes import bump_case, run_ron, solid_case, write_case_folder  # noqa: E402

from gpps.camera import Orthographic, Perspective  # noqa: E402
from gpps.flows.ron import RONConfig  # noqa: E402
from gpps.host.metrics import normal_errors  # noqa: E402
from gpps.host.perspective import gradient_to_normals, normals_to_gradient  # noqa: E402
from gpps.host.perspective import affine_normal  # noqa: E402
from gpps.host.two_light import dark_observations, two_light_log_depth  # noqa: E402
from gpps.lights import DirectionalLights, ring_directions  # noqa: E402
from gpps.pipeline.depth_refine import cauchy_likelihood  # noqa: E402

CAMERAS = {"orthographic": Orthographic(1.0),
           "perspective": Perspective([[300.0, 0, 31.5], [0, 300.0, 31.5], [0, 0, 1]])}


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


@pytest.mark.parametrize("cam", sorted(CAMERAS))
def test_affine_normal_is_the_gradients_normal(cam):
    """``u_x a + u_y b + c`` normalised is the normal whose gradient is ``(u_x, u_y)``: gpps.host.perspective's
    normals_to_gradient (its own ray formula, PPN 3.2-3.3) gives the gradient back (float32 there: 1e-6 of it)."""
    camera = CAMERAS[cam]
    rng = np.random.default_rng(0)
    g = rng.normal(scale=0.02 if cam == "perspective" else 0.5, size=(64, 64, 2))
    m = np.ones((64, 64), bool)
    a, b, c = affine_normal(camera, (64, 64))
    n = g[..., :1] * a + g[..., 1:] * b + c
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    np.testing.assert_allclose(normals_to_gradient(n, m, camera), g, rtol=1e-5, atol=1e-6 * np.abs(g).max())
    with pytest.raises(TypeError, match="camera"):
        affine_normal(object(), (4, 4))


def _plane(cam, size=64):
    """A tilted plane: its exact depth, ``u`` (log-depth or depth) and unit normal per pixel."""
    camera = CAMERAS[cam]
    n0 = np.array([0.35, -0.25, 1.0])
    n0 /= np.linalg.norm(n0)
    jj, ii = np.meshgrid(np.arange(size, dtype=np.float64), np.arange(size, dtype=np.float64))
    if cam == "orthographic":  # the plane n . X = const with X = (j, -i, -d)
        d = 100.0 + (n0[0] * jj - n0[1] * ii) / n0[2]
        return d, d, np.broadcast_to(n0, (size, size, 3)).copy()
    cx, cy = camera.principal_point()
    r = np.stack([(jj - cx) / camera.fx, -(ii - cy) / camera.fy, -np.ones_like(jj)], -1)
    d = -200.0 * n0[2] / (r @ n0)  # the ray r d meets n . X = -200 n_z
    return d, np.log(d), np.broadcast_to(n0, (size, size, 3)).copy()


@pytest.mark.parametrize("coarse", [False, True])
@pytest.mark.parametrize("cam", sorted(CAMERAS))
def test_two_light_equations_recover_a_shadowed_plane(cam, coarse):
    """A Lambertian plane (colour albedo with a texture) under 3 directional lights, the third's observations dark
    in a disc (a cast shadow); the per-pixel normals there tilted 35 deg (what a fit explaining the shadow does):
    the two-light surface's normals in the disc are the plane's within 0.5 deg, and the start's ``u`` equals the
    plane's up to a constant (0.2 % of its span); outside the disc nothing needs it (no two-light pixel there).
    ``coarse``: the solve on 2 x 2 blocks (``max_pixels`` 1024 of the 4096 pixels), ``u`` interpolated back: the
    normals' bounds (measured 0.004 deg in the disc's interior), ``u`` within 2 % of its span (measured 0.8 %: the
    outermost half block is held at its block's value, not extrapolated)."""
    size = 64
    d, u_true, n_true = _plane(cam, size)
    lights = DirectionalLights(ring_directions(3, 40.0))
    jj, ii = np.meshgrid(np.arange(size), np.arange(size))
    albedo = np.stack([0.5 + 0.3 * np.sin(jj / 5.0), 0.6 + 0.2 * np.cos(ii / 7.0), np.full((size, size), 0.4)], -1)
    shade = np.clip(np.einsum("hwc,kc->khw", n_true, lights.directions), 0, None)
    assert shade.min() > 0.2  # (every light reaches the plane: the only dark observations are the disc's)
    images = albedo[None] * shade[..., None]
    disc = (ii - 30) ** 2 + (jj - 34) ** 2 < 14 ** 2
    images[2][disc] = 0.002
    m = np.ones((size, size), bool)
    dark = dark_observations(images, m)
    assert dark[2][disc].all() and not dark[:2].any()
    tilt = np.where(disc[..., None], np.array([0.0, 0.57, 0.82]), n_true)  # 35 deg off inside the disc
    tilt /= np.linalg.norm(tilt, axis=-1, keepdims=True)
    u, two = two_light_log_depth(images, dark, tilt, m, CAMERAS[cam], lights.directions,
                                 max_pixels=1024 if coarse else None)
    if coarse:  # (the blocks straddling the disc's edge are two-light blocks too)
        assert abs(int(two.sum()) - int(dark[2].sum())) < 0.25 * dark[2].sum()
    else:
        assert two.sum() == dark[2].sum() and np.array_equal(two, dark[2])
    g = np.zeros((size, size, 2))
    g[:, 1:-1, 0] = (u[:, 2:] - u[:, :-2]) / 2
    g[1:-1, :, 1] = (u[2:] - u[:-2]) / 2
    n = gradient_to_normals(g, m, CAMERAS[cam]).astype(np.float64)
    inner = disc.copy()
    inner[:, [0, -1]] = inner[[0, -1], :] = False
    err = _angles(n, n_true)[inner]
    ref = u_true - u_true.mean()
    dev = np.abs(u - ref).max() / np.ptp(ref)
    print(f"\n{cam}: shadowed-disc normals {err.mean():.4f} deg mean, {err.max():.4f} max; u off by {dev:.2e} of its span")
    assert err.mean() < 0.5 and err.max() < 2.0
    assert dev < (2e-2 if coarse else 2e-3)
    # (the per-pixel normals were 35 deg off there)
    assert _angles(tilt, n_true)[disc].mean() > 30


def test_two_light_none_without_two_light_pixels():
    """No pixel with exactly two lit observations: no start (None) and an empty two-light mask."""
    m = np.ones((16, 16), bool)
    images = np.full((3, 16, 16, 3), 0.5)
    dark = dark_observations(images, m)
    n = np.zeros((16, 16, 3))
    n[..., 2] = 1.0
    u, two = two_light_log_depth(images, dark, n, m, Orthographic(1.0), ring_directions(3, 30.0))
    assert u is None and not two.any()


def test_dark_observations_rule_and_checks():
    """Dark: below 0.1 of the pixel's brightest grey value, grown by ``dilate`` pixels, invalid ones dark too, and
    nothing outside the mask; bad arguments are errors naming them."""
    y = np.full((3, 9, 9), 1.0)
    y[0, 4, 4] = 0.05
    m = np.ones((9, 9), bool)
    m[0, 0] = False
    d0 = dark_observations(y, m, dilate=0)
    assert d0.sum() == 1 and d0[0, 4, 4]
    d1 = dark_observations(y, m)
    assert d1[0].sum() == 5 and not d1[1:].any()  # (the cross of 4-neighbours)
    valid = np.ones((3, 9, 9), bool)
    valid[2, 1, 1] = False
    assert dark_observations(y, m, valid, dilate=0)[2, 1, 1]
    y[1, 0, 0] = 0.0
    assert not dark_observations(y, m, dilate=0)[1, 0, 0]  # (outside the mask)
    with pytest.raises(ValueError, match="relative"):
        dark_observations(y, m, relative=1.5)
    with pytest.raises(ValueError, match="images"):
        dark_observations(np.ones((9, 9)), m)
    with pytest.raises(ValueError, match="valid"):
        dark_observations(y, m, np.ones((2, 9, 9), bool))
    with pytest.raises(ValueError, match="directions"):
        two_light_log_depth(y, d1, np.zeros((9, 9, 3)), m, Orthographic(1.0), np.ones((2, 3)))


@pytest.mark.parametrize("seed", [0, 1])
def test_cauchy_likelihood_is_scipys_fit(seed):
    """The scale solves the likelihood equation ``mean(r^2 / (r^2 + s^2)) = 1/2`` (to 1e-12) and agrees with
    scipy.stats.cauchy's numerical fit (location 0; scipy's optimiser stops at about 1e-4 relative), whose mean
    negative log-likelihood, scipy's own logpdf, is never lower (the exact root is the optimum) and within 1e-6;
    absolute residuals give the same (the density is symmetric); half the residuals 0 gives -inf."""
    rng = np.random.default_rng(seed)
    r = stats.cauchy.rvs(scale=0.03, size=4000, random_state=rng)
    got = cauchy_likelihood(r)
    s = got["scale"]
    assert abs(np.mean(r * r / (r * r + s * s)) - 0.5) < 1e-12
    loc, scale = stats.cauchy.fit(r, floc=0.0)
    assert s == pytest.approx(scale, rel=1e-3)
    mine = -float(np.mean(stats.cauchy.logpdf(r, loc=0.0, scale=s)))
    theirs = -float(np.mean(stats.cauchy.logpdf(r, loc=0.0, scale=scale)))
    assert got["nll"] == pytest.approx(mine, rel=1e-12, abs=1e-12)
    assert mine <= theirs + 1e-12 and theirs - mine < 1e-6
    assert cauchy_likelihood(np.abs(r))["nll"] == pytest.approx(got["nll"], rel=1e-12)
    assert got["observations"] == r.size
    assert cauchy_likelihood(np.r_[np.zeros(10), 1.0])["nll"] == -np.inf
    with pytest.raises(ValueError, match="residuals"):
        cauchy_likelihood([np.nan])


def _ron(device, case, **cfg):
    return run_ron(device, case, refine=True, **cfg)


@pytest.mark.parametrize("scene", ["box-perspective", "box-orthographic"])
def test_two_light_start_recovers_cast_shadows(device, scene):
    """A box standing on a plane, 3 directional lights at slant 45 (exact 3D cast shadows, Blinn-Phong, 64^2,
    noise 0.002), both cameras: the refinement from the integrated depth keeps the shadows' tilt; the two-light
    start's refined surface is likelier and is kept.  Measured on the CPU: perspective MAEN 11.74 -> 0.08 deg
    (cast-shadow pixels 30.2 -> 0.12), orthographic 15.95 -> 0.06 (40.2 -> 0.08).  (A hemisphere on the plane:
    the integrated start's surface stays the likelier and is kept, 7.97 deg orthographic.)"""
    name, cam = scene.split("-")
    case = solid_case(name, "directional", 3, 64, camera=cam)
    m = case["mask"]
    sh = case["shadow"].any(0)
    off = _ron(device, case, refine_two_light=False)
    on = _ron(device, case)
    e_off = normal_errors(off.normals, case["normals"], m)["mean"]
    e_on = normal_errors(on.normals, case["normals"], m)["mean"]
    s_off = normal_errors(off.normals, case["normals"], sh)["mean"]
    s_on = normal_errors(on.normals, case["normals"], sh)["mean"]
    info = on.refinement
    print(f"\n{scene}: MAEN {e_off:.3f} -> {e_on:.3f}, cast-shadow pixels {s_off:.2f} -> {s_on:.2f}; "
          f"{info['starts']}")
    assert "starts" not in off.refinement
    assert info["chosen"] == "two-light"
    assert info["starts"]["two-light"]["nll"] < info["starts"]["integrated"]["nll"]
    assert info["starts"]["two-light"]["pixels"] > 0.05 * m.sum()
    assert e_on < 0.1 * e_off
    assert s_on < 0.4 * s_off
    assert np.all(np.isfinite(on.normals[m])) and np.all(on.depth[on.depth_mask] > 0)


def test_two_light_start_on_a_smooth_relief(device):
    """The Gaussian bumps on a plane, 3 directional lights at slant 60 (short cast shadows beside long attached
    ones): the two-light surface is the likelier and is kept; it mends the cast-shadow pixels (measured on the CPU
    5.69 -> 0.25 deg) and costs elsewhere (whole mask 0.98 -> 1.22: the truth's likelihood is higher than either
    refined surface's, both refinements stop short of it, and the likelihood prefers the one nearer in the
    shadows).  The whole mask may not lose more than 0.5 deg."""
    case = bump_case("directional", 3, 64, slant=60.0)
    m = case["mask"]
    sh = case["shadow"].any(0)
    off = _ron(device, case, refine_two_light=False)
    on = _ron(device, case)
    e = [normal_errors(r.normals, case["normals"], w)["mean"] for r in (off, on) for w in (m, sh)]
    print(f"\nbumps, 3 lights: MAEN {e[0]:.3f} -> {e[2]:.3f}, cast-shadow pixels {e[1]:.2f} -> {e[3]:.2f}; "
          f"chosen {on.refinement['chosen']}")
    assert on.refinement["chosen"] == "two-light"
    assert e[3] < 0.2 * e[1]
    assert e[2] < e[0] + 0.5


def test_two_light_start_not_run_where_it_cannot_apply(device):
    """Point lights (their directions depend on the depth being solved) and scenes where no pixel keeps exactly
    two lit observations (12 lights from near the view axis) refine from the integrated depth alone: the same
    result with and without ``refine_two_light``."""
    for case in (bump_case("point", 3, 48, slant=60.0), bump_case("directional", 12, 48, slant=25.0)):
        a = _ron(device, case)
        b = _ron(device, case, refine_two_light=False)
        assert "starts" not in a.refinement
        np.testing.assert_array_equal(a.normals, b.normals)
        np.testing.assert_array_equal(a.depth, b.depth)


def test_refine_two_light_settings():
    """RONConfig / FolderConfig check the switch; ``gpps reconstruct --no-two-light`` turns it off (on by default)."""
    import argparse

    import gpps
    from gpps.cli.reconstruct import add_reconstruct_options, folder_config

    with pytest.raises(TypeError, match="refine_two_light"):
        RONConfig(refine=True, refine_two_light="yes")
    with pytest.raises(TypeError, match="two_light"):
        gpps.FolderConfig(two_light=1)
    p = argparse.ArgumentParser()
    add_reconstruct_options(p)
    assert folder_config(p.parse_args([])).two_light is True
    assert folder_config(p.parse_args(["--no-two-light"])).two_light is False
    assert RONConfig().refine_two_light is True


def test_gradient_round_trip_reference():
    """(The reference the plane test relies on: normals_to_gradient inverts gradient_to_normals.)"""
    cam = CAMERAS["perspective"]
    d, u, n = _plane("perspective")
    m = np.ones(d.shape, bool)
    g = normals_to_gradient(n, m, cam).astype(np.float64)
    np.testing.assert_allclose(gradient_to_normals(g, m, cam), n, atol=2e-6)


def test_folder_flow_two_light(tmp_path, device):
    """``gpps.reconstruct_folder`` on the box standing on a plane (3 directional lights, 16-bit files): the default
    refines from both starts and reports them (the two-light surface kept, MAEN under 1 deg); ``two_light=False``
    refines from the integrated depth alone (no ``starts``).  Measured on the CPU: 0.24 against 0.45 deg; before
    the neighbour pass told cast shadows from attached ones (``SolverConfig.held_dark_refit``, session 35) the
    integrated start alone gave 10.28."""
    import gpps

    case = solid_case("box", "directional", 3, 64)
    folder = write_case_folder(case, tmp_path / "cap")
    on = gpps.reconstruct_folder(folder, device=device)
    off = gpps.reconstruct_folder(folder, gpps.FolderConfig(two_light=False), device=device)
    m = case["mask"]
    e_on = normal_errors(on.normals, case["normals"], m)["mean"]
    e_off = normal_errors(off.normals, case["normals"], m)["mean"]
    print(f"\nfolder flow, box on a plane: two-light off {e_off:.3f} -> on {e_on:.3f} deg")
    assert on.report["refinement"]["chosen"] == "two-light" and set(on.report["refinement"]["starts"]) == {
        "integrated", "two-light"}
    assert "starts" not in off.report["refinement"]
    assert e_on < 1.0 and e_on < e_off < 1.0
