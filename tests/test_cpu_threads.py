"""CPU launches split across threads (gpps/pipeline/cpu_threads.py): same results as one launch."""

from __future__ import annotations

import numpy as np
import pytest
from cases import make_case
from conftest import DEVICES

from gpps.pipeline import cpu_threads as ct
from gpps.pipeline.material import MaterialScorer
from gpps.pipeline.solver import PixelSolver, SolverConfig


needs_cpu = pytest.mark.skipif("cpu" not in DEVICES, reason="the Warp CPU backend is not among the test devices")


def test_balanced_bounds():
    w = np.array([0, 0, 5, 5, 0, 10, 0, 0])
    b = ct.balanced_bounds(w, 3)
    assert b[0][0] == 0 and b[-1][1] == w.size
    assert all(x[1] == y[0] for x, y in zip(b, b[1:]))
    assert all(bb > a for a, bb in b)
    loads = [w[a:bb].sum() for a, bb in b]
    assert max(loads) <= 10 and sum(loads) == w.sum()
    assert ct.balanced_bounds(w, 1) == [(0, 8)]
    assert ct.balanced_bounds(np.zeros(4), 3) == [(0, 4)]
    assert ct.balanced_bounds([], 3) == []


def test_cpu_threads_env(monkeypatch):
    monkeypatch.setenv("GPPS_CPU_THREADS", "3")
    assert ct.cpu_threads() == 3
    monkeypatch.setenv("GPPS_CPU_THREADS", "0")
    with pytest.raises(ValueError, match="GPPS_CPU_THREADS"):
        ct.cpu_threads()
    monkeypatch.setenv("GPPS_CPU_THREADS", "many")
    with pytest.raises(ValueError, match="GPPS_CPU_THREADS"):
        ct.cpu_threads()
    monkeypatch.delenv("GPPS_CPU_THREADS")
    assert ct.cpu_threads() >= 1


def test_run_all_reraises():
    out = []

    def bad():
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        ct.run_all([lambda: out.append(1), bad])
    ct.run_all([lambda: out.append(2)])
    assert 2 in out


def _solve(monkeypatch, threads, img, lights, sc, mat, cfg, mask):
    monkeypatch.setenv("GPPS_CPU_THREADS", str(threads))
    s = PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device="cpu")
    out = s.run(img, mask)
    return out, s._row_bounds


@needs_cpu
@pytest.mark.parametrize("solver", ["lm", "bfgs"])
def test_pixel_solver_split_equals_one_launch(monkeypatch, solver):
    """Row ranges on 3 threads give bitwise the outputs of one launch (each thread writes its own rows),
    including pixels outside the mask and the neighbour pass that runs after the split solve."""
    img, lights, sc, mat = make_case("sphere", 40, "perspective", "directional", "blinn-phong", device="cpu")
    cfg = SolverConfig(solver=solver, starts=3)
    one, b1 = _solve(monkeypatch, 1, img, lights, sc, mat, cfg, sc.mask)
    three, b3 = _solve(monkeypatch, 3, img, lights, sc, mat, cfg, sc.mask)
    assert b1 is None and b3 is not None and len(b3) == 3
    for k in one:
        np.testing.assert_array_equal(one[k], three[k], err_msg=k)


@needs_cpu
def test_scorer_split_equals_one_launch(monkeypatch):
    img, lights, sc, mat = make_case("sphere", 32, "perspective", "directional", "cook-torrance", device="cpu")
    rng = np.random.default_rng(0)
    sample = np.zeros(sc.mask.size, bool)
    sample[rng.choice(np.flatnonzero(sc.mask.ravel()), 120, replace=False)] = True
    sample = sample.reshape(sc.mask.shape)
    cfg = SolverConfig(starts=4, neighbour_radius=0)
    out = {}
    for threads in (1, 3):
        monkeypatch.setenv("GPPS_CPU_THREADS", str(threads))
        with MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=120, max_candidates=2,
                            device="cpu") as scorer:
            scorer.upload(img, sample)
            scorer.step([mat, mat.__class__.default_for("cook-torrance")])
            out[threads] = scorer.fetch_pixels()
    for k in out[1]:
        np.testing.assert_array_equal(out[1][k], out[3][k], err_msg=k)
