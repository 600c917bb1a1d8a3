"""``gpps reconstruct DIR --out OUT``: photometric stereo on a folder of images (calibrated or not).

With light files (``light_directions.txt`` or ``light_positions.txt``) the
calibrated pipeline runs; without them (or with ``--uncalibrated``) the lights
are estimated (:func:`gpps.flows.uncalibrated.solve_uncalibrated`) and written to
``lights_estimated.txt`` / ``light_intensities_estimated.txt``.  The folder is
read by :func:`gpps.io.capture.read_capture` (any image format, no filenames.txt
or mask.png needed); the outputs are :data:`gpps.io.outputs.OUTPUT_FILES`.
"""

from __future__ import annotations

import json
import time

from gpps.cli._output import add_output_args, prepare_out, warning_messages


def register(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="normals, albedo, depth and material from a folder of images (lights known or not)",
                              description=__doc__.splitlines()[0])
    p.add_argument("dir", help="folder of images (PNG 8/16, JPEG, TIFF 8/16/32f, EXR, PGM, camera RAW); optional: filenames.txt, "
                               "light_directions.txt or light_positions.txt, light_intensities.txt, mask.png, K.txt, an *ambient* image")
    add_output_args(p, "output folder (normals.npy/.png, albedo.npy/.png, depth.npy/.tiff/.exr, mesh.ply/.obj, view.png, mask.png, "
                       "report.json; uncalibrated: lights_estimated.txt, light_intensities_estimated.txt)")
    p.add_argument("--uncalibrated", action="store_true", help="estimate the lights from the images even when light files are present "
                                                               "(without light files this is automatic)")
    p.add_argument("--lights", default=None, help="folder with the light files (e.g. from gpps calibrate-lights), rows in the images' order; "
                                                  "default: the light files in DIR")
    p.add_argument("--mask", default=None, help="mask image (non-zero = object); default: DIR/mask.* if present, else an automatic mask "
                                                "(pixels lit in enough images), written to the outputs; 'auto' forces the automatic mask")
    p.add_argument("--max-size", type=int, default=None, help="downscale images whose longer side exceeds this many pixels "
                                                              "(K.txt scaled with them); default: full size")
    p.add_argument("--transfer", default="auto", choices=["auto", "linear", "srgb"],
                   help="images' transfer curve: auto decodes sRGB for JPEG only (other formats are taken as linear)")
    p.add_argument("--ambient", default="auto", help="image with every light off, subtracted from each image: 'auto' (a file named *ambient* in DIR), "
                                                     "'none', or a file name")
    p.add_argument("--method", default="ron", choices=["ron", "ppn", "pps"],
                   help="ron (default): the pipeline: least squares, DGMC starts, RON rounds of normals/albedo/depth/material; "
                        "ppn: one per-pixel solve (known material) then integration; pps: perspective Blinn-Phong in log depth")
    p.add_argument("--brdf", default=None, help="reflectance model (default: material.json's, else blinn-phong)")
    p.add_argument("--solver", default="lm", choices=["lm", "dogleg", "bfgs", "none"], help="per-pixel solver (none: Lambertian least squares)")
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
    p.add_argument("--rounds", type=int, default=5, help="RON: round cap")
    p.add_argument("--material-rule", default="photometric", choices=["photometric", "depth-rms"], help="RON material update (depth-rms: the seed's 4.19)")
    p.add_argument("--pixel-size", type=float, default=None, help="orthographic camera (no K.txt): scene units per pixel; default: depth in pixels")
    p.add_argument("--reference-depth", "--depth", dest="reference_depth", type=float, default=None,
                   help="mean object distance (scene units): sets the depth's scale; needed for point lights unless depth_gt.npy exists")
    p.add_argument("--json", action="store_true", help="print the report as JSON on stdout (progress stays on stderr)")
    p.set_defaults(func=run)


