"""How fast BiNI's inner solves could be on this CPU: a compiled floor beside BiNI's reference and gpps (issue 21).

Issue 21 asks for the default integrator (BiNI, faithful: every DiLiGenT map within 1.1x of BiNI's published
error) to run at least 5x faster than BiNI's reference code in the same run.  BiNI's accuracy is that of its
trajectory: warm-started Jacobi-PCG to a relative residual of 1e-3 inside each IRLS iteration (gpps reproduces
its outer and CG iteration counts exactly, ``perf/integration_bini.py``).  The CG iterations are the cost, so
this script measures what one such iteration costs at best on this machine, written by hand:

* the same float64 iteration as gpps's CPU build (:func:`gpps.kernels.bini._cg_serial_kernel`: the fused
  ``p = z + beta p``, ``q = A p`` over the compact pixel list with its four neighbour indices, ``p.q``; then
  ``x += a p``, ``r -= a q``, ``z = D^-1 r``, ``|r|^2``, ``r.z``), branch-free (a missing neighbour indexes the
  pixel itself, whose term is then exactly 0), in C compiled with ``gcc -O3 -march=native -ffast-math`` (free
  to reorder and vectorise the sums), on one thread and with OpenMP on every core (static schedule, the sums
  by OpenMP reductions);
* a structured variant (the bounding box, neighbours at +-1 and +-W, contiguous loads the compiler can
  vectorise), which costs the box's extra cells.

``floor_s`` = gpps's CG iteration count on the map x the fastest of these per iteration: the CG alone, without
BiNI's per-IRLS assembly, reweighting and energy (which any implementation adds).  ``max_speedup`` = BiNI's
reference time / ``floor_s``: what an implementation of the same trajectory written this way (float64, the CG
alone, on every core) gains over the reference on this machine; the other per-iteration work only lowers it.

Perf-only: needs ``gcc`` with OpenMP (a C compiler is not a runtime dependency of gpps), BiNI's reference
(``--bini-path``, as perf/integration_bini.py) and the DiLiGenT maps in ../shared/data/integration/diligent.

Usage:  python perf/bini_cpu_floor.py --bini-path /tmp/bini21 [--repeat 3] [--objects bear,cow] [--out FILE]
"""

from __future__ import annotations

import argparse
import ctypes
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from integration_bini import BINI_MM, Bini, load, made, timed  # noqa: E402

C_SOURCE = r"""
#include <omp.h>
void set_threads(int k) { omp_set_num_threads(k); }
/* compact layout: nb[4 p + k] = right, left, down, up (the pixel itself where there is none) */
void cg_compact(int iters, int n, double beta, double a, double* z, double* p0, double* p1, double* q,
                double* x, double* r, const double* Wr, const double* Wd, const double* dv, const int* nb,
                double* out) {
  for (int t = 0; t < iters; t++) {
    double pq = 0;
    #pragma omp parallel for reduction(+:pq) schedule(static)
    for (int p = 0; p < n; p++) {
      double pp = z[p] + beta * p0[p];
      int o0 = nb[4 * p], o1 = nb[4 * p + 1], o2 = nb[4 * p + 2], o3 = nb[4 * p + 3];
      double s = Wr[p] * (pp - (z[o0] + beta * p0[o0])) + Wr[o1] * (pp - (z[o1] + beta * p0[o1]))
               + Wd[p] * (pp - (z[o2] + beta * p0[o2])) + Wd[o3] * (pp - (z[o3] + beta * p0[o3]));
      q[p] = s; p1[p] = pp; pq += pp * s;
    }
    double rr = 0, rz = 0;
    #pragma omp parallel for reduction(+:rr,rz) schedule(static)
    for (int p = 0; p < n; p++) {
      x[p] += a * p1[p]; double rv = r[p] - a * q[p]; r[p] = rv; double zv = dv[p] * rv; z[p] = zv;
      rr += rv * rv; rz += rv * zv;
    }
    out[0] = pq; out[1] = rr; out[2] = rz;
  }
}
/* structured layout: cells n0 .. n1 - 1 of a (H, W) box, weights 0 off the mask */
void cg_box(int iters, int n0, int n1, int W, double beta, double a, double* z, double* p0, double* p1,
            double* q, double* x, double* r, const double* Wr, const double* Wd, const double* dv, double* out) {
  for (int t = 0; t < iters; t++) {
    double pq = 0;
    #pragma omp parallel for reduction(+:pq) schedule(static)
    for (int p = n0; p < n1; p++) {
      double pp = z[p] + beta * p0[p];
      double s = Wr[p] * (pp - (z[p + 1] + beta * p0[p + 1])) + Wr[p - 1] * (pp - (z[p - 1] + beta * p0[p - 1]))
               + Wd[p] * (pp - (z[p + W] + beta * p0[p + W])) + Wd[p - W] * (pp - (z[p - W] + beta * p0[p - W]));
      q[p] = s; p1[p] = pp; pq += pp * s;
    }
    double rr = 0, rz = 0;
    #pragma omp parallel for reduction(+:rr,rz) schedule(static)
    for (int p = n0; p < n1; p++) {
      x[p] += a * p1[p]; double rv = r[p] - a * q[p]; r[p] = rv; double zv = dv[p] * rv; z[p] = zv;
      rr += rv * rv; rz += rv * zv;
    }
    out[0] = pq; out[1] = rr; out[2] = rz;
  }
}
"""


