"""Kernel modules compiled ahead of their first launch, on helper threads (a first run's compiles overlapped).

A Warp module compiles at its first launch in an installation: seconds a module on the CPU, more on CUDA.  A
reconstruction launches some fifteen modules one after the other, so a first run (an empty kernel cache: a new
install, a new Warp, a changed kernel) spends its compiles one at a time, on one core, between its solves
(DiLiGenT ball on the 2-core development CPU: 22.6 s of a 67 s first run, none of it overlapped; on a fresh H200
machine 536 s, almost all of it compiling).

:class:`KernelPrefetch` takes the modules a run will launch, in the order it will launch them
(:meth:`gpps.flows.ron.RON.kernel_plan`), and compiles each into Warp's kernel cache on a helper thread while
the run goes on.  It only compiles: the stage that launches a kernel still loads its module itself, and finds
the binary in the cache instead of building it.  So a module is never loaded twice, a plan that names a module
the run does not launch costs only that compile, and a run that launches a module the plan lacks compiles it
as before.  Warp builds a module in a directory of its own per thread and moves it into the cache atomically,
so a stage compiling a module the helper is also compiling builds it twice at worst; :func:`settle` (called by
the stages' explicit load points) waits for the helper's build instead.

Compiling without loading needs four of ``warp.Module``'s private methods (Warp is pinned to 1.19 in
``pyproject.toml``); where they are missing the prefetch does nothing and says so in :attr:`KernelPrefetch.skipped`.
The cache is checked the way ``Module.load`` checks it, so a warm cache costs the helper a module hash each.
Measured (``perf/results/s42``, ``s43``): DiLiGenT ball's first run on a fresh H200 machine 536 -> 117 s, on the
2-core CPU 65-69 -> 52.7-53.6 s (with the CPU's module layout of :func:`gpps.kernels.solve.batched_in_solve_module`),
results unchanged bit for bit.
"""

from __future__ import annotations

import os
import threading
import time
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Iterable

from gpps._check import check_number
from gpps._runtime import warp

__all__ = ["KernelPrefetch", "compile_into_cache", "is_loaded", "launch_block_dim", "prefetch_enabled", "settle"]

_ACTIVE: dict = {}  # (id(module), device, block size) -> Future of its compile, until it ends or is cancelled
_ACTIVE_LOCK = threading.Lock()
_LIVE: "weakref.WeakSet[KernelPrefetch]" = weakref.WeakSet()  # (closed at interpreter exit: see _close_at_exit)


def _close_at_exit() -> None:
    """Drop the queued compiles of every helper not closed (a RON or Reconstructor never closed): the interpreter
    otherwise runs a helper's whole queue before it exits (``concurrent.futures`` joins its threads then)."""
    for p in list(_LIVE):
        p.close()


# (threading's exit hooks run last-registered first: this one, registered after concurrent.futures' own, runs
# before it joins the helpers; a Python without the hook leaves the queue to run)
_register = getattr(threading, "_register_atexit", None)
if _register is not None:
    try:
        _register(_close_at_exit)
    except RuntimeError:  # pragma: no cover - (imported during interpreter shutdown)
        pass


def prefetch_enabled() -> bool:
    """Whether runs compile their kernels ahead (``GPPS_PREFETCH``: ``0`` turns it off; on by default)."""
    env = os.environ.get("GPPS_PREFETCH", "1").strip().lower()
    if env in ("0", "off", "false", "no"):
        return False
    if env in ("1", "on", "true", "yes", ""):
        return True
    raise ValueError(f"GPPS_PREFETCH: expected 0 or 1, got {env!r}")


def _module_of(item, name: str = "kernels"):
    """The Warp module of a kernel or a module (None for None); of a ``(kernel, block_dim)`` entry, its kernel's.
    TypeError naming ``name`` for anything else."""
    if isinstance(item, tuple) and len(item) == 2:
        item = item[0]
    if item is None:
        return None
    wp = warp()
    if isinstance(item, wp.Module):
        return item
    module = getattr(item, "module", None)
    if isinstance(module, wp.Module):
        return module
    raise TypeError(f"{name}: expected a Warp kernel or module (or a (kernel, block_dim) pair), got "
                    f"{type(item).__name__}")


