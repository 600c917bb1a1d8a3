"""Where the stream's sanity check spends its time: each of its steps alone, device-synchronised (median of 50).

Usage:  python perf/stream_check_profile.py [--device cuda:0] [--size 1024] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    from _common import moving_bumps

    from gpps._runtime import resolve_device, warp
    from gpps.pipeline.stream import Stream, StreamConfig

    wp = warp()
    dev = resolve_device(a.device)
    sc, mat, L, frames, truth, mask = moving_bumps(a.size, dev, positions=4)
    frames = [wp.array(f, dtype=wp.uint16, device=dev) for f in frames]
    s = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(), device=dev)
    for i in range(20):
        r = s.run(frames[i % 4])
        assert r.ok, r.error
    key = (np.dtype(np.uint16), 3)

    def quiet(judge):
        try:
            judge(False)
        except Exception:  # the sums of repeated launches need not pass; only the read-back is timed
            pass

    def t(fn, n=50):
        fn()
        wp.synchronize_device(dev)
        ts = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            wp.synchronize_device(dev)
            ts.append(time.perf_counter() - t0)
        return 1e3 * statistics.median(ts)

    res = {
        "device_name": wp.get_device(dev).name, "size": a.size,
        "process_ms": t(lambda: s.run(frames[1])),
        "solve_warm_ms": t(lambda: s.solver.step()),
        "frame_stats_ms": t(lambda: (s._fstats.zero_(), s._cmd("stats", key).launch())),
        "mark_jumps_ms": t(lambda: s._cmd("jumps").launch()),
        "redo_solve_ms": t(lambda: s.solver.step_subset(s._redo, s._redo_cfg)),
        "residual_sum_ms": t(lambda: s._cmd("residual").launch()),
        "judge_readback_ms": t(lambda: quiet(s._judge)),
        "kept_copies_ms": t(lambda: (wp.copy(s._kept, s.solver.normals), wp.copy(s._kept_res, s.solver.residual))),
        "accept_ms": t(lambda: s._accept(dict(lit_fraction=1.0, saturated_fraction=0.0, noise_ratio=0.01,
                                               residual=1e-5, grey=0.4, redone=0))),
        "redone_pixels_per_frame": int(s.stats["redone_pixels"] / max(s.frames_done - 1, 1)),
    }
    out = Path(a.out or ROOT / "perf" / "results" / f"stream_check_profile_{dev.replace(':', '')}_{a.size}.json")
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
