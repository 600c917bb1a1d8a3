"""The multigrid PCG of the Poisson integrator per iteration and per kernel: block sums against per-pixel atomics.

``IntegratorConfig.cg_sums`` picks how the CG's float64 dot products are summed (:mod:`gpps.kernels.poisson`):
``"atomic"`` adds each pixel's term into one scalar (on CUDA one float64 atomic a pixel on one address: an
H100 profile of the 256^2 bumps reconstruction showed each summing loop at ~117 us), ``"block"`` tree-reduces
each sum per block of 128 threads in shared memory with one atomic a block (CUDA only).  On the scene of
``perf/reconstruct_synthetic.py`` (perspective bumps, ``gpps.host.scenes.make_scene("bumps", n)``, 43 234 mask
pixels at 256^2) with the pipeline's integrator settings (n_z^2 weighting, tol 1e-5, float32), per size and
build:

* ``solve``: :meth:`Integrator.run` to tolerance, wall (median of ``--repeat`` after a warm-up), its
  ``timings["solve"]``, iterations, and the depth's largest difference to the atomic build's;
* ``iteration_wall_ms``: ``--iters`` CG iterations (cg_step, V-cycle, cg_direction) queued without host
  reads after a restart from 0, minus the restart alone, per iteration, device-synchronised;
* ``kernel_wall_us``: each CG kernel called ``--inner`` times back to back, per call (host launch included);
* ``device`` (CUDA, unless ``--no-profile``): Taichi's kernel profiler (CUDA events around every task, in a
  child process with ``TI_KERNEL_PROFILER=1``, since it slows the host side) over the same ``--iters``
  iterations: device microseconds per iteration for each task (``kernel/task``), summed per kernel, and the
  V-cycle's share.

Usage:  python perf/integration_pcg_sums.py [--device cuda:0] [--sizes 256,1024] [--builds atomic,block]
            [--iters 20] [--repeat 10] [--out FILE]
On the CPU only ``--builds atomic`` runs (the block build needs CUDA).  Writes ``--out`` (default
perf/results/integration_pcg_sums_<device>.json).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from _integration_common import TASK, med, problem, run_row  # noqa: E402

CG_KERNELS = ("cg_step", "cg_direction", "cg_start", "cg_first_direction", "residual_norm")
VCYCLE_KERNELS = ("down", "up", "coarse_exact")


def _config(build: str, a):
    from gpps.pipeline.integration import IntegratorConfig

    return IntegratorConfig(cg_sums=build, weighting=a.weighting, dtype=a.dtype, tol=a.tol)


def _cg(integ):
    """Closures over the integrator's fields: restart from 0, one CG iteration, and each CG kernel alone."""
    from gpps.kernels import poisson as K

    d = integ._dev  # noqa: SLF001 - a profile of the stage's own loop
    h, w = integ.shape
    blk = integ._block_sums()  # noqa: SLF001
    args = (d["wx"], d["wy"], d["dg"], d["sc"], h, w, blk)

    def restart():
        d["z"].fill(0)
        K.cg_start(d["z"], d["b"], d["r"], d["e"], d["f"], *args)
        integ._vcycle()  # noqa: SLF001
        K.cg_first_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk)

    def iteration():
        K.cg_step(d["z"], d["r"], d["p"], d["q"], d["e"], d["f"], *args)
        integ._vcycle()  # noqa: SLF001
        K.cg_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk)

    kernels = {
        "cg_step": lambda: K.cg_step(d["z"], d["r"], d["p"], d["q"], d["e"], d["f"], *args),
        "cg_direction": lambda: K.cg_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk),
        "cg_start": lambda: K.cg_start(d["z"], d["b"], d["r"], d["e"], d["f"], *args),
        "cg_first_direction": lambda: K.cg_first_direction(d["r"], d["e"], d["p"], d["sc"], h, w, blk),
        "residual_norm": lambda: K.residual_norm(d["z"], d["b"], d["r"], d["wx"], d["wy"], d["dg"], d["sc"], h, w,
                                                 blk),
        "vcycle": integ._vcycle,  # noqa: SLF001
    }
    return restart, iteration, kernels


