"""Device-resident Poisson integration speed (issue 4): cold to tolerance and warm-started, per piece.

The streaming integrator (:class:`gpps.pipeline.integration_device.StreamIntegrator`,
fused Taichi kernels, normals and depth on the device) on the smooth test
surface of ``perf/integration_speed.py`` (full square, orthographic, float32).
"To tolerance" is measured against the solution, not the float32 residual
(whose floor at 1024^2 is near 1e-3 of |b|, see the JSON): the reference is the
same integrator in float64 run to a relative residual of 1e-10, and a run
counts as converged when its mean absolute depth difference to the reference
is at most ``--accuracy`` (default 1e-4) of the depth range, ten times below
the 1e-3 the analytic-surface tests ask of the discretisation.

Per size and configuration (``coarsest`` x ``method``):

* pieces, median of device-synchronised repeats after warm-up: an empty
  Taichi launch (``noop``), the coarsest-level solve, one V-cycle, one
  iteration (PCG iteration or V-cycle correction), the right-hand side, the
  final depth write (``finish``), and one host read of the scalars;
* cold: from u = 0, ``k`` iterations with no host sync for k = 1..10: time and
  depth error; the smallest k within ``--accuracy`` is the cold time;
* warm: converged on frame A, then frame B (the surface shifted by 0.2 % of
  the width, a streaming step): ``k`` iterations from A's solution, k = 1..4,
  time and depth error against B's reference.  This is the latency of one
  isolated frame: host sync before and after, so the host-side launch
  (Taichi's argument handling of the two torch tensors alone is about 90 us,
  see perf/integration_launch_overhead.py) adds to the device time;
* warm, streamed: 20 frames alternating B, A, B, ... (each a 0.2 % step from
  the previous), ``k`` cycles each, submitted back to back as a stream does;
  time per frame = total / 20, and the largest depth error along the
  sequence (checked in an untimed pass).

* warm, queued (CUDA): the same 20 one-cycle frames queued while the GPU sleeps
  (``torch.cuda._sleep``), host time of queueing them and device time between two
  events around them, per frame: the device's share alone;
* warm with the normals and the depth in Taichi ndarrays instead of torch tensors
  (isolated and streamed), since Taichi's host-side argument handling differs.

Launch forms (``--launches``): ``tasks`` (one Taichi task per phase) and
``persistent:<blocks per SM>:<size>`` (levels of at most ``size`` pixels a side in one
persistent task with grid barriers; see ``StreamIntegratorConfig.launch``); a trailing
``:plain`` calls the frame kernel through Taichi's own argument handling instead of
:class:`gpps._taichi.DirectLaunch` (``StreamIntegratorConfig.direct_launch``).

Roofline: the copy bandwidth is measured in the same run (torch device copy
of 256 MiB, read + write); the warm one-cycle frame's DRAM traffic is counted
from its passes (float32 fields, per pixel: normals to steps 24 B,
right-hand side with the first residual 32, descent 21 (pre-smoothing 20,
restriction 1), ascent 45 (first sweep 25, second sweep into the depth
update 20), the finish's sum and write passes 24; every coarser level adds
its descent and ascent at 1/4 the pixels of the level above), and ``roofline_ratio`` = the
measured warm time / (bytes / bandwidth).  At these sizes the frame is bound
by launches, not memory: the ratio says how far.

Usage:  python perf/integration_device_speed.py [--device cuda:0] [--sizes 256,1024] [--repeat 20]
            [--launches tasks,persistent:2:256] [--out FILE]
Writes perf/results/integration_device_speed_<device>.json.  Committed H100 runs (all ``--quick``,
``--sizes 1024 --coarsest 16 --methods multigrid --max-cold 3``):
integration_device_speed_cuda0_H100.json (``--launches persistent:2:256,persistent:2:512``: the
default and the level-1-inside form, with the one-pass right-hand side and the CUDA warp sums);
..._H100_direct.json (``persistent:2:256,persistent:2:256:plain``: the frame launched through
``DirectLaunch`` against Taichi's own call, before those two); ..._H100_p512.json (``persistent:2:512``,
same commit as _direct); ..._H100_{tasks,persistent}.json (full runs of an earlier session, one
launch form each, plain calls).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))
sys.path.insert(0, str(ROOT / "perf"))

from _fused_variants import profiling_kernels  # noqa: E402
from integration_speed import surface_normals  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--sizes", default="256,1024")
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--accuracy", type=float, default=1e-4)
    ap.add_argument("--coarsest", default="16,32")
    ap.add_argument("--methods", default="pcg,multigrid")
    ap.add_argument("--launches", default="tasks,persistent:2:256",
                    help="multigrid frame launch forms, comma-separated: tasks, or "
                         "persistent:<blocks per SM>:<largest level side in the persistent task>")
    ap.add_argument("--max-cold", type=int, default=10, help="cold runs of 1..N iterations (each N <= 4 compiles a kernel)")
    ap.add_argument("--quick", action="store_true",
                    help="no per-piece timings and no tol mode; cold runs of --max-cold cycles only; warm and "
                         "streamed runs of one cycle only (fewer kernels to compile on a fresh GPU machine)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)

    from gpps import _taichi
    from gpps.camera import Orthographic
    from gpps.pipeline.integration_device import StreamIntegrator, StreamIntegratorConfig

    ti = _taichi.init(a.device)
    dev_name = a.device
    try:
        import torch

        cuda = a.device.startswith("cuda")
        if cuda:
            dev_name = torch.cuda.get_device_name(0)
    except ImportError:  # CPU runs here need no torch
        torch, cuda = None, False

    def dev(x):
        return torch.from_numpy(np.ascontiguousarray(x)).to("cuda") if cuda else np.ascontiguousarray(x)

    def host(x):
        return x.cpu().numpy() if cuda else x

    def med(fn, repeat, inner=1):
        fn()
        ti.sync()
        ts = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            ti.sync()
            ts.append((time.perf_counter() - t0) / inner)
        return statistics.median(ts)

    bandwidth = None
    if cuda:
        src = torch.empty(64 * 2**20, dtype=torch.float32, device="cuda")
        dst = torch.empty_like(src)
        t = med(lambda: dst.copy_(src), a.repeat, 5)
        bandwidth = 2 * src.numel() * 4 / t  # bytes read + written per second
        del src, dst

    def frame_bytes(shapes):
        """DRAM bytes of one warm one-cycle multigrid frame (float32), from its passes (see the docstring)."""
        h, w = shapes[0]
        total = (24 + 32 + 24) * h * w  # steps, rhs + residual, finish
        for (hh, ww) in shapes[:-1]:
            total += (21 + 45) * hh * ww  # descent and ascent of each level but the coarsest
        return total

    rows = []
    for n in map(int, a.sizes.split(",")):
        mask = np.ones((n, n), bool)
        cam = Orthographic(1.0 / n)
        nA = surface_normals(n, 0.0).astype(np.float32)
        nB = surface_normals(n, 0.002).astype(np.float32)
        # references: float64, relative residual 1e-10
        ref = StreamIntegrator(mask, cam, StreamIntegratorConfig(dtype="float64", check_every=1), device=a.device)
        refs = {}
        for tag, nn in (("A", nA), ("B", nB)):
            o = dev(np.zeros((n, n), np.float32))
            ref.reset()
            ref.step(dev(nn), o, tol=1e-10, max_iterations=400)
            refs[tag] = host(o).astype(np.float64)
        ref.close()
        rng = float(np.ptp(refs["A"]))
        nAd, nBd = dev(nA), dev(nB)
        combos = []
        for coarsest in map(int, a.coarsest.split(",")):
            for method in a.methods.split(","):
                for launch in (a.launches.split(",") if method == "multigrid" else ["tasks"]):
                    if launch.startswith("persistent") and not cuda:
                        continue
                    parts = launch.split(":")
                    plain = parts[-1] == "plain"
                    parts = parts[:-1] if plain else parts
                    kind, bps, psize = (parts + ["2", "256"])[:3]
                    combos.append((coarsest, method, kind, int(bps), int(psize), not plain))
        if True:
            for coarsest, method, launch, bps, psize, direct in combos:
                cfg = StreamIntegratorConfig(coarsest=coarsest, method=method, launch=launch, blocks_per_sm=bps,
                                             persistent_size=psize, direct_launch=direct)
                si = StreamIntegrator(mask, cam, cfg, device=a.device)
                K = {**si._K, **profiling_kernels(si._K)}  # with vcycle_only, coarse_only, noop
                out = dev(np.zeros((n, n), np.float32))
                si.step(nAd, out, iterations=1)  # compile
                if not a.quick:
                    K["vcycle_only"](), K["coarse_only"](), K["noop"](), K["scalars"]()
                step = K["mg_step"] if method == "multigrid" else K["pcg_iteration"]
                rhs = (lambda: K["rhs_only"](nAd, *si._cam, cfg.min_nz)) if method == "multigrid" else \
                    (lambda: K["rhs_begin"](nAd, *si._cam, cfg.min_nz))
                row = {"size": n, "coarsest": coarsest, "method": method, "launch": si.launch,
                       "direct_launch": direct,
                       "blocks_per_sm": si._bps if si.launch == "persistent" else None,
                       "persistent_levels": [f"{hh}x{ww}" for (_, hh, ww) in si.levels[si._top:]]
                       if si.launch == "persistent" else [], "levels": len(si.levels),
                       "coarsest_cells": int(si._F["cidx"].shape[0])}
                row["pieces_us"] = {} if a.quick else {
                    "noop_launch": 1e6 * med(K["noop"], a.repeat, 10),
                    "coarse_solve": 1e6 * med(K["coarse_only"], a.repeat, 10),
                    "vcycle": 1e6 * med(K["vcycle_only"], a.repeat, 10),
                    "iteration": 1e6 * med(step, a.repeat, 10),
                    "rhs": 1e6 * med(rhs, a.repeat, 5),
                    "finish": 1e6 * med(lambda: K["finish"](out, 0.0), a.repeat, 5),
                    "read_scalars": 1e6 * med(lambda: K["scalars"](), a.repeat, 5),
                }
                # cold: k iterations, no host sync
                cold = []
                for k in ([a.max_cold] if a.quick else range(1, a.max_cold + 1)):
                    def run(k=k):
                        si.reset()
                        si.step(nAd, out, iterations=k)
                    t = med(run, max(5, a.repeat // 2))
                    d = host(out).astype(np.float64)
                    d = d - d.mean() + refs["A"].mean()
                    cold.append({"iterations": k, "ms": 1e3 * t, "depth_error": float(np.abs(d - refs["A"]).mean() / rng)})
                row["cold"] = cold
                ok = [c for c in cold if c["depth_error"] <= a.accuracy]
                row["cold_to_accuracy"] = ok[0] if ok else None
                # the tol mode (host checks of the residual)
                def run_tol():
                    si.reset()
                    si.step(nAd, out, tol=1e-3)
                if not a.quick:
                    row["cold_tol_1e-3"] = {"ms": 1e3 * med(run_tol, max(5, a.repeat // 2)),
                                            "iterations": si.last_iterations, "residual": si.last_residual}
                nfr = 20

                def rel_err(d, tag):
                    """Mean depth error against reference ``tag``, after the offset, over the depth range."""
                    d = d.astype(np.float64)
                    d = d - d.mean() + refs[tag].mean()
                    return float(np.abs(d - refs[tag]).mean() / rng)

                def converge(A, O):
                    si.reset()
                    si.step(A, O, iterations=12)
                    ti.sync()

                def isolated(A, B, O, k):
                    """Median seconds of k cycles on B from A's solution, synced before and after."""
                    ts = []
                    for _ in range(max(5, a.repeat // 2)):
                        converge(A, O)
                        t0 = time.perf_counter()
                        si.step(B, O, iterations=k)
                        ti.sync()
                        ts.append(time.perf_counter() - t0)
                    return statistics.median(ts)

                def streamed(A, B, O, k):
                    """Median seconds per frame of nfr frames B, A, B, ... of k cycles, back to back."""
                    ts = []
                    for _ in range(max(5, a.repeat // 3)):
                        converge(A, O)
                        t0 = time.perf_counter()
                        for x in [B, A] * (nfr // 2):
                            si.step(x, O, iterations=k)
                        ti.sync()
                        ts.append((time.perf_counter() - t0) / nfr)
                    return statistics.median(ts)

                # warm: converge on A, then k iterations on B from A's solution
                warm = []
                for k in ((1,) if a.quick else range(1, 5)):
                    t = isolated(nAd, nBd, out, k)
                    warm.append({"iterations": k, "ms": 1e3 * t, "depth_error": rel_err(host(out), "B")})
                row["warm"] = warm
                ok = [w for w in warm if w["depth_error"] <= a.accuracy]
                row["warm_to_accuracy"] = ok[0] if ok else None
                # warm, streamed: frames alternate B, A, B, ... (each 0.2 % from the one before), k cycles
                # each, submitted back to back as a stream does (no host sync between frames, so the host's
                # launch of frame i+1 overlaps the device's work on frame i); time per frame = total / frames.
                # The accuracy is checked along the same sequence in an untimed pass with host copies.
                seq = [nBd, nAd] * (nfr // 2)
                stream = []
                for k in ((1,) if a.quick else (1, 2)):
                    t = streamed(nAd, nBd, out, k)
                    converge(nAd, out)
                    errs = []
                    for idx, x in enumerate(seq):
                        si.step(x, out, iterations=k)
                        errs.append(rel_err(host(out), "B" if idx % 2 == 0 else "A"))
                    stream.append({"iterations": k, "ms_per_frame": 1e3 * t, "max_depth_error": max(errs),
                                   "frames": nfr})
                row["warm_stream"] = stream
                if cuda:
                    # device time of a streamed warm frame: the GPU is put to sleep while the host queues
                    # the 20 frames, then two events around them time the device alone
                    hs, ds = [], []
                    for _ in range(5):
                        converge(nAd, out)
                        torch.cuda.synchronize()
                        e0, e1 = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                        torch.cuda._sleep(int(40e6))
                        e0.record()
                        t0 = time.perf_counter()
                        for x in seq:
                            si.step(x, out, iterations=1)
                        t1 = time.perf_counter()
                        e1.record()
                        torch.cuda.synchronize()
                        hs.append(1e3 * (t1 - t0) / nfr)
                        ds.append(e0.elapsed_time(e1) / nfr)
                    row["warm_1_cycle_queued"] = {"host_ms_per_frame": statistics.median(hs),
                                                  "device_ms_per_frame": statistics.median(ds)}
                    # the same frames with the normals and the depth in Taichi ndarrays (which Warp can
                    # write in place through their device pointers) instead of torch tensors: Taichi's
                    # host-side argument handling is the cheaper one
                    tA, tB, tO = ti.ndarray(ti.f32, (n, n, 3)), ti.ndarray(ti.f32, (n, n, 3)), ti.ndarray(ti.f32, (n, n))
                    tA.from_numpy(nA)
                    tB.from_numpy(nB)
                    t_iso = isolated(tA, tB, tO, 1)
                    row["warm_1_cycle_taichi_ndarrays"] = {"isolated_ms": 1e3 * t_iso,
                                                           "isolated_depth_error": rel_err(tO.to_numpy(), "B"),
                                                           "streamed_ms_per_frame": 1e3 * streamed(tA, tB, tO, 1)}
                ok = [w for w in stream if w["max_depth_error"] <= a.accuracy]
                row["warm_stream_to_accuracy"] = ok[0] if ok else None
                if bandwidth and method == "multigrid":
                    by = frame_bytes([(hh, ww) for (_, hh, ww) in si.levels])
                    w1 = warm[0]["ms"] * 1e-3
                    wd = row["warm_1_cycle_queued"]["device_ms_per_frame"] * 1e-3
                    row["warm_1_cycle_roofline"] = {"bytes": by, "bandwidth_Bps": bandwidth,
                                                    "bound_ms": 1e3 * by / bandwidth,
                                                    "roofline_ratio": w1 / (by / bandwidth),
                                                    "device_roofline_ratio": wd / (by / bandwidth)}
                si.close()
                rows.append(row)
                p = row["pieces_us"]
                ca, wa = row["cold_to_accuracy"], row["warm_to_accuracy"]
                q = row.get("warm_1_cycle_queued", {})
                print(f"{n:5d} coarsest {coarsest:2d} {method:9s} {si.launch}:{row['blocks_per_sm']}:{psize}{'' if direct else ':plain'} | warm 1-cycle queued: "
                      f"host {q.get('host_ms_per_frame', float('nan')):.3f} device {q.get('device_ms_per_frame', float('nan')):.3f} "
                      f"ms/frame; Taichi ndarrays: {row.get('warm_1_cycle_taichi_ndarrays')}", flush=True)
                pieces = " ".join(f"{k} {v:.1f}" for k, v in p.items()) + " us | " if p else ""
                tol = f" | tol1e-3 {row['cold_tol_1e-3']['ms']:.3f} ms" if "cold_tol_1e-3" in row else ""
                sw = row["warm_stream_to_accuracy"]
                print(f"{n:5d} coarsest {coarsest:2d} {method:9s} | {pieces}cold {ca['iterations'] if ca else '-'} it "
                      f"{ca['ms'] if ca else float('nan'):.3f} ms | warm {wa['iterations'] if wa else '-'} it "
                      f"{wa['ms'] if wa else float('nan'):.3f} ms | streamed warm {sw['iterations'] if sw else '-'} it "
                      f"{sw['ms_per_frame'] if sw else float('nan'):.3f} ms/frame{tol}", flush=True)
    from gpps.io import save_json

    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"integration_device_speed_{a.device.replace(':', '')}.json"
    save_json(out, {"device": a.device, "device_name": dev_name, "accuracy": a.accuracy, "dtype": "float32",
                    "copy_bandwidth_Bps": bandwidth,
                    "surface": "perf/integration_speed.py surface_normals, full square, orthographic; warm frame shifted 0.002",
                    "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
