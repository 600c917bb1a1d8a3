"""Argument checks shared by the public API and the stages ("expected ..., got ...")."""

from __future__ import annotations

import functools
import os
import warnings
from dataclasses import fields
from pathlib import Path
from types import UnionType
from typing import Literal, Union, get_args, get_origin, get_type_hints

import numpy as np

from gpps import names


class GppsWarning(UserWarning):
    """A result gpps computed but does not trust fully (lights behind the object, an estimate on its
    search bound, rounds that did not converge, many undetermined pixels).  Also listed in the result's
    ``warnings`` and in the CLI's report.json."""


def warn(message: str, sink: list | None = None, stacklevel: int = 3) -> None:
    """Issue a :class:`GppsWarning` and append its message to ``sink`` (a result's ``warnings`` list)."""
    if sink is not None:
        sink.append(message)
    warnings.warn(message, GppsWarning, stacklevel=stacklevel)


#: Full scale of the integer image types: the one rule for images everywhere in gpps.  uint8 and uint16
#: images are divided by it (0..1); floating-point images are taken as they are (linear, 1 = full scale);
#: any other dtype (int32, complex, bool, object, ...) is a TypeError naming the argument.
IMAGE_FULL_SCALE = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}

_NOT_NUMBERS = "cbOUSVMm"  # complex, bool, object, strings, void, datetimes: never silently cast to floats


def _source(name, a):
    """``a`` as a numpy array as given (no cast), refusing what is not an array of real numbers."""
    if hasattr(a, "numpy") and not isinstance(a, np.ndarray):  # warp / torch arrays
        a = a.numpy()
    try:
        src = np.asarray(a)
    except (TypeError, ValueError):
        raise TypeError(f"{name}: expected an array of real numbers, got {type(a).__name__}") from None
    if src.dtype.kind in _NOT_NUMBERS:
        raise TypeError(f"{name}: expected an array of real numbers (float or integer), got dtype {src.dtype}")
    return src


def as_images(name, a, *, dtype=np.float32) -> np.ndarray:
    """Images as floats by the one rule of :data:`IMAGE_FULL_SCALE` (no shape check).

    Raises:
        TypeError: complex, bool, object or integer types other than uint8 / uint16.
        ValueError: NaN, inf or negative values.
    """
    src = _source(name, a)
    if src.dtype.kind in "iu" and src.dtype not in IMAGE_FULL_SCALE:
        raise TypeError(f"{name}: expected uint8, uint16 (scaled by full scale) or floating-point images "
                        f"(linear, 1 = full scale), got dtype {src.dtype}")
    scale = IMAGE_FULL_SCALE.get(src.dtype)
    if scale:  # uint8 / uint16: one float copy divided in place, finite and >= 0 by construction
        arr = src.astype(dtype)
        arr /= dtype(scale)
        return arr
    arr = np.asarray(src, dtype=dtype)  # no copy when ``a`` already has the dtype
    lo, hi = _extremes(arr)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    if lo < 0:
        raise ValueError(f"{name}: expected values >= 0, got a minimum of {float(lo):.6g}")
    return arr


def _extremes(arr):
    """``(min, max)`` of a float array in two reductions without temporaries: NaN when it holds a NaN
    (min and max propagate it), so both are finite exactly when every value is; (0, 0) when empty."""
    if arr.size == 0:
        return 0.0, 0.0
    return np.min(arr), np.max(arr)


def as_array(name, a, *, ndim=None, shape=None, dtype=np.float32, finite=True) -> np.ndarray:
    """``a`` as a numpy array of ``dtype``, checked for dimension, shape and finiteness.

    ``shape`` may hold None for free axes.  Complex, bool, object and string
    arrays are a TypeError (never cast silently).
    """
    src = _source(name, a)
    try:
        arr = np.asarray(src, dtype=dtype)
    except (TypeError, ValueError, OverflowError):
        raise TypeError(f"{name}: expected an array of numbers, got {type(a).__name__}") from None
    if ndim is not None and arr.ndim != ndim:
        want = shape if shape is not None else f"{ndim} dimensions"
        raise ValueError(f"{name}: expected shape {_fmt(want)}, got {arr.shape}")
    if shape is not None:
        if len(shape) != arr.ndim or any(w is not None and w != g for w, g in zip(shape, arr.shape)):
            raise ValueError(f"{name}: expected shape {_fmt(shape)}, got {arr.shape}")
    if finite and np.issubdtype(arr.dtype, np.floating) and not all(np.isfinite(_extremes(arr))):
        raise ValueError(f"{name}: expected finite values, got NaN or inf")
    return arr


def _fmt(shape):
    if isinstance(shape, str):
        return shape
    return "(" + ", ".join("?" if s is None else str(s) for s in shape) + ")"