def _profile(a) -> dict:
    """Child process (``TI_KERNEL_PROFILER=1``): device time per task over ``--iters`` iterations, per build."""
    from gpps import _taichi
    from gpps.pipeline.integration import Integrator

    ti = _taichi.init(a.device)
    from taichi.lang import impl

    prog = impl.get_runtime().prog
    out = {}
    for size in map(int, a.sizes.split(",")):
        mask, n, cam = problem(size)
        for build in a.builds.split(","):
            integ = Integrator(mask, cam, _config(build, a), device=a.device)
            integ.run(n)  # compile, fill the fields
            restart, iteration, _ = _cg(integ)
            restart()
            iteration()
            restart()
            ti.sync()
            ti.profiler.clear_kernel_profiler_info()
            for _ in range(a.iters):
                iteration()
            ti.sync()
            prog.sync_kernel_profiler()
            prog.update_kernel_profiler()
            tasks: dict = {}
            for rec in prog.get_kernel_profiler_records():
                m = TASK.match(rec.name)
                key = f"{m['kernel']}/{m['task']}" if m else rec.name
                tasks[key] = tasks.get(key, 0.0) + rec.kernel_time * 1e3 / a.iters  # ms -> us per iteration
            kernels: dict = {}
            for key, us in tasks.items():
                kernels[key.split("/")[0]] = kernels.get(key.split("/")[0], 0.0) + us
            out[f"{size}/{build}"] = {
                "iteration_us": sum(tasks.values()),
                "cg_kernels_us": sum(v for k, v in kernels.items() if k in CG_KERNELS),
                "vcycle_us": sum(v for k, v in kernels.items() if k in VCYCLE_KERNELS),
                "per_kernel_us": dict(sorted(kernels.items(), key=lambda kv: -kv[1])),
                "per_task_us": dict(sorted(tasks.items(), key=lambda kv: -kv[1])),
            }
            integ.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--sizes", default="256,1024")
    ap.add_argument("--builds", default=None, help="comma-separated cg_sums builds (default atomic,block on CUDA, "
                                                   "atomic on the CPU)")
    ap.add_argument("--weighting", default="normal")
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--tol", type=float, default=1e-5)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--inner", type=int, default=20)
    ap.add_argument("--no-profile", action="store_true", help="skip the kernel-profiler child (CUDA)")
    ap.add_argument("--profile-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    cuda = a.device.startswith("cuda")
    if a.builds is None:
        a.builds = "atomic,block" if cuda else "atomic"
    if a.profile_child:
        Path(a.profile_child).write_text(json.dumps(_profile(a)))
        return 0

    from gpps import _taichi
    from gpps.pipeline.integration import Integrator

    ti = _taichi.init(a.device)
    dev_name = a.device
    if cuda:
        try:
            import torch

            dev_name = torch.cuda.get_device_name(0)
        except ImportError:
            pass
    rows = []
    for size in map(int, a.sizes.split(",")):
        mask, n, cam = problem(size)
        ref_depth = None
        for build in a.builds.split(","):
            integ = Integrator(mask, cam, _config(build, a), device=a.device)
            res, row = run_row(integ, n, size, a.repeat, ref_depth, {"build": build})
            if ref_depth is None:
                ref_depth = res.depth
            restart, iteration, kernels = _cg(integ)

            def iterations(k, restart=restart, iteration=iteration):
                restart()
                for _ in range(k):
                    iteration()

            t_k = med(lambda: iterations(a.iters), ti.sync, a.repeat)
            t_0 = med(lambda: iterations(0), ti.sync, a.repeat)
            row["iteration_wall_ms"] = 1e3 * (t_k - t_0) / a.iters
            restart()
            row["kernel_wall_us"] = {k: 1e6 * med(fn, ti.sync, a.repeat, a.inner) for k, fn in kernels.items()}
            integ.close()
            rows.append(row)
            print(f"{size:5d} {build:6s} {row['mask_pixels']} px: {row['iterations']} it, run {row['run_ms']:.2f} ms "
                  f"(solve {row['solve_ms']:.2f}), iteration {row['iteration_wall_ms']:.3f} ms wall; per call us: "
                  + " ".join(f"{k} {v:.1f}" for k, v in row["kernel_wall_us"].items()), flush=True)
    device = None
    if cuda and not a.no_profile:
        with tempfile.TemporaryDirectory() as tmp:
            child = Path(tmp) / "profile.json"
            cmd = [sys.executable, __file__, "--device", a.device, "--sizes", a.sizes, "--builds", a.builds,
                   "--weighting", a.weighting, "--dtype", a.dtype, "--tol", str(a.tol), "--iters", str(a.iters),
                   "--profile-child", str(child)]
            subprocess.run(cmd, check=True, env={**os.environ, "TI_KERNEL_PROFILER": "1"})
            device = json.loads(child.read_text())
        for row in rows:
            p = device.get(f"{row['size']}/{row['build']}")
            row["device"] = p
            if p:
                top = ", ".join(f"{k} {v:.1f}" for k, v in list(p["per_task_us"].items())[:6])
                print(f"{row['size']:5d} {row['build']:6s} device us/iteration: {p['iteration_us']:.1f} (CG kernels "
                      f"{p['cg_kernels_us']:.1f}, V-cycle {p['vcycle_us']:.1f}); top tasks: {top}", flush=True)
    from gpps.io import save_json

    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"integration_pcg_sums_{a.device.replace(':', '')}.json"
    save_json(out, {"device": a.device, "device_name": dev_name, "scene": "make_scene('bumps', n, 'perspective')",
                    "weighting": a.weighting, "dtype": a.dtype, "tol": a.tol, "iters": a.iters, "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
