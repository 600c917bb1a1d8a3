"""MaterialScorer (gpps/pipeline/material.py): K candidate materials x P resident sample pixels per launch.

Reference: RON's material energy as ``RON._fit_energy`` computed it at f93cc14: ``PixelSolver.run`` on the
whole frame with the sample mask and RON's fit config (``starts=material_starts, neighbour_radius=0,
smoothness=0, warm_start=False``), the sample pixels' squared residuals sorted in float64 and trimmed by
``material_trim``.  The reference is written out here (not called through RON) so that it stays the
independent check when RON itself moves to the scorer.

Tolerance.  The scorer runs the same ``@wp.func`` solve code (gpps.kernels.solve_methods) on the same
float32 inputs (observations, weights, noise levels, start normal and pixel point computed by the same
functions); only the enclosing kernel and Warp module differ.  On the CPU backend the residuals come out
bitwise equal (observed: max |diff| = 0).  A compiler may still inline or contract (FMA) differently in
another module: a last-bit change of the iterate, which at a converged minimum moves the cost only to second
order and otherwise shifts where ``tol_step`` (1e-6 rad) stops the iteration.  The bound used,
``|dE| <= 1e-5 E + (1e-6 s)^2`` (``s``: the 99th percentile grey value, so ``1e-6 s`` is a few float32 ulps
of an observation), covers that; near-exact fits (3 images, E ~ 1e-15 s^2) fall under the absolute term.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cases import make_case

from gpps.flows.synthetic import default_lights, render
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights, PointLights
from gpps.material import Material
from gpps.pipeline.material import MaterialScorer, trimmed_energy
from gpps.pipeline.solver import PixelSolver, SolverConfig

TRIM = 0.02
STARTS = 4


def fit_config(**kw) -> SolverConfig:
    """RON's material-fit config: the default solver settings with RON's overrides."""
    return replace(SolverConfig(**kw), starts=STARTS, neighbour_radius=0, smoothness=0.0, warm_start=False)


def sample_mask(mask, n, seed=0, block=False):
    """``n`` random mask pixels (and, with ``block``, a dense 8x8 patch, so the noise estimate sees pixels)."""
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(mask.ravel())
    s = np.zeros(mask.size, bool)
    s[rng.choice(idx, min(n, idx.size), replace=False)] = True
    s = s.reshape(mask.shape)
    if block:
        ci, cj = (int(np.mean(a)) for a in np.nonzero(mask))
        s[ci - 4 : ci + 4, cj - 4 : cj + 4] = True
    return s & mask


def candidates_around(mat: Material) -> list[Material]:
    """The true material and four others: ks and the lobe width moved by factors 0.25-4."""
    lobe = {"blinn-phong": "shininess", "phong": "shininess", "cook-torrance": "roughness", "plastic": "roughness"}[mat.brdf]
    out = [mat]
    for fk, fl in ((0.25, 1.0), (1.0, 2.0), (2.0, 0.5), (0.5, 1.6)):
        d = mat.to_dict()
        d["ks"] = mat.ks * fk
        d[lobe] = getattr(mat, lobe) * fl
        out.append(Material.from_dict(d))
    return out


def reference(images, sample, camera, lights, cands, config, *, depth, valid, device):
    """RON's ``_fit_energy`` for each candidate, and the residuals / normals at the sample (row-major)."""
    solver = PixelSolver(images.shape[:3], camera, lights, cands[0], config, device=device)
    energies, residuals, normals = [], [], []
    for m in cands:
        solver.set_material(m)
        out = solver.run(images, sample, depth=depth, valid=valid)
        r = np.sort(out["residual"][sample].astype(np.float64) ** 2)
        keep = max(1, int(round(r.size * (1.0 - TRIM))))
        energies.append(float(np.mean(r[:keep])))
        residuals.append(out["residual"][sample])
        normals.append(out["normals"][sample])
    return np.array(energies), np.array(residuals), np.array(normals)


