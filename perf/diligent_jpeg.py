"""A DiLiGenT object as a user's JPEGs (no mask.png, no filenames.txt) against its PNGs with the mask, through the CLI.

The JPEG folder is made from the 16-bit linear PNGs as a camera would store
them: sRGB-encoded, 8 bits, JPEG quality 95 (OpenCV), named ``001.jpg ...``
(sorted = the light order), with the light files, ``K.txt`` and
``normal_gt.npy`` copied; no ``mask.png``, no ``filenames.txt``.  ``gpps
reconstruct`` then decodes sRGB (``--transfer auto``), makes its automatic
mask and runs the default pipeline; the reference is ``gpps reconstruct`` on
the original folder (PNGs, mask.png).  Both are scored against
``normal_gt.npy`` on the true mask's pixels that the automatic mask covers
(its coverage and IoU are reported too), and on the full true mask (pixels the
automatic mask missed count as 90 deg).

Usage: python perf/diligent_jpeg.py [--objects ball bear] [--lights K] [--args ...]
Writes perf/results/diligent_jpeg.json.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np

DATA = ROOT.parent / "shared" / "data" / "diligent"


def make_jpeg_folder(src: Path, dst: Path, quality: int = 95, indices=None):
    import cv2

    from gpps.io.formats import linear_to_srgb

    dst.mkdir(parents=True, exist_ok=True)
    names = [s.strip() for s in (src / "filenames.txt").read_text().split() if s.strip()]
    sel = range(len(names)) if indices is None else indices
    for j, k in enumerate(sel):
        a = cv2.imread(str(src / names[k]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535.0
        enc = np.round(linear_to_srgb(a) * 255).astype(np.uint8)
        cv2.imwrite(str(dst / f"{j + 1:03d}.jpg"), enc, [cv2.IMWRITE_JPEG_QUALITY, quality])
    for f in ("light_directions.txt", "light_intensities.txt"):
        rows = np.loadtxt(src / f)[list(sel)]
        np.savetxt(dst / f, rows)
    for f in ("K.txt", "normal_gt.npy"):
        shutil.copy(src / f, dst / f)


def subset_png_folder(src: Path, dst: Path, indices):
    dst.mkdir(parents=True, exist_ok=True)
    names = [s.strip() for s in (src / "filenames.txt").read_text().split() if s.strip()]
    for k in indices:
        shutil.copy(src / names[k], dst / names[k])
    (dst / "filenames.txt").write_text("\n".join(names[k] for k in indices) + "\n")
    for f in ("light_directions.txt", "light_intensities.txt"):
        np.savetxt(dst / f, np.loadtxt(src / f)[list(indices)])
    for f in ("K.txt", "normal_gt.npy", "mask.png"):
        shutil.copy(src / f, dst / f)


def score(normals, gt, gt_mask, auto_mask):
    from gpps.host.metrics import angular_error

    both = gt_mask & auto_mask
    e = angular_error(normals, gt, both)[both]
    full = angular_error(np.where(auto_mask[..., None], normals, 0.0) + np.where(auto_mask[..., None], 0.0, [0.0, 0.0, -1.0]), gt, gt_mask)[gt_mask]
    return {"maen_on_covered": float(e.mean()), "maen_full_true_mask": float(np.minimum(full, 90).mean()), "pixels": int(both.sum())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="+", default=["ball"])
    ap.add_argument("--lights", type=int, default=None, help="use every k-th light only (default: all 96)")
    ap.add_argument("--quality", type=int, default=95)
    ap.add_argument("--keep", default=None)
    ap.add_argument("--args", nargs=argparse.REMAINDER, default=[], help="extra gpps reconstruct arguments for both runs")
    a = ap.parse_args(argv)
    import cv2

    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="gpps_jpeg_"))
    rows = []
    for obj in a.objects:
        src = DATA / obj
        n = len((src / "filenames.txt").read_text().split())
        idx = list(range(0, n, a.lights)) if a.lights else list(range(n))
        png = src
        if a.lights:
            png = work / f"{obj}_png"
            subset_png_folder(src, png, idx)
        jpg = work / f"{obj}_jpg"
        make_jpeg_folder(src, jpg, a.quality, idx)
        res = {}
        for tag, folder in (("png_with_mask", png), ("jpeg_no_mask", jpg)):
            out = work / f"{obj}_{tag}_out"
            cmd = [sys.executable, "-m", "gpps", "--device", "cpu", "reconstruct", str(folder), "--out", str(out), "--json", "--quiet", *a.args]
            t = time.perf_counter()
            p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
            if p.returncode != 0:
                raise SystemExit(p.stderr[-3000:])
            rep = json.loads(p.stdout)
            res[tag] = {"seconds": time.perf_counter() - t, "command": " ".join(cmd[1:]), "input": rep["input"]["formats"],
                        "mask": rep["input"]["mask"], "normals": np.load(out / "normals.npy"),
                        "mask_used": cv2.imread(str(out / "mask.png"), cv2.IMREAD_UNCHANGED) > 0, "maen_report": rep.get("maen_deg")}
        gt = np.load(src / "normal_gt.npy")
        gt_mask = cv2.imread(str(src / "mask.png"), cv2.IMREAD_UNCHANGED) > 0
        if gt_mask.ndim == 3:
            gt_mask = gt_mask.any(-1)
        am = res["jpeg_no_mask"]["mask_used"]
        s_png = score(res["png_with_mask"]["normals"], gt, gt_mask, am)
        s_jpg = score(res["jpeg_no_mask"]["normals"], gt, gt_mask, am)
        row = {"object": obj, "lights": len(idx), "jpeg_quality": a.quality,
               "automask_coverage_of_true_mask": float((am & gt_mask).sum() / gt_mask.sum()),
               "automask_iou": float((am & gt_mask).sum() / (am | gt_mask).sum()),
               "png_with_mask": {k: v for k, v in res["png_with_mask"].items() if k not in ("normals", "mask_used")} | s_png,
               "jpeg_no_mask": {k: v for k, v in res["jpeg_no_mask"].items() if k not in ("normals", "mask_used")} | s_jpg,
               "difference_deg": s_jpg["maen_on_covered"] - s_png["maen_on_covered"]}
        rows.append(row)
        print(f"{obj} ({len(idx)} lights): PNG+mask MAEN {s_png['maen_on_covered']:.3f} deg, JPEG no mask {s_jpg['maen_on_covered']:.3f} deg "
              f"(difference {row['difference_deg']:+.3f}); automatic mask covers {100 * row['automask_coverage_of_true_mask']:.1f}% of the true mask, "
              f"IoU {row['automask_iou']:.3f}; {res['png_with_mask']['seconds']:.0f} s + {res['jpeg_no_mask']['seconds']:.0f} s", flush=True)
    from gpps.io import save_json

    out = ROOT / "perf" / "results" / "diligent_jpeg.json"
    save_json(out, {"rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
