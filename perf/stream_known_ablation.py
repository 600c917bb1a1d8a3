"""Known-material stream frames at 1024^2 with and without the misfit retries (issue 20's >= 500 triples/s line):
the same device-resident frames as ``perf/stream_full.py`` through kept streams, interleaved blocks, device-synchronised.

Usage:  python perf/stream_known_ablation.py [--size 1024] [--frames 60] [--blocks 3] [--device cuda:0]
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

from _common import moving_bumps  # noqa: E402

from gpps._runtime import resolve_device, warp  # noqa: E402
from gpps.host.metrics import normal_errors  # noqa: E402
from gpps.material import Material  # noqa: E402
from gpps.pipeline.stream import Stream, StreamConfig  # noqa: E402

TRUE = Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
VARIANTS = {"default": {}, "no-retry": {"retry_rows": 0}, "no-retry-no-hold": {"retry_rows": 0, "neighbour_radius": 0}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    wp = warp()
    device = resolve_device(a.device)
    sc, _, L, fr, truth, mask = moving_bumps(a.size, device, 8, material=TRUE)
    frames = [wp.array(f, dtype=wp.uint16, device=device) for f in fr]
    path = list(range(8)) + list(range(6, 0, -1))
    streams = {k: Stream(mask.shape, sc.camera, L, TRUE, mask=mask, config=StreamConfig(output="device", **v),
                         device=device) for k, v in VARIANTS.items()}
    for st in streams.values():  # warm-up: the cold frame, the graph captures
        for f in range(6):
            st.run(frames[path[f % len(path)]])
    res = {k: {"ms": [], "maen": []} for k in VARIANTS}
    pos = {k: 6 for k in VARIANTS}
    for _ in range(a.blocks):
        for k, st in streams.items():
            for _ in range(a.frames):
                p = path[pos[k] % len(path)]
                pos[k] += 1
                t0 = time.perf_counter()
                r = st.run(frames[p])
                wp.synchronize_device(device)
                res[k]["ms"].append(1e3 * (time.perf_counter() - t0))
            res[k]["maen"].append(normal_errors(r.normals.numpy(), truth[p], mask)["mean"])
    out = {"device": device, "device_name": wp.get_device(device).name, "size": a.size, "frames": a.frames,
           "blocks": a.blocks, "variants": {}}
    for k, v in res.items():
        med = statistics.median(v["ms"])
        out["variants"][k] = {"config": VARIANTS[k], "median_ms": med, "triples_per_s": 1e3 / med,
                              "mean_rate": 1e3 * len(v["ms"]) / sum(v["ms"]), "maen_last": v["maen"],
                              "redone": streams[k].stats["redone_pixels"]}
        print(f"{k:18s} median {med:.3f} ms ({1e3 / med:.0f} triples/s, mean rate {out['variants'][k]['mean_rate']:.0f}), "
              f"MAEN at block ends {[round(m, 4) for m in v['maen']]}", flush=True)
    path_out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"stream_known_ablation_{a.size}.json"
    path_out.write_text(json.dumps(out, indent=1))
    print("wrote", path_out)


if __name__ == "__main__":
    main()
