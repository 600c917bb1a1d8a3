"""LM from Lambertian vs DGMC starts (seed 4.1.9): iterations and MAEN on the highlight pixels.

Four ways to solve the highlight pixels, each reported by its mean cost
evaluations per highlight pixel and its MAEN there:

* ``lambertian``: one LM start from the least-squares (Woodham) normal;
* ``dgmc``: one LM start from :func:`dgmc_start` (the seed's rule, 4.16-4.18,
  sources on the region's outer boundary, least-squares normals);
* ``front``: :func:`propagate_front`: the same rule with the boundary moved
  inward ring by ring, each pixel started from a solved neighbour's normal;
  the sources outside the highlights are solved with the pipeline's default
  multi-start (``SolverConfig()``, 10 starts), as RON does;
* ``multistart``: the pipeline's default multi-start without DGMC (10 starts).

Scenes: cases.make_case sphere and bumps, Blinn-Phong and Cook-Torrance
(Material.default_for), orthographic and perspective, 3 directional lights,
16-bit.  For each: the Lambertian least-squares normals (solve_normals,
solver="none"), DGMC starts from them (gpps.host.dgmc.dgmc_start, default
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
sys.path.insert(0, str(ROOT / "tests"))  # tests/cases.py: the evaluation cases shared with the tests
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

from cases import make_case  # noqa: E402
from gpps.host.metrics import angular_error  # noqa: E402
from gpps.flows.photometric import solve_normals  # noqa: E402
from gpps.host.dgmc import DGMCConfig, dgmc_start  # noqa: E402
from gpps.pipeline.front import propagate_front  # noqa: E402
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
    # the pipeline's multi-start (no DGMC): its non-highlight pixels are the front's sources
    multi = PixelSolver(img.shape[:3], sc.camera, L, mat, SolverConfig(max_iters=max_iters), device=device)
    t0 = time.perf_counter()
    ms = multi.run(img, m)
    t_ms = time.perf_counter() - t0
    t0 = time.perf_counter()
    fr = propagate_front(solver, img, m, hm, ms, gaussian=dg.gaussian, mean=dg.mean, config=cfg, keep_better=False)
    t_fr = time.perf_counter() - t0
    row["front_rings"] = fr.n_rings
    row["front_unreached"] = int(np.sum(fr.ring < 0))
    for tag, nrm, its, dt, st in (("front", fr.normals, fr.iterations, t_fr, None),
                                  ("multistart", ms["normals"], ms["iterations"], t_ms, None)):
        e = angular_error(nrm, sc.normals, m)
        eh = e[hm]
        row[tag] = {"start_maen": st, "maen": float(eh.mean()), "median": float(np.median(eh)),
                    "under_1deg": float(np.mean(eh < 1.0)), "mean_iterations": float(its[hm].mean()),
                    "maen_all_pixels": float(e[m].mean()), "seconds": dt}
    for tag, init in (("lambertian", ls.normals), ("dgmc", dg.normals)):
        t0 = time.perf_counter()
        out = solver.run(img, m, init_normals=init)
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
    tags = ("lambertian", "dgmc", "front", "multistart")
    head = (f"{'scene':7s} {'camera':12s} {'brdf':14s} {'hl px':>6s} | {'MAEN on highlight pixels (deg)':>31s} | "
            f"{'<1deg':>23s} | {'evaluations per highlight pixel':>31s}")
    sub = " ".join(f"{t[:7]:>7s}" for t in tags)
    print(head + "\n" + " " * 44 + f"| {sub} | {' '.join(f'{t[:5]:>5s}' for t in tags)} | {sub}")
    for scene in a.scenes:
        for camera in ("orthographic", "perspective"):
            for brdf in ("blinn-phong", "cook-torrance"):
                r = run(scene, a.size, camera, brdf, a.device, cfg, a.max_iters)
                rows.append(r)
                print(
                    f"{scene:7s} {camera:12s} {brdf:14s} {r['highlight_pixels']:6d} | "
                    + " ".join(f"{r[t]['maen']:7.3f}" for t in tags) + " | "
                    + " ".join(f"{r[t]['under_1deg']:5.3f}" for t in tags) + " | "
                    + " ".join(f"{r[t]['mean_iterations']:7.1f}" for t in tags),
                    flush=True,
                )
    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"dgmc_start_{a.device.split(':')[0]}.json"
    from gpps.io import save_json

    save_json(out, {"size": a.size, "device": a.device, "lights": "directional x3", "max_iters": a.max_iters,
                    "solver": "lm, warm_start=True, starts=1 (lambertian, dgmc, front); SolverConfig() 10 starts (multistart)", "dgmc_config": asdict(cfg), "rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