def scale_of(images, mask) -> float:
    g = np.asarray(images, np.float64)[:, mask]
    if g.ndim == 3:
        g = g.mean(-1)
    return float(np.percentile(g, 99.0))


def assert_energies_equal(e, ref, s):
    tol = 1e-5 * ref + (1e-6 * s) ** 2
    assert e.shape == ref.shape
    assert np.all(np.abs(e - ref) <= tol), (e, ref, np.abs(e - ref) / np.maximum(ref, 1e-300))


def score(images, sample, camera, lights, cands, config, *, depth=None, valid=None, device, **kw):
    with MaterialScorer(images.shape[:3], camera, lights, cands[0].brdf, config, max_samples=int(sample.sum()) + 7,
                        max_candidates=8, trim=TRIM, device=device) as sc:
        sc.upload(images, sample, depth=depth, valid=valid)
        sc.step(cands, **kw)
        return sc.fetch(), sc.fetch_pixels(), (sc.rows_host, sc.cols_host)


CASES_3 = [
    ("blinn-phong", "directional", "perspective"),
    ("blinn-phong", "point", "orthographic"),
    ("cook-torrance", "directional", "orthographic"),
    ("cook-torrance", "point", "perspective"),
    ("plastic", "directional", "perspective"),
]


@pytest.mark.parametrize("brdf,light_kind,camera", CASES_3)
def test_energies_equal_pixel_solver_three_images(brdf, light_kind, camera, device):
    """make_case scenes (3 images): energies, residuals and normals equal PixelSolver's on the sample mask."""
    img, lights, sc, mat = make_case("sphere", 32, camera, light_kind, brdf, device=device)
    sample = sample_mask(sc.mask, 150, seed=1)
    depth = sc.depth if light_kind == "point" else None
    cands = candidates_around(mat)
    cfg = fit_config()
    ref, ref_r, ref_n = reference(img, sample, sc.camera, lights, cands, cfg, depth=depth, valid=None, device=device)
    e, px, (rows, cols) = score(img, sample, sc.camera, lights, cands, cfg, depth=depth, device=device)
    s = scale_of(img, sc.mask)
    assert_energies_equal(e, ref, s)
    np.testing.assert_array_equal(rows * sc.mask.shape[1] + cols, np.flatnonzero(sample.ravel()))
    assert np.abs(px["residual"] - ref_r).max() <= 1e-5 * s
    assert px["normals"].shape == ref_n.shape == (len(cands), int(sample.sum()), 3)


def _many_lights_case(brdf, light_kind, n, size=32, noise=0.01, device=None):
    """Like tests/cases.make_case with ``n`` lights (spiral layout) and 16-bit noisy images."""
    sc = make_scene("sphere", size, "perspective", albedo="texture")
    mat = Material.default_for(brdf)
    L = default_lights(light_kind, n, layout="spiral")
    img = render(sc, mat, L, bits=16, noise=noise, device=device)
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    Lu = DirectionalLights(L.directions) if light_kind == "directional" else PointLights(L.positions)
    return img, Lu, sc, mat


