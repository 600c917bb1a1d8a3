"""The ``gpps`` command line (also ``python -m gpps``).

Each subcommand lives in its own module of this package with a
``register(subparsers)`` function that adds its parser and sets
``func=handler(args) -> int``.  Only the CLI prints; library code reports
progress through callbacks, which :func:`gpps.cli._progress.bar` shows.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# Subcommand modules, in the order they appear in --help.
SUBCOMMANDS = ["render", "reconstruct", "integrate", "stream", "demo", "single"]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gpps",
        description="Generalized perspective photometric stereo: normals, albedo and depth from a few images.",
    )
    parser.add_argument("--device", default="auto", help="Warp/Taichi device: auto (CUDA if present), cpu, cuda:0 ...")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        try:
            mod = importlib.import_module(f"gpps.cli.{name}")
        except ModuleNotFoundError as e:  # a subcommand not built yet
            if e.name == f"gpps.cli.{name}":
                continue
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ValueError, TypeError, FileNotFoundError) as e:
        print(f"gpps {args.command}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
