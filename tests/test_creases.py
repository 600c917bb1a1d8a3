"""Crease cut and stitch (gpps.host.creases) against ray-cast ground truth and analytic continuous surfaces."""

import numpy as np
import pytest

from crease_scenes import global_error, render_surface
from discontinuity_scenes import render_box, render_scene, surface_errors
from gpps.camera import Orthographic, Perspective
from gpps.flows.integrate import Integrator, IntegratorConfig, integrate_normals, integrate_normals_creases
from gpps.host.creases import (_edges, crease_edges, crease_pieces, integrate_creases, separating_cuts, stitch_bini,
                               stitch_cut_pieces)
from gpps.host.poisson import pixel_gradients


def _camera(sc):
    return Perspective(sc["K"]) if "K" in sc else Orthographic(sc["pixel_size"])


def test_planar_staircase_is_exact_per_piece():
    # overlapping tilted planes with depth jumps (the suite's "steps", orthographic): each crease piece is one
    # plane, integrated alone, so every piece is exact to rounding after its own offset; Poisson bends them
    sc = render_scene("steps", 40, "orthographic")
    r = integrate_creases(sc["normals"], sc["mask"], _camera(sc))
    pieces, rng = surface_errors(r.depth, sc["depth"], sc["labels"], r.mask, False)
    assert len(pieces) == 4
    assert max(p["max"] for p in pieces) <= 1e-6 * rng
    # the cut pieces are exactly the surfaces
    for k in range(1, r.n_pieces + 1):
        assert np.unique(sc["labels"][r.labels == k]).size == 1


def test_planar_staircase_perspective_per_piece():
    sc = render_scene("steps", 40, "perspective")
    r = integrate_creases(sc["normals"], sc["mask"], _camera(sc), target="mid")
    pieces, rng = surface_errors(r.depth, sc["depth"], sc["labels"], r.mask, True)
    assert max(p["mean"] for p in pieces) <= 1e-5 * rng


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_sphere_mid_normal_targets_are_exact(camera):
    # a sphere's cross-sections are circles: the mid-normal target is the chord's slope, so the disc integrates
    # to rounding (orthographic) or to the perspective cross-section's non-circularity (tiny)
    sc = render_surface("sphere", 40, camera)
    r = integrate_creases(sc["normals"], sc["mask"], _camera(sc), target="mid")
    mean, _ = global_error(r.depth, sc["depth"], sc["mask"], camera == "perspective")
    assert mean <= (1e-9 if camera == "orthographic" else 1e-4)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_continuous_ridge_is_stitched_back(camera):
    # two planes meeting at a vertical fold, no depth jump: the fold is cut into two pieces and the stitch puts
    # them back continuous, so one global offset / scale fits the whole map.  The fold lies 0.3 px from the
    # midpoint of the edges it crosses, a sub-pixel position no integrator can see: the step across a cut edge
    # is then uncertain by 0.3 of the slope change, for the uncut (Poisson) solve too
    size = 40
    sc = render_surface("ridge", size, camera)
    r = integrate_creases(sc["normals"], sc["mask"], _camera(sc), target="mid")
    assert r.n_pieces == 2 and r.info["cut_edges"] == size
    mean, _ = global_error(r.depth, sc["depth"], sc["mask"], camera == "perspective")
    rp = integrate_creases(sc["normals"], sc["mask"], _camera(sc), threshold_deg=89.0)  # nothing cut: Poisson
    assert rp.n_pieces == 1 and rp.info["cut_edges"] == 0
    ref, _ = global_error(rp.depth, sc["depth"], sc["mask"], camera == "perspective")
    # stitched: as good as the uncut solve (both limited by the fold's unknown sub-pixel position), and small
    assert mean <= 1.2 * ref and mean < 1e-2
    # and no jump across the fold beyond the sub-pixel ambiguity: the estimate's step across the cut edges
    # matches the true step to 0.35 of the slope change per pixel
    u = np.log(r.depth) if camera == "perspective" else r.depth
    g = np.log(sc["depth"]) if camera == "perspective" else sc["depth"]
    ii, jj = np.nonzero(r.cut_x)
    est = u[ii, jj + 1] - u[ii, jj]
    tru = g[ii, jj + 1] - g[ii, jj]
    slope_change = np.abs((g[ii, jj + 2] - g[ii, jj + 1]) - (g[ii, jj] - g[ii, jj - 1]))
    assert np.all(np.abs(est - tru) <= 0.35 * slope_change + 1e-12)


