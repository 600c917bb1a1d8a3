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

import gpps
import gpps.io
from gpps.cli._output import add_output_args, as_options, prepare_out, warning_messages
from gpps.cli._progress import bar


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


def run(args) -> int:
    """Calibrate with :func:`gpps.calibrate_lights` and write the light files into ``--out``."""
    inputs = [i for i in (args.dir, args.chrome_mask, args.K) if i is not None]
    out = prepare_out(args, inputs=inputs)
    with as_options("chrome", "chrome_mask", "sphere_radius", "min_contrast", "matte", "card"):
        cal = gpps.calibrate_lights(
            args.dir, chrome=args.chrome, chrome_mask=args.chrome_mask, sphere_radius=args.sphere_radius,
            matte=args.matte, card=args.card, card_normal=args.card_normal, K=args.K, transfer=args.transfer,
            ambient=args.ambient, min_contrast=args.min_contrast, progress=bar("calibrate"), read_progress=bar("read"),
        )
    with gpps.io.atomic_dir(out, overwrite=args.overwrite, inputs=inputs, name="--out") as tmp:
        report = cal.write(tmp, warnings=warning_messages(args))
    if args.json:
        print(json.dumps(report, indent=2, default=gpps.io.json_default))
    else:
        print(f"wrote {out}: {len(cal.directions)} light directions ({len(cal.spheres)} mirror sphere(s), outline {cal.outlines[0]}), "
              f"intensities: {cal.intensities_from}" + (", positions" if cal.positions is not None else ""))
    return 0
