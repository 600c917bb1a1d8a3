"""The ``gpps`` command line (also ``python -m gpps``).

Each subcommand lives in its own module of this package with a
``register(subparsers)`` function that adds its parser and sets
``func=handler(args) -> int``.  Only the CLI prints; library code reports
progress through callbacks, which :func:`gpps.cli._progress.bar` shows.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import sys
import warnings

import gpps
from gpps.cli import _progress

# Subcommand modules, in the order they appear in --help.
SUBCOMMANDS = ["render", "reconstruct", "batch", "calibrate-lights", "integrate", "stream", "demo", "single"]


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Shows every option's default (except where the help text already states it, for flags
    (store_true) and for ``None`` defaults, whose help says what happens then); descriptions and epilogs keep their lines."""

    def _get_help_string(self, action):
        h = action.help or ""
        if "default" in h.lower() or action.default in (None, False, argparse.SUPPRESS) or isinstance(action, argparse._VersionAction):
            return h
        if action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return h + " (default: %(default)s)"
        return h


class _Parser(argparse.ArgumentParser):
    def __init__(self, *a, **k):
        k.setdefault("formatter_class", HelpFormatter)
        super().__init__(*a, **k)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="gpps",
        description="Generalized perspective photometric stereo: normals, albedo and depth from a few images.",
    )
    parser.add_argument("--version", action="version", version=f"gpps {gpps.__version__}", help="print the version and exit")
    parser.add_argument("--device", default="auto", help="Warp/Taichi device: auto (CUDA if present), cpu, cuda:0 ...")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress and no summary lines (errors, warnings and --json output still shown)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in SUBCOMMANDS:
        mod_name = name.replace("-", "_")
        try:
            mod = importlib.import_module(f"gpps.cli.{mod_name}")
        except ModuleNotFoundError as e:  # a subcommand not built yet
            if e.name == f"gpps.cli.{mod_name}":
                continue
            raise
        mod.register(sub)
    for p in sub.choices.values():  # also accepted after the command: gpps reconstruct DIR --quiet
        p.add_argument("--quiet", "-q", action="store_true", default=argparse.SUPPRESS,
                       help="no progress and no summary lines (errors, warnings and --json output still shown)")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one subcommand; returns the exit status.

    0 on success; 2 for bad input, a refused ``--out`` or an input too large for the
    memory (one line on stderr, no traceback); 130 when interrupted (nothing
    half-written is left behind).
    :class:`gpps.GppsWarning` warnings are collected into ``args.warnings`` (the
    commands copy them into report.json) and printed on stderr.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    _progress.configure(quiet=args.quiet)
    quiet_out = args.quiet and not getattr(args, "json", False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", gpps.GppsWarning)
        args.warnings = caught
        try:
            with contextlib.redirect_stdout(io.StringIO()) if quiet_out else contextlib.nullcontext():
                status = int(args.func(args) or 0)
        except KeyboardInterrupt:
            print(f"gpps {args.command}: interrupted; nothing was written", file=sys.stderr)
            status = 130
        except (ValueError, TypeError, OSError) as e:
            print(f"gpps {args.command}: error: {e}", file=sys.stderr)
            status = 2
        except MemoryError as e:  # (an input too large for this machine: say so in one line, leave nothing)
            print(f"gpps {args.command}: error: not enough memory ({e or 'MemoryError'}): try smaller inputs "
                  "(--size, --max-size) or another device", file=sys.stderr)
            status = 2
    counts: dict = {}  # each distinct GppsWarning once, with how often it was issued
    for w in caught:
        if issubclass(w.category, gpps.GppsWarning):
            counts[str(w.message)] = counts.get(str(w.message), 0) + 1
        else:
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    for msg, k in counts.items():
        print(f"gpps {args.command}: warning: {msg}" + (f" ({k} times)" if k > 1 else ""), file=sys.stderr)
    return status


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