def launch_block_dim(device, block_dim: int | None = None) -> int:
    """The block size of the module variant a ``wp.launch(..., block_dim=block_dim)`` on ``device`` loads (Warp's
    rule).

    Args:
        device: a Warp device or its name.
        block_dim: the launch's block size (None or <= 0: Warp's default).

    Returns:
        CUDA: ``block_dim``, or 256.  CPU: 1, unless ``warp.config.enable_cpu_blocks`` is on and ``block_dim`` > 1
        (Warp runs a CPU block as one thread otherwise).
    """
    if str(device).startswith("cpu"):
        on = bool(warp().config.enable_cpu_blocks)
        return int(block_dim) if on and block_dim is not None and int(block_dim) > 1 else 1
    return 256 if block_dim is None or int(block_dim) <= 0 else int(block_dim)


def is_loaded(module, device, block_dim: int | None = None) -> bool:
    """Whether ``module``'s variant for launches of ``block_dim`` (None: Warp's default) on ``device`` is loaded in
    this process (Warp's table of loaded variants, keyed by device context and block size; False when this Warp
    has no such table: a load is then a no-op for a loaded module anyway)."""
    try:
        return (warp().get_device(device).context, launch_block_dim(device, block_dim)) in module.execs
    except AttributeError:
        return False


def _block_dim_of(item) -> int | None:
    return int(item[1]) if isinstance(item, tuple) and len(item) == 2 and item[1] is not None else None


def compile_into_cache(module, device, block_dim: int | None = None) -> bool:
    """Compile ``module`` for ``device`` into Warp's kernel cache unless it is there or loaded; do not load it.

    The variant is the one ``wp.launch(..., block_dim=block_dim)`` loads (:func:`launch_block_dim`).  The cache
    path, output name and options are those ``Module.load`` uses, so its later load finds this binary.

    Args:
        module: a ``warp.Module`` (or a kernel: its module).
        device: a Warp device or its name.
        block_dim: the launches' block size (None: Warp's default).

    Returns:
        True when it compiled, False when the binary was already there (or the module already loaded).

    Raises:
        AttributeError: this Warp lacks the private methods used (:class:`KernelPrefetch` then skips).
    """
    wp = warp()
    module = _module_of(module, "module")
    dev = wp.get_device(device)
    dim = launch_block_dim(dev, block_dim)
    if is_loaded(module, dev, dim):
        return False
    module.get_module_hash(dim)  # (hashes the variant and resolves its options, as Module.load does)
    options = module.resolved_options[dim]
    name_short = module.get_module_identifier(dim)
    module_dir = os.path.join(wp.config.kernel_cache_dir, name_short)
    output_name = module._get_compile_output_name(dev, block_dim=dim)  # noqa: SLF001 - see the module docstring
    output_arch = module._get_compile_arch(dev)  # noqa: SLF001
    return bool(module._compile(dev, module_dir, output_name, output_arch, options=options))  # noqa: SLF001


def settle(kernel_or_module, device) -> None:
    """Before a stage loads a module: wait for a helper's compile of it if one is running; a compile still queued is
    taken off the queue (the caller builds it now).  A no-op otherwise.

    Args:
        kernel_or_module: a Warp kernel or module, or ``(kernel, block_dim)``: the variant of that block size.
        device: the Warp device (or its name) the stage launches on.
    """
    module = _module_of(kernel_or_module, "kernel_or_module")
    if module is None:
        return
    dev = str(warp().get_device(device))
    key = (id(module), dev, launch_block_dim(dev, _block_dim_of(kernel_or_module)))
    with _ACTIVE_LOCK:
        fut = _ACTIVE.get(key)
    if fut is None:
        return
    if not fut.cancel():
        try:
            fut.result()
        except BaseException:  # noqa: BLE001 - the stage's own load reports the failure
            pass


def _drop(key, fut) -> None:
    """``fut`` (ended or cancelled) out of the registry :func:`settle` reads, unless another took its place."""
    with _ACTIVE_LOCK:
        if _ACTIVE.get(key) is fut:
            del _ACTIVE[key]


