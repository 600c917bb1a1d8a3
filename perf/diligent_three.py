"""DiLiGenT ball and bear from three images through the default folder flow (issue 25's final check of the
3-image path, which refines the depth: RONConfig.refine, refine_two_light).

The three images are fixed by a rule, not by score: the light triple with the largest ``|det|`` of its directions
(the best-conditioned for photometric stereo; perf/_common.best_triple, perf/single_real.py's rule).  Each object's triple is copied into a
temporary folder with its light rows, K, mask and ground truth, and ``gpps.reconstruct_folder`` runs with the
default :class:`gpps.FolderConfig`; one JSON line per object (MAEN, the refinement's choice, seconds).  To
compare two trees, run it with each on ``PYTHONPATH`` (the script does not put its own tree first).

    python perf/diligent_three.py OUT.jsonl [--data ../shared/data/diligent] [--device cpu]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import best_triple, diligent_subset  # (perf/ is the script's directory: first on sys.path)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data" / "diligent"))
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    import gpps
    from gpps.host.metrics import normal_errors

    with tempfile.TemporaryDirectory(prefix="gpps-dil3-") as tmp, open(a.out, "a") as f:
        for obj in ("ball", "bear"):
            src = Path(a.data) / obj
            idx = best_triple(np.loadtxt(src / "light_directions.txt"))
            folder = diligent_subset(src, Path(tmp) / obj, idx)
            t = time.perf_counter()
            r = gpps.reconstruct_folder(folder, device=a.device)
            dt = time.perf_counter() - t
            gt = np.load(folder / "normal_gt.npy")
            e = normal_errors(r.normals, gt, r.mask)
            ref = r.report.get("refinement") or {}
            row = {"object": obj, "images": [int(k) + 1 for k in idx], "maen": e["mean"], "median": e["median"],
                   "seconds": dt, "device": a.device, "refine": r.report.get("refine"),
                   "chosen": ref.get("chosen"), "starts": ref.get("starts")}
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
