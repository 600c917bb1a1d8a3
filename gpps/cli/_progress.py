"""A terminal progress bar fed by the library's progress callbacks."""

from __future__ import annotations

import sys
import time


class Bar:
    """Callable ``bar(done, total, message="")`` drawing a one-line bar on stderr."""

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


def bar(label: str = "") -> Bar:
    return Bar(label)
