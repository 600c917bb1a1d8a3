"""Kernel modules compiled ahead of their first launch (:mod:`gpps.pipeline.prefetch`): the helper compiles into
Warp's kernel cache without loading, the stage's own load then finds the binary (no second compile) and the
kernel computes what it computes without the helper; a run's plan (:meth:`gpps.flows.ron.RON.kernel_plan`) names
every gpps module the run launches."""

import os

import numpy as np
import pytest
import warp as wp

import gpps
from conftest import RENDER_DEVICE
from gpps.flows.ron import RON, RONConfig
from gpps.flows.synthetic import default_lights, render
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights
from gpps.material import Material
from gpps.pipeline import prefetch as pf
from kernels_for_tests import make_scale_kernel

Module = type(wp.get_module(pf.__name__))


@pytest.fixture
def compiles(monkeypatch, tmp_path):
    """Every ``Module._compile`` call of this file's test kernels (modules named after ``make_scale_kernel``) as
    ``(module name, built, thread name)``, in a kernel cache of its own (a helper of an earlier test's run may
    still be compiling gpps's modules in this process)."""
    import threading

    calls = []
    orig = Module._compile

    def spy(self, *a, **k):
        built = orig(self, *a, **k)
        if "make_scale_kernel" in self.name:
            calls.append((self.name, bool(built), threading.current_thread().name))
        return built

    monkeypatch.setattr(Module, "_compile", spy)
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))
    return calls


def _fresh_kernel():
    """A kernel whose module no cache holds (a factor drawn at random)."""
    factor = float(np.random.default_rng().uniform(2.0, 3.0))
    return make_scale_kernel(factor), factor


def test_compile_into_cache_then_load_finds_it(device, compiles):
    k, factor = _fresh_kernel()
    assert pf.compile_into_cache(k, device) is True
    assert compiles == [(k.module.name, True, compiles[0][2])]
    assert pf.compile_into_cache(k.module, device) is False  # (in the cache now)
    a = wp.array(np.arange(5, dtype=np.float32), device=device)
    out = wp.zeros(5, dtype=wp.float32, device=device)
    wp.launch(k, dim=5, inputs=[a], outputs=[out], device=device)  # (loads: must find the binary)
    assert [c[1] for c in compiles if c[0] == k.module.name] == [True, False, False]  # (the load built nothing)
    np.testing.assert_allclose(out.numpy(), factor * np.arange(5, dtype=np.float32), rtol=1e-6)
    assert pf.compile_into_cache(k, device) is False  # (loaded)


def test_prefetch_compiles_on_a_helper_in_order(device, compiles):
    kernels = [_fresh_kernel()[0] for _ in range(3)]
    with pf.KernelPrefetch(device, workers=1) as p:
        assert p.submit([kernels[0], None, kernels[1], kernels[0].module, kernels[2]]) == 3  # (each module once)
        p.wait()
        assert [name for name, _ in p.compiled] == [k.module.name for k in kernels]
        assert all(s > 0 for _, s in p.compiled) and p.failed == [] and p.skipped is None
    assert [c[0] for c in compiles] == [k.module.name for k in kernels]
    assert all(c[1] and c[2].startswith("gpps-prefetch") for c in compiles)
    for k in kernels:
        pf.settle(k, device)  # (done: nothing to wait for)
        wp.load_module(k.module, device=device)
    assert len(compiles) == 6 and not any(c[1] for c in compiles[3:])  # (the loads found the binaries)
    with pf.KernelPrefetch(device) as again:  # (a later run's plan: loaded modules are not queued)
        assert again.submit(kernels) == 0 and again._pool is None


def _held_helper(device, monkeypatch):
    """A one-thread helper given two fresh modules, whose first compile waits for ``gate``: ``(helper, running
    kernel, queued kernel, started event, gate event)``; ``started`` is set when the first compile begins."""
    import threading

    started, gate = threading.Event(), threading.Event()
    running, _ = _fresh_kernel()
    queued, _ = _fresh_kernel()
    orig = pf.compile_into_cache

    def held(module, dev, *a):
        if module is running.module:
            started.set()
            gate.wait(30)
        return orig(module, dev, *a)

    monkeypatch.setattr(pf, "compile_into_cache", held)
    p = pf.KernelPrefetch(device, workers=1)
    p.submit([running, queued])
    return p, running, queued, started, gate


