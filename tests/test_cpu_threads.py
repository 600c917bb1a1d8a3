"""CPU launches split across threads (gpps/pipeline/cpu_threads.py): same results as one launch."""

from __future__ import annotations

import os
import platform

import numpy as np
import pytest
from cases import make_case
from conftest import DEVICES, RENDER_DEVICE

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


def test_submit_and_run_all_inside_pool_tasks(monkeypatch):
    """submit returns the task's value (and re-raises its error); run_all and submit called from inside a pool task
    run in line on that thread (with every worker of a 2-thread pool in such a task, a queued part would
    otherwise never start)."""
    import threading

    monkeypatch.setattr(ct, "_POOL", None)
    monkeypatch.setenv("GPPS_CPU_THREADS", "2")
    assert ct.submit(lambda a, b=0: a + b, 2, b=3).result(timeout=30) == 5
    with pytest.raises(RuntimeError, match="boom"):
        ct.submit(lambda: (_ for _ in ()).throw(RuntimeError("boom"))).result(timeout=30)
    both = threading.Barrier(2, timeout=30)

    def outer(k):
        both.wait()  # both workers busy in an outer task
        names = []
        ct.run_all([lambda: names.append(threading.current_thread().name) for _ in range(3)])
        return names, threading.current_thread().name

    for names, me in [f.result(timeout=60) for f in [ct.submit(outer, k) for k in range(2)]]:
        assert names == [me] * 3

    def nested(k):
        both.wait()
        inner = ct.submit(lambda: threading.current_thread().name)
        assert inner.done()
        return inner.result(), threading.current_thread().name

    for got, me in [f.result(timeout=60) for f in [ct.submit(nested, k) for k in range(2)]]:
        assert got == me


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


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="reads and sets the x86-64 MXCSR flush-to-zero bit")
def test_pool_tasks_run_in_the_callers_floating_point_mode(monkeypatch):
    """Threads inherit the floating-point mode of the thread that made them, and Taichi's initialisation turns
    flush-to-zero on in its thread: pool threads made earlier rounded denormal results otherwise (split
    launches differing from run to run). run_all's tasks take the caller's mode."""
    import ctypes
    import threading

    from gpps.pipeline import cpu_threads as ct

    from gpps import _fpenv

    fegetenv, fesetenv = _fpenv._libm()
    saved = ctypes.create_string_buffer(_fpenv._FENV_BYTES)
    assert fegetenv(saved) == 0
    monkeypatch.setattr(ct, "_POOL", None)
    monkeypatch.setenv("GPPS_CPU_THREADS", "2")
    try:
        off = ctypes.create_string_buffer(saved.raw, _fpenv._FENV_BYTES)
        mx = int.from_bytes(off.raw[28:32], "little") & ~0x8040  # FTZ and DAZ off
        off[28:32] = mx.to_bytes(4, "little")
        assert fesetenv(off) == 0
        made = threading.Barrier(2, timeout=30)
        ct.run_all([made.wait, made.wait])  # both pool threads exist, made with flush-to-zero off
        assert float((np.array([1e-30], np.float32) * np.float32(1e-9))[0]) > 0.0
        on = ctypes.create_string_buffer(off.raw, _fpenv._FENV_BYTES)
        on[28:32] = (mx | 0x8000).to_bytes(4, "little")
        assert fesetenv(on) == 0
        small = np.array([1e-30], np.float32)  # normal; times 1e-9 a float32 denormal unless flushed
        here = float((small * np.float32(1e-9))[0])
        got = [None, None]

        both = threading.Barrier(2, timeout=30)

        def task(k):
            def run():
                both.wait()  # one task on each of the two threads
                got[k] = float((small * np.float32(1e-9))[0])
            return run

        ct.run_all([task(0), task(1)])
    finally:
        fesetenv(saved)
    assert here == 0.0  # flush-to-zero in this thread
    assert got == [here, here]


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="reads the x86-64 MXCSR flush-to-zero bit")
def test_taichi_init_leaves_the_callers_floating_point_mode():
    """ti.init turns flush-to-zero on in its thread; gpps._taichi.init puts the caller's mode back (run in a
    fresh process: Taichi initialises once a process)."""
    import subprocess
    import sys
    from pathlib import Path

    code = ("import numpy as np\n"
            "from gpps import _fpenv, _taichi\n"
            "def ftz():\n"
            "    return bool(int.from_bytes(_fpenv.get().raw[28:32], 'little') & 0x8000)\n"
            "before = ftz()\n"
            "_taichi.init('cpu')\n"
            "small = np.array([1e-30], np.float32) * np.float32(1e-9)\n"
            "print(before, ftz(), float(small[0]) > 0.0)\n")
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300)
    assert p.returncode == 0, p.stderr
    assert p.stdout.split()[-3:] == ["False", "False", "True"], p.stdout


def test_run_reporting_reports_while_the_task_runs_and_reraises():
    import threading
    import time

    seen, threads = [], []

    def slow():
        threads.append(threading.current_thread())
        time.sleep(0.35)

    ct.run_reporting(slow, lambda s: seen.append((s, threading.current_thread())), every=0.1)
    assert len(seen) >= 2 and all(b > a for (a, _), (b, _) in zip(seen, seen[1:]))
    assert all(t is threading.current_thread() for _, t in seen)  # reports on the caller's thread
    assert threads[0] is not threading.current_thread()  # the task on a helper
    ct.run_reporting(slow, None)
    assert threads[1] is threading.current_thread()  # no report: inline

    def bad():
        raise KeyError("boom")

    with pytest.raises(KeyError, match="boom"):
        ct.run_reporting(bad, lambda s: None, every=0.05)


def test_solver_load_reports_while_its_modules_load(monkeypatch, device):
    """``PixelSolver.load(progress=)`` keeps the caller's progress moving while a module compiles (a cold cache:
    seconds on the CPU, minutes on CUDA), and loads nothing when the modules are loaded."""
    import time

    import warp as wp

    img, lights, sc, mat = make_case("sphere", 16, "orthographic", "directional", "blinn-phong", device=RENDER_DEVICE)
    ps = PixelSolver(img.shape[:3], sc.camera, lights, mat, SolverConfig(), device=device)
    ps.load()
    mods = {id(k.module): k.module for k in ps.kernels[:1] if k is not None}.values()
    assert mods and all(ps._loaded(m) for m in mods)  # (Warp's table read right: loaded ones start no thread)
    calls = []
    ps.load(progress=lambda *a: calls.append(a))
    assert calls == []  # loaded: nothing to report
    orig = wp.load_module

    def slow_load(module, *a, **k):
        time.sleep(1.3)
        return orig(module, *a, **k)

    monkeypatch.setattr(wp, "load_module", slow_load)
    monkeypatch.setattr(PixelSolver, "_loaded", lambda self, m, block_dim=None: False)
    ps._loaded_for.clear()  # (the solver's note of configs already loaded: as if none were)
    ps.load(progress=lambda *a: calls.append(a))
    assert calls and all(t is None and "loading the solver's kernels" in msg for _, t, msg in calls)
    out = ps.run(img, sc.mask)
    assert np.isfinite(out["normals"][sc.mask]).all()
    ps.close()
