"""How much of a warm ``gpps.reconstruct`` call is the set-up of its stages (issue 20's 256^2 x 3 line).

``gpps.reconstruct`` builds a :class:`gpps.flows.ron.RON` (two pixel solvers, the integrator's Taichi fields, the
material scorer and its searches) for every call and frees it after; ``gpps.Reconstructor`` builds it at its first
call and keeps it.  This probe times, on one device, issue 20's synthetic capture (``_common.reconstruct_inputs``,
the material unknown):

* ``fresh``: ``gpps.reconstruct`` as users call it (a new RON per call);
* ``reconstructor``: the same calls through one ``gpps.Reconstructor`` (built by an untimed first call of its
  block and closed after the block, so that the fresh calls find the process's buffer pools as users do);

in ``--blocks`` interleaved blocks of ``--repeat`` warm calls each (the lent machine's host speed drifts between
blocks: interleaving keeps the comparison fair), device-synchronised, with the MAEN of every call (the two must
agree: the Reconstructor's results are reconstruct's bit for bit).

Usage:  python perf/reconstruct_reuse.py [--size 256] [--images 3] [--device cuda:0] [--repeat 5] [--blocks 3]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

import gpps  # noqa: E402
from _common import device_label, reconstruct_inputs  # noqa: E402


def _sync():
    import warp as wp
    wp.synchronize()


def _timed(call, repeat, truth, mask):
    ts, maens = [], []
    for _ in range(repeat):
        _sync()
        t = time.perf_counter()
        rec = call()
        _sync()
        ts.append(time.perf_counter() - t)
        maens.append(float(gpps.normal_errors(rec.normals, truth, mask)["mean"]))
    return ts, maens


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    c = reconstruct_inputs(a.size, a.images, a.device)
    kw = dict(camera=c["camera"], material="cook-torrance", device=a.device)
    img, mask, lights = c["images"], c["mask"], c["lights"]
    # each reconstructor block builds its own and closes it after: while one is open it holds the pooled buffers
    # and Taichi fields that reconstruct's RON would otherwise take again (a fresh call would pay new ones)
    builds = []

    def fresh_block():
        return _timed(lambda: gpps.reconstruct(img, mask, lights, **kw), a.repeat, c["normals"], mask)

    def kept_block():
        with gpps.Reconstructor(mask, lights, **kw) as rc:
            rc(img)  # (builds the stages: not timed)
            got = _timed(lambda: rc(img), a.repeat, c["normals"], mask)
            builds.append(rc.builds)
        return got

    modes = {"fresh": fresh_block, "reconstructor": kept_block}
    gpps.reconstruct(img, mask, lights, **kw)  # cold (compiles)
    res = {k: {"ms": [], "maen": []} for k in modes}
    for _ in range(a.blocks):
        for k, f in modes.items():
            ts, maens = f()
            res[k]["ms"].append([1e3 * t for t in ts])
            res[k]["maen"].extend(maens)
    out = {"device": a.device, "device_name": device_label(a.device or "cuda:0"), "size": a.size, "images": a.images,
           "repeat": a.repeat, "blocks": a.blocks, "builds": builds}
    for k, v in res.items():
        flat = [t for b in v["ms"] for t in b]
        out[k] = {"median_ms": float(np.median(flat)), "block_medians_ms": [float(np.median(b)) for b in v["ms"]],
                  "ms": v["ms"], "maen": sorted(set(v["maen"]))}
    print(json.dumps({k: (v if not isinstance(v, dict) else {kk: vv for kk, vv in v.items() if kk != "ms"})
                      for k, v in out.items()}), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
