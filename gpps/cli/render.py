"""``gpps render``: write a synthetic DiLiGenT-style capture with ground truth."""

from __future__ import annotations

import time

import gpps
from gpps import BRDF_NAMES, Material
from gpps.cli._output import add_output_args, as_options, prepare_out
from gpps.io import write_dataset


def register(sub):
    p = sub.add_parser("render", help="render a synthetic scene to a DiLiGenT-style folder (16-bit PNGs + ground truth)")
    p.add_argument("--scene", choices=gpps.SCENE_NAMES, default="sphere", help="synthetic object")
    p.add_argument("--brdf", choices=BRDF_NAMES, default="blinn-phong", help="reflectance model")
    p.add_argument("--lights", choices=["directional", "point"], default="directional", help="light kind (point: near lights on the camera plane)")
    p.add_argument("--n-lights", type=int, default=3, help="number of lights (one image each)")
    p.add_argument("--slant", type=float, default=35.0, help="angle of the lights from the view axis (deg), ring layout")
    p.add_argument("--layout", choices=["ring", "spiral"], default="ring", help="ring: equal slants; spiral: slants from 15 to 50 deg")
    p.add_argument("--camera", choices=["orthographic", "perspective"], default="perspective", help="camera model")
    p.add_argument("--size", type=int, default=256, help="image size (pixels, square)")
    p.add_argument("--albedo", choices=["uniform", "texture"], default="uniform", help="uniform colour or a smooth random texture")
    p.add_argument("--noise", type=float, default=0.0, help="Gaussian noise standard deviation (1 = white)")
    p.add_argument("--bits", type=int, choices=[8, 16], default=16, help="PNG bit depth")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise and the texture")
    for name in ("ks", "shininess", "roughness", "f0", "eta_u", "eta_v"):
        p.add_argument(f"--{name.replace('_', '-')}", type=float, default=None, help=f"material {name} (default: per model)")
    p.add_argument("--ior", type=float, default=None, help="index of refraction instead of --f0 (plastic: default 1.5)")
    add_output_args(p, "output folder (DiLiGenT-style capture with ground truth)")
    p.set_defaults(func=run)


def material_from_args(args) -> Material:
    m = Material.default_for(args.brdf).to_dict()
    for name in ("ks", "shininess", "roughness", "f0", "eta_u", "eta_v"):
        v = getattr(args, name, None)
        if v is not None:
            m[name] = v
    ior = getattr(args, "ior", None)
    if ior is not None:
        if getattr(args, "f0", None) is not None:
            raise ValueError("ior: give either --ior or --f0, not both")
        m["f0"] = Material.f0_from_ior(ior)
    return Material.from_dict(m)


def run(args) -> int:
    t0 = time.perf_counter()
    out = prepare_out(args)
    with as_options("size", "seed", "noise", "ks", "shininess", "roughness", "f0", "eta_u", "eta_v", "ior",
                    n="--n-lights", slant_deg="--slant"):
        scene = gpps.make_scene(args.scene, args.size, args.camera, albedo=args.albedo, seed=args.seed)
        lights = gpps.default_lights(args.lights, args.n_lights, slant_deg=args.slant, layout=args.layout)
        ds = gpps.render_dataset(scene, material_from_args(args), lights, noise=args.noise, bits=args.bits,
                                 seed=args.seed, device=args.device)
    write_dataset(out, ds, bits=args.bits, overwrite=args.overwrite)
    print(f"wrote {len(ds.images)} images of {args.scene} ({args.size}x{args.size}, {args.camera}, {args.lights} lights, {args.brdf}) to {args.out} in {time.perf_counter() - t0:.2f} s")
    return 0
