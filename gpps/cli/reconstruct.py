"""``gpps reconstruct DIR --out OUT``: photometric stereo on a folder of images (calibrated or not).

With light files (``light_directions.txt`` or ``light_positions.txt``) the
calibrated pipeline runs; without them (or with ``--uncalibrated``) the lights
are estimated (:func:`gpps.solve_uncalibrated`) and written to
``lights_estimated.txt`` / ``light_intensities_estimated.txt``.  The folder is
read by :func:`gpps.io.read_capture` (any image format, no filenames.txt
or mask.png needed); the outputs are :data:`gpps.io.OUTPUT_FILES`.  The work is
:func:`gpps.reconstruct_folder`'s; this command maps its options to a
:class:`gpps.FolderConfig` and writes the result.
"""

from __future__ import annotations

import argparse
import json
import time

import gpps
import gpps.io
from gpps.cli._output import add_output_args, as_options, prepare_out, warning_messages
from gpps.cli._progress import bar


def register(subparsers) -> None:
    p = subparsers.add_parser("reconstruct", help="normals, albedo, depth and material from a folder of images (lights known or not)",
                              description=__doc__.splitlines()[0])
    p.add_argument("dir", help="folder of images (PNG 8/16, JPEG, TIFF 8/16/32f, EXR, PGM, camera RAW); optional: filenames.txt, "
                               "light_directions.txt or light_positions.txt, light_intensities.txt, mask.png, K.txt, an *ambient* image")
    add_output_args(p, "output folder (normals.npy/.png, albedo.npy/.png, depth.npy/.tiff/.exr, mesh.ply/.obj, view.png, mask.png, "
                       "report.json; uncalibrated: lights_estimated.txt, light_intensities_estimated.txt)")
    add_reconstruct_options(p)
    p.add_argument("--json", action="store_true", help="print the report as JSON on stdout (progress stays on stderr)")
    p.set_defaults(func=run)


def add_reconstruct_options(p) -> None:
    """The reconstruction's options (all but DIR, --out and --json): shared with ``gpps batch``."""
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
    p.add_argument("--robust", default=None, choices=["none", "huber", "cauchy"], help="robust loss (default: cauchy for N > 3 images, none otherwise)")
    p.add_argument("--ks", type=float, default=None, help="known specular weight (else estimated with --method ron)")
    p.add_argument("--shininess", type=float, default=None, help="known Phong/Blinn-Phong exponent (else estimated)")
    p.add_argument("--roughness", type=float, default=None, help="known Cook-Torrance / plastic roughness m (else estimated)")
    p.add_argument("--eta", type=float, default=None, help="known Ashikhmin-Shirley exponent eta_u = eta_v (else estimated)")
    p.add_argument("--f0", type=float, default=None, help="Fresnel f0 (never estimated; default 0.5, plastic 0.04: index of refraction 1.5)")
    p.add_argument("--known-material", action="store_true", help="use material.json's parameters as known (no estimation)")
    p.add_argument("--no-dgmc", action="store_true", help="RON: no DGMC starts for highlight pixels")
    p.add_argument("--no-integrate", action="store_true", help="no depth (no integration, no mesh)")
    p.add_argument("--integration", default="bini", choices=["bini", "poisson"],
                   help="the returned depth: 'bini' (default): bilateral normal integration of the final normals "
                        "(keeps depth discontinuities; BiNI's k=2 and tolerances); 'poisson': one least-squares solve "
                        "(smooth surfaces). RON's rounds move point lights with a Poisson depth either way")
    p.add_argument("--no-estimate", action="store_true", help="RON: do not estimate the material (defaults for what is not given)")
    p.add_argument("--rounds", type=int, default=5, help="RON: round cap")
    p.add_argument("--cast-shadows", action="store_true",
                   help="RON: leave observations in cast shadows, marched over each round's depth, out of the next "
                        "round's fit")
    p.add_argument("--refine", action=argparse.BooleanOptionalAction, default=None,
                   help="RON: refine the depth itself after the rounds (robust misfit over every observation, normals "
                        "tied to one surface); default: on with exactly 3 images, off with more")
    p.add_argument("--two-light", action=argparse.BooleanOptionalAction, default=True,
                   help="RON's refinement (3 images): also start from the surface the pixels with two lit "
                        "observations fix, and keep the likelier (cast shadows under directional lights; default on)")
    p.add_argument("--interreflections", default="auto", choices=["auto", "off", "subtract"],
                   help="RON: 'subtract' takes the diffuse interreflections gathered over the reconstructed surface out "
                        "of the images and reconstructs again (skipped on metals and convex objects); default auto: "
                        "subtract from 5 images on")
    p.add_argument("--interreflection-rounds", type=int, default=1,
                   help="interreflection compensation: gather-and-reconstruct rounds")
    p.add_argument("--albedo-scale", type=float, default=None,
                   help="interreflection compensation: physical albedo over the estimated one (1: radiometric light "
                        "intensities); default: unknown, the brightest pixels' albedo taken as 0.5")
    p.add_argument("--compare-models", default=None, metavar="MODEL[,MODEL...]",
                   help="RON: other reflectance models to fit beside --brdf's in the first material fit; one whose "
                        "residual is lower beyond the sample's noise is kept (e.g. plastic; none: no comparison; "
                        "default: the rough conductor and plastic with 5 or more images)")
    p.add_argument("--material-rule", default="photometric", choices=["photometric", "depth-rms"], help="RON material update (depth-rms: the seed's 4.19)")
    p.add_argument("--pixel-size", type=float, default=None, help="orthographic camera (no K.txt): scene units per pixel; default: depth in pixels")
    p.add_argument("--reference-depth", "--depth", dest="reference_depth", type=float, default=None,
                   help="mean object distance (scene units): sets the depth's scale; needed for point lights unless depth_gt.npy exists")


