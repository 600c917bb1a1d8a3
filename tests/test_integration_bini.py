"""Bilateral normal integration (BiNI) on the device: reference, ground truth with discontinuities, real data.

The reference here is BiNI written from the paper's matrix form (Cao et al.,
ECCV 2022, eqs. (19)-(20)) in scipy: four sparse one-sided difference
operators scaled by each pixel's own ``N`` (missing neighbours give empty rows),
the IRLS weights ``sigmoid(k ((A_- u)^2 - (A_+ u)^2))``, the normal equations
``A^T W A u = A^T W b`` solved by Jacobi-preconditioned CG to relative residual
1e-3 warm-started, and the stopping rule on the relative energy change.  It
shares nothing with the device code but :func:`bini_coefficients`, whose
equations are checked on their own against exact planes.
"""

import numpy as np
import pytest
import scipy.sparse as sp

from discontinuity_scenes import SCENES, render_scene, surface_errors
from gpps.camera import Orthographic, Perspective
from gpps.flows.integrate import Integrator, IntegratorConfig, integrate_normals
from gpps.pipeline.integration_bini import BilateralIntegrator, BiniConfig, bini_coefficients


def _camera(sc):
    return Perspective(sc["K"]) if "K" in sc else Orthographic(sc["pixel_size"])


# ----------------------------------------------------------------------------- numpy reference (the paper's form)


def _ops(valid, N_j, N_i, cuts=None):
    """Sparse (n x n) ops ``A_right, A_left, A_down, A_up``: row p = N_p (u_q - u_p) or N_p (u_p - u_q); a neighbour
    across a cut edge (``cuts = (cut_x, cut_y)``, the edges (i, j)-(i, j+1) and (i, j)-(i+1, j)) is missing."""
    h, w = valid.shape
    cut_x, cut_y = cuts if cuts is not None else (np.zeros((h, w), bool), np.zeros((h, w), bool))
    idx = -np.ones((h, w), int)
    idx[valid] = np.arange(valid.sum())
    ii, jj = np.nonzero(valid)
    n = ii.size
    ops = []
    for di, dj, Nf, sign in ((0, 1, N_j, 1), (0, -1, N_j, -1), (1, 0, N_i, 1), (-1, 0, N_i, -1)):
        qi, qj = ii + di, jj + dj
        ok = (qi >= 0) & (qi < h) & (qj >= 0) & (qj < w)
        ok[ok] = valid[qi[ok], qj[ok]]
        # the edge's owner: its upper / left pixel
        ei, ej = np.minimum(ii, qi), np.minimum(jj, qj)
        ok[ok] = ~(cut_x if di == 0 else cut_y)[ei[ok], ej[ok]]
        rows = np.nonzero(ok)[0]
        q = idx[qi[ok], qj[ok]]
        c = Nf[ii[ok], jj[ok]] * sign
        A = sp.csr_matrix((np.concatenate([c, -c]), (np.concatenate([rows, rows]), np.concatenate([q, rows]))),
                          shape=(n, n))
        ops.append(A)
    return ops


def _jacobi_pcg(A, b, x, tol, maxit=5000):
    d = 1.0 / np.clip(A.diagonal(), 1e-5, None)
    r = b - A @ x
    z = d * r
    p = z.copy()
    rz = r @ z
    bb = b @ b
    its = 0
    for _ in range(maxit):
        q = A @ p
        pq = p @ q
        if pq == 0:
            break
        a = rz / pq
        x = x + a * p
        r = r - a * q
        its += 1
        if r @ r <= tol * tol * bb:
            break
        z = d * r
        rzn = r @ z
        p = z + rzn / rz * p
        rz = rzn
    return x, its


