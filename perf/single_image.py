"""Issue 8 on held-out renders: the network's MAEN and scale-invariant depth error against a flat
plane, and the cuckoo refinement with three images, per test scene (256^2, CPU or CUDA).

Test scenes (never used in training): four scenes of the training recipe with held-out seeds
(``TEST_SEED_BASE + i``, shapes and textures never drawn in training), plus gpps's own ``sphere`` and
``bumps`` scenes with their sinusoid texture, a family the recipe never draws.  Each is rendered by
gpps's Warp renderer under three directional lights (a ring at 35 deg slant, white, intensity 0.8),
with the material the recipe drew (held-out seeds) or Blinn-Phong / Lambertian (gpps scenes), 8-bit.

* network: the first image alone (``normals_net_first``), MAEN and the offset-invariant RMS height
  error ``sqrt(mean D^2 - mean(D)^2)`` (D = predicted - true relative height, units of half the image
  width); the flat plane: n = (0, 0, 1), height 0.
* refined: ``reconstruct_single`` on the three images (network on each, averaged; lights by least
  squares, their bas-relief, ks and shininess from the highlights; one cuckoo round, defaults of
  SingleConfig).  Per row also the light error (deg), ks, shininess and the highlight fit.

    python perf/single_image.py [--device cpu] [--size 256] [--scenes sphere,bumps]

The JSON is written only for the full set of scenes (``--scenes`` is for looking at a few).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))  # training/shapes.py: the training scenes
from _common import write_results  # noqa: E402


def si_height(pred, true, mask):
    d = (pred - true)[mask]
    return float(np.sqrt(max(np.mean(d * d) - np.mean(d) ** 2, 0.0)))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--generations", type=int, default=80)
    ap.add_argument("--scenes", default=None,
                    help="comma-separated subset of heldout-0..3,sphere,bumps (printed, no JSON written)")
    args = ap.parse_args()

    from gpps.lights import DirectionalLights, ring_directions
    from gpps.material import Material
    from gpps.host.metrics import normal_errors
    from gpps.nn.model import SingleNet
    from shapes import TEST_SEED_BASE, RandomScene, SceneRenderer, random_scene
    from gpps.pipeline.cuckoo import CuckooConfig
    from gpps.flows.single import SingleConfig, reconstruct_single
    from gpps.host.scenes import D0, HALF_EXTENT, make_scene

    S = args.size
    rend = SceneRenderer(args.device)
    net = SingleNet.load()
    lights = DirectionalLights(ring_directions(3, 35.0), np.full((3, 3), 0.8))
    scenes = []
    for i in range(4):
        scenes.append(("heldout-%d" % i, random_scene(S, TEST_SEED_BASE + i)))
    for name, mat in (("sphere", Material("blinn-phong", ks=0.3, shininess=40)), ("bumps", Material("lambertian", ks=0.0))):
        sc = make_scene(name, S, "orthographic", albedo="texture", seed=123)
        height = np.where(sc.mask, (D0 - sc.depth) / HALF_EXTENT, 0.0)
        scenes.append((name, RandomScene(height, sc.mask, sc.albedo, sc.depth, "orthographic", mat, name, {})))
    if args.scenes:
        names = [n.strip() for n in args.scenes.split(",") if n.strip()]
        unknown = sorted(set(names) - {n for n, _ in scenes})
        if unknown:
            ap.error(f"--scenes: unknown {unknown}; expected some of {[n for n, _ in scenes]}")
        scenes = [(n, sc) for n, sc in scenes if n in names]
    cfg = SingleConfig(cuckoo=CuckooConfig(nests=12, generations=args.generations), integrate=False)
    rows = []
    for name, sc in scenes:
        n_gt = rend.normals(sc)
        imgs = rend.render(sc, lights, n_gt, bits=8)
        m = sc.mask
        t0 = time.perf_counter()
        n1, h1 = net.predict(imgs[0], m)
        t_net = time.perf_counter() - t0
        z_true = sc.relative_height()
        flat = np.zeros_like(n_gt)
        flat[..., 2] = 1.0
        res = reconstruct_single(imgs, m, config=cfg, net=net, device=args.device)
        row = {
            "scene": name, "family": sc.family, "brdf": sc.material.brdf, "camera": sc.camera_kind,
            "albedo": sc.info.get("albedo", "sinusoid texture (gpps.host.scenes)"), "pixels": int(m.sum()),
            "flat_maen": normal_errors(flat, n_gt, m)["mean"],
            "net_maen": normal_errors(n1, n_gt, m)["mean"],
            "net3_avg_maen": normal_errors(res.normals_net, n_gt, m)["mean"],
            "refined3_maen": normal_errors(res.normals, n_gt, m)["mean"],
            "flat_si_height": si_height(np.zeros_like(z_true), z_true, m),
            "net_si_height": si_height(h1, z_true, m),
            "light_error_deg": np.degrees(np.arccos(np.clip(np.sum(res.light_directions * lights.directions, 1), -1, 1))).tolist(),
            "ks": res.ks, "shininess": res.shininess, "highlights": res.highlights,
            "objective": res.objective, "net_seconds": t_net, "timings_s": res.timings,
        }
        row["refined_lower_than_net"] = row["refined3_maen"] < row["net_maen"]
        row["refined_lower_than_net3"] = row["refined3_maen"] < row["net3_avg_maen"]
        rows.append(row)
        print(f"{name:12s} {sc.material.brdf:18s} flat {row['flat_maen']:6.2f}  net {row['net_maen']:6.2f}  "
              f"net(3 avg) {row['net3_avg_maen']:6.2f}  refined {row['refined3_maen']:6.2f}  "
              f"lights {np.round(row['light_error_deg'], 1)} deg  ks {res.ks:.3f} shininess {res.shininess:.0f}  "
              f"SI height net {row['net_si_height']:.4f} flat {row['flat_si_height']:.4f}  {res.timings['total']:.1f}s", flush=True)
    summary = {k: float(np.mean([r[k] for r in rows])) for k in
               ("flat_maen", "net_maen", "net3_avg_maen", "refined3_maen", "flat_si_height", "net_si_height")}
    summary["refined_lower_than_net_on"] = f"{sum(r['refined_lower_than_net'] for r in rows)}/{len(rows)}"
    summary["refined_lower_than_net3_on"] = f"{sum(r['refined_lower_than_net3'] for r in rows)}/{len(rows)}"
    print(summary)
    if args.scenes:
        return
    path = write_results("single_image", args.device, {
        "size": S, "lights": "3 directional, ring at 35 deg slant", "bits": 8,
        "config": {"nests": cfg.cuckoo.nests, "generations": cfg.cuckoo.generations, "beta": cfg.cuckoo.beta,
                   "p_c": cfg.cuckoo.p_c, "rounds": cfg.rounds, "lights": cfg.lights, "albedo": cfg.albedo,
                   "specular": cfg.specular, "shininess_range": list(cfg.shininess_range),
                   "highlight_prior_deg": cfg.highlight_prior_deg or net.meta.get("val_maen_deg")},
        "weights_meta": net.meta, "rows": rows, "summary": summary,
    })
    print(path)


if __name__ == "__main__":
    main()
