"""One material-search step: MaterialScorer (one batched launch) vs RON's per-candidate PixelSolver.run path.

Scene: a perspective Cook-Torrance sphere at DiLiGenT's crop size (166^2 by default), N directional lights
(golden-angle spiral), 16-bit images with 0.5 % noise; a sample of 2000 mask pixels (RON's
``material_samples``); candidates on RON's log grid over ``ks`` in [0.02, 3] and ``roughness`` in [0.03, 0.8]
(K = 9: 3 x 3, K = 25: 5 x 5, RON's first-round grid).  Solver: RON's fit config
(``SolverConfig()`` with ``starts=4, neighbour_radius=0, smoothness=0, warm_start=False``).

Per (N, K) it reports, as medians after a warm-up (compilation excluded), device-synchronised:

* ``pixel_solver_step_s``: the current path, what ``RON._fit_energy`` does for each of the K candidates
  (``set_material``; ``run(images, sample)``: upload of the whole frame, noise estimate, H x W launch,
  7 frame fetches; the trimmed energy), summed over the K candidates;
* ``scorer_upload_s``: ``MaterialScorer.upload`` (once per RON round: gather, noise, material-free terms);
* ``scorer_step_s``: ``step(K candidates)`` + ``fetch()`` (one launch, (K, P) residuals back, energies);
* ``speedup_step``: pixel_solver_step_s / scorer_step_s;
* ``max_rel_energy_diff``: the two paths' energies compared (0 on the CPU backend: same code).

JSON to perf/results/material_device_<device>.json (``--device cpu``: material_device_cpu.json).

Usage:  python perf/material_device.py [--device cpu] [--images 12 96] [--candidates 9 25]
        [--size 166] [--samples 2000] [--repeat 3] [--baseline-repeat 1]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from _common import RESULTS, device_label, timeit  # noqa: E402

from gpps._runtime import warp  # noqa: E402
from gpps.flows.synthetic import default_lights, render  # noqa: E402
from gpps.host.scenes import make_scene  # noqa: E402
from gpps.lights import DirectionalLights  # noqa: E402
from gpps.material import Material  # noqa: E402
from gpps.pipeline.material import MaterialScorer, trimmed_energy  # noqa: E402
from gpps.pipeline.solver import PixelSolver, SolverConfig  # noqa: E402

TRIM = 0.02
RANGES = {"ks": (0.02, 3.0), "roughness": (0.03, 0.8)}


def grid_candidates(mat: Material, k: int) -> list[Material]:
    """RON's first-round grid: sqrt(k) log-spaced values per parameter (k must be a square)."""
    g = int(round(np.sqrt(k)))
    if g * g != k:
        raise ValueError(f"candidates: expected a square number (a g x g grid), got {k}")
    axes = [np.exp(np.linspace(np.log(lo), np.log(hi), g)) for lo, hi in RANGES.values()]
    out = []
    for ks in axes[0]:
        for m in axes[1]:
            d = mat.to_dict()
            d["ks"], d["roughness"] = float(ks), float(m)
            out.append(Material.from_dict(d))
    return out


def sample_of(mask, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    idx = np.flatnonzero(mask.ravel())
    s = np.zeros(mask.size, bool)
    s[rng.choice(idx, min(n, idx.size), replace=False)] = True
    return s.reshape(mask.shape)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--images", type=int, nargs="*", default=[12, 96])
    ap.add_argument("--candidates", type=int, nargs="*", default=[9, 25])
    ap.add_argument("--size", type=int, default=166)
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--baseline-repeat", type=int, default=1)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    wp = warp()
    dev = a.device

    def sync():
        wp.synchronize_device(dev)

    cfg = replace(SolverConfig(), starts=4, neighbour_radius=0, smoothness=0.0, warm_start=False)
    mat = Material.default_for("cook-torrance")
    sc = make_scene("sphere", a.size, "perspective", albedo="texture")
    sample = sample_of(sc.mask, a.samples)
    p = int(sample.sum())
    rows = []
    for n in a.images:
        L = default_lights("directional", n, layout="spiral")
        img = render(sc, mat, L, bits=16, noise=0.005, device=dev)
        img = (img / np.asarray(L.intensities, np.float32)[:, None, None, :]).astype(np.float32)
        lights = DirectionalLights(L.directions)
        solver = PixelSolver(img.shape[:3], sc.camera, lights, mat, cfg, device=dev)
        scorer = MaterialScorer(img.shape[:3], sc.camera, lights, mat, cfg, max_samples=p,
                                max_candidates=max(a.candidates), trim=TRIM, device=dev)

        def per_candidate(cands):
            out = []
            for c in cands:
                solver.set_material(c)
                res = solver.run(img, sample)
                out.append(trimmed_energy(res["residual"][sample], TRIM))
            return np.array(out)

        # warm-up: compile both modules
        per_candidate([mat])
        scorer.upload(img, sample)
        scorer.step([mat])
        scorer.fetch()
        up = timeit(lambda: scorer.upload(img, sample), sync, warmup=1, repeat=a.repeat)
        for k in a.candidates:
            cands = grid_candidates(mat, k)
            ref = {}

            def baseline():
                ref["e"] = per_candidate(cands)

            base = timeit(baseline, sync, warmup=0, repeat=max(1, a.baseline_repeat))
            e_ref = ref["e"]
            scorer.upload(img, sample)
            box = {}

            def scored():
                scorer.step(cands)
                box["e"] = scorer.fetch()

            st = timeit(scored, sync, warmup=1, repeat=a.repeat)
            e = box["e"]
            rel = float(np.max(np.abs(e - e_ref) / np.maximum(np.abs(e_ref), 1e-300)))
            row = {
                "images": n, "candidates": k, "samples": p, "size": a.size,
                "pixel_solver_step_s": base["median_s"], "pixel_solver_runs": base["runs"],
                "pixel_solver_per_candidate_s": base["median_s"] / k,
                "scorer_upload_s": up["median_s"], "scorer_step_s": st["median_s"], "scorer_step_iqr_s": st["iqr_s"],
                "scorer_runs": st["runs"], "speedup_step": base["median_s"] / st["median_s"],
                "speedup_step_with_upload": base["median_s"] / (st["median_s"] + up["median_s"]),
                "max_rel_energy_diff": rel, "best_candidate": int(np.argmin(e)),
                "best": {"ks": cands[int(np.argmin(e))].ks, "roughness": cands[int(np.argmin(e))].roughness},
            }
            rows.append(row)
            print(json.dumps(row), flush=True)
        scorer.close()

    payload = {
        "script": "perf/material_device.py", "argv": sys.argv[1:], "device": dev, "device_name": device_label(dev),
        "host": platform.node(), "scene": f"sphere {a.size}^2 perspective, cook-torrance {mat.to_dict()}, "
                                          "spiral directional lights, 16-bit, noise 0.005, textured albedo",
        "solver": {"solver": cfg.solver, "starts": cfg.starts, "max_iters": cfg.max_iters},
        "trim": TRIM, "rows": rows,
    }
    out = Path(a.out) if a.out else RESULTS / f"material_device_{'cpu' if dev == 'cpu' else dev.replace(':', '')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(payload, indent=2) + "\n")
    print(out)


if __name__ == "__main__":
    main()
