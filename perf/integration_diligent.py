"""Perspective normal integration on the true DiLiGenT normal maps vs depth_gt (BiNI's protocol).

For each object of ``<data>/integration/diligent`` integrates the ground-truth
normal map (BiNI 16-bit colour coding) with the object's K in three modes:

* ``poisson``: plain uniform log-depth Poisson (w = 1/2, no N_z weighting);
* ``bilateral``: BiNI (the default of ``gpps integrate``): its IRLS with its
  defaults (k = 2, N-multiplied one-sided equations, first solve with
  w = 1/2, relative energy change 1e-4, at most 150 iterations) and its inner
  Jacobi-preconditioned CG to 1e-3, warm-started, on the device in float64
  (gpps/pipeline/integration_bini.py; perf/integration_bini.py times it
  against BiNI's reference code);
* ``robust``: uniform Poisson with a Cauchy loss on the edge residuals
  (IntegratorConfig.robust, 8 re-weighted solves, sigma = 2 robust standard
  deviations): the few wrong normals of the maps stop bending the surface.
* ``curl``: uniform Poisson with each edge weighted by a Cauchy function of
  the curl of its 2x2 loops (robust="curl", sigma = 2 robust standard
  deviations of the loop curls): one convex solve.

``--curl-scales 1,1.5,2,3,4`` adds a sensitivity sweep of the curl mode's
sigma (robust_scale) over the same objects, so that the default's margin is
on record rather than picked from the table.

The Poisson solves are Taichi multigrid-preconditioned CG in float64.  The error is
the mean absolute depth error (MADE, mm) over mask & finite depth_gt after
aligning the one free scale either by BiNI's rule (``median(gt / est)``, the
published protocol: ``ratio`` uses it) or by least squares.

Usage: python perf/integration_diligent.py [--device cpu] [--solver multigrid] [--objects bear,cow]
       [--modes poisson,bilateral,robust,curl] [--curl-scales 1,1.5,2,3,4]
Writes perf/results/integration_diligent_<device>.json.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

BINI = {"bear": 0.334, "buddha": 1.098, "cow": 0.058, "goblet": 9.018, "pot1": 0.635, "pot2": 0.220}
SMOOTH = {"bear", "cow", "pot1", "pot2"}  # the 1.2x target; buddha and goblet are reported
MODES = {
    "poisson": dict(bilateral=False, weighting="uniform"),
    "bilateral": dict(bilateral=True),
    "robust": dict(robust="cauchy", weighting="uniform"),
    "curl": dict(robust="curl", weighting="uniform"),
}


def load(folder: Path):
    import cv2

    raw = cv2.imread(str(folder / "normal_map.png"), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise FileNotFoundError(folder / "normal_map.png")
    n = raw[..., ::-1].astype(np.float64) / 65535.0 * 2.0 - 1.0  # BGR -> (x, y, z), gpps frame
    mask = cv2.imread(str(folder / "mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    K = np.loadtxt(folder / "K.txt")
    gt = np.load(folder / "depth_gt.npz")["depth_gt"].astype(np.float64)
    return n, mask, K, gt


def made(depth, valid, gt):
    """(MADE with BiNI's median-ratio scale, MADE with the least-squares scale) in mm."""
    ev = valid & np.isfinite(gt)
    d = depth.astype(np.float64)[ev]
    g = gt[ev]
    med = float(np.mean(np.abs(np.median(g / d) * d - g)))
    ls = float(np.mean(np.abs(float(d @ g / (d @ d)) * d - g)))
    return med, ls, int(ev.sum())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--solver", default="multigrid")
    ap.add_argument("--data", default=os.environ.get("GPPS_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--objects", default=",".join(BINI))
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--curl-scales", default="", help="comma-separated robust_scale values for the curl sweep")
    args = ap.parse_args(argv)

    from gpps.camera import Perspective
    from gpps.flows.integrate import integrate_normals

    modes = args.modes.split(",")
    for m in modes:
        if m not in MODES:
            ap.error(f"--modes: unknown mode {m!r}; expected some of {list(MODES)}")
    rows = []
    print(f"{'object':8s} {'mode':16s} {'MADE med':>9s} {'MADE ls':>8s} {'BiNI':>7s} {'ratio':>6s} {'iters':>6s} "
          f"{'outer':>5s} {'time s':>7s}")
    for name in args.objects.split(","):
        n, mask, K, gt = load(Path(args.data) / "integration" / "diligent" / name)
        for mode in modes:
            t0 = time.perf_counter()
            res = integrate_normals(n, mask, camera=Perspective(K), solver=args.solver, device=args.device,
                                    tol=1e-6, dtype="float64", **MODES[mode])
            dt = time.perf_counter() - t0
            med, ls, npx = made(res.depth, res.mask, gt)
            row = dict(object=name, mode=mode, made_mm_median_scale=med, made_mm_lsq_scale=ls, bini_mm=BINI[name],
                       ratio=med / BINI[name], ratio_lsq=ls / BINI[name],
                       meets_1p2x=bool(med <= 1.2 * BINI[name]), smooth_target=name in SMOOTH,
                       iterations=res.iterations, outer_iterations=res.outer_iterations, residual=res.residual,
                       seconds=dt, n_pixels=npx, n_invalid=res.n_invalid)
            rows.append(row)
            print(f"{name:8s} {mode:16s} {med:9.3f} {ls:8.3f} {BINI[name]:7.3f} {row['ratio']:6.2f} "
                  f"{res.iterations:6d} {res.outer_iterations:5d} {dt:7.2f}", flush=True)
    sweep = []
    scales = [float(v) for v in args.curl_scales.split(",") if v.strip()]
    if scales:
        print("curl mode, sensitivity to robust_scale (ratio to BiNI):")
        print(f"{'object':8s} " + " ".join(f"{sc:>6g}" for sc in scales))
    for name in args.objects.split(",") if scales else []:
        n, mask, K, gt = load(Path(args.data) / "integration" / "diligent" / name)
        line = []
        for sc in scales:
            res = integrate_normals(n, mask, camera=Perspective(K), solver=args.solver, device=args.device,
                                    tol=1e-6, dtype="float64", robust="curl", robust_scale=sc)
            med, ls, _ = made(res.depth, res.mask, gt)
            sweep.append(dict(object=name, robust_scale=sc, made_mm_median_scale=med, ratio=med / BINI[name],
                              meets_1p2x=bool(med <= 1.2 * BINI[name])))
            line.append(med / BINI[name])
        print(f"{name:8s} " + " ".join(f"{v:6.2f}" for v in line), flush=True)
    summary = {}
    for mode in modes:
        rs = [r for r in rows if r["mode"] == mode]
        summary[mode] = dict(
            smooth_within_1p2x=[r["object"] for r in rs if r["smooth_target"] and r["meets_1p2x"]],
            smooth_short=[r["object"] for r in rs if r["smooth_target"] and not r["meets_1p2x"]],
            all_within_1p2x=[r["object"] for r in rs if r["meets_1p2x"]],
        )
        print(f"{mode}: smooth objects within 1.2x of BiNI: {summary[mode]['smooth_within_1p2x']}, "
              f"short: {summary[mode]['smooth_short']}")
    out = ROOT / "perf" / "results" / f"integration_diligent_{args.device.replace(':', '')}.json"
    from gpps.io import save_json

    save_json(out, {"device": args.device, "solver": args.solver, "dtype": "float64", "tol": 1e-6,
                    "cpu_count": os.cpu_count(), "rows": rows, "summary": summary,
                    "curl_scale_sweep": sweep,
                    "note": "MADE over mask & finite depth_gt; ratio = median-scale MADE / BiNI published "
                            "(BiNI's protocol: scale = nanmedian(gt / est)); ratio_lsq uses the least-squares scale"})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
