"""``gpps.reconstruct_single`` with three images on our own development scenes (issue 24): is the refinement
better than the network alone, scene by scene?

Scenes: ``--scenes`` validation scenes of the training recipe v2 (:mod:`training/shapes.py`; seeds
``TRAIN_SEED_LIMIT - 1 - k``, never trained on), each rendered by gpps's renderer under three random lights of
one kind with the recipe's cast shadows, fill light, exposure, noise and quantisation: the hard cases the
refinement's Blinn-Phong model lacks.  Reports per scene the network's MAEN (deg) and the refined MAEN, and the
share of scenes the refinement made worse.  ``--set KEY=VALUE`` overrides :class:`gpps.SingleConfig` fields
(numbers or names), so variants are compared on the same scenes.  This is the data refinement rules are chosen
on; the Mitsuba held-out set (perf/heldout_eval.py) is the check afterwards.  ``--mitsuba SHARD``: the scenes of a
three-light shard of :mod:`training/mitsuba_random.py` instead (the same generator rendered by Mitsuba's path
tracer: interreflections, real rough dielectrics and metals; validation seeds 910000+, never trained on).

    python perf/single_dev.py [--scenes 30] [--size 128] [--set prior_weight=0.01] [--mitsuba SHARD] [--tag T]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "training"))
from _common import write_results  # noqa: E402


def _value(v: str):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return {"None": None, "True": True, "False": False}.get(v, v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=30)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE of SingleConfig")
    ap.add_argument("--tag", default=None)
    ap.add_argument("--mitsuba", default=None, help="a three-light shard of training/mitsuba_random.py")
    a = ap.parse_args(argv)
    from shapes import TRAIN_SEED_LIMIT, SceneRenderer, render_random_sample

    import gpps
    from gpps.host.metrics import normal_errors

    kw = {k: _value(v) for k, v in (s.split("=", 1) for s in a.set)}
    cfg = gpps.SingleConfig(integrate=False, **kw)
    rend = SceneRenderer(a.device)
    shard = None
    if a.mitsuba:
        from mitsuba_random import decode_shard

        shard = decode_shard(a.mitsuba)
        if shard["images"].ndim != 5 or shard["images"].shape[1] < 3:
            raise SystemExit(f"--mitsuba: expected a shard of scenes with three lights, got images {shard['images'].shape}")
    rows = []
    t0 = time.perf_counter()
    for k in range(a.scenes if shard is None else min(a.scenes, len(shard["mask"]))):
        if shard is None:
            sc, n, imgs, lights = render_random_sample(a.size, TRAIN_SEED_LIMIT - 1 - k, rend, n_lights=3)
            mask, seed, family, brdf, kind = sc.mask, TRAIN_SEED_LIMIT - 1 - k, sc.family, sc.material.brdf, lights.kind
        else:
            info = shard["info"][k]
            imgs, n, mask = shard["images"][k][:3], shard["normals"][k], shard["mask"][k]
            seed, family, brdf, kind = info["seed"], info["family"], info["bsdf_objects"], info["light"]
        res = gpps.reconstruct_single(imgs, mask, config=cfg, device=a.device)
        e_net = normal_errors(res.normals_net, n, res.mask)["mean"]
        e_ref = normal_errors(res.normals, n, res.mask)["mean"]
        rows.append({"seed": int(seed), "family": family, "brdf": brdf, "lights": kind, "maen_net": e_net, "maen": e_ref,
                     "kept_network": res.kept_network, "pixels": int(res.mask.sum())})
        print(f"{k:3d} {family:12s} {brdf:18s} {kind:11s} net {e_net:6.2f}  refined {e_ref:6.2f}"
              f"  kept {res.kept_network / res.mask.sum():.2f}", flush=True)
    net = np.array([r["maen_net"] for r in rows])
    ref = np.array([r["maen"] for r in rows])
    summary = {"maen_net": float(net.mean()), "maen": float(ref.mean()), "worse_share": float(np.mean(ref > net)),
               "worse_by_1deg_share": float(np.mean(ref > net + 1.0)), "worst_delta": float(np.max(ref - net)),
               "seconds": time.perf_counter() - t0}
    print(f"mean net {summary['maen_net']:.2f}  refined {summary['maen']:.2f}  worse on {100 * summary['worse_share']:.0f} % "
          f"(by > 1 deg {100 * summary['worse_by_1deg_share']:.0f} %), worst +{summary['worst_delta']:.2f} deg")
    name = "single_dev" + (f"_{a.tag}" if a.tag else "")
    print("wrote", write_results(name, a.device, {"config": {k: str(v) for k, v in kw.items()}, "scenes": a.scenes,
                                                  "data": a.mitsuba or "recipe v2, gpps renders",
                                                  "rows": rows, "summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
