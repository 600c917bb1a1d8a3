"""Speed of the Poisson integrator: Taichi multigrid (cold and warm-started) vs scipy DCT.

A smooth random surface on a full square (so the DCT solver applies), float32,
tolerance 1e-5 on the relative residual.  Median of several runs after a
warm-up.  ``warm`` integrates a slightly changed normal map starting from the
previous depth (the streaming case).  On CUDA, times include the host upload
of the normals and download of the depth (the numpy API); the GPU-resident
path avoids both.

Usage: python perf/integration_speed.py [--device cpu|cuda:0] [--sizes 512,1024] [--repeat 5]
Writes perf/results/integration_speed_<device>.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))


def surface_normals(n: int, phase: float = 0.0) -> np.ndarray:
    y, x = np.mgrid[0:n, 0:n] / n
    hx = 0.3 * 2 * np.pi * np.cos(2 * np.pi * (x + phase)) * np.cos(3 * np.pi * y)
    hy = -0.3 * 3 * np.pi * np.sin(2 * np.pi * (x + phase)) * np.sin(3 * np.pi * y)
    nrm = np.stack([-hx, hy, np.ones_like(hx)], -1)  # rows go down: d/dy = -d/di
    return nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="512,1024")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--tol", type=float, default=1e-5)
    args = ap.parse_args(argv)

    from gpps.camera import Orthographic
    from gpps.pipeline.integration import Integrator, IntegratorConfig

    rows = []
    print(f"{'size':>6s} {'solver':14s} {'median ms':>10s} {'solve ms':>9s} {'iters':>6s} {'residual':>9s}")
    for n in map(int, args.sizes.split(",")):
        mask = np.ones((n, n), bool)
        cam = Orthographic(1.0 / n)
        frames = [surface_normals(n, 0.002 * k) for k in range(args.repeat + 2)]
        runs = {}
        for name, cfg in (("multigrid", IntegratorConfig(tol=args.tol)), ("dct (scipy)", IntegratorConfig(solver="dct"))):
            integ = Integrator(mask, cam, cfg, device=args.device)
            integ.run(frames[0])  # warm-up (compilation, allocation)
            tot, sol, its, res = [], [], [], []
            for f in frames[1:-1]:
                t0 = time.perf_counter()
                r = integ.run(f)
                tot.append(time.perf_counter() - t0)
                sol.append(r.timings["solve"] + r.timings.get("rhs", 0))
                its.append(r.iterations)
                res.append(r.solver_residual)
            runs[name] = (tot, sol, its, res)
            if name == "multigrid":
                prev = integ.run(frames[0]).depth
                wt, ws, wi, wr = [], [], [], []
                for f in frames[1:-1]:
                    t0 = time.perf_counter()
                    r = integ.run(f, warm_start=prev)
                    wt.append(time.perf_counter() - t0)
                    ws.append(r.timings["solve"] + r.timings.get("rhs", 0))
                    wi.append(r.iterations)
                    wr.append(r.solver_residual)
                    prev = r.depth
                runs["multigrid warm"] = (wt, ws, wi, wr)
            integ.close()
        for name, (tot, sol, its, res) in runs.items():
            row = dict(size=n, solver=name, median_total_ms=1e3 * statistics.median(tot),
                       median_solve_ms=1e3 * statistics.median(sol), iterations=int(statistics.median(its)),
                       residual=float(statistics.median(res)), repeat=len(tot))
            rows.append(row)
            print(f"{n:6d} {name:14s} {row['median_total_ms']:10.1f} {row['median_solve_ms']:9.1f} "
                  f"{row['iterations']:6d} {row['residual']:9.1e}")
    from gpps.io import save_json

    out = ROOT / "perf" / "results" / f"integration_speed_{args.device.replace(':', '')}.json"
    save_json(out, {"device": args.device, "tol": args.tol, "dtype": "float32", "cpu_count": os.cpu_count(),
                    "rows": rows,
                    "note": "solve = rhs on device + solver (incl. host<->device copies of the numpy API); "
                            "total adds input checks, gradients on host and component alignment"})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