def test_settle_takes_a_queued_compile_back(device, compiles, monkeypatch):
    """A stage about to load a module still queued takes it off the queue and builds it itself: one compile."""
    p, blocker, queued, _, gate = _held_helper(device, monkeypatch)
    try:
        pf.settle(queued, device)  # (queued behind the held compile: cancelled)
        wp.load_module(queued.module, device=device)
        gate.set()
        p.wait()
    finally:
        gate.set()
        p.close()
    assert [c for c in compiles if c[0] == queued.module.name] == [(queued.module.name, True, "MainThread")]
    assert [n for n, _ in p.compiled] == [blocker.module.name]


def test_prefetch_errors_and_switch(monkeypatch):
    with pytest.raises(TypeError, match="kernels"):
        pf.KernelPrefetch("cpu").submit(["solve"])
    with pytest.raises(ValueError, match="workers"):
        pf.KernelPrefetch(RENDER_DEVICE, workers=0)
    with pytest.raises(TypeError, match="workers"):
        pf.KernelPrefetch(RENDER_DEVICE, workers=2.5)
    with pytest.raises(TypeError, match="kernel_or_module"):
        pf.settle("solve", RENDER_DEVICE)
    monkeypatch.setenv("GPPS_PREFETCH", "0")
    assert pf.prefetch_enabled() is False
    monkeypatch.setenv("GPPS_PREFETCH", "1")
    assert pf.prefetch_enabled() is True
    monkeypatch.setenv("GPPS_PREFETCH", "maybe")
    with pytest.raises(ValueError, match="GPPS_PREFETCH"):
        pf.prefetch_enabled()


def _failing_helper(monkeypatch, error):
    """A helper whose every compile raises ``error``, given one fresh kernel and waited for: ``(helper, kernel)``
    (the caller closes it)."""
    k, _ = _fresh_kernel()

    def fail(module, dev, *a):
        raise error

    monkeypatch.setattr(pf, "compile_into_cache", fail)
    p = pf.KernelPrefetch(RENDER_DEVICE)
    p.submit([k])
    p.wait()
    return p, k


def test_a_failed_compile_is_kept_not_raised(monkeypatch):
    p, k = _failing_helper(monkeypatch, RuntimeError("no compiler"))
    p.close()
    assert p.failed == [(k.module.name, "RuntimeError: no compiler")] and p.compiled == []


def test_a_warp_without_the_methods_skips(monkeypatch):
    p, _ = _failing_helper(monkeypatch, AttributeError("'Module' object has no attribute '_compile'"))
    with p:
        assert p.skipped is not None and "cannot compile" in p.skipped
        assert p.submit([_fresh_kernel()[0]]) == 0


PLASTIC = Material.from_ior("plastic", 1.5, ks=1.2, roughness=0.15)


@pytest.mark.parametrize("warm", [False, True])
def test_the_plan_names_every_module_a_run_launches(device, monkeypatch, warm):
    """A RON comparing two models, three rounds, cast shadows: every gpps Warp module variant (module and block size)
    its run loads on the device is in :meth:`RON.kernel_plan` (one outside it would compile at its first launch, as
    without a plan)."""
    sc = make_scene("sphere", 32, "perspective")
    L = default_lights("directional", 6, layout="spiral")
    img = render(sc, PLASTIC, L, bits=16, noise=0.0, seed=1, device=RENDER_DEVICE)
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    lights = DirectionalLights(L.directions)
    cfg = RONConfig(models=("cook-torrance",), estimate=("ks", "roughness"), rounds=3, cast_shadows=True)
    # (with the helper on, as runs are: it only compiles, so the loads seen are the run's own)
    ron = RON(img.shape[:3], sc.camera, lights, PLASTIC, sc.mask, cfg, device=device)
    try:
        ref = float(sc.depth[sc.mask].mean())
        start = None
        if warm:
            first = ron.run(img, reference_depth=ref)
            start = (first.normals, first.highlight)
        loaded = _loads_on(device, monkeypatch)
        ron.run(img, reference_depth=ref, start=start)
        plan = set()
        for x in ron.kernel_plan(warm_start=warm):
            item, dim = x if isinstance(x, tuple) else (x, None)
            plan.add((getattr(item, "module", item).name, pf.launch_block_dim(device, dim)))
    finally:
        ron.close()
    assert loaded, "the spy saw no load"
    assert loaded <= plan, f"launched outside the plan: {sorted(loaded - plan)}"


