"""Readers, what every format module shares: its problems reported as
:class:`~smart_marl.errors.ScenarioReadError` naming the file and the record.

* :func:`read_errors`: a Scenario (or part of one) built from a file's content that fails the
  Scenario's own validation is a read error of that file and record;
* :func:`load_json_object`: a JSON file whose top level is an object, or a read error saying why not;
* :func:`json_point`: one ``{"x": .., "y": .., "z": ..}`` point of a JSON scene, checked.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from typing import Any, Iterator

from ..errors import ScenarioReadError, ScenarioValidationError


@contextmanager
def read_errors(path: str | os.PathLike, record: Any = None, prefix: str = "") -> Iterator[None]:
    """Inside, a :class:`ScenarioValidationError` (a Scenario built from bad content) becomes a
    :class:`ScenarioReadError` of ``path`` and ``record``, its message after ``prefix``."""
    try:
        yield
    except ScenarioValidationError as exc:
        raise ScenarioReadError(path, f"{prefix}{exc}", record) from exc


def load_json_object(path: str | os.PathLike) -> dict:
    """The top-level JSON object of a file (a read error when it is unreadable, not UTF-8 text, not
    JSON, nested too deeply, or a JSON value other than an object)."""
    try:
        with open(path, "rb") as f:
            data = json.load(f)
    except json.JSONDecodeError as exc:
        raise ScenarioReadError(path, f"invalid JSON at line {exc.lineno} column {exc.colno}: {exc.msg}") from exc
    except UnicodeDecodeError as exc:
        raise ScenarioReadError(path, f"not UTF-8 text: {exc}") from exc
    except RecursionError as exc:
        raise ScenarioReadError(path, "JSON nested too deeply to read") from exc
    except OSError as exc:
        raise ScenarioReadError(path, f"cannot read: {exc.strerror or exc}") from exc
    if not isinstance(data, dict):
        raise ScenarioReadError(path, f"top level is a JSON {type(data).__name__}, expected an object")
    return data


def is_json_number(value: Any) -> bool:
    """A JSON number (int or float; not a bool, not a numeric string)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def json_point(point: Any, path: str, record: str, with_z: bool = True) -> tuple[float, float, float | None]:
    """(x, y, z) of one JSON point object (z None when it has none or ``with_z`` is off); a read error
    naming ``record`` when it is not an object with numeric x and y (and z, when present)."""
    if not isinstance(point, dict):
        raise ScenarioReadError(path, f"is a {type(point).__name__}, expected an object with x, y", record=record)
    for axis in ("x", "y"):
        if axis not in point:
            raise ScenarioReadError(path, f"missing field '{axis}'", record=record)
    bad = [axis for axis in ("x", "y", "z") if axis in point and not is_json_number(point[axis])]
    if bad:
        raise ScenarioReadError(path, f"coordinate {bad[0]} is {point[bad[0]]!r}, not a number", record=record)
    z = float(point["z"]) if with_z and "z" in point else None
    return float(point["x"]), float(point["y"]), z
