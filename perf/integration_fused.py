"""The multigrid PCG launched fused (one Taichi launch an iteration) against per level (~13), and the host
time of the rest of :meth:`Integrator.run`.

``IntegratorConfig.launch`` picks how the PCG is launched (:mod:`gpps.kernels.poisson`): ``"per-level"``
calls cg_step, down per level, coarse_exact, up per level and cg_direction (13 Taichi launches an
iteration at 256^2, 6 levels; Taichi 1.7 spends 60-100 us of host time on each call), ``"fused"`` one
:func:`pcg_iteration` an iteration (and one :func:`pcg_start`).  On the scene of
``perf/reconstruct_synthetic.py`` (perspective bumps, ``make_scene("bumps", n)``, 43 234 mask pixels at 256^2)
with the pipeline's integrator settings (n_z^2 weighting, tol 1e-5, float32), per size and launch form:

* ``run_ms`` / ``solve_ms``: :meth:`Integrator.run` to tolerance, wall (median of ``--repeat`` after a
  warm-up) and its ``timings["solve"]``; iterations; the depth's largest difference to the first form's;
* ``iteration_wall_ms``: ``--iters`` PCG iterations queued without host reads after a restart from 0,
  minus the restart alone, per iteration, device-synchronised;
* ``iteration_host_ms``: the same without the final synchronisation: the host's time to issue an
  iteration (on CUDA the launches are asynchronous; on the CPU it equals the wall);
* ``device`` (CUDA, unless ``--no-profile``): Taichi's kernel profiler (CUDA events around every task, in
  a child process with ``TI_KERNEL_PROFILER=1``) over the same ``--iters`` iterations: device
  microseconds an iteration, summed over tasks, and the task count an iteration.

``host_parts_ms`` (per size, once): the host steps of one ``run`` besides the solve, each timed alone
(median of ``--repeat``): ``_check_normals``, ``pixel_gradients``, ``edge_system``, ``_upload_levels``
(``build_levels``, the coarsest level's dense pseudo-inverse, the uploads) and its pseudo-inverse alone,
``divergence_rhs``, ``normal_equation_residual``, and ``run`` of the same map with its levels kept (as for
uniform weights and a fixed mask) and rebuilt (as for a new map's n_z^2 weights, or after a
:class:`gpps.pipeline.integration_rounds.DeviceSystem` solve).

Usage:  python perf/integration_fused.py [--device cuda:0] [--sizes 256,1024] [--launches fused,per-level]
            [--iters 20] [--repeat 10] [--out FILE]
Writes ``--out`` (default perf/results/integration_fused_<device>.json).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from _integration_common import TASK, med, problem, run_row  # noqa: E402


def _config(launch: str, a):
    from gpps.pipeline.integration import IntegratorConfig

    return IntegratorConfig(launch=launch, weighting=a.weighting, dtype=a.dtype, tol=a.tol)


def _loop(integ):
    """``iterations(k)``: restart the PCG from 0 (its start launch(es)) and queue k iterations, no reads."""
    d = integ._dev  # noqa: SLF001 - a profile of the stage's own loop
    start, iteration = integ._pcg_launches(integ._block_sums())  # noqa: SLF001

    def iterations(k):
        d["z"].fill(0)
        start()
        for _ in range(k):
            iteration()

    return iterations


def _host_med(fn, sync, repeat):
    """Median host time of ``fn`` alone (synchronised before, not after; then synchronised)."""
    ts = []
    for _ in range(repeat):
        sync()
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        sync()
    return statistics.median(ts)


def _host_parts(integ, n, a, sync) -> dict:
    """The host steps of one :meth:`Integrator.run` besides the solve, each timed alone (ms)."""
    from gpps.host import poisson as P

    cfg, cam = integ.config, integ.camera
    nn, valid, _ = integ._check_normals(n)  # noqa: SLF001
    gj, gi, nzj, nzi = P.pixel_gradients(nn, valid, cam, cfg.min_nz)
    scale = float(np.mean(nzj[valid] ** 2))
    cj, ci = (nzj ** 2 / scale, nzi ** 2 / scale) if cfg.weighting == "normal" else (None, None)
    wx, wy, tx, ty = P.edge_system(valid, gj, gi, cj, ci)
    b = P.divergence_rhs(wx, wy, tx, ty)
    u = np.where(valid, integ._dev["z"].to_numpy().astype(np.float64), 0.0)  # noqa: SLF001
    levels = P.build_levels(wx, wy, cfg.coarsest, alpha=1.0)
    lx, ly = levels[-1]
    dgc = P.diagonal(lx, ly)
    Ac = P.laplacian(lx, ly, dgc > 0)[0].toarray()

    def upload_levels():
        integ._levels_key = None  # noqa: SLF001
        integ._upload_levels(valid, wx, wy)  # noqa: SLF001

    def run_rebuilt():
        integ._levels_key = None  # noqa: SLF001 - as after a new map's weights (or a DeviceSystem solve)
        integ.run(n)

    parts = {
        "check_normals": lambda: integ._check_normals(n),  # noqa: SLF001
        "pixel_gradients": lambda: P.pixel_gradients(nn, valid, cam, cfg.min_nz),
        "edge_system": lambda: P.edge_system(valid, gj, gi, cj, ci),
        "upload_levels": upload_levels,
        "coarsest_pinv": lambda: np.linalg.pinv(Ac, hermitian=True),
        "divergence_rhs": lambda: P.divergence_rhs(wx, wy, tx, ty),
        "normal_equation_residual": lambda: P.normal_equation_residual(u, wx, wy, b),
        "run_same_map": lambda: integ.run(n),
        "run_levels_rebuilt": run_rebuilt,
    }
    out = {k: 1e3 * _host_med(fn, sync, a.repeat) for k, fn in parts.items()}
    out["coarsest_cells"] = int(Ac.shape[0])
    return out


def _profile(a) -> dict:
    """Child process (``TI_KERNEL_PROFILER=1``): device time an iteration over ``--iters`` iterations."""
    from gpps import _taichi
    from gpps.pipeline.integration import Integrator

    ti = _taichi.init(a.device)
    from taichi.lang import impl

    prog = impl.get_runtime().prog
    out = {}
    for size in map(int, a.sizes.split(",")):
        mask, n, cam = problem(size)
        for launch in a.launches.split(","):
            integ = Integrator(mask, cam, _config(launch, a), device=a.device)
            integ.run(n)  # compile, fill the fields
            iterations = _loop(integ)
            iterations(1)
            ti.sync()
            iterations(0)
            ti.sync()
            ti.profiler.clear_kernel_profiler_info()
            iterations(a.iters)
            ti.sync()
            prog.sync_kernel_profiler()
            prog.update_kernel_profiler()
            recs = prog.get_kernel_profiler_records()
            ti.profiler.clear_kernel_profiler_info()
            iterations(0)
            ti.sync()
            prog.sync_kernel_profiler()
            prog.update_kernel_profiler()
            recs0 = prog.get_kernel_profiler_records()
            total = sum(r.kernel_time for r in recs) - sum(r.kernel_time for r in recs0)  # ms
            kernels: dict = {}
            for sign, rs in ((1.0, recs), (-1.0, recs0)):
                for rec in rs:
                    m = TASK.match(rec.name)
                    key = m["kernel"] if m else rec.name
                    kernels[key] = kernels.get(key, 0.0) + sign * rec.kernel_time * 1e3 / a.iters
            out[f"{size}/{launch}"] = {"iteration_us": total * 1e3 / a.iters,
                                       "tasks_per_iteration": (len(recs) - len(recs0)) / a.iters,
                                       "per_kernel_us": dict(sorted(kernels.items(), key=lambda kv: -kv[1]))}
            integ.close()
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--sizes", default="256,1024")
    ap.add_argument("--launches", default="fused,per-level")
    ap.add_argument("--weighting", default="normal")
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--tol", type=float, default=1e-5)
    ap.add_argument("--iters", type=int, default=20)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--no-profile", action="store_true", help="skip the kernel-profiler child (CUDA)")
    ap.add_argument("--no-host-parts", action="store_true", help="skip the host steps of run")
    ap.add_argument("--profile-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    cuda = a.device.startswith("cuda")
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
    rows, host_parts = [], {}
    for size in map(int, a.sizes.split(",")):
        mask, n, cam = problem(size)
        ref_depth = None
        for launch in a.launches.split(","):
            integ = Integrator(mask, cam, _config(launch, a), device=a.device)
            res, row = run_row(integ, n, size, a.repeat, ref_depth, {"launch": launch})
            if ref_depth is None:
                ref_depth = res.depth
            iterations = _loop(integ)
            t_k = med(lambda: iterations(a.iters), ti.sync, a.repeat)
            t_0 = med(lambda: iterations(0), ti.sync, a.repeat)
            row["iteration_wall_ms"] = 1e3 * (t_k - t_0) / a.iters
            h_k = _host_med(lambda: iterations(a.iters), ti.sync, a.repeat)
            h_0 = _host_med(lambda: iterations(0), ti.sync, a.repeat)
            row["iteration_host_ms"] = 1e3 * (h_k - h_0) / a.iters
            if not a.no_host_parts and size not in host_parts:
                host_parts[size] = _host_parts(integ, n, a, ti.sync)
                print(f"{size:5d} host ms: " + ", ".join(f"{k} {v:.3f}" for k, v in host_parts[size].items()),
                      flush=True)
            integ.close()
            rows.append(row)
            print(f"{size:5d} {launch:9s} {row['mask_pixels']} px: {row['iterations']} it, run {row['run_ms']:.2f} ms "
                  f"(solve {row['solve_ms']:.2f}), iteration {row['iteration_wall_ms']:.3f} ms wall, "
                  f"{row['iteration_host_ms']:.3f} ms host; depth diff {row['depth_max_diff_to_first']:.2e}",
                  flush=True)
    if cuda and not a.no_profile:
        with tempfile.TemporaryDirectory() as tmp:
            child = Path(tmp) / "profile.json"
            cmd = [sys.executable, __file__, "--device", a.device, "--sizes", a.sizes, "--launches", a.launches,
                   "--weighting", a.weighting, "--dtype", a.dtype, "--tol", str(a.tol), "--iters", str(a.iters),
                   "--profile-child", str(child)]
            subprocess.run(cmd, check=True, env={**os.environ, "TI_KERNEL_PROFILER": "1"})
            device = json.loads(child.read_text())
        for row in rows:
            p = device.get(f"{row['size']}/{row['launch']}")
            row["device"] = p
            if p:
                print(f"{row['size']:5d} {row['launch']:9s} device us/iteration: {p['iteration_us']:.1f} "
                      f"({p['tasks_per_iteration']:.0f} tasks)", flush=True)
    from gpps.io import save_json

    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"integration_fused_{a.device.replace(':', '')}.json"
    save_json(out, {"device": a.device, "device_name": dev_name, "scene": "make_scene('bumps', n, 'perspective')",
                    "weighting": a.weighting, "dtype": a.dtype, "tol": a.tol, "iters": a.iters, "rows": rows,
                    "host_parts_ms": {str(k): v for k, v in host_parts.items()}})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
