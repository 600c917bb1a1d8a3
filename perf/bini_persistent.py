"""BiNI's two device launches side by side on the DiLiGenT maps: the per-phase tasks against one persistent
task an IRLS iteration (grid barriers between its phases), at several blocks per multiprocessor.

For each map (BiNI's defaults, the map's K) and each launch: the stage's own split (upload, solve, fetch; the
solve is the device IRLS with one host read per iteration, device-synchronised by that read), the IRLS and CG
iteration counts (the same for every launch: a check), the CG time per iteration (solve / CG iterations) and
the whole ``integrate_normals(bilateral=True)`` call (checks, coefficients, the stage, the depth and its
scale) for the default launch.  Times are medians of ``--repeat`` runs after one warm-up run.

Usage:  python perf/bini_persistent.py [--data DIR] [--objects bear,...] [--bps 1,2,4] [--repeat 3] [--out FILE]
(DIR holds integration/diligent/<object>/ as ../shared/data does).  Writes perf/results/bini_persistent_<dev>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from integration_diligent import load  # noqa: E402

OBJECTS = ("bear", "buddha", "cow", "goblet", "pot1", "pot2")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.environ.get("GPPS_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--objects", default=",".join(OBJECTS))
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--bps", default="1,2,4", help="blocks per multiprocessor of the persistent launch")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    from gpps import _taichi
    from gpps.camera import Perspective
    from gpps.flows.integrate import integrate_normals
    from gpps.pipeline.integration_bini import BilateralIntegrator, BiniConfig

    _taichi.init(a.device)
    variants = [("tasks", BiniConfig(launch="tasks"))]
    for b in a.bps.split(","):
        variants.append((f"persistent_bps{int(b)}", BiniConfig(launch="persistent", blocks_per_sm=int(b))))
    rows = []
    for name in a.objects.split(","):
        n, mask, K, gt = load(Path(a.data) / "integration" / "diligent" / name)
        cam = Perspective(K)
        row = {"object": name, "pixels": int(mask.sum())}
        for label, cfg in variants:
            with BilateralIntegrator(mask, cam, cfg, device=a.device) as bi:
                res = bi.run(n)  # warm-up (compilation)
                tims = []
                for _ in range(a.repeat):
                    res = bi.run(n)
                    tims.append(res.timings)
                grid = list(bi._grid()) if label != "tasks" else None
            solve = statistics.median(t["solve"] for t in tims)
            row[label] = {"solve_s": solve, "upload_s": statistics.median(t["upload"] for t in tims),
                          "fetch_s": statistics.median(t["fetch"] for t in tims), "outer": res.outer_iterations,
                          "cg": res.cg_iterations, "us_per_cg_iteration": 1e6 * solve / max(res.cg_iterations, 1),
                          "grid": grid}
            print(f"{name:7s} {label:18s} solve {solve * 1e3:8.2f} ms  {row[label]['us_per_cg_iteration']:6.2f} us/CG it"
                  f"  ({res.outer_iterations} / {res.cg_iterations})  grid {grid}", flush=True)
        ts = []
        integrate_normals(n, mask, camera=cam, bilateral=True, device=a.device)
        for _ in range(a.repeat):
            t = time.perf_counter()
            integrate_normals(n, mask, camera=cam, bilateral=True, device=a.device)
            ts.append(time.perf_counter() - t)
        row["integrate_normals_s"] = statistics.median(ts)
        print(f"{name:7s} integrate_normals(bilateral=True) {row['integrate_normals_s'] * 1e3:8.2f} ms", flush=True)
        rows.append(row)
    out = {"device": a.device, "repeat": a.repeat, "rows": rows}
    try:
        import warp as wp
        out["device_name"] = wp.get_device(a.device).name
    except Exception:  # noqa: BLE001
        pass
    path = Path(a.out) if a.out else ROOT / "perf" / "results" / f"bini_persistent_{a.device.replace(':', '')}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))
    print("wrote", path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
