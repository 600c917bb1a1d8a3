"""Worst relative error of each Warp reflectance model against the float64 numpy reference.

`python perf/model_accuracy.py [--device cpu] [--samples 5000] [--sets 10]`: random lit and visible geometries,
random parameters (exponents up to 60), relative error over values > 1e-4.
"""

import argparse
import sys

import numpy as np
from _common import ROOT, write_results

sys.path.insert(0, str(ROOT / "tests"))  # the independent reference lives with the tests

import reference_models as ref  # noqa: E402
from test_models import eval_kernel, random_geometry, random_material  # noqa: E402

from gpps._runtime import resolve_device  # noqa: E402
from gpps.material import BRDF_NAMES  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--samples", type=int, default=5000)
    ap.add_argument("--sets", type=int, default=10)
    a = ap.parse_args()
    dev = resolve_device(a.device)
    rng = np.random.default_rng(99)
    rows = []
    for b in BRDF_NAMES:
        worst = worst_abs = 0.0
        for _ in range(a.sets):
            mat = random_material(rng, b)
            n, l, v = random_geometry(rng, a.samples)
            got = eval_kernel(dev, mat, n, l, v)
            cos, s = ref.terms(mat, n, l, v)
            for g, w in ((got[:, 0], cos), (got[:, 1], s)):
                big = np.abs(w) > 1e-4
                if big.any():
                    worst = max(worst, float(np.max(np.abs(g[big] - w[big]) / np.abs(w[big]))))
                worst_abs = max(worst_abs, float(np.max(np.abs(g - w))))
        rows.append({"brdf": b, "max_rel_err": worst, "max_abs_err": worst_abs, "samples": a.samples * a.sets})
        print(f"{b:18s} max rel err {worst:.2e}  max abs err {worst_abs:.2e}  ({a.samples * a.sets} samples)")
    print("wrote", write_results("model_accuracy", dev, {"rows": rows}))


if __name__ == "__main__":
    main()
