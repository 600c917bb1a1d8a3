"""Test-time augmentation of the single-image network, chosen on our own renders (issue 24).

Renders ``--scenes`` validation scenes of the training recipe (:mod:`training/shapes.py`, recipe v2, the
validation seeds ``TRAIN_SEED_LIMIT - 1 - k`` that training never draws) with gpps's renderer, one random
light each, and reports the network's MAEN (deg) for each ``tta`` of :meth:`gpps.nn.model.SingleNet.predict`
beside the flat plane, with the time per image.  This is the data the choice is made on; the Mitsuba
held-out set (perf/heldout_eval.py) is only the check afterwards.

    python perf/single_tta.py [--scenes 100] [--size 128] [--device cpu]
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=100)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args(argv)
    from shapes import TRAIN_SEED_LIMIT, SceneRenderer, render_random_sample

    from gpps.host.metrics import normal_errors
    from gpps.nn.model import TTA_NAMES, SingleNet

    net = SingleNet.load()
    rend = SceneRenderer(a.device)
    err = {t: [] for t in ("flat",) + TTA_NAMES}
    secs = {t: 0.0 for t in TTA_NAMES}
    fam = []
    for k in range(a.scenes):
        sc, n, imgs, _ = render_random_sample(a.size, TRAIN_SEED_LIMIT - 1 - k, rend, n_lights=1)
        flat = np.zeros_like(n)
        flat[..., 2] = 1
        err["flat"].append(normal_errors(flat, n, sc.mask)["mean"])
        fam.append(sc.family)
        for t in TTA_NAMES:
            t0 = time.perf_counter()
            p, _ = net.predict(imgs[0], sc.mask, tta=t)
            secs[t] += time.perf_counter() - t0
            err[t].append(normal_errors(p, n, sc.mask)["mean"])
    rows = {t: {"maen": float(np.mean(v)), "median": float(np.median(v))} for t, v in err.items()}
    for t in TTA_NAMES:
        rows[t]["seconds_per_image"] = secs[t] / a.scenes
        rows[t]["better_than_none"] = float(np.mean(np.array(err[t]) < np.array(err["none"])))
    by_family = {f: {t: float(np.mean([e for e, g in zip(err[t], fam) if g == f])) for t in err} for f in sorted(set(fam))}
    for t, r in rows.items():
        print(f"{t:9s} MAEN {r['maen']:6.2f}  median {r['median']:6.2f}" + (f"  {r['seconds_per_image']:.3f} s/image, "
              f"better than none on {100 * r['better_than_none']:.0f} %" if t in secs else ""))
    for f, v in by_family.items():
        print(f"  {f:12s} " + "  ".join(f"{t} {x:.2f}" for t, x in v.items()))
    print("wrote", write_results("single_tta", a.device, {"scenes": a.scenes, "size": a.size, "rows": rows,
                                                          "by_family": by_family, "weights": net.meta}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