@pytest.mark.parametrize("brdf,light_kind", [("blinn-phong", "directional"), ("cook-torrance", "point"), ("plastic", "point")])
def test_energies_equal_pixel_solver_eight_noisy_images(brdf, light_kind, device):
    """8 images with noise, textured albedo, a dense patch in the sample (non-zero noise estimate), a
    ``valid`` mask and a shadow threshold: the energies still equal PixelSolver's, and identify the material."""
    img, lights, sc, mat = _many_lights_case(brdf, light_kind, 8, device=device)
    sample = sample_mask(sc.mask, 200, seed=2, block=True)
    depth = sc.depth if light_kind == "point" else None
    valid = np.random.default_rng(3).random(img.shape[:3]) > 0.1
    cands = candidates_around(mat)
    cfg = fit_config(shadow_threshold=0.02)
    ref, ref_r, ref_n = reference(img, sample, sc.camera, lights, cands, cfg, depth=depth, valid=valid, device=device)
    e, px, _ = score(img, sample, sc.camera, lights, cands, cfg, depth=depth, valid=valid, device=device)
    s = scale_of(img, sc.mask)
    assert_energies_equal(e, ref, s)
    assert np.abs(px["residual"] - ref_r).max() <= 1e-5 * s
    # angle between unit normals, 2 asin(|a - b| / 2) in float64 (arccos of a float32 cosine resolves only ~0.02 deg)
    ang = np.degrees(2.0 * np.arcsin(np.linalg.norm(px["normals"].astype(np.float64) - ref_n, axis=-1) / 2.0))
    assert np.mean(ang < 1e-2) >= 0.99
    # the test discriminates: the rendered material scores best, clearly (plastic's runner-up, twice ks at half
    # the roughness, scores 1.46x: its default highlight, peak ks s = 0.25 at normal incidence, is dimmer than
    # Cook-Torrance's 0.38 and its Fresnel rises toward grazing)
    assert int(np.argmin(ref)) == 0 and np.sort(ref)[1] > (1.4 if brdf == "plastic" else 2.0) * ref[0]


@pytest.mark.parametrize("light_kind", ["directional", "point"])
def test_upload_from_a_solver_scores_with_the_frames_noise(light_kind, device):
    """upload_from (RON's path): the sample gathered from a PixelSolver's resident frame (images, valid, depth) with
    the solver's noise levels (the whole frame's estimate) scores exactly as a host upload of the same sample given
    those levels, and equals PixelSolver.run on the sample mask with them.  The frame's estimate is not the
    sample's: a sparse sample has no 3x3 neighbourhoods to estimate from (0, unknown), so without it the scores
    would treat dim observations the solver calls unlit as lit."""
    img, lights, sc, mat = _many_lights_case("cook-torrance", light_kind, 8, device=device)
    sample = sample_mask(sc.mask, 200, seed=4)
    depth = sc.depth if light_kind == "point" else None
    valid = np.random.default_rng(5).random(img.shape[:3]) > 0.1
    cands = candidates_around(mat)
    cfg = fit_config(shadow_threshold=0.02)
    with PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=device) as frame:
        frame.upload(img, sc.mask, depth=depth, valid=valid)
        noise = frame.noise_level.copy()
        assert np.all(noise > 0)
        kw = dict(max_samples=int(sample.sum()) + 7, max_candidates=8, trim=TRIM, device=device)
        with MaterialScorer(img.shape[:3], sc.camera, lights, "cook-torrance", cfg, **kw) as a, \
                MaterialScorer(img.shape[:3], sc.camera, lights, "cook-torrance", cfg, **kw) as b:
            a.upload(img, sample, depth=depth, valid=valid)
            assert np.all(a.noise_level == 0)  # (the sample's own estimate: unknown)
            b.upload_from(frame, sample)
            np.testing.assert_array_equal(b.noise_level, noise)
            a.upload(img, sample, depth=depth, valid=valid, noise=noise)
            np.testing.assert_array_equal(b.rows_host, a.rows_host)
            for sc_ in (a, b):
                sc_.step(cands)
            np.testing.assert_array_equal(b.fetch(), a.fetch())
            for k, v in b.fetch_pixels().items():
                np.testing.assert_array_equal(v, a.fetch_pixels()[k], err_msg=k)
            e = b.fetch()
            with pytest.raises(ValueError, match=r"^solver: expected a PixelSolver for"):
                with PixelSolver((img.shape[0], 16, 16), sc.camera, lights, mat, SolverConfig(),
                                 device=device) as other:
                    b.upload_from(other, sample)
    ref = []
    with PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=device) as solver:
        for m in cands:
            solver.set_material(m)
            out = solver.run(img, sample, depth=depth, valid=valid, noise=noise)
            r = np.sort(out["residual"][sample].astype(np.float64) ** 2)
            ref.append(float(np.mean(r[: max(1, int(round(r.size * (1.0 - TRIM))))])))
    assert_energies_equal(e, np.array(ref), scale_of(img, sc.mask))


