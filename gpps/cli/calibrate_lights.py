"""``gpps calibrate-lights DIR --out LIGHTS``: light directions (and intensities, positions) from images of spheres.

DIR holds one image per light (any format ``gpps reconstruct`` reads; same
order rules: filenames.txt, else sorted names) of a mirror (chrome) sphere,
optionally with a matte (Lambertian) sphere or a grey card in view, and
optionally ``K.txt`` (perspective camera).  Where things are:

* the mirror sphere: ``--chrome CX CY R`` (a circle, pixels), or a mask image
  ``chrome_mask.png`` in DIR (or ``--chrome-mask FILE``), else found in the
  images (the median over the lights shows the sphere against the background).
  A second ``--chrome`` (or a second blob in the mask) with ``--sphere-radius``
  and K.txt gives near-light positions.
* the matte sphere: ``--matte CX CY R`` or ``matte_mask.png``; the grey card:
  ``--card X0 Y0 X1 Y1`` or ``card_mask.png`` (normal ``--card-normal``,
  default facing the camera).  Either gives relative RGB intensities.

Writes into LIGHTS: ``light_directions.txt`` (N x 3, gpps frame: x right,
y up, z toward the camera; toward the lights), ``light_intensities.txt``
(N x 3, relative, mean 1; ones without a matte sphere or card),
``light_positions.txt`` (two spheres of known radius), ``filenames.txt``
(the calibration images, in order) and ``calibration.json``.  Copy the light
files into the object's folder, or pass ``--lights LIGHTS`` to ``gpps
reconstruct``: the object's images must be in the same light order.
"""

from __future__ import annotations

import json
from pathlib import Path

from gpps.cli._output import add_output_args, prepare_out, warning_messages


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate-lights", help="light directions/intensities/positions from images of a mirror sphere (+ matte sphere or grey card)",
                              description=__doc__.splitlines()[0], epilog="\n".join(__doc__.splitlines()[2:]),
                              )
    p.add_argument("dir", help="folder of calibration images, one per light (and K.txt for a perspective camera)")
    add_output_args(p, "output folder for the light files and calibration.json")
    p.add_argument("--chrome", nargs=3, type=float, action="append", metavar=("CX", "CY", "R"), default=None,
                   help="mirror sphere outline as a circle in pixels (repeat for a second sphere); default: chrome_mask.* in DIR, else found in the images")
    p.add_argument("--chrome-mask", default=None, help="mask image of the mirror sphere(s) (one blob each); default: DIR/chrome_mask.* if present")
    p.add_argument("--sphere-radius", type=float, nargs="+", default=None,
                   help="the mirror spheres' radii (scene units, one per sphere or one for all): with two spheres and K.txt, near-light positions")
    p.add_argument("--matte", nargs=3, type=float, metavar=("CX", "CY", "R"), default=None,
                   help="matte (Lambertian) sphere outline in pixels, for intensities; default: DIR/matte_mask.* if present")
    p.add_argument("--card", nargs=4, type=int, metavar=("X0", "Y0", "X1", "Y1"), default=None,
                   help="grey card rectangle in pixels (columns X0..X1, rows Y0..Y1), for intensities; default: DIR/card_mask.* if present")
    p.add_argument("--card-normal", nargs=3, type=float, default=[0.0, 0.0, 1.0], metavar=("NX", "NY", "NZ"),
                   help="the card's normal, gpps frame")
    p.add_argument("--K", dest="K", default=None, help="3x3 intrinsics text file (default: DIR/K.txt if present; else orthographic)")
    p.add_argument("--transfer", default="auto", choices=["auto", "linear", "srgb"], help="images' transfer curve (auto: sRGB decoded for JPEG only)")
    p.add_argument("--ambient", default="auto", help="image with the lights off, subtracted: 'auto' (*ambient* in DIR), 'none' or a file")
    p.add_argument("--min-contrast", type=float, default=3.0, help="a highlight's peak must exceed the sphere's median by this factor")
    p.add_argument("--json", action="store_true", help="print calibration.json on stdout (progress stays on stderr)")
    p.set_defaults(func=run)


