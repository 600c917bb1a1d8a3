"""The rules every writing command follows for ``--out`` (checked before any computing)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import gpps
import gpps.io


def add_output_args(p, help: str) -> None:
    """Add ``--out`` (required) and ``--overwrite`` to a subcommand's parser."""
    p.add_argument("--out", required=True,
                   help=help + "; must be new, empty, or an earlier gpps output (with --overwrite). "
                               "Written to a temporary sibling and renamed: complete or absent")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out when it holds an earlier gpps output (never other files)")


def prepare_out(args, inputs=()) -> Path:
    """Check ``args.out`` against the command's inputs before computing; the resolved path."""
    return gpps.io.check_output_dir(args.out, inputs=[i for i in inputs if i is not None], overwrite=args.overwrite,
                                    name="--out")


def warning_messages(args) -> list[str]:
    """The distinct :class:`gpps.GppsWarning` messages issued so far by this command, in the order first issued
    (for report.json; a stage that checks the same lights at every step says it once)."""
    seen = [str(w.message) for w in getattr(args, "warnings", []) if issubclass(w.category, gpps.GppsWarning)]
    return list(dict.fromkeys(seen))


@contextlib.contextmanager
def as_options(*names: str, **options: str):
    """Errors that name one of ``names`` first (a library argument or config field: ``"rounds: expected ..."``)
    name the command's option instead (``"--rounds: expected ..."``), as the command's own checks would;
    ``options`` maps arguments whose option is named otherwise (``bilateral_k="--k"``)."""
    try:
        yield
    except (ValueError, TypeError, FileNotFoundError) as e:
        msg = str(e)
        pairs = [(name, "--" + name.replace("_", "-")) for name in names] + list(options.items())
        for name, option in pairs:
            if msg.startswith((name + ":", name + " ")):
                raise type(e)(option + msg[len(name):]) from e
        raise
