"""Config files and ``key=value`` overrides, the one reader that ``smart-marl train`` and
``smart-marl finetune`` share, and the checks of the values in them: :func:`check_fields` with the
rules :func:`integer`, :func:`number`, :func:`seed`, :func:`text`, :func:`flag`, :func:`optional`,
:func:`one_of`, :func:`sequence`, :func:`interval`, :func:`probabilities` (and :func:`check_value` for a single value), and the
problems of a device name (:func:`device_problem`) or an output folder (:func:`output_dir_problem`),
which the command line's argument types use too; and the limits several configs share (:data:`MAX_TIME_LIMIT_S`,
:data:`MAX_GRAD_NORM`, :data:`MAX_LOSS_WEIGHT`, :data:`MAX_SCENE_COUNT`, :data:`MAX_DISTANCE_M`)."""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .errors import check_regular_file, on_kernel_file_system

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


def strict_json(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` that writes JSON: NaN and infinities (which Python writes as ``NaN``/``Infinity``,
    which no JSON parser takes) become ``null``; numpy numbers and other objects go through ``float``."""
    def clean(v):
        if isinstance(v, (float, np.floating)):
            v = float(v)
            return v if math.isfinite(v) else None
        if isinstance(v, Mapping):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v
    return json.dumps(clean(value), allow_nan=False, **kwargs,
                      default=lambda v: int(v) if isinstance(v, numbers.Integral) else clean(float(v)))


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
    group = values.pop(nested, {})
    if not isinstance(group, Mapping):  # a config file's `model_overrides = "ten"` or null
        raise error(f"{what} config: {nested} must be a mapping ({{...}}), got {group!r}")
    group = dict(group)
    for key, val in items:
        if key.startswith(prefix + "."):
            group[key[len(prefix) + 1:]] = val
        elif key == nested:
            if not isinstance(val, Mapping):  # it would be dropped for the file's: refuse it instead
                raise error(f"{what} config: {nested} must be a mapping ({{...}}) or set as {prefix}.KEY=VALUE, got {val!r}")
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
# The one way a value a user gives is checked (issue 34): a rule takes the value and says what is wrong
# with it (None when it is fine), naming the value and what is allowed; :func:`check_value` and
# :func:`check_fields` turn a problem into the caller's SmartMarlError naming the argument. The
# environment's arguments (envs/_arguments.py), every config dataclass (train, finetune, SUMO, the model,
# what-if edits) and the command line's argument types (smart_marl.commands.arguments) use these rules.
MAX_SEED = 2**63 - 1
"""The largest seed taken anywhere (numpy, torch and Python generators all accept 0..2**63 - 1)."""
# The limits several configs share (issue 56: every number a run divides, loops or multiplies by is bounded on both sides).
MAX_TIME_LIMIT_S = 30 * 24 * 3600.0
"""The longest ``time_limit_s`` of a training or fine-tuning run: 30 days. A longer limit is no limit (the project's
longest runs took hours), so a value such as 1e18 is a slip; ask for none with 0 (fine-tuning) or null (training)."""
MAX_GRAD_NORM = 1e6
"""The largest gradient-norm clip (fine-tuning ``max_grad_norm``, training ``grad_clip``): a run whose gradients reach a
norm of a million has already diverged, so a larger clip never clips; 1e300 is a slip, not a setting."""
MAX_LOSS_WEIGHT = 1e3
"""The largest weight of a loss term (fine-tuning ``beta``, ``imitation``, ``entropy_coeff``, ``critic_coeff``, training
``speed_trend_weights``): a term 1,000x the objective it is added to already drowns it, and a weight such as 1e300
overflows float32 (3.4e38): inf losses and NaN gradients."""
MAX_SCENE_COUNT = 10**7
"""The most scenes a config may ask for by count (fine-tuning ``num_scenes``, training ``vocab_scenes``, ``val_scenes``):
20x WOMD's training split (487,002 scenes), the largest data set the project reads; each is a pass of a loop."""
MAX_DISTANCE_M = 10_000.0
"""The longest distance in metres a config gives (a goal radius, a route length, a drift): 10 km, farther than any
scene reaches (a WOMD scene spans a few hundred metres; 20 s at 200 km/h is 1.1 km)."""


def is_integer(value: Any) -> bool:
    """An int or a numpy integer; never a bool, a float (not even 2.0) or a string."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """A finite int or float (numpy ones too) that a float64 holds; never a bool, NaN, an infinity, an
    integer beyond 1.7e308 or a string."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return False
    if isinstance(value, numbers.Integral):
        return abs(int(value)) <= 1.7e308  # exact comparison: math.isfinite would overflow on 10**400
    return math.isfinite(value)


def shown(value: Any, form=repr, width: int = 80) -> str:
    """``value`` for an error message: its repr (or ``form``), cut to ``width`` characters."""
    text = form(value)
    return text if len(text) <= width else text[: width - 3] + "..."


def _limit(high, why: str) -> str:
    return f"{high}{f' ({why})' if why else ''}"


def integer(low: int | None = None, high: int | None = None, why: str = "") -> Rule:
    """An integer (:func:`is_integer`) in [low, high]; ``why`` says where the upper limit comes from."""
    allowed = (f"{low}..{high}" if low is not None and high is not None else f">= {low}" if low is not None
               else f"<= {high}" if high is not None else "")

    def rule(value):
        if not is_integer(value):
            return f"must be an integer, got {shown(value)}" + (f" (allowed: {allowed})" if allowed else "")
        if low is not None and value < low:
            return f"must be at least {low}, got {shown(value, str)}"
        if high is not None and value > high:
            return f"must be at most {_limit(high, why)}, got {shown(value, str)}"
        return None
    return rule


def number(low: float | None = None, high: float | None = None, low_open: bool = False, high_open: bool = False,
           why: str = "") -> Rule:
    """A finite number (:func:`is_number`) in [low, high] (an open end with ``low_open`` / ``high_open``);
    ``why`` says where the upper limit comes from."""
    lows = f"{'>' if low_open else '>='} {low}" if low is not None else ""
    highs = f"{'<' if high_open else '<='} {high}" if high is not None else ""
    allowed = " and ".join(x for x in (lows, highs) if x)

    def rule(value):
        if not is_number(value):
            return f"must be a finite number, got {shown(value)}" + (f" (allowed: {allowed})" if allowed else "")
        if low is not None and (value <= low if low_open else value < low):
            return f"must be {lows}, got {shown(value, str)}"
        if high is not None and (value >= high if high_open else value > high):
            return f"must be {'<' if high_open else '<='} {_limit(high, why)}, got {shown(value, str)}"
        return None
    return rule


seed = integer(0, MAX_SEED, "the largest seed the random generators take")
"""A random seed: an integer in 0..2**63 - 1."""


def text(value: Any) -> str | None:
    """A string."""
    return None if isinstance(value, str) else f"must be a string, got {shown(value)}"


def flag(value: Any) -> str | None:
    """A boolean (true/false; a numpy bool too), never the string "false" or a number."""
    return None if isinstance(value, (bool, np.bool_)) else f"must be true or false, got {shown(value)}"


def optional(rule: Rule) -> Rule:
    """None, or a value ``rule`` accepts."""
    return lambda value: None if value is None else rule(value)


def one_of(*options: Any) -> Rule:
    """One of ``options`` (compared with ==; a value of another type is refused, not converted)."""
    def rule(value):
        try:
            ok = any(type(value) is type(o) and value == o for o in options)
        except Exception:  # noqa: BLE001 - a value whose == raises (an array...) is not an option
            ok = False
        return None if ok else f"must be one of {', '.join(map(repr, options))}, got {shown(value)}"
    return rule


def sequence(rule: Rule, length: int | None = None, min_length: int = 0, max_length: int | None = None) -> Rule:
    """A list or tuple whose items each pass ``rule``: exactly ``length`` items, or min..max_length."""
    def check(value):
        if not isinstance(value, (list, tuple)):
            return f"must be a list, got {shown(value)}"
        n = len(value)
        if length is not None and n != length:
            return f"must be a list of {length} item(s), got {n}"
        if n < min_length or (max_length is not None and n > max_length):
            return f"must be a list of {min_length}..{max_length if max_length is not None else 'any'} items, got {n}"
        for i, item in enumerate(value):
            problem = rule(item)
            if problem:
                return f"[{i}] {problem}"
        return None
    return check


def interval(low: float | None = None, high: float | None = None, low_open: bool = False) -> Rule:
    """A (lo, hi) pair of finite numbers in [low, high] (lo > low with ``low_open``) with lo <= hi."""
    item = number(low, high, low_open=low_open)
    pair = sequence(item, length=2)

    def rule(value):
        problem = pair(value)
        if problem:
            return problem
        return None if value[0] <= value[1] else f"must be a range (low, high) with low <= high, got {shown(value)}"
    return rule


def probabilities(length: int | None = None) -> Rule:
    """A list of ``length`` finite numbers >= 0 that add up to 1 (a probability per choice)."""
    items = sequence(number(0.0, 1.0), length=length, min_length=1)

    def rule(value):
        problem = items(value)
        if problem:
            return problem
        return None if abs(sum(value) - 1.0) <= 1e-6 else f"must add up to 1 (probabilities), got {shown(value)} (sum {sum(value):g})"
    return rule


def check_value(name: str, value: Any, rule: Rule, error: Callable[[str], Exception], what: str = "") -> Any:
    """``value`` when ``rule`` accepts it, else ``error("{what}: {name} {problem}")`` (the argument, the
    value and what is allowed, in one line)."""
    problem = rule(value)
    if problem:
        raise error(f"{what + ': ' if what else ''}{name} {problem}")
    return value


def check_fields(cfg: Any, rules: Mapping[str, Rule], what: str, error: type[Exception]) -> None:
    """Raise ``error`` naming the first field of ``cfg`` whose value its rule refuses."""
    for name, rule in rules.items():
        check_value(name, getattr(cfg, name), rule, error, f"{what} config")


def unruled_fields(cls: type, rules: Mapping[str, Rule]) -> list[str]:
    """The fields of the dataclass ``cls`` that ``rules`` has no rule for (every one should have one)."""
    return sorted({f.name for f in dataclasses.fields(cls)} - set(rules))


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
    """Why ``path`` cannot be the folder a command writes into (an existing file, a path below a file,
    a folder under /proc or /sys, a parent this user cannot write into...), or None."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        return f"the output folder must be a path, got {path!r}"
    path = os.fspath(path)
    if "\0" in path:
        return f"the output folder {path!r} holds a NUL character"
    if on_kernel_file_system(path):
        return f"{path} is under /proc or /sys (a kernel file system, not a place to write results)"
    if os.path.exists(path):
        return None if os.path.isdir(path) else f"{path} exists and is not a folder"
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):  # the nearest existing folder above: it must be a folder we can write into
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent):
        return f"{path} cannot be created: {parent} is a file, not a folder"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"{path} cannot be created: {parent} is not writable"
    return None


def output_file_problem(path: Any) -> str | None:
    """Why ``path`` cannot be a file (or a file name stem) a command writes: an existing folder, or a
    folder above it that :func:`output_dir_problem` refuses; None when it can."""
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        return f"the output file must be a path, got {path!r}"
    if os.path.isdir(path):
        return f"{os.fspath(path)} is a folder, not a file name"
    return output_dir_problem(os.path.dirname(os.path.abspath(path)))