def test_robust_loss_and_chunked_progress(device):
    """Huber IRLS (per-candidate weights buffer) equals PixelSolver; a chunked step with a progress
    callback gives the same energies as one launch and reports K * P pixel solves."""
    img, lights, sc, mat = _many_lights_case("blinn-phong", "directional", 6, size=24, device=device)
    sample = sample_mask(sc.mask, 120, seed=4)
    cands = candidates_around(mat)
    cfg = fit_config(robust="huber", irls_rounds=2)
    ref, _, _ = reference(img, sample, sc.camera, lights, cands, cfg, depth=None, valid=None, device=device)
    e1, _, _ = score(img, sample, sc.camera, lights, cands, cfg, device=device)
    calls = []
    e2, _, _ = score(img, sample, sc.camera, lights, cands, cfg, device=device,
                     progress=lambda d, t, msg: calls.append((d, t)), chunks=3)
    s = scale_of(img, sc.mask)
    assert_energies_equal(e1, ref, s)
    np.testing.assert_array_equal(e1, e2)
    total = len(cands) * int(sample.sum())
    assert len(calls) == 3 and calls[-1] == (total, total)
    assert all(a[0] < b[0] for a, b in zip(calls, calls[1:]))


def test_reupload_and_steps_reuse_buffers(device):
    """Several steps of different K on one upload, then a new sample: each equals a fresh scorer."""
    img, lights, sc, mat = make_case("sphere", 24, "perspective", "directional", "blinn-phong", device=device)
    cfg = fit_config()
    cands = candidates_around(mat)
    s1, s2 = sample_mask(sc.mask, 100, seed=5), sample_mask(sc.mask, 60, seed=6)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=128, max_candidates=5,
                        device=device) as scorer:
        scorer.upload(img, s1)
        scorer.step(cands[:2])
        a = scorer.fetch()
        scorer.step(cands)
        b = scorer.fetch()
        scorer.upload(img, s2)
        scorer.step(cands[3:])
        c = scorer.fetch()
    np.testing.assert_array_equal(a, b[:2])
    ref2, _, _ = reference(img, s2, sc.camera, lights, cands[3:], cfg, depth=None, valid=None, device=device)
    assert_energies_equal(c, ref2, scale_of(img, sc.mask))


@pytest.mark.parametrize("brdf", ["blinn-phong", "cook-torrance", "ashikhmin-shirley"])
def test_lobe_candidates_equal_materials(brdf, device):
    """lobe_candidates (the search's candidates packed without a Material each): the same device rows, hence the
    same energies bit for bit, as the Materials with_lobe builds; and its checks."""
    from gpps.names import LOBE_PARAMETERS
    from gpps.pipeline.stream_material import with_lobe

    mat = Material.default_for(brdf)
    img, lights, sc, _ = make_case("sphere", 24, "perspective", "directional", brdf, device=device)
    names = LOBE_PARAMETERS[brdf]
    values = np.array([[0.3, 0.1 if brdf == "cook-torrance" else 20.0], [1.1, 0.4 if brdf == "cook-torrance" else 80.0],
                       [0.02, 0.03 if brdf == "cook-torrance" else 2.0]])
    cands = [with_lobe(mat, dict(zip(names, v))) for v in values]
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit_config(), max_samples=64, max_candidates=4,
                        device=device) as scorer:
        scorer.upload(img, sample_mask(sc.mask, 60, seed=3))
        scorer.step(cands)
        rows = scorer._mats_host[:3].copy()
        a = scorer.fetch()
        scorer.step(scorer.lobe_candidates(mat, names, values))
        np.testing.assert_array_equal(scorer._mats_host[:3], rows)
        np.testing.assert_array_equal(scorer.fetch(), a)
        with pytest.raises(ValueError, match="values: expected"):
            scorer.lobe_candidates(mat, names, values[:, :1])
        with pytest.raises(ValueError, match="max_candidates"):
            scorer.lobe_candidates(mat, names, np.repeat(values, 2, 0))
        with pytest.raises(ValueError, match=f"{names[0]} in"):
            scorer.lobe_candidates(mat, names, values * np.array([100.0, 1.0]))
        with pytest.raises(ValueError, match="names"):
            scorer.lobe_candidates(mat, ("f0",), values[:, :1])
        with pytest.raises(ValueError, match="material"):
            scorer.lobe_candidates(Material.default_for("lambertian"), (), values[:, :0])


