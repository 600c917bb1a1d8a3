"""The interreflection compensation's assumed albedo scale against the true one on the self-lit Lambertian cap of
tests/test_interreflection.py (8 directional lights, exact multi-bounce indirect light, least squares on the true
depth, one round), for cap albedos around ``ASSUMED_BRIGHT_ALBEDO``: MAEN (deg) without compensation, with the
assumed scale (and its tau) and with the true scale.  Session 39.

Usage:  python perf/interreflection_cap_rule.py
"""
import os
import sys
import warnings
warnings.simplefilter("ignore")
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import numpy as np

import test_interreflection as T
from gpps.flows.interreflection import reconstruct_subtracting

for kd in (0.8, 0.5, 0.25, 0.0625):
    m, depth, n, lights, cam, direct, images = T._self_lit('cpu', kd)
    solve = T._least_squares_solver(m, lights, depth)
    maen = lambda nn: float(np.degrees(np.arccos(np.clip((nn[m] * n[m]).sum(-1), -1, 1))).mean())  # noqa: E731
    before = maen(solve(images).normals)
    out = {}
    for name, sc in (("assumed", None), ("true", 1.0)):
        rec, info = reconstruct_subtracting(solve, images, m, lights, cam, rounds=1, albedo_scale=sc, device='cpu')
        out[name] = (round(maen(rec.normals), 3), round(info['tau'][0], 3) if info['tau'] else None)
    print(f"kd {kd}: none {before:.3f}", out)
