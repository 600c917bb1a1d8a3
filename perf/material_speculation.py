"""Does RON's Nelder-Mead gain from scoring ahead?  Interleaved warm reconstructions of issue 20's synthetic
case (``perf/_common.reconstruct_case``) with the look-ahead RON picks (``RON._speculate``: a step's points
in one batch on CUDA) and without (one point at a time), in alternation on one machine (the host's speed
drifts between runs), reporting the median whole call, material stage and scoring launches of each.

``perf/results/material_speculation_256x3_H100.json`` is this script's first version, run on the tree at
fbc30f6, when RON could also score two steps ahead ("chosen" there) against one step ("one_step"): 56 against
44 ms of material stage on the H100, so two steps ahead was removed.

Usage:  python perf/material_speculation.py [--size 256] [--images 3] [--device cuda:0] [--pairs 8] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))

from _common import reconstruct_case  # noqa: E402

from gpps.flows import ron as ron_mod  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--pairs", type=int, default=8)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    call = reconstruct_case(a.size, a.images, a.device)
    chosen = ron_mod.RON._speculate
    launches = [0]
    score = ron_mod.RON._score

    def counted(self, *args, **kw):
        launches[0] += 1
        return score(self, *args, **kw)

    ron_mod.RON._score = counted
    modes = {"chosen": chosen, "none": lambda self: 0}
    for m in modes.values():  # (cold compile and one warm call each)
        ron_mod.RON._speculate = m
        call()
        call()
    rows = {k: {"wall_s": [], "material_s": [], "launches": [], "maen": []} for k in modes}
    for _ in range(a.pairs):
        for k, m in modes.items():
            ron_mod.RON._speculate = m
            launches[0] = 0
            t = time.perf_counter()
            rec, maen = call()
            rows[k]["wall_s"].append(time.perf_counter() - t)
            rows[k]["material_s"].append(rec.timings["material"])
            rows[k]["launches"].append(launches[0])
            rows[k]["maen"].append(maen())
    ron_mod.RON._speculate = chosen
    out = {"device": a.device, "size": a.size, "images": a.images, "pairs": a.pairs,
           "median": {k: {"wall_s": statistics.median(v["wall_s"]), "material_s": statistics.median(v["material_s"]),
                          "launches": statistics.median(v["launches"]), "maen": v["maen"][0]} for k, v in rows.items()},
           "runs": rows}
    print(json.dumps(out["median"], indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
