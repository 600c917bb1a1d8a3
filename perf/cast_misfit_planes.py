"""Planes under cast shadows, 5 lights, the pixel solver alone (session 37: the cast-shadow refit's third contradiction).

24 x 24 pixels, normals within 40 deg of the view, albedo 0.3-0.7, 5 directional lights at 30-65 deg elevation; in
every pixel one light (two in 30 %) casts a shadow where it faces the surface by n.l > 0.2 (the observation replaced by
0-4 % of the albedo: light bounced from elsewhere), noise 0.002.  The robust fit as the folder flow runs it from 4
images (Cauchy, 3 IRLS rounds, shadow threshold 0.02, ``shadow_relative`` 0.1).  Prints the error of the pixels with a
cast shadow, one and two; run it on two trees to compare (``PYTHONPATH``).  The 12 x 12 version is
``tests/test_solvers.py::test_cast_shadow_refit_from_the_lit_misfit``::

    python perf/cast_misfit_planes.py SEED [blinn-phong|plastic|cook-torrance]
"""
import sys

import numpy as np

from gpps import DirectionalLights, Material, Orthographic, SolverConfig
from gpps.pipeline.render import Renderer
from gpps.pipeline.solver import PixelSolver

rng = np.random.default_rng(int(sys.argv[1]) if len(sys.argv) > 1 else 0)
brdf = sys.argv[2] if len(sys.argv) > 2 else "blinn-phong"
nl, h, w = 5, 24, 24
el = np.radians(rng.uniform(30, 65, nl))
az = np.radians(np.arange(nl) * 360 / nl + rng.uniform(-20, 20, nl))
dirs = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
t = np.radians(rng.uniform(0, 40, (h, w)))
p = rng.uniform(0, 2 * np.pi, (h, w))
n = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).astype(np.float32)
kd = rng.uniform(0.3, 0.7, (h, w, 1)).repeat(3, -1).astype(np.float32)
mat = Material(brdf, ks=0.2, shininess=20.0) if brdf == "blinn-phong" else Material(brdf, ks=0.5, roughness=0.3)
cam = Orthographic()
mask = np.ones((h, w), bool)
img = Renderer((h, w), cam, DirectionalLights(dirs), mat, device="cpu").run(np.ones((h, w), np.float32), mask, kd, normals=n)
k1 = rng.integers(0, nl, (h, w))
two = rng.random((h, w)) < 0.3
k2 = (k1 + rng.integers(1, nl, (h, w))) % nl
shad = np.stack([(k1 == k) | (two & (k2 == k)) for k in range(nl)]) & (np.einsum("hwc,kc->khw", n, dirs) > 0.2)
dark = rng.uniform(0.0, 0.04, (nl, h, w))[..., None] * kd[None]
img = np.where(shad[..., None], dark, img)
img = np.maximum(img + rng.normal(0, 0.002, img.shape), 0).astype(np.float32)
cfg = SolverConfig(solver="lm", starts=4, robust="cauchy", irls_rounds=3, noise_level=2e-3, shadow_threshold=0.02,
                   shadow_relative=0.1)
out = PixelSolver(img.shape[:3], cam, DirectionalLights(dirs), mat, cfg, device="cpu").run(img, mask)
e = np.degrees(np.arccos(np.clip(np.sum(out["normals"] * n, -1), -1, 1)))
has, one, both = shad.any(0), shad.sum(0) == 1, shad.sum(0) == 2
print(f"{brdf}: cast-shadow pixels {has.sum()} mean {e[has].mean():.3f}; one shadow {one.sum()}: mean "
      f"{e[one].mean():.3f}, 90th percentile {np.percentile(e[one], 90):.3f}; two {both.sum()}: mean {e[both].mean():.3f}; "
      f"no shadow: mean {e[~has].mean():.3f}")