def bini_reference(normals, valid, camera, k=2.0, max_iter=150, tol=1e-4, cg_tol=1e-3, cuts=None):
    Nj, Ni, mj, mi = bini_coefficients(normals, valid, camera)
    A1, A2, A3, A4 = _ops(valid, Nj, Ni, cuts)
    m1, m2 = mj[valid], mi[valid]
    b = np.concatenate([m1, m1, m2, m2])
    A = sp.vstack([A1, A2, A3, A4]).tocsr()
    n = A1.shape[0]
    w = np.full(4 * n, 0.5)
    u = np.zeros(n)
    e_old = float(np.sum(w * b * b))
    its = 0
    for it in range(max_iter):
        W = sp.diags(w)
        u, k_its = _jacobi_pcg((A.T @ W @ A).tocsr(), A.T @ (w * b), u, cg_tol)
        its += k_its
        a1, a2, a3, a4 = A1 @ u, A2 @ u, A3 @ u, A4 @ u
        wj = 1 / (1 + np.exp(-k * (a2 ** 2 - a1 ** 2)))
        wi = 1 / (1 + np.exp(-k * (a4 ** 2 - a3 ** 2)))
        w = np.concatenate([wj, 1 - wj, wi, 1 - wi])
        r = A @ u - b
        e = float(np.sum(w * r * r))
        if abs(e - e_old) / e_old < tol:
            break
        e_old = e
    out = np.zeros(valid.shape)
    out[valid] = u
    return out, it + 1, its


# ----------------------------------------------------------------------------- tests


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_coefficients_are_the_surface_derivatives(camera):
    # N du/dj = m_j and N du/di = m_i for u = depth (orthographic) or log-depth (perspective), checked on a
    # tilted plane: exactly by one-sided differences (orthographic: u is linear), to second order by central
    # differences (perspective: log of 1 / a linear function)
    sc = render_scene("steps", 40, camera)
    cam = _camera(sc)
    valid = sc["labels"] == 0
    Nj, Ni, mj, mi = bini_coefficients(sc["normals"], valid, cam)
    assert np.all(Nj[valid] > 0) and np.all(Ni[valid] > 0)
    scale = np.abs(mj[valid]).max() + np.abs(mi[valid]).max()
    if not cam.is_perspective:
        u = sc["depth"]
        ej = valid[:, 1:] & valid[:, :-1]
        ei = valid[1:] & valid[:-1]
        for N, m, D, e in ((Nj[:, :-1], mj[:, :-1], u[:, 1:] - u[:, :-1], ej),
                           (Nj[:, 1:], mj[:, 1:], u[:, 1:] - u[:, :-1], ej),
                           (Ni[:-1], mi[:-1], u[1:] - u[:-1], ei), (Ni[1:], mi[1:], u[1:] - u[:-1], ei)):
            assert np.abs(N * D - m)[e].max() <= 1e-10 * scale
    else:
        u = np.log(sc["depth"])
        c = valid[1:-1, 1:-1] & valid[1:-1, 2:] & valid[1:-1, :-2] & valid[2:, 1:-1] & valid[:-2, 1:-1]
        dj = (u[1:-1, 2:] - u[1:-1, :-2]) / 2
        di = (u[2:, 1:-1] - u[:-2, 1:-1]) / 2
        assert np.abs(Nj[1:-1, 1:-1] * dj - mj[1:-1, 1:-1])[c].max() <= 1e-5 * scale
        assert np.abs(Ni[1:-1, 1:-1] * di - mi[1:-1, 1:-1])[c].max() <= 1e-5 * scale


