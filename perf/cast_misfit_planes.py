"""Planes under cast shadows, 5 lights, the pixel solver alone (session 37: the cast-shadow refit's third contradiction).

The scene of ``tests/shadow_reference.py::planes_under_cast_shadows`` at 24 x 24 (the test uses 12 x 12): normals
within 40 deg of the view, 5 directional lights, one light (two in 30 % of the pixels) casting a shadow with 0-4 % of
bounced light, noise 0.002.  The robust fit as the folder flow runs it from 4 images (Cauchy, 3 IRLS rounds, shadow
threshold 0.02, ``shadow_relative`` 0.1).  Prints the error of the pixels with one and with two cast shadows; run it
on two trees to compare (``PYTHONPATH``)::

    python perf/cast_misfit_planes.py SEED [blinn-phong|plastic|cook-torrance]
"""
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # tests/shadow_reference.py: the scene

import numpy as np  # noqa: E402

from gpps import DirectionalLights, Orthographic, SolverConfig  # noqa: E402
from gpps.pipeline.solver import PixelSolver  # noqa: E402
from shadow_reference import planes_under_cast_shadows  # noqa: E402

seed = int(sys.argv[1]) if len(sys.argv) > 1 else 0
brdf = sys.argv[2] if len(sys.argv) > 2 else "blinn-phong"
dirs, mat, n, shad, img = planes_under_cast_shadows("cpu", seed, 24, 24, brdf)
cfg = SolverConfig(solver="lm", starts=4, robust="cauchy", irls_rounds=3, noise_level=2e-3, shadow_threshold=0.02,
                   shadow_relative=0.1)
out = PixelSolver(img.shape[:3], Orthographic(), DirectionalLights(dirs), mat, cfg, device="cpu").run(
    img, np.ones(img.shape[1:3], bool))
e = np.degrees(np.arccos(np.clip(np.sum(out["normals"] * n, -1), -1, 1)))
has, one, both = shad.any(0), shad.sum(0) == 1, shad.sum(0) == 2
print(f"{brdf}: cast-shadow pixels {has.sum()} mean {e[has].mean():.3f}; one shadow {one.sum()}: mean "
      f"{e[one].mean():.3f}, 90th percentile {np.percentile(e[one], 90):.3f}; two {both.sum()}: mean {e[both].mean():.3f}; "
      f"no shadow: mean {e[~has].mean():.3f}")
