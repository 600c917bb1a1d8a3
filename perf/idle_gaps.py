"""Why the GPU waits during a warm ``gpps.reconstruct`` call: its idle time charged to the host code running then.

The pipeline's stage methods (``perf/stage_timeline.py``'s list) are wrapped in ``torch.profiler.record_function``
ranges, without synchronising (the call keeps its real overlap of host and device).  One warm call runs under
``torch.profiler`` with CUDA activity tracing (CUPTI sees Warp's and Taichi's kernels and copies).  The GPU's busy
intervals are merged; every idle stretch between them (and before the first and after the last, up to the call's
ends) is charged, piece by piece, to the innermost wrapped method the host was in at that time.  A method with
much idle time charged to it is host work the device waited for (Python, a host computation, or a copy's wait
whose result the next launch needs).

Writes ``--out`` (JSON): the call's wall time, GPU busy time, idle time per method (sorted), and per method its
inclusive host time and the GPU busy time inside its ranges.  Needs CUDA and torch.

Usage:  python perf/idle_gaps.py [--synthetic 256] [--images 3] [--device cuda:0] [--warm 3] [--reconstructor]
        --out FILE
"""

from __future__ import annotations

import argparse
import functools
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))

import stage_timeline as st  # noqa: E402  (its WRAPS, and the same environment)
from _common import reconstruct_case, reconstructor_case  # noqa: E402

PREFIX = "gpps::"


def _extra():
    """Finer ranges than stage_timeline's list: the material search, the front's launches, the solver's small
    calls and the integrator."""
    from gpps.pipeline import material_search as ms
    from gpps.pipeline import solver as sv
    return [
        (ms.NelderMeadSearch, "upload", "search.upload"), (ms.NelderMeadSearch, "step", "search.step"),
        (ms.NelderMeadSearch, "fetch", "search.fetch"), (ms.NelderMeadSearch, "__init__", "search.__init__"),
        (st.front_mod.DeviceFront, "write_back", "front.write_back"),
        (st.front_mod.DeviceFront, "fetch_sources", "front.fetch_sources"),
        (st.front_mod.DeviceFront, "__init__", "front.__init__"),
        (sv.PixelSolver, "set_config", "solver.set_config"), (sv.PixelSolver, "set_material", "solver.set_material"),
        (sv.PixelSolver, "set_mask", "solver.set_mask"), (sv.PixelSolver, "select_pixels", "solver.select_pixels"),
        (sv.PixelSolver, "save", "solver.save"), (sv.PixelSolver, "merge_saved", "solver.merge_saved"),
        (sv.PixelSolver, "load", "solver.load"), (sv.PixelSolver, "set_start", "solver.set_start"),
        (st.integ_mod.Integrator, "run", "integrator.run"),
        (st.ron_mod.RON, "_select_model", "material.select_model"),
        (st.rec_mod.Reconstructor, "__call__", "Reconstructor.call"),
        (st.ron_mod.RON, "_scorer_for", "material.scorer_for"),
        (st.rec_mod, "_reconstruct_impl", "reconstruct.impl") if hasattr(st.rec_mod, "_reconstruct_impl") else None,
    ]


def _wrap(owner, name: str, label: str) -> None:
    import torch

    fn = getattr(owner, name)

    @functools.wraps(fn)
    def inner(*a, **k):
        with torch.profiler.record_function(PREFIX + label):
            return fn(*a, **k)
    setattr(owner, name, inner)


def _merge(spans):
    out = []
    for t0, t1 in sorted(spans):
        if out and t0 <= out[-1][1]:
            out[-1][1] = max(out[-1][1], t1)
        else:
            out.append([t0, t1])
    return out


