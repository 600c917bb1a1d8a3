"""RON's continuation defaults against every round cold, on rendered scenes with the hard cases in them.

``RONConfig()`` scores the later material fits from warm starts (``material_warm``) and solves the normals
cold only in the first ``cold_rounds`` rounds; ``RONConfig(material_warm=False, cold_rounds=rounds)`` is the
pipeline before them (every candidate and every round from the cold multi-start).  Scenes: ``bumps`` and
``sphere`` (gpps.host.scenes), perspective, Cook-Torrance and Blinn-Phong, 3 and 12 directional lights and 3
point lights, 16-bit or 8-bit, image noise 0 or 1 %, material withheld (the model name only).  Reported per
case and mode: MAEN (deg), the estimates, rounds, seconds and per-stage timings.

Usage:  python perf/ron_continuation.py [--size 128] [--device cpu] [--out FILE]
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
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

import gpps  # noqa: E402
from gpps.flows.synthetic import default_lights, render  # noqa: E402
from gpps.host.metrics import angular_error  # noqa: E402
from gpps.host.scenes import make_scene  # noqa: E402
from gpps.lights import DirectionalLights, PointLights  # noqa: E402
from gpps.material import Material  # noqa: E402

TRUE = {
    "blinn-phong": Material("blinn-phong", ks=0.7, shininess=60.0),
    "cook-torrance": Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5),
}
CASES = [  # scene, brdf, light kind, lights, bits, noise
    ("bumps", "cook-torrance", "directional", 3, 16, 0.0),
    ("bumps", "cook-torrance", "directional", 3, 8, 0.01),
    ("bumps", "blinn-phong", "directional", 3, 16, 0.01),
    ("bumps", "cook-torrance", "directional", 12, 8, 0.01),
    ("sphere", "cook-torrance", "point", 3, 16, 0.01),
    ("sphere", "blinn-phong", "directional", 12, 16, 0.0),
]


def run_case(scene, brdf, kind, n, bits, noise, size, device):
    sc = make_scene(scene, size, "perspective", albedo="texture")
    L = default_lights(kind, n, layout="spiral") if n > 3 else default_lights(kind, n)
    raw = render(sc, TRUE[brdf], L, bits=bits, noise=noise, device=device)
    img = raw / np.asarray(L.intensities, np.float32)[:, None, None, :]
    Lu = DirectionalLights(L.directions) if kind == "directional" else PointLights(L.positions)
    sat = float(0.999 / np.min(L.intensities))
    ref = float(sc.depth[sc.mask].mean())
    rows = {}
    rounds = gpps.RONConfig().rounds
    for mode, cfg in (("continuation", gpps.RONConfig()),
                      ("all_cold", gpps.RONConfig(material_warm=False, cold_rounds=rounds))):
        t = time.perf_counter()
        rec = gpps.reconstruct(img, sc.mask, Lu, camera=sc.camera, material=brdf, reference_depth=ref,
                               saturation=sat, config=cfg, device=device)
        dt = time.perf_counter() - t
        e = angular_error(rec.normals, sc.normals, sc.mask)[sc.mask]
        rows[mode] = {"maen": float(e.mean()), "estimated": rec.estimated, "rounds": rec.rounds, "seconds": dt,
                      "timings": rec.timings}
    return {"scene": scene, "brdf": brdf, "lights": kind, "images": n, "bits": bits, "noise": noise, "size": size,
            "true": {k: getattr(TRUE[brdf], k) for k in rows["all_cold"]["estimated"]}, **rows}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    out = Path(a.out or ROOT / "perf" / "results" / f"ron_continuation_{a.device.replace(':', '')}.json")
    rows = []
    for case in CASES:
        r = run_case(*case, a.size, a.device)
        rows.append(r)
        c, w = r["all_cold"], r["continuation"]
        print(f"{r['scene']:6s} {r['brdf']:13s} {r['lights']:11s} {r['images']:2d} img {r['bits']:2d} bit noise "
              f"{r['noise']:.2f}: MAEN cold {c['maen']:.3f} cont {w['maen']:.3f} deg | {c['seconds']:.1f} -> "
              f"{w['seconds']:.1f} s | est cold {c['estimated']} cont {w['estimated']} true {r['true']}", flush=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"device": a.device, "size": a.size, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
