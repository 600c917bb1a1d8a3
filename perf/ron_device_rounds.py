"""RON's rounds with the integration exchange on the device against the host rounds (issue 20).

A rendered perspective Blinn-Phong sphere under 3 point lights, known material, ``rounds`` rounds
(tolerances 0: every round runs); per mode (``RONConfig(device_rounds=False / True)``), interleaved
repeats after a warm-up run: the whole ``RON.run`` and the rounds' integration (``timings["integration"]``
less the final depth's integration, timed around ``RON._final_depth``).

    python perf/ron_device_rounds.py --device cpu --sizes 128 256 --repeat 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from _common import RESULTS, device_label
from gpps.flows.ron import RON, RONConfig
from gpps.flows.synthetic import default_lights, render
from gpps.host.scenes import make_scene
from gpps.lights import PointLights
from gpps.material import Material


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    mat = Material("blinn-phong", ks=0.7, shininess=60.0)
    final = {"t": 0.0}
    orig = RON._final_depth

    def timed_final(self, *args, **kw):
        t = time.perf_counter()
        try:
            return orig(self, *args, **kw)
        finally:
            final["t"] = time.perf_counter() - t

    RON._final_depth = timed_final
    rows = []
    for size in a.sizes:
        sc = make_scene("sphere", size, "perspective")
        L = default_lights("point", 3)
        img = render(sc, mat, L, bits=16, noise=0.0) / np.asarray(L.intensities, np.float32)[:, None, None, :]
        lights = PointLights(L.positions)
        ref = float(sc.depth[sc.mask].mean())
        cfg = RONConfig(rounds=a.rounds, tol=0.0, tol_normals_deg=0.0)
        rons = {dr: RON(img.shape[:3], sc.camera, lights, mat, sc.mask, RONConfig(**{**cfg.__dict__, "device_rounds": dr}),
                        device=a.device) for dr in (False, True)}
        got = {False: [], True: []}
        for rep in range(a.repeat + 1):
            for dr in (False, True):
                t = time.perf_counter()
                res = rons[dr].run(img, reference_depth=ref)
                total = time.perf_counter() - t
                if rep:
                    got[dr].append((total, res.timings["integration"] - final["t"], res.energy, res.normal_change_deg))
        for dr in (False, True):
            rons[dr].close()
        row = {"size": size, "rounds": a.rounds, "integrations_in_rounds": a.rounds - 1}
        for dr, name in ((False, "host"), (True, "device")):
            row[name] = {"total_s": statistics.median(g[0] for g in got[dr]),
                         "rounds_integration_s": statistics.median(g[1] for g in got[dr]),
                         "energy": got[dr][-1][2], "normal_change_deg": got[dr][-1][3]}
        rows.append(row)
        print(f"{size}^2: rounds' integration host {row['host']['rounds_integration_s'] * 1e3:.1f} ms, device "
              f"{row['device']['rounds_integration_s'] * 1e3:.1f} ms ({a.rounds - 1} integrations); whole run "
              f"{row['host']['total_s']:.3f} s -> {row['device']['total_s']:.3f} s", flush=True)
    out = a.out or RESULTS / f"ron_device_rounds_{device_label(a.device)}.json"
    with open(out, "w") as f:
        json.dump({"device": device_label(a.device), "scene": "perspective Blinn-Phong sphere, 3 point lights, "
                   "known material", "runs": a.repeat, "rows": rows}, f, indent=1)
    print("wrote", out)


if __name__ == "__main__":
    main()
