"""Config files and ``key=value`` overrides, the one reader that ``smart-marl train`` and
``smart-marl finetune`` share."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any


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
    strings; ``"{prefix}.k=v"`` sets key ``k`` of the nested dict ``values[nested]``. Keys that are
    not fields of the dataclass ``fields_of`` raise ``error`` listing the known ones."""
    values = dict(values)
    items = overrides.items() if isinstance(overrides, Mapping) else (split_override(o, error) for o in overrides)
    group = dict(values.pop(nested, {}) or {})
    for key, val in items:
        if key.startswith(prefix + "."):
            group[key[len(prefix) + 1:]] = val
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