def _mask_file(root: Path, stem: str, given: str | None):
    from gpps.io.capture import _find_side

    if given:
        p = Path(given)
        if not p.is_file():
            raise FileNotFoundError(f"--{stem.replace('_', '-')}: file not found: {p}")
        return p
    return _find_side(root, stem)


def _read_mask(path, shape):
    import numpy as np

    from gpps.io.formats import read_image_file

    m, _ = read_image_file(path, transfer="linear")
    m = np.any(m > 0.5, axis=-1)
    if m.shape != shape:
        raise ValueError(f"{path}: expected a mask of shape {shape}, got {m.shape}")
    return m


def run(args) -> int:
    import numpy as np
    from scipy import ndimage

    from gpps.host.calibrate import (_disc_mask, card_intensities, circle_points, find_outline, fit_sphere,
                                highlight_direction, mask_outline, matte_intensities, triangulate_lights)
    from gpps.camera import Orthographic, camera_from_K
    from gpps.io.capture import read_capture
    from gpps.cli._progress import bar
    from gpps.io import atomic_dir, read_K, save_json, save_txt

    root = Path(args.dir)
    inputs = [args.dir, args.chrome_mask, args.K]
    out = prepare_out(args, inputs=inputs)
    # no object here: read with the mask "none" (no mask file, no automatic mask)
    cap = read_capture(root, transfer=args.transfer, ambient=None if args.ambient == "none" else args.ambient,
                       mask="none", normalise=False, progress=bar("read"))
    ds = cap.dataset
    images = ds.images
    n, h, w = images.shape[:3]
    if args.K:
        K = read_K(args.K)
    else:
        K = ds.K
    camera = camera_from_K(K) if K is not None else Orthographic()
    report = {"dir": str(root), "images": n, "shape": [h, w], "camera": camera.kind, "filenames": ds.filenames,
              "formats": cap.formats, "ambient_subtracted": cap.ambient}
    prog = bar("calibrate")
    # --- mirror spheres
    fits, sources = [], []
    chrome_mask = _mask_file(root, "chrome_mask", args.chrome_mask) if not args.chrome else None
    if args.chrome:
        for cx, cy, r in args.chrome:
            fits.append(fit_sphere(circle_points(cx, cy, r), camera))
            sources.append("given circle")
    elif chrome_mask is not None:
        m = _read_mask(chrome_mask, (h, w))
        lab, k = ndimage.label(m)
        if k == 0:
            raise ValueError(f"{chrome_mask}: the mask is empty")
        sizes = np.bincount(lab.ravel())[1:]
        for idx in np.argsort(sizes)[::-1]:
            if sizes[idx] < 0.2 * sizes.max():
                break
            fits.append(fit_sphere(mask_outline(lab == idx + 1), camera))
            sources.append(f"mask {chrome_mask.name}")
    else:
        pts, _ = find_outline(images)
        fits.append(fit_sphere(pts, camera))
        sources.append("found in the images")
    radii = None
    if args.sphere_radius:
        radii = list(args.sphere_radius) * (len(fits) if len(args.sphere_radius) == 1 else 1)
        if len(radii) != len(fits) or min(radii) <= 0:
            raise ValueError(f"--sphere-radius: expected one radius > 0 or one per sphere ({len(fits)}), got {args.sphere_radius}")
        for f, r in zip(fits, radii):
            f.radius = float(r)
    dirs = np.full((len(fits), n, 3), np.nan)
    cents = np.full((len(fits), n, 2), np.nan)
    per = []
    for s, f in enumerate(fits):
        region = _disc_mask(f, (h, w), shrink=1.0)
        rows = []
        for k in range(n):
            l, info = highlight_direction(f, images[k], region, min_contrast=args.min_contrast)
            if l is not None:
                dirs[s, k] = l
                cents[s, k] = info["centroid"]
            rows.append({"file": ds.filenames[k], **{kk: vv for kk, vv in info.items()}})
            prog(s * n + k + 1, len(fits) * n, f"sphere {s + 1}: {ds.filenames[k]}")
        per.append({"outline": sources[s], **f.to_dict(), "highlights": rows})
    report["spheres"] = per
    found = np.all(np.isfinite(dirs), -1)
    missing = [ds.filenames[k] for k in range(n) if not found[:, k].any()]
    if missing:
        raise ValueError(f"images: no highlight on the mirror sphere in {', '.join(missing)} (light behind the sphere, off, or too weak: see --min-contrast)")
    mean_dir = np.nanmean(dirs, 0)
    mean_dir /= np.linalg.norm(mean_dir, axis=1, keepdims=True)
    if len(fits) > 1:
        spread = [float(np.degrees(np.arccos(np.clip(dirs[0, k] @ dirs[1, k], -1, 1)))) for k in range(n)]
        report["direction_difference_between_spheres_deg"] = spread
    positions = None
    if len(fits) >= 2 and radii is not None and camera.is_perspective:
        positions, tri = triangulate_lights(fits, list(cents), radii)
        report["triangulation"] = tri
        ang = np.asarray(tri["ray_angle_deg"])
        if np.any(~np.isfinite(ang)) or np.median(ang) < 1.0:
            report["triangulation"]["note"] = ("the reflected rays are nearly parallel (median angle "
                                               f"{np.nanmedian(ang):.2f} deg): the lights are too far for positions; only directions written")
            positions = None
    elif len(fits) >= 2 and radii is not None:
        report["triangulation"] = {"note": "positions need a perspective camera (K.txt)"}
    # --- intensities
    intens = np.ones((n, 3))
    intens_src = "none (ones): no matte sphere or grey card"
    matte_mask = _mask_file(root, "matte_mask", None) if args.matte is None else None
    card_mask = _mask_file(root, "card_mask", None) if args.card is None else None
    if args.matte is not None or matte_mask is not None:
        if args.matte is not None:
            mf = fit_sphere(circle_points(*args.matte), camera)
        else:
            mf = fit_sphere(mask_outline(_read_mask(matte_mask, (h, w))), camera)
        intens, info = matte_intensities(images, mf, mean_dir)
        intens_src = "matte sphere"
        report["matte_sphere"] = {**mf.to_dict(), **info}
    elif args.card is not None or card_mask is not None:
        if args.card is not None:
            x0, y0, x1, y1 = args.card
            region = np.zeros((h, w), bool)
            region[min(y0, y1):max(y0, y1) + 1, min(x0, x1):max(x0, x1) + 1] = True
        else:
            region = _read_mask(card_mask, (h, w))
        intens, info = card_intensities(images, region, mean_dir, args.card_normal)
        intens_src = "grey card"
        report["grey_card"] = {"normal": list(args.card_normal), **info}
    report["intensities_from"] = intens_src
    report["light_directions"] = mean_dir
    report["light_intensities"] = intens
    if positions is not None:
        report["light_positions"] = positions
    report["warnings"] = warning_messages(args)
    with atomic_dir(out, overwrite=args.overwrite, inputs=[i for i in inputs if i is not None], name="--out") as tmp:
        save_txt(tmp / "light_directions.txt", mean_dir)
        save_txt(tmp / "light_intensities.txt", intens)
        if positions is not None:
            save_txt(tmp / "light_positions.txt", positions)
        (tmp / "filenames.txt").write_text("\n".join(ds.filenames) + "\n")
        save_json(tmp / "calibration.json", report)
    if args.json:
        from gpps.io import _json_default

        print(json.dumps(report, indent=2, default=_json_default))
    else:
        print(f"wrote {out}: {n} light directions ({len(fits)} mirror sphere(s), outline {sources[0]}), intensities: {intens_src}"
              + (", positions" if positions is not None else ""))
    return 0