def _flip_decision(res, mask, camera) -> tuple[bool, dict]:
    """The convex/concave decision for an uncalibrated result.

    When the images decided it (perspective cues, ``res.flip == "resolved"``)
    it is kept.  Otherwise the two members of the pair explain the images
    equally well, and the convex one is taken: its normals point away from the
    object's middle, ``mean(n_xy . (p - centroid)) > 0`` over the mask (p the
    pixel's position in the gpps frame, y up), which holds for any surface
    that bulges toward the camera (faces, most objects).

    Returns:
        (whether to flip, the report entry).
    """
    import numpy as np

    h, w = mask.shape
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = jj[mask] - jj[mask].mean(), -(ii[mask] - ii[mask].mean())
    r = np.sqrt(x**2 + y**2) + 1e-9
    n = res.normals[mask]
    score = float(np.mean((n[:, 0] * x + n[:, 1] * y) / r))
    if res.flip == "resolved":
        return False, {"flip": "resolved", "by": "perspective cues (specular residual or curl)",
                       "surface": "convex" if score > 0 else "concave", "convexity_score": score}
    flip = score < 0
    return flip, {"flip": "ambiguous", "by": "convexity prior: the images cannot tell the pair apart; the member whose "
                                             "normals point away from the object's middle was kept",
                  "surface": "convex", "convexity_score": abs(score), "flipped": bool(flip)}


def _save_rows(path, rows, header: str) -> None:
    import numpy as np

    from gpps.io import atomic_write

    with atomic_write(path) as tmp:
        np.savetxt(tmp, np.atleast_2d(np.asarray(rows, np.float64)), fmt="%.9g", header=header)


