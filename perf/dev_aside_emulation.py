"""Session 17 experiment (issue 25, not merged): set dark observations aside before the per-pixel fit.

On the Mitsuba development captures (seeds 3000-3009, cached by perf/dev_eval.py) the default pipeline's largest
12-light error is the torus' backdrop seen through its hole: lit by 5-6 of 12 lights, the others in cast shadow
with 2-7 % of inter-reflected light (above the noise, so two-sided terms).  A normal tilted away from the camera
axis fits those 12 observations better than the true one, under least squares and under the Cauchy loss (a
RANSAC over light triples scored by the Cauchy cost picks it too), so no start or reweighting round finds the true
normal.  This script emulates the rule "set aside every observation darker than ``tau`` times the pixel's lit
level (the grey value a quarter of its observations reach)" by removing those observations through the folder
flow's ``valid`` mask (``gpps.flows.folder._saturation``, patched), and runs the default pipeline::

    python perf/dev_aside_emulation.py TAU OUT.jsonl "*directional12*seed300*,*point12*seed300*"
    python perf/dev_aside_emulation.py TAU OUT.jsonl ball,bear --diligent ../shared/data/diligent
    python perf/dev_aside_emulation.py 0.3 OUT.jsonl "*directional12*seed300*" --oracle   (directional lights)

Rows are those of perf/dev_visible_eval.py (its ``table`` mode compares files).  Results and the kernel variants
tried are in perf/results/s17/README.md.
"""

from __future__ import annotations

import argparse
import glob
import json
import os
import time
import warnings

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("tau", type=float, help="fraction of the lit level below which an observation is set aside")
    ap.add_argument("out", help="JSON lines, appended")
    ap.add_argument("patterns", help="comma-separated capture globs (or object names with --diligent)")
    ap.add_argument("--diligent", default=None, help="DiLiGenT root: the patterns are object names")
    ap.add_argument("--oracle", action="store_true",
                    help="instead, remove the observations below tau x the ground truth's Lambertian prediction "
                         "(albedo: the median of I / n.l over the lights with n.l > 0.15): cast shadows known")
    a = ap.parse_args()

    import gpps
    import gpps.flows.folder as folder
    from gpps.host.metrics import normal_errors
    from gpps.io import read_capture

    warnings.simplefilter("ignore")
    if a.diligent:
        caps = [os.path.join(a.diligent, p) for p in a.patterns.split(",")]
    else:
        root = os.path.join(os.environ.get("GPPS_CACHE_DIR", ".cache"), "mitsuba_captures")
        caps = sorted(c for p in a.patterns.split(",") for c in glob.glob(os.path.join(root, p)))
    if not caps:
        raise SystemExit(f"no capture matches {a.patterns!r}")
    saturation = folder._saturation
    try:
        for c in caps:
            ds = read_capture(c).dataset
            g = np.asarray(ds.images).mean(-1)
            n = g.shape[0]
            if a.oracle:
                ndl = np.einsum("hwc,nc->nhw", ds.normal_gt, np.asarray(ds.light_directions, float))
                with np.errstate(all="ignore"):
                    rho = np.nanmedian(np.where(ndl > 0.15, g / ndl, np.nan), 0)
                    aside = (ndl > 0.15) & (g < a.tau * rho * ndl)
            else:
                level = np.sort(g, 0)[n - (n + 3) // 4]  # the grey value a quarter of the observations reach
                aside = g < a.tau * level[None]
            folder._saturation = lambda cap, aside=aside: saturation(cap) & ~aside
            t = time.perf_counter()
            r = gpps.reconstruct_folder(c, gpps.FolderConfig(), device="cpu")
            dt = time.perf_counter() - t
            folder._saturation = saturation
            e = normal_errors(r.normals, ds.normal_gt, ds.mask)
            row = dict(capture=os.path.basename(c), method="pipeline", maen=e["mean"], median=e["median"],
                       seconds=dt, tau=a.tau, oracle=a.oracle, aside=float(aside[:, ds.mask].mean()))
            with open(a.out, "a") as f:
                f.write(json.dumps(row) + "\n")
            print(row, flush=True)
    finally:
        folder._saturation = saturation


if __name__ == "__main__":
    main()
