"""Progress on stderr, fed by the library's ``progress(done, total, message)`` callbacks.

On a terminal: a one-line bar redrawn in place.  Elsewhere (logs, pipes, CI):
plain lines, one per 10% step or message change at most every 2 s, so logs do
not fill with carriage returns.  ``--quiet`` turns both off.  Progress always
goes to stderr, so ``--json`` output on stdout stays clean.
"""

from __future__ import annotations

import sys
import time

_QUIET = False


def configure(*, quiet: bool = False) -> None:
    """Set once by the CLI's ``main`` from ``--quiet``."""
    global _QUIET
    _QUIET = bool(quiet)


def quiet() -> bool:
    return _QUIET


class Bar:
    """Callable ``bar(done, total, message="")`` drawing a one-line bar on a terminal's stderr."""

    def __init__(self, label: str = "", stream=None, width: int = 30):
        self.label = label
        self.stream = stream or sys.stderr
        self.width = width
        self.t0 = time.perf_counter()
        self._last = 0.0

    def __call__(self, done: float, total: float, message: str = "") -> None:
        now = time.perf_counter()
        if done < total and now - self._last < 0.05:
            return
        self._last = now
        frac = 0.0 if total <= 0 else min(max(done / total, 0.0), 1.0)
        n = int(round(frac * self.width))
        line = f"\r{self.label} [{'#' * n}{'.' * (self.width - n)}] {100 * frac:5.1f}% {now - self.t0:6.1f}s {message}"
        self.stream.write(line[:120].ljust(80))
        if done >= total:
            self.stream.write("\n")
        self.stream.flush()


class Lines:
    """Callable ``lines(done, total, message="")`` writing plain progress lines (for logs)."""

    def __init__(self, label: str = "", stream=None, step: float = 0.1, interval: float = 2.0):
        self.label = label
        self.stream = stream or sys.stderr
        self.step = step
        self.interval = interval
        self.t0 = time.perf_counter()
        self._last_t = -1e9
        self._last_frac = -1.0
        self._last_msg = None

    def __call__(self, done: float, total: float, message: str = "") -> None:
        now = time.perf_counter()
        frac = 0.0 if total <= 0 else min(max(done / total, 0.0), 1.0)
        finished = done >= total
        if not finished:
            if now - self._last_t < self.interval:
                return
            if frac - self._last_frac < self.step and message == self._last_msg:
                return
        if finished and self._last_frac >= 1.0:
            return
        self._last_t, self._last_frac, self._last_msg = now, frac, message
        self.stream.write(f"{self.label}: {100 * frac:5.1f}% {now - self.t0:7.1f}s {message}\n")
        self.stream.flush()


def _silent(done, total, message=""):
    return None


def bar(label: str = ""):
    """The progress callback for a command: a bar on a terminal, plain lines otherwise, nothing with ``--quiet``."""
    if _QUIET:
        return _silent
    stream = sys.stderr
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return Bar(label, stream)
    return Lines(label, stream)