def run(args) -> int:
    import numpy as np

    from gpps.camera import Orthographic, camera_from_K
    from gpps.io.capture import read_capture
    from gpps.cli._progress import bar
    from gpps.io import atomic_dir, save_json
    from gpps.lights import DirectionalLights, PointLights
    from gpps.material import Material
    from gpps.host.metrics import normal_errors
    from gpps.io.outputs import apply_depth_convention, depth_convention, write_outputs
    from gpps.flows.ron import LOBE_PARAMETERS

    t0 = time.perf_counter()
    if args.rounds < 1:
        raise ValueError(f"--rounds: expected an integer >= 1, got {args.rounds}")
    if args.pixel_size is not None and not args.pixel_size > 0:
        raise ValueError(f"--pixel-size: expected a number > 0, got {args.pixel_size}")
    out = prepare_out(args, inputs=[args.dir, args.lights, args.mask if args.mask not in (None, "auto", "none") else None])
    prog = bar("reconstruct")
    cap = read_capture(args.dir, transfer=args.transfer, max_size=args.max_size,
                       ambient=None if args.ambient == "none" else args.ambient,
                       mask=args.mask, normalise=not args.uncalibrated, lights=args.lights, progress=bar("read"))
    ds = cap.dataset
    n, h, w = ds.images.shape[:3]
    camera = camera_from_K(ds.K) if ds.K is not None else Orthographic(args.pixel_size or 1.0)
    uncalibrated = args.uncalibrated or not cap.calibrated
    device = None if args.device == "auto" else args.device
    report = {"dir": str(args.dir), "images": n, "shape": [h, w], "camera": camera.kind,
              "integration": None if args.no_integrate else args.integration,
              "input": {"formats": cap.formats, "mask": cap.mask_source, "ambient_subtracted": cap.ambient,
                        "downscale": cap.scale, "filenames": ds.filenames}}
    if cap.automask is not None:
        report["input"]["automatic_mask"] = cap.automask
    if ds.mask.sum() < 10:
        raise ValueError(f"mask: expected at least 10 object pixels, got {int(ds.mask.sum())}")
    depth = dmask = None
    reference = args.reference_depth
    scale_source = "--reference-depth" if reference is not None else None
    if uncalibrated:
        from gpps.flows.uncalibrated import UncalibratedConfig, solve_uncalibrated
        from gpps.host.gbr import dark_images

        cfg = UncalibratedConfig()
        drop = dark_images(ds.images, ds.mask, cfg.dark_fraction) if cfg.dark_fraction > 0 else []
        if drop:
            import warnings

            from gpps._check import GppsWarning

            warnings.warn(f"left out {len(drop)} nearly dark image(s) (failed captures?): {', '.join(ds.filenames[k] for k in drop)}",
                          GppsWarning, stacklevel=1)
        keep = [k for k in range(n) if k not in drop]
        used = [ds.filenames[k] for k in keep]
        t = time.perf_counter()
        # the lights are estimated from the pixels that carry evidence: lit in enough images (a pupil or a
        # hole dark in nearly every image says nothing about them); the rest of the mask is then solved
        # with the estimated lights (Lambertian least squares)
        from gpps.host.automask import lit_pixels

        imgs_used = ds.images[keep]
        evidence = ds.mask & lit_pixels(imgs_used)
        if evidence.sum() < 0.5 * ds.mask.sum():
            evidence = ds.mask
        res = solve_uncalibrated(imgs_used, evidence, camera=camera if camera.is_perspective else None, config=cfg,
                                 device=device, progress=prog)
        flip, decision = _flip_decision(res, evidence, camera)
        F = np.diag([-1.0, -1.0, 1.0])
        normals, ldirs = (res.normals @ F, res.light_directions @ F) if flip else (res.normals, res.light_directions)
        albedo = res.albedo
        intens = np.repeat(np.asarray(res.light_intensities, np.float64)[:, None], 3, 1)
        rest = ds.mask & ~evidence
        if rest.any():
            from gpps.flows.photometric import solve_normals

            ls = solve_normals(imgs_used / intens[:, None, None, :].astype(np.float32), rest, DirectionalLights(ldirs),
                               camera=camera, solver="none", device=device)
            normals = np.where(rest[..., None], ls.normals, normals)
            albedo = np.where(rest[..., None], ls.albedo, albedo)
        report.update(method="uncalibrated", lights="estimated (directional)", convex_concave=decision,
                      images_used=used, images_left_out=[ds.filenames[k] for k in drop],
                      light_evidence_pixels=int(evidence.sum()), material=res.material, gbr=res.gbr,
                      timings={"uncalibrated": time.perf_counter() - t, **res.timings})
        lights = DirectionalLights(ldirs)
    else:
        report["method"] = args.method
        if ds.light_positions is not None:
            lights = PointLights(ds.light_positions)
        else:
            lights = DirectionalLights(ds.light_directions)
        report["lights"] = lights.kind
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
        if reference is None and ds.depth_gt is not None and (camera.is_perspective or isinstance(lights, PointLights)):
            reference = float(np.nanmean(np.asarray(ds.depth_gt, np.float64)[ds.mask]))
            scale_source = "depth_gt.npy"
        if isinstance(lights, PointLights):
            if reference is None:
                raise ValueError("--reference-depth: expected the object's distance for point lights (light_positions.txt), got none")
            scale_source = "light_positions.txt" + (f" (distance from {scale_source})" if scale_source else "")
        internal_reference = reference
        if internal_reference is None and camera.is_perspective:
            internal_reference = float(np.sqrt(camera.fx * camera.fy))  # any scale: the shape does not depend on it
        valid = None
        integer_input = all(f["format"] not in ("exr",) and not (f["format"] == "tiff" and f["bits"] == 32) for f in cap.formats)
        if integer_input:  # saturated in the file (integer images were read as 0..full scale; float ones have no ceiling)
            raw = ds.images
            if ds.light_intensities is not None and ds.normalised:
                raw = ds.images * np.asarray(ds.light_intensities, np.float32)[:, None, None, :]
            valid = ~np.any(raw >= 0.995, axis=-1)
        robust = args.robust or ("cauchy" if n > 6 else "none")
        if args.method == "pps":
            from gpps.host.perspective import pps_blinn_phong

            if not camera.is_perspective or not isinstance(lights, DirectionalLights):
                raise ValueError("--method pps: expected a perspective camera (K.txt) and directional lights")
            t = time.perf_counter()
            r = pps_blinn_phong(ds.images, ds.mask, lights, camera, ks=material.ks, shininess=material.shininess)
            normals, albedo = r["normals"], np.repeat(r["albedo"][..., None], 3, -1)
            report["timings"] = {"solve": time.perf_counter() - t}
            report["material"] = material.to_dict()
        elif args.method == "ppn" or args.solver == "none":
            from gpps.flows.photometric import solve_normals

            opts = {"shadow_threshold": 0.02, "starts": 4} if n > 6 else {}
            res = solve_normals(
                ds.images, ds.mask, lights, camera=camera, material=material, solver=args.solver,
                depth=None if not isinstance(lights, PointLights) else np.full((h, w), internal_reference, np.float32),
                robust=robust, valid=valid, device=device, progress=prog, **opts,
            )
            normals, albedo = res.normals, res.albedo
            report.update(solver=args.solver, robust=robust, timings=res.timings, material=material.to_dict(),
                          mean_iterations=float(res.iterations[ds.mask].mean()),
                          flagged_pixels=int(np.count_nonzero(res.flags[ds.mask])))
        else:
            from dataclasses import replace

            from gpps.flows.ron import RONConfig
            from gpps.flows.reconstruction import reconstruct

            from gpps.pipeline.integration import IntegratorConfig

            cfg = RONConfig(rounds=args.rounds, dgmc=not args.no_dgmc, integrate=not args.no_integrate,
                            material_rule=args.material_rule,
                            final_integrator=IntegratorConfig(bilateral=True) if args.integration == "bini" else None)
            solver = replace(cfg.solver, solver=args.solver, robust=robust)
            if n > 6:
                solver = replace(solver, shadow_threshold=0.02, starts=4)
            cfg = replace(cfg, solver=solver)
            rec = reconstruct(ds.images, ds.mask, lights, camera=camera, material=material, estimate=estimate,
                              reference_depth=internal_reference, valid=valid,
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
        from gpps.flows.integrate import integrate_normals

        t = time.perf_counter()
        ref_i = reference if reference is not None else (float(np.sqrt(camera.fx * camera.fy)) if camera.is_perspective else None)
        ir = integrate_normals(normals, ds.mask, camera=camera, reference_depth=ref_i, device=args.device,
                               bilateral=args.integration == "bini")
        depth, dmask = ir.depth, ir.mask
        report.setdefault("timings", {})["integration"] = time.perf_counter() - t
    conv = depth_convention(camera, known_scale=scale_source)
    if args.pixel_size is not None and not camera.is_perspective:
        conv = depth_convention(camera)
    if depth is not None:
        depth = apply_depth_convention(depth, dmask, conv)
        report["depth"] = conv
    if ds.normal_gt is not None and ds.normal_gt.shape[:2] == (h, w):
        report["errors"] = normal_errors(normals, ds.normal_gt, ds.mask)
        report["maen_deg"] = report["errors"]["mean"]
    inputs = [args.dir, args.lights, args.mask if args.mask not in (None, "auto", "none") else None]
    with atomic_dir(out, overwrite=args.overwrite, inputs=[i for i in inputs if i is not None], name="--out") as tmp:
        written = write_outputs(tmp, normals=normals, albedo=albedo, mask=ds.mask, depth=depth, depth_mask=dmask,
                                camera=camera, depth_info=conv if depth is not None else None)
        if uncalibrated:
            hdr = (f"gpps uncalibrated estimate, one row per image used (images_used in report.json, in order): "
                   f"{{}}; gpps frame: x right, y up, z toward the camera")
            _save_rows(tmp / "lights_estimated.txt", ldirs, hdr.format("unit directions toward the lights"))
            _save_rows(tmp / "light_intensities_estimated.txt", intens, hdr.format("relative RGB intensities (mean 1)"))
            (tmp / "filenames_used.txt").write_text("\n".join(used) + "\n")
            written["files"] += ["lights_estimated.txt", "light_intensities_estimated.txt", "filenames_used.txt"]
        report["outputs"] = written["files"]
        if "view" in written:
            report["view"] = written["view"]
        report.setdefault("timings", {})["total"] = time.perf_counter() - t0
        report["warnings"] = warning_messages(args)
        save_json(tmp / "report.json", report)
    if args.json:
        print(json.dumps(report, indent=2, default=_json_default))
    else:
        msg = f"wrote {out}"
        if "maen_deg" in report:
            msg += f"  (MAEN {report['maen_deg']:.2f} deg)"
        if report.get("estimated"):
            msg += "  estimated " + ", ".join(f"{k}={v:.3g}" for k, v in report["estimated"].items())
        if uncalibrated:
            msg += f"  lights estimated ({report['convex_concave']['surface']}, flip {report['convex_concave']['flip']})"
        print(msg)
    return 0


def _json_default(o):
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
