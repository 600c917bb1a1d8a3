"""Is ``gpps.reconstruct`` free of the images' scale?  (Session 18: ``gpps.flows.photometric.working_scale``.)

Three synthetic scenes with ground truth (64^2, perspective, 16-bit, material unknown): Blinn-Phong bumps under 8
directional lights, Cook-Torrance sphere under 4, Cook-Torrance bumps under 3.  Each is reconstructed with its
images times ``s`` (the lights' intensities 1: the albedo scales with ``s``) and with images and intensities
both times ``s`` (the albedo stays, the images' own scale moves).  Prints and writes MAEN (deg) and the estimated
ks per scale to ``perf/results/scale_invariance_<device>.json`` (or ``--out``).  The band of :data:`WORKING_ALBEDO` came from
the first mode's sweep on the tree before the change (``--scales`` from 1/64 to 16).

    python perf/scale_invariance.py [--device cpu] [--scales 1e-8,1e-3,0.0625,1,16,1e3,1e6] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import warnings

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scales", default="1e-8,1e-3,0.015625,0.0625,1,4,16,64,1e3,1e6")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    import gpps

    scales = [float(x) for x in args.scales.split(",")]
    bumps = gpps.make_scene("bumps", 64, "perspective")
    sphere = gpps.make_scene("sphere", 64, "perspective")
    ct = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    cases = [("bumps, Blinn-Phong, 8 directional", bumps, gpps.Material("blinn-phong", ks=0.4, shininess=30.0),
              gpps.default_lights("directional", 8), "blinn-phong"),
             ("sphere, Cook-Torrance, 4 directional", sphere, ct, gpps.default_lights("directional", 4), "cook-torrance"),
             ("bumps, Cook-Torrance, 3 directional", bumps, ct, gpps.default_lights("directional", 3, layout="ring"),
              "cook-torrance")]
    rows = []
    for name, sc, mat, L, model in cases:
        img = (gpps.render(sc, mat, L, bits=16, device=args.device) / L.intensities[:, None, None, :]).astype(np.float32)
        n = len(L.directions)
        for mode in ("images", "images and intensities"):
            for s in scales:
                lights = gpps.DirectionalLights(L.directions, np.full((n, 3), s if mode != "images" else 1.0))
                r = gpps.reconstruct(img * np.float32(s), sc.mask, lights, camera=sc.camera, material=model,
                                     device=args.device)
                row = dict(case=name, mode=mode, scale=s,
                           maen=float(gpps.normal_errors(r.normals, sc.normals, sc.mask)["mean"]),
                           ks=float(r.material.ks), rescaled=any("albedo scale" in w for w in r.warnings))
                rows.append(row)
                print(f"{name:40s} {mode:24s} x{s:<9g} MAEN {row['maen']:.3f}  ks {row['ks']:.4g}"
                      f"{'  (rescaled)' if row['rescaled'] else ''}", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"device": args.device, "rows": rows}, f, indent=1)
        print("wrote", args.out)
    else:
        from _common import write_results

        print("wrote", write_results("scale_invariance", args.device, {"rows": rows}))


if __name__ == "__main__":
    main()
