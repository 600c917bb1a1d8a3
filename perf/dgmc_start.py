"""LM from Lambertian vs DGMC starts (seed 4.1.9): iterations and MAEN on the highlight pixels.

Scenes: gpps.evaluation.make_case sphere and bumps, Blinn-Phong and Cook-Torrance
(Material.default_for), orthographic and perspective, 3 directional lights,
16-bit.  For each: the Lambertian least-squares normals (solve_normals,
solver="none"), DGMC starts from them (gpps.pipeline.dgmc.dgmc_start, default
DGMCConfig), then one PixelSolver with SolverConfig(solver="lm", warm_start=True,
starts=1) run twice, with init_normals = (a) the Lambertian normals and (b) the
DGMC normals.  Reported on the DGMC highlight pixels: MAEN of the starts, MAEN
after LM, median error after LM, fraction under 1 deg, and mean cost evaluations
(PixelSolver ``iterations``); the JSON also has the start MAEN of the nearest
boundary pixel alone (no curvature test) and the fraction of highlight pixels
where no candidate met 4.17-4.18 (nearest-pixel fallback).

Usage:  python perf/dgmc_start.py [--size 256] [--device cpu] [--out perf/results/dgmc_start_cpu.json]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import asdict, replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

from gpps.evaluation import make_case  # noqa: E402
from gpps.metrics import angular_error  # noqa: E402
from gpps.photometric import solve_normals  # noqa: E402
from gpps.pipeline.dgmc import DGMCConfig, dgmc_start  # noqa: E402
from gpps.pipeline.solver import PixelSolver, SolverConfig  # noqa: E402


def run(scene, size, camera, brdf, device, cfg: DGMCConfig, max_iters: int) -> dict:
    img, L, sc, mat = make_case(scene, size, camera, "directional", brdf, device=device)
    m = sc.mask
    ls = solve_normals(img, m, L, camera=sc.camera, material=mat, solver="none", device=device)
    t0 = time.perf_counter()
    dg = dgmc_start(img, m, ls.normals, lights=L, config=cfg)
    t_dgmc = time.perf_counter() - t0
    hm = dg.highlight
    solver = PixelSolver(img.shape[:3], sc.camera, L, mat,
                         SolverConfig(solver="lm", warm_start=True, starts=1, max_iters=max_iters), device=device)
    # ablation: the nearest boundary pixel alone (no curvature test, 4.17-4.18 skipped)
    near = dgmc_start(img, m, ls.normals, lights=L, config=replace(cfg, tolerance=0.0, widen_steps=0))
    row = {
        "scene": scene, "size": size, "camera": camera, "brdf": brdf,
        "mask_pixels": int(m.sum()), "highlight_pixels": int(hm.sum()), "regions": dg.highlights.n_regions,
        "dgmc_seconds": t_dgmc,
        "fallback_fraction": float(np.mean(np.isinf(dg.tolerance[hm]))) if hm.any() else 0.0,
        "mean_rank": float(dg.rank[hm].mean()) if hm.any() else 0.0,
        "start_maen_nearest_only": float(angular_error(near.normals, sc.normals, m)[hm].mean()),
    }
    for tag, init in (("lambertian", ls.normals), ("dgmc", dg.normals)):
        t0 = time.perf_counter()
        out = solver.solve(img, m, init_normals=init)
        dt = time.perf_counter() - t0
        e0 = angular_error(init, sc.normals, m)[hm]
        e = angular_error(out["normals"], sc.normals, m)
        eh = e[hm]
        row[tag] = {
            "start_maen": float(e0.mean()),
            "maen": float(eh.mean()),
            "median": float(np.median(eh)),
            "under_1deg": float(np.mean(eh < 1.0)),
            "mean_iterations": float(out["iterations"][hm].mean()),
            "maen_all_pixels": float(e[m].mean()),
            "seconds": dt,
        }
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--max-iters", type=int, default=50)
    ap.add_argument("--scenes", nargs="*", default=["sphere", "bumps"])
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    cfg = DGMCConfig()
    rows = []
    head = (f"{'scene':7s} {'camera':12s} {'brdf':14s} {'hl px':>6s} | {'start MAEN':>17s} | {'LM MAEN':>15s} | "
            f"{'LM median':>15s} | {'<1deg':>11s} | {'iterations':>13s}")
    print(head + "\n" + " " * 44 + "|   Lamb.    DGMC |  Lamb.   DGMC |  Lamb.   DGMC | Lamb. DGMC |  Lamb.   DGMC")
    for scene in a.scenes:
        for camera in ("orthographic", "perspective"):
            for brdf in ("blinn-phong", "cook-torrance"):
                r = run(scene, a.size, camera, brdf, a.device, cfg, a.max_iters)
                rows.append(r)
                la, dg = r["lambertian"], r["dgmc"]
                print(
                    f"{scene:7s} {camera:12s} {brdf:14s} {r['highlight_pixels']:6d} | {la['start_maen']:7.2f} {dg['start_maen']:7.2f} | "
                    f"{la['maen']:6.2f} {dg['maen']:6.2f} | {la['median']:6.2f} {dg['median']:6.2f} | "
                    f"{la['under_1deg']:5.2f} {dg['under_1deg']:4.2f} | {la['mean_iterations']:6.1f} {dg['mean_iterations']:6.1f}",
                    flush=True,
                )
    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"dgmc_start_{a.device.split(':')[0]}.json"
    from gpps.io import save_json

    save_json(out, {"size": a.size, "device": a.device, "lights": "directional x3", "max_iters": a.max_iters,
                    "solver": "lm, warm_start=True, starts=1", "dgmc_config": asdict(cfg), "rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
