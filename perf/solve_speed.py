"""Per-pixel solve time of each solver at 256^2, 512^2, 1024^2 (sphere, Blinn-Phong, 3 directional lights).

Times one PixelSolver.step() + device synchronise (compilation and upload excluded,
one warm-up solve first); reports seconds, microseconds per masked pixel and the
mean number of cost evaluations.  JSON to perf/results/solve_speed_<device>.json.

Usage:  python perf/solve_speed.py [--device cpu|cuda:0] [--sizes 256 512 1024] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))



def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="*", default=[256, 512, 1024])
    ap.add_argument("--solvers", nargs="*", default=["none", "lm", "dogleg", "bfgs"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    from synthetic_calibrated import make_case

    from gpps._runtime import warp
    from gpps.io import save_json
    from gpps.host.metrics import normal_errors
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    wp = warp()
    rows = []
    for size in a.sizes:
        img, L, sc, mat = make_case("sphere", size, "perspective", "directional", "blinn-phong", device=a.device)
        npx = int(sc.mask.sum())
        for solver in a.solvers:
            ps = PixelSolver(img.shape[:3], sc.camera, L, mat, SolverConfig(solver=solver), device=a.device)
            ps.upload(img, sc.mask)
            ps.step()
            wp.synchronize_device(ps.device)
            times = []
            for _ in range(max(1, a.repeat)):
                t = time.perf_counter()
                ps.step()
                wp.synchronize_device(ps.device)
                times.append(time.perf_counter() - t)
            out = ps.fetch()
            best = min(times)
            row = {
                "size": size,
                "solver": solver,
                "pixels": npx,
                "seconds": best,
                "us_per_pixel": 1e6 * best / npx,
                "mean_evaluations": float(out["iterations"][sc.mask].mean()),
                "maen": normal_errors(out["normals"], sc.normals, sc.mask)["mean"],
            }
            rows.append(row)
            print(f"{size:5d}^2 {solver:7s} {best:8.3f} s  {row['us_per_pixel']:8.2f} us/px  evals {row['mean_evaluations']:6.1f}  MAEN {row['maen']:.3f}", flush=True)
    path = Path(a.out) if a.out else ROOT / "perf" / "results" / f"solve_speed_{a.device.split(':')[0]}.json"
    save_json(path, {"device": a.device, "scene": "sphere perspective, blinn-phong, 3 directional lights, 16-bit", "config": "SolverConfig() defaults (10 starts)", "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
