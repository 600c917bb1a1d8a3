"""Bilateral normal integration (gpps's device BiNI) side by side with BiNI's reference code and dbini-torch.

Three parts, all in one process:

1. ``diligent``: the six shared true DiLiGenT normal maps with their K.  gpps
   (``integrate_normals(..., bilateral=True)``: BiNI's defaults k = 2, energy
   tolerance 1e-4, CG tolerance 1e-3, at most 150 iterations) and, when
   given, BiNI's reference implementation (``--bini-path``: a folder holding
   ``bilateral_normal_integration_cpu.py`` from github.com/xucao-42/
   bilateral_normal_integration, run with the same defaults) and dbini-torch
   (``--dbini``, on the same device as gpps when it is CUDA).  Error: BiNI's
   protocol, mean absolute depth error (mm) over mask & finite depth_gt after
   one scale ``median(gt / est)`` (what perf/integration_diligent.py and
   BiNI's evaluation_diligent.py use).
2. ``suite``: the ray-cast discontinuity scenes of ``tests/discontinuity_scenes.py``
   (both cameras, ``--suite-size``): worst per-piece mean |error| / depth range,
   each 4-connected piece of each surface aligned by its own offset
   (orthographic) or scale (perspective), for gpps BiNI, plain Poisson and the
   reference.
3. ``mp``: one ~1 MP map (the ``overlap`` scene, ``--mp-size`` squared, perspective):
   gpps's time to BiNI's tolerance, and dbini-torch's (``--dbini``) and the
   reference's (``--mp-bini``) on the same map.

Times are medians of ``--repeat`` runs after one warm-up run (compilation,
numba's cache); gpps's solve ends with host reads of the result, so it is
device-synchronised; dbini-torch is synchronised with ``torch.cuda.synchronize``.

Usage: python perf/integration_bini.py [--device cpu|cuda:0] [--bini-path /tmp/bini] [--dbini] [--launch auto] [--compare-tasks]
       [--parts diligent,suite,mp] [--repeat 3] [--suite-size 128] [--mp-size 1024] [--out FILE]
Writes perf/results/integration_bini_<device>.json (or --out).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from integration_diligent import load  # noqa: E402  (one reader of the BiNI-coded DiLiGenT maps)

BINI_MM = {"bear": 0.334, "buddha": 1.098, "cow": 0.058, "goblet": 9.018, "pot1": 0.635, "pot2": 0.220}


def made(depth, valid, gt):
    ev = valid & np.isfinite(gt) & np.isfinite(depth) & (depth > 0)
    d, g = depth.astype(np.float64)[ev], gt[ev]
    return float(np.mean(np.abs(np.median(g / d) * d - g)))


def timed(fn, repeat, sync=None):
    """(last result, median seconds of ``repeat`` runs after one warm-up run, all times)."""
    out = fn()
    ts = []
    for _ in range(repeat):
        if sync:
            sync()
        t = time.perf_counter()
        out = fn()
        if sync:
            sync()
        ts.append(time.perf_counter() - t)
    return out, float(np.median(ts)), ts


class Bini:
    """BiNI's reference code, imported from a folder given on the command line (never vendored)."""

    def __init__(self, path):
        sys.path.insert(0, str(path))
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            import bilateral_normal_integration_cpu as m  # noqa: PLC0415
        self.m = m

    def __call__(self, normals, mask, K=None, step_size=1.0):
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if K is not None:
                d, _, _, _, el = self.m.bilateral_normal_integration(normals, mask, K=K)
            else:
                d, _, _, _, el = self.m.bilateral_normal_integration(normals, mask, step_size=step_size)
        return d, len(el)


