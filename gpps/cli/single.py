"""``gpps single``: shape from one (or three) images with no lights, camera or scene known.

The shipped network predicts normals and depth; with the images' lights
estimated jointly, a cuckoo search refines each pixel's normal and albedo on the
Blinn-Phong reprojection error (seed ch. 6).  Writes the output set of
:mod:`gpps.io.outputs` (normals, albedo, depth as npy/TIFF/EXR, mesh as PLY/OBJ,
view, mask), ``normals_net.npy``, ``normals_net.png``, ``height_net.npy`` and
``report.json`` into ``--out`` (atomically: the folder appears complete or not
at all).  Nothing is known about the camera: orthographic, depth in pixels
(relative, mean 0).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

import gpps
from gpps import Orthographic
from gpps.cli._output import add_output_args, as_options, prepare_out, warning_messages
from gpps.cli._progress import bar
from gpps.io import (apply_depth_convention, atomic_dir, depth_convention, read_image, read_mask, save_json, save_npy,
                     save_png, write_outputs)


def register(subparsers) -> None:
    p = subparsers.add_parser("single", help="normals, depth, mesh from one or three images (network + cuckoo search)",
                              description=__doc__.splitlines()[0])
    p.add_argument("images", nargs="+", help="IMAGE [IMAGE2 IMAGE3]: the same object under other (unknown) lights")
    p.add_argument("--mask", default=None, help="mask image (non-zero = object); default: every lit pixel")
    add_output_args(p, "output folder")
    p.add_argument("--rounds", type=int, default=1, help="light-estimation / cuckoo rounds (0: network only)")
    p.add_argument("--generations", type=int, default=80, help="cuckoo generations per round")
    p.add_argument("--nests", type=int, default=12, help="nests (habitats) per pixel")
    p.add_argument("--beta", type=float, default=0.01, help="Levy step size (seed 6.2.5: 0.01)")
    p.add_argument("--pc", type=float, default=0.4, help="abandonment probability p_c (seed 6.2.5: 0.4)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the search")
    p.add_argument("--prior-weight", type=float, default=None, help="pull toward the network's normals (None: the search's default)")
    p.add_argument("--max-size", type=int, default=512, help="downscale images whose longer side exceeds this")
    p.add_argument("--tta", choices=["none", "flips", "dihedral"], default="flips",
                   help="the network's test-time augmentation: mean over the mirror images (flips), and their transposes")
    p.add_argument("--weights", default=None,
                   help="the single-image network's weights file (.npz, as training/train_single.py writes); default: the shipped one")
    p.add_argument("--min-explained", type=float, default=0.5,
                   help="keep the network's normal where the refined model explains less of a pixel's observations")
    p.set_defaults(func=run)


def _read(path: str) -> np.ndarray:
    if not Path(path).is_file():
        raise FileNotFoundError(f"images: file not found: {path}")
    return read_image(path)


def _normal_png(n, mask):
    return np.where(mask[..., None], (n + 1.0) / 2.0, 0.0)


def run(args) -> int:
    if len(args.images) not in (1, 2, 3):
        raise ValueError(f"images: expected 1 to 3 images, got {len(args.images)}")
    inputs = [*args.images, args.mask]
    out_dir = prepare_out(args, inputs=inputs)
    net = gpps.SingleNet.load(args.weights)  # before any work: a missing or wrong file is reported first
    imgs = [_read(p) for p in args.images]
    if any(i.shape[:2] != imgs[0].shape[:2] for i in imgs):
        raise ValueError(f"images: expected one size, got {[i.shape[:2] for i in imgs]}")
    imgs = [np.repeat(i[..., None], 3, -1) if i.ndim == 2 else i[..., :3] for i in imgs]
    mask = read_mask(args.mask) if args.mask else None
    h, w = imgs[0].shape[:2]
    if mask is not None and mask.shape != (h, w):
        raise ValueError(f"mask: expected shape {(h, w)} matching the images, got {mask.shape}")
    s = min(1.0, args.max_size / max(h, w))
    if s < 1.0:
        size = (round(w * s), round(h * s))
        imgs = [cv2.resize(i, size, interpolation=cv2.INTER_AREA) for i in imgs]
        if mask is not None:
            mask = cv2.resize(mask.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
    with as_options("nests", "generations", "beta", "seed", "rounds", "prior_weight", "min_explained", p_c="--pc"):
        cfg = gpps.SingleConfig(
            cuckoo=gpps.CuckooConfig(nests=args.nests, generations=args.generations, beta=args.beta, p_c=args.pc,
                                     seed=args.seed),
            rounds=args.rounds, prior_weight=args.prior_weight, tta=args.tta, min_explained=args.min_explained,
        )
    device = None if args.device == "auto" else args.device
    res = gpps.reconstruct_single(imgs, mask, config=cfg, device=device, net=net, progress=bar("single"))
    m = res.mask
    cam = Orthographic(1.0)
    conv = depth_convention(cam)
    depth = None
    if res.depth is not None:  # the network's depth is in units of half the longer image side: to pixels
        depth = apply_depth_convention(np.asarray(res.depth, np.float64) * (max(m.shape) / 2.0), m, conv)
    with atomic_dir(out_dir, overwrite=args.overwrite, inputs=inputs, name="--out") as out:
        written = write_outputs(out, normals=res.normals, albedo=res.albedo, mask=m, depth=depth, depth_mask=m,
                                camera=cam, depth_info=conv)
        save_npy(out / "normals_net.npy", res.normals_net)
        save_png(out / "normals_net.png", _normal_png(res.normals_net, m), bits=16)
        save_npy(out / "height_net.npy", res.height_net)
        report = {
            "images": [str(p) for p in args.images], "shape": list(m.shape), "pixels": int(m.sum()),
            "config": {"rounds": cfg.rounds, "nests": args.nests, "generations": args.generations, "beta": args.beta,
                       "p_c": args.pc, "seed": args.seed, "prior_weight": cfg.prior_weight},
            "light_directions": res.light_directions, "light_intensities": res.light_intensities, "ks": res.ks,
            "network": {"weights": args.weights or "shipped", **{k: net.meta.get(k) for k in ("widths", "steps", "val_maen_deg")}},
            "shininess": res.shininess, "highlights": res.highlights, "objective": res.objective, "timings_s": res.timings,
            "view": written.get("view"), "depth": conv, "outputs": written["files"] + ["normals_net.npy", "normals_net.png", "height_net.npy"],
        }
        if "view_fallback_reason" in written:
            report["view_fallback_reason"] = written["view_fallback_reason"]
        report["warnings"] = warning_messages(args)
        save_json(out / "report.json", report)
    print(f"single: {int(m.sum())} pixels, {len(imgs)} image(s), {res.timings.get('total', 0):.1f} s -> {args.out}")
    return 0