@pytest.mark.parametrize("launch", ["tasks", "persistent"])
@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
@pytest.mark.parametrize("name", ["figure", "overlap"])
def test_device_bini_follows_the_reference_trajectory(name, camera, launch, device):
    # the same IRLS iterations, CG iterations and solution as the scipy form of the paper, with either launch
    # (the persistent one runs as one thread off CUDA: its arithmetic in order)
    sc = render_scene(name, 32, camera)
    cam = _camera(sc)
    ref, outer, its = bini_reference(sc["normals"], sc["mask"], cam)
    with BilateralIntegrator(sc["mask"], cam, BiniConfig(launch=launch), device=device) as bi:
        res = bi.run(sc["normals"])
    assert res.converged and res.outer_iterations == outer and res.cg_iterations == its
    u = res.u - res.u[sc["mask"]].mean()
    r = ref - ref[sc["mask"]].mean()
    assert np.abs(u - r)[sc["mask"]].max() <= 1e-8 * np.ptp(r[sc["mask"]])
    assert len(res.energy) == outer and res.energy[-1] < res.energy[0]
    assert 0 < res.residual <= 1e-3


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
@pytest.mark.parametrize("name", SCENES)
def test_discontinuity_suite(name, camera, device):
    """BiNI against plain Poisson on ray-cast scenes with depth discontinuities (48 px; perf/integration_bini.py
    runs them larger and prints the table).  Each 4-connected piece of each surface is aligned by its own
    offset (orthographic) or scale (perspective); the error is the worst piece's mean |error| / the scene's
    depth range.  Occluding-rim discontinuities (the figure, overlapping spheres) are cut: BiNI is 2-4x better
    than Poisson there.  Where a jump leaves no trace in the normals (a planar tread's sharp edge, a gap
    between slabs) BiNI's weights cannot see it and both smear alike.  Neither reaches the issue's 1e-3 of the
    range: measured when written (48 px, CPU, orthographic / perspective) BiNI vs Poisson: steps 6.2e-2 /
    6.5e-2 vs 6.3e-2 / 6.8e-2, overlap 7.0e-3 / 1.1e-2 vs 1.3e-2 / 4.7e-2, figure 7.8e-3 / 1.4e-2 vs 2.6e-2 /
    5.7e-2, gaps 4.8e-2 / 5.6e-2 vs 4.9e-2 / 5.5e-2, rims 8.5e-2 / 3.9e-2 vs 9.3e-2 / 7.5e-2 (at 128 px the
    orthographic rims scene is worse with BiNI than with Poisson: 1.23e-1 vs 9.4e-2, BiNI's reference code alike;
    perf/results/integration_bini_cpu.json)."""
    sc = render_scene(name, 48, camera)
    cam = _camera(sc)
    persp = cam.is_perspective
    out = {}
    for mode in ("bini", "poisson"):
        r = integrate_normals(sc["normals"], sc["mask"], camera=cam, bilateral=mode == "bini", device=device)
        assert r.n_invalid == 0 and np.all(np.isfinite(r.depth))
        rows, rng = surface_errors(r.depth, sc["depth"], sc["labels"], r.mask, persp)
        out[mode] = max(x["mean"] for x in rows) / rng
    assert out["bini"] <= 1.1 * out["poisson"], out
    if name in ("figure", "overlap"):
        assert out["bini"] <= 0.6 * out["poisson"], out
    if name == "rims":
        assert out["bini"] <= 0.95 * out["poisson"], out


def _crease_cuts(sc):
    """The cuts of a scene: every edge between two different surfaces, and the edges of one column of surface 0."""
    lab = sc["labels"]
    cut_x = np.zeros(lab.shape, bool)
    cut_y = np.zeros(lab.shape, bool)
    cut_x[:, :-1] = lab[:, :-1] != lab[:, 1:]
    cut_y[:-1] = lab[:-1] != lab[1:]
    j0 = lab.shape[1] // 2
    cut_x[:, j0] |= lab[:, j0] == 0
    return cut_x & sc["mask"], cut_y & sc["mask"]


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_cut_edges_follow_the_reference_trajectory(camera, device):
    # a cut edge is a missing neighbour on both sides: the scipy form with those rows removed takes the same IRLS
    # and CG iterations to the same solution
    sc = render_scene("overlap", 32, camera)
    cam = _camera(sc)
    cuts = _crease_cuts(sc)
    assert cuts[0].any() and cuts[1].any()
    ref, outer, its = bini_reference(sc["normals"], sc["mask"], cam, cuts=cuts)
    with BilateralIntegrator(sc["mask"], cam, device=device, cuts=cuts) as bi:
        res = bi.run(sc["normals"])
    assert res.outer_iterations == outer and res.cg_iterations == its
    ref0, _, _ = bini_reference(sc["normals"], sc["mask"], cam)
    assert np.abs(ref - ref0)[sc["mask"]].max() > 1e-3 * np.ptp(ref0[sc["mask"]])  # the cuts change the solve
    # each cut-free piece has its own constant (the CG's start 0 and its search directions set it): compare
    # whole solutions, they are the same trajectory
    assert np.abs(res.u - ref)[sc["mask"]].max() <= 1e-8 * np.ptp(ref[sc["mask"]])


