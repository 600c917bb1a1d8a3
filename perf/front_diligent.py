"""DGMC's front on real captures: warm ``gpps.reconstruct_folder`` (the whole default pipeline) with the
device-resident front (:func:`gpps.pipeline.front.propagate_front`) and with the old host loop over rings
(tests/front_reference.py) patched into RON; per folder the median of 3 warm runs of the total, RON's DGMC stage
and the front's calls themselves (device-synchronised around each), the rings and MAEN.  Runs device, host,
device (the two device rows bracket the host one).

Usage:  python perf/front_diligent.py FOLDER... [--device cuda:0]

perf/results/front_diligent_H100.log: DiLiGenT ball and bear (the folders as perf/diligent.py reads them), H100.
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
sys.path.insert(0, str(ROOT / "tests"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from front_reference import propagate_front_host  # noqa: E402

import gpps  # noqa: E402
import gpps.flows.ron as ron_module  # noqa: E402
from gpps._runtime import resolve_device, warp  # noqa: E402
from gpps.pipeline.front import propagate_front  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--device", default=None)
    a = ap.parse_args(argv)
    device = resolve_device(a.device)
    wp = warp()
    calls = []

    def timed(fn):
        def front(*args, **kw):
            wp.synchronize_device(device)
            t = time.perf_counter()
            r = fn(*args, **kw)
            wp.synchronize_device(device)
            calls.append((time.perf_counter() - t, r.n_rings, int((r.ring > 0).sum())))
            return r
        return front

    for folder in a.folders:
        gpps.reconstruct_folder(folder, device=device)
        for impl, fn in (("device", propagate_front), ("host", propagate_front_host), ("device", propagate_front)):
            ron_module.propagate_front = timed(fn)
            try:
                tot, dg, fr = [], [], []
                for _ in range(3):
                    calls.clear()
                    t = time.perf_counter()
                    res = gpps.reconstruct_folder(folder, device=device)
                    tot.append(time.perf_counter() - t)
                    dg.append(res.report["timings"]["dgmc"])
                    fr.append(sum(c[0] for c in calls))
            finally:
                ron_module.propagate_front = propagate_front
            print(json.dumps({"folder": folder, "front": impl, "total_s": float(np.median(tot)),
                              "dgmc_s": float(np.median(dg)), "front_s": float(np.median(fr)),
                              "rings": calls[0][1] if calls else 0, "ring_pixels": calls[0][2] if calls else 0,
                              "maen_deg": res.report.get("maen_deg")}), flush=True)


if __name__ == "__main__":
    main()
