"""NelderMeadSearch (gpps/pipeline/material_search.py): RON's Nelder-Mead with each step decided on the device.

Reference: the host method :meth:`gpps.flows.ron.RON._nelder_mead` (scipy's coefficients; a test in test_ron.py
holds it to scipy's trajectory), run on the same scorer, so both read residuals of the same kernel on the same
float32 material rows; the energies differ only in the float64 summation order of the trimmed mean.  So the
searches take the same steps: the same best vertex to 1e-12 (log units), its energy to 1e-12 relative, the same
number of evaluations read.  Two scorers: a fake one whose residuals are an analytic valley (any step of the method
can be forced: expansions, contractions, shrinks, the budget), and MaterialScorer on a rendered Cook-Torrance
scene, cold and warm.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from cases import make_case
from kernels_for_tests import valley_residual_kernel

from gpps.flows.ron import RON, initial_simplex
from gpps.material import Material
from gpps.names import LOBE_RANGES
from gpps.pipeline.material import MaterialScorer, trimmed_energy
from gpps.pipeline.material_search import NelderMeadSearch
from gpps.pipeline.solver import SolverConfig

NAMES = ("ks", "roughness")
LO = np.log([LOBE_RANGES[n][0] for n in NAMES])
HI = np.log([LOBE_RANGES[n][1] for n in NAMES])


class ValleyScorer:
    """The scorer protocol NelderMeadSearch needs, residuals from tests/kernels_for_tests.valley_residual_kernel."""

    brdf = "cook-torrance"

    def __init__(self, device, samples=9, trim=0.2, max_candidates=8):
        import warp as wp

        from gpps.kernels.brdf import MaterialParams

        self.device, self.trim, self.max_candidates, self.max_samples = device, trim, max_candidates, samples + 3
        self.samples = samples
        w = np.ones(self.max_samples, np.float32)
        w[:samples] = 1.0 + 0.1 * np.arange(samples)
        w[samples - 1] = 50.0  # an outlier the trim drops
        self.weights = wp.array(w, dtype=wp.float32, device=device)
        self.mats = wp.zeros(max_candidates, dtype=MaterialParams, device=device)
        self.residual = wp.zeros((max_candidates, self.max_samples), dtype=wp.float32, device=device)
        self.launches = 0

    def launch(self, *, count, warm=False):
        import warp as wp

        self.launches += 1
        wp.launch(valley_residual_kernel, dim=(count, self.samples), inputs=[self.mats, self.weights],
                  outputs=[self.residual], device=self.device)

    def score(self, material, xs):
        """Host-driven scoring of points ``xs`` (clipped as RON's score does): the trimmed energies."""
        from gpps.kernels.brdf import MaterialParams

        xs = np.clip(np.asarray(xs, np.float64), LO, HI)
        rows = np.zeros(self.max_candidates, dtype=MaterialParams.numpy_dtype())
        m = material
        rows[:] = (m.device_tag, m.ks, m.shininess, m.roughness, m.f0, m.eta_u, m.eta_v)
        vals = np.exp(xs)
        rows["ks"][:len(xs)] = vals[:, 0]
        rows["roughness"][:len(xs)] = vals[:, 1]
        self.mats.assign(rows)
        self.launch(count=len(xs))
        return device_order_energy(self.residual.numpy()[:len(xs), :self.samples], self.trim)


def device_order_energy(residual, trim):
    """:func:`trimmed_energy` summed in the device's order (gpps.kernels.material_search: strided partial sums in
    index order, then the partials in order): the float64 sum the device forms, bit for bit."""
    from gpps.kernels.material_search import PARTIAL_LANES

    r = np.asarray(residual, np.float32)
    k, p = r.shape
    keep = max(1, int(round(p * (1.0 - float(trim)))))
    out = np.zeros(k)
    for c in range(k):
        key = np.where(np.isnan(r[c]), np.float32(np.inf), r[c])
        kept = np.zeros(p, bool)
        kept[np.argsort(key, kind="stable")[:keep]] = True
        contrib = np.where(kept, r[c].astype(np.float64) ** 2, 0.0)
        total = 0.0
        for t in range(PARTIAL_LANES):
            part = 0.0
            for v in contrib[t::PARTIAL_LANES]:
                part += float(v)
            total += part
        out[c] = total / keep
    return out


def host_search(score, simplex, maxfev, xatol):
    """RON's host Nelder-Mead (no speculation) and the number of evaluations it read."""
    calls = []

    def counted(xs):
        calls.append(len(xs))
        return score(xs)

    fx, x, _ = RON._nelder_mead(counted, simplex, None, maxfev, xatol, speculate=0, bounds=(LO, HI))
    return fx, x, sum(calls)


def initial(x0, step):
    return initial_simplex(x0, step, LO, HI)


@pytest.mark.parametrize("x0,step,maxfev,xatol", [
    ((np.log(2.0), np.log(0.6)), (0.5, 0.5), 200, 1e-4),   # far start: expansions, then contractions
    ((np.log(0.4), np.log(0.2)), (0.3, -0.4), 200, 1e-6),  # at the minimum: contractions and shrinks
    ((np.log(0.05), np.log(0.05)), (0.2, 0.2), 25, 1e-8),   # runs out of budget mid-valley
    ((np.log(2.9), np.log(0.78)), (0.4, 0.4), 120, 1e-3),   # against the bounds (clipped scoring)
])
def test_valley_same_trajectory_as_host(x0, step, maxfev, xatol, device):
    sc = ValleyScorer(device)
    base = Material.default_for("cook-torrance")
    simplex = initial(np.array(x0), np.array(step))
    fx, x, scored = host_search(lambda xs: sc.score(base, xs), simplex, maxfev, xatol)
    f_init = sc.score(base, simplex)
    with NelderMeadSearch(sc, 2) as search:
        got = search.run(base, NAMES, simplex, f_init, lo=LO, hi=HI, maxfev=maxfev, xatol=xatol)
    np.testing.assert_allclose(got["x"], x, rtol=0, atol=1e-12)
    assert abs(got["energy"] - fx) <= 1e-12 * abs(fx)
    assert got["status"] == ("budget" if maxfev == 25 else "converged")
    if got["status"] == "converged":
        sim_size = xatol  # the method stopped because the simplex is small: the best vertex is near the minimum
        assert sim_size > 0
    # every host read was scored once (speculate=0 scores exactly what is read); against the bounds clipped points
    # repeat, which the host scores once and both count at every read
    against = x0[0] == np.log(2.9)
    assert (got["evaluations"] >= scored if against else got["evaluations"] == min(scored, maxfev)) \
        or got["status"] == "budget"
    assert got["scored"] == got["steps"] * 4


@pytest.mark.parametrize("graph", ["auto", "off"])
def test_valley_finds_the_minimum(graph, device):
    """Both loop forms (on CUDA "auto" is a CUDA graph with a conditional node, "off" the host-driven loop;
    on the CPU both are host-driven), the second search replaying the first's graph."""
    import warp as wp

    sc = ValleyScorer(device)
    base = Material.default_for("cook-torrance")
    simplex = initial(np.log([1.0, 0.5]), np.array([0.5, 0.5]))
    with NelderMeadSearch(sc, 2, graph=graph) as search:
        first = search.run(base, NAMES, simplex, sc.score(base, simplex), lo=LO, hi=HI, maxfev=400, xatol=1e-7)
        got = search.run(base, NAMES, simplex, sc.score(base, simplex), lo=LO, hi=HI, maxfev=400, xatol=1e-7)
        assert search.uses_graph() == (graph == "auto" and device.startswith("cuda")
                                       and bool(wp.is_conditional_graph_supported()))
    assert first == {**got, "x": first["x"]} and np.array_equal(first["x"], got["x"])
    assert got["status"] == "converged"
    np.testing.assert_allclose(np.exp(got["x"]), [0.4, 0.2], rtol=1e-4)
    # trimmed: the outlier sample (weight 50) is left out; mean of (w_i^2) * f_min over the 7 kept of 9
    w = 1.0 + 0.1 * np.arange(9)
    keep = int(round(9 * 0.8))
    assert got["energy"] == pytest.approx(0.01 * np.mean(np.sort(w[:8] ** 2)[:keep]), rel=1e-5)


def test_converged_simplex_needs_no_step(device):
    sc = ValleyScorer(device)
    base = Material.default_for("cook-torrance")
    simplex = initial(np.log([0.4, 0.2]), np.array([1e-5, 1e-5]))
    with NelderMeadSearch(sc, 2) as search:
        search.upload(base, NAMES, simplex, sc.score(base, simplex), lo=LO, hi=HI, maxfev=40, xatol=1e-3)
        n = sc.launches
        search.step()
        got = search.fetch()
    assert sc.launches == n and got["steps"] == 0 and got["status"] == "converged"
    # unscored: the init pass scores the simplex, sorts it and stops there (converged)
    with NelderMeadSearch(sc, 2) as search:
        assert search.scores_simplex
        search.upload(base, NAMES, simplex, None, lo=LO, hi=HI, maxfev=40, xatol=1e-3)
        n = sc.launches
        search.step()
        itself = search.fetch()
    assert sc.launches == n + 1 and itself["steps"] == 1 and itself["status"] == "converged"
    assert itself["scored"] == 3 and itself["evaluations"] == got["evaluations"]
    np.testing.assert_array_equal(itself["x"], got["x"])
    assert itself["f_start"] == sc.score(base, simplex[:1])[0]
    with NelderMeadSearch(ValleyScorer(device, max_candidates=8), 4) as search:  # (5 vertices: not one pass)
        assert not search.scores_simplex


def _scene(device):
    img, lights, scene, mat = make_case("sphere", 32, "perspective", "directional", "cook-torrance", device=device)
    rng = np.random.default_rng(3)
    idx = np.flatnonzero(scene.mask.ravel())
    sample = np.zeros(scene.mask.size, bool)
    sample[rng.choice(idx, 120, replace=False)] = True
    return img, lights, scene, mat, sample.reshape(scene.mask.shape)


@pytest.mark.parametrize("warm", [False, True])
def test_material_scorer_same_trajectory_as_host(warm, device):
    img, lights, scene, mat, sample = _scene(device)
    cfg = replace(SolverConfig(), starts=4, neighbour_radius=0, smoothness=0.0, warm_start=False)
    start = Material.from_dict(dict(mat.to_dict(), ks=mat.ks * 2.0, roughness=mat.roughness * 0.6))
    with MaterialScorer(img.shape[:3], scene.camera, lights, "cook-torrance", cfg, max_samples=int(sample.sum()),
                        max_candidates=8, trim=0.02, device=device) as sc:
        sc.upload(img, sample)
        if warm:
            sc.step([start])
            sc.set_start(candidate=0)

        def score(xs):
            xs = np.clip(np.asarray(xs, np.float64), LO, HI)
            sc.step(sc.lobe_candidates(start, NAMES, np.exp(xs)), warm=warm)
            return device_order_energy(sc.fetch_pixels(("residual",))["residual"], sc.trim)

        x0 = np.log([start.ks, start.roughness])
        simplex = initial(x0, np.array([0.15, 0.15]))
        fx, x, _ = host_search(score, simplex, 40, 1e-3)
        f_init = score(simplex)
        with NelderMeadSearch(sc, 2) as search:
            got = search.run(start, NAMES, simplex, f_init, lo=LO, hi=HI, maxfev=40, xatol=1e-3, warm=warm)
            # the simplex scored by the search itself (its init pass): the same trajectory and evaluations, and the
            # start's energy back
            itself = search.run(start, NAMES, simplex, None, lo=LO, hi=HI, maxfev=40, xatol=1e-3, warm=warm)
    np.testing.assert_allclose(got["x"], x, rtol=0, atol=1e-12)
    assert abs(got["energy"] - fx) <= 1e-9 * abs(fx)
    np.testing.assert_array_equal(itself["x"], got["x"])
    assert itself["energy"] == got["energy"] and itself["evaluations"] == got["evaluations"]
    assert itself["steps"] == got["steps"] + 1 and itself["scored"] == got["scored"] + 3
    assert itself["f_start"] == f_init[0] and got["f_start"] is None
    # the true material is nearer than the start
    truth = np.log([mat.ks, mat.roughness])
    assert np.linalg.norm(got["x"] - truth) < np.linalg.norm(x0 - truth)


def test_bad_input(device):
    sc = ValleyScorer(device, max_candidates=3)
    with pytest.raises(ValueError, match="max_candidates >= 4"):
        NelderMeadSearch(sc, 2)
    with pytest.raises(ValueError, match="dims"):
        NelderMeadSearch(ValleyScorer(device), 0)
    with pytest.raises(TypeError, match="scorer"):
        NelderMeadSearch(object(), 1)
    with pytest.raises(ValueError, match="graph"):
        NelderMeadSearch(ValleyScorer(device), 2, graph="always")
    sc = ValleyScorer(device)
    base = Material.default_for("cook-torrance")
    simplex = initial(np.log([0.4, 0.2]), np.array([0.1, 0.1]))
    with NelderMeadSearch(sc, 2) as search:
        with pytest.raises(ValueError, match="upload"):
            search.step()
        with pytest.raises(ValueError, match="names"):
            search.upload(base, ("ks", "shininess"), simplex, np.ones(3), lo=LO, hi=HI, maxfev=40, xatol=1e-3)
        with pytest.raises(ValueError, match="simplex"):
            search.upload(base, NAMES, simplex[:2], np.ones(3), lo=LO, hi=HI, maxfev=40, xatol=1e-3)
        with pytest.raises(ValueError, match="maxfev"):
            search.upload(base, NAMES, simplex, np.ones(3), lo=LO, hi=HI, maxfev=3, xatol=1e-3)
        with pytest.raises(ValueError, match="cook-torrance"):
            search.upload(Material.default_for("blinn-phong"), NAMES, simplex, np.ones(3), lo=LO, hi=HI, maxfev=40,
                          xatol=1e-3)
    with pytest.raises(ValueError, match="closed"):
        search.fetch()


@pytest.mark.parametrize("p,trim", [(2000, 0.02), (150, 0.0), (7, 0.3), (1, 0.5)])
def test_trimmed_energy_kernels(p, trim, device):
    """The device trimmed mean: the float64 sum of the device order bit for bit, numpy's partition mean to
    float64 rounding; ties (quantised residuals), infinities and NaN (kept last, as numpy's partition)."""
    import warp as wp

    from gpps.kernels import material_search as ms

    rng = np.random.default_rng(p)
    k = 5
    r = (np.round(rng.gamma(2.0, 1.0, (k, p)) * 8.0) / 8.0).astype(np.float32)  # many exact ties
    if p > 10:
        r[1, :3] = np.inf
        r[2, 5] = np.nan
    res = wp.array(r, dtype=wp.float32, device=device)
    keep = max(1, int(round(p * (1.0 - trim))))
    contrib = wp.zeros((k, p), dtype=wp.float64, device=device)
    before = wp.zeros((k, p), dtype=wp.int32, device=device)
    partial = wp.zeros((k, ms.PARTIAL_LANES), dtype=wp.float64, device=device)
    energy = wp.zeros(k, dtype=wp.float64, device=device)
    seg = 37  # (segments that do not divide the row)
    wp.launch(ms.trimmed_rank_kernel, dim=(k, p, (p + seg - 1) // seg), inputs=[res, p, seg], outputs=[before],
              device=device)
    ranks = before.numpy()
    # the counts are the ranks in (value, index) order: a permutation of 0..p-1 per row
    key = np.where(np.isnan(r), np.float32(np.inf), r)
    for c in range(k):
        np.testing.assert_array_equal(np.sort(ranks[c]), np.arange(p))
        np.testing.assert_array_equal(np.argsort(ranks[c], kind="stable"), np.argsort(key[c], kind="stable"))
    wp.launch(ms.trimmed_contrib_kernel, dim=(k, p), inputs=[res, keep], outputs=[before, contrib], device=device)
    assert not before.numpy().any()  # cleared for the next pass
    wp.launch(ms.trimmed_partial_kernel, dim=(k, ms.PARTIAL_LANES), inputs=[contrib, p], outputs=[partial],
              device=device)
    wp.launch(ms.trimmed_energy_kernel, dim=k, inputs=[partial, keep], outputs=[energy], device=device)
    e = energy.numpy()
    np.testing.assert_array_equal(e, device_order_energy(r, trim))
    host = trimmed_energy(r, trim)
    fin = np.isfinite(host)
    np.testing.assert_allclose(e[fin], host[fin], rtol=1e-13, atol=0)
    np.testing.assert_array_equal(np.isfinite(e), fin)
    # exactly `keep` values kept per candidate
    assert np.all((contrib.numpy() > 0).sum(1) <= keep)


def test_reconstruct_device_loop_equals_host_loop(device):
    """RON with Nelder-Mead's steps on the device gives the host loop's reconstruction (3 images, perspective
    Cook-Torrance, ks and roughness unknown): the same estimates to float64 rounding of the energies' sums, and
    so the same normals; both CPU and CUDA (on CUDA the device loop is a CUDA graph where conditional nodes exist)."""
    import gpps
    from gpps.flows.ron import RONConfig

    img, lights, scene, mat = make_case("sphere", 48, "perspective", "directional", "cook-torrance", device=device)
    ref = float(scene.depth[scene.mask].mean())
    out = {}
    for loop in ("host", "device"):
        rec = gpps.reconstruct(img, scene.mask, lights, camera=scene.camera, material="cook-torrance",
                               reference_depth=ref, config=RONConfig(material_loop=loop, material_samples=300),
                               device=device)
        out[loop] = rec
    h, d = out["host"], out["device"]
    assert h.estimated.keys() == d.estimated.keys() and h.estimated
    for k, v in h.estimated.items():
        assert d.estimated[k] == pytest.approx(v, rel=1e-9), (h.estimated, d.estimated)
    assert h.rounds == d.rounds
    np.testing.assert_allclose(d.normals[scene.mask], h.normals[scene.mask], atol=1e-5)


def test_nan_energies_sort_last_as_numpy(device):
    """A step whose energies are NaN (a degenerate sample) sorts them last, as the host's argsort does."""
    import warp as wp

    from gpps.kernels import material_search as ms

    sim0 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    f0 = np.array([1.0, 2.0, 3.0])
    # every candidate NaN: the reflection is not better than anything -> inside contraction read (NaN) -> shrink
    sim = wp.array(sim0, dtype=wp.float64, device=device)
    fsim = wp.array(f0, dtype=wp.float64, device=device)
    cand = wp.array(np.arange(8.0).reshape(4, 2), dtype=wp.float64, device=device)
    energy = wp.array(np.full(4, np.nan), dtype=wp.float64, device=device)
    state = wp.array(np.array([3, 0, 0, 0], np.int32), dtype=wp.int32, device=device)
    cond = wp.array(np.array([1], np.int32), dtype=wp.int32, device=device)
    fstart = wp.zeros(1, dtype=wp.float64, device=device)
    args = dict(inputs=[energy, cand, 2, 40, wp.float64(1e-3)], outputs=[sim, fsim, fstart, state, cond],
                device=device)
    wp.launch(ms.search_step_kernel, dim=1, **args)
    assert state.numpy()[3] == 1  # a shrink next
    # the shrink pass: vertex 1 gets a number, vertex 2 NaN; numpy's stable argsort puts NaN last
    energy.assign(np.array([0.5, np.nan, 9.0, 9.0]))
    cand.assign(np.array([[0.5, 0.0], [0.0, 0.5], [9.0, 9.0], [9.0, 9.0]]))
    wp.launch(ms.search_step_kernel, dim=1, **args)
    f = fsim.numpy()
    ref = np.array([1.0, 0.5, np.nan])[np.argsort(np.array([1.0, 0.5, np.nan]), kind="stable")]
    np.testing.assert_array_equal(f, ref)
    np.testing.assert_array_equal(sim.numpy(), np.array([[0.5, 0.0], [0.0, 0.0], [0.0, 0.5]]))
