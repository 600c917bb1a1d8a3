"""gpps.reconstruct on rendered scenes with highlights, material withheld (issue 5's Done-when).

Cases: sphere (and bumps with --scenes), 256^2, 3 lights, 16-bit, Blinn-Phong
(ks 0.7, shininess 60) and Cook-Torrance (ks 0.8, m 0.2, f0 0.5), orthographic
and perspective, directional and point lights.  The pipeline gets the model
name only: ks and the lobe width are estimated (f0 stays at its default 0.5).
Point lights start from a flat depth at the object's mean distance.  Saturated
observations (16-bit clipping) are passed as ``saturation``.

Reported per case: MAEN and median (deg), depth error after offset
(orthographic) or scale (perspective) alignment as a fraction of the depth
range, the same for the integrator fed with the exact normals (its
discretisation floor), the estimated parameters, energy per round, rounds, seconds.

DGMC (seed 4.1.9), per directional case with the material known: the round-1
normal solve on the DGMC highlight pixels four ways: (a) the multi-start solver
(10 starts from least squares), (b) one start from the least-squares normal,
(c) one start from the seed's DGMC normal (sources on the region boundary),
(d) one start from the DGMC front (the pipeline's default,
``gpps.pipeline.front.propagate_front``: sources on the solved front, ring by
ring; the non-highlight sources solved as in (a)).  Cost evaluations per pixel
(PixelSolver ``iterations``, all starts summed) and MAEN on those pixels.

Usage:  python perf/reconstruct_synthetic.py [--size 256] [--device cpu] [--scenes sphere bumps]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np  # noqa: E402

import gpps  # noqa: E402
from gpps.host.metrics import depth_error  # noqa: E402
from gpps.flows.integrate import integrate_normals  # noqa: E402
from gpps.lights import DirectionalLights, PointLights  # noqa: E402
from gpps.material import Material  # noqa: E402
from gpps.host.metrics import angular_error  # noqa: E402
from gpps.flows.photometric import solve_normals  # noqa: E402
from gpps.host.dgmc import dgmc_start  # noqa: E402
from gpps.pipeline.front import propagate_front  # noqa: E402
from gpps.pipeline.solver import PixelSolver, SolverConfig  # noqa: E402
from gpps.host.scenes import make_scene  # noqa: E402
from gpps.flows.synthetic import default_lights, render  # noqa: E402

TRUE = {
    "blinn-phong": Material("blinn-phong", ks=0.7, shininess=60.0),
    "cook-torrance": Material("cook-torrance", ks=0.8, roughness=0.2, f0=0.5),
}


def case(scene, size, camera, kind, brdf, device):
    sc = make_scene(scene, size, camera)
    L = default_lights(kind, 3)
    raw = render(sc, TRUE[brdf], L, bits=16, device=device)
    img = raw / np.asarray(L.intensities, np.float32)[:, None, None, :]
    Lu = DirectionalLights(L.directions) if kind == "directional" else PointLights(L.positions)
    return img, Lu, sc, float(0.999 / np.min(L.intensities))


def pipeline_row(scene, size, camera, kind, brdf, device):
    img, L, sc, sat = case(scene, size, camera, kind, brdf, device)
    ref = float(sc.depth[sc.mask].mean())
    t = time.perf_counter()
    rec = gpps.reconstruct(img, sc.mask, L, camera=sc.camera, material=brdf, reference_depth=ref, saturation=sat,
                           device=device)
    dt = time.perf_counter() - t
    e = angular_error(rec.normals, sc.normals, sc.mask)[sc.mask]
    floor = integrate_normals(sc.normals, sc.mask, camera=sc.camera, reference_depth=ref, device="cpu" if device == "cpu" else device)
    return {
        "scene": scene, "size": size, "camera": camera, "lights": kind, "brdf": brdf,
        "true": {k: getattr(TRUE[brdf], k) for k in rec.estimated}, "estimated": rec.estimated,
        "maen": float(e.mean()), "median": float(np.median(e)), "under_1deg": float(np.mean(e < 1.0)),
        "depth_error": depth_error(rec.depth, rec.depth_mask, sc),
        "depth_error_exact_normals": depth_error(floor.depth, floor.mask, sc),
        "energy": rec.energy, "rounds": rec.rounds, "converged": rec.converged,
        "highlight_pixels": int(rec.highlight.sum()), "seconds": dt, "timings": rec.timings,
    }


def dgmc_row(scene, size, camera, brdf, device):
    img, L, sc, sat = case(scene, size, camera, "directional", brdf, device)
    mat, m = TRUE[brdf], sc.mask
    base = SolverConfig(saturation=sat, neighbour_radius=0)
    ls = solve_normals(img, m, L, camera=sc.camera, solver="none", device=device).normals
    dg = dgmc_start(img, m, np.where(m[..., None], ls, (0.0, 0.0, 1.0)), lights=L)
    hl = dg.highlight
    ps = PixelSolver(img.shape[:3], sc.camera, L, mat, base, device=device)
    row = {"scene": scene, "size": size, "camera": camera, "brdf": brdf, "highlight_pixels": int(hl.sum())}
    variants = {
        "multistart_10": (base, None),
        "one_start_least_squares": (replace(base, warm_start=True, starts=1), ls),
        "one_start_dgmc": (replace(base, warm_start=True, starts=1), dg.normals),
    }
    for name, (cfg, init) in variants.items():
        ps.set_config(cfg)
        out = ps.run(img, hl, init_normals=init)
        e = angular_error(out["normals"], sc.normals, hl)[hl]
        row[name] = {"evaluations_per_pixel": float(out["iterations"][hl].mean()), "maen": float(e.mean()),
                     "median": float(np.median(e)), "over_5deg": float(np.mean(e > 5.0))}
    # the pipeline's default: DGMC on the solved front, sources = the multi-start solution of the mask
    ps.set_config(base)
    src = ps.run(img, m)
    ps.set_config(replace(base, warm_start=True, starts=1))
    fr = propagate_front(ps, img, m, hl, src, gaussian=dg.gaussian, mean=dg.mean, keep_better=False)
    e = angular_error(fr.normals, sc.normals, hl)[hl]
    row["one_start_dgmc_front"] = {"evaluations_per_pixel": float(fr.iterations[hl].mean()), "maen": float(e.mean()),
                                   "median": float(np.median(e)), "over_5deg": float(np.mean(e > 5.0)),
                                   "rings": fr.n_rings}
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scenes", nargs="+", default=["sphere"])
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    out = Path(a.out or ROOT / "perf" / "results" / f"reconstruct_synthetic_{a.device.replace(':', '')}.json")
    rows, dg = [], []
    for scene in a.scenes:
        for brdf in TRUE:
            for camera in ("orthographic", "perspective"):
                dg.append(dgmc_row(scene, a.size, camera, brdf, a.device))
                for kind in ("directional", "point"):
                    rows.append(pipeline_row(scene, a.size, camera, kind, brdf, a.device))
                    r = rows[-1]
                    print(f"{scene:7s} {brdf:14s} {camera:12s} {kind:11s} MAEN {r['maen']:.3f}  depth {100 * r['depth_error']:.2f} %"
                          f" (floor {100 * r['depth_error_exact_normals']:.2f} %)  {r['estimated']}  rounds {r['rounds']}  {r['seconds']:.1f} s",
                          file=sys.stderr)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps({"size": a.size, "device": a.device, "pipeline": rows, "dgmc": dg}, indent=1, default=float))
    os.replace(tmp, out)
    print(f"\n{'scene':7s} {'brdf':14s} {'camera':12s} {'lights':11s} {'MAEN':>6s} {'depth %':>8s} {'floor %':>8s}  estimated (true)  s")
    for r in rows:
        est = ", ".join(f"{k} {v:.3g} ({r['true'][k]:.3g})" for k, v in r["estimated"].items())
        print(f"{r['scene']:7s} {r['brdf']:14s} {r['camera']:12s} {r['lights']:11s} {r['maen']:6.3f} {100 * r['depth_error']:8.3f} "
              f"{100 * r['depth_error_exact_normals']:8.3f}  {est}  {r['seconds']:.0f}")
    print("\nDGMC on highlight pixels (known material): evaluations per pixel / MAEN deg")
    for r in dg:
        cells = "  ".join(f"{k}: {r[k]['evaluations_per_pixel']:.1f} / {r[k]['maen']:.3f}" for k in
                          ("multistart_10", "one_start_least_squares", "one_start_dgmc", "one_start_dgmc_front"))
        print(f"{r['scene']:7s} {r['brdf']:14s} {r['camera']:12s} px {r['highlight_pixels']:5d}  {cells}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
