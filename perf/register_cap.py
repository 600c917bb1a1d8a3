"""Does capping the registers of the cold whole-image solve pay on the GPU?  (issue 20, CUDA only)

The starts-parallel cold solve (:mod:`gpps.kernels.solve_split`, RON's first full-frame solves: ~8.4 ms of the
256^2 x 3 reconstruction's 43 ms of GPU time) runs H x W x ``starts`` threads at 216 registers a thread: 8 warps
an SM (12.5 % theoretical occupancy), ~10 waves at 256^2 with 10 starts.  A throughput-bound launch like this one
may run faster with more threads resident (a register cap, ``cuda_max_registers`` module option of Warp 1.19), or
slower when the cap spills to local memory.  This measures it: for each cap the split module is rebuilt, a
:class:`gpps.pipeline.solver.PixelSolver` solves the issue's 256^2 frame (perspective Cook-Torrance bumps, 3
directional lights, the true material, the default config: cold, 10 starts) ``--repeat`` times after a warm-up,
device-synchronised, and the normals are compared with the uncapped build's.

Usage:  python perf/register_cap.py [--size 256] [--caps 0 168 128 96] [--repeat 10] [--out FILE]  (0: no cap)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import warp as wp  # noqa: E402

import gpps  # noqa: E402
from gpps.kernels.solve import module_name  # noqa: E402
from gpps.pipeline.solver import PixelSolver, SolverConfig  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--caps", type=int, nargs="+", default=[0, 168, 128, 96])
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    dev = a.device
    sc = gpps.make_scene("bumps", a.size, "perspective")
    L = gpps.default_lights("directional", 3, layout="ring")
    true = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    img = gpps.render(sc, true, L, bits=16, device=dev) / L.intensities[:, None, None, :]
    lu = gpps.DirectionalLights(L.directions)
    cfg = SolverConfig()
    module = wp.get_module(module_name(cfg.solver, "cook-torrance", cfg.robust if cfg.irls_rounds > 0 else "none")
                           + "_split")
    rows, ref = [], None
    for cap in a.caps:
        module.options.pop("cuda_max_registers", None)
        if cap > 0:
            module.options["cuda_max_registers"] = int(cap)
        module.mark_modified()
        solver = PixelSolver(img.shape[:3], sc.camera, lu, true, cfg, device=dev)
        t0 = time.perf_counter()
        solver.upload(img, sc.mask)
        solver.step()
        wp.synchronize_device(dev)
        first = time.perf_counter() - t0
        times = []
        for _ in range(a.repeat):
            wp.synchronize_device(dev)
            t = time.perf_counter()
            solver.step()
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t)
        out = solver.fetch(("normals", "iterations"))
        n = out["normals"][sc.mask].astype(np.float64)
        if ref is None:
            ref = n
        ang = np.degrees(np.arctan2(np.linalg.norm(np.cross(n, ref), axis=-1), np.sum(n * ref, -1)))
        maen = float(gpps.normal_errors(out["normals"], sc.normals, sc.mask)["mean"])
        row = {"cap": cap or None, "first_s": first, "step_ms_median": 1e3 * float(np.median(times)),
               "step_ms_all": [1e3 * x for x in times], "maen_deg": maen, "max_angle_to_uncapped_deg": float(ang.max()),
               "split_starts": bool(solver._uses_split())}
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "step_ms_all"}), flush=True)
        solver.close()
    payload = {"device": dev, "device_name": wp.get_device(dev).name, "size": a.size, "starts": cfg.starts,
               "module": module.name, "rows": rows}
    if a.out:
        Path(a.out).write_text(json.dumps(payload, indent=1))


if __name__ == "__main__":
    main()
