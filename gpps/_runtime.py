"""Lazy, once-per-process initialisation of Warp and device selection.

Warp is initialised on first use, never at import of :mod:`gpps`, so that
``import gpps`` is cheap and so that callers (tests, CI, the CLI) can choose
the kernel cache folder first.  The cache folder is taken, in order, from
``GPPS_CACHE_DIR`` (``<dir>/warp``), ``WARP_CACHE_PATH`` or Warp's default.
"""

from __future__ import annotations

import os
import sys
import tempfile
import threading

_lock = threading.Lock()
_wp = None


def warp():
    """Return the initialised ``warp`` module (initialising it once)."""
    global _wp
    if _wp is not None:
        return _wp
    with _lock:
        if _wp is None:
            import warp as wp  # lazy by design: `import gpps` stays cheap and callers set the cache folder first

            wp.config.log_level = wp.LOG_WARNING
            wp.config.quiet = True
            cache = os.environ.get("GPPS_CACHE_DIR")
            if cache:
                wp.config.kernel_cache_dir = os.path.join(cache, "warp")
            elif os.environ.get("WARP_CACHE_PATH"):
                wp.config.kernel_cache_dir = os.environ["WARP_CACHE_PATH"]
            _init_quietly(wp)
            _wp = wp
    return _wp


# printed by Warp's native library (fprintf to stderr, not Python's) on every machine without an NVIDIA driver:
# not a problem there (gpps runs on the CPU), so it is dropped; anything else Warp prints is passed on
_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def _init_quietly(wp) -> None:
    """``wp.init()`` with the native "no CUDA driver" warning filtered out of stderr (fd 2)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):  # no real fd 2 (embedded interpreters)
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        try:
            os.dup2(tmp.fileno(), 2)
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode("utf-8", "replace")
    rest = "".join(line for line in text.splitlines(keepends=True) if _NO_DRIVER not in line)
    if rest:
        sys.stderr.write(rest)
        sys.stderr.flush()


def available_devices() -> list[str]:
    """Names of the Warp devices present: always ``"cpu"``, plus ``"cuda:i"``."""
    wp = warp()
    return [str(d) for d in wp.get_devices()]


def resolve_device(device: str | None = None) -> str:
    """Return a Warp device name.

    Args:
        device: ``None`` or ``"auto"`` picks ``"cuda:0"`` when Warp sees a CUDA
            device and ``"cpu"`` otherwise; ``"cpu"``, ``"cuda"`` or
            ``"cuda:N"`` are checked against the devices present.

    Raises:
        ValueError: the requested device does not exist here.
    """
    wp = warp()
    if device is None or device == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    if not isinstance(device, str):
        device = str(device)
    if device == "cuda":
        device = "cuda:0"
    names = available_devices()
    if device not in names:
        raise ValueError(f"device: expected one of {names} or 'auto', got {device!r}")
    return device


def block_lanes(device: str, lanes: int) -> int:
    """The threads a block of ``lanes`` gets on ``device``: ``lanes`` on CUDA; on the CPU 1, unless
    ``warp.config.enable_cpu_blocks`` (Warp runs a CPU block as one thread otherwise).  Launch a tiled kernel
    over ``(..., block_lanes(...))`` with that ``block_dim``, so that each block is one pixel's lanes."""
    if str(device).startswith("cuda") or warp().config.enable_cpu_blocks:
        return int(lanes)
    return 1
