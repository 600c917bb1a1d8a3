"""How many observations a pixel of each cached Mitsuba development capture has (issue 25's 3-light target).

A pixel's observation counts as lit when its grey value exceeds 5 noise levels (Immerkaer's estimate,
:func:`gpps.pipeline.solver.estimate_noise`) and 1 % of the mask's 99th-percentile grey value.  Prints, per capture,
the share of mask pixels with fewer than 3 lit observations (a normal and an albedo cannot be fixed from them
per pixel) and with none::

    python perf/dev_lit_counts.py [PATTERN]   (default "*-seed30*": perf/dev_eval.py's development captures)
"""

import glob
import os
import sys

import numpy as np

from gpps.io import read_capture
from gpps.pipeline.solver import estimate_noise

if __name__ == "__main__":
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", ".cache"), "mitsuba_captures")
    pattern = sys.argv[1] if len(sys.argv) > 1 else "*-seed30*"
    for c in sorted(glob.glob(os.path.join(root, pattern))):
        ds = read_capture(c).dataset
        m = ds.mask
        img = np.asarray(ds.images)
        g = img.mean(-1)
        sig = estimate_noise(img, m)
        lit = g > np.maximum(5 * sig[:, None, None], 0.01 * np.percentile(g[:, m], 99))
        nl = lit.sum(0)[m]
        print(f"{os.path.basename(c).split('-s128')[0]:46s} N={img.shape[0]:2d}  fewer than 3 lit: {(nl < 3).mean():.3f}"
              f"  none lit: {(nl == 0).mean():.3f}")