def test_clean_smooth_surface_is_not_cut():
    sc = render_surface("bump", 40, "orthographic")
    r = integrate_creases(sc["normals"], sc["mask"], _camera(sc))
    assert r.info["cut_edges"] == 0 and r.n_pieces == 1


def test_bad_input():
    sc = render_scene("steps", 16, "orthographic")
    cam = _camera(sc)
    n, m = sc["normals"], sc["mask"]
    with pytest.raises(ValueError, match="normals"):
        integrate_creases(n[..., :2], m, cam)
    with pytest.raises(ValueError, match="mask"):
        integrate_creases(n, m.astype(int), cam)
    with pytest.raises(ValueError, match="mask"):
        integrate_creases(n, np.zeros_like(m), cam)
    with pytest.raises(ValueError, match="camera"):
        integrate_creases(n, m, None)
    with pytest.raises(ValueError, match="inner"):
        integrate_creases(n, m, cam, inner="multigrid")
    with pytest.raises(ValueError, match="stitch_mode"):
        integrate_creases(n, m, cam, stitch_mode="tree")
    with pytest.raises(ValueError, match="target"):
        integrate_creases(n, m, cam, target="central")
    with pytest.raises(ValueError, match="floor_deg"):
        crease_edges(n, m, floor_deg=-1.0)
    with pytest.raises(ValueError, match="threshold_deg"):
        crease_edges(n, m, threshold_deg=float("nan"))
    with pytest.raises(ValueError, match="min_nz"):
        integrate_creases(n, m, cam, min_nz=2.0)


# ----------------------------------------------------------------------------- faithful BiNI with the creases cut


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_bini_cut_planar_staircase_is_exact_per_piece(camera, device):
    # BiNI with the crease edges as missing neighbours: each piece is one plane, whose one-sided equations the
    # plane satisfies (orthographic exactly; perspective to BiNI's log-depth discretisation), so the error is
    # the inner CG's: within the 1e-3 of the range at BiNI's own tolerance (measured 6.9e-5 / 8.3e-5;
    # uncut BiNI 6.4e-2 / 6.7e-2), and at rounding (float32 depth) / discretisation level with a tight one
    sc = render_scene("steps", 40, camera)
    persp = camera == "perspective"
    for tol, bound in ((1e-3, 2e-4), (1e-10, 1e-8 if not persp else 2e-6)):
        r, c = integrate_normals_creases(sc["normals"], sc["mask"], camera=_camera(sc), device=device,
                                         bilateral_inner_tol=tol)
        pieces, rng = surface_errors(r.depth.astype(np.float64), sc["depth"], sc["labels"], r.mask, persp)
        assert len(pieces) == 4 and max(p["mean"] for p in pieces) <= bound * rng, (tol, pieces)
        assert c["n_pieces"] == 4
        for k in range(1, c["n_pieces"] + 1):
            assert np.unique(sc["labels"][c["pieces"] == k]).size == 1


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_bini_cut_without_creases_is_bini_bitwise(camera, device):
    # (at 32 px the perspective bump's peak is cut: 6 edges; at 40 px nothing is).  Bitwise on the CPU; on CUDA
    # BiNI's float64 block sums end in atomics (their order varies run to run), so two runs agree to rounding
    sc = render_surface("bump", 40, camera)
    cam = _camera(sc)
    r, c = integrate_normals_creases(sc["normals"], sc["mask"], camera=cam, device=device, reference_depth=5.0)
    r0 = integrate_normals(sc["normals"], sc["mask"], camera=cam, bilateral=True, device=device, reference_depth=5.0)
    assert c["cut_edges"] == 0 and c["n_pieces"] == 1
    if device == "cpu":
        assert np.array_equal(r.depth, r0.depth) and r.iterations == r0.iterations and r.energy == r0.energy
    else:
        m = r0.mask
        assert np.abs(r.depth - r0.depth)[m].max() <= 1e-5 * np.ptp(r0.depth[m])