def test_trimmed_energy():
    r = np.array([[3.0, 1.0, 2.0, 10.0], [0.5, 0.5, 0.5, 0.5]])
    np.testing.assert_allclose(trimmed_energy(r, 0.25), [(1 + 4 + 9) / 3, 0.25])
    np.testing.assert_allclose(trimmed_energy(r, 0.0), [(9 + 1 + 4 + 100) / 4, 0.25])
    assert trimmed_energy(np.array([2.0]), 0.5) == 4.0


def test_bad_input(device):
    img, lights, sc, mat = make_case("sphere", 16, "perspective", "directional", "blinn-phong", device=device)
    cfg = fit_config()
    with pytest.raises(ValueError, match="neighbour_radius"):
        MaterialScorer(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=device)
    with pytest.raises(ValueError, match="solver='none'"):
        MaterialScorer(img.shape[:3], sc.camera, lights, mat, replace(cfg, solver="none"), device=device)
    with pytest.raises(ValueError, match="brdf"):
        MaterialScorer(img.shape[:3], sc.camera, lights, "glass", cfg, device=device)
    with pytest.raises(ValueError, match="lights"):
        MaterialScorer((4,) + img.shape[1:3], sc.camera, lights, mat, cfg, device=device)
    scorer = MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=10, max_candidates=2, device=device)
    with pytest.raises(ValueError, match="upload"):
        scorer.step([mat])
    with pytest.raises(ValueError, match="max_samples"):
        scorer.upload(img, sc.mask)
    with pytest.raises(ValueError, match="images"):
        scorer.upload(img[:2], sample_mask(sc.mask, 5))
    scorer.upload(img, sample_mask(sc.mask, 5))
    with pytest.raises(ValueError, match="max_candidates"):
        scorer.step([mat, mat, mat])
    with pytest.raises(ValueError, match="'blinn-phong' materials"):
        scorer.step([Material.default_for("cook-torrance")])
    with pytest.raises(TypeError, match="candidates"):
        scorer.step([mat.to_dict()])
    with pytest.raises(ValueError, match="step first"):
        scorer.fetch()
    scorer.close()
    with pytest.raises(ValueError, match="closed"):
        scorer.upload(img, sample_mask(sc.mask, 5))


