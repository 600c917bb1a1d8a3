"""The Python calls of one warm reconstruction (issue 20's 256^2 x 3 case): cProfile tables by call count, own time
and cumulative time, through ``gpps.reconstruct`` or one kept ``gpps.Reconstructor``.

On CUDA the host's part of the call is Python work between launches; this shows where its function calls are (the
profiler adds about a microsecond a call, so the profiled time overstates the host's share).

Usage:  python perf/host_calls.py [--size 256] [--images 3] [--device cuda:0] [--reconstructor] [--top 60] --out DIR
"""

from __future__ import annotations

import argparse
import cProfile
import io
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
from _common import reconstruct_inputs  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--reconstructor", action="store_true")
    ap.add_argument("--top", type=int, default=60)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    c = reconstruct_inputs(a.size, a.images, a.device)
    kw = dict(camera=c["camera"], material="cook-torrance", device=a.device)
    if a.reconstructor:
        rc = gpps.Reconstructor(c["mask"], c["lights"], **kw)
        call = lambda: rc(c["images"])  # noqa: E731
    else:
        call = lambda: gpps.reconstruct(c["images"], c["mask"], c["lights"], **kw)  # noqa: E731
    for _ in range(3):
        call()
    prof = cProfile.Profile()
    t = time.perf_counter()
    prof.enable()
    call()
    prof.disable()
    wall = time.perf_counter() - t
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    tag = "reconstructor" if a.reconstructor else "reconstruct"
    for key in ("ncalls", "tottime", "cumulative"):
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats(key).print_stats(a.top)
        (out / f"{tag}_{key}.txt").write_text(s.getvalue())
    st = pstats.Stats(prof)
    calls = sum(v[1] for v in st.stats.values())
    print(f"{tag}: profiled call {wall * 1e3:.1f} ms, {calls} function calls")


if __name__ == "__main__":
    main()
