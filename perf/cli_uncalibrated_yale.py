"""Yale B subjects through the command line, uncalibrated: ``gpps reconstruct DIR --uncalibrated``.

Each subject's folder is given to the CLI as it is on disk (64 8-bit PGMs, the
``*_Ambient.pgm`` image, which the CLI subtracts, a ``.info`` file; no mask, no
light files).  The CLI makes its automatic mask, leaves out nearly dark images,
estimates the lights and decides the convex/concave flip itself (convexity
prior: the images of an orthographic camera cannot tell).  Score: the mean
angle between ``lights_estimated.txt`` and the nominal lights of the file
names (``perf/uncalibrated_real.py``'s convention: ``x = -cos(E) sin(A), y =
sin(E), z = cos(E) cos(A)``), *as written* (no flip applied by the scorer);
the score after the better flip is printed beside it for comparison with the
API's numbers (which are after the better flip when the API says ambiguous).

Usage: python perf/cli_uncalibrated_yale.py [--subjects yaleB01 ...] [--keep DIR]
Writes perf/results/cli_uncalibrated_yale.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np

DATA = ROOT.parent / "shared" / "data" / "yaleb"
API = {"yaleB01": 4.13, "yaleB02": 5.36, "yaleB03": 4.35, "yaleB04": 3.80}  # the API's numbers before this work (issue 22)


def nominal(names):
    ae = np.array([[int(m[1]), int(m[2])] for m in (re.search(r"A([+-]\d+)E([+-]\d+)", n) for n in names)], np.float64)
    a, e = np.radians(ae[:, 0]), np.radians(ae[:, 1])
    return np.stack([-np.cos(e) * np.sin(a), np.sin(e), np.cos(e) * np.cos(a)], -1)


def errors(est, true):
    est = est / np.linalg.norm(est, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip((est * true).sum(1), -1, 1)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--subjects", nargs="*", default=list(API))
    ap.add_argument("--data", default=str(DATA))
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--keep", default=None, help="keep the CLI's output folders here")
    a = ap.parse_args(argv)
    rows = []
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="gpps_yale_"))
    for s in a.subjects:
        out = work / s
        cmd = [sys.executable, "-m", "gpps", "--device", a.device, "reconstruct", str(Path(a.data) / s), "--uncalibrated", "--out", str(out), "--json", "--quiet"]
        t = time.perf_counter()
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        sec = time.perf_counter() - t
        if p.returncode != 0:
            print(p.stderr)
            raise SystemExit(f"{s}: gpps failed ({p.returncode})")
        rep = json.loads(p.stdout)
        used = (out / "filenames_used.txt").read_text().split()
        est = np.loadtxt(out / "lights_estimated.txt")
        true = nominal(used)
        e = errors(est, true)
        ef = errors(est * [-1, -1, 1], true)
        row = {"subject": s, "command": " ".join(cmd[1:]), "seconds": sec, "images_used": len(used), "left_out": rep["images_left_out"],
               "mask": rep["input"]["mask"], "mask_pixels": rep["input"].get("automatic_mask", {}).get("pixels"),
               "ambient": rep["input"]["ambient_subtracted"], "convex_concave": rep["convex_concave"],
               "mean_deg_as_written": float(e.mean()), "median_deg": float(np.median(e)), "max_deg": float(e.max()),
               "mean_deg_better_flip": float(min(e.mean(), ef.mean())), "api_before": API.get(s)}
        rows.append(row)
        print(f"{s}: mean light error {e.mean():.2f} deg as written (better flip {row['mean_deg_better_flip']:.2f}; API before {API.get(s)}), "
              f"{len(used)} images, left out {rep['images_left_out']}, flip {rep['convex_concave']['flip']}/{rep['convex_concave']['surface']}, {sec:.0f} s", flush=True)
    from gpps.io import save_json

    path = ROOT / "perf" / "results" / "cli_uncalibrated_yale.json"
    save_json(path, {"device": a.device, "rows": rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
