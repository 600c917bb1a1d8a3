"""The default folder flow on cached Mitsuba captures with the neighbour pass's attached / cast shadow choice on or
off (``SolverConfig.held_dark_refit``, session 35), one JSON line per capture.

    python perf/dev_held_dark_eval.py OUT.jsonl "GLOB[,GLOB...]" on|off [THRESHOLD]

``THRESHOLD`` > 0 also drops every observation below that fraction of the pixel's brightest with few images
(``shadow_threshold``, the many-images setting; session 35's first probe).  Captures: perf/dev_eval.py's and
perf/heldout_eval.py's (``--render-only``), under ``$GPPS_CACHE_DIR/mitsuba_captures``.  ``GPPS_EVAL_DEVICE``
in the environment: the device (default ``cpu``).
"""
from __future__ import annotations

import glob
import json
import os
import sys
import time
import warnings

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))


def main(out: str, patterns: str, mode: str, threshold: float = 0.0) -> None:
    import gpps
    import gpps.flows.folder as ff
    from gpps.host.metrics import normal_errors
    from gpps.io import read_capture

    warnings.simplefilter("ignore")
    on = {"on": True, "off": False}[mode]
    device = os.environ.get("GPPS_EVAL_DEVICE", "cpu")
    orig = ff.automatic_solver_options

    def patched(n, robust=None):
        o = orig(n, robust)
        if n <= ff.MANY_IMAGES and threshold > 0:
            o.update(shadow_threshold=threshold)
        o.update(held_dark_refit=on)
        return o

    ff.automatic_solver_options = patched
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", ".cache"), "mitsuba_captures")
    caps = sorted(c for p in patterns.split(",") for c in glob.glob(os.path.join(root, p)))
    if not caps:
        raise SystemExit(f"no capture under {root} matches {patterns!r}")
    with open(out, "a") as f:
        for c in caps:
            ds = read_capture(c).dataset
            t = time.perf_counter()
            r = gpps.reconstruct_folder(c, gpps.FolderConfig(), device=device)
            e = normal_errors(r.normals, ds.normal_gt, ds.mask)
            row = dict(capture=os.path.basename(c), device=device, held_dark_refit=on, threshold=threshold,
                       maen=e["mean"], seconds=time.perf_counter() - t, brdf=r.report["material"]["brdf"],
                       refine=r.report.get("refine", {}).get("on"))
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(row["capture"][:50], on, threshold, round(e["mean"], 2), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4]) if len(sys.argv) > 4 else 0.0)