def test_stitch_leaves_pieces_without_cut_edges_exactly():
    # two mask components, creases only in the left one: the stitch gives the right one the constant 0.0
    sc = render_scene("steps", 24, "orthographic")
    sb = render_surface("bump", 24, "orthographic")
    n = np.concatenate([sc["normals"], np.zeros((24, 1, 3)), sb["normals"]], axis=1)
    m = np.concatenate([sc["mask"], np.zeros((24, 1), bool), sb["mask"]], axis=1)
    lab = np.concatenate([sc["labels"] + 1, np.zeros((24, 25), int)], axis=1)  # the steps' surfaces 1..4
    cut_x = np.zeros(m.shape, bool)
    cut_y = np.zeros(m.shape, bool)
    cut_x[:, :-1] = m[:, :-1] & m[:, 1:] & (lab[:, :-1] != lab[:, 1:])
    cut_y[:-1] = m[:-1] & m[1:] & (lab[:-1] != lab[1:])
    assert cut_x.sum() + cut_y.sum() > 0
    rng = np.random.default_rng(0)
    u = np.where(m, rng.normal(size=m.shape), 0.0)
    us, labels, npc = stitch_cut_pieces(u, n, m, Orthographic(sc["pixel_size"]), cut_x, cut_y)
    assert npc == 5 and np.array_equal(us[:, 25:], u[:, 25:])
    assert not np.array_equal(us[:, :24], u[:, :24])
    # each group of stitched pieces keeps its mean
    assert us[:, :24][m[:, :24]].mean() == pytest.approx(u[:, :24][m[:, :24]].mean(), abs=1e-12)


def test_bini_cut_bad_input(device):
    sc = render_scene("steps", 16, "orthographic")
    cam = _camera(sc)
    n, m = sc["normals"], sc["mask"]
    with pytest.raises(ValueError, match="threshold_deg"):
        integrate_normals_creases(n, m, camera=cam, threshold_deg=0.0, device=device)
    with pytest.raises(ValueError, match="normals"):
        integrate_normals_creases(n[..., :2], m, camera=cam, device=device)
    with pytest.raises(ValueError, match="cuts"):
        Integrator(m, cam, IntegratorConfig(bilateral=True), device=device).run(n, cuts=(m, m[:-1]))


# ----------------------------------------------------------------------------- slits dropped, BiNI-criterion stitch


def _true_cuts(labels, mask):
    cut_x = np.zeros(mask.shape, bool)
    cut_y = np.zeros(mask.shape, bool)
    cut_x[:, :-1] = mask[:, :-1] & mask[:, 1:] & (labels[:, :-1] != labels[:, 1:])
    cut_y[:-1] = mask[:-1] & mask[1:] & (labels[:-1] != labels[1:])
    return cut_x, cut_y


def test_separating_cuts_drop_exactly_the_slits():
    # the staircase's true surface boundaries separate 4 pieces; add slits (a cut line ending inside a tread, and
    # single cut edges inside the back plane) and cuts leaving the mask: only the separating ones survive, and
    # the pieces' labels are those of the full cut
    sc = render_scene("steps", 32, "orthographic")
    m = sc["mask"].copy()
    m[:, -3:] = False
    cut_x, cut_y = _true_cuts(sc["labels"], m)
    sep_x, sep_y = cut_x.copy(), cut_y.copy()
    slit_x = np.zeros_like(cut_x)
    slit_x[10:16, 20] = True  # a line of cut j-edges inside one surface, open at both ends
    slit_x[2, 2] = True
    slit_y = np.zeros_like(cut_y)
    slit_y[3, 5] = True
    slit_x &= ~cut_x
    slit_y &= ~cut_y
    out_x = np.zeros_like(cut_x)
    out_x[:, -3] = True  # edges leaving the mask: not edges at all
    ax, ay = cut_x | slit_x | out_x, cut_y | slit_y
    kx, ky, labels, npc = separating_cuts(m, ax, ay)
    assert np.array_equal(kx, sep_x) and np.array_equal(ky, sep_y)
    full, nfull = crease_pieces(m, _edges(m)[0] & ~ax, _edges(m)[1] & ~ay)
    assert npc == nfull == 4 and np.array_equal(labels, full)
    # nothing left to drop: a second pass is the identity
    kx2, ky2, labels2, _ = separating_cuts(m, kx, ky)
    assert np.array_equal(kx2, kx) and np.array_equal(ky2, ky) and np.array_equal(labels2, labels)