def as_mask(name, m, shape=None, allow_empty=False) -> np.ndarray:
    arr = np.asarray(m)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected shape (H, W), got {arr.shape}")
    if shape is not None and arr.shape != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {arr.shape}")
    arr = _bools(name, arr, "(H, W)", "a pixel is inside")
    if not allow_empty and not arr.any():
        raise ValueError(f"{name}: expected at least one pixel inside the mask, got an empty mask")
    return arr


def as_flags(name, v, shape) -> np.ndarray:
    """``v`` as a bool array of exactly ``shape`` (e.g. the (N, H, W) ``valid`` observations): booleans, or
    finite numbers (> 0 is True), as :func:`as_mask` takes them; ValueError/TypeError naming ``name``."""
    arr = np.asarray(v)
    if arr.shape != tuple(shape):
        raise ValueError(f"{name}: expected shape {tuple(shape)}, got {arr.shape}")
    return _bools(name, arr, _fmt(shape), "True")


def _bools(name, arr, form, meaning) -> np.ndarray:
    """``arr`` as bools: bool as it is, integers and finite floats ``> 0``; anything else a TypeError."""
    if arr.dtype == bool:
        return arr
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise TypeError(f"{name}: expected a boolean or numeric {form} array, got {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating) and not np.isfinite(arr).all():
        raise ValueError(f"{name}: expected finite values ({meaning} when > 0), got NaN or inf")
    return arr > 0


def check_shape(name, shape, form: str, lo: int = 1) -> tuple[int, ...]:
    """``shape`` as a tuple of ``len(form)`` integers >= ``lo`` (``form`` the axes' names, e.g. ``"HW"``);
    ValueError/TypeError naming ``name`` ("shape: expected (H, W) ..., got ...")."""
    want = "(" + ", ".join(form) + ")"
    try:
        sizes = tuple(shape)
    except TypeError:
        raise TypeError(f"{name}: expected {want} integers, got {shape!r}") from None
    if isinstance(shape, (str, bytes)) or len(sizes) != len(form):
        raise ValueError(f"{name}: expected {want}, got {shape!r}")
    out = []
    for s in sizes:
        try:
            out.append(check_number(name, s, integer=True))
        except (TypeError, ValueError):
            raise TypeError(f"{name}: expected {want} integers, got {shape!r}") from None
    if min(out) < lo:
        raise ValueError(f"{name}: expected {want} with sizes >= {lo}, got {shape!r}")
    return tuple(out)


def check_unit(name, vectors, tol=1e-3, where="inside the mask") -> np.ndarray:
    """The norms of (M, 3) ``vectors``; ValueError naming ``name`` when one is farther than ``tol`` from 1."""
    norms = np.linalg.norm(vectors, axis=-1)
    if np.any(np.abs(norms - 1.0) > tol):
        k = int(np.argmax(np.abs(norms - 1.0)))
        raise ValueError(f"{name}: expected unit vectors {where}, got norm {norms[k]:.6g}")
    return norms


def unit_normals(name, n, mask, tol=1e-3) -> np.ndarray:
    """(H, W, 3) float32 normals, unit inside ``mask`` (checked), zero outside."""
    h, w = mask.shape
    arr = as_array(name, n, shape=(h, w, 3))
    norms = check_unit(name, arr[mask], tol)
    out = np.zeros_like(arr)
    out[mask] = arr[mask] / norms[:, None]
    return out


def albedo_map(name, a, shape) -> np.ndarray:
    """(H, W, 3) float32 albedo from an (H, W, 3) map, an (H, W) grey map or an RGB triple."""
    h, w = shape
    arr = as_array(name, a)
    if arr.shape == (3,):
        arr = np.broadcast_to(arr, (h, w, 3))
    elif arr.shape == ():
        arr = np.full((h, w, 3), float(arr), np.float32)
    elif arr.shape == (h, w):
        arr = np.repeat(arr[..., None], 3, axis=-1)
    elif arr.shape != (h, w, 3):
        raise ValueError(f"{name}: expected (H, W, 3), (H, W) or (3,) with (H, W) = {shape}, got {arr.shape}")
    if np.any(arr < 0):
        raise ValueError(f"{name}: expected values >= 0")
    return np.ascontiguousarray(arr, dtype=np.float32)


def clipping(peak) -> tuple[str | None, float, float]:
    """The clipping rule of images given without a saturation level (:data:`gpps.names.CLIP_LEVELS`).

    Args:
        peak: the observations' brightest channels (any shape, non-empty).

    Returns:
        ``(verdict, full scale, share)``: ``verdict`` ``"saturated"`` (``names.SATURATED_SHARE`` or more of the
        observations at the full scale: an error for the caller), ``"clipped"`` (``names.CLIPPED_SHARE`` or more and
        ``names.CLIPPED_MIN`` observations: a warning) or None; ``full scale`` the maximum (None-verdict also when it
        is not a full-scale value); ``share`` the fraction of observations at it.
    """
    top = float(np.max(peak))
    if top not in names.CLIP_LEVELS:
        return None, top, 0.0
    at_top = np.asarray(peak) >= top
    share = float(at_top.mean())
    if share >= names.SATURATED_SHARE:
        return "saturated", top, share
    if share >= names.CLIPPED_SHARE and int(np.count_nonzero(at_top)) >= names.CLIPPED_MIN:
        return "clipped", top, share
    return None, top, share


def as_path(name, v):
    """``v`` as a :class:`pathlib.Path` (a ``str`` or ``os.PathLike``); else a TypeError naming ``name``."""
    if isinstance(v, (str, os.PathLike)) and not isinstance(v, bytes):
        return Path(v)
    raise TypeError(f"{name}: expected a path (str or os.PathLike), got {type(v).__name__}")


def check_bool(name, v) -> bool:
    """``v`` as a bool (True/False or numpy bools only); TypeError naming ``name``."""
    if not isinstance(v, (bool, np.bool_)):
        raise TypeError(f"{name}: expected True or False, got {v!r}")
    return bool(v)


def check_number(name, v, lo=None, hi=None, integer=False, lo_open=False):
    """``v`` as a finite float (or int), checked against ``lo`` / ``hi``; ValueError/TypeError naming ``name``."""
    if isinstance(v, np.ndarray) and v.ndim == 0:
        v = v.item()
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise TypeError(f"{name}: expected a{'n integer' if integer else ' number'}, got {v!r}")
    if not np.isfinite(float(v)):
        raise ValueError(f"{name}: expected a finite number, got {v!r}")
    if integer:
        if float(v) != int(v):
            raise TypeError(f"{name}: expected an integer, got {v!r}")
        x = int(v)
    else:
        x = float(v)
    if lo is not None and (x < lo or (lo_open and x == lo)):
        raise ValueError(f"{name}: expected {'>' if lo_open else '>='} {lo}, got {v!r}")
    if hi is not None and x > hi:
        raise ValueError(f"{name}: expected <= {hi}, got {v!r}")
    return x


def check_choice(name: str, value, choices, *, allow_none: bool = False):
    """``value`` if it is one of ``choices`` (a tuple or a ``Literal[...]`` type), else ValueError naming ``name``.

    The one choice check of gpps: every config field and string argument with a fixed set of values
    goes through it, so the message is the same everywhere ("name: expected one of [...], got ...").
    """
    options = tuple(get_args(choices)) if get_origin(choices) is Literal else tuple(choices)
    if value is None and allow_none:
        return value
    try:
        ok = not isinstance(value, (bool, np.bool_)) and any(value == o and isinstance(value, str) == isinstance(o, str)
                                                              for o in options)
    except (TypeError, ValueError):  # arrays and other values without a plain ==
        ok = False
    if not ok:
        extra = " or None" if allow_none else ""
        raise ValueError(f"{name}: expected one of {list(options)}{extra}, got {value!r}")
    return value


def _literal_options(annotation):
    """(choices, allow_none) of a ``Literal[...]`` or ``Literal[...] | None`` annotation, else None."""
    if get_origin(annotation) is Literal:
        return get_args(annotation), False
    if get_origin(annotation) in (Union, UnionType):
        args = get_args(annotation)
        lits = [a for a in args if get_origin(a) is Literal]
        if len(lits) == 1 and len(args) == 2 and type(None) in args:
            return get_args(lits[0]), True
    return None


def check_choices(config) -> None:
    """Check every ``Literal``-annotated field of a dataclass instance with :func:`check_choice`.

    Called first in each config's ``__post_init__``: the allowed values are read from the field's
    annotation, so a new choice is declared in one place (the ``Literal`` in :mod:`gpps.names` or the
    config) and checked everywhere.
    """
    for name, options, allow_none in _choice_fields(type(config)):
        value = getattr(config, name)
        # (fast path: a str among string options; everything else through the one full check)
        if not (type(value) is str and value in options):
            check_choice(name, value, options, allow_none=allow_none)


@functools.lru_cache(maxsize=None)
def _choice_fields(cls) -> tuple:
    """``(name, options, allow_none)`` of each ``Literal`` field of the dataclass ``cls``, read once per class
    (``get_type_hints`` and the ``typing`` introspection cost ~0.1 ms a config: the material search builds
    hundreds of :class:`gpps.Material` candidates per reconstruction)."""
    hints = get_type_hints(cls)
    out = []
    for f in fields(cls):
        spec = _literal_options(hints.get(f.name))
        if spec is not None:
            out.append((f.name, tuple(spec[0]), spec[1]))
    return tuple(out)
