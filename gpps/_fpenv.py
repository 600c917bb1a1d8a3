"""The C floating-point environment of the calling thread (rounding, exception masks and, on x86-64, the
flush-to-zero and denormals-are-zero bits of MXCSR), read and set through the C library's ``fegetenv`` /
``fesetenv``.

Why gpps cares: Taichi's initialisation turns flush-to-zero on in the thread that calls it (MXCSR 0x1fa0 ->
0x9fa0), and a new thread inherits the mode of the thread that made it.  Warp's CPU kernels then rounded
denormal results one way or the other depending on which thread ran them, and when (a capture's normals held
7e-40 in one process and 0 in another).  :func:`gpps._taichi.init` therefore leaves the caller's mode as it
found it (:func:`kept`), and :func:`gpps.pipeline.cpu_threads.run_all` runs each task in the caller's mode.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util

__all__ = ["get", "set_env", "set_default", "kept"]

_FENV_BYTES = 256  # room for any platform's fenv_t (x86-64 glibc: 32 bytes)
_LIBM = None  # (fegetenv, fesetenv), or False where there is no C math library to load


def _libm():
    global _LIBM
    if _LIBM is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library("m") or "libm.so.6")
            _LIBM = (lib.fegetenv, lib.fesetenv)
        except (OSError, AttributeError):  # pragma: no cover - no C math library
            _LIBM = False
    return _LIBM or None


def get():
    """This thread's floating-point environment (an opaque buffer for :func:`set_env`), or None where it
    cannot be read."""
    lib = _libm()
    if lib is None:
        return None
    env = ctypes.create_string_buffer(_FENV_BYTES)
    return env if lib[0](env) == 0 else None


def set_env(env) -> None:
    """Make ``env`` (from :func:`get`, in any thread) this thread's floating-point environment; None: nothing."""
    lib = _libm()
    if env is not None and lib is not None:
        lib[1](env)


def set_default() -> None:
    """Make the C library's default environment this thread's (glibc's ``FE_DFL_ENV``: round to nearest, no
    flush-to-zero); nothing where the C library does not offer it."""
    lib = _libm()
    if lib is not None:
        try:
            lib[1](ctypes.c_void_p(-1))  # FE_DFL_ENV is ((const fenv_t *) -1) in glibc
        except (OSError, ValueError):  # pragma: no cover - another C library
            pass


@contextlib.contextmanager
def kept():
    """Restore this thread's floating-point environment on exit (whatever the body changed)."""
    env = get()
    try:
        yield
    finally:
        set_env(env)
