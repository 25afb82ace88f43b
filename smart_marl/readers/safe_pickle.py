"""Restricted unpickling for the pickle-based readers (first stage of the data flow: files -> Scenario).

A pickle can import and call any Python global, so an untrusted ``.pkl`` must never go through a
bare :func:`pickle.load`. :func:`load_restricted` resolves only the globals in an allow-list of
``(module, name)`` pairs and refuses every other one with a :class:`ScenarioReadError` *before*
anything is imported or called.

The allow-lists below were taken from what the real files use (``pickletools``):

* ScenarioNet / MetaDrive scenario descriptions: numpy array reconstruction, ``numpy.dtype``,
  numpy scalars, ``collections.defaultdict`` with ``builtins.int`` as factory (format 1.2 and the
  nuScenes conversions), plus the plain-container builtins protocol 2 pickles need.
* SMART preprocessed pickles (dicts of torch tensors written with ``pickle.dump``):
  ``torch._utils._rebuild_tensor_v2`` (replaced by :func:`_rebuild_tensor_checked`, which refuses a
  view that reaches past its storage: torch would grow the storage with uninitialised memory),
  ``torch.storage._load_from_bytes`` (replaced by a loader that calls
  ``torch.load(..., weights_only=True)``), ``collections.OrderedDict`` and numpy scalars. torch is
  imported only when such a file is read (:func:`smart_pickle_globals`).

numpy's reconstruction functions are taken from numpy's own ``__reduce__`` output rather than
imported by name, so pickles written by numpy 1 (``numpy.core``) and numpy 2 (``numpy._core``)
both load without touching numpy's deprecated module aliases.
"""

from __future__ import annotations

import collections
import io
import os
import pickle
from typing import IO, Any, Mapping, Union

import numpy as np

from ..errors import ScenarioReadError, check_regular_file

Allowed = Union[set, frozenset, Mapping]
"""A set of ``(module, name)`` pairs (resolved by import), or a mapping from such pairs to the object
to use instead (``None``: resolve by import)."""

_reconstruct = np.zeros(1).__reduce__()[0]  # numpy.(_)core.multiarray._reconstruct
_scalar = np.float64(0.0).__reduce__()[0]  # numpy.(_)core.multiarray.scalar

NUMPY_GLOBALS: dict[tuple[str, str], Any] = {}
for _module in ("numpy.core.multiarray", "numpy._core.multiarray"):
    NUMPY_GLOBALS[(_module, "_reconstruct")] = _reconstruct
    NUMPY_GLOBALS[(_module, "scalar")] = _scalar
NUMPY_GLOBALS[("numpy", "ndarray")] = np.ndarray
NUMPY_GLOBALS[("numpy", "dtype")] = np.dtype

CONTAINER_GLOBALS: dict[tuple[str, str], Any] = {
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("collections", "defaultdict"): collections.defaultdict,
    ("builtins", "set"): set,
    ("builtins", "frozenset"): frozenset,
    ("builtins", "int"): int,  # defaultdict(int) factory
    ("builtins", "float"): float,
    ("builtins", "complex"): complex,
    ("builtins", "bool"): bool,
}

SCENARIONET_GLOBALS: dict[tuple[str, str], Any] = {**NUMPY_GLOBALS, **CONTAINER_GLOBALS}
"""What ScenarioNet / MetaDrive scenario pickles may import."""


