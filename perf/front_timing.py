"""DGMC's front propagation (``propagate_front``) timed warm, and its host<->device copies counted per ring.

A rendered 256^2 perspective Cook-Torrance bumps scene (the pipeline's synthetic case) with 3 and 12 directional
lights: least squares, DGMC's highlights and curvatures (:func:`gpps.pipeline.dgmc.dgmc_start_device`), the
multi-start solution of the mask (the front's sources), then the front as RON calls it (``images=None``: the
solver holds the frame; ``keep_better=True``).  ``--impl host`` is the old host loop over rings
(tests/front_reference.py), ``device`` the device-resident front (:func:`gpps.pipeline.front.propagate_front`);
with both, their results are compared (they must be equal).

``--reconstruct``: also the whole ``gpps.reconstruct`` (material unknown) on the same scenes, warm, with each
implementation in RON (the host loop patched into :mod:`gpps.flows.ron` for ``host``), with its DGMC stage time.

Copies: calls of ``warp.copy`` (``array.assign`` goes through it), ``array.numpy`` and ``warp.array(data=...)``
counted between the progress reports of consecutive rings (per ring), before the first and after the last.

Usage:  python perf/front_timing.py [--size 256] [--lights 3 12] [--impl host device] [--device cpu] [--reconstruct]
        [--out NAME]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from _common import timeit, write_results  # noqa: E402
from cases import copy_counter  # noqa: E402
from front_reference import propagate_front_host  # noqa: E402

import gpps  # noqa: E402
import gpps.flows.ron as ron_module  # noqa: E402
from gpps._runtime import resolve_device, warp  # noqa: E402
from gpps.pipeline.dgmc import dgmc_start_device  # noqa: E402
from gpps.pipeline.front import propagate_front  # noqa: E402
from gpps.pipeline.solver import PixelSolver, SolverConfig  # noqa: E402

IMPLS = {"host": propagate_front_host, "device": propagate_front}


def scene(size: int, n_lights: int, device: str):
    """perf/profile_reconstruct.py's synthetic case: images divided by the intensities, unit lights, scene, material."""
    sc = gpps.make_scene("bumps", size, "perspective")
    L = gpps.default_lights("directional", n_lights, layout="ring" if n_lights <= 4 else "spiral")
    mat = gpps.Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5)
    img = gpps.render(sc, mat, L, bits=16, device=device) / L.intensities[:, None, None, :]
    return img, gpps.DirectionalLights(L.directions), sc, mat


def case(size: int, n_lights: int, device: str):
    """The scene's frame on a PixelSolver with its multi-start solution, the highlights and the curvatures."""
    img, lu, sc, mat = scene(size, n_lights, device)
    solver = PixelSolver(img.shape[:3], sc.camera, lu, mat, SolverConfig(solver="none"), device=device)
    ls = solver.run(img, sc.mask)
    nrm = ls["normals"].astype(np.float64)
    ok = sc.mask & (np.abs(np.linalg.norm(nrm, axis=-1) - 1.0) < 1e-3)
    nrm[~ok] = (0.0, 0.0, 1.0)
    dg = dgmc_start_device(img, sc.mask, nrm, lights=lu, device=device)
    solver.set_config(SolverConfig())
    solver.set_mask(sc.mask)
    solver.step()
    sol = solver.fetch(("normals", "albedo", "residual", "iterations", "flags"))
    return solver, sc.mask, dg, sol


def measure(impl: str, solver, mask, dg, sol, device: str, repeat: int) -> tuple[dict, object]:
    fn = IMPLS[impl]
    wp = warp()

    def call():
        return fn(solver, None, mask, dg.highlight, sol, gaussian=dg.gaussian, mean=dg.mean, keep_better=True)

    t = timeit(call, lambda: wp.synchronize_device(device), warmup=1, repeat=repeat)
    marks = []
    with copy_counter() as n:
        t0 = time.perf_counter()
        fr = fn(solver, None, mask, dg.highlight, sol, gaussian=dg.gaussian, mean=dg.mean, keep_better=True,
                progress=lambda k, _t, _m: marks.append(n[0]))
        end = n[0]
        dt = time.perf_counter() - t0
    per_ring = np.diff(marks).tolist()
    return {"impl": impl, "median_s": t["median_s"], "iqr_s": t["iqr_s"], "runs": t["runs"], "counted_run_s": dt,
            "n_rings": fr.n_rings, "ring_pixels": int((fr.ring > 0).sum()),
            "copies_before_first_ring": marks[0] if marks else end, "copies_per_ring_max": max(per_ring, default=0),
            "copies_per_ring_total": int(sum(per_ring)), "copies_after_last_ring": end - (marks[-1] if marks else 0),
            "mean_iterations": float(fr.iterations[fr.ring > 0].mean()) if fr.n_rings else 0.0}, fr


def reconstruct(size: int, n_lights: int, device: str, impls, repeat: int) -> list[dict]:
    """Warm ``gpps.reconstruct`` (material unknown) with each front implementation in RON."""
    img, lu, sc, _ = scene(size, n_lights, device)
    rows = []
    for impl in impls:
        ron_module.propagate_front = IMPLS[impl]
        try:
            def call():
                return gpps.reconstruct(img, sc.mask, lu, camera=sc.camera, material="cook-torrance", device=device)

            call()
            ts, dg, maen = [], [], None
            for _ in range(repeat):
                t0 = time.perf_counter()
                rec = call()
                ts.append(time.perf_counter() - t0)
                dg.append(rec.timings["dgmc"])
                maen = gpps.normal_errors(rec.normals, sc.normals, sc.mask)["mean"]
        finally:
            ron_module.propagate_front = propagate_front
        rows.append({"reconstruct": impl, "size": size, "lights": n_lights, "median_s": float(np.median(ts)),
                     "dgmc_median_s": float(np.median(dg)), "runs": repeat, "maen_deg": maen})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--lights", type=int, nargs="+", default=[3, 12])
    ap.add_argument("--impl", nargs="+", default=["host", "device"], choices=sorted(IMPLS))
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--reconstruct", action="store_true")
    ap.add_argument("--out", default=None, help="results name under perf/results (default: none written)")
    a = ap.parse_args(argv)
    device = resolve_device(a.device)
    rows = []
    for n in a.lights:
        solver, mask, dg, sol = case(a.size, n, device)
        results = {}
        for impl in a.impl:
            row, results[impl] = measure(impl, solver, mask, dg, sol, device, a.repeat)
            row.update(size=a.size, lights=n, highlight_pixels=int(dg.highlight.sum()))
            rows.append(row)
            print(json.dumps(row), flush=True)
        if len(results) == 2:
            h, d = results["host"], results["device"]
            same = all(np.array_equal(getattr(h, k), getattr(d, k)) for k in
                       ("normals", "albedo", "residual", "flags", "iterations", "ring", "source", "won"))
            print(json.dumps({"lights": n, "identical": bool(same and h.n_rings == d.n_rings)}), flush=True)
            rows[-1]["identical_to_host"] = bool(same and h.n_rings == d.n_rings)
        if a.reconstruct:
            rows += reconstruct(a.size, n, device, a.impl, max(3, a.repeat // 2))
    if a.out:
        print(write_results(a.out, device, {"rows": rows, "command": " ".join(sys.argv)}))


if __name__ == "__main__":
    main()
