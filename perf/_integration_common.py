"""What perf/integration_pcg_sums.py and perf/integration_fused.py share: the problem, a synchronised
median, and one integrator's timed runs as a result row."""

from __future__ import annotations

import re
import statistics
import time

import numpy as np

# a Taichi task's name in the kernel profiler: <kernel>_c<N>_<M>_kernel_<task>
TASK = re.compile(r"^(?P<kernel>.+?)_c\d+_\d+_kernel_(?P<task>\d+_\w+)$")


def problem(size: int):
    """The 256^2-style perspective bumps map: (mask, normals, camera)."""
    from gpps.host.scenes import make_scene

    sc = make_scene("bumps", size, "perspective")
    return sc.mask, sc.normals, sc.camera


def med(fn, sync, repeat, inner=1):
    """Median wall time (s) of ``inner`` calls of ``fn`` then ``sync``, after one warm-up call."""
    fn()
    sync()
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        sync()
        ts.append((time.perf_counter() - t0) / inner)
    return statistics.median(ts)


def run_row(integ, normals, size: int, repeat: int, ref_depth, label: dict):
    """One compile run, then ``repeat`` timed :meth:`Integrator.run` calls: ``(result, row)``; the row has the
    median run and solve times (ms), iterations, convergence and the depth's largest difference to
    ``ref_depth`` (the first variant's; itself when None)."""
    res = integ.run(normals)  # compile
    walls, solves = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = integ.run(normals)
        walls.append(time.perf_counter() - t0)
        solves.append(res.timings["solve"])
    m = res.mask
    ref = res.depth if ref_depth is None else ref_depth
    row = {"size": size, "mask_pixels": int(m.sum()), **label, "iterations": res.iterations,
           "converged": res.converged, "solver_residual": res.solver_residual,
           "depth_max_diff_to_first": float(np.max(np.abs(res.depth[m] - ref[m]))),
           "depth_range": float(np.ptp(res.depth[m])),
           "run_ms": 1e3 * statistics.median(walls), "solve_ms": 1e3 * statistics.median(solves)}
    return res, row
