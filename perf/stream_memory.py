"""Memory of a long stream: 10,000 frame triples through one gpps Stream (issue 6: "memory stays flat over 10k frames").

The scene: Blinn-Phong bumps, 3 directional lights, perspective, uint16 frames;
the frames cycle through 8 renders of the scene moving sideways, and every
97th frame is bad (a NaN, a wrong shape or a wrong dtype, in turn), so error
entries are part of the run.  Results stay on the device (``output="device"``,
ring of 2).

Measured every ``--every`` frames: the process's resident set size
(/proc/self/statm), the Python heap (tracemalloc, started after the warm-up),
and, on CUDA, the device memory in use (``cudaMemGetInfo`` through Warp).
The growth between the first sample after warm-up and the last is reported;
flat means: no per-frame allocation survives.

Usage:  python perf/stream_memory.py [--device cpu] [--size 32] [--frames 10000] [--every 500]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tracemalloc
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--every", type=int, default=500)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()

    from gpps._runtime import warp
    from gpps.material import Material
    from gpps.pipeline.stream import Stream, StreamConfig
    from gpps.host.scenes import make_scene
    from gpps.flows.synthetic import default_lights, render

    wp = warp()
    mat = Material.default_for("blinn-phong")
    L = default_lights("directional", 3)
    sc = make_scene("bumps", a.size, "perspective")
    frames = []
    for k in range(8):  # the same object moved sideways by k pixels: every frame differs from the last
        img = render(sc, mat, L, bits=16, device=a.device)
        frames.append(np.ascontiguousarray(np.roll(np.round(np.clip(img, 0, 1) * 65535).astype(np.uint16), k, axis=2)))
    nan = frames[0].astype(np.float32) / 65535
    nan[0, 1, 1] = np.nan
    bad = [nan, frames[0][:2], frames[0].astype(np.int64)]
    mask = np.ones(sc.mask.shape, bool)

    def source():
        for i in range(a.frames):
            yield bad[(i // 97) % 3] if i % 97 == 96 else frames[i % 8]

    st = Stream(sc.mask.shape, sc.camera, L, mat, mask=mask, config=StreamConfig(), device=a.device)
    cuda = str(st.device).startswith("cuda")

    def dev_used_mb():
        if not cuda:
            return None
        dev = wp.get_device(a.device)  # Warp's Device.free_memory / total_memory (cudaMemGetInfo)
        return (dev.total_memory - dev.free_memory) / 2**20

    samples, errors = [], 0
    t0 = time.perf_counter()
    for r in st.iterate(source()):
        errors += not r.ok
        i = r.index + 1
        if i == 200:
            tracemalloc.start()
        if i >= 200 and (i % a.every == 0 or i == a.frames):
            wp.synchronize_device(st.device)
            samples.append({"frame": i, "rss_mb": rss_mb(), "python_heap_mb": tracemalloc.get_traced_memory()[0] / 2**20,
                            "device_used_mb": dev_used_mb(), "seconds": time.perf_counter() - t0})
            print(f"frame {i:6d}  rss {samples[-1]['rss_mb']:8.1f} MB  heap {samples[-1]['python_heap_mb']:6.2f} MB  "
                  f"device {samples[-1]['device_used_mb']}  errors {errors}", file=sys.stderr)
    tracemalloc.stop()
    first, last = samples[0], samples[-1]
    res = {
        "device": str(st.device), "size": a.size, "frames": a.frames, "bad_frames": errors,
        "expected_bad_frames": sum(1 for i in range(a.frames) if i % 97 == 96),
        "seconds": time.perf_counter() - t0, "samples": samples,
        "rss_growth_mb": last["rss_mb"] - first["rss_mb"],
        "python_heap_growth_mb": last["python_heap_mb"] - first["python_heap_mb"],
        "device_growth_mb": None if first["device_used_mb"] is None else last["device_used_mb"] - first["device_used_mb"],
        "stats": {k: v for k, v in st.stats.items() if isinstance(v, (int, float, str))},
    }
    out = Path(a.out or ROOT / "perf" / "results" / f"stream_memory_{a.device.replace(':', '')}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=float))
    os.replace(tmp, out)
    print(f"{a.frames} frames ({errors} reported bad, expected {res['expected_bad_frames']}) in {res['seconds']:.1f} s on {res['device']}: "
          f"RSS growth {res['rss_growth_mb']:+.2f} MB, Python heap growth {res['python_heap_growth_mb']:+.3f} MB, "
          f"device growth {res['device_growth_mb']} MB  -> {out}")


if __name__ == "__main__":
    main()
