"""MAEN of calibrated per-pixel PS on rendered scenes: every BRDF x camera x light kind.

Scenes: gpps.host.scenes.make_scene sphere and bumps (uniform albedo), 3 lights from
gpps.flows.synthetic.default_lights, 16-bit quantised (render(..., bits=16)), noise-free
and with 1% Gaussian noise.  Point lights use the true depth as the solver's
depth estimate.  Images are divided by the light intensities (as gpps.io.read_dataset
does) and solved with unit-intensity lights.

Noisy cases can be solved with the smoothness term (``--smoothness``, SolverConfig.smoothness).
"determined px": MAEN over the pixels with at least 3 lit observations (the
others, in attached shadow of a light, are under-determined from 3 images).
The solver estimates each image's noise level itself (SolverConfig.noise_level
None: Immerkaer's estimate); nothing here passes it the true 1 %.

Usage:  python perf/synthetic_calibrated.py [--size 256] [--device cpu] [--solver lm] [--smoothness 1] [--out perf/results/synthetic_calibrated_cpu.json]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # tests/cases.py: the evaluation cases shared with the tests
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))


from cases import BRDFS, MIN_LIGHTS, make_case, run_case  # noqa: E402,F401


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--solver", default="lm")
    ap.add_argument("--noise", type=float, nargs="*", default=[0.0, 0.01])
    ap.add_argument("--scenes", nargs="*", default=["sphere", "bumps"])
    ap.add_argument("--smoothness", type=float, default=0.0, help="SolverConfig.smoothness for the noisy cases (0: pixelwise)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    rows = []
    for noise in a.noise:
        for scene in a.scenes:
            for cam in ["orthographic", "perspective"]:
                for lk in ["directional", "point"]:
                    for brdf in BRDFS:
                        opts = {"smoothness": a.smoothness} if (noise > 0 and a.smoothness > 0) else {}
                        r = run_case(scene, a.size, cam, lk, brdf, noise=noise, solver=a.solver, device=a.device,
                                     n_lights=MIN_LIGHTS[brdf], **opts)
                        rows.append(r)
                        print(
                            f"{scene:7s} {cam:12s} {lk:11s} {brdf:18s} noise={noise:.2f}  LS {r['maen_least_squares']:6.2f}  "
                            f"{a.solver} {r['maen']:6.3f} (med {r['median']:.3f}, <5deg {100 * r['under_5deg']:.1f}%, "
                            f"determined px {r['maen_determined']:.3f} / {100 * (1 - r['underdetermined_fraction']):.0f}%)  {r['seconds']:.2f}s",
                            flush=True,
                        )
    out = Path(a.out) if a.out else ROOT / "perf" / "results" / f"synthetic_calibrated_{a.device.split(':')[0]}.json"
    from gpps.io import save_json

    save_json(out, {"size": a.size, "device": a.device, "solver": a.solver, "smoothness_noisy": a.smoothness, "rows": rows})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
