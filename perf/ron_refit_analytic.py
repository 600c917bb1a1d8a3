"""The cast-shadow refit (``SolverConfig.shadow_relative``) on the analytic cast-shadow scenes of
perf/ron_shadows.py (bumps, hemisphere, box on a plane; a sphere without cast shadows): RON with the many-image
solver settings (Cauchy IRLS, 2 % shadow threshold, 4 starts) with and without the refit, 12 and 24 lights,
directional and point, 64 px.  Shadows there are exactly black (the exact visibility times a shadow-free render,
noise 0.002): no inter-reflected light in them, unlike the Mitsuba captures.  MAEN over the mask and over the
pixels with a cast-shadowed observation; JSON rows to perf/results/s17/ron_refit_analytic_cpu.json.

Usage: ``python perf/ron_refit_analytic.py [--device cpu]``
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
sys.path.insert(0, str(ROOT / "tests"))

import ron_shadows as rs  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(ROOT / "perf" / "results" / "s17" / "ron_refit_analytic_cpu.json"))
    a = ap.parse_args(argv)
    from gpps.flows.ron import RON, RONConfig
    from gpps.lights import PointLights
    from gpps.pipeline.solver import SolverConfig

    warnings.simplefilter("ignore")
    rows = []
    for n in (12, 24):
        for scene in ("bumps", "hemisphere", "box", "sphere"):
            for kind in ("directional", "point"):
                case = rs.make_case(scene, kind, n, 64)
                case.setdefault("facing", rs._facing(case))
                out = {}
                for rel in (0.0, 0.1):
                    solver = SolverConfig(robust="cauchy", shadow_threshold=0.02, starts=4, shadow_relative=rel)
                    ron = RON((n,) + case["mask"].shape, case["camera"], case["lights"], case["material"],
                              case["mask"], RONConfig(solver=solver), device=a.device)
                    try:
                        ref = case["reference_depth"] if isinstance(case["lights"], PointLights) else None
                        m = rs.measure(case, ron.run(case["images"], reference_depth=ref))
                    finally:
                        ron.close()
                    out[rel] = {"maen": m["maen"], "maen_shadowed": m["maen_shadowed"]}
                rows.append(dict(scene=scene, kind=kind, lights=n, robust=out[0.0], refit=out[0.1]))
                print(f"{scene:11s} {kind:11s} {n:3d}  robust: MAEN {out[0.0]['maen']:.3f}   "
                      f"+refit: MAEN {out[0.1]['maen']:.3f}", flush=True)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    with open(a.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
