"""``gpps.reconstruct_folder`` (what ``gpps reconstruct`` runs, without writing) on capture folders: wall time
per call, per-stage timings, the longest stretches without a progress report (and the reports around them) and MAEN
where ground truth exists.  Usage:
``python perf/reconstruct_folder_timing.py FOLDER... [--device cuda:0] [--repeat 2] [--refine] [--out FILE]``
(``--refine``: ``FolderConfig(refine=True)``, the depth refinement after RON's rounds; ``--interreflections
subtract`` [``--interreflection-rounds K``]: the interreflection compensation)."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import gpps  # noqa: E402
from gpps.io import json_default  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="+")
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--out", default=None)
    ap.add_argument("--refine", action="store_true", help="FolderConfig(refine=True)")
    ap.add_argument("--interreflections", default=None, choices=("auto", "off", "subtract"),
                    help="FolderConfig(interreflections=...); default: the FolderConfig default")
    ap.add_argument("--interreflection-rounds", type=int, default=None)
    a = ap.parse_args(argv)
    extra = {} if a.interreflections is None else {"interreflections": a.interreflections}
    if a.interreflection_rounds is not None:
        extra["interreflection_rounds"] = a.interreflection_rounds
    cfg = gpps.FolderConfig(refine=a.refine, **extra)
    rows = []
    for folder in a.folders:
        for k in range(a.repeat):
            t = time.perf_counter()
            last, gaps = [t, "start"], []

            def progress(done, total, msg):  # the longest time the progress callback sat still
                now = time.perf_counter()
                gaps.append((now - last[0], last[1], str(msg)))
                last[0], last[1] = now, str(msg)

            res = gpps.reconstruct_folder(folder, cfg, device=a.device, progress=progress)
            wall = time.perf_counter() - t
            gaps.append((time.perf_counter() - last[0], last[1], "end"))
            rep = res.report
            row = {"folder": Path(folder).name, "call": k, "wall_s": wall, "maen_deg": rep.get("maen_deg"),
                   "timings": rep.get("timings"), "images": rep.get("images"), "shape": rep.get("shape"),
                   "max_progress_gap_s": max(g[0] for g in gaps), "refine": a.refine,
                   "refinement": rep.get("refinement"), "interreflections": rep.get("interreflections"),
                   # the three longest stretches without a report: (seconds, the report before, the report after)
                   "longest_gaps": sorted(gaps, key=lambda g: -g[0])[:3]}
            rows.append(row)
            print(json.dumps(row, default=json_default), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps({"device": a.device, "refine": a.refine, "config": str(cfg), "rows": rows}, indent=1, default=json_default))


if __name__ == "__main__":
    main()
