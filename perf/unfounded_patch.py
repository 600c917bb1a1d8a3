"""Write ``tests/data/unfounded_patch.npz``: a 13 x 13 crop of a Mitsuba development capture whose centre pixel the
solver fits with a free albedo (``FLAG_UNFOUNDED``, tests/test_unfounded.py).

The capture is ``spheres-roughplastic0.3-tex-point12-...-seed3004`` (perf/dev_eval.py's renders: rough-plastic
spheres on a textured plane, 12 point lights, interreflections), the crop centred on pixel (40, 68) at a sphere's
rim where it meets another.  With the material the default folder flow estimates there (plastic, ks 0.412,
roughness 0.238) and the solver settings of a 12-image reconstruction, the fit of that pixel turns its normal
grazing to the view, where plastic's diffuse term vanishes, and returns an albedo of 8258 (its neighbours'
0.2-0.4): found in session 35 with ``reconstruct_folder`` returning 4.5e5 there.  Saved: the images (already
divided by the lights' intensities), the mask, the true depth, the crop's intrinsics, the lights and the material.

Usage:  python perf/unfounded_patch.py [OUT]
"""

from __future__ import annotations

import glob
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(out: str) -> None:
    import gpps
    from gpps.io import read_capture

    warnings.simplefilter("ignore")
    root = os.path.join(os.environ.get("GPPS_CACHE_DIR", str(ROOT / ".cache")), "mitsuba_captures")
    caps = glob.glob(os.path.join(root, "spheres-roughplastic0.3-tex-point12-*-seed3004-v1"))
    if not caps:
        raise SystemExit(f"render the development captures first (python perf/dev_eval.py --render-only) under {root}")
    c = caps[0]
    r = gpps.reconstruct_folder(c, gpps.FolderConfig(), device="cpu")
    ds = read_capture(c).dataset
    y0, x0, rad = 40, 68, 6
    rows, cols = slice(y0 - rad, y0 + rad + 1), slice(x0 - rad, x0 + rad + 1)
    K = np.array(ds.K, float)
    K[0, 2] -= x0 - rad
    K[1, 2] -= y0 - rad
    np.savez_compressed(out, images=ds.images[:, rows, cols].astype(np.float32), mask=ds.mask[rows, cols],
                        depth=np.load(os.path.join(c, "depth_gt.npy"))[rows, cols].astype(np.float32), K=K,
                        positions=np.asarray(r.lights.positions, float),
                        intensities=np.asarray(r.lights.intensities, float),
                        material=json.dumps(r.report["material"]), source=os.path.basename(c))
    print("wrote", out)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else str(ROOT / "tests" / "data" / "unfounded_patch.npz"))
