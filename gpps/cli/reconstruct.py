"""``gpps reconstruct DIR --out OUT``: calibrated photometric stereo on a DiLiGenT-style folder."""

from __future__ import annotations

import json
import time

from gpps.cli._output import add_output_args, prepare_out, warning_messages


def register(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="normals, albedo, depth and material from a calibrated photometric-stereo folder")
    p.add_argument("dir", help="DiLiGenT-style folder (images, light_directions.txt or light_positions.txt, light_intensities.txt, mask.png, K.txt)")
    add_output_args(p, "output folder (normals.npy, albedo.png, normals.png, depth.npy, depth.tiff, mesh.ply, view.png, report.json)")
    p.add_argument("--method", default="ron", choices=["ron", "ppn", "pps"],
                   help="ron (default): the pipeline: least squares, DGMC starts, RON rounds of normals/albedo/depth/material; "
                        "ppn: one per-pixel solve (known material) then integration; pps: perspective Blinn-Phong in log depth")
    p.add_argument("--brdf", default=None, help="reflectance model (default: material.json's, else blinn-phong)")
    p.add_argument("--solver", default="lm", choices=["lm", "dogleg", "bfgs", "none"])
    p.add_argument("--robust", default=None, choices=["none", "huber", "cauchy"], help="robust loss (default: cauchy for N > 6 images, none otherwise)")
    p.add_argument("--ks", type=float, default=None, help="known specular weight (else estimated with --method ron)")
    p.add_argument("--shininess", type=float, default=None, help="known Phong/Blinn-Phong exponent (else estimated)")
    p.add_argument("--roughness", type=float, default=None, help="known Cook-Torrance roughness m (else estimated)")
    p.add_argument("--eta", type=float, default=None, help="known Ashikhmin-Shirley exponent eta_u = eta_v (else estimated)")
    p.add_argument("--f0", type=float, default=None, help="Fresnel f0 (never estimated; default 0.5)")
    p.add_argument("--known-material", action="store_true", help="use material.json's parameters as known (no estimation)")
    p.add_argument("--no-dgmc", action="store_true", help="RON: no DGMC starts for highlight pixels")
    p.add_argument("--no-integrate", action="store_true", help="no depth (no integration, no mesh)")
    p.add_argument("--integration", default="bini", choices=["bini", "poisson"],
                   help="the returned depth: 'bini' (default): bilateral normal integration of the final normals "
                        "(keeps depth discontinuities; BiNI's k=2 and tolerances); 'poisson': one least-squares solve "
                        "(smooth surfaces). RON's rounds move point lights with a Poisson depth either way")
    p.add_argument("--no-estimate", action="store_true", help="RON: do not estimate the material (defaults for what is not given)")
    p.add_argument("--rounds", type=int, default=5, help="RON: round cap (default 5)")
    p.add_argument("--material-rule", default="photometric", choices=["photometric", "depth-rms"], help="RON material update (depth-rms: the seed's 4.19)")
    p.add_argument("--reference-depth", "--depth", dest="reference_depth", type=float, default=None,
                   help="mean object distance (scene units): sets the depth's scale; needed for point lights unless depth_gt.npy exists")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from gpps.camera import Orthographic, camera_from_K
    from gpps.cli._progress import bar
    from gpps.io import atomic_dir, read_dataset, save_json, save_npy, save_png, save_tiff
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material
    from gpps.metrics import normal_errors
    from gpps.pipeline.ron import LOBE_PARAMETERS

    t0 = time.perf_counter()
    if args.rounds < 1:
        raise ValueError(f"--rounds: expected an integer >= 1, got {args.rounds}")
    out = prepare_out(args, inputs=[args.dir])
    ds = read_dataset(args.dir)
    n, h, w = ds.images.shape[:3]
    camera = camera_from_K(ds.K) if ds.K is not None else Orthographic()
    if ds.light_positions is not None:
        lights = PointLights(ds.light_positions)
    elif ds.light_directions is not None:
        lights = DirectionalLights(ds.light_directions)
    else:
        raise ValueError(f"{args.dir}: expected light_directions.txt or light_positions.txt")
    base = Material.from_dict(ds.material) if ds.material else None
    brdf = args.brdf or (base.brdf if base is not None else "blinn-phong")
    if args.known_material and base is not None and base.brdf == brdf:
        mat_d = base.to_dict()
    else:
        mat_d = Material.default_for(brdf).to_dict()
    given = {k: getattr(args, k) for k in ("ks", "shininess", "roughness", "f0") if getattr(args, k) is not None}
    if args.eta is not None:
        given.update(eta_u=args.eta, eta_v=args.eta)
    mat_d.update(brdf=brdf, **given)
    material = Material.from_dict(mat_d)
    given_names = {"eta" if k in ("eta_u", "eta_v") else k for k in given}
    if args.known_material or args.no_estimate or args.method != "ron":
        estimate = ()
    else:
        estimate = tuple(k for k in LOBE_PARAMETERS[brdf] if k not in given_names)
    reference = args.reference_depth
    if isinstance(lights, PointLights) and reference is None:
        if ds.depth_gt is not None:
            reference = float(np.nanmean(np.asarray(ds.depth_gt, np.float64)[ds.mask]))
        else:
            raise ValueError("--reference-depth: expected the object's distance for point lights (light_positions.txt), got none")
    if reference is None and camera.is_perspective:
        reference = float(np.sqrt(camera.fx * camera.fy))  # unknown scale: one pixel ~ one unit at the mean depth
    raw = ds.images
    if ds.light_intensities is not None and ds.normalised:
        raw = ds.images * np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
    valid = ~np.any(raw >= 0.995, axis=-1)  # saturated in the file (the images were read as 0..full scale)
    robust = args.robust or ("cauchy" if n > 6 else "none")
    device = None if args.device == "auto" else args.device
    report = {"dir": str(args.dir), "images": n, "shape": [h, w], "camera": camera.kind, "lights": lights.kind,
              "method": args.method, "integration": None if args.no_integrate else args.integration}
    prog = None if args.json else bar("reconstruct")
    depth = dmask = None
    if args.method == "pps":
        from gpps.perspective import pps_blinn_phong

        if not camera.is_perspective or not isinstance(lights, DirectionalLights):
            raise ValueError("--method pps: expected a perspective camera (K.txt) and directional lights")
        t = time.perf_counter()
        r = pps_blinn_phong(ds.images, ds.mask, lights, camera, ks=material.ks, shininess=material.shininess)
        normals, albedo = r["normals"], np.repeat(r["albedo"][..., None], 3, -1)
        report["timings"] = {"solve": time.perf_counter() - t}
        report["material"] = material.to_dict()
    elif args.method == "ppn" or args.solver == "none":
        from gpps.photometric import solve_normals

        opts = {"shadow_threshold": 0.02, "starts": 4} if n > 6 else {}
        res = solve_normals(
            ds.images, ds.mask, lights, camera=camera, material=material, solver=args.solver,
            depth=None if not isinstance(lights, PointLights) else np.full((h, w), reference, np.float32),
            robust=robust, valid=valid, device=device, progress=prog, **opts,
        )
        normals, albedo = res.normals, res.albedo
        report.update(solver=args.solver, robust=robust, timings=res.timings, material=material.to_dict(),
                      mean_iterations=float(res.iterations[ds.mask].mean()),
                      flagged_pixels=int(np.count_nonzero(res.flags[ds.mask])))
    else:
        from dataclasses import replace

        from gpps.pipeline.ron import RONConfig
        from gpps.reconstruction import reconstruct

        from gpps.pipeline.integration import IntegratorConfig

        cfg = RONConfig(rounds=args.rounds, dgmc=not args.no_dgmc, integrate=not args.no_integrate,
                        material_rule=args.material_rule,
                        final_integrator=IntegratorConfig(bilateral=True) if args.integration == "bini" else None)
        solver = replace(cfg.solver, solver=args.solver, robust=robust)
        if n > 6:
            solver = replace(solver, shadow_threshold=0.02, starts=4)
        cfg = replace(cfg, solver=solver)
        rec = reconstruct(ds.images, ds.mask, lights, camera=camera, material=material, estimate=estimate,
                          reference_depth=reference, valid=valid,
                          config=cfg, device=device, progress=prog)
        normals, albedo = rec.normals, rec.albedo
        depth, dmask = rec.depth, rec.depth_mask
        report.update(solver=args.solver, robust=robust, timings=rec.timings, material=rec.material.to_dict(),
                      estimated=rec.estimated, fixed=rec.fixed, known=sorted(given_names) if not args.known_material else "material.json",
                      energy_per_round=rec.energy, rounds=rec.rounds, converged=rec.converged,
                      highlight_pixels=int(rec.highlight.sum()),
                      mean_iterations=float(rec.iterations[ds.mask].mean()),
                      flagged_pixels=int(np.count_nonzero(rec.flags[ds.mask])))
    normals = np.where(ds.mask[..., None], normals, 0.0).astype(np.float32)
    if depth is None and not args.no_integrate:
        from gpps.integrate import integrate_normals

        t = time.perf_counter()
        ir = integrate_normals(normals, ds.mask, camera=camera, reference_depth=reference, device=args.device,
                               bilateral=args.integration == "bini")
        depth, dmask = ir.depth, ir.mask
        report.setdefault("timings", {})["integration"] = time.perf_counter() - t
    if ds.normal_gt is not None:
        report["errors"] = normal_errors(normals, ds.normal_gt, ds.mask)
        report["maen_deg"] = report["errors"]["mean"]
    with atomic_dir(out, overwrite=args.overwrite, inputs=[args.dir], name="--out") as tmp:
        save_npy(tmp / "normals.npy", normals)
        a = albedo / max(float(np.percentile(albedo[ds.mask], 99)), 1e-12)
        save_png(tmp / "albedo.png", np.clip(a, 0, 1), bits=8)
        save_png(tmp / "normals.png", np.where(ds.mask[..., None], (normals + 1) / 2, 0), bits=8)
        if depth is not None:
            from gpps.mesh import depth_to_mesh, render_view, save_mesh

            save_npy(tmp / "depth.npy", depth.astype(np.float32))
            save_tiff(tmp / "depth.tiff", depth.astype(np.float32))
            save_mesh(depth_to_mesh(depth, dmask, camera), tmp / "mesh.ply")
            view = render_view(depth, dmask, camera, tmp / "view.png")
            report["view"] = view["method"]
        report["timings"]["total"] = time.perf_counter() - t0
        report["warnings"] = warning_messages(args)
        save_json(tmp / "report.json", report)
    if args.json:
        print(json.dumps(report, indent=2, default=float))
    else:
        msg = f"wrote {out}"
        if "maen_deg" in report:
            msg += f"  (MAEN {report['maen_deg']:.2f} deg)"
        if report.get("estimated"):
            msg += "  estimated " + ", ".join(f"{k}={v:.3g}" for k, v in report["estimated"].items())
        print(msg)
    return 0
