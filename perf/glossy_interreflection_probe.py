"""Does the first bounce under the fitted model predict a metal's interreflections?  (issue 25, session 34)

On a Mitsuba development capture (perf/dev_eval.py's scenes; default: copper ridges, GGX alpha 0.2, 12 directional
lights) this renders the scene twice, with interreflections (``max_depth`` 4, the capture) and without (``max_depth``
2), takes their difference as the true indirect light, and compares it with
``gpps.flows.interreflection.interreflection_terms(..., glossy=True)`` (the one-bounce gather under the fitted
reflectance model at both ends, :meth:`gpps.pipeline.interreflection.Interreflections.gather_model`) computed

* ``truth``: on the true depth and normals, the conductor of the scene's alpha, the albedo fitted by least squares
  to the direct-only images on the true normals;
* ``reconstruction``: on the default pipeline's reconstruction (its depth, normals, albedo and chosen model);

and prints the ratio of the sums (predicted / true) and their correlation over the mask's pixels and images.  Then
it runs the compensation as ``reconstruct_subtracting`` would with this gather (``--rounds`` rounds: subtract,
reconstruct again) and prints the MAEN after each reconstruction.  Nothing in the library is tuned on it.

    python perf/glossy_interreflection_probe.py [--scene ridges_roughconductor] [--kind directional] [--lights 12]
        [--rounds 4] [--device cpu]
"""

from __future__ import annotations

import argparse
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
sys.path.insert(0, str(ROOT / "training"))
from _common import folder_solve  # noqa: E402
from dev_eval import DEV  # noqa: E402


def main(argv=None) -> None:
    import mitsuba_scenes as ms

    import gpps
    import gpps.flows.interreflection as gi
    from gpps.camera import camera_from_K
    from gpps.io import read_capture
    from gpps.pipeline.render import Renderer

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="ridges_roughconductor")
    ap.add_argument("--kind", default="directional")
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    name, shape, material, alpha, texture, seed = next(d for d in DEV if d[0] == a.scene)
    spec = ms.CaptureSpec(shape=shape, material=material, alpha=alpha, texture=texture, light_kind=a.kind,
                          n_lights=a.lights, size=128, spp=64, bits=16, seed=seed)
    d4, d2 = ms.make_capture(spec), ms.make_capture(replace(spec, max_depth=2))
    ds4, ds2 = read_capture(d4).dataset, read_capture(d2).dataset  # (images already over the light intensities)
    I4, I2 = ds4.images.astype(np.float64), ds2.images.astype(np.float64)
    m, gt = ds4.mask, ds4.normal_gt
    true_indirect = I4 - I2
    cam = camera_from_K(ds4.K)
    if ds4.light_positions is not None:
        lights = gpps.PointLights(ds4.light_positions)
    else:
        lights = gpps.DirectionalLights(ds4.light_directions)
    print(f"capture {spec.name}: true indirect share {true_indirect[:, m].sum() / I4[:, m].sum():.4f}")

    def compare(tag, B):
        t, b = true_indirect[:, m].ravel(), B[:, m].ravel()
        print(f"{tag}: predicted / true indirect (sums) {b.sum() / t.sum():.3f}, correlation {np.corrcoef(t, b)[0, 1]:.3f}",
              flush=True)

    from types import SimpleNamespace

    mat = gpps.Material("conductor", roughness=alpha, f0=1.0) if material == "roughconductor" else None
    if mat is not None:
        with Renderer(m.shape, cam, lights, mat, device=a.device) as rd:
            P = rd.run(ds4.depth_gt.astype(np.float32), m, np.ones(m.shape + (3,), np.float32),
                       gt.astype(np.float32)).astype(np.float64)
        alb = ((I2 * P).sum(0) / np.maximum((P * P).sum(0), 1e-12)).astype(np.float32)
        print(f"truth: albedo fitted to the direct light on the true normals, median {np.median(alb[m], 0).round(3)}")
        rec = SimpleNamespace(normals=gt.astype(np.float32), depth=ds4.depth_gt, depth_mask=m, albedo=alb,
                              material=mat)
        compare("truth", gi.interreflection_terms(I4.astype(np.float32), m, lights, cam, rec, glossy=True,
                                                  device=a.device)["B"])

    solve, first = folder_solve(d4, a.device)

    def maen(r):
        return float(np.degrees(np.arccos(np.clip((r.normals * gt).sum(-1), -1, 1)))[m].mean())

    images = I4.astype(np.float32)
    rec = first
    print(f"round 0: MAEN {maen(rec):.3f} deg, model {rec.material.brdf}", flush=True)
    for r in range(a.rounds):
        B = gi.interreflection_terms(images, m, lights, cam, rec, glossy=True, device=a.device)["B"]
        compare(f"round {r + 1} gather on the last reconstruction", B)
        rec = solve(np.clip(images - B, 0.0, None))
        print(f"round {r + 1}: MAEN {maen(rec):.3f} deg, model {rec.material.brdf}", flush=True)


if __name__ == "__main__":
    main()
