"""How much of a warm ``gpps.reconstruct`` call is the set-up of its stages (issue 20's 256^2 x 3 line).

``gpps.reconstruct`` builds a :class:`gpps.flows.ron.RON` (two pixel solvers, the integrator's Taichi fields, the
material scorer and its searches) for every call and frees it after.  This probe times, on one device:

* ``fresh``: ``gpps.reconstruct`` as users call it (a new RON per call);
* ``reuse``: the same calls with one RON kept for the whole run (``gpps.flows.reconstruction.RON`` replaced by a
  factory that hands back the instance built for the same shape, mask, camera, lights, material and config, and
  whose ``close`` waits until the probe ends), so each call's time is the pipeline's alone;

each the median of ``--repeat`` warm calls, with the MAEN of each (the two must agree).  The difference is what a
persistent reconstructor object would save; what is left is the pipeline's own host and device time.

Usage:  python perf/reconstruct_reuse.py [--size 256] [--images 3] [--device cuda:0] [--repeat 7] [--out FILE]
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
from _common import device_label, reconstruct_case  # noqa: E402
from gpps.flows import reconstruction as rec_mod  # noqa: E402


def _sync(device):
    import warp as wp
    wp.synchronize()


def _timed(call, repeat, device):
    call()  # cold (compiles) or first of the mode
    ts, maens = [], []
    for _ in range(repeat):
        _sync(device)
        t = time.perf_counter()
        rec, maen = call()
        _sync(device)
        ts.append(time.perf_counter() - t)
        maens.append(maen())
    return ts, maens


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    call = reconstruct_case(a.size, a.images, a.device)
    out = {"device": a.device, "device_name": device_label(a.device or "cuda:0"), "size": a.size, "images": a.images}
    ts, maens = _timed(call, a.repeat, a.device)
    out["fresh"] = {"ms": [1e3 * t for t in ts], "median_ms": 1e3 * float(np.median(ts)), "maen": maens}

    real = rec_mod.RON
    kept: dict = {}

    class _Kept:
        def __init__(self, ron):
            self._ron = ron

        def __getattr__(self, name):
            return getattr(self._ron, name)

        def close(self):  # (closed at the end of the probe)
            pass

    def factory(shape, camera, lights, material, mask, config=None, device=None):
        key = (tuple(shape), id(camera), id(lights), repr(material), np.asarray(mask).tobytes(), repr(config), device)
        if key not in kept:
            kept[key] = real(shape, camera, lights, material, mask, config, device=device)
        return _Kept(kept[key])

    rec_mod.RON = factory
    try:
        ts, maens = _timed(call, a.repeat, a.device)
    finally:
        rec_mod.RON = real
        for r in kept.values():
            r.close()
    out["reuse"] = {"ms": [1e3 * t for t in ts], "median_ms": 1e3 * float(np.median(ts)), "maen": maens,
                    "instances": len(kept)}
    print(json.dumps(out), flush=True)
    if a.out:
        Path(a.out).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
