"""gpps.reconstruct on the real near-light LED capture ../shared/data/nearlight/hehe12 (no ground truth).

Reads the capture with gpps.io.nearlight.read_nearlight (ambient subtracted,
images divided by Phi / mean(Phi), LED positions and axes converted from the
capture's computer-vision frame to gpps's, K un-transposed), block-averages it
by ``--downsample`` (default 4: 1920x1200 -> 480x300) for CPU time, estimates
the object's distance (gpps.io.nearlight.estimate_distance: the flat distance
whose Lambertian point-light fit leaves the lowest relative residual, over a
log grid of 100-1000 mm), and runs gpps.reconstruct with point lights and a
flat initial depth at that distance; each RON round re-derives the LED
directions and falloff from the integrated depth.

Writes perf/results/nearlight_hehe12/: normals.png, albedo.png, depth.npy
(float32, mm), mesh.ply (binary), view.png, report.json.

Usage:  python perf/nearlight.py [--root ../shared/data/nearlight/hehe12] [--downsample 4] [--distance MM]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("GPPS_CACHE_DIR", str(ROOT / ".cache"))

import numpy as np


def oblique_view(mesh, path, azimuth=35.0, elevation=30.0) -> str:
    """The mesh seen from the side (view.png is head-on, which hides the relief); 'skipped: why' without GL."""
    try:
        import cv2
        import pyvista as pv

        from gpps.io import atomic_write

        pl = pv.Plotter(off_screen=True, window_size=[800, 800])
        pl.set_background("white")
        pl.add_mesh(mesh.compute_normals(auto_orient_normals=False, consistent_normals=False),
                    color="lightgray", smooth_shading=True, specular=0.2)
        pl.camera_position = "xy"
        pl.camera.Azimuth(azimuth)
        pl.camera.Elevation(elevation)
        img = pl.screenshot(None, return_img=True)
        pl.close()
        with atomic_write(path) as tmp:
            cv2.imwrite(str(tmp), np.asarray(img)[..., 2::-1])
        return f"azimuth {azimuth}, elevation {elevation}"
    except Exception as e:  # noqa: BLE001  (no GL: the head-on view.png is still there)
        return f"skipped: {type(e).__name__}: {e}"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=str(ROOT.parent / "shared" / "data" / "nearlight" / "hehe12"))
    ap.add_argument("--downsample", type=int, default=4)
    ap.add_argument("--distance", type=float, default=None, help="object distance in mm (default: estimated)")
    ap.add_argument("--material", default="blinn-phong")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--samples", type=int, default=1000, help="pixels sampled for the material fit")
    ap.add_argument("--grid", type=int, default=4)
    ap.add_argument("--evals", type=int, default=15)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=str(ROOT / "perf" / "results" / "nearlight_hehe12"))
    a = ap.parse_args(argv)
    log = lambda s: print(s, flush=True)


    from gpps.io import atomic_dir, save_json, save_npy, save_png
    from gpps.io.mesh import depth_to_mesh, render_view, save_mesh
    from gpps.io.nearlight import estimate_distance, read_nearlight
    from gpps.flows.ron import RONConfig
    from gpps.pipeline.solver import SolverConfig
    from gpps.flows.reconstruction import reconstruct

    t0 = time.perf_counter()
    cap = read_nearlight(a.root, downsample=a.downsample)
    n, h, w = cap.images.shape
    log(f"read {n} images {h}x{w} (downsample {a.downsample}), {int(cap.mask.sum())} mask pixels, "
        f"K fx={cap.K[0, 0]:.1f} cx={cap.K[0, 2]:.1f} cy={cap.K[1, 2]:.1f}; LEDs aimed at {cap.working_distance:.0f} mm "
        f"({time.perf_counter() - t0:.1f} s)")
    scores = None
    if a.distance is None:
        dist, scores = estimate_distance(cap.images, cap.mask, cap.camera, cap.lights, np.geomspace(100, 1000, 41))
        log(f"estimated distance {dist:.0f} mm (relative Lambertian residual {scores[dist]:.4f})")
    else:
        dist = float(a.distance)
    # the real-data settings reconstruct picks for N > 6 images, with a cheaper material fit
    solver = SolverConfig(robust="cauchy", shadow_threshold=0.02, starts=4)
    cfg = RONConfig(rounds=a.rounds, material_samples=a.samples, material_grid=a.grid, material_evals=a.evals,
                    solver=solver)
    t = time.perf_counter()
    rec = reconstruct(cap.images, cap.mask, cap.lights, camera=cap.camera, material=a.material,
                      reference_depth=dist, valid=~cap.saturated, config=cfg, device=a.device,
                      progress=lambda d, tot, m: log(f"   {m}"))
    secs = time.perf_counter() - t
    depth, dmask = rec.depth, rec.depth_mask
    d = depth[dmask]
    pts = cap.camera.backproject(np.where(dmask, depth, dist))[dmask]
    ext = pts.max(0) - pts.min(0)
    log(f"reconstructed in {secs:.0f} s: {rec.rounds} rounds, energy {[f'{e:.3g}' for e in rec.energy]}, "
        f"estimated {rec.estimated}; depth {d.min():.1f}..{d.max():.1f} mm (mean {d.mean():.1f}), "
        f"extent x {ext[0]:.1f} y {ext[1]:.1f} z {ext[2]:.1f} mm")
    report = {
        "root": str(a.root), "images": n, "shape": [h, w], "downsample": a.downsample,
        "mask_pixels": int(cap.mask.sum()), "K": cap.K.tolist(), "led_aim_distance_mm": cap.working_distance,
        "distance_mm": dist, "distance_scores": scores, "distance_rule": "estimate_distance (flat Lambertian fit)"
        if a.distance is None else "given",
        "material_model": a.material, "material": rec.material.to_dict(), "estimated": rec.estimated,
        "ron": {"rounds": a.rounds, "material_samples": a.samples, "material_grid": a.grid, "material_evals": a.evals,
                "solver": "lm, cauchy, shadow_threshold 0.02, 4 starts"},
        "energy_per_round": rec.energy, "rounds": rec.rounds, "converged": rec.converged,
        "normal_change_deg": rec.details.normal_change_deg, "highlight_pixels": int(rec.highlight.sum()),
        "depth_mm": {"min": float(d.min()), "max": float(d.max()), "mean": float(d.mean()), "std": float(d.std())},
        "extent_mm": ext.tolist(), "timings": rec.timings, "seconds": secs,
    }
    out = Path(a.out)
    with atomic_dir(out) as tmp:
        m = cap.mask
        save_png(tmp / "normals.png", np.where(m[..., None], (rec.normals + 1) / 2, 0), bits=8)
        alb = rec.albedo if rec.albedo.ndim == 3 else rec.albedo[..., None]
        alb = alb / max(float(np.percentile(alb[m], 99)), 1e-12)
        save_png(tmp / "albedo.png", np.clip(alb, 0, 1), bits=8)
        save_npy(tmp / "depth.npy", depth.astype(np.float32))
        save_mesh(depth_to_mesh(depth, dmask, cap.camera), tmp / "mesh.ply")
        view = render_view(depth, dmask, cap.camera, tmp / "view.png")
        report["view"] = view["method"]
        report["view_oblique"] = oblique_view(depth_to_mesh(depth, dmask, cap.camera), tmp / "view_oblique.png")
        report["seconds_total"] = time.perf_counter() - t0
        save_json(tmp / "report.json", report)
    sizes = {p.name: p.stat().st_size for p in out.iterdir()}
    log(f"wrote {out}: " + ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sorted(sizes.items())))


if __name__ == "__main__":
    main()