def analyse(events, t_start: float, t_end: float) -> dict:
    """Idle GPU time per innermost host range (microseconds in, milliseconds out)."""
    gpu, ranges = [], []
    kernels: dict = defaultdict(lambda: [0, 0.0])
    for e in events:
        t0, t1 = e.time_range.start, e.time_range.end
        if e.device_type.name == "CUDA":
            if e.name.startswith(PREFIX):  # (the profiler's GPU-side copies of the host ranges: not work)
                continue
            gpu.append((t0, t1))
            k = kernels[e.name[:100]]
            k[0] += 1
            k[1] += t1 - t0
        elif e.name.startswith(PREFIX):
            ranges.append((t0, t1, e.name[len(PREFIX):]))
    busy = _merge(gpu)
    lo = min([t_start] + [r[0] for r in ranges])
    hi = max([t_end] + [r[1] for r in ranges] + [b[1] for b in busy])
    idle, cur = [], lo
    for b0, b1 in busy:
        if b0 > cur:
            idle.append((cur, b0))
        cur = max(cur, b1)
    if hi > cur:
        idle.append((cur, hi))
    # cut every idle stretch at the ranges' ends and charge each piece to the innermost range (latest start, then earliest end)
    cuts = sorted({t for r in ranges for t in r[:2]})
    charged: dict = defaultdict(float)
    for a, b in idle:
        pts = [a] + [t for t in cuts if a < t < b] + [b]
        for p0, p1 in zip(pts[:-1], pts[1:]):
            mid = 0.5 * (p0 + p1)
            inside = [r for r in ranges if r[0] <= mid < r[1]]
            label = max(inside, key=lambda r: (r[0], -r[1]))[2] if inside else "(outside every method)"
            charged[label] += p1 - p0
    host: dict = defaultdict(lambda: [0, 0.0, 0.0])
    for r0, r1, label in ranges:
        h = host[label]
        h[0] += 1
        h[1] += r1 - r0
        h[2] += sum(max(0.0, min(r1, b1) - max(r0, b0)) for b0, b1 in busy)
    return {
        "wall_ms": (hi - lo) * 1e-3,
        "gpu_busy_ms": sum(b1 - b0 for b0, b1 in busy) * 1e-3,
        "gpu_events": len(gpu),
        "kernels": {k: {"count": v[0], "gpu_ms": round(v[1] * 1e-3, 3)}
                    for k, v in sorted(kernels.items(), key=lambda kv: -kv[1][1])},
        "idle_ms_by_method": {k: round(v * 1e-3, 3) for k, v in sorted(charged.items(), key=lambda kv: -kv[1])},
        "methods": {k: {"calls": v[0], "host_ms": round(v[1] * 1e-3, 3), "gpu_busy_ms": round(v[2] * 1e-3, 3)}
                    for k, v in sorted(host.items(), key=lambda kv: -kv[1][1])},
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthetic", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--warm", type=int, default=3, help="unprofiled warm calls first (their times are reported)")
    ap.add_argument("--reconstructor", action="store_true",
                    help="the calls through one gpps.Reconstructor (the stages kept between calls)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    import torch
    from torch.profiler import ProfilerActivity, profile

    import gpps

    call = (reconstructor_case if a.reconstructor else reconstruct_case)(a.synthetic, a.images, a.device)
    call()  # cold: compiles
    warm = []
    for _ in range(a.warm):
        t = time.perf_counter()
        _, maen = call()
        warm.append(time.perf_counter() - t)
    for w in st.WRAPS + [x for x in _extra() if x is not None]:
        _wrap(*w)
    gpps.reconstruct = st.rec_mod.reconstruct
    call()  # (once through the wrappers before the profiled call)
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t = time.perf_counter()
        _, maen = call()
        torch.cuda.synchronize()
        wall = time.perf_counter() - t
    out = analyse(prof.events(), float("inf"), float("-inf"))
    out.update({"device": a.device, "size": a.synthetic, "images": a.images, "warm_s": warm,
                "reconstructor": bool(a.reconstructor),
                "profiled_call_s": wall, "maen_deg": maen()})
    Path(a.out).write_text(json.dumps(out, indent=1))
    print(f"warm {[round(w * 1e3, 1) for w in warm]} ms; profiled {wall * 1e3:.1f} ms; "
          f"GPU busy {out['gpu_busy_ms']:.1f} ms; MAEN {out['maen_deg']:.6f}")
    for k, v in list(out["idle_ms_by_method"].items())[:25]:
        print(f"  idle {v:8.2f} ms  in {k}")


if __name__ == "__main__":
    main()