class Dbini:
    """dbini-torch (pip package), on CUDA when available."""

    def __init__(self, device):
        import torch
        from dbini_torch import bilateral_normal_integration

        self.torch, self.f = torch, bilateral_normal_integration
        self.dev = torch.device("cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu")

    def sync(self):
        if self.dev.type == "cuda":
            self.torch.cuda.synchronize()

    def __call__(self, normals, mask, K=None):
        t = self.torch
        nm = t.as_tensor(np.ascontiguousarray(np.moveaxis(normals, -1, 0)), dtype=t.float64, device=self.dev)
        mk = t.as_tensor(mask, device=self.dev)
        Kt = None if K is None else t.as_tensor(K, dtype=t.float64, device=self.dev)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            out = self.f(nm, mk, K=Kt)
        d = out[0].detach().cpu().numpy()
        return d, len(out[4]) if len(out) > 4 and hasattr(out[4], "__len__") else -1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--data", default=os.environ.get("GPPS_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--bini-path", default=None, help="folder with BiNI's bilateral_normal_integration_cpu.py")
    ap.add_argument("--dbini", action="store_true", help="also time dbini-torch (pip package dbini-torch)")
    ap.add_argument("--parts", default="diligent,suite,mp")
    ap.add_argument("--objects", default=",".join(BINI_MM))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--suite-size", type=int, default=128)
    ap.add_argument("--mp-size", type=int, default=1024)
    ap.add_argument("--mp-bini", action="store_true", help="also run the reference on the ~1 MP map (minutes)")
    ap.add_argument("--launch", default="auto", help="BiNI's launch on the device: auto, tasks or persistent")
    ap.add_argument("--compare-tasks", action="store_true",
                    help="diligent part: also time launch='tasks' (the per-phase launches) beside --launch")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    from gpps import _taichi
    from gpps.camera import Orthographic, Perspective
    from gpps.flows.integrate import integrate_normals

    _taichi.init(args.device)
    bini = Bini(args.bini_path) if args.bini_path else None
    dbini = None
    dbini_error = None
    if args.dbini:
        try:
            dbini = Dbini(args.device)
        except Exception as e:  # noqa: BLE001 - reported, not fatal
            dbini_error = f"{type(e).__name__}: {e}"
            print(f"dbini-torch not available: {dbini_error}")
    parts = args.parts.split(",")
    from gpps.io import save_json

    path = Path(args.out) if args.out else ROOT / "perf" / "results" / f"integration_bini_{args.device.replace(':', '')}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    out = {"device": args.device, "host": platform.node(), "cpu_count": os.cpu_count(), "repeat": args.repeat,
           "bini_reference": str(args.bini_path) if bini else None,
           "dbini_torch": (dbini.dev.type if dbini else None), "dbini_error": dbini_error,
           "note": "gpps = integrate_normals(bilateral=True) (BiNI's defaults, float64, device Jacobi-PCG); "
                   "times: median after one warm-up run"}

    def gpps_bini(n, mask, cam, launch=args.launch):
        return integrate_normals(n, mask, camera=cam, bilateral=True, device=args.device, bilateral_launch=launch)

    out["launch"] = args.launch

    if "diligent" in parts:
        rows = []
        print(f"{'object':8s} {'pixels':>7s} {'gpps mm':>8s} {'ratio':>6s} {'it':>4s} {'cg':>6s} {'gpps s':>7s} "
              f"{'BiNI mm':>8s} {'it':>4s} {'BiNI s':>7s} {'speedup':>7s} {'dbini mm':>8s} {'dbini s':>8s} "
              f"{'x dbini':>7s}")
        for name in args.objects.split(","):
            n, mask, K, gt = load(Path(args.data) / "integration" / "diligent" / name)
            cam = Perspective(K)
            res, t_g, ts_g = timed(lambda: gpps_bini(n, mask, cam), args.repeat)
            row = dict(object=name, pixels=int(mask.sum()), gpps_mm=made(res.depth, res.mask, gt), bini_published_mm=BINI_MM[name],
                       outer_iterations=res.outer_iterations, cg_iterations=res.iterations, gpps_s=t_g, gpps_runs_s=ts_g)
            row["ratio_to_published"] = row["gpps_mm"] / BINI_MM[name]
            if args.compare_tasks:
                rt, t_t, ts_t = timed(lambda: gpps_bini(n, mask, cam, "tasks"), args.repeat)
                row.update(tasks_s=t_t, tasks_runs_s=ts_t, tasks_mm=made(rt.depth, rt.mask, gt),
                           tasks_outer_iterations=rt.outer_iterations, tasks_cg_iterations=rt.iterations,
                           speedup_vs_tasks=t_t / t_g)
                print(f"{name:8s} tasks launch: {t_t:.4f} s ({rt.outer_iterations} / {rt.iterations} iterations, "
                      f"{row['tasks_mm']:.4f} mm); this launch {t_g:.4f} s: {t_t / t_g:.1f}x", flush=True)
            if bini:
                (d, it), t_b, ts_b = timed(lambda: bini(n, mask, K=K), args.repeat)
                row.update(bini_mm=made(d, mask, gt), bini_iterations=it, bini_s=t_b, bini_runs_s=ts_b,
                           speedup_vs_bini=t_b / t_g)
            if dbini:
                try:
                    (d, it), t_d, ts_d = timed(lambda: dbini(n, mask, K=K), args.repeat, dbini.sync)
                    row.update(dbini_mm=made(d, mask, gt), dbini_iterations=it, dbini_s=t_d, dbini_runs_s=ts_d,
                               speedup_vs_dbini=t_d / t_g)
                except Exception as e:  # noqa: BLE001
                    row["dbini_error"] = f"{type(e).__name__}: {e}"
            rows.append(row)
            print(f"{name:8s} {row['pixels']:7d} {row['gpps_mm']:8.4f} {row['ratio_to_published']:6.3f} "
                  f"{res.outer_iterations:4d} {res.iterations:6d} {t_g:7.3f} "
                  f"{row.get('bini_mm', float('nan')):8.4f} {row.get('bini_iterations', 0):4d} "
                  f"{row.get('bini_s', float('nan')):7.3f} {row.get('speedup_vs_bini', float('nan')):7.2f} "
                  f"{row.get('dbini_mm', float('nan')):8.4f} {row.get('dbini_s', float('nan')):8.3f} "
                  f"{row.get('speedup_vs_dbini', float('nan')):7.1f}", flush=True)
        out["diligent"] = rows
        out["diligent_summary"] = {
            "all_within_1p1x_of_published": all(r["ratio_to_published"] <= 1.1 for r in rows),
            "gpps_total_s": sum(r["gpps_s"] for r in rows),
            "bini_total_s": sum(r.get("bini_s", 0.0) for r in rows) if bini else None,
            "dbini_total_s": sum(r.get("dbini_s", 0.0) for r in rows) if dbini else None,
        }
        print(out["diligent_summary"])
        save_json(path, out)  # after each part: a later part that runs out of time loses only itself

    if "suite" in parts:
        from discontinuity_scenes import SCENES, render_scene, surface_errors

        rows = []
        print(f"suite at {args.suite_size}^2: worst per-piece mean |error| / depth range (interior: >= 3 px from an edge)")
        for camera in ("orthographic", "perspective"):
            for name in SCENES:
                sc = render_scene(name, args.suite_size, camera)
                cam = Perspective(sc["K"]) if camera == "perspective" else Orthographic(sc["pixel_size"])
                persp = camera == "perspective"
                row = dict(scene=name, camera=camera, size=args.suite_size)
                ests = {}
                r = gpps_bini(sc["normals"], sc["mask"], cam)
                ests["gpps_bini"] = (r.depth, r.mask)
                row.update(outer_iterations=r.outer_iterations, cg_iterations=r.iterations)
                r = integrate_normals(sc["normals"], sc["mask"], camera=cam, device=args.device)
                ests["poisson"] = (r.depth, r.mask)
                if bini:
                    d, _ = bini(sc["normals"], sc["mask"], K=sc.get("K"), step_size=sc.get("pixel_size", 1.0))
                    ests["bini_reference"] = (d, sc["mask"])
                for key, (d, m) in ests.items():
                    for margin, tag in ((0, ""), (3, "_interior")):
                        pieces, rng = surface_errors(d, sc["depth"], sc["labels"], m, persp, margin)
                        row[key + tag] = max(p["mean"] for p in pieces) / rng
                row["meets_1e-3"] = row["gpps_bini"] <= 1e-3
                rows.append(row)
                print(f"{camera[:5]} {name:8s} gpps BiNI {row['gpps_bini']:.2e} (interior {row['gpps_bini_interior']:.2e})"
                      f"  Poisson {row['poisson']:.2e}"
                      + (f"  BiNI reference {row['bini_reference']:.2e}" if bini else ""), flush=True)
        out["suite"] = rows
        save_json(path, out)

    if "mp" in parts:
        from discontinuity_scenes import render_scene

        sc = render_scene("overlap", args.mp_size, "perspective")
        cam = Perspective(sc["K"])
        n, mask = sc["normals"], sc["mask"]
        res, t_g, ts_g = timed(lambda: gpps_bini(n, mask, cam), args.repeat)
        row = dict(scene="overlap", camera="perspective", size=args.mp_size, pixels=int(mask.sum()), gpps_s=t_g,
                   gpps_runs_s=ts_g, outer_iterations=res.outer_iterations, cg_iterations=res.iterations,
                   gpps_timings=res.timings, target_s=0.020)
        print(f"{args.mp_size}^2 map ({row['pixels']} px): gpps {t_g * 1e3:.1f} ms, {res.outer_iterations} IRLS, {res.iterations} CG "
              f"iterations ({(res.timings.get('solve', 0)) / max(res.iterations, 1) * 1e6:.1f} us per CG iteration)",
              flush=True)
        save_json(path, {**out, "mp": row})
        if dbini:
            try:  # one run (dbini-torch is warm from the other parts, or pays its warm-up here)
                dbini.sync()
                t0 = time.perf_counter()
                dbini(n, mask, K=sc["K"])
                dbini.sync()
                t_d = time.perf_counter() - t0
                row.update(dbini_s=t_d, dbini_runs_s=[t_d], speedup_vs_dbini=t_d / t_g)
                print(f"   dbini-torch {t_d:.3f} s ({t_d / t_g:.1f}x gpps)", flush=True)
            except Exception as e:  # noqa: BLE001
                row["dbini_error"] = f"{type(e).__name__}: {e}"
                print("   dbini-torch failed:", row["dbini_error"])
        if bini and args.mp_bini:
            (d, it), t_b, _ = timed(lambda: bini(n, mask, K=sc["K"]), 1)
            row.update(bini_s=t_b, speedup_vs_bini=t_b / t_g)
            print(f"   BiNI reference {t_b:.2f} s ({t_b / t_g:.1f}x gpps)", flush=True)
        out["mp"] = row

    save_json(path, out)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