@pytest.mark.parametrize("light_kind", ["directional", "point"])
def test_warm_step_equals_pixel_solver_warm_start(light_kind, device):
    """``set_start`` + ``step(warm=True)``: each pixel solved from one given start normal equals
    PixelSolver's warm-started solve (``warm_start=True, starts=1``) from the same normals; a start
    copied on the device from a candidate of the last step equals the same start given from the host."""
    img, lights, sc, mat = _many_lights_case("cook-torrance", light_kind, 8, device=device)
    sample = sample_mask(sc.mask, 150, seed=7, block=True)
    depth = sc.depth if light_kind == "point" else None
    cands = candidates_around(mat)
    cfg = fit_config()
    # start normals: the cold solution for cands[2] (a material far from the others)
    _, _, cold_n = reference(img, sample, sc.camera, lights, [cands[2]], cfg, depth=depth, valid=None, device=device)
    init = np.zeros(sc.mask.shape + (3,), np.float32)
    init[..., 2] = 1.0
    init[sample] = cold_n[0]
    solver = PixelSolver(img.shape[:3], sc.camera, lights, cands[0], replace(cfg, warm_start=True, starts=1),
                         device=device)
    ref, ref_r = [], []
    for m in cands:
        solver.set_material(m)
        out = solver.run(img, sample, depth=depth, init_normals=init)
        r = out["residual"][sample]
        ref.append(float(trimmed_energy(r, TRIM)))
        ref_r.append(r)
    s = scale_of(img, sc.mask)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=int(sample.sum()),
                        max_candidates=len(cands), trim=TRIM, device=device) as scorer:
        scorer.upload(img, sample, depth=depth)
        with pytest.raises(ValueError, match="set_start"):
            scorer.step(cands, warm=True)
        scorer.set_start(init[sample])
        scorer.step(cands, warm=True)
        e_host = scorer.fetch()
        r_host = scorer.fetch_pixels(("residual", "iterations"))
        # from the device: candidate 2's cold normals are the same start
        scorer.step(cands)
        e_cold = scorer.fetch()
        it_cold = scorer.fetch_pixels(("iterations",))["iterations"]
        scorer.set_start(candidate=2)
        scorer.step(cands, warm=True)
        e_dev = scorer.fetch()
        with pytest.raises(ValueError, match="candidate"):
            scorer.set_start(candidate=len(cands))
        with pytest.raises(ValueError, match="exactly one"):
            scorer.set_start()
        with pytest.raises(ValueError, match="unit"):
            scorer.set_start(2.0 * init[sample])
    assert_energies_equal(e_host, np.array(ref), s)
    assert np.abs(r_host["residual"] - np.array(ref_r)).max() <= 1e-5 * s
    np.testing.assert_allclose(e_dev, e_host, rtol=1e-5, atol=(1e-6 * s) ** 2)
    # from its own cold solution, candidate 2 keeps that minimum at a fraction of the cold multi-start's cost
    assert_energies_equal(e_host[2:3], e_cold[2:3], s)
    assert r_host["iterations"][2].mean() < 0.5 * it_cold[2].mean()


def test_warm_max_iters_caps_warm_steps_only(device):
    """``warm_max_iters``: a warm step's solves stop after that many cost evaluations, as PixelSolver's warm solve
    with ``max_iters`` set so; cold steps keep ``config.max_iters``; a bad cap is refused by name."""
    img, lights, sc, mat = _many_lights_case("cook-torrance", "directional", 8, device=device)
    sample = sample_mask(sc.mask, 150, seed=7, block=True)
    cands = candidates_around(mat)
    cfg = fit_config()
    init = np.zeros(sc.mask.shape + (3,), np.float32)
    init[..., 2] = 1.0  # a start far from most pixels' normals: the solves need many evaluations
    cap = 4
    solver = PixelSolver(img.shape[:3], sc.camera, lights, cands[0],
                         replace(cfg, warm_start=True, starts=1, max_iters=cap), device=device)
    ref = []
    for m in cands:
        solver.set_material(m)
        ref.append(solver.run(img, sample, init_normals=init)["residual"][sample])
    kw = dict(max_samples=int(sample.sum()), max_candidates=len(cands), trim=TRIM, device=device)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, warm_max_iters=cap, **kw) as capped, \
            MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, **kw) as free:
        for s_ in (capped, free):
            s_.upload(img, sample)
            s_.set_start(init[sample])
            s_.step(cands, warm=True)
        got = capped.fetch_pixels(("residual", "iterations"))
        full = free.fetch_pixels(("residual", "iterations"))
        capped.step(cands)
        free.step(cands)
        cold_capped, cold_free = capped.fetch(), free.fetch()
    s = scale_of(img, sc.mask)
    assert got["iterations"].max() <= cap < full["iterations"].max()
    assert np.abs(got["residual"] - np.array(ref)).max() <= 1e-5 * s
    np.testing.assert_array_equal(cold_capped, cold_free)
    with pytest.raises(ValueError, match="warm_max_iters"):
        MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, warm_max_iters=0, **kw)


