"""Where a warm ``gpps.reconstruct_folder`` / ``gpps.reconstruct`` call spends its host time (cProfile).

Each case: one cold call (compilation), ``--repeat`` warm calls (the median reported, each one's stages kept),
then a warm call under cProfile; writes the top
functions by cumulative time, own time and call count (``<case>_cumulative.txt``, ``<case>_tottime.txt``,
``<case>_ncalls.txt``), the Python function calls of that call and the stage timings (``profile.json``) to
``--out``.  With ``--reconstructor`` the synthetic cases run through one kept ``gpps.Reconstructor`` (case name
``..._reconstructor``; the profiler adds about a microsecond a call, so the profiled time overstates the host's
share).  On CUDA the host waits at synchronisation points (fetches), so a
kernel's device time shows up in the function that fetches its result.

With ``--trace`` (CUDA, needs torch) one more warm call runs under ``torch.profiler`` with CUDA activity
tracing (CUPTI sees every kernel of the process: Warp's and Taichi's): ``<case>_kernels.json`` gets the GPU
time per kernel name and the GPU busy time (the union of kernel and copy intervals) against the call's wall time,
which separates device work from host overhead.

Usage:  python perf/profile_reconstruct.py [FOLDER...] [--synthetic 256] [--images 3] [--device cuda:0] [--trace]
        [--reconstructor] --out DIR
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import gpps  # noqa: E402
from _common import reconstruct_case, reconstructor_case  # noqa: E402
from gpps.io import json_default  # noqa: E402


def _stats(prof, key: str, top: int) -> str:
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats(key).print_stats(top)
    return s.getvalue()


def _trace(call) -> dict:
    """One call under torch.profiler (CUDA activities): GPU time per kernel, busy time, wall time."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t = time.perf_counter()
        call()
        torch.cuda.synchronize()
        wall = time.perf_counter() - t
    per: dict[str, list] = {}
    spans = []
    for e in prof.events():
        if e.device_type.name != "CUDA":
            continue
        t0 = e.time_range.start
        t1 = e.time_range.end
        spans.append((t0, t1))
        d = per.setdefault(e.name[:120], [0, 0.0, []])
        d[0] += 1
        d[1] += (t1 - t0) * 1e-6
        d[2].append(round((t1 - t0) * 1e-3, 2))
    spans.sort()
    busy, cur0, cur1 = 0.0, None, None
    for t0, t1 in spans:
        if cur1 is None or t0 > cur1:
            if cur1 is not None:
                busy += cur1 - cur0
            cur0, cur1 = t0, t1
        else:
            cur1 = max(cur1, t1)
    if cur1 is not None:
        busy += cur1 - cur0
    # each launch's duration (us, in launch order) for the kernels that took 1 ms or more in all
    rows = sorted(({"name": k, "count": v[0], "gpu_s": v[1], **({"launches_us": v[2]} if v[1] >= 1e-3 else {})}
                   for k, v in per.items()), key=lambda r: -r["gpu_s"])
    return {"wall_s": wall, "gpu_busy_s": busy * 1e-6, "events": len(spans),
            "span_s": (spans[-1][1] - spans[0][0]) * 1e-6 if spans else 0.0, "kernels": rows}


def _synthetic(size: int, n: int, device, kept: bool = False):
    case = (reconstructor_case if kept else reconstruct_case)(size, n, device)

    def call():
        rec, maen = case()
        return rec.timings, maen
    return call


def _folder(folder: str, device):
    def call():
        res = gpps.reconstruct_folder(folder, device=device)
        return res.report.get("timings"), lambda: res.report.get("maen_deg")
    return call


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folders", nargs="*")
    ap.add_argument("--synthetic", type=int, nargs="*", default=[])
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--top", type=int, default=45)
    ap.add_argument("--repeat", type=int, default=3, help="warm calls (the median is reported)")
    ap.add_argument("--trace", action="store_true", help="one more warm call under torch.profiler (CUDA)")
    ap.add_argument("--reconstructor", action="store_true",
                    help="the synthetic cases through one kept gpps.Reconstructor")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    cases = [(Path(f).name, _folder(f, a.device)) for f in a.folders]
    tag = "_reconstructor" if a.reconstructor else ""
    cases += [(f"bumps{s}x{a.images}{tag}", _synthetic(s, a.images, a.device, a.reconstructor)) for s in a.synthetic]
    rows = []
    for name, call in cases:
        t = time.perf_counter()
        call()
        cold = time.perf_counter() - t
        warm_all, stages_all = [], []
        for _ in range(max(1, a.repeat)):
            t = time.perf_counter()
            timings, maen = call()
            warm_all.append(time.perf_counter() - t)
            maen = maen()
            stages_all.append(timings)
        warm = float(sorted(warm_all)[len(warm_all) // 2])  # median of the warm calls
        timings = stages_all[warm_all.index(warm)]
        prof = cProfile.Profile()
        t = time.perf_counter()
        prof.enable()
        call()
        prof.disable()
        profiled = time.perf_counter() - t
        (out / f"{name}_cumulative.txt").write_text(_stats(prof, "cumulative", a.top))
        (out / f"{name}_tottime.txt").write_text(_stats(prof, "tottime", a.top))
        (out / f"{name}_ncalls.txt").write_text(_stats(prof, "ncalls", a.top))
        calls = sum(v[1] for v in pstats.Stats(prof).stats.values())
        prof.dump_stats(str(out / f"{name}.pstats"))  # (for callers / callees offline: pstats.Stats(path))
        rows.append({"case": name, "cold_s": cold, "warm_s": warm, "warm_all_s": warm_all, "profiled_s": profiled,
                     "python_calls": calls, "maen_deg": maen, "timings": timings, "timings_all": stages_all})
        if a.trace:
            tr = _trace(call)
            (out / f"{name}_kernels.json").write_text(json.dumps(tr, indent=1))
            rows[-1]["trace"] = {k: tr[k] for k in ("wall_s", "gpu_busy_s", "events", "span_s")}
        print(json.dumps(rows[-1], default=json_default), flush=True)
    (out / "profile.json").write_text(json.dumps({"device": a.device, "rows": rows}, indent=1, default=json_default))


if __name__ == "__main__":
    main()
