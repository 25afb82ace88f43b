"""Config files and ``key=value`` overrides, the one reader that ``smart-marl train`` and
``smart-marl finetune`` share, and the checks of the values in them: :func:`check_fields` with the
rules :func:`integer`, :func:`number`, :func:`text`, :func:`flag`, :func:`optional`, and the
problems of a device name (:func:`device_problem`) or an output folder (:func:`output_dir_problem`),
which the command line's argument types use too."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from .errors import check_regular_file

Rule = Callable[[Any], "str | None"]
"""A check of one config value: None when it is fine, else what is wrong with it."""


def parse_value(text: str) -> Any:
    """An override's value: JSON when it parses, else none/null/true/false, else the text itself."""
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        low = text.lower()
        if low in ("none", "null"):
            return None
        if low in ("true", "false"):
            return low == "true"
        return text


def split_override(text: str, error: type[Exception]) -> tuple[str, Any]:
    """``"key=value"`` -> (key, parsed value); ``error`` when there is no ``=``."""
    if "=" not in text:
        raise error(f"override {text!r} is not key=value")
    k, v = text.split("=", 1)
    return k.strip(), parse_value(v.strip())


def read_config_file(path: Path, what: str, error: type[Exception]) -> dict[str, Any]:
    """The dict in a JSON or TOML (by suffix) config file; ``error`` naming the file when it cannot be read."""
    check_regular_file(path, lambda p, problem: error(f"{p}: cannot read the {what} config: {problem}"))
    try:
        text = path.read_text()
        if path.suffix == ".toml":
            import tomllib

            return dict(tomllib.loads(text))
        return dict(json.loads(text))
    except Exception as exc:  # noqa: BLE001 - reported with the file name
        raise error(f"{path}: cannot read the {what} config: {exc}") from exc


def apply_overrides(values: dict[str, Any], overrides, fields_of: type, nested: str, prefix: str, what: str,
                    error: type[Exception]) -> dict[str, Any]:
    """``values`` (a config file's dict) with ``overrides`` applied: a mapping or ``"key=value"``
    strings; ``"{prefix}.k=v"`` sets key ``k`` of the nested dict ``values[nested]``, ``nested`` itself
    (``reward={...}``) replaces it. Keys that are not fields of the dataclass ``fields_of`` raise
    ``error`` listing the known ones."""
    values = dict(values)
    items = overrides.items() if isinstance(overrides, Mapping) else (split_override(o, error) for o in overrides)
    group = dict(values.pop(nested, {}) or {})
    for key, val in items:
        if key.startswith(prefix + "."):
            group[key[len(prefix) + 1:]] = val
        elif key == nested and isinstance(val, Mapping):
            group = dict(val)
        else:
            values[key] = val
    values[nested] = group
    known = {f.name for f in dataclasses.fields(fields_of)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise error(f"unknown {what} config key(s) {unknown}; known: {sorted(known)}")
    return values


def apply_command_flags(cfg, args) -> None:
    """The flags every config-driven command shares (``--out``, ``--seed``, ``--device``) win over
    the config file and the ``key=value`` overrides."""
    for flag, field in (("out", "out_dir"), ("seed", "seed"), ("device", "device")):
        value = getattr(args, flag, None)
        if value is not None:
            setattr(cfg, field, value)


# ------------------------------------------------------------------------------ value checks
def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def integer(low: int | None = None) -> Rule:
    """An int (not a bool, not a float) >= ``low``."""
    def rule(value):
        if not _is_int(value):
            return f"must be an integer, got {value!r}"
        if low is not None and value < low:
            return f"must be at least {low}, got {value}"
        return None
    return rule


def number(low: float | None = None, high: float | None = None, low_open: bool = False, high_open: bool = False) -> Rule:
    """A finite int or float in [low, high] (an open end with ``low_open`` / ``high_open``)."""
    def rule(value):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return f"must be a finite number, got {value!r}"
        if low is not None and (value <= low if low_open else value < low):
            return f"must be {'>' if low_open else '>='} {low}, got {value}"
        if high is not None and (value >= high if high_open else value > high):
            return f"must be {'<' if high_open else '<='} {high}, got {value}"
        return None
    return rule


def text(value: Any) -> str | None:
    """A string."""
    return None if isinstance(value, str) else f"must be a string, got {value!r}"


def flag(value: Any) -> str | None:
    """A boolean (true/false)."""
    return None if isinstance(value, bool) else f"must be true or false, got {value!r}"


def optional(rule: Rule) -> Rule:
    """None, or a value ``rule`` accepts."""
    return lambda value: None if value is None else rule(value)


def check_fields(cfg: Any, rules: Mapping[str, Rule], what: str, error: type[Exception]) -> None:
    """Raise ``error`` naming the first field of ``cfg`` whose value its rule refuses."""
    for name, rule in rules.items():
        problem = rule(getattr(cfg, name))
        if problem:
            raise error(f"{what} config: {name} {problem}")


def device_problem(name: Any) -> str | None:
    """Why ``name`` is not a torch device this machine can run on (cpu, cuda[:i], mps), or None."""
    if not isinstance(name, str):
        return f"device must be a string such as cpu or cuda, got {name!r}"
    import torch

    try:
        dev = torch.device(name)
    except (RuntimeError, ValueError):
        return f"{name!r} is not a torch device (cpu, cuda, cuda:N or mps)"
    if dev.type == "cpu":
        return None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            return f"{name}: CUDA is not available on this machine"
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            return f"{name}: this machine has {torch.cuda.device_count()} CUDA device(s)"
        return None
    if dev.type == "mps":
        return None if torch.backends.mps.is_available() else f"{name}: MPS is not available on this machine"
    return f"{name}: smart-marl runs on cpu, cuda or mps"


def output_dir_problem(path: Any) -> str | None:
    """Why ``path`` cannot be the folder a command writes into (it is an existing file...), or None."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        return f"the output folder must be a path, got {path!r}"
    if os.path.exists(path) and not os.path.isdir(path):
        return f"{os.fspath(path)} exists and is not a folder"
    return None
