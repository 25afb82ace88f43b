"""Checked arrays: untrusted values coerced without silent changes, and the read-only array helpers
the scene dataclasses (:mod:`smart_marl.scenario`, :mod:`smart_marl.road_map`) share.

* :func:`as_integers`, :func:`as_int`, :func:`as_floats`, :func:`as_mask`: a reader's values as
  arrays, refusing what a cast would silently change (strings, fractions, out-of-range numbers);
* ``_coerce`` / ``_check``: a frozen dataclass's field validated in ``__post_init__``;
* ``_trusted`` / ``_replace``: instances built from arrays already validated, without re-validating.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .errors import ScenarioValidationError



def _readonly(array: np.ndarray) -> np.ndarray:
    view = array.view()
    view.flags.writeable = False
    return view


def as_integers(value: Any, dtype=np.int64, what: str = "value") -> np.ndarray:
    """``value`` as an array of the integer ``dtype``, refusing what a cast would silently change:
    non-numbers (strings, None), floats that are not whole or not finite (id 12.7 is not id 12) and
    values outside the dtype's range (a difficulty of 1000 is not an int8)."""
    dtype = np.dtype(dtype)
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:  # ragged nested lists
        raise ScenarioValidationError(f"{what}: not an array of integers ({exc})") from None
    kind = array.dtype.kind
    if kind == "b" or (kind in "iu" and np.can_cast(array.dtype, dtype, "safe")):
        return array.astype(dtype, copy=False)  # every value fits: nothing to check, no copy when the dtype is already right
    if kind not in "iuf":
        raise ScenarioValidationError(f"{what}: expected integers, got values of type {_kind_name(array)}")
    if array.size:
        if kind == "f":
            bad = ~np.isfinite(array) | (array != np.round(array))
            if bad.any():
                raise ScenarioValidationError(f"{what}: {array.reshape(-1)[np.flatnonzero(bad.reshape(-1))[0]].item()!r} is not a whole number")
        info = np.iinfo(dtype)
        low, high = array.min(), array.max()
        if low < info.min or high > info.max:
            raise ScenarioValidationError(f"{what}: {(low if low < info.min else high).item()!r} is outside the range of {dtype} "
                                          f"[{info.min}, {info.max}]")
    return array.astype(dtype, copy=False)


def as_int(value: Any, what: str = "value") -> int:
    """One integer (an int, a numpy integer or a whole float; not a bool, a string or None)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ScenarioValidationError(f"{what}: expected an integer, got {value!r} ({type(value).__name__})")
    return int(as_integers(value, np.int64, what))


def as_floats(value: Any, dtype=np.float64, what: str = "value") -> np.ndarray:
    """``value`` as a float array; strings, None and other non-numbers are refused (never parsed)."""
    try:
        array = np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise ScenarioValidationError(f"{what}: not an array of numbers ({exc})") from None
    if array.dtype.kind not in "biuf":
        raise ScenarioValidationError(f"{what}: expected numbers, got values of type {_kind_name(array)}")
    with np.errstate(over="ignore"):
        return array.astype(dtype, copy=False)


def as_mask(value: Any, what: str = "value") -> np.ndarray:
    """A boolean mask: booleans, or numbers that are exactly 0 or 1 (float validity masks); strings
    such as ``"False"`` are refused (they are not false)."""
    array = np.asarray(value)
    if array.dtype.kind == "b":
        return array
    if array.dtype.kind not in "iuf":
        raise ScenarioValidationError(f"{what}: expected booleans, got values of type {_kind_name(array)}")
    bad = (array != 0) & (array != 1)
    if bad.any():
        raise ScenarioValidationError(f"{what}: {array.reshape(-1)[np.flatnonzero(bad.reshape(-1))[0]].item()!r} is neither 0/false nor 1/true")
    return array != 0


def _kind_name(array: np.ndarray) -> str:
    if array.dtype.kind == "O" and array.size:
        return ", ".join(sorted({type(v).__name__ for v in array.reshape(-1)[:1000]}))
    return {"U": "str", "S": "bytes", "O": "object"}.get(array.dtype.kind, str(array.dtype))


def _coerce(owner: Any, name: str, dtype: np.dtype, ndim: int | None = None) -> None:
    """Coerce ``owner.name`` to a read-only array of ``dtype`` (frozen dataclass friendly); integer
    and float fields refuse what a cast would silently change (see :func:`as_integers`)."""
    value = getattr(owner, name)
    what = f"{type(owner).__name__}.{name}"
    kind = np.dtype(dtype).kind
    if kind in "iu":
        array = as_integers(value, dtype, what)
    elif kind == "f":
        array = as_floats(value, dtype, what)
    else:
        try:
            array = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise ScenarioValidationError(f"{what}: cannot convert to {np.dtype(dtype)}: {exc}") from None
    if ndim is not None and array.ndim != ndim:
        raise ScenarioValidationError(f"{what}: expected {ndim} dimensions, got shape {array.shape}")
    object.__setattr__(owner, name, _readonly(array))


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ScenarioValidationError(message)


def _trusted(cls, **values):
    """Build a dataclass instance from already validated arrays, without re-validating."""
    obj = object.__new__(cls)
    for name, value in values.items():
        if isinstance(value, np.ndarray) and value.flags.writeable:
            value = _readonly(value)
        object.__setattr__(obj, name, value)
    return obj


def _replace(obj, **changes):
    values = {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    values.update(changes)
    return _trusted(type(obj), **values)


def _arrays_equal(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
