"""Readers, what every format module shares: its problems reported as
:class:`~smart_marl.errors.ScenarioReadError` naming the file and the record.

* :func:`read_errors`: a Scenario (or part of one) built from a file's content that fails the
  Scenario's own validation is a read error of that file and record;
* :func:`load_json_object`: a JSON file whose top level is an object, or a read error saying why not;
* :func:`json_point`: one ``{"x": .., "y": .., "z": ..}`` point of a JSON scene, checked;
* :func:`choose_frame`: the local frame a reader shifts a scene's source coordinates into.
"""

from __future__ import annotations

import json
import os
from contextlib import contextmanager
from typing import Any, Iterator

import numpy as np

from ..errors import ScenarioReadError, ScenarioValidationError
from ..scenario import SceneFrame


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


def choose_frame(scenario_positions: np.ndarray, valid: np.ndarray, sdc_index: int, current_frame: int,
                 fallback: np.ndarray | None = None) -> SceneFrame:
    """The local frame readers use: the self-driving car's position at the current frame (exactly,
    so re-reading a written scene picks the same origin), else the mean of the valid positions at
    the current frame, else ``fallback`` (e.g. the map's centre), else the source origin.

    ``scenario_positions`` are source coordinates [N, T, 3] (float64).
    """
    if 0 <= sdc_index < len(valid) and valid[sdc_index, current_frame]:
        x, y, z = scenario_positions[sdc_index, current_frame]
        return SceneFrame(float(x), float(y), float(z), 0.0)
    cur = valid[:, current_frame] if valid.size else np.zeros(0, bool)
    if cur.any():
        x, y, z = scenario_positions[cur, current_frame].mean(axis=0)
        return SceneFrame(float(x), float(y), float(z), 0.0)
    if fallback is not None and len(fallback):
        x, y, z = np.asarray(fallback, np.float64).reshape(-1, 3).mean(axis=0)
        return SceneFrame(float(x), float(y), float(z), 0.0)
    return SceneFrame()
