"""What each stage of a warm 256^2 x 3 reconstruction costs in wall time (issue 20's 30 ms line).

Profilers tell where the host spends its time and where the GPU idles, but not what the call would cost without a
stage: a stage's host work may overlap the GPU's, and its syncs may only move a wait elsewhere.  This probe answers
that directly: it times issue 20's synthetic capture (``_common.reconstruct_inputs``: Cook-Torrance bumps,
perspective, 3 directional lights, 16-bit) through one kept ``gpps.Reconstructor`` per variant, each variant the
default pipeline less one stage (or with fewer of its steps), in interleaved blocks of warm, device-synchronised
calls, and prints the median wall time, the stage timings the call reports, and the MAEN.

Variants (``--variants``, comma-separated):

* ``default``: the pipeline as users call it (material unknown);
* ``known``: the material given (Cook-Torrance ks 0.8, roughness 0.2, the rendered one): no material estimation;
* ``no-dgmc``: ``RONConfig(dgmc=False)``: no highlight test, no front;
* ``no-depth``: ``RONConfig(integrate=False)``: no final integration;
* ``rounds3``, ``rounds2``: ``RONConfig(rounds=3 / 2)``;
* ``evals20``: ``RONConfig(material_evals=20)``: half the Nelder-Mead budget;
* ``fused-pcg``: ``RONConfig()`` given: the integrator's PCG one Taichi launch an iteration (``launch="fused"``),
  where a Reconstructor given no config launches it as one persistent task on CUDA
  (``gpps.flows.reconstruction.kept_stages_config``, session 44; before it, the default);
* ``one-thread-neighbours``: the default, but the solver's neighbour pass (pixels with fewer than 3 lit
  observations) as ``underdetermined_kernel``, every start of a pixel in its thread, instead of its
  starts-parallel form (``gpps.kernels.solve_split.split_under_kernels_for``; session 27);
* ``warm-uncapped``: ``RONConfig(material_warm_iters=None)``: the material search's warm candidate solves run to
  the solver's ``max_iters`` (50) instead of the default 12 (session 28);
* ``host-loop``: ``RONConfig(material_loop="host")``: the material search's Nelder-Mead steps decided on the host
  (the same trajectory) instead of in CUDA graphs, so that ``--kernel-times`` (CUDA events a launch, which do not
  see a graph's kernels) counts all of the GPU's work: the call's GPU floor (session 31);
* ``no-held-dark``: ``SolverConfig(held_dark_refit=False)`` in RON's solver: the neighbour pass without the
  attached / cast shadow refit, the pipeline before session 35.

Only the time and the MAEN are compared; a variant with a worse MAEN is not a proposal, it says what the stage is
worth.

Usage:  python perf/reconstruct_ablation.py [--size 256] [--images 3] [--device cuda:0] [--repeat 5] [--blocks 2]
        [--variants default,known,...] [--out FILE]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import gpps  # noqa: E402
from _common import device_label, reconstruct_inputs  # noqa: E402

VARIANTS = ("default", "known", "no-dgmc", "no-depth", "rounds3", "rounds2", "evals20", "fused-pcg",
            "one-thread-neighbours", "warm-uncapped", "host-loop", "no-held-dark")


def _sync():
    import warp as wp
    wp.synchronize()


def variant_kwargs(name: str) -> dict:
    """The Reconstructor's ``material`` and ``config`` of a variant."""
    from gpps.flows.ron import RONConfig

    base = RONConfig()
    if name in ("default", "one-thread-neighbours"):
        return {"material": "cook-torrance"}
    if name == "known":
        return {"material": gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)}
    if name == "fused-pcg":
        return {"material": "cook-torrance", "config": base}
    changes = {"no-dgmc": {"dgmc": False}, "no-depth": {"integrate": False}, "rounds3": {"rounds": 3},
               "rounds2": {"rounds": 2}, "evals20": {"material_evals": 20},
               "warm-uncapped": {"material_warm_iters": None},
               # the material search's steps driven from the host: the same trajectory, but every scorer launch a
               # plain launch (no CUDA graph), so --kernel-times sees all of the GPU's work
               "host-loop": {"material_loop": "host"},
               # the neighbour pass without its attached / cast shadow refit (session 35)
               "no-held-dark": {"solver": replace(base.solver, held_dark_refit=False)}}
    if name not in changes:
        raise ValueError(f"variant: expected one of {VARIANTS}, got {name!r}")
    return {"material": "cook-torrance", "config": replace(base, **changes[name])}


