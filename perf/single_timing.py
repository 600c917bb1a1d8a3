"""Wall time of ``gpps.reconstruct_single`` (the flow behind ``gpps single``) with one and three images, on one device.

Times are medians of ``--repeat`` calls after one warm-up call (compilation), the network in numpy, the cuckoo
refinement and the integration on ``--device``.  The capture is a folder as ``gpps render`` or
``perf/heldout_eval.py`` writes it (default: gpps's own sphere rendered here, 128^2, three directional lights).

    python perf/single_timing.py [--capture DIR] [--device cpu|cuda:0] [--repeat 3] [--out FILE]

Writes perf/results/single_timing_<sphere | the capture's first word>_<device>.json (and a copy to --out).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_results  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", default=None)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", default=None)
    ap.add_argument("--weights", default=None, help="the single-image network's weights file (default: the shipped one)")
    ap.add_argument("--tag", default=None, help="a suffix of the results name")
    a = ap.parse_args(argv)
    import gpps

    net = gpps.SingleNet.load(a.weights)
    from gpps.host.metrics import normal_errors

    if a.capture:
        from gpps.io import read_capture

        ds = read_capture(a.capture).dataset
        images, mask, gt, name = ds.images[:3], ds.mask, ds.normal_gt, Path(a.capture).name
    else:
        from gpps.flows.synthetic import render
        from gpps.host.scenes import make_scene
        from gpps.lights import DirectionalLights, ring_directions
        from gpps.material import Material

        sc = make_scene("sphere", 128, "orthographic", albedo="texture", seed=5)
        lights = DirectionalLights(ring_directions(3, 35.0), np.full((3, 3), 0.8))
        images = render(sc, Material("blinn-phong", ks=0.3, shininess=30.0), lights, device=a.device)
        mask, gt, name = sc.mask, sc.normals, "sphere-blinn-phong-128"
    rows = []
    for k in (1, 3):
        ts = []
        for r in range(a.repeat + 1):
            t = time.perf_counter()
            res = gpps.reconstruct_single(images[:k], mask, device=a.device, net=net)
            ts.append(time.perf_counter() - t)
        row = {"images": k, "seconds": statistics.median(ts[1:]), "runs_s": ts[1:], "first_s": ts[0],
               "timings": {kk: float(v) for kk, v in res.timings.items()},
               "maen_net": normal_errors(res.normals_net, gt, res.mask)["mean"],
               "maen": normal_errors(res.normals, gt, res.mask)["mean"]}
        rows.append(row)
        print(f"{name} {k} image(s) on {a.device}: {row['seconds']:.3f} s (first {ts[0]:.2f} s), "
              f"MAEN net {row['maen_net']:.2f} refined {row['maen']:.2f}", flush=True)
    tag = "sphere" if not a.capture else name.split("-")[0]
    tag = f"{tag}_{a.tag}" if a.tag else tag
    path = write_results(f"single_timing_{tag}", a.device, {"capture": name, "repeat": a.repeat, "rows": rows,
                                                            "weights": a.weights or "shipped", "widths": net.widths})
    if a.out:
        Path(a.out).write_text(path.read_text())
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