_FIRST_RUN = r"""
import json, sys, threading
import numpy as np
import warp as wp
import gpps
from gpps.flows.synthetic import default_lights, render
from gpps.host.scenes import make_scene
from gpps.lights import DirectionalLights
from gpps.material import Material
from gpps.pipeline import prefetch as pf

Module = type(wp.get_module(pf.__name__))
built = []
orig = Module._compile
def spy(self, *a, **k):
    r = orig(self, *a, **k)
    if r:
        built.append((self.name, threading.current_thread().name))
    return r
Module._compile = spy
sc = make_scene("sphere", 24, "perspective")
L = default_lights("directional", 4, layout="spiral")
m = Material.from_ior("plastic", 1.5, ks=1.2, roughness=0.15)
img = render(sc, m, L, bits=16, noise=0.0, seed=2, device="cpu")
img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
rec = gpps.reconstruct(img, sc.mask, DirectionalLights(L.directions), camera=sc.camera, material="plastic",
                       reference_depth=float(sc.depth[sc.mask].mean()), device="cpu")
np.save(sys.argv[1], np.stack([rec.normals[..., 0], rec.normals[..., 1], rec.normals[..., 2], rec.depth]))
print(json.dumps(built))
"""


def test_a_first_run_with_the_helper_equals_one_without(tmp_path):
    """A first run (an empty kernel cache, a new process) with the helper compiling ahead returns what a run
    without a helper returns, bit for bit (the helper only moves compiles); the helper built modules and none was
    built twice (CPU: the process compiles about fifteen modules, ~20 s here)."""
    import json
    import subprocess
    import sys

    if "cpu" not in [str(d) for d in wp.get_devices()]:
        pytest.skip("needs Warp's CPU device (the first run is timed on the CPU)")
    env = dict(os.environ, GPPS_CACHE_DIR=str(tmp_path / "cache"), GPPS_PREFETCH="1")
    out = tmp_path / "first.npy"
    got = subprocess.run([sys.executable, "-c", _FIRST_RUN, str(out)], env=env, capture_output=True, text=True,
                         timeout=900)
    assert got.returncode == 0, got.stderr[-3000:]
    built = json.loads(got.stdout.strip().splitlines()[-1])
    names = [n for n, _ in built]
    assert len(names) == len(set(names)), f"built twice: {names}"
    assert any(t.startswith("gpps-prefetch") for _, t in built), built
    sc = make_scene("sphere", 24, "perspective")
    L = default_lights("directional", 4, layout="spiral")
    img = render(sc, PLASTIC, L, bits=16, noise=0.0, seed=2, device="cpu")
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    rec = gpps.reconstruct(img, sc.mask, DirectionalLights(L.directions), camera=sc.camera, material="plastic",
                           reference_depth=float(sc.depth[sc.mask].mean()), device="cpu")
    first = np.load(out)
    np.testing.assert_array_equal(first[:3], np.moveaxis(rec.normals, -1, 0))
    np.testing.assert_array_equal(first[3], rec.depth)


def _loads_on(device, monkeypatch):
    """The gpps module variants (name, block size) loaded on ``device`` from now on."""
    loaded = set()
    orig = Module.load

    def spy(self, dev, block_dim=None, *a, **k):
        if self.name.startswith("gpps.") and str(wp.get_device(dev)) == str(wp.get_device(device)):
            loaded.add((self.name, int(block_dim if block_dim is not None else self.options["block_dim"])))
        return orig(self, dev, block_dim, *a, **k)

    monkeypatch.setattr(Module, "load", spy)
    return loaded


def test_the_compensation_stage_names_its_modules(device, monkeypatch):
    """The interreflection stage's gather, total and subtraction load only what ``kernel_modules`` names (the folder
    flow queues those behind the first reconstruction's plan)."""
    from test_interreflection import _self_lit

    from gpps.camera import Orthographic
    from gpps.pipeline.interreflection import InterreflectionConfig, Interreflections

    m, depth, n, lights, cam, direct, images = _self_lit(device)
    loaded = _loads_on(device, monkeypatch)
    with Interreflections(images.shape[:3], Orthographic(1.0), InterreflectionConfig(max_sources=300),
                          device=device) as st:
        st.upload(depth, m, n, images)
        st.step()
        st.indirect_total(np.full(m.shape + (3,), 0.5, np.float32))
        st.subtract_from(wp.array(images, dtype=wp.vec3, device=device), 0.5)
    named = {(x.name, pf.launch_block_dim(device)) for x in Interreflections.kernel_modules()}
    assert loaded and loaded <= named, sorted(loaded - named)


