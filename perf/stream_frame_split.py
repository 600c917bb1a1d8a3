"""Where a known-material stream frame's time goes (issue 20's >= 500 triples/s line, as ``perf/bench.py`` times it).

The frame of ``perf/bench.py``'s ``frame_device`` row (``_common.bumps_frame``: perspective Blinn-Phong bumps, 3
directional lights, a uint16 RGB triple already on the device), through a kept :class:`Stream` per variant, in
interleaved blocks, each frame device-synchronised (as the bench times it).  For the default stream the frame is
split by host clocks at the stream's own synchronisation points (no extra syncs):

* ``solve``: from the call to the end of the sanity check's read-back (the graph of convert, solve, jump re-solve,
  misfit retries and residual sum, launched and waited for);
* ``integrate``: the integrator's step and its synchronisation;
* ``rest``: the kept-buffer copies, the running levels and the result's ring copies (to the final device sync);

and the device-only times of the pieces are taken by replaying them back to back: the captured solve graph, the
integrator's step (``integration_iterations`` PCG iterations).

Usage:  python perf/stream_frame_split.py [--size 1024] [--frames 60] [--blocks 3] [--device cuda:0] [--out F]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

from _common import bumps_frame  # noqa: E402

from gpps import _taichi  # noqa: E402
from gpps._runtime import resolve_device, warp  # noqa: E402
from gpps.host.metrics import normal_errors  # noqa: E402
from gpps.pipeline.stream import Stream, StreamConfig  # noqa: E402

VARIANTS = {
    "default": {},
    "no-retry": {"retry_rows": 0},
    "no-check": {"check": False},
    "1-pcg": {"integration_iterations": 1},
    "no-integrate": {"integrate": False},
    "split-subsets": {},
    "split-full-grid": {},
}
# the jump re-solves and misfit retries (``PixelSolver.step_subset``) with each start in a thread of its own
# (``SolverConfig(split_starts=True)``: gpps.kernels.solve_split), over one wave of blocks (SUBSET_BLOCKS_PER_SM)
# or, in the second, over the whole grid; the default stream runs them as one thread a pixel over the whole grid.
# Set on the stream after construction.
SPLIT = ("split-subsets", "split-full-grid")
FULL_GRID = ("split-full-grid",)


def _variant(st, name):
    if name in SPLIT:
        st._redo_cfg = replace(st._redo_cfg, split_starts=True)
    if name in FULL_GRID:
        st.solver._subset_blocks = lambda: {}
    return st


class _Clock:
    """Host-clock marks at the stream's own synchronisation points (wrapping its methods; adds no sync)."""

    def __init__(self, st):
        self.marks = {}
        self.st = st
        judge, step = st._judge, st.integrator.step if st.integrator is not None else None

        def timed_judge(cold):
            r = judge(cold)
            self.marks["judged"] = time.perf_counter()
            return r

        st._judge = timed_judge
        if step is not None:
            def timed_step(*a, **k):
                self.marks["integrate0"] = time.perf_counter()
                r = step(*a, **k)
                return r

            st.integrator.step = timed_step
            accept = st._accept

            def timed_accept(got):
                self.marks["integrated"] = time.perf_counter()
                return accept(got)

            st._accept = timed_accept


