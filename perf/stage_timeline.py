"""Where a warm ``gpps.reconstruct`` call spends its time, method by method, device-synchronised.

Wraps the pipeline's stage methods (least squares, DGMC's parts, the front, the rounds, the material search,
the final integration, ...) so that each call synchronises the Warp device (and Taichi) on entry and exit and
adds its wall time to the method's total (inclusive: a wrapped method inside another counts in both).  The
synchronisation costs a little and removes overlap between host and device, so the totals add up to a bit more
than an unwrapped call; use it to see which part of the chain to shorten, and ``perf/profile_reconstruct.py``
for the call's real time.

``--reconstructor``: the calls go through one kept ``gpps.Reconstructor`` (issue 20's 30 ms line is measured that
way: no stage built in a warm call); ``--known``: with it, the rendered material given (no estimation).

Usage:  python perf/stage_timeline.py [--synthetic 256] [--images 3] [--device cuda:0] [--repeat 3]
        [--reconstructor [--known]] [--out FILE]
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import gpps  # noqa: E402
from _common import reconstruct_case, reconstructor_case  # noqa: E402
from gpps.flows import ron as ron_mod  # noqa: E402
from gpps.pipeline import dgmc as dgmc_mod  # noqa: E402
from gpps.pipeline import front as front_mod  # noqa: E402
from gpps.pipeline import material as material_mod  # noqa: E402
from gpps.pipeline import ron_rounds as rounds_mod  # noqa: E402
from gpps.pipeline import solver as solver_mod  # noqa: E402
from gpps.pipeline import integration as integ_mod  # noqa: E402
from gpps.pipeline import integration_rounds as irounds_mod  # noqa: E402
from gpps.flows import reconstruction as rec_mod  # noqa: E402

TOTALS: dict = defaultdict(lambda: [0, 0.0])
ACTIVE = [True]
ITERATIONS: list = []  # the integrator's CG iterations, call by call


def _sync():
    import warp as wp
    wp.synchronize()
    try:
        import taichi as ti
        ti.sync()
    except Exception:  # (Taichi not initialised yet)
        pass


def _wrap(owner, name: str, label: str) -> None:
    fn = getattr(owner, name)

    @functools.wraps(fn)
    def inner(*a, **k):
        if not ACTIVE[0]:
            return fn(*a, **k)
        _sync()
        t = time.perf_counter()
        got = None
        try:
            got = fn(*a, **k)
            return got
        finally:
            _sync()
            s = TOTALS[label]
            s[0] += 1
            s[1] += time.perf_counter() - t
            if label == "integrator.pcg" and isinstance(got, tuple):
                ITERATIONS.append(int(got[0]))  # (its CG iterations: a stage's time read beside its work)
    setattr(owner, name, inner)


WRAPS = [
    (rec_mod, "reconstruct", "reconstruct"),
    (rec_mod.Reconstructor, "__call__", "Reconstructor.call"),
    (rec_mod, "_prepare", "prepare"),
    (ron_mod.RON, "run", "RON.run"),
    (ron_mod.RON, "__init__", "RON.__init__"),
    (ron_mod.RON, "_least_squares_and_dgmc", "ls+dgmc"),
    (ron_mod.RON, "_frame", "RON._frame"),
    (ron_mod.RON, "_solve", "RON._solve"),
    (ron_mod.RON, "_fit_material", "material.fit"),
    (ron_mod.RON, "_score", "material.score"),
    (ron_mod.RON, "_final_depth", "final_depth"),
    (ron_mod.RON, "_sample", "material.sample"),
    (ron_mod, "normal_change_deg", "normal_change_deg"),
    (ron_mod, "propagate_front", "front"),
    (front_mod.DeviceFront, "upload", "front.upload"),
    (front_mod.DeviceFront, "step", "front.step"),
    (front_mod.DeviceFront, "fetch", "front.fetch"),
    (dgmc_mod.DeviceDGMC, "__init__", "dgmc.__init__"),
    (dgmc_mod.DeviceDGMC, "upload", "dgmc.upload"),
    (dgmc_mod.DeviceDGMC, "_highlights", "dgmc.highlights"),
    (dgmc_mod.DeviceDGMC, "_regions", "dgmc.regions"),
    (dgmc_mod.DeviceDGMC, "_geodesics", "dgmc.geodesics"),
    (dgmc_mod.DeviceDGMC, "_curvatures", "dgmc.curvatures"),
    (dgmc_mod.DeviceDGMC, "_select", "dgmc.select"),
    (dgmc_mod.DeviceDGMC, "fetch_start", "dgmc.fetch_start"),
    (dgmc_mod.DeviceDGMC, "close", "dgmc.close"),
    (solver_mod.PixelSolver, "upload", "solver.upload"),
    (solver_mod.PixelSolver, "step", "solver.step"),
    (solver_mod.PixelSolver, "fetch", "solver.fetch"),
    (solver_mod, "estimate_noise", "estimate_noise"),
    (material_mod.MaterialScorer, "upload", "scorer.upload"),
    (material_mod.MaterialScorer, "step", "scorer.step"),
    (material_mod.MaterialScorer, "fetch", "scorer.fetch"),
    (rounds_mod.DeviceRounds, "step", "rounds.step"),
    (rounds_mod.DeviceRounds, "fetch", "rounds.fetch"),
    (rounds_mod.DeviceRounds, "upload", "rounds.upload"),
    (rounds_mod.DeviceRounds, "integrate", "rounds.integrate"),
    (rounds_mod.DeviceRounds, "depth_host", "rounds.depth_host"),
    (irounds_mod.DeviceSystem, "_solve_system", "system.solve_system"),
    (integ_mod.Integrator, "_iterate", "integrator.pcg"),
    (integ_mod.Integrator, "set_coarsest", "integrator.set_coarsest"),
    (ron_mod.RON, "_device_rounds", "RON._device_rounds"),
    (ron_mod.RON, "close", "RON.close"),
    (material_mod.MaterialScorer, "set_start", "scorer.set_start"),
    (material_mod.MaterialScorer, "__init__", "scorer.__init__"),
]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--synthetic", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--reconstructor", action="store_true", help="one kept gpps.Reconstructor")
    ap.add_argument("--known", action="store_true", help="with --reconstructor: the material given")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.known and not a.reconstructor:
        ap.error("--known needs --reconstructor")
    call = (reconstructor_case(a.synthetic, a.images, a.device, known=a.known) if a.reconstructor
            else reconstruct_case(a.synthetic, a.images, a.device))
    t = time.perf_counter()
    call()
    cold = time.perf_counter() - t
    warm = []
    for _ in range(a.repeat):  # unwrapped warm calls: the real time
        t = time.perf_counter()
        rec, maen = call()
        warm.append(time.perf_counter() - t)
        maen = maen()
    for owner, name, label in WRAPS:
        _wrap(owner, name, label)
    # (reconstruct is re-exported: wrap the public name too)
    gpps.reconstruct = rec_mod.reconstruct
    TOTALS.clear()
    ITERATIONS.clear()
    runs = max(1, a.repeat)
    for _ in range(runs):
        rec, maen = call()
    maen = maen()
    rows = {k: {"calls": v[0] / runs, "ms": 1e3 * v[1] / runs} for k, v in sorted(TOTALS.items(),
                                                                                  key=lambda kv: -kv[1][1])}
    out = {"device": a.device, "size": a.synthetic, "images": a.images, "reconstructor": a.reconstructor,
           "known": a.known, "cold_s": cold, "warm_s": sorted(warm),
           "maen_deg": maen, "pcg_iterations": list(ITERATIONS), "timings_ms": {k: 1e3 * v for k, v in rec.timings.items()}, "methods": rows}
    text = json.dumps(out, indent=1)
    if a.out:
        Path(a.out).write_text(text)
    print(f"warm {sorted(warm)}  maen {maen:.6f}  pcg iterations {ITERATIONS}")
    for k, v in rows.items():
        print(f"  {k:22s} {v['calls']:7.1f} calls {v['ms']:9.2f} ms")


if __name__ == "__main__":
    main()
