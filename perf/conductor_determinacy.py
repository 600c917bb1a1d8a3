"""How many lights determine a metal's normals: gpps's own conductor renders (GGX alpha 0.3 and 0.15; bumps and
spheres; directional and point lights; 48^2, 16-bit, noise 0 and 1 %), solved with the material known, 3-6 lights
(session 36: gpps.names.CONDUCTOR_MIN_IMAGES).  Prints the MAEN and median (deg) per case.

Usage:  python perf/conductor_determinacy.py
"""
import os
import sys
import warnings

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), '..')
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, 'tests'))
warnings.simplefilter('ignore')

import gpps  # noqa: E402,F401
from gpps.flows.photometric import solve_normals
from gpps.host.metrics import normal_errors
from gpps.material import Material
from test_plastic import _case  # noqa: E402

for rough in (0.3, 0.15):
    TRUE = Material("conductor", roughness=rough)
    for scene, kind in (("bumps", "directional"), ("sphere", "point"), ("sphere", "directional")):
        for n in (3, 4, 5, 6):
            row = []
            for noise in (0.0, 0.01):
                img, L, sc, sat = _case(scene, n, kind, 48, noise, TRUE)
                depth = sc.depth if kind == "point" else None
                r = solve_normals(img, sc.mask, L, camera=sc.camera, material=TRUE, saturation=sat, depth=depth, device='cpu')
                e = normal_errors(r.normals, sc.normals, sc.mask)
                row.append(f"noise {noise}: mean {e['mean']:.2f} med {e['median']:.2f}")
            print(rough, scene, kind, n, ' | '.join(row), flush=True)
