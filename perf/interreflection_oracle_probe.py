"""How much of what the interreflection compensation leaves is the reconstructed surface's fault?  (issue 25)

On one Mitsuba development capture (cached by perf/dev_eval.py; default: rough-plastic steps, 12 directional lights)
this takes the default pipeline's first reconstruction (``FolderConfig(interreflections="subtract")``'s ``solve``)
and runs one compensation round four ways, each followed by the same reconstruction:

* the diffuse gather (``interreflection_terms``, what the flow does) over the reconstructed surface, then over the
  true one (true depth and normals; the reconstruction's albedo and model);
* the diffuse gather plus the model gather's glossy paths (``glossy=True`` with the fitted model, less the same
  with ``ks = 0``: the paths through a specular lobe at either end) over each surface.

Printed: the share of the images' light taken out and the MAEN after.  Where ``d2`` renders of the capture are
cached (perf/dev_floor.py renders them) the true indirect share is printed too.  A diagnosis, nothing tuned.

    python perf/interreflection_oracle_probe.py ["steps-roughplastic0.15-directional12*seed300*"]
"""

from __future__ import annotations

import glob
import os
import sys
import warnings
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))


def main(argv=None) -> None:
    import gpps
    import gpps.flows.interreflection as gi
    from _common import folder_solve
    from gpps.camera import camera_from_K
    from gpps.io import read_capture

    argv = sys.argv[1:] if argv is None else argv
    pattern = argv[0] if argv else "steps-roughplastic0.15-directional12*seed300*"
    warnings.simplefilter("ignore")
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", str(ROOT / ".cache")), "mitsuba_captures")
    caps = sorted(c for c in glob.glob(os.path.join(root, pattern)) if "-d4-" in c)
    if not caps:
        raise SystemExit(f"no capture under {root} matches {pattern!r} (render them with perf/dev_eval.py)")
    c = caps[0]
    ds = read_capture(c).dataset
    g, m = ds.normal_gt, ds.mask
    images = ds.images.astype(np.float32)
    d2 = c.replace("-d4-", "-d2-")
    if os.path.isdir(d2):
        i2 = read_capture(d2).dataset.images
        print(f"true indirect share {(images - i2)[:, m].sum() / images[:, m].sum():.4f}")
    solve, rec = folder_solve(c, "cpu")
    cam = camera_from_K(ds.K)
    lights = (gpps.PointLights(ds.light_positions) if ds.light_positions is not None
              else gpps.DirectionalLights(ds.light_directions))

    def maen(r):
        return float(np.degrees(np.arccos(np.clip((r.normals * g).sum(-1), -1, 1)))[m].mean())

    print(f"{os.path.basename(c)}\nfirst reconstruction: MAEN {maen(rec):.3f} deg ({rec.material.brdf})", flush=True)
    surfaces = {"reconstructed": SimpleNamespace(normals=rec.normals, depth=rec.depth, depth_mask=rec.depth_mask,
                                                 albedo=rec.albedo, material=rec.material),
                "true": SimpleNamespace(normals=g.astype(np.float32), depth=ds.depth_gt, depth_mask=m,
                                        albedo=rec.albedo, material=rec.material)}
    for tag, s in surfaces.items():
        D = gi.interreflection_terms(images, m, lights, cam, s, max_albedo=1.0, device="cpu")["B"]
        full = gi.interreflection_terms(images, m, lights, cam, s, max_albedo=1.0, glossy=True, device="cpu")["B"]
        matte = SimpleNamespace(**{**vars(s), "material": replace(s.material, ks=0.0)})
        dd = gi.interreflection_terms(images, m, lights, cam, matte, max_albedo=1.0, glossy=True, device="cpu")["B"]
        for kind, B in (("diffuse", D), ("diffuse + glossy paths", D + full - dd)):
            r2 = solve(np.clip(images - B, 0.0, None))
            print(f"{tag} surface, {kind}: share taken out {B[:, m].sum() / images[:, m].sum():.4f} -> MAEN "
                  f"{maen(r2):.3f} deg", flush=True)


if __name__ == "__main__":
    main()
