"""MaterialScorer: one thread a (candidate, pixel) solve ("pixels") against one 32-lane block a solve with the
lights split over the lanes ("lights"), by image count: where the lights-parallel build pays off.

Scene: a perspective Cook-Torrance sphere (166^2, DiLiGenT's crop size), N directional lights (spiral), 16-bit
images with 0.5 % noise, textured albedo; RON's sample size for N images (``material_observations`` = 24000
observations: 2000 pixels up to 12 images, at least 500); solver: RON's fit config with the DiLiGenT settings
gpps uses above 6 images (Cauchy IRLS, 3 rounds, shadow threshold 0.02, 4 starts).  Per N and build: a cold
step of the first-round grid (K = 25) and a warm step of 4 candidates (one start from the true normals, as
RON's later fits), medians after a warm-up, device-synchronised, and the energies' largest relative
difference between the builds.

Writes ``perf/results/material_lanes_<device>.json`` (or ``--out``).

Usage:  python perf/material_lanes.py [--device cuda:0] [--images 3 8 12 16 24 48 96] [--repeat 5]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from _common import RESULTS, device_label, timeit  # noqa: E402
from material_device import grid_candidates, sample_of  # noqa: E402

from gpps._runtime import warp  # noqa: E402
from gpps.flows.synthetic import default_lights, render  # noqa: E402
from gpps.host.scenes import make_scene  # noqa: E402
from gpps.lights import DirectionalLights  # noqa: E402
from gpps.material import Material  # noqa: E402
from gpps.pipeline.material import MaterialScorer  # noqa: E402
from gpps.pipeline.solver import SolverConfig  # noqa: E402

TRIM = 0.02


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--images", type=int, nargs="*", default=[3, 8, 12, 16, 24, 48, 96])
    ap.add_argument("--size", type=int, default=166)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp = warp()
    dev = a.device

    def sync():
        wp.synchronize_device(dev)

    mat = Material.default_for("cook-torrance")
    sc = make_scene("sphere", a.size, "perspective", albedo="texture")
    rows = []
    for n in a.images:
        robust = dict(robust="cauchy", shadow_threshold=0.02) if n > 6 else {}
        cfg = replace(SolverConfig(**robust), starts=4, neighbour_radius=0, smoothness=0.0, warm_start=False)
        p_want = int(np.clip(24000 // n, 500, 2000))
        sample = sample_of(sc.mask, p_want)
        p = int(sample.sum())
        L = default_lights("directional", n, layout="ring" if n <= 4 else "spiral")
        img = render(sc, mat, L, bits=16, noise=0.005, device=dev)
        img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
        lights = DirectionalLights(L.directions)
        grid = grid_candidates(mat, 25)
        warm_cands = grid_candidates(mat, 4)
        res = {}
        for par in ("pixels", "lights"):
            sc_ = MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=p, max_candidates=25,
                                 trim=TRIM, parallel=par, device=dev)
            sc_.upload(img, sample)
            sc_.set_start(sc.normals[sample].astype(np.float32))
            box = {}

            def cold():
                sc_.step(grid)
                box["cold"] = sc_.fetch()

            def warm():
                sc_.step(warm_cands, warm=True)
                box["warm"] = sc_.fetch()

            tc = timeit(cold, sync, warmup=1, repeat=a.repeat)
            tw = timeit(warm, sync, warmup=1, repeat=a.repeat)
            res[par] = {"cold_s": tc["median_s"], "warm_s": tw["median_s"], "cold_e": box["cold"], "warm_e": box["warm"]}
            sc_.close()
        rel = max(float(np.max(np.abs(res["lights"][k] - res["pixels"][k]) / np.maximum(res["pixels"][k], 1e-300)))
                  for k in ("cold_e", "warm_e"))
        row = {"images": n, "samples": p, "robust": cfg.robust,
               "pixels_cold_s": res["pixels"]["cold_s"], "lights_cold_s": res["lights"]["cold_s"],
               "pixels_warm_s": res["pixels"]["warm_s"], "lights_warm_s": res["lights"]["warm_s"],
               "speedup_cold": res["pixels"]["cold_s"] / res["lights"]["cold_s"],
               "speedup_warm": res["pixels"]["warm_s"] / res["lights"]["warm_s"],
               "max_rel_energy_diff": rel,
               "best_same": bool(np.argmin(res["pixels"]["cold_e"]) == np.argmin(res["lights"]["cold_e"]))}
        rows.append(row)
        print(json.dumps(row), flush=True)
    payload = {"script": "perf/material_lanes.py", "argv": sys.argv[1:], "device": dev,
               "device_name": device_label(dev),
               "scene": f"sphere {a.size}^2 perspective, cook-torrance {mat.to_dict()}, spiral directional lights, "
                        "16-bit, noise 0.005, textured albedo", "rows": rows}
    out = Path(a.out) if a.out else RESULTS / f"material_lanes_{device_label(dev)}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(payload, indent=2) + "\n")
    print(out)


if __name__ == "__main__":
    main()
