"""A per-process pool of Warp device buffers, so that stages of one size reuse theirs across objects.

A stage takes its buffers with :meth:`gpps.pipeline.stage.Stage._buffer` and gives them back at
:meth:`~gpps.pipeline.stage.Stage.close`; the next stage that asks for the same ``(device, shape, dtype)``
gets one of them back, zeroed (or filled) as a new one would be.  A process that reconstructs many captures
of one size (``gpps batch``'s workers, a loop over folders) thus allocates its buffers once, as the
integrators' Taichi fields already are (:mod:`gpps.pipeline.integration`'s pool).  At most
:data:`MAX_PER_KEY` free buffers are kept per key; :func:`clear` drops them (e.g. before a change of size).

A buffer given back must not be used by its old owner: a closed stage refuses work (``Stage`` protocol).
"""

from __future__ import annotations

import threading

from gpps._runtime import warp

__all__ = ["take", "give", "clear", "stats", "MAX_PER_KEY"]

MAX_PER_KEY = 4  # free buffers kept per (device, shape, dtype)

_LOCK = threading.Lock()
_FREE: dict = {}
_COUNTS = {"taken": 0, "reused": 0, "given": 0, "dropped": 0}


def _key(shape, dtype, device) -> tuple:
    shp = (int(shape),) if isinstance(shape, int) else tuple(int(s) for s in shape)
    return str(device), shp, dtype


def take(shape, dtype, device, fill=0):
    """A ``wp.array`` of ``shape`` and ``dtype`` on ``device`` holding ``fill`` everywhere (0: zeros): a free
    one of the pool when there is one, else a new one."""
    wp = warp()
    key = _key(shape, dtype, device)
    with _LOCK:
        free = _FREE.get(key)
        a = free.pop() if free else None
        _COUNTS["taken"] += 1
        if a is not None:
            _COUNTS["reused"] += 1
    if a is None:
        return wp.zeros(key[1], dtype=dtype, device=device) if fill == 0 else wp.full(key[1], fill, dtype=dtype,
                                                                                       device=device)
    if fill == 0:
        a.zero_()
    else:
        a.fill_(fill)
    return a


def give(arrays) -> None:
    """Give buffers back (those of a closed stage); past :data:`MAX_PER_KEY` free ones a key drops them."""
    with _LOCK:
        for a in arrays:
            key = _key(a.shape, a.dtype, a.device)
            free = _FREE.setdefault(key, [])
            _COUNTS["given"] += 1
            if len(free) < MAX_PER_KEY and all(b is not a for b in free):
                free.append(a)
            else:
                _COUNTS["dropped"] += 1


def clear(device=None) -> None:
    """Drop the free buffers (of ``device``; None: of every device)."""
    with _LOCK:
        for key in [k for k in _FREE if device is None or k[0] == str(device)]:
            del _FREE[key]


def stats() -> dict:
    """Counts since the process started (``taken``, ``reused``, ``given``, ``dropped``) and ``free`` buffers now."""
    with _LOCK:
        return dict(_COUNTS, free=sum(len(v) for v in _FREE.values()))
