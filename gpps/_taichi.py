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

import numpy as np

from gpps import _fpenv
from gpps._runtime import resolve_device

os.environ.setdefault("ENABLE_TAICHI_HEADER_PRINT", "0")
os.environ.setdefault("TI_SKIP_VERSION_CHECK", "ON")
os.environ.setdefault("TI_LOG_LEVEL", "warn")
if os.environ.get("GPPS_CACHE_DIR") and "TI_OFFLINE_CACHE_FILE_PATH" not in os.environ:
    os.environ["TI_OFFLINE_CACHE_FILE_PATH"] = os.path.join(os.environ["GPPS_CACHE_DIR"], "taichi")

import taichi as ti  # noqa: E402  (after the environment above: Taichi reads it at import)
from taichi.lang import impl  # noqa: E402
from taichi.lang._ndarray import Ndarray  # noqa: E402
from taichi.lang.util import cook_dtype  # noqa: E402
from taichi.types import ndarray_type, primitive_types  # noqa: E402
from taichi.types.utils import is_signed  # noqa: E402

__all__ = ["ti", "init", "current_device", "taichi_device", "DirectLaunch"]

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
            # ti.init also turns flush-to-zero on in this thread: the caller's floating-point mode is put back
            # (gpps._fpenv), so Warp's CPU kernels round alike in every thread and process
            with contextlib.redirect_stdout(io.StringIO()), _fpenv.kept():
                ti.init(arch=arch, offline_cache=True)
            _device = dev
        elif dev != _device:
            raise RuntimeError(f"device: Taichi is already initialised on {_device!r}, cannot switch to {dev!r}")
    return ti


def current_device() -> str | None:
    """The device Taichi runs on, or ``None`` before :func:`init`."""
    return _device


class DirectLaunch:
    """Call one Taichi kernel again and again on the same arrays, with less host work.

    Taichi 1.7's ``kernel(*args)`` re-derives every argument's template
    features and converts every array in Python on each call: on the H100
    machine's host an empty kernel took 41 us with no arguments, 67 us with two
    Taichi ndarrays (31 launched this way) and 110 us with two torch CUDA
    tensors (61 this way; ``perf/integration_launch_overhead.py``), time that a
    streamed frame waits before its first task reaches the GPU.

    The first call on a set of array objects goes through ``kernel(*args)``
    (Taichi checks the arguments and compiles).  It then records the compiled
    kernel and, per argument, how to set it; a later call on the same array
    objects (any of the last ``MAX_PLANS`` sets, which it keeps alive) builds
    the launch context directly: per array a shape check and its data pointer
    read anew, per scalar one setter.  Kernels with template arguments or a return
    value, arrays with gradients, and any Taichi whose internals differ from
    1.7's are always called the plain way.

    Args:
        kernel: a ``@ti.kernel`` function.
    """

    #: argument sets remembered (a stream may ping-pong between buffers); each holds its arrays alive
    MAX_PLANS = 4

    def __init__(self, kernel):
        self._kernel = kernel
        self._plans = {}  # ids of the array arguments -> (compiled kernel, program, data, arrays, setters)
        self._pos = None  # positions of the array arguments (the kernel's annotations fix them)
        self._usable = hasattr(kernel, "_primal")

    def __call__(self, *args):
        pos = self._pos
        if pos is not None:
            plan = self._plans.get(tuple([id(args[k]) for k in pos if k < len(args)]))
            if plan is not None and len(args) == len(plan[4]):
                t_kernel, prog, data, _, setters = plan
                ctx = t_kernel.make_launch_context()
                for k, setter in enumerate(setters):
                    setter(ctx, k, args[k])
                prog.launch_kernel(data, ctx)
                return
        self._kernel(*args)
        if self._usable:
            try:
                plan = self._make_plan(args)
            except Exception:  # noqa: BLE001 - other Taichi internals: stay on the plain path
                self._plans.clear()
                self._usable = False
                return
            if plan is not None:
                self._pos = tuple(k for k, _ in plan[3])
                if len(self._plans) >= self.MAX_PLANS:
                    self._plans.pop(next(iter(self._plans)))
                self._plans[tuple(id(a) for _, a in plan[3])] = plan

    def _make_plan(self, args):
        kern = self._kernel._primal
        if kern.return_type is not None or getattr(kern, "has_print", False):
            return None
        cuda = impl.current_cfg().arch == ti.cuda
        arrays, setters = [], []
        for k, (a, arg) in enumerate(zip(args, kern.arguments)):
            anno = arg.annotation
            if id(anno) in primitive_types.real_type_ids and isinstance(a, (float, int, np.floating, np.integer)):
                setters.append(_set_float)
            elif id(anno) in primitive_types.integer_type_ids and isinstance(a, (int, np.integer)):
                if not is_signed(cook_dtype(anno)):
                    return None
                setters.append(_set_int)
            elif isinstance(anno, ndarray_type.NdarrayType) and (anno.dtype is None or id(anno.dtype) in primitive_types.type_ids):
                if isinstance(a, Ndarray):
                    if a.grad is not None:
                        return None
                    setters.append(_ndarray_setter(a.arr))
                elif isinstance(a, np.ndarray):
                    if cuda or not a.flags.c_contiguous:
                        return None
                    setters.append(_numpy_setter(a.shape))
                elif type(a).__module__ == "torch" and type(a).__name__ == "Tensor":
                    if not a.is_contiguous() or a.requires_grad or (a.device.type == "cuda") != cuda:
                        return None
                    setters.append(_torch_setter(a.shape, a.element_size() * a.nelement()))
                else:
                    return None
                arrays.append((k, a))
            else:
                return None
        key = kern.ensure_compiled(*args)
        t_kernel = kern.compiled_kernels[key]
        prog = impl.get_runtime().prog
        data = prog.compile_kernel(prog.config(), prog.get_device_caps(), t_kernel)
        return t_kernel, prog, data, tuple(arrays), tuple(setters)


def _set_float(ctx, k, v):
    ctx.set_arg_float((k,), float(v))


def _set_int(ctx, k, v):
    ctx.set_arg_int((k,), int(v))


def _ndarray_setter(arr):
    def setter(ctx, k, v):
        ctx.set_arg_ndarray((k,), arr)

    return setter


def _shape_changed(k, shape, v):
    return ValueError(f"argument {k}: an array resized in place since the kernel was prepared: expected shape "
                      f"{tuple(shape)}, got {tuple(v.shape)}")


def _numpy_setter(shape):
    shape = tuple(shape)

    def setter(ctx, k, v):
        if v.shape != shape or not v.flags.c_contiguous:
            raise _shape_changed(k, shape, v)
        ctx.set_arg_external_array_with_shape((k,), v.__array_interface__["data"][0], v.nbytes, shape, 0)

    return setter


def _torch_setter(shape, nbytes):
    shape = tuple(shape)

    def setter(ctx, k, v):
        if v.shape != shape:
            raise _shape_changed(k, shape, v)
        ctx.set_arg_external_array_with_shape((k,), v.data_ptr(), nbytes, shape, 0)

    return setter
