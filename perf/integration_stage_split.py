"""Where RON's integration stage spends its wall time on a warm ``gpps.reconstruct`` (256^2 x 3 by default).

Wraps the device integration's pieces (``DeviceRounds.integrate``, ``DeviceSystem.step``,
``Integrator._iterate``, ``Integrator.set_coarsest``) and the host path's
``Integrator.run`` with wall-clock timers that synchronise the device (Warp and Taichi) before and after,
so each piece's time includes its own device work and nothing else's.  Prints and writes JSON.

Usage:  python perf/integration_stage_split.py [--size 256] [--images 3] [--device cuda:0] [--repeat 5] --out FILE
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import gpps  # noqa: E402
from gpps import _taichi  # noqa: E402
from gpps._runtime import warp  # noqa: E402
from gpps.pipeline.integration import Integrator  # noqa: E402
from gpps.pipeline.integration_rounds import DeviceSystem  # noqa: E402
from gpps.pipeline.ron_rounds import DeviceRounds  # noqa: E402


def _sync():
    warp().synchronize()
    try:
        _taichi.ti.sync()
    except Exception:  # noqa: BLE001 (Taichi not initialised yet)
        pass


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    acc = defaultdict(list)
    cur = {}

    def wrap(cls, name, label):
        orig = getattr(cls, name)

        def timed(*args, **kwargs):
            _sync()
            t = time.perf_counter()
            try:
                return orig(*args, **kwargs)
            finally:
                _sync()
                cur[label] = cur.get(label, 0.0) + time.perf_counter() - t
        setattr(cls, name, timed)

    wrap(DeviceRounds, "integrate", "DeviceRounds.integrate")
    wrap(DeviceSystem, "step", "DeviceSystem.step")
    wrap(DeviceSystem, "__init__", "DeviceSystem.__init__")
    wrap(Integrator, "_iterate", "Integrator._iterate (PCG)")
    wrap(Integrator, "set_coarsest", "Integrator.set_coarsest (pinv)")
    wrap(Integrator, "run", "Integrator.run (host path)")
    sc = gpps.make_scene("bumps", a.size, "perspective")
    L = gpps.default_lights("directional", a.images, layout="ring" if a.images <= 4 else "spiral")
    img = gpps.render(sc, gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5), L, bits=16,
                      device=a.device) / L.intensities[:, None, None, :]
    lu = gpps.DirectionalLights(L.directions)
    for i in range(a.repeat + 1):
        cur.clear()
        rec = gpps.reconstruct(img, sc.mask, lu, camera=sc.camera, material="cook-torrance", device=a.device)
        if i:
            for k, v in cur.items():
                acc[k].append(v)
            acc["timings.integration"].append(rec.timings["integration"])
            acc["timings.total"].append(rec.timings["total"])
    rows = {k: {"median_ms": 1e3 * sorted(v)[len(v) // 2], "all_ms": [round(1e3 * x, 2) for x in v]} for k, v in acc.items()}
    for k, r in rows.items():
        print(f"{r['median_ms']:8.2f} ms  {k}")
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps({"device": a.device, "size": a.size, "images": a.images, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
