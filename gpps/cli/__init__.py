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
import warnings

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
    """Run one subcommand; returns the exit status.

    0 on success; 2 for bad input or a refused ``--out`` (one line on stderr, no
    traceback); 130 when interrupted (nothing half-written is left behind).
    :class:`gpps.GppsWarning` warnings are collected into ``args.warnings`` (the
    commands copy them into report.json) and printed on stderr.
    """
    from gpps._check import GppsWarning

    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", GppsWarning)
        args.warnings = caught
        try:
            status = int(args.func(args) or 0)
        except KeyboardInterrupt:
            print(f"gpps {args.command}: interrupted; nothing was written", file=sys.stderr)
            status = 130
        except (ValueError, TypeError, OSError) as e:
            print(f"gpps {args.command}: error: {e}", file=sys.stderr)
            status = 2
    for w in caught:
        if issubclass(w.category, GppsWarning):
            print(f"gpps {args.command}: warning: {w.message}", file=sys.stderr)
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