def _score_parallel(images, sample, camera, lights, cands, config, parallel, *, device, depth=None, warm=None):
    with MaterialScorer(images.shape[:3], camera, lights, cands[0].brdf, config, max_samples=int(sample.sum()),
                        max_candidates=len(cands), trim=TRIM, parallel=parallel, device=device) as sc:
        sc.upload(images, sample, depth=depth)
        if warm is not None:
            sc.set_start(warm)
        sc.step(cands, warm=warm is not None)
        return sc.fetch(), sc.fetch_pixels(), sc.parallel


@pytest.mark.parametrize("method,robust,light_kind", [("lm", "cauchy", "directional"), ("dogleg", "none", "point"),
                                                      ("bfgs", "huber", "directional")])
@pytest.mark.parametrize("cpu_blocks", [False, True])
def test_lights_parallel_equals_one_thread_a_pixel(method, robust, light_kind, cpu_blocks, device, monkeypatch):
    """The lights-parallel build (a block of 32 lanes a (candidate, pixel) solve, the lights split over the
    lanes and the sums reduced over the block) against one thread a solve, 40 noisy images with a shadow
    threshold, IRLS (the lanes reweight their own lights), cold multi-start and warm steps.

    The sums differ only in order: on one lane (the CPU without ``enable_cpu_blocks``) the order is the same
    and the results are bitwise equal; with 32 lanes (CUDA, or the CPU's cooperative blocks) the energies
    agree to the float32 rounding of a sum of 40 terms carried through the fit (rtol 1e-4), and the normals
    to 0.01 deg on all but a few pixels (a rounding difference can move where an iteration stops)."""
    import warp as wp

    if cpu_blocks:
        if device != "cpu":
            pytest.skip("enable_cpu_blocks concerns the CPU backend")
        monkeypatch.setattr(wp.config, "enable_cpu_blocks", True)
    img, lights, sc, mat = _many_lights_case("cook-torrance", light_kind, 40, size=24, device=device)
    sample = sample_mask(sc.mask, 90, seed=7)
    depth = sc.depth if light_kind == "point" else None
    cands = candidates_around(mat)
    cfg = fit_config(solver=method, robust=robust, irls_rounds=2 if robust != "none" else 3, shadow_threshold=0.02)
    s = scale_of(img, sc.mask)
    warm = sc.normals[sample].astype(np.float32)
    for start in (None, warm):
        e1, p1, k1 = _score_parallel(img, sample, sc.camera, lights, cands, cfg, "pixels", device=device,
                                     depth=depth, warm=start)
        e2, p2, k2 = _score_parallel(img, sample, sc.camera, lights, cands, cfg, "lights", device=device,
                                     depth=depth, warm=start)
        assert (k1, k2) == ("pixels", "lights")
        if device == "cpu" and not cpu_blocks:
            np.testing.assert_array_equal(e1, e2)
            for name in ("normals", "albedo", "residual", "iterations", "flags"):
                np.testing.assert_array_equal(p1[name], p2[name])
            continue
        np.testing.assert_allclose(e2, e1, rtol=1e-4, atol=(1e-6 * s) ** 2)
        ang = np.degrees(2.0 * np.arcsin(np.linalg.norm(p1["normals"].astype(np.float64) - p2["normals"], axis=-1) / 2))
        assert np.mean(ang < 1e-2) >= 0.97, np.sort(ang.ravel())[-10:]
        np.testing.assert_array_equal(p1["flags"] & ~4, p2["flags"] & ~4)  # all but "not converged"


