"""The final depth's CG residuals, check by check, in a warm 256^2 x 3 Reconstructor call (issue 20's capture,
``_common.reconstruct_inputs``) with the material known, estimated, and known with a float64 integrator.

Session 32 found the known-material call's CG taking 30 iterations on CUDA against 14 on the CPU: at the float32
floor its residual rose by orders of magnitude before coming down again (``gpps.pipeline.integration._FLOOR_RR``).
Prints each call's time, integration stage, iterations, residual and checks, and the float32 depth's difference
from the float64 one.

Usage:  python perf/probe_pcg_floor.py [cpu | cuda:0]
"""
import sys
import time
import warnings
from pathlib import Path
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
warnings.simplefilter("ignore")
import numpy as np
import gpps
from gpps.flows.ron import RONConfig
from gpps.pipeline import integration as integ_mod
from gpps.pipeline.integration import IntegratorConfig
from _common import reconstruct_inputs

dev = sys.argv[1] if len(sys.argv) > 1 else "cpu"
c = reconstruct_inputs(256, 3, "cpu" if dev == "cpu" else dev)
orig = integ_mod.Integrator._iterate
LOG = []
def patched(self, progress, tol):
    seq = []
    got = orig(self, lambda i, cap, msg: seq.append((i, float(msg.split()[-1]))), tol)
    LOG.append((got, seq))
    return got
integ_mod.Integrator._iterate = patched
KNOWN = c["material"]
for name, mat, cfg in (("known", KNOWN, None), ("default", "cook-torrance", None),
                       ("known-f64", KNOWN, RONConfig(integrator=IntegratorConfig(tol=1e-5, weighting="normal", dtype="float64")))):
    with gpps.Reconstructor(c["mask"], c["lights"], camera=c["camera"], material=mat, device=dev, config=cfg) as rc:
        rc(c["images"]); rc(c["images"]); LOG.clear()
        t = time.perf_counter(); rec = rc(c["images"]); dt = time.perf_counter() - t
        (its, res), seq = LOG[-1]
        print(f"{name}: {1e3 * dt:.1f} ms, integration {1e3 * rec.timings['integration']:.1f} ms, CG {its} iterations, "
              f"residual {res:.3g}; checks {[(i, f'{r:.2e}') for i, r in seq]}")
        print(f"   depth range {float(np.ptp(rec.depth[rec.depth_mask])):.4g}")
    if name == "known":
        known_depth = rec.depth.copy()
    if name == "known-f64":
        m = rec.depth_mask
        d = np.abs(rec.depth[m] - known_depth[m])
        print(f"   known float32 vs float64 depth: max {d.max():.3g}, mean {d.mean():.3g} (range {np.ptp(known_depth[m]):.3g})")
