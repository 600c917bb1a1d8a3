"""``gpps reconstruct DIR --out OUT``: calibrated photometric stereo on a DiLiGenT-style folder."""

from __future__ import annotations

import json
import time
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="normals and albedo from a calibrated photometric-stereo folder")
    p.add_argument("dir", help="DiLiGenT-style folder (images, light_directions.txt or light_positions.txt, light_intensities.txt, mask.png, K.txt)")
    p.add_argument("--out", required=True, help="output folder (normals.npy, albedo.png, normals.png, report.json)")
    p.add_argument("--brdf", default=None, help="reflectance model (default: material.json's, else lambertian)")
    p.add_argument("--solver", default="lm", choices=["lm", "dogleg", "bfgs", "none"])
    p.add_argument("--method", default="ppn", choices=["ppn", "pps"], help="ppn: per-pixel normals (default); pps: perspective Blinn-Phong in log depth (3 directional lights, perspective)")
    p.add_argument("--robust", default=None, choices=["none", "huber", "cauchy"], help="robust loss (default: cauchy for N > 6 images, none otherwise)")
    p.add_argument("--ks", type=float, default=None)
    p.add_argument("--shininess", type=float, default=None)
    p.add_argument("--roughness", type=float, default=None)
    p.add_argument("--f0", type=float, default=None)
    p.add_argument("--depth", type=float, default=None, help="constant depth estimate for point lights (default: K's focal length scale is unknown, so required with light_positions.txt unless depth_gt.npy exists)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from gpps.camera import Orthographic, camera_from_K
    from gpps.cli._progress import bar
    from gpps.io import read_dataset, save_json, save_npy, save_png
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material
    from gpps.metrics import normal_errors

    t0 = time.perf_counter()
    ds = read_dataset(args.dir)
    n, h, w = ds.images.shape[:3]
    camera = camera_from_K(ds.K) if ds.K is not None else Orthographic()
    if ds.light_positions is not None:
        lights = PointLights(ds.light_positions)
    elif ds.light_directions is not None:
        lights = DirectionalLights(ds.light_directions)
    else:
        raise ValueError(f"{args.dir}: expected light_directions.txt or light_positions.txt")
    if not ds.normalised and ds.light_intensities is None:
        pass  # unit intensities: images used as they are
    base = Material.from_dict(ds.material) if ds.material else Material("lambertian", ks=0.0)
    brdf = args.brdf or base.brdf
    kw = {k: getattr(args, k) for k in ("ks", "shininess", "roughness", "f0") if getattr(args, k) is not None}
    mat_d = base.to_dict() if brdf == base.brdf else Material.default_for(brdf).to_dict()
    mat_d.update(brdf=brdf, **kw)
    material = Material.from_dict(mat_d)
    depth = None
    if isinstance(lights, PointLights):
        if args.depth is not None:
            depth = np.full((h, w), float(args.depth), np.float32)
        elif ds.depth_gt is not None:
            depth = np.asarray(ds.depth_gt, np.float32)
        else:
            raise ValueError("--depth: expected a depth estimate for point lights (light_positions.txt), got none")
    valid = None
    if ds.light_intensities is not None and ds.normalised:
        raw = ds.images * np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
        valid = ~np.any(raw >= 0.995, axis=-1)  # saturated in the file
    robust = args.robust or ("cauchy" if n > 6 else "none")
    report = {"dir": str(args.dir), "images": n, "shape": [h, w], "camera": camera.kind, "lights": lights.kind, "material": material.to_dict(), "method": args.method}
    prog = None if args.json else bar("reconstruct")
    if args.method == "pps":
        from gpps.perspective import pps_blinn_phong

        if not camera.is_perspective or not isinstance(lights, DirectionalLights):
            raise ValueError("--method pps: expected a perspective camera (K.txt) and directional lights")
        t = time.perf_counter()
        r = pps_blinn_phong(ds.images, ds.mask, lights, camera, ks=material.ks, shininess=material.shininess)
        normals, albedo = r["normals"], np.repeat(r["albedo"][..., None], 3, -1)
        report["timings"] = {"solve": time.perf_counter() - t}
    else:
        from gpps.photometric import solve_normals

        opts = {}
        if n > 6:
            opts.update(shadow_threshold=0.02, starts=4)
        res = solve_normals(
            ds.images, ds.mask, lights, camera=camera, material=material, solver=args.solver, depth=depth,
            robust=robust, valid=valid, device=None if args.device == "auto" else args.device, progress=prog, **opts,
        )
        normals, albedo = res.normals, res.albedo
        report["solver"] = args.solver
        report["robust"] = robust
        report["timings"] = res.timings
        report["mean_iterations"] = float(res.iterations[ds.mask].mean())
        report["flagged_pixels"] = int(np.count_nonzero(res.flags[ds.mask]))
    normals = np.where(ds.mask[..., None], normals, 0.0).astype(np.float32)
    if ds.normal_gt is not None:
        report["errors"] = normal_errors(normals, ds.normal_gt, ds.mask)
        report["maen_deg"] = report["errors"]["mean"]
    out = Path(args.out)
    save_npy(out / "normals.npy", normals)
    a = albedo / max(float(np.percentile(albedo[ds.mask], 99)), 1e-12)
    save_png(out / "albedo.png", np.clip(a, 0, 1), bits=8)
    save_png(out / "normals.png", np.where(ds.mask[..., None], (normals + 1) / 2, 0), bits=8)
    report["timings"]["total"] = time.perf_counter() - t0
    save_json(out / "report.json", report)
    if args.json:
        print(json.dumps(report, indent=2, default=float))
    else:
        msg = f"wrote {out}"
        if "maen_deg" in report:
            msg += f"  (MAEN {report['maen_deg']:.2f} deg)"
        print(msg)
    return 0