def test_slits_dropped_when_nothing_separates_is_bini_bitwise(device):
    # the box's detected creases leak at its corners: one piece, every cut a slit; dropping them gives BiNI
    # (bitwise on the CPU; on CUDA to rounding, as test_bini_cut_without_creases_is_bini_bitwise)
    sc = render_box(48, "orthographic")  # (at 40 px three pieces separate)
    cam = _camera(sc)
    r, c = integrate_normals_creases(sc["normals"], sc["mask"], camera=cam, device=device, slits="drop")
    r0 = integrate_normals(sc["normals"], sc["mask"], camera=cam, bilateral=True, device=device)
    assert c["n_pieces"] == 1 and c["cut_edges"] == 0 and c["slits"] > 0
    if device == "cpu":
        assert np.array_equal(r.depth, r0.depth)
    else:
        m = r0.mask
        assert np.abs(r.depth - r0.depth)[m].max() <= 1e-5 * np.ptp(r0.depth[m])


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_bini_stitch_planar_staircase_exact_per_piece(camera):
    # exact plane shapes with random constants per piece: the stitch only moves whole pieces, so each piece is
    # still exact to rounding after its own alignment, whatever constants the criterion picks
    sc = render_scene("steps", 32, camera)
    persp = camera == "perspective"
    m = sc["mask"]
    cut_x, cut_y = _true_cuts(sc["labels"], m)
    kx, ky, labels, npc = separating_cuts(m, cut_x, cut_y)
    g = np.log(sc["depth"]) if persp else sc["depth"]
    u = g + np.random.default_rng(1).normal(size=npc + 1)[labels]
    gj, gi, nzj, nzi = pixel_gradients(sc["normals"], m, _camera(sc), 1e-3)
    us, c, info = stitch_bini(u, labels, npc, kx, ky, m, gj, gi, nzj, nzi)
    assert info["iterations"] >= 2 and len(info["energy"]) == info["iterations"]
    d = np.exp(us) if persp else us
    pieces, rng = surface_errors(d, sc["depth"], sc["labels"], m, persp)
    assert max(p["max"] for p in pieces) <= 1e-12 * rng * (1e3 if persp else 1)
    # the constants keep each connected group's pixel mean
    assert us[m].mean() == pytest.approx(u[m].mean(), abs=1e-12)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_bini_stitch_continuous_on_the_ridge(camera, device):
    # the fold's two planes from random constants: BiNI's criterion stitches them back continuous, as well as
    # the mid-normal stitch (both limited by the fold's unknown sub-pixel position), far from the random start
    size = 40
    sc = render_surface("ridge", size, camera)
    persp = camera == "perspective"
    r, c = integrate_normals_creases(sc["normals"], sc["mask"], camera=_camera(sc), device=device,
                                     cut_stitch="bini", bilateral_inner_tol=1e-10)
    rm, _ = integrate_normals_creases(sc["normals"], sc["mask"], camera=_camera(sc), device=device,
                                      bilateral_inner_tol=1e-10)
    assert c["n_pieces"] == 2 and c["cut_edges"] == size
    mean, _ = global_error(r.depth.astype(np.float64), sc["depth"], sc["mask"], persp)
    ref, _ = global_error(rm.depth.astype(np.float64), sc["depth"], sc["mask"], persp)
    assert mean <= 1.2 * ref + 1e-6 and mean < 1e-2
    # no step across the fold beyond the sub-pixel ambiguity (0.35 of the slope change per pixel)
    u = np.log(r.depth.astype(np.float64)) if persp else r.depth.astype(np.float64)
    gt = np.log(sc["depth"]) if persp else sc["depth"]
    ii, jj = np.nonzero(c["cut_x"])
    est = u[ii, jj + 1] - u[ii, jj]
    tru = gt[ii, jj + 1] - gt[ii, jj]
    slope_change = np.abs((gt[ii, jj + 2] - gt[ii, jj + 1]) - (gt[ii, jj] - gt[ii, jj - 1]))
    assert np.all(np.abs(est - tru) <= 0.35 * slope_change + 1e-5 * np.ptp(gt))


def test_slits_and_stitch_bad_input():
    sc = render_scene("steps", 16, "orthographic")
    cam = _camera(sc)
    n, m = sc["normals"], sc["mask"]
    with pytest.raises(ValueError, match="slits"):
        integrate_normals_creases(n, m, camera=cam, slits="some", device="cpu")
    with pytest.raises(ValueError, match="cut_stitch"):
        integrate_normals_creases(n, m, camera=cam, cut_stitch="continuity", device="cpu")
    with pytest.raises(ValueError, match="mode"):
        stitch_cut_pieces(np.zeros(m.shape), n, m, cam, m, m, mode="trapezoid")
    with pytest.raises(ValueError, match="valid"):
        separating_cuts(m.astype(int), m, m)
    with pytest.raises(ValueError, match="cut_y"):
        separating_cuts(m, m, m[:-1])
    with pytest.raises(ValueError, match="cut_x"):
        separating_cuts(m, m.astype(float), m)
