"""Mutations for the hostile-input fuzz tests (tests/test_fuzz_*.py), drawn with hypothesis.

Two kinds, applied to copies of real files:

* structural (:func:`mutate_structure`): a random walk down a parsed file (dicts, lists, tuples,
  numpy arrays, torch tensors) picks one node and replaces it by a value of the wrong type (None, a
  string, NaN, infinities, huge numbers, a non-whole float, a bool, empty or nested containers, a
  marker that becomes deeply nested JSON), deletes it, or changes it inside (an array's dtype,
  shape, one element set to NaN, a huge value or a non-whole number);
* bytes (:func:`mutate_bytes`): bit flips, a truncation, a duplicated slice, random bytes over a
  region.

:func:`run_fuzz` runs a property over one of two budgets: ``"default"`` (few examples, a fixed seed:
the default test run) and ``"long"`` (many examples, random seeds: the tests marked slow).
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

DEEP_MARKER = "__fuzz_deeply_nested__"
"""A string that :func:`to_json` turns into 100,000 nested JSON lists."""

WRONG_VALUES: list[Any] = [
    None, "ten", "", "False", float("nan"), float("inf"), -float("inf"), -1, 0, 12.7, 10**30, -(10**30), 2**63,
    1e300, True, [], {}, [None], ["x", "y"], [[[[[]]]]], {"a": {"b": None}}, DEEP_MARKER,
]
"""What a field may be replaced by: wrong types, non-finite and huge numbers, containers."""

BUDGETS = {"default": dict(max_examples=20, derandomize=True), "long": dict(max_examples=250, derandomize=False)}
"""Examples per fuzz target: the default run's fixed-seed budget, and the slow run's."""


def _children(node: Any) -> list:
    if isinstance(node, dict):
        return list(node.keys())
    if isinstance(node, (list, tuple)):
        return list(range(len(node)))
    return []


def _is_array(node: Any) -> bool:
    return isinstance(node, np.ndarray) or type(node).__name__ == "Tensor"


def _mutated_array(data, node: Any) -> Any:
    """A changed copy of an array or tensor (a tensor stays a tensor when the change allows it)."""
    is_tensor = not isinstance(node, np.ndarray)
    a = node.detach().cpu().numpy().copy() if is_tensor else np.array(node, copy=True)
    if a.dtype.kind not in "biuf":  # strings or objects: numbers where text was, None, fewer rows
        kind = data.draw(st.sampled_from(["numbers", "objects", "drop_row", "empty"]), label="text array mutation")
        if kind == "numbers":
            return np.arange(len(a), dtype=np.float64) + 0.5 if a.ndim else np.float64(0.5)
    else:
        kind = data.draw(st.sampled_from(["nan", "huge", "non_whole", "strings", "objects", "drop_row", "flatten", "negate",
                                          "empty", "bools"]), label="array mutation")
    if kind in ("nan", "huge", "negate", "non_whole") and a.size:
        if kind in ("nan", "non_whole") or a.dtype.kind == "b":
            a = a.astype(np.float64)
        elif kind == "negate" and a.dtype.kind == "u":
            a = a.astype(np.int64)
        i = data.draw(st.integers(0, a.size - 1), label="element")
        flat = a.reshape(-1)
        if kind == "nan":
            flat[i] = np.nan
        elif kind == "huge":
            flat[i] = np.iinfo(a.dtype).max if a.dtype.kind in "iu" else 1e30
        elif kind == "negate":
            flat *= -1
        else:
            flat[i] += 0.5
    elif kind == "strings":
        return a.astype(str)
    elif kind == "objects":
        out = a.astype(object)
        if out.size:
            out.reshape(-1)[0] = None
        return out
    elif kind == "drop_row" and a.ndim and len(a):
        a = a[:-1]
    elif kind == "flatten":
        a = a.reshape(-1)
    elif kind == "empty":
        a = a[:0]
    elif kind == "bools":
        a = a != 0 if a.dtype.kind in "iufb" else a
    if is_tensor:
        import torch

        return torch.from_numpy(np.ascontiguousarray(a))
    return a


def mutate_structure(data, root: Any, leaf_types: tuple = ()) -> Any:
    """A copy of ``root`` (only the containers on the mutated path are copied) with one node changed.
    ``leaf_types``: extra types to treat as leaves (never walked into)."""
    path = []
    node = root
    while True:
        keys = _children(node) if not isinstance(node, leaf_types) else []
        if not keys or (path and data.draw(st.integers(0, 3), label="stop here?") == 0):
            break
        key = keys[data.draw(st.integers(0, len(keys) - 1), label="child")]
        path.append(key)
        node = node[key]
    action = data.draw(st.sampled_from(["replace", "replace", "delete", "inner"]), label="action")
    if action == "inner" and _is_array(node):
        new = _mutated_array(data, node)
    elif action == "inner" and isinstance(node, (int, float)) and not isinstance(node, bool):
        new = data.draw(st.sampled_from([float(node) + 0.5, -node - 1, node * 10**12, float("nan"), str(node), bool(node)]),
                        label="number mutation")
    elif action == "delete" and path:
        return _set(root, path, None, delete=True)
    else:
        new = data.draw(st.sampled_from(WRONG_VALUES), label="wrong value")
    return _set(root, path, new) if path else new


def _set(root: Any, path: list, value: Any, delete: bool = False) -> Any:
    if not path:
        return value
    key, rest = path[0], path[1:]
    copy = root.copy() if isinstance(root, dict) else list(root)  # dict.copy keeps an OrderedDict / defaultdict
    if rest:
        copy[key] = _set(root[key], rest, value, delete)
    elif delete:
        del copy[key]
    else:
        copy[key] = value
    return tuple(copy) if isinstance(root, tuple) else copy


def mutate_bytes(data, blob: bytes) -> bytes:
    """``blob`` with bit flips, a truncation, a duplicated slice or random bytes over a region."""
    n = len(blob)
    kind = data.draw(st.sampled_from(["flip", "flip", "truncate", "duplicate", "overwrite"]), label="byte mutation")
    out = bytearray(blob)
    if kind == "flip":
        for _ in range(data.draw(st.integers(1, 8), label="flips")):
            i = data.draw(st.integers(0, n - 1), label="byte")
            out[i] ^= 1 << data.draw(st.integers(0, 7), label="bit")
    elif kind == "truncate":
        out = out[: data.draw(st.integers(0, n - 1), label="keep bytes")]
    elif kind == "duplicate":
        i = data.draw(st.integers(0, n - 1), label="from")
        j = data.draw(st.integers(i, min(n, i + 4096)), label="to")
        out[j:j] = out[i:j]
    else:
        i = data.draw(st.integers(0, n - 1), label="at")
        noise = data.draw(st.binary(min_size=1, max_size=64), label="noise")
        out[i : i + len(noise)] = noise
    return bytes(out)


def to_json(value: Any) -> str:
    """JSON text of a mutated structure: NaN and infinities as Python's json writes them
    (``NaN``, ``Infinity``), :data:`DEEP_MARKER` as 100,000 nested lists."""
    import json

    text = json.dumps(value, default=_jsonable)
    return text.replace(json.dumps(DEEP_MARKER), "[" * 100_000 + "]" * 100_000)


def _jsonable(value: Any) -> Any:
    if _is_array(value):
        return np.asarray(value).tolist()
    raise TypeError(f"not JSON: {type(value).__name__}")


def run_fuzz(budget: str, check: Callable[[Any], None]) -> None:
    """Run ``check(data)`` (``data``: hypothesis's draw object) on the budget's examples."""

    @settings(database=None, deadline=None, print_blob=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
              **BUDGETS[budget])
    @given(st.data())
    def fuzz(data):
        check(data)

    fuzz()