def build(tmp: Path, flags: list[str]) -> ctypes.CDLL:
    """Compile :data:`C_SOURCE` with ``gcc`` and ``flags`` into ``tmp``; the loaded library."""
    src = tmp / "cg.c"
    src.write_text(C_SOURCE)
    lib = tmp / f"cg{abs(hash(tuple(flags)))}.so"
    subprocess.run(["gcc", "-O3", "-march=native", "-fopenmp", "-shared", "-fPIC", *flags, "-o", str(lib), str(src)],
                   check=True)
    return ctypes.CDLL(str(lib))


def per_iteration(fn, args, iters: int, repeat: int) -> float:
    """Seconds per CG iteration: the best of ``repeat`` calls of ``iters`` iterations after one warm-up call."""
    fn(ctypes.c_int(iters), *args)
    best = float("inf")
    for _ in range(repeat):
        t = time.perf_counter()
        fn(ctypes.c_int(iters), *args)
        best = min(best, time.perf_counter() - t)
    return best / iters


def floor_per_iteration(lib, mask: np.ndarray, iters: int, repeat: int) -> dict:
    """Seconds per CG iteration of both layouts on ``mask``'s pixels (values random: no branch depends on them)."""
    P = ctypes.POINTER(ctypes.c_double)
    rng = np.random.default_rng(0)
    h, w = mask.shape
    ii, jj = np.nonzero(mask)
    n = ii.size
    lab = -np.ones((h + 2, w + 2), np.int32)
    lab[ii + 1, jj + 1] = np.arange(n, dtype=np.int32)
    nb = np.stack([lab[ii + 1, jj + 2], lab[ii + 1, jj], lab[ii + 2, jj + 1], lab[ii, jj + 1]], 1)
    nb = np.ascontiguousarray(np.where(nb >= 0, nb, np.arange(n, dtype=np.int32)[:, None]), dtype=np.int32)

    def vectors(size):
        v = {k: np.zeros(size) for k in ("z", "p0", "p1", "q", "x", "r", "Wr", "Wd", "dv")}
        for k in ("z", "r", "p0", "Wr", "Wd"):
            v[k][:] = rng.random(size)
        v["dv"][:] = 1.0 / (1.0 + rng.random(size))
        return v

    out = np.zeros(3)
    v = vectors(n)
    args = [ctypes.c_int(n), ctypes.c_double(0.5), ctypes.c_double(1e-3)]
    args += [v[k].ctypes.data_as(P) for k in ("z", "p0", "p1", "q", "x", "r", "Wr", "Wd", "dv")]
    args += [nb.ctypes.data_as(ctypes.POINTER(ctypes.c_int)), out.ctypes.data_as(P)]
    compact = per_iteration(lib.cg_compact, args, iters, repeat)
    i0, i1, j0, j1 = ii.min(), ii.max() + 1, jj.min(), jj.max() + 1
    H, W = i1 - i0 + 2, j1 - j0 + 2
    cells = H * W
    b = vectors(cells)
    args = [ctypes.c_int(W), ctypes.c_int(cells - W), ctypes.c_int(W), ctypes.c_double(0.5), ctypes.c_double(1e-3)]
    args += [b[k].ctypes.data_as(P) for k in ("z", "p0", "p1", "q", "x", "r", "Wr", "Wd", "dv")]
    args += [out.ctypes.data_as(P)]
    box = per_iteration(lib.cg_box, args, iters, repeat)
    return {"pixels": int(n), "box_cells": int(cells), "compact_s": compact, "box_s": box}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=os.environ.get("GPPS_DATA", str(ROOT.parent / "shared" / "data")))
    ap.add_argument("--bini-path", required=True, help="folder with BiNI's bilateral_normal_integration_cpu.py")
    ap.add_argument("--objects", default=",".join(BINI_MM))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--iters", type=int, default=200, help="CG iterations per timed call of the compiled floor")
    ap.add_argument("--out", default=str(ROOT / "perf" / "results" / "bini_cpu_floor_cpu.json"))
    a = ap.parse_args(argv)
    if shutil.which("gcc") is None:
        print("gcc not found: the compiled floor needs a C compiler with OpenMP")
        return 1

    from gpps import _taichi
    from gpps.camera import Perspective
    from gpps.flows.integrate import integrate_normals
    from gpps.io import save_json

    _taichi.init("cpu")
    bini = Bini(a.bini_path)
    cores = os.cpu_count()
    rows = []
    with tempfile.TemporaryDirectory() as td:
        lib = build(Path(td), ["-ffast-math"])
        libs = {"1 thread": 1, f"{cores} threads": cores}
        print(f"{'object':8s} {'pixels':>7s} {'cg':>6s} {'BiNI s':>7s} {'gpps s':>7s} {'ns/px 1t':>9s} "
              f"{'ns/px nt':>9s} {'box nt':>7s} {'floor s':>8s} {'max x':>6s} {'gpps x':>6s}")
        for name in a.objects.split(","):
            n, mask, K, gt = load(Path(a.data) / "integration" / "diligent" / name)
            cam = Perspective(K)
            res, t_g, _ = timed(lambda: integrate_normals(n, mask, camera=cam, bilateral=True, device="cpu"),
                                a.repeat)
            (d, it), t_b, _ = timed(lambda: bini(n, mask, K=K), a.repeat)
            row = {"object": name, "pixels": int(mask.sum()), "outer_iterations": res.outer_iterations,
                   "cg_iterations": res.iterations, "bini_outer_iterations": it, "gpps_s": t_g, "bini_s": t_b,
                   "gpps_mm": made(res.depth, res.mask, gt), "bini_mm": made(d, mask, gt)}
            for label, threads in libs.items():
                lib.set_threads(ctypes.c_int(threads))
                f = floor_per_iteration(lib, mask, a.iters, a.repeat)
                row[label] = f
            best = min(min(f["compact_s"], f["box_s"]) for f in (row[k] for k in libs))
            row["floor_s"] = best * res.iterations
            row["max_speedup"] = t_b / row["floor_s"]
            row["gpps_speedup"] = t_b / t_g
            nt = row[f"{cores} threads"]
            rows.append(row)
            print(f"{name:8s} {row['pixels']:7d} {res.iterations:6d} {t_b:7.3f} {t_g:7.3f} "
                  f"{row['1 thread']['compact_s'] / row['pixels'] * 1e9:9.2f} "
                  f"{nt['compact_s'] / row['pixels'] * 1e9:9.2f} {nt['box_s'] / row['pixels'] * 1e9:7.2f} "
                  f"{row['floor_s']:8.3f} {row['max_speedup']:6.2f} {row['gpps_speedup']:6.2f}", flush=True)
    out = {"host": platform.node(), "cpu": platform.processor() or platform.machine(), "cpu_count": cores,
           "repeat": a.repeat, "iters": a.iters, "bini_reference": str(a.bini_path),
           "note": "floor_s = gpps's CG iterations (= BiNI's trajectory) x the fastest compiled float64 CG iteration "
                   "(compact or box layout, 1 or all threads); the CG alone: BiNI's assembly, reweighting and energy "
                   "come on top. max_speedup = bini_s / floor_s. Times: best of repeat (floor), median of repeat "
                   "after a warm-up (gpps, BiNI)",
           "rows": rows,
           "max_speedup_min": min(r["max_speedup"] for r in rows),
           "max_speedup_max": max(r["max_speedup"] for r in rows)}
    save_json(a.out, out)
    print(f"max speedup over BiNI at the floor: {out['max_speedup_min']:.2f}-{out['max_speedup_max']:.2f}x; "
          f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
