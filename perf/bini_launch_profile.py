"""Where a device BiNI solve spends its time: per launch of the CG kernel, the host's done-flag read, and the
IRLS steps, on one DiLiGenT normal map (BiNI's defaults).

Each ``cg`` launch runs ``check_every`` gated Jacobi-PCG iterations (two parallel loops each); the host then
reads one done flag.  Reports the whole solve (median of ``--repeat``), the launch count, and a replay of
the same solve with a device synchronisation around each launch and each read, to split host from device
time.  Run it under ``nsys profile --stats=true`` for per-offload kernel times.

Usage:  python perf/bini_launch_profile.py FOLDER [--device cuda:0] [--repeat 3] [--out FILE]
(FOLDER: a BiNI-coded DiLiGenT map, e.g. ../shared/data/integration/diligent/bear)
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

from gpps._taichi import ti  # noqa: E402
from gpps.camera import Perspective  # noqa: E402
from gpps.pipeline.integration_bini import BilateralIntegrator  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    n, mask, K, _ = load(Path(a.folder))
    cam = Perspective(K)
    bi = BilateralIntegrator(mask, cam, device=a.device)
    walls = []
    for _ in range(a.repeat + 1):
        t = time.perf_counter()
        res = bi.run(n)
        walls.append(time.perf_counter() - t)
    # replay with synchronisation around every launch and read
    F = bi._F  # noqa: SLF001 - a profile of the stage's own loop
    kn = F["kernels"]
    cfg = bi.config
    bi.upload(n)
    last = (F["unroll"] - 1) % 3
    t_cg, t_read, t_begin, t_rew, launches = [], [], [], [], 0
    e_old = bi._state["e0"]  # noqa: SLF001
    for _it in range(cfg.max_iter):
        ti.sync()
        t = time.perf_counter()
        kn["begin"](bi.n)
        ti.sync()
        t_begin.append(time.perf_counter() - t)
        while True:
            t = time.perf_counter()
            kn["cg"](bi.n, cfg.cg_tol ** 2, cfg.cg_max_iter)
            ti.sync()
            t_cg.append(time.perf_counter() - t)
            launches += 1
            t = time.perf_counter()
            done = F["done"][last][0] != 0
            t_read.append(time.perf_counter() - t)
            if done:
                break
        t = time.perf_counter()
        kn["reweight"](bi.n, float(cfg.k))
        sc = F["sc"].to_numpy()
        t_rew.append(time.perf_counter() - t)
        e = float(sc[1])
        if abs(e - e_old) / e_old < cfg.tol:
            break
        e_old = e
    row = {"map": Path(a.folder).name, "pixels": int(mask.sum()), "device": a.device,
           "solve_s": statistics.median(walls[1:]), "outer": res.outer_iterations, "cg_iterations": res.cg_iterations,
           "cg_launches": launches, "unroll": F["unroll"],
           "cg_launch_s": {"median": statistics.median(t_cg), "sum": sum(t_cg)},
           "done_read_s": {"median": statistics.median(t_read), "sum": sum(t_read)},
           "begin_s": sum(t_begin), "reweight_and_scalars_s": sum(t_rew)}
    print(json.dumps(row, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(row, indent=1))
    bi.close()


if __name__ == "__main__":
    main()
