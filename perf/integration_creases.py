"""Crease cut + stitch (gpps.host.creases) against plain Poisson and BiNI: the discontinuity suite, robustness on
continuous surfaces, and (last, never to choose parameters) the six shared DiLiGenT normal maps.

Parts:

1. ``suite``: tests/discontinuity_scenes.py at ``--sizes`` (48, 128), both cameras: worst per-piece mean
   |error| / depth range (each 4-connected piece of each surface aligned by its own median offset or scale).
2. ``robust``: tests/crease_scenes.py (ridge, oblique ridge, sphere, bump; clean, 1 and 3 degree noise, 8-bit
   quantised): mean |error| / range after ONE offset (orthographic) or scale (perspective) for the whole mask.
3. ``diligent``: BiNI's protocol (mean absolute mm after one median scale) for the variants, as the ratio to
   BiNI's published errors.

Methods: ``poisson`` (integrate_normals, uniform weights, sparse LU), ``bini`` (integrate_normals(bilateral=True):
today's default, device code on the CPU), ``cs_trap`` (cut + N_z^2 Poisson pieces + trapezoid stitch), ``cs_mid``
(the same with mid-normal targets), ``cs_cont`` (mid-normal pieces, continuity stitch), ``cs_bini`` (BiNI's IRLS
per piece, cut edges as missing neighbours, trapezoid stitch), ``cs_mid_bini`` (cs_mid, then BiNI on the uncut
graph from it), ``bini_cut`` (gpps.flows.integrate.integrate_normals_creases: the crease edges cut in the faithful
device BiNI, the pieces stitched with mid-normal targets), ``bini_cut_drop`` (the same with the slits dropped:
only cuts that separate pieces), ``bini_cut_bstitch`` (every cut, pieces stitched by BiNI's bilateral energy of
the cut edges), ``bini_cut_drop_bstitch`` (both).

4. ``box``: tests/discontinuity_scenes.render_box (folds and occluding steps on one crease network), worst
   per-piece and global (one offset / scale) error of the methods, and of the device BiNI with the TRUE surface
   boundaries cut (``true_mid``, ``true_bstitch``: the stitches alone, detection aside).  Times: one run each (seconds, this machine; the
DiLiGenT part times ``bini`` and ``bini_cut`` best of ``--repeat`` runs).

Usage: python perf/integration_creases.py [--parts suite,robust,box,diligent] [--sizes 48,128] [--suite-methods ...]
       [--robust-methods ...] [--diligent-methods ...] [--repeat N] [--out FILE]
Writes perf/results/integration_creases_cpu.json (bini_cut: perf/results/integration_creases_bini_cut_cpu.json;
the slit / stitch variants: perf/results/integration_creases_stitch_cpu.json).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

BINI_MM = {"bear": 0.334, "buddha": 1.098, "cow": 0.058, "goblet": 9.018, "pot1": 0.635, "pot2": 0.220}
# the crease-cut device BiNI's options (gpps.flows.integrate.integrate_normals_creases): slits dropped and / or the
# pieces stitched by BiNI's own criterion (bini_cut itself: every cut kept, mid-normal stitch)
CUT_VARIANTS = {
    "bini_cut": dict(),
    "bini_cut_drop": dict(slits="drop"),
    "bini_cut_bstitch": dict(cut_stitch="bini"),
    "bini_cut_drop_bstitch": dict(slits="drop", cut_stitch="bini"),
}
VARIANTS = {
    "cs_trap": dict(),
    "cs_mid": dict(target="mid"),
    "cs_cont": dict(target="mid", stitch_mode="continuity"),
    "cs_bini": dict(inner="bini"),
    "cs_mid_bini": dict(target="mid", refine="bini"),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parts", default="suite,robust,diligent")
    ap.add_argument("--box-methods", default="bini," + ",".join(CUT_VARIANTS))
    ap.add_argument("--sizes", default="48,128")
    ap.add_argument("--suite-methods", default="poisson,bini," + ",".join(VARIANTS) + ",bini_cut")
    ap.add_argument("--robust-methods", default="poisson,bini,cs_trap,cs_mid")
    ap.add_argument("--repeat", type=int, default=1, help="DiLiGenT: best of this many runs per method")
    ap.add_argument("--diligent-methods", default="cs_mid,cs_trap")
    ap.add_argument("--data", default=os.environ.get("GPPS_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--out", default=str(ROOT / "perf" / "results" / "integration_creases_cpu.json"))
    args = ap.parse_args(argv)

    from gpps import _taichi
    from gpps.camera import Orthographic, Perspective
    from gpps.flows.integrate import integrate_normals, integrate_normals_creases
    from gpps.host.creases import integrate_creases
    from gpps.io import save_json

    _taichi.init("cpu")
    sizes = [int(s) for s in args.sizes.split(",")]
    parts = args.parts.split(",")
    out = {"host": platform.node(), "cpu_count": os.cpu_count(),
           "variants": {k: str(v) for k, v in {**VARIANTS, **CUT_VARIANTS}.items()},
           "note": "suite: worst per-piece mean |error| / depth range; robust: mean |error| / range after one "
                   "global offset/scale; times: one run, seconds"}
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)

    def run(method, n, mask, cam):
        t = time.perf_counter()
        if method == "poisson":
            r = integrate_normals(n, mask, camera=cam, solver="direct", device="cpu")
            d, m, info = r.depth.astype(np.float64), r.mask, {}
        elif method == "bini":
            r = integrate_normals(n, mask, camera=cam, bilateral=True, device="cpu")
            d, m, info = r.depth.astype(np.float64), r.mask, {"outer": r.outer_iterations, "cg": r.iterations}
        elif method in CUT_VARIANTS:
            r, c = integrate_normals_creases(n, mask, camera=cam, device="cpu", **CUT_VARIANTS[method])
            d, m = r.depth.astype(np.float64), r.mask
            info = {"outer": r.outer_iterations, "cg": r.iterations, "pieces": c["n_pieces"], "cut": c["cut_edges"],
                    "slits": c["slits"], "threshold_deg": c["threshold_deg"], "stitch_s": r.timings.get("stitch", 0.0)}
        else:
            r = integrate_creases(n, mask, cam, **VARIANTS[method])
            d, m, info = r.depth, r.mask, {"pieces": r.n_pieces, "cut": r.info["cut_edges"],
                                           "threshold_deg": r.info["threshold_deg"]}
        return d, m, time.perf_counter() - t, info

    def camera_of(sc):
        return Perspective(sc["K"]) if "K" in sc else Orthographic(sc["pixel_size"])

    if "suite" in parts:
        from discontinuity_scenes import SCENES, render_scene, surface_errors

        rows = []
        methods = args.suite_methods.split(",")
        print("suite: worst per-piece mean |error| / range")
        print(f"{'size':>4s} {'camera':6s} {'scene':8s} " + " ".join(f"{m:>11s}" for m in methods))
        for size in sizes:
            for camera in ("orthographic", "perspective"):
                for name in SCENES:
                    sc = render_scene(name, size, camera)
                    cam = camera_of(sc)
                    row = dict(size=size, camera=camera, scene=name)
                    for method in methods:
                        d, m, dt, info = run(method, sc["normals"], sc["mask"], cam)
                        pieces, rng = surface_errors(d, sc["depth"], sc["labels"], m, camera == "perspective")
                        row[method] = max(p["mean"] for p in pieces) / rng
                        row[method + "_s"] = dt
                        if info:
                            row[method + "_info"] = info
                    rows.append(row)
                    print(f"{size:4d} {camera[:6]:6s} {name:8s} " + " ".join(f"{row[m]:11.1e}" for m in methods), flush=True)
        out["suite"] = rows
        save_json(path, out)

    if "robust" in parts:
        from crease_scenes import SURFACES, global_error, perturb, quantise8, render_surface

        rows = []
        methods = args.robust_methods.split(",")
        print("robustness: mean |error| / range after one global offset / scale")
        print(f"{'size':>4s} {'camera':6s} {'surface':13s} {'case':7s} " + " ".join(f"{m:>9s}" for m in methods))
        for size in sizes:
            for camera in ("orthographic", "perspective"):
                for name in SURFACES:
                    sc = render_surface(name, size, camera)
                    cam = camera_of(sc)
                    for case in ("clean", "noise1", "noise3", "q8"):
                        n = sc["normals"]
                        if case.startswith("noise"):
                            n = perturb(n, float(case[5:]), seed=size)
                        elif case == "q8":
                            n = quantise8(n)
                        row = dict(size=size, camera=camera, surface=name, case=case)
                        for method in methods:
                            d, m, dt, info = run(method, n, sc["mask"], cam)
                            mean, mx = global_error(d, sc["depth"], m & sc["mask"], camera == "perspective")
                            row[method], row[method + "_max"], row[method + "_s"] = mean, mx, dt
                            if info:
                                row[method + "_info"] = info
                        rows.append(row)
                        print(f"{size:4d} {camera[:6]:6s} {name:13s} {case:7s} " + " ".join(f"{row[m]:9.1e}" for m in methods),
                              flush=True)
        out["robust"] = rows
        save_json(path, out)

    if "box" in parts:
        from crease_scenes import global_error
        from discontinuity_scenes import render_box, surface_errors

        from gpps.flows.integrate import Integrator, IntegratorConfig

        rows = []
        methods = args.box_methods.split(",")
        print("box: worst per-piece / global mean |error| / range")
        for size in sizes:
            for camera in ("orthographic", "perspective"):
                sc = render_box(size, camera)
                cam = camera_of(sc)
                persp = camera == "perspective"
                row = dict(size=size, camera=camera)
                m0, lab = sc["mask"], sc["labels"]
                tcx = np.zeros(m0.shape, bool)
                tcy = np.zeros(m0.shape, bool)
                tcx[:, :-1] = m0[:, :-1] & m0[:, 1:] & (lab[:, :-1] != lab[:, 1:])
                tcy[:-1] = m0[:-1] & m0[1:] & (lab[:-1] != lab[1:])
                for method in methods + ["true_mid", "true_bstitch"]:
                    if method.startswith("true_"):
                        t = time.perf_counter()
                        cfg = IntegratorConfig(bilateral=True, weighting="normal",
                                               cut_stitch="mid" if method == "true_mid" else "bini")
                        integ = Integrator(m0, cam, cfg, device="cpu")
                        r = integ.run(sc["normals"], cuts=(tcx, tcy))
                        integ.close()
                        d, m, dt, info = r.depth.astype(np.float64), r.mask, time.perf_counter() - t, {
                            "cut": int(tcx.sum() + tcy.sum()), "stitch_s": r.timings.get("stitch", 0.0)}
                    else:
                        d, m, dt, info = run(method, sc["normals"], m0, cam)
                    pieces, rng = surface_errors(d, sc["depth"], lab, m, persp)
                    row[method + "_piece"] = max(p["mean"] for p in pieces) / rng
                    row[method + "_global"] = global_error(d, sc["depth"], m, persp)[0]
                    row[method + "_s"] = dt
                    row[method + "_info"] = info
                rows.append(row)
                print(f"{size:4d} {camera[:6]:6s} " + " ".join(
                    f"{k} {row[k + '_piece']:.1e}/{row[k + '_global']:.1e}" for k in methods + ["true_mid", "true_bstitch"]),
                    flush=True)
        out["box"] = rows
        save_json(path, out)

    if "diligent" in parts:
        from integration_diligent import load

        rows = []
        methods = args.diligent_methods.split(",")
        print("DiLiGenT (final check): mean |error| mm after one median scale, ratio to BiNI's published")
        for name in BINI_MM:
            folder = Path(args.data) / "integration" / "diligent" / name
            if not folder.exists():
                print(f"{name}: no data at {folder}")
                continue
            n, mask, K, gt = load(folder)
            cam = Perspective(K)
            row = dict(object=name, pixels=int(mask.sum()), bini_published_mm=BINI_MM[name])
            for method in methods:
                d, m, dt, info = run(method, n, mask, cam)
                for _ in range(args.repeat - 1):
                    dt = min(dt, run(method, n, mask, cam)[2])
                ev = m & np.isfinite(gt) & (d > 0)
                mm = float(np.mean(np.abs(np.median(gt[ev] / d[ev]) * d[ev] - gt[ev])))
                row[method + "_mm"], row[method + "_ratio"], row[method + "_s"] = mm, mm / BINI_MM[name], dt
                row[method + "_info"] = info
            rows.append(row)
            print(f"{name:8s} " + " ".join(f"{m} {row[m + '_mm']:.4f} mm ({row[m + '_ratio']:.2f}x, {row[m + '_s']:.1f} s, "
                                          f"{row[m + '_info'].get('pieces', '-')} pieces)" for m in methods), flush=True)
        out["diligent"] = rows
        save_json(path, out)

    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
