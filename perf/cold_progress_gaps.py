"""``gpps.reconstruct_folder`` on one capture folder with every progress call timed: the wall time, the MAEN and the
six longest gaps between progress calls with the messages either side (issue 20: progress at least every 5 s).
Run it with an empty kernel cache to see a first run's compiles: ``GPPS_CACHE_DIR=$(mktemp -d) python
perf/cold_progress_gaps.py .data/diligent/ball [--device cpu]``; ``GPPS_PREFETCH=0`` for a first run without the
compiles ahead (:mod:`gpps.pipeline.prefetch`).  One JSON object on stdout."""
import argparse
import json
import os
import time
import warnings

warnings.simplefilter("ignore")
import gpps  # noqa: E402
from gpps.io import read_capture  # noqa: E402

ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
ap.add_argument("folder")
ap.add_argument("--device", default="cpu")
a = ap.parse_args()
t0 = time.perf_counter()
last, gaps, prev = [t0], [], ["start"]


def progress(done, total, msg):
    now = time.perf_counter()
    gaps.append((round(now - last[0], 3), prev[0], msg))
    last[0], prev[0] = now, msg


res = gpps.reconstruct_folder(a.folder, gpps.FolderConfig(), device=a.device, progress=progress)
wall = time.perf_counter() - t0
ds = read_capture(a.folder).dataset
maen = float(gpps.normal_errors(res.normals, ds.normal_gt, res.mask)["mean"]) if ds.normal_gt is not None else None
print(json.dumps({"folder": a.folder, "device": a.device, "prefetch": os.environ.get("GPPS_PREFETCH", "1"),
                  "wall_s": wall, "maen_deg": maen, "calls": len(gaps),
                  "longest_gaps": sorted(gaps, reverse=True)[:6]}, indent=1))