@contextlib.contextmanager
def variant_patch(name: str):
    """What a variant changes besides the Reconstructor's arguments, for the duration of its block."""
    if name != "one-thread-neighbours":
        yield
        return
    from gpps.pipeline.solver import PixelSolver

    orig = PixelSolver._launch_underdetermined

    def one_thread(self, solve_mask, config=None, *, split):
        return orig(self, solve_mask, config, split=False)
    PixelSolver._launch_underdetermined = one_thread
    try:
        yield
    finally:
        PixelSolver._launch_underdetermined = orig


def _kernel_times(rc, img) -> dict:
    """One call of ``rc`` under ``wp.timing_begin`` (CUDA events a launch): ``{kernel: {"ms", "launches"}}``,
    the longest first."""
    import warp as wp

    _sync()
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    rc(img)
    _sync()
    agg: dict = {}
    for r in wp.timing_end():
        t = agg.setdefault(r.name, [0.0, 0])
        t[0] += r.elapsed
        t[1] += 1
    return {k: {"ms": round(v[0], 4), "launches": v[1]} for k, v in sorted(agg.items(), key=lambda kv: -kv[1][0])}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--blocks", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--kernel-times", action="store_true",
                    help="after the blocks, one more call a variant under wp.timing (CUDA events): the Warp kernels' "
                         "device time by name (launches replayed from a CUDA graph and Taichi's are not in it)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    names = [v.strip() for v in a.variants.split(",") if v.strip()]
    for v in names:
        variant_kwargs(v)  # (a bad name fails before any work)
    c = reconstruct_inputs(a.size, a.images, a.device)
    img, mask, truth = c["images"], c["mask"], c["normals"]
    rows = {v: {"ms": [], "maen": [], "timings_ms": [], "estimated": None} for v in names}
    for blk in range(a.blocks):
        for v in names:
            with variant_patch(v), gpps.Reconstructor(mask, c["lights"], camera=c["camera"], device=a.device,
                                                      **variant_kwargs(v)) as rc:
                rc(img)  # (builds the stages, loads the kernels: not timed)
                rc(img)
                for _ in range(a.repeat):
                    _sync()
                    t = time.perf_counter()
                    rec = rc(img)
                    _sync()
                    rows[v]["ms"].append(1e3 * (time.perf_counter() - t))
                    rows[v]["maen"].append(float(gpps.normal_errors(rec.normals, truth, mask)["mean"]))
                    rows[v]["timings_ms"].append({k: 1e3 * s for k, s in rec.timings.items()})
                    rows[v]["estimated"] = {k: float(x) for k, x in rec.estimated.items()}
                if a.kernel_times and blk == a.blocks - 1:
                    rows[v]["kernels_ms"] = _kernel_times(rc, img)
    out = {"device": a.device or "auto", "device_name": device_label(a.device or "cpu"), "size": a.size,
           "images": a.images, "repeat": a.repeat, "blocks": a.blocks, "variants": {}}
    base = None
    for v in names:
        r = rows[v]
        med = statistics.median(r["ms"])
        stages = {k: statistics.median(t[k] for t in r["timings_ms"]) for k in r["timings_ms"][0]}
        out["variants"][v] = {"kernels_ms": r.get("kernels_ms"), "median_ms": med, "min_ms": min(r["ms"]), "max_ms": max(r["ms"]),
                              "maen_deg": statistics.median(r["maen"]), "estimated": r["estimated"], "stages_ms": stages,
                              "ms": r["ms"]}
        if v == "default":
            base = med
    print(f"{'variant':22s} {'median ms':>10s} {'saved':>7s} {'MAEN':>8s}  stages (ms)")
    for v, r in out["variants"].items():
        saved = "" if base is None or v == "default" else f"{base - r['median_ms']:7.1f}"
        st = " ".join(f"{k}={x:.1f}" for k, x in r["stages_ms"].items())
        est = " ".join(f"{k}={x:.4g}" for k, x in (r["estimated"] or {}).items())
        print(f"{v:22s} {r['median_ms']:10.1f} {saved:>7s} {r['maen_deg']:8.4f}  {st}  {est}")
    for v, r in out["variants"].items():
        if r["kernels_ms"]:
            top = list(r["kernels_ms"].items())[:6]
            print(f"{v:22s} Warp kernels {sum(x['ms'] for x in r['kernels_ms'].values()):.1f} ms: "
                  + ", ".join(f"{k.split('__')[0]} {x['ms']:.2f} ({x['launches']})" for k, x in top))
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2) + "\n")
    return out


if __name__ == "__main__":
    main()