# the library's errors that name these settings name the options instead
_OPTIONS = ("rounds", "pixel_size", "reference_depth", "method", "ks", "shininess", "roughness", "eta", "f0", "max_size",
            "interreflections", "interreflection_rounds", "albedo_scale")


def folder_config(args) -> gpps.FolderConfig:
    """The :class:`gpps.FolderConfig` of the command's options (checked: errors name the options)."""
    try:
        return _folder_config(args)
    except (ValueError, TypeError) as e:
        if str(e).startswith("models:"):  # (FolderConfig.models is the --compare-models option)
            raise type(e)("--compare-models" + str(e)[len("models"):]) from e
        raise


def _folder_config(args) -> gpps.FolderConfig:
    with as_options(*_OPTIONS):
        return gpps.FolderConfig(
            transfer=args.transfer, max_size=args.max_size, uncalibrated=args.uncalibrated, method=args.method,
            brdf=args.brdf, solver=args.solver, robust=args.robust, ks=args.ks, shininess=args.shininess,
            roughness=args.roughness, eta=args.eta, f0=args.f0, known_material=args.known_material,
            dgmc=not args.no_dgmc, integrate=not args.no_integrate, integration=args.integration,
            estimate=not args.no_estimate, rounds=args.rounds, material_rule=args.material_rule,
            pixel_size=args.pixel_size, reference_depth=args.reference_depth,
            models=(None if args.compare_models is None else ()
                    if args.compare_models.strip().lower() == "none"
                    else tuple(b.strip() for b in args.compare_models.split(",") if b.strip())),
            cast_shadows=args.cast_shadows, refine=args.refine, two_light=args.two_light,
            interreflections=args.interreflections,
            interreflection_rounds=args.interreflection_rounds, albedo_scale=args.albedo_scale,
        )


def run(args) -> int:
    t0 = time.perf_counter()
    config = folder_config(args)
    mask_file = args.mask if args.mask not in (None, "auto", "none") else None
    inputs = [i for i in (args.dir, args.lights, mask_file) if i is not None]
    out = prepare_out(args, inputs=inputs)
    prog = bar("reconstruct")
    with as_options(*_OPTIONS):
        res = gpps.reconstruct_folder(args.dir, config, lights=args.lights, mask=args.mask, ambient=args.ambient,
                                      device=args.device, progress=prog, read_progress=bar("read"))
    with gpps.io.atomic_dir(out, overwrite=args.overwrite, inputs=inputs, name="--out") as tmp:
        report = res.write(tmp, warnings=warning_messages(args), started=t0)
    if args.json:
        print(json.dumps(report, indent=2, default=gpps.io.json_default))
    else:
        msg = f"wrote {out}"
        if "maen_deg" in report:
            msg += f"  (MAEN {report['maen_deg']:.2f} deg)"
        if report.get("estimated"):
            msg += "  estimated " + ", ".join(f"{k}={v:.3g}" for k, v in report["estimated"].items())
        if res.uncalibrated:
            msg += f"  lights estimated ({report['convex_concave']['surface']}, flip {report['convex_concave']['flip']})"
        print(msg)
    return 0
