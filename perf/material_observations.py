"""RON's material sample sized by an observation budget (``RONConfig.material_observations``) against the fixed
2000 pixels, on rendered scenes with many lights: estimates, MAEN and seconds.

Scenes: ``bumps`` and ``sphere`` (gpps.host.scenes), perspective, textured albedo, Cook-Torrance (ks 0.8,
m 0.2) or Blinn-Phong (ks 0.7, shininess 60), N directional lights on a spiral, 16-bit with 0.5 % noise,
material withheld.  Usage:  python perf/material_observations.py [--size 128] [--device cpu] [--images 24 96]
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
from gpps.flows.ron import estimable_parameters  # noqa: E402
from gpps.lights import DirectionalLights  # noqa: E402
from gpps.material import Material  # noqa: E402

TRUE = {"cook-torrance": Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5),
        "blinn-phong": Material("blinn-phong", ks=0.7, shininess=60.0)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--images", type=int, nargs="*", default=[24, 96])
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    rows = []
    for scene, brdf in (("bumps", "cook-torrance"), ("sphere", "blinn-phong")):
        sc = make_scene(scene, a.size, "perspective", albedo="texture")
        for n in a.images:
            L = default_lights("directional", n, layout="spiral")
            raw = render(sc, TRUE[brdf], L, bits=16, noise=0.005, device=a.device)
            img = raw / np.asarray(L.intensities, np.float32)[:, None, None, :]
            Lu = DirectionalLights(L.directions)
            sat = float(0.999 / np.min(L.intensities))
            ref = float(sc.depth[sc.mask].mean())
            row = {"scene": scene, "brdf": brdf, "images": n, "size": a.size,
                   "true": {k: getattr(TRUE[brdf], k) for k in estimable_parameters(brdf)}}
            for name, cfg in (("fixed_2000", gpps.RONConfig(material_observations=10**9)),
                              ("budget", gpps.RONConfig())):
                t = time.perf_counter()
                rec = gpps.reconstruct(img, sc.mask, Lu, camera=sc.camera, material=brdf, reference_depth=ref,
                                       saturation=sat, config=cfg, device=a.device)
                e = angular_error(rec.normals, sc.normals, sc.mask)[sc.mask]
                row[name] = {"maen": float(e.mean()), "estimated": rec.estimated, "seconds": time.perf_counter() - t,
                             "material_s": rec.timings["material"]}
            rows.append(row)
            f, b = row["fixed_2000"], row["budget"]
            print(f"{scene:6s} {brdf:13s} N={n:3d}: MAEN {f['maen']:.3f} -> {b['maen']:.3f} deg, material "
                  f"{f['material_s']:.1f} -> {b['material_s']:.1f} s, est {f['estimated']} -> {b['estimated']} "
                  f"(true {row['true']})", flush=True)
    out = Path(a.out or ROOT / "perf" / "results" / f"material_observations_{a.device.replace(':', '')}.json")
    out.write_text(json.dumps({"device": a.device, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
