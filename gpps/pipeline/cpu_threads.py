"""Warp launches on the CPU split across threads.

Warp 1.19's CPU backend runs a launch on one thread, but it releases the GIL while the kernel runs (the
launch is a ctypes call), so launches on disjoint parts of the problem from several Python threads run on
several cores.  The stages split only their per-pixel solves this way (the work that dominates on the
CPU): :class:`gpps.pipeline.solver.PixelSolver` by image rows (``SolverParams.row0``), balanced by the
mask's pixel count, and :class:`gpps.pipeline.material.MaterialScorer` by sample pixels.  Every pixel's
result is the same as in one launch (each thread writes only its own pixels).

The thread count is ``GPPS_CPU_THREADS`` when set (1 disables the split), else the cores this process
may run on.

Also :func:`run_reporting` (any device): a task on a helper thread while the caller's progress keeps moving (a
kernel module's first compile).
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Callable, Sequence

import numpy as np

from gpps import _fpenv
from gpps._runtime import warp
from gpps.pipeline.prefetch import settle

__all__ = ["cpu_threads", "run_all", "submit", "balanced_bounds", "load_first", "run_reporting"]

_POOL: ThreadPoolExecutor | None = None
_PREFIX = "gpps-cpu"
_POOL_LOCK = threading.Lock()


def cpu_threads() -> int:
    """Threads for CPU launches: ``GPPS_CPU_THREADS`` (an integer >= 1) or the usable cores."""
    env = os.environ.get("GPPS_CPU_THREADS")
    if env:
        try:
            n = int(env)
        except ValueError:
            raise ValueError(f"GPPS_CPU_THREADS: expected an integer >= 1, got {env!r}") from None
        if n < 1:
            raise ValueError(f"GPPS_CPU_THREADS: expected an integer >= 1, got {env!r}")
        return n
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def load_first(kernel, device, block_dim: int | None = None) -> None:
    """Compile / load the Warp module of ``kernel`` (a kernel or a module) on this thread, the variant for launches
    of ``block_dim`` (None: Warp's default), before launches from several threads race to (after a helper's compile
    of it ahead, if one is running: :func:`gpps.pipeline.prefetch.settle`)."""
    settle((kernel, block_dim), device)
    warp().load_module(getattr(kernel, "module", kernel), device=device, block_dim=block_dim)


def run_reporting(task: Callable[[], None], report: Callable[[float], None] | None, every: float = 1.0) -> None:
    """``task()`` on a helper thread while this thread calls ``report(elapsed seconds)`` every ``every`` seconds
    until it ends, then raises here what it raised.  For work that holds no progress of its own (a kernel module's
    first compile: seconds on the CPU, minutes on CUDA) so that the caller's progress keeps moving, and the
    callback keeps being called on the caller's thread.  Without ``report``: ``task()`` on this thread.

    (Warp loads modules from its own worker threads too: ``warp.load_module(..., max_workers=)``.)
    """
    if report is None:
        task()
        return
    box: dict = {}

    def run():
        try:
            task()
        except BaseException as e:  # (re-raised on the caller's thread)
            box["error"] = e

    t0 = time.perf_counter()
    worker = threading.Thread(target=run, name="gpps-load", daemon=True)
    worker.start()
    while True:
        worker.join(every)
        if not worker.is_alive():
            break
        report(time.perf_counter() - t0)
    if "error" in box:
        raise box["error"]


def _in_env(task, env):
    """``task`` run under the floating-point environment ``env`` (the caller's)."""
    def run():
        _fpenv.set_env(env)
        return task()
    return run


def _pool() -> ThreadPoolExecutor:
    """The shared pool, of :func:`cpu_threads` workers (made again when that count changed)."""
    global _POOL
    n = cpu_threads()
    with _POOL_LOCK:
        if _POOL is None or _POOL._max_workers != n:  # noqa: SLF001 - size check only
            _POOL = ThreadPoolExecutor(max_workers=n, thread_name_prefix=_PREFIX)
        return _POOL


def _in_pool() -> bool:
    """Whether this thread is one of the shared pool's (its tasks then run their parts in line: a worker that
    waited on parts queued behind it could wait for ever once every worker waits)."""
    return threading.current_thread().name.startswith(_PREFIX)


def run_all(tasks: Sequence[Callable[[], None]]) -> None:
    """Run the tasks, concurrently on the shared pool when there are several; re-raise the first error.

    Each task runs under the caller's floating-point environment (:mod:`gpps._fpenv`): a thread inherits the
    mode of the thread that made it, so pool threads made while another mode was on (Taichi's initialisation
    turns flush-to-zero on in its thread, or a caller's own setting) rounded denormal results otherwise, and
    which thread ran which part depended on timing (normals 7e-40 against 0 on 343 pixels of a rendered
    capture, run to run under load).  A split launch computes what one launch on the calling thread
    computes, bit for bit.  Called from a task of the pool (:func:`submit`), the tasks run one after another
    on that thread.
    """
    if len(tasks) <= 1 or _in_pool():
        for t in tasks:
            t()
        return
    pool = _pool()
    env = _fpenv.get()
    for f in [pool.submit(_in_env(t, env)) for t in tasks]:
        f.result()


def submit(fn: Callable, *args, **kwargs) -> Future:
    """``fn(*args, **kwargs)`` on the shared pool, under the caller's floating-point environment (as
    :func:`run_all`'s tasks): host work that overlaps the caller's.  Returns its future; called from a task of the
    pool, ``fn`` runs in line and the future comes back done (as :func:`run_all`: no wait on a queued job)."""
    if _in_pool():
        done: Future = Future()
        try:
            done.set_result(fn(*args, **kwargs))
        except BaseException as e:  # (raised by result(), as from the pool)
            done.set_exception(e)
        return done
    return _pool().submit(_in_env(lambda: fn(*args, **kwargs), _fpenv.get()))


def balanced_bounds(weights, parts: int) -> list[tuple[int, int]]:
    """Split ``range(len(weights))`` into at most ``parts`` contiguous, non-empty ranges of about equal weight.

    Args:
        weights: (R,) non-negative work per item (e.g. mask pixels per image row).
        parts: the most ranges to return (>= 1).

    Returns:
        ``[(a, b), ...]`` covering ``0..R`` in order; ranges with no weight are merged into their neighbours.
    """
    w = np.asarray(weights, np.float64)
    r = w.size
    if r == 0:
        return []
    total = float(w.sum())
    if parts <= 1 or total <= 0:
        return [(0, r)]
    cum = np.cumsum(w)
    cuts = np.searchsorted(cum, total * np.arange(1, parts) / parts, side="left") + 1
    edges = np.unique(np.concatenate([[0], np.clip(cuts, 1, r), [r]]))
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b > a]
