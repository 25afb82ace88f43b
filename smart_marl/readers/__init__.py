"""Readers: driving-log files -> streams of :class:`smart_marl.Scenario`.

One entry point, :func:`read_scenarios`, takes a file, a directory or a glob, picks each file's
format from its content (never from the directory as a whole: a WOMD shard may be named
``training.tfrecord-00000-of-01000``) and yields Scenarios one at a time, so a shard of hundreds of
scenes or a directory of thousands of files is never held in memory at once.

Each format lives in its own module exposing ``NAME`` (the format's name), ``sniff(path, head)``
(does this file look like mine? ``head`` is the file's first bytes) and ``read(path)`` (a generator
of Scenarios). Errors are :class:`smart_marl.errors.ScenarioReadError`, naming file and record.

Whatever a file holds, reading it yields Scenarios or raises a :class:`ScenarioReadError` naming the
file (and the scene's index in it): the readers name what they check, and :func:`read_scenarios`
turns anything a reader did not foresee (a wrongly typed field deep in a structure, a recursion
limit, a declared size the memory cannot hold) into one naming the file, with the original error
chained. Only regular files are opened (a FIFO given as input would block forever).
"""

from __future__ import annotations

import glob as _glob
import importlib
import importlib.util
import os
from pathlib import Path
from typing import Iterable, Iterator

from ..errors import ScenarioReadError, SmartMarlError, UnknownFormatError, UsageError, check_regular_file
from ..scenario import Scenario
from .scene_cache import is_cache_dir, read_cache, shard_paths

# Order matters: the first module whose sniff() accepts a file reads it.
_FORMAT_MODULES = ("scene_cache", "womd", "scenarionet", "smart_pkl", "gpudrive_json", "av2")

# In a directory, only names like these are taken as scene files (README.md, .binproto... are not).
_SCENE_NAME_HINTS = (".smsc", ".tfrecord", "tfrecord-", ".pkl", ".pickle", ".json", ".parquet")
_SNIFF_BYTES = 4096


class UnknownFormatNameError(UsageError):
    """``format=`` names no reader."""


def _formats():
    for name in _FORMAT_MODULES:
        if importlib.util.find_spec(f"{__name__}.{name}") is not None:
            yield importlib.import_module(f"{__name__}.{name}")


def format_names() -> list[str]:
    return [m.NAME for m in _formats()]


def _head(path: str) -> bytes:
    check_regular_file(path)
    try:
        with open(path, "rb") as f:
            return f.read(_SNIFF_BYTES)
    except OSError as exc:
        raise ScenarioReadError(path, f"cannot open: {exc.strerror or exc}") from exc


def detect_format(path: str | os.PathLike) -> str:
    """The name of the format that reads ``path``; UnknownFormatError when none does."""
    path = os.fspath(path)
    head = _head(path)
    for module in _formats():
        try:
            verdict = module.sniff(path, head)
        except Exception as exc:  # noqa: BLE001 - a sniffer choking on a hostile head: named, not a traceback
            raise ScenarioReadError(path, f"cannot tell its format ({module.NAME} check failed: {type(exc).__name__}: {exc})") from exc
        if verdict:
            return module.NAME
    raise UnknownFormatError(
        path,
        "not a scene file of any known format (WOMD Scenario TFRecord, plain or GZIP; ScenarioNet "
        "pickle; SMART preprocessed pickle; GPUDrive/Nocturne JSON; Argoverse 2 scenario parquet)",
    )


def _is_scene_name(name: str) -> bool:
    lower = name.lower()
    return not lower.startswith(".") and any(h in lower for h in _SCENE_NAME_HINTS)


def expand_paths(path_or_glob: str | os.PathLike | Iterable[str | os.PathLike]) -> list[str]:
    """Files named by a path, a directory (searched recursively) or a glob, sorted; a list of those
    is expanded item by item. Companion files that are not scenes on their own (an AV2
    ``log_map_archive_*.json``) are left out of directories and globs."""
    if not isinstance(path_or_glob, (str, os.PathLike)):
        out: list[str] = []
        for item in path_or_glob:
            out.extend(expand_paths(item))
        return out
    text = os.fspath(path_or_glob)
    if os.path.isdir(text) and is_cache_dir(text):
        return [str(p) for p in shard_paths(text)]
    if os.path.isdir(text):
        files = sorted(str(p) for p in Path(text).rglob("*") if p.is_file() and _is_scene_name(p.name))
        return [f for f in files if not _is_companion(f)]
    if os.path.exists(text):
        return [text]
    if any(ch in text for ch in "*?["):
        files = sorted(f for f in _glob.glob(text, recursive=True) if os.path.isfile(f))
        if not files:
            raise ScenarioReadError(text, "the glob matches no file")
        return [f for f in files if not _is_companion(f)]
    raise ScenarioReadError(text, "no such file or directory")


def _is_companion(path: str) -> bool:
    return os.path.basename(path).startswith("log_map_archive_")


def read_scenarios(path_or_glob, format: str | None = None) -> Iterator[Scenario]:
    """Yield the Scenarios in a file, a directory, a glob or a list of them, one at a time.

    ``format`` forces one reader (see :func:`format_names`) instead of detecting it per file.
    """
    modules = {m.NAME: m for m in _formats()}
    if format is not None and format not in modules:
        raise UnknownFormatNameError(f"unknown format {format!r}; known: {', '.join(modules)}")
    for path, is_cache in _inputs(path_or_glob):
        if is_cache and format in (None, "scene_cache"):  # its shards, checked against the manifest (as SceneCache does)
            yield from read_cache(path)
            continue
        for file in expand_paths(path) if is_cache else [path]:
            name = format or detect_format(file)
            check_regular_file(file)
            yield from _guarded(modules[name], file)


def _inputs(path_or_glob) -> Iterator[tuple[str, bool]]:
    """(path, whether it is a scene-cache folder) of every input :func:`expand_paths` would expand."""
    if not isinstance(path_or_glob, (str, os.PathLike)):
        for item in path_or_glob:
            yield from _inputs(item)
        return
    text = os.fspath(path_or_glob)
    if os.path.isdir(text) and is_cache_dir(text):
        yield text, True
    else:
        yield from ((p, False) for p in expand_paths(text))


def _guarded(module, path: str) -> Iterator[Scenario]:
    """``module.read(path)``, with every error that does not already name the file turned into a
    :class:`ScenarioReadError` that does (``record``: the index of the scene being read, in formats
    with several scenes per file)."""
    count = 0
    where = lambda: count if getattr(module, "MULTI_SCENE", False) else None  # noqa: E731
    try:
        for scenario in module.read(path):
            yield scenario
            count += 1
    except ScenarioReadError:
        raise
    except SmartMarlError as exc:
        raise ScenarioReadError(path, str(exc), record=where()) from exc
    except RecursionError as exc:
        raise ScenarioReadError(path, "nested too deeply to read", record=where()) from exc
    except MemoryError as exc:
        raise ScenarioReadError(path, "does not fit in memory (a declared size larger than the data?)", record=where()) from exc
    except Exception as exc:  # noqa: BLE001 - whatever a hostile file provokes, the error names the file
        raise ScenarioReadError(path, f"the {module.NAME} reader failed on it: {type(exc).__name__}: {exc}",
                                record=where()) from exc


def read_scenario(path: str | os.PathLike, index: int = 0, format: str | None = None) -> Scenario:
    """The ``index``-th Scenario of one file."""
    for i, scenario in enumerate(read_scenarios(path, format=format)):
        if i == index:
            return scenario
    raise ScenarioReadError(path, f"has no scene number {index}")