class KernelPrefetch:
    """Compiles modules into Warp's kernel cache on helper threads, in the order given.

    Args:
        device: the Warp device the run launches on.
        workers: helper threads (default on the CPU: one a core of the CPU's launches (:func:`cpu_threads`), up to
            8.  A run's first modules (least squares' and round 1's solve) are needed at once and compile side by
            side; the later ones share the cores with the solves, which is what one helper did too (DiLiGenT ball's
            first run on the 2-core CPU: 56.2 s with one, 52.7 s with two, ``perf/results/s43``).  On CUDA one a
            host core but the run's own, up to 16: the compiles run on the host's cores while the GPU solves, and
            the longest (a model's whole-image solve, 50-75 s on a fresh H200) should start early.)

    Use: ``pf = KernelPrefetch("cpu"); pf.submit(kernels)``; the stages launch as usual; ``pf.close()`` drops
    what has not started.  Failures are kept (:attr:`failed`), not raised: a stage's own load raises them.
    """

    def __init__(self, device, *, workers: int | None = None):
        wp = warp()
        self.device = str(wp.get_device(device))
        self._context = wp.get_device(device).context
        if workers is None:
            if self.device.startswith("cpu"):
                from gpps.pipeline.cpu_threads import cpu_threads  # (it imports settle from here)

                workers = min(8, cpu_threads())
            else:
                workers = min(16, max(1, (os.cpu_count() or 2) - 1))
        self.workers = check_number("workers", workers, lo=1, integer=True)
        self._pool: ThreadPoolExecutor | None = None
        self._futures: list[tuple[object, Future]] = []
        self._seen: set[tuple] = set()
        self.compiled: list[tuple[str, float]] = []  #: (module name, seconds) of each module it compiled
        self.failed: list[tuple[str, str]] = []  #: (module name, error) of each compile that failed
        self.skipped: str | None = None  #: why nothing is compiled ahead (a Warp without the methods used)
        self._lock = threading.Lock()
        _LIVE.add(self)

    def submit(self, kernels: Iterable) -> int:
        """Queue the modules of ``kernels`` (Warp kernels or modules, or ``(kernel, block_dim)`` for launches of
        that block size; None entries ignored; a module variant once).

        Returns:
            How many modules were queued (a module variant already loaded in this process is not).
        """
        if self.skipped is not None:
            return 0
        queued = 0
        for item in kernels:
            module = _module_of(item)
            if module is None:
                continue
            dim = launch_block_dim(self.device, _block_dim_of(item))
            key = (id(module), self.device, dim)
            if key in self._seen:
                continue
            self._seen.add(key)
            if is_loaded(module, self.device, dim):  # (loaded in this process: a later run's plan costs nothing)
                continue
            if self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=self.workers, thread_name_prefix="gpps-prefetch")
            fut = self._pool.submit(self._build, module, dim)
            with _ACTIVE_LOCK:
                _ACTIVE[key] = fut
            self._futures.append((key, fut))
            queued += 1
        return queued

    def _build(self, module, block_dim: int) -> None:
        if self.skipped is not None:
            return
        t = time.perf_counter()
        try:
            built = compile_into_cache(module, self.device, block_dim)
        except AttributeError as e:  # (a Warp whose Module lacks the private methods used)
            self.skipped = f"this Warp cannot compile without loading ({e})"
            return
        except Exception as e:  # noqa: BLE001 - the stage's own load raises it, where the caller sees it
            with self._lock:
                self.failed.append((module.name, f"{type(e).__name__}: {e}"))
            return
        if built:
            with self._lock:
                self.compiled.append((module.name, time.perf_counter() - t))

    def wait(self) -> None:
        """Block until every queued compile has ended (tests; a run never needs to)."""
        for _, fut in list(self._futures):
            if not fut.cancelled():
                fut.result()

    def close(self) -> None:
        """Drop the compiles that have not started; those running finish on their thread (not waited for here;
        :func:`settle` still waits for them until they end; the interpreter waits for them at exit: at most one
        compile per helper, only on a run that compiled).  Helpers not closed are closed at interpreter exit."""
        for key, fut in self._futures:
            if fut.cancel():
                _drop(key, fut)
            else:
                fut.add_done_callback(lambda f, key=key: _drop(key, f))
        self._futures.clear()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