def kernel_times(variant, sc, mat, L, fdev, size, device, frames=20):
    """Each Warp kernel's device time per frame (``wp.timing_begin``'s CUDA events) over ``frames`` eager
    (``graph="off"``) frames of a stream of ``variant``; the Taichi integrator's kernels are not in it."""
    wp = warp()
    st = Stream((size, size), sc.camera, L, mat, mask=sc.mask,
                config=StreamConfig(graph="off", **VARIANTS[variant]), device=device)
    _variant(st, variant)
    try:
        for _ in range(6):
            st.run(fdev)
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
        for _ in range(frames):
            st.run(fdev)
        results = wp.timing_end()
    finally:
        st.close()
    agg = {}
    for r in results:
        t = agg.setdefault(r.name, [0.0, 0])
        t[0] += r.elapsed / frames
        t[1] += 1
    rows = {k: {"ms_per_frame": v[0], "launches_per_frame": v[1] / frames}
            for k, v in sorted(agg.items(), key=lambda kv: -kv[1][0])}
    total = sum(v["ms_per_frame"] for v in rows.values())
    print(f"[{variant}] Warp kernels, eager frames: {total:.3f} ms a frame", flush=True)
    for k, v in list(rows.items())[:8]:
        print(f"   {v['ms_per_frame']:.4f} ms  x{v['launches_per_frame']:.0f}  {k}", flush=True)
    return {"total_ms": total, "rows": rows}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=None)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS),
                    help="the streams to time (default: all; 'default' always)")
    a = ap.parse_args(argv)
    names = ["default"] + [k for k in a.variants if k != "default"]
    wp = warp()
    device = resolve_device(a.device)
    sync = lambda: wp.synchronize_device(device)  # noqa: E731
    sc, mat, L, frame16 = bumps_frame(a.size, device)
    fdev = wp.array(frame16, dtype=wp.uint16, device=device)
    streams = {k: Stream((a.size, a.size), sc.camera, L, mat, mask=sc.mask, config=StreamConfig(**v), device=device)
               for k, v in VARIANTS.items() if k in names}
    for k, st in streams.items():
        _variant(st, k)
    for st in streams.values():  # the cold frame and the graph captures
        for _ in range(6):
            r = st.run(fdev)
            assert r.ok, r.error
    sync()
    clock = _Clock(streams["default"])
    res = {k: [] for k in names}
    split = {"solve": [], "integrate": [], "rest": []}
    for _ in range(a.blocks):
        for k, st in streams.items():
            for _ in range(a.frames):
                t0 = time.perf_counter()
                st.run(fdev)
                sync()
                t1 = time.perf_counter()
                res[k].append(1e3 * (t1 - t0))
                if k == "default":
                    m = clock.marks
                    split["solve"].append(1e3 * (m["judged"] - t0))
                    split["integrate"].append(1e3 * (m["integrated"] - m["integrate0"]))
                    split["rest"].append(1e3 * (t1 - t0) - split["solve"][-1] - split["integrate"][-1])
    out = {"device": device, "device_name": wp.get_device(device).name, "size": a.size, "frames": a.frames,
           "blocks": a.blocks, "variants": {}, "split_default_ms": {k: statistics.median(v) for k, v in split.items()}}
    for k, v in res.items():
        st = streams[k]
        r = st.run(fdev)
        sync()
        med = statistics.median(v)
        out["variants"][k] = {"config": VARIANTS[k], "median_ms": med, "triples_per_s": 1e3 / med,
                              "maen": normal_errors(r.normals.numpy(), sc.normals, sc.mask)["mean"],
                              "redone": st.stats["redone_pixels"]}
        print(f"{k:14s} median {med:.3f} ms ({1e3 / med:.0f} triples/s), MAEN {out['variants'][k]['maen']:.4f}, "
              f"redone {st.stats['redone_pixels']}", flush=True)
    print("default split (median ms):", {k: round(v, 3) for k, v in out["split_default_ms"].items()}, flush=True)
    # device-only pieces, back to back
    st = streams["default"]
    if st.is_cuda and st._graphs:
        g = next(iter(st._graphs.values()))
        for _ in range(3):
            wp.capture_launch(g)
        sync()
        t = time.perf_counter()
        for _ in range(50):
            wp.capture_launch(g)
        sync()
        out["solve_graph_ms"] = 1e3 * (time.perf_counter() - t) / 50
        print(f"solve graph replayed back to back: {out['solve_graph_ms']:.3f} ms", flush=True)
    if st.integrator is not None:
        its = st.config.integration_iterations
        sync()
        _taichi.ti.sync()
        t = time.perf_counter()
        for _ in range(50):
            st.integrator.step(st._nrm_view, st._dep_view, iterations=its, reference=st.config.reference_depth)
        _taichi.ti.sync()
        out["integrate_ms"] = 1e3 * (time.perf_counter() - t) / 50
        print(f"integrator step ({its} PCG iterations) back to back: {out['integrate_ms']:.3f} ms", flush=True)
    for s in streams.values():
        s.close()
    if device.startswith("cuda"):
        out["kernels"] = {k: kernel_times(k, sc, mat, L, fdev, a.size, device) for k in names if k == "default" or k in SPLIT}
    path_out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"stream_frame_split_{a.size}.json"
    path_out.write_text(json.dumps(out, indent=1))
    print("wrote", path_out)


if __name__ == "__main__":
    main()
