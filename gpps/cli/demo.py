"""``gpps demo``: the main job on an embedded scene, end to end."""

from __future__ import annotations

import time

import gpps
from gpps.cli._output import prepare_out
from gpps.cli._progress import bar


def register(sub):
    p = sub.add_parser("demo", help="render an embedded perspective Cook-Torrance scene under near point lights and reconstruct it with the pipeline")
    p.add_argument("--out", default="gpps_demo", help="output folder: the capture, the outputs, report.json (default gpps_demo); "
                                                      "must be new, empty, or an earlier gpps output (with --overwrite)")
    p.add_argument("--overwrite", action="store_true", help="replace --out when it holds an earlier gpps output")
    p.add_argument("--size", type=int, default=256, help="image size of the rendered scene (pixels)")
    p.set_defaults(func=run)


def run(args) -> int:
    t0 = time.perf_counter()
    out = prepare_out(args)
    report = gpps.run_demo(out, size=args.size, device=args.device, progress=bar("demo"), overwrite=args.overwrite)
    for k, v in report["summary"].items():
        print(f"{k:>28}: {v}")
    print(f"wrote {args.out} in {time.perf_counter() - t0:.1f} s")
    return 0
