"""Lazy, once-per-process initialisation of Taichi on the requested device.

Importing this module imports ``taichi`` (with its banner and version check
silenced) but does not initialise it: :func:`init` does that once, on the
architecture that matches a gpps device string.  Taichi cannot be initialised
twice in one process (a second ``ti.init`` destroys every field), so a later
request for the same architecture returns at once and a request for another
one raises :class:`RuntimeError`.

The offline kernel cache goes to ``$GPPS_CACHE_DIR/taichi`` when
``GPPS_CACHE_DIR`` is set, else Taichi's default.
"""

from __future__ import annotations

import contextlib
import io
import os
import threading

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
os.environ.setdefault("TI_LOG_LEVEL", "warn")
if os.environ.get("GPPS_CACHE_DIR") and "TI_OFFLINE_CACHE_FILE_PATH" not in os.environ:
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = os.path.join(os.environ["GPPS_CACHE_DIR"], "taichi")

import taichi as ti  # noqa: E402

__all__ = ["ti", "init", "current_device", "taichi_device"]

_lock = threading.Lock()
_device: str | None = None  # "cpu" or "cuda:0" once initialised


def taichi_device(device: str | None = "auto") -> str:
    """Map a gpps device string to the one Taichi will run on.

    Args:
        device: ``"auto"``/``None``, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``
            (checked by :func:`gpps._runtime.resolve_device`).

    Returns:
        ``"cpu"`` or ``"cuda:0"``.

    Raises:
        ValueError: the device does not exist, or is a CUDA device other than
            ``cuda:0`` (Taichi uses the first visible GPU; select another one
            with ``CUDA_VISIBLE_DEVICES``).
    """
    if device in (None, "auto"):
        # Once Taichi runs, "auto" means whatever it runs on.
        if _device is not None:
            return _device
    from gpps._runtime import resolve_device

    dev = resolve_device(device)
    if dev.startswith("cuda") and dev != "cuda:0":
        raise ValueError(
            f"device: Taichi runs on the first visible GPU only; expected 'cpu' or 'cuda:0' "
            f"(use CUDA_VISIBLE_DEVICES to pick another GPU), got {device!r}"
        )
    return dev


def init(device: str | None = "auto"):
    """Initialise Taichi once on ``device`` and return the ``taichi`` module.

    Args:
        device: gpps device string (see :func:`taichi_device`).

    Raises:
        RuntimeError: Taichi is already running on another device in this
            process.
    """
    global _device
    dev = taichi_device(device)
    if _device is not None:
        if dev != _device:
            raise RuntimeError(
                f"device: Taichi is already initialised on {_device!r} in this process and cannot "
                f"switch to {dev!r}; run the other device in a separate process"
            )
        return ti
    with _lock:
        if _device is None:
            arch = ti.cuda if dev.startswith("cuda") else ti.cpu  # never ti.gpu: it crashes here
            # The cache folder comes from TI_OFFLINE_CACHE_FILE_PATH (set above).
            # ti.init prints "[Taichi] Starting on arch=..." unconditionally; library code never prints.
            with contextlib.redirect_stdout(io.StringIO()):
                ti.init(arch=arch, offline_cache=True)
            _device = dev
        elif dev != _device:
            raise RuntimeError(f"device: Taichi is already initialised on {_device!r}, cannot switch to {dev!r}")
    return ti


def current_device() -> str | None:
    """The device Taichi runs on, or ``None`` before :func:`init`."""
    return _device
