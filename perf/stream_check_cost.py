"""Cost of the stream's per-frame sanity check: the same stream with ``check`` on and off, in one process.

Moving Blinn-Phong bumps (perspective, 3 directional lights, uint16 RGB frames,
8 positions), known material, device-resident frames (on CUDA), output on the
device.  Median wall time per frame of :meth:`Stream.process` (which ends at the
frame's synchronisation), after a warm-up, each mode in its own stream; the
modes alternate in blocks so drift hits both.

Usage:  python perf/stream_check_cost.py [--device cuda:0] [--size 1024] [--frames 400] [--out FILE]
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



def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    from _common import moving_bumps

    from gpps._runtime import resolve_device, warp
    from gpps.pipeline.stream import Stream, StreamConfig

    wp = warp()
    dev = resolve_device(a.device)
    sc, mat, L, frames, truth, mask = moving_bumps(a.size, dev)
    if dev.startswith("cuda"):
        frames = [wp.array(f, dtype=wp.uint16, device=dev) for f in frames]
    streams = {c: Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(check=c), device=dev)
               for c in (True, False)}
    times = {True: [], False: []}
    for c, s in streams.items():  # warm-up: compile, capture graphs
        for i in range(20):
            assert s.run(frames[i % 8]).ok
    block = 20
    for b in range(a.frames // block):
        for c in ((True, False) if b % 2 == 0 else (False, True)):
            s = streams[c]
            for i in range(block):
                t = time.perf_counter()
                r = s.run(frames[(b * block + i) // 2 % 8])
                times[c].append(time.perf_counter() - t)
                assert r.ok
    med = {c: statistics.median(v) for c, v in times.items()}
    res = {"device": dev, "device_name": wp.get_device(dev).name, "size": a.size, "frames_per_mode": len(times[True]),
           "median_ms_check_on": 1e3 * med[True], "median_ms_check_off": 1e3 * med[False],
           "frames_per_s_check_on": 1 / med[True], "frames_per_s_check_off": 1 / med[False],
           "overhead_ms": 1e3 * (med[True] - med[False]),
           "command": "python perf/stream_check_cost.py " + " ".join(sys.argv[1:])}
    out = Path(a.out or ROOT / "perf" / "results" / f"stream_check_cost_{dev.replace(':', '')}_{a.size}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