def test_no_cut_is_bitwise_uncut_and_the_table_does_not_leak(device):
    """Bitwise on the CPU, to rounding on CUDA (see ``same``)."""
    sc = render_scene("figure", 24, "orthographic")
    cam = _camera(sc)
    m = sc["mask"]
    with BilateralIntegrator(m, cam, device=device) as a:
        ra = a.run(sc["normals"])
        fa = a._F
    # nothing cut, or only edges that leave the image or the mask (already missing neighbours): bitwise the same
    none = np.zeros(m.shape, bool)
    outside_x = none.copy()
    outside_x[:, -1] = True
    outside_x[:, :-1] |= ~(m[:, :-1] & m[:, 1:])
    outside_y = none.copy()
    outside_y[-1] = True
    outside_y[:-1] |= ~(m[:-1] & m[1:])
    def same(rb, ra):
        # bitwise on the CPU; on CUDA the float64 block sums end in atomics whose order varies run to run
        if device == "cpu":
            return np.array_equal(rb.u, ra.u) and rb.cg_iterations == ra.cg_iterations and rb.energy == ra.energy
        return np.abs(rb.u - ra.u)[m].max() <= 1e-5 * np.ptp(ra.u[m])

    for cuts in ((none, none), [outside_x, outside_y]):
        with BilateralIntegrator(m, cam, device=device, cuts=cuts) as b:
            rb = b.run(sc["normals"])
        assert same(rb, ra)
    # a cut integrator takes the pooled buffers; the next uncut one on them rebuilds its neighbour table
    with BilateralIntegrator(m, cam, device=device, cuts=_crease_cuts(sc)) as c:
        rc = c.run(sc["normals"])
        assert c._F is fa
    assert not np.array_equal(rc.u, ra.u)
    with BilateralIntegrator(m, cam, device=device) as d:
        rd = d.run(sc["normals"])
        assert d._F is fa
    assert same(rd, ra)


def test_bad_cuts(device):
    sc = render_scene("figure", 16, "orthographic")
    m = sc["mask"]
    z = np.zeros(m.shape, bool)
    for bad in (z, (z,), (z, z, z), (z, z.astype(int)), (z, z[:, :-1]), (z[None], z), "cuts"):
        with pytest.raises(ValueError, match="cuts"):
            BilateralIntegrator(m, _camera(sc), cuts=bad)
    with pytest.raises(ValueError, match="cuts"):
        Integrator(m, _camera(sc), IntegratorConfig(solver="direct"), device=device).run(sc["normals"], cuts=(z, z))


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_persistent_launch_is_the_tasks_launch(camera, device):
    # the whole IRLS iteration in one task (grid barriers between its phases) against the tasks launch, on a
    # larger map than the reference test (several blocks' worth of pixels a thread on CUDA), with a cap on the
    # CG iterations that ends some inner solves early: the same iteration counts, energies and solution
    # (to rounding: the tasks launch's system kernel sums in its own order; on CUDA both end in atomics)
    sc = render_scene("overlap", 96, camera)
    cam = _camera(sc)
    got = {}
    for launch in ("tasks", "persistent"):
        with BilateralIntegrator(sc["mask"], cam, BiniConfig(launch=launch, cg_max_iter=40, max_iter=12),
                                 device=device) as bi:
            got[launch] = bi.run(sc["normals"])
    a, b = got["tasks"], got["persistent"]
    assert a.outer_iterations == b.outer_iterations == 12 and a.cg_iterations == b.cg_iterations
    assert a.cg_iterations == 12 * 40  # every inner solve stopped by the cap
    rng = np.ptp(a.u[sc["mask"]])
    tol = 1e-12 if device == "cpu" else 1e-9
    assert np.abs(a.u - b.u)[sc["mask"]].max() <= tol * rng
    assert np.allclose(a.energy, b.energy, rtol=tol, atol=0) and abs(a.residual - b.residual) <= tol + 1e-12
    assert np.abs(a.wj - b.wj).max() <= tol * 1e3 and np.abs(a.wi - b.wi).max() <= tol * 1e3


def test_config_pool_and_progress(device):
    sc = render_scene("figure", 24, "orthographic")
    cam = _camera(sc)
    calls = []
    with BilateralIntegrator(sc["mask"], cam, device=device) as a:
        ra = a.run(sc["normals"], progress=lambda d, t, msg: calls.append((d, t)))
        fa = a._F
    assert [d for d, _ in calls] == list(range(1, ra.outer_iterations + 1)) and calls[0][1] == 150
    with BilateralIntegrator(sc["mask"] & (np.arange(24) > 2)[:, None], cam, device=device) as b:
        b.run(sc["normals"])
        assert b._F is fa  # the buffers (and compiled kernels) of the same size class are reused
    for kw in (dict(k=0), dict(tol=1.0), dict(cg_tol=0), dict(max_iter=0), dict(cg_max_iter=1.5), dict(k=True),
               dict(launch="graph"), dict(launch=None), dict(blocks_per_sm=0)):
        with pytest.raises(ValueError, match=next(iter(kw))):
            BiniConfig(**kw)
    with pytest.raises(TypeError, match="blocks_per_sm"):
        BiniConfig(blocks_per_sm=2.5)
    with pytest.raises(ValueError, match="robust"):
        IntegratorConfig(bilateral=True, robust="curl")
    with pytest.raises(ValueError, match="bilateral_cg_max_iter"):
        IntegratorConfig(bilateral_cg_max_iter=0)


