"""The solver's neighbour pass alone (pixels with fewer than 3 lit observations), in its forms, on issue 20's capture.

``PixelSolver``'s second pass (``SolverConfig.neighbour_radius``) holds an under-determined pixel's albedo at its
well-determined neighbours' and solves its normal with every start.  It ran as ``underdetermined_kernel`` (a
pixel's starts one after another in one thread: about 5 ms a launch at 256^2 x 3 on an H200, session 27) and now
runs starts-parallel with the split solve (``gpps.kernels.solve_split.split_under_kernels_for``: a prelude with the
neighbours' statistics, one thread a start, the pick and store).  This probe times the pass alone after one whole
solve of the capture (``_common.reconstruct_inputs``: perspective Cook-Torrance bumps, 3 directional lights,
16-bit, its clipped highlights left out as ``gpps.reconstruct`` leaves them, the rendered material given), each
form's launches device-synchronised (the solve's outputs restored before each, untimed), in interleaved blocks:

* ``one-thread``: ``underdetermined_kernel``;
* ``split``: the starts-parallel form as the library builds it (its register cap,
  ``gpps.names.SPLIT_UNDER_MAX_REGISTERS``, the split solve's value);
* ``split-nocap``: the same kernels in a module without the cap (``gpps.names`` keeps the compiler's choice for
  latency-bound launches; the pass's launches have few working threads: is it one?).

With ``--kernel-times`` (CUDA) it also reports each kernel's device time (``wp.timing_begin``).  Every form must
give the same normals (bitwise on the CPU, to rounding on CUDA): the largest angle between a form's and the
one-thread form's is printed.

Usage:  python perf/neighbour_pass.py [--size 256] [--device cuda:0] [--repeat 20] [--blocks 3] [--kernel-times]
        [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
import types
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "perf"))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

import gpps  # noqa: E402
from _common import device_label, reconstruct_inputs  # noqa: E402

FORMS = ("one-thread", "split", "split-nocap")


def _nocap_kernels(method, brdf, robust):
    """``split_under_kernels_for``'s kernels in a module of this probe's own, without the register cap."""
    import warp as wp

    from gpps.kernels import solve as sk
    from gpps.kernels.solve_split import split_under_kernels_for

    name = sk.module_name(method, brdf, robust) + "_split_under_nocap"
    sfx = "__" + name.rsplit(".", 1)[1]
    funcs = sk.solver_funcs(*sk.specialisation_key(method, brdf, robust), wp.get_module(name), sfx)
    return split_under_kernels_for(funcs.one_start, funcs.finish_pixel, wp.get_module(name), sfx)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--kernel-times", action="store_true")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    import warp as wp

    from gpps.host.clipping import clipped_observations
    from gpps.names import FLAG_ALBEDO_FROM_NEIGHBOURS, FLAG_FEW_OBSERVATIONS
    from gpps.pipeline.solver import PixelSolver, SolverConfig

    dev = a.device or ("cuda:0" if wp.get_cuda_device_count() else "cpu")
    c = reconstruct_inputs(a.size, 3, dev)
    mat = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    cfg = SolverConfig()
    img = np.asarray(c["images"], np.float32)
    s = PixelSolver(img.shape[:3], c["camera"], c["lights"], mat, cfg, device=dev)
    keep, _ = clipped_observations(img, c["mask"])  # (the clipped highlights out, as gpps.reconstruct leaves them)
    first = s.run(img, c["mask"], valid=keep)
    few = ((first["flags"] & FLAG_FEW_OBSERVATIONS) != 0) & c["mask"]
    held = (first["flags"] & FLAG_ALBEDO_FROM_NEIGHBOURS) != 0
    robust = cfg.robust if cfg.irls_rounds > 0 else "none"
    nocap = _nocap_kernels(cfg.solver, mat.brdf, robust)
    real_sk = s._sk  # noqa: SLF001

    state = ("weights", "normals", "albedo", "residual", "iterations", "flags")
    saved = {k: wp.clone(getattr(s, k)) for k in state}  # (the whole solve's outputs: each run starts there)

    def launch(form):
        for k in state:
            wp.copy(getattr(s, k), saved[k])
        wp.synchronize_device(dev)
        t = time.perf_counter()
        if form == "split-nocap":
            shim = types.SimpleNamespace(**{k: getattr(real_sk, k) for k in dir(real_sk) if not k.startswith("__")})
            shim.get_split_under_kernels = lambda *k: nocap
            s._sk = shim  # noqa: SLF001
        s._cmds.pop(("underdetermined", True), None)  # noqa: SLF001  (re-recorded with this form's kernels)
        try:
            s._launch_underdetermined(s.mask, split=form != "one-thread")  # noqa: SLF001
        finally:
            s._sk = real_sk  # noqa: SLF001
        wp.synchronize_device(dev)
        return 1e3 * (time.perf_counter() - t)

    ms = {f: [] for f in FORMS}
    normals = {}
    for f in FORMS:  # (compiles, and each form's answer)
        launch(f)
        normals[f] = s.fetch(("normals",))["normals"]
    for _ in range(a.blocks):
        for f in FORMS:
            for _ in range(a.repeat):
                ms[f].append(launch(f))
    kernels = {}
    if a.kernel_times and dev.startswith("cuda"):
        for f in FORMS:
            wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
            for _ in range(a.repeat):
                launch(f)
            agg: dict = {}
            for r in wp.timing_end():
                agg[r.name] = agg.get(r.name, 0.0) + r.elapsed / a.repeat
            kernels[f] = {k: round(v, 4) for k, v in sorted(agg.items(), key=lambda kv: -kv[1])}

    def angle(x, y):
        """The largest angle (deg) between two forms' normals at the held pixels, in float64 (a float32 dot of
        a unit vector with itself reads 0.02 deg)."""
        x, y = x[held].astype(np.float64), y[held].astype(np.float64)
        if not x.size:
            return 0.0
        x /= np.linalg.norm(x, axis=-1, keepdims=True)
        y /= np.linalg.norm(y, axis=-1, keepdims=True)
        return float(np.degrees(np.arctan2(np.linalg.norm(np.cross(x, y), axis=-1), np.sum(x * y, -1))).max())

    out = {"device": dev, "device_name": device_label(dev), "size": a.size, "mask_pixels": int(c["mask"].sum()),
           "under_determined": int(few.sum()), "held": int(held.sum()), "repeat": a.repeat, "blocks": a.blocks,
           "forms": {f: {"median_ms": statistics.median(ms[f]), "min_ms": min(ms[f]), "max_ms": max(ms[f]),
                         "max_angle_to_one_thread_deg": angle(normals[f], normals["one-thread"]),
                         "bitwise_equal_to_one_thread": bool(np.array_equal(normals[f], normals["one-thread"])),
                         "kernels_ms": kernels.get(f)} for f in FORMS}}
    print(f"{a.size}^2 x 3 on {out['device_name']}: {out['under_determined']} of {out['mask_pixels']} pixels "
          f"under-determined, {out['held']} held")
    for f, r in out["forms"].items():
        kt = "" if not r["kernels_ms"] else "  kernels: " + ", ".join(
            f"{k.split('__')[0]} {v:.3f}" for k, v in r["kernels_ms"].items())
        print(f"  {f:12s} median {r['median_ms']:8.3f} ms (min {r['min_ms']:.3f})  max angle to one-thread "
              f"{r['max_angle_to_one_thread_deg']:.2e} deg (bitwise {r['bitwise_equal_to_one_thread']}){kt}")
    if a.out:
        Path(a.out).parent.mkdir(parents=True, exist_ok=True)
        Path(a.out).write_text(json.dumps(out, indent=2) + "\n")
    s.close()
    return out


if __name__ == "__main__":
    main()