def test_parallel_choice(device):
    """``parallel``: checked; "auto" stays per launch on CUDA from LIGHTS_PARALLEL_MIN images (the lanes for
    launches of at most LIGHTS_PARALLEL_PAIRS_PER_IMAGE x N pairs), else one thread a pair."""
    from gpps.names import LIGHTS_PARALLEL_MIN, LIGHTS_PARALLEL_PAIRS_PER_IMAGE

    img, lights, sc, mat = make_case("sphere", 16, "orthographic", "directional", "blinn-phong", device=device)
    with pytest.raises(ValueError, match="parallel"):
        MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit_config(), parallel="warps", device=device)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit_config(), device=device) as a:
        assert a.parallel == "pixels"  # 3 images
    n = LIGHTS_PARALLEL_MIN
    shape = (n,) + img.shape[1:3]
    many = DirectionalLights(default_lights("directional", n, layout="spiral").directions)
    with MaterialScorer(shape, sc.camera, many, mat, fit_config(), device=device) as b:
        cuda = device.startswith("cuda")
        assert b.parallel == ("auto" if cuda else "pixels")
        limit = LIGHTS_PARALLEL_PAIRS_PER_IMAGE * n
        assert b._uses_lanes(limit) == cuda and not b._uses_lanes(limit + 1)
    with MaterialScorer(shape, sc.camera, many, mat, fit_config(), parallel="lights", device=device) as c:
        assert c._uses_lanes(10 ** 9) and c._kernel is None


@pytest.mark.parametrize("robust,light_kind,camera", [("none", "directional", "perspective"),
                                                      ("cauchy", "point", "orthographic")])
def test_split_starts_equal_one_thread_a_candidate(robust, light_kind, camera, device):
    """The starts-parallel cold step (a thread a start, the best picked in start order, then finish_pixel)
    gives the one-thread kernel's results: bitwise on the CPU (the same functions, the same order), and on
    CUDA to the code generator's choices (another module); warm steps take the one-thread kernel either way."""
    img, lights, sc, mat = make_case("bumps", 40, camera, light_kind, "cook-torrance", device=device)
    depth = sc.depth if light_kind == "point" else None
    sample = sample_mask(sc.mask, 150, seed=3)
    cfg = fit_config(robust=robust, irls_rounds=2 if robust != "none" else 0)
    cands = candidates_around(mat)
    got = {}
    for split in (False, True):
        with MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=int(sample.sum()),
                            max_candidates=len(cands), trim=TRIM, split_starts=split, device=device) as s:
            assert s.split_starts is split
            s.upload(img, sample, depth=depth)
            s.step(cands)
            got[split] = (s.fetch(), s.fetch_pixels())
    (e0, p0), (e1, p1) = got[False], got[True]
    if device.startswith("cuda"):
        # another module: the code generator's choices (FMA contraction) differ, and a 3-image fit's starts
        # can end in other minima of equal cost for some pairs (seen on an H100: 7.5 % of the pairs more
        # than 0.01 deg apart): the energies agree, and most normals
        assert_energies_equal(e1, e0, scale_of(img, sc.mask))
        cos = np.clip(np.sum(p0["normals"] * p1["normals"], -1), -1.0, 1.0)
        assert np.median(np.degrees(np.arccos(cos))) < 1e-3
    else:
        assert np.array_equal(e0, e1)
        for k in p0:
            assert np.array_equal(p0[k], p1[k]), k


def test_split_starts_choice(device):
    img, lights, sc, mat = make_case("bumps", 24, "perspective", "directional", "cook-torrance", device=device)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit_config(), max_samples=50, device=device) as s:
        assert s.split_starts is (device.startswith("cuda") and STARTS > 1)
    with MaterialScorer(img.shape[:3], sc.camera, lights, mat, replace(fit_config(), starts=1), max_samples=50,
                        device=device) as s:
        assert s.split_starts is False
    with pytest.raises(TypeError, match="split_starts"):
        MaterialScorer(img.shape[:3], sc.camera, lights, mat, fit_config(), max_samples=50, split_starts="yes",
                       device=device)