def test_a_flow_queues_its_later_stages_behind_the_plan(monkeypatch):
    """``ResidentFrame.compile_ahead`` (the folder flow's compensation): the modules go to the helper after the
    run's plan, at the first run; with the helper off nothing is queued."""
    from gpps.flows.reconstruction import ResidentFrame
    from gpps.pipeline.interreflection import Interreflections

    sc = make_scene("sphere", 16, "orthographic")
    L = default_lights("directional", 3, layout="ring")
    img = render(sc, Material("lambertian"), L, bits=16, noise=0.0, seed=3, device=RENDER_DEVICE)
    img = img / np.asarray(L.intensities, np.float32)[:, None, None, :]
    submitted = []
    orig = pf.KernelPrefetch.submit

    def spy(self, kernels):
        kernels = list(kernels)
        submitted.append([getattr(k, "module", k) for k in kernels])
        return orig(self, kernels)

    monkeypatch.setattr(pf.KernelPrefetch, "submit", spy)
    extra = Interreflections.kernel_modules()
    with ResidentFrame(img, sc.mask, DirectionalLights(L.directions), camera=sc.camera, material="lambertian",
                       device=RENDER_DEVICE) as frame:
        frame.compile_ahead(extra)
        assert submitted == []  # (queued at the first run)
        frame.run()
    assert len(submitted) == 1 and submitted[0][-len(extra):] == extra and len(submitted[0]) > len(extra)
    monkeypatch.setenv("GPPS_PREFETCH", "0")
    submitted.clear()
    with ResidentFrame(img, sc.mask, DirectionalLights(L.directions), camera=sc.camera, material="lambertian",
                       device=RENDER_DEVICE) as frame:
        frame.compile_ahead(extra)
        frame.run()
    assert submitted == []


def test_close_keeps_a_running_compile_visible_to_settle(device, compiles, monkeypatch):
    """After ``close()`` a compile still running stays in the registry until it ends: a stage settling on its module
    waits for it instead of building it a second time; a closed helper's queue is dropped."""
    import threading
    import time

    p, running, queued, started, gate = _held_helper(device, monkeypatch)
    assert started.wait(30)
    p.close()  # (the queued one dropped; the running one goes on)
    threading.Timer(0.3, gate.set).start()
    t = time.perf_counter()
    pf.settle(running, device)  # (waits for the running compile)
    assert time.perf_counter() - t >= 0.2
    wp.load_module(running.module, device=device)
    assert [c[1] for c in compiles if c[0] == running.module.name] == [True, False]  # (built once)
    assert not any(c[0] == queued.module.name for c in compiles)  # (dropped at close)


def test_exit_drops_what_an_unclosed_helper_has_queued(device, compiles, monkeypatch):
    """The interpreter-exit hook closes helpers nobody closed (a RON or Reconstructor left open): their queues are
    dropped rather than compiled while the process exits; a compile already running ends."""
    p, running, queued, started, gate = _held_helper(device, monkeypatch)
    futures = [f for _, f in p._futures]
    assert started.wait(30) and p in set(pf._LIVE)
    pf._close_at_exit()
    gate.set()
    futures[0].result(timeout=60)
    assert futures[1].cancelled()
    assert [c[0] for c in compiles] == [running.module.name]


def test_the_rounds_stage_settles_at_its_first_step(device, monkeypatch):
    """RON builds its device rounds at a run's start and steps them after round 1's solve: the stage settles on its
    module at its first step, not in its constructor (which took a first run's queued compile off the helper, to
    be built later on the run's own thread), and once."""
    from gpps.pipeline import stage
    from gpps.pipeline.ron_rounds import DeviceRounds
    from gpps.pipeline.solver import PixelSolver

    settled = []
    orig = stage.settle
    monkeypatch.setattr(stage, "settle", lambda k, dev: (settled.append(pf._module_of(k)), orig(k, dev))[1])
    sc = make_scene("sphere", 16, "orthographic")
    s = PixelSolver((3, 16, 16), sc.camera, default_lights("directional", 3), Material.default_for("blinn-phong"),
                    device=device)
    dr = DeviceRounds(s, sc.mask)
    (module,) = DeviceRounds.kernel_modules()
    assert module not in settled
    dr.step()
    assert settled.count(module) == 1
    dr.step()
    assert settled.count(module) == 1
    dr.close()
    s.close()


def test_cpu_helpers_follow_the_cpu_threads(monkeypatch):
    """On the CPU a helper a core of the CPU launches (GPPS_CPU_THREADS), up to 8; an explicit count wins."""
    for env, want in (("1", 1), ("3", 3), ("20", 8)):
        monkeypatch.setenv("GPPS_CPU_THREADS", env)
        p = pf.KernelPrefetch("cpu")
        assert p.workers == want
        p.close()
    p = pf.KernelPrefetch("cpu", workers=2)
    assert p.workers == 2
    p.close()
