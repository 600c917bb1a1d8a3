"""RON's material search on synthetic ground truth: every model, scene, light kind and count (session 19).

``gpps.reconstruct`` with the model name only (ks and the lobe estimated) on gpps renders with exact normals:
Blinn-Phong (ks 0.7, shininess 60), Cook-Torrance (ks 0.8, m 0.2, f0 0.5) and plastic (ior 1.5, ks 1.2, m 0.15);
the bumps and the sphere; 3, 4, 6, 8 and 12 directional and point lights (``default_lights``); perspective,
16-bit, Gaussian noise 0.002, 96^2.  One JSON line per case: MAEN (deg), the estimate, seconds.  Run it from two
trees (``PYTHONPATH=<tree>``) to compare them::

    python perf/material_search_sweep.py OUT.jsonl [blinn-phong,cook-torrance,plastic] [size]
"""

from __future__ import annotations

import json
import sys
import time
import warnings

import numpy as np


def main(out: str, brdfs: str = "blinn-phong,cook-torrance,plastic", size: str = "96") -> None:
    import gpps
    from gpps.flows.synthetic import default_lights, render
    from gpps.host.metrics import angular_error
    from gpps.host.scenes import make_scene
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material

    warnings.simplefilter("ignore")
    mats = {"blinn-phong": Material("blinn-phong", ks=0.7, shininess=60.0),
            "cook-torrance": Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5),
            "plastic": Material.from_ior("plastic", 1.5, ks=1.2, roughness=0.15)}
    with open(out, "w") as f:
        for brdf in brdfs.split(","):
            for scene in ("bumps", "sphere"):
                for kind in ("directional", "point"):
                    for n in (3, 4, 6, 8, 12):
                        sc = make_scene(scene, int(size), "perspective")
                        lights = default_lights(kind, n)
                        raw = render(sc, mats[brdf], lights, bits=16, noise=0.002, seed=n)
                        img = raw / np.asarray(lights.intensities, np.float32)[:, None, None, :]
                        lu = DirectionalLights(lights.directions) if kind == "directional" else PointLights(lights.positions)
                        t = time.perf_counter()
                        rec = gpps.reconstruct(img, sc.mask, lu, camera=sc.camera, material=brdf,
                                               reference_depth=float(sc.depth[sc.mask].mean()),
                                               saturation=float(0.999 / np.min(lights.intensities)), device="cpu")
                        e = angular_error(rec.normals, sc.normals, sc.mask)[sc.mask]
                        row = dict(brdf=brdf, scene=scene, kind=kind, n=n, maen=float(e.mean()),
                                   est={k: round(v, 4) for k, v in rec.estimated.items()}, s=time.perf_counter() - t)
                        f.write(json.dumps(row) + "\n")
                        f.flush()
                        print(row, flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:])