def test_integrate_normals_bilateral_result(device):
    sc = render_scene("figure", 32, "perspective")
    cam = _camera(sc)
    r = integrate_normals(sc["normals"], sc["mask"], camera=cam, bilateral=True, reference_depth=10.0, device=device)
    assert r.solver == "bini" and r.converged and r.outer_iterations == len(r.energy) >= 2
    assert abs(r.depth[r.mask].mean() - 10.0) < 1e-3 and r.iterations > 0 and r.residual <= 1e-3


# BiNI's published mean absolute depth errors (mm) on the true DiLiGenT normal maps
BINI_MM = {"bear": 0.334, "buddha": 1.098, "cow": 0.058, "goblet": 9.018, "pot1": 0.635, "pot2": 0.220}


@pytest.mark.parametrize("name", sorted(BINI_MM))
def test_diligent_default_mode_within_1p1x_of_bini(name, data_root, device):
    """The issue's line: the default mode (bilateral) within 1.1x of BiNI's published error on each shared map
    (BiNI's protocol: scale median(gt / est), mean |error| over mask & finite depth_gt).  Measured when
    written (CPU): bear 0.3339, buddha 1.0971, cow 0.0578, goblet 9.0177, pot1 0.6355, pot2 0.2198 mm,
    BiNI's own numbers to the printed digit."""
    import cv2

    folder = data_root / "integration" / "diligent" / name
    raw = cv2.imread(str(folder / "normal_map.png"), cv2.IMREAD_UNCHANGED)
    n = raw[..., ::-1].astype(np.float64) / 65535.0 * 2.0 - 1.0
    mask = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    gt = np.load(folder / "depth_gt.npz")["depth_gt"].astype(np.float64)
    res = integrate_normals(n, mask, camera=Perspective(np.loadtxt(folder / "K.txt")), bilateral=True, device=device)
    ev = res.mask & np.isfinite(gt)
    d, g = res.depth.astype(np.float64)[ev], gt[ev]
    made = float(np.mean(np.abs(np.median(g / d) * d - g)))
    assert res.converged and made <= 1.1 * BINI_MM[name], (made, BINI_MM[name])
    assert made == pytest.approx(BINI_MM[name], rel=0.01)


@pytest.mark.parametrize("camera", ["orthographic", "perspective"])
def test_coefficients_at_pixels_are_the_full_frame_ones(camera):
    # the stage uploads bini_coefficients_at (the mask's pixels only): the same values as the full-frame form
    from gpps.pipeline.integration_bini import bini_coefficients_at

    sc = render_scene("overlap", 40, camera)
    cam = _camera(sc)
    m = sc["mask"]
    ii, jj = np.nonzero(m)
    full = bini_coefficients(sc["normals"], m, cam)
    at = bini_coefficients_at(sc["normals"], ii, jj, cam, m.shape)
    for f, a in zip(full, at):
        assert a.shape == (ii.size,) and np.array_equal(f[ii, jj], a) and not f[~m].any()


def test_pooled_buffers_carry_nothing_from_a_larger_map(device):
    # two maps of one size class share the pooled buffers: a larger map run in between leaves values past the
    # smaller one's pixel count, which the one-launch uploads must reset (bitwise on the CPU, rounding on CUDA)
    small = render_scene("figure", 24, "perspective")
    large = render_scene("overlap", 32, "perspective")
    assert small["mask"].sum() < large["mask"].sum() <= 1024  # (one size class: 1024 entries)
    runs = []
    for sc in (small, large, small):
        with BilateralIntegrator(sc["mask"], _camera(sc), device=device) as bi:
            runs.append((bi.run(sc["normals"]), bi._F))
    (a, fa), (_, fb), (c, fc) = runs
    assert fa is fb is fc
    m = small["mask"]
    if device == "cpu":
        assert np.array_equal(a.u, c.u) and a.energy == c.energy and a.cg_iterations == c.cg_iterations
    else:
        assert np.abs(a.u - c.u)[m].max() <= 1e-5 * np.ptp(a.u[m])