def _load_storage_from_bytes(data: bytes):
    """Stand-in for ``torch.storage._load_from_bytes``: the restricted torch loader, never the full one."""
    import torch

    return torch.load(io.BytesIO(data), weights_only=True)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _rebuild_tensor_checked(storage, storage_offset, size, stride, requires_grad=False, backward_hooks=None,
                            metadata=None):
    """Stand-in for ``torch._utils._rebuild_tensor_v2`` that rebuilds only a plain view inside its
    storage: integer offset, sizes and strides (none negative), every element it addresses within
    the storage's elements, no backward hooks and no tensor metadata. Raises ValueError otherwise
    (the unpickler turns it into a ScenarioReadError naming the file)."""
    import torch
    import torch._utils

    if not isinstance(storage, torch.storage.TypedStorage):
        raise ValueError(f"a tensor is rebuilt from a {type(storage).__name__}, not a torch storage")
    if not (isinstance(size, tuple) and isinstance(stride, tuple) and len(size) == len(stride)
            and all(_is_int(v) and v >= 0 for v in (*size, *stride)) and _is_int(storage_offset) and storage_offset >= 0):
        raise ValueError(f"a tensor view has an invalid offset {storage_offset!r}, size {size!r} or stride {stride!r}")
    if backward_hooks or metadata or not isinstance(requires_grad, bool):
        raise ValueError("a tensor carries backward hooks, metadata or a non-boolean requires_grad")
    elements = storage._size()  # (the public size() warns that TypedStorage is deprecated)
    if all(size):  # an empty view addresses nothing
        last = storage_offset + sum((n - 1) * s for n, s in zip(size, stride))
        if last >= elements:
            raise ValueError(f"a tensor view of size {list(size)}, stride {list(stride)} at offset {storage_offset} reaches "
                             f"element {last} of a storage of {elements} elements")
    return torch._utils._rebuild_tensor_v2(storage, storage_offset, size, stride, requires_grad, collections.OrderedDict())


def smart_pickle_globals() -> dict[tuple[str, str], Any]:
    """What SMART preprocessed pickles may import (imports torch)."""
    return {
        **NUMPY_GLOBALS,
        ("collections", "OrderedDict"): collections.OrderedDict,
        ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor_checked,
        ("torch.storage", "_load_from_bytes"): _load_storage_from_bytes,
    }


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file: IO[bytes], allowed: Mapping[tuple[str, str], Any], path: str):
        super().__init__(file)
        self._allowed = allowed
        self._path = path

    def find_class(self, module: str, name: str) -> Any:
        key = (module, name)
        if key not in self._allowed:
            raise ScenarioReadError(self._path, f"pickle tries to import {module}.{name}, which is not allowed")
        target = self._allowed[key]
        return super().find_class(module, name) if target is None else target

    def persistent_load(self, pid: Any) -> Any:
        raise ScenarioReadError(self._path, "pickle uses persistent ids, which are not allowed")


def load_restricted(path_or_file: str | os.PathLike | IO[bytes], allowed: Allowed,
                    path: str | os.PathLike | None = None) -> Any:
    """Unpickle a file, resolving only the globals in ``allowed``.

    ``path_or_file`` is a path or a binary file object; ``path`` names the file in errors when a file
    object is given. Raises :class:`ScenarioReadError` (naming the file) for a forbidden global
    (nothing is imported or called), a truncated or corrupt pickle, or an unreadable file.
    """
    allowed_map: Mapping[tuple[str, str], Any] = (
        allowed if isinstance(allowed, Mapping) else {tuple(k): None for k in allowed}
    )
    if isinstance(path_or_file, (str, os.PathLike)):
        name = os.fspath(path_or_file)
        check_regular_file(name)
        try:
            with open(name, "rb") as f:
                return _load(f, allowed_map, name)
        except OSError as exc:
            raise ScenarioReadError(name, f"cannot open: {exc.strerror or exc}") from exc
    name = os.fspath(path) if path is not None else str(getattr(path_or_file, "name", "<file object>"))
    return _load(path_or_file, allowed_map, name)


def _load(f: IO[bytes], allowed: Mapping[tuple[str, str], Any], name: str) -> Any:
    try:
        return _RestrictedUnpickler(f, allowed, name).load()
    except ScenarioReadError:
        raise
    except RecursionError as exc:
        raise ScenarioReadError(name, "not a valid pickle: nested too deeply") from exc
    except Exception as exc:  # noqa: BLE001 - UnpicklingError, EOFError, ValueError... all name the file
        raise ScenarioReadError(name, f"not a valid pickle: {type(exc).__name__}: {exc}") from exc


def looks_like_pickle(head: bytes) -> bool:
    """A pickle of protocol 2 or later starts with the PROTO opcode (0x80) and the protocol number."""
    return len(head) >= 2 and head[0] == 0x80 and 2 <= head[1] <= 5


__all__ = ["Allowed", "SCENARIONET_GLOBALS", "NUMPY_GLOBALS", "CONTAINER_GLOBALS", "load_restricted",
           "looks_like_pickle", "smart_pickle_globals"]
