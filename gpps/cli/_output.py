"""The rules every writing command follows for ``--out`` (checked before any computing)."""

from __future__ import annotations

from pathlib import Path

from gpps.io import check_output_dir


def add_output_args(p, help: str) -> None:
    """Add ``--out`` (required) and ``--overwrite`` to a subcommand's parser."""
    p.add_argument("--out", required=True,
                   help=help + "; must be new, empty, or an earlier gpps output (with --overwrite). "
                               "Written to a temporary sibling and renamed: complete or absent")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it holds an earlier gpps output (never other files)")


def prepare_out(args, inputs=()) -> Path:
    """Check ``args.out`` against the command's inputs before computing; the resolved path."""
    return check_output_dir(args.out, inputs=[i for i in inputs if i is not None], overwrite=args.overwrite,
                            name="--out")


def warning_messages(args) -> list[str]:
    """The :class:`gpps.GppsWarning` messages issued so far by this command (for report.json)."""
    from gpps._check import GppsWarning

    return [str(w.message) for w in getattr(args, "warnings", []) if issubclass(w.category, GppsWarning)]
