"""The scene cache: Scenarios from any source, preprocessed into compact shards for fast training reads.

Second stage of the data flow (logs -> Scenario -> **scene cache** -> tokens). A cache is a folder:

* ``*.smsc`` shards and ``manifest.json``: the format, its writer and its reader live in
  :mod:`smart_marl.readers.scene_cache` (a cache folder is one more source for ``read_scenarios``);
  ``write_shard``, ``ShardReader`` and ``write_manifest`` are importable from here too;
* ``parts/*.json``: one marker per finished input file (its shards and scenes). A preprocess run
  that is killed leaves no half-written shard (shards and markers are written to a temporary
  name and renamed) and a rerun skips every input that already has a marker.

:class:`SceneCache` is a map-style dataset (``len`` and ``[i]``) that a ``torch.utils.data.DataLoader``
reads with workers (use ``collate_fn=list`` or a collate of your own); each worker opens the
shards lazily. :func:`preprocess` converts scene files of any format into a cache.
"""

from __future__ import annotations

import hashlib
import json
import os
import sys
import time
from concurrent.futures import as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

from tqdm import tqdm

from .errors import ScenarioReadError, SmartMarlError, UsageError
from .readers import expand_paths, read_scenarios
from .readers.scene_cache import (
    MANIFEST, MANIFEST_KIND, SHARD_SUFFIX, ShardReader, atomic_write, file_sha256, is_cache_dir, listed_scene, load_manifest,
    open_listed_shard, read_manifest, scene_entry, shard_name_problem, write_manifest, write_shard,
)
from .scenario import Scenario
from .workers import worker_pool

__all__ = [
    "MANIFEST", "MANIFEST_KIND", "SHARD_SUFFIX", "PreprocessError", "PreprocessReport", "SceneCache", "ShardReader",
    "is_cache_dir", "preprocess", "scene_entry", "write_manifest", "write_shard",
]


# ------------------------------------------------------------------------------------ the dataset
class SceneCache:
    """A preprocessed cache folder as a map-style dataset of Scenarios.

    ``SceneCache(dir)[i]`` is the i-th scene of the manifest; ``shard_paths()`` lists the shard
    files. Safe to hand to DataLoader workers: open shards are not pickled, each process opens its
    own. The manifest is checked when the cache is opened (shard entries must be plain file names
    inside the folder) and against the shards when they are read (each shard holds as many scenes
    as the manifest lists, with the same scenario ids); a mismatch raises :class:`ScenarioReadError`.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.manifest = read_manifest(self.root)  # checked: shard entries are plain file names with scenario ids
        self.scenes: list[dict[str, Any]] = [s for shard in self.manifest["shards"] for s in shard["scenes"]]
        self._locations = [(k, j) for k, shard in enumerate(self.manifest["shards"]) for j in range(len(shard["scenes"]))]
        self._readers: dict[int, ShardReader] = {}
        if not self.scenes:
            raise ScenarioReadError(self.root, "the scene cache holds no scene")

    def shard_paths(self) -> list[Path]:
        return [self.root / shard["file"] for shard in self.manifest["shards"]]

    def check_shards(self) -> None:
        """Open every shard's header (no scene decoded, no checksum computed) and check that it holds as many scenes
        as the manifest lists: a missing, truncated or mismatched shard is a :class:`ScenarioReadError` now, not at
        the first read that reaches it (a scene pool read lazily may reach it hours into a run)."""
        for k, shard in enumerate(self.manifest["shards"]):
            reader = ShardReader(self.root / shard["file"])
            try:
                if len(reader) != len(shard["scenes"]):
                    raise ScenarioReadError(reader.path, f"holds {len(reader)} scenes, the manifest lists {len(shard['scenes'])}")
            finally:
                reader.close()

    def __len__(self) -> int:
        return len(self._locations)

    def _reader(self, k: int) -> ShardReader:
        reader = self._readers.get(k)
        if reader is None:
            reader = self._readers[k] = open_listed_shard(self.root, self.manifest["shards"][k])
        return reader

    def __getitem__(self, i: int) -> Scenario:
        k, j = self._locations[i]
        return listed_scene(self._reader(k), self.manifest["shards"][k], j)

    def __iter__(self) -> Iterator[Scenario]:
        for i in range(len(self)):
            yield self[i]

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_readers"] = {}
        return state


# ------------------------------------------------------------------------------------ preprocess
@dataclass
class PreprocessReport:
    """What a preprocess run did."""

    files: int = 0
    files_done_before: int = 0
    scenes: int = 0
    shards: int = 0
    bytes_written: int = 0
    skipped: list[dict[str, str]] = field(default_factory=list)
    seconds: float = 0.0


def _input_key(path: str) -> str:
    return hashlib.sha1(os.path.abspath(path).encode()).hexdigest()[:16]


def _input_stamp(path: str) -> dict[str, int]:
    st = os.stat(path)
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def _process_file(path: str, out: str, scenes_per_shard: int, reader_format: str | None) -> dict[str, Any]:
    """Convert one input file into shards plus its marker. Runs in a worker process."""
    out_dir = Path(out)
    key = _input_key(path)
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(path).name)[:60]
    shards, pending, nbytes = [], [], 0

    def flush() -> None:
        nonlocal nbytes
        name = f"{stem}-{key[:8]}-{len(shards):04d}{SHARD_SUFFIX}"
        nbytes += write_shard(out_dir / name, pending)
        shards.append({"file": name, "scenes": [scene_entry(s, name) for s in pending], "sha256": file_sha256(out_dir / name)})
        pending.clear()

    try:
        for scenario in read_scenarios(path, format=reader_format):
            pending.append(scenario)
            if len(pending) >= scenes_per_shard:
                flush()
        if pending:
            flush()
    except ScenarioReadError as exc:
        return {"status": "bad", "input": path, "error": str(exc)}
    marker = {"input": os.path.abspath(path), "stamp": _input_stamp(path), "shards": shards, "bytes": nbytes}
    atomic_write(out_dir / "parts" / f"{key}.json", [json.dumps(marker).encode()])
    return {"status": "ok", "input": path, "marker": marker}


def _load_marker(out_dir: Path, path: str, check_stamp: bool = True) -> dict[str, Any] | None:
    """The marker of a converted input, or None when there is none or it cannot be used (the input
    changed since, a shard is gone, the marker is not what preprocess writes): convert it again."""
    marker_path = out_dir / "parts" / f"{_input_key(path)}.json"
    if not marker_path.is_file():
        return None
    try:
        marker = json.loads(marker_path.read_text())
        shards = marker["shards"]
        if not (isinstance(shards, list) and all(isinstance(sh, dict) and shard_name_problem(sh.get("file")) is None
                                                 and isinstance(sh.get("scenes"), list) for sh in shards)):
            return None
        if check_stamp and marker.get("stamp") != _input_stamp(path):
            return None  # the input changed since: convert it again
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError, OSError):
        return None
    if not all((out_dir / shard["file"]).is_file() for shard in shards):
        return None
    return marker


def _write_manifest(out_dir: Path, inputs: list[str], markers: dict[str, dict], skipped: list[dict]) -> None:
    """The manifest of a preprocess run: the shards of every finished input, in input order."""
    shards = [{"file": shard["file"], "input": markers[path]["input"], "scenes": shard["scenes"],
               **({"sha256": shard["sha256"]} if isinstance(shard.get("sha256"), str) else {})}
              for path in inputs if markers.get(path) for shard in markers[path]["shards"]]
    write_manifest(out_dir, shards, inputs=[os.path.abspath(p) for p in inputs], skipped=skipped)


class PreprocessError(SmartMarlError):
    """An input file was bad and ``skip_bad`` was off."""


class CacheConflictError(PreprocessError, UsageError):
    """``out`` already holds a cache of other inputs (and ``append`` was not asked for), or is not a folder."""


def _previous_run(out_dir: Path) -> tuple[list[str], list[dict]]:
    """(the inputs whose scenes the cache already in ``out_dir`` holds, in order; its skipped
    entries); nothing when there is no cache."""
    manifest_path = out_dir / MANIFEST
    if not manifest_path.is_file():
        return [], []
    manifest = load_manifest(manifest_path)
    if not (isinstance(manifest, dict) and manifest.get("kind") == MANIFEST_KIND):
        raise CacheConflictError(f"--out {out_dir}: it holds a {MANIFEST} that is not a scene cache's; choose another folder")
    shards = manifest.get("shards") if isinstance(manifest.get("shards"), list) else []
    with_scenes = [sh.get("input") for sh in shards if isinstance(sh, dict) and isinstance(sh.get("input"), str)]
    skipped = manifest.get("skipped") if isinstance(manifest.get("skipped"), list) else []
    return (list(dict.fromkeys(with_scenes)),
            [e for e in skipped if isinstance(e, dict) and isinstance(e.get("input"), str)])


def preprocess(sources: Iterable[str | os.PathLike] | str, out: str | os.PathLike, workers: int = 1,
               scenes_per_shard: int = 64, skip_bad: bool = False, reader_format: str | None = None,
               progress: bool = True, append: bool = False) -> PreprocessReport:
    """Convert every scene file under ``sources`` into a scene cache at ``out``.

    Resumable: inputs whose marker exists (and whose size and mtime did not change) are not read
    again. A bad input stops the run with :class:`PreprocessError` (what was finished stays, so a
    rerun continues) unless ``skip_bad``, which reports it, records it in the manifest and goes on.
    A cache already in ``out`` that holds scenes of inputs not among ``sources`` is never silently
    replaced: :class:`CacheConflictError`, unless ``append``, which keeps those scenes and adds these.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise UsageError(f"workers must be an integer >= 1, got {workers!r}")
    if isinstance(scenes_per_shard, bool) or not isinstance(scenes_per_shard, int) or scenes_per_shard < 1:
        raise UsageError(f"scenes_per_shard must be an integer >= 1, got {scenes_per_shard!r}")
    started = time.perf_counter()
    out_dir = Path(out)
    if out_dir.exists() and not out_dir.is_dir():
        raise CacheConflictError(f"--out {out_dir}: exists and is not a folder")
    inputs = expand_paths(sources if not isinstance(sources, (str, os.PathLike)) else [sources])
    if not inputs:
        raise ScenarioReadError(os.fspath(out), "no input scene files found")
    previous, previous_skipped = _previous_run(out_dir)
    ours = {os.path.abspath(p) for p in inputs}
    others = [p for p in previous if p not in ours]
    if others and not append:
        raise CacheConflictError(f"--out {out_dir} already holds a scene cache of {len(others)} other input(s) (first: "
                                 f"{others[0]}); pass --append to add these inputs to it, or choose another folder")
    (out_dir / "parts").mkdir(parents=True, exist_ok=True)
    for stale in list(out_dir.glob(".*.tmp-*")) + list((out_dir / "parts").glob(".*.tmp-*")):
        stale.unlink()  # left by a killed run
    markers: dict[str, dict] = {}
    kept = []  # inputs of the cache that this run keeps as they are (append)
    for path in others:
        marker = _load_marker(out_dir, path, check_stamp=os.path.exists(path))
        if marker is None:
            raise CacheConflictError(f"--out {out_dir}: the cache's input {path} has no usable record in parts/ (its "
                                     f"shards are gone?); rebuild the cache in a new folder")
        markers[path] = marker
        kept.append(path)
    report = PreprocessReport(files=len(inputs))
    todo = []
    for path in inputs:
        marker = _load_marker(out_dir, path)
        if marker is None:
            todo.append(path)
        else:
            markers[path] = marker
    report.files_done_before = len(markers) - len(kept)
    if append:
        report.skipped.extend(e for e in previous_skipped if e["input"] not in ours)

    bar = tqdm(total=len(inputs), initial=len(markers), unit="file", desc="preprocess", disable=not progress,
               file=sys.stderr)
    failure: dict | None = None

    def handle(result: dict) -> bool:
        nonlocal failure
        bar.update(1)
        if result["status"] == "ok":
            markers[result["input"]] = result["marker"]
            report.bytes_written += result["marker"]["bytes"]
            return True
        entry = {"input": os.path.abspath(result["input"]), "error": result["error"]}
        report.skipped.append(entry)
        if skip_bad:
            bar.write(f"skipped bad input: {result['error']}", file=sys.stderr)
            return True
        failure = entry
        return False

    try:
        if workers <= 1 or len(todo) <= 1:
            for path in todo:
                if not handle(_process_file(path, os.fspath(out_dir), scenes_per_shard, reader_format)):
                    break
        else:
            with worker_pool(workers) as pool:
                futures = [pool.submit(_process_file, p, os.fspath(out_dir), scenes_per_shard, reader_format) for p in todo]
                for future in as_completed(futures):
                    if not handle(future.result()):
                        for f in futures:
                            f.cancel()
                        break
    finally:
        bar.close()
        _write_manifest(out_dir, kept + inputs, markers, report.skipped)
    for marker in markers.values():
        report.shards += len(marker["shards"])
        report.scenes += sum(len(s["scenes"]) for s in marker["shards"])
    report.seconds = time.perf_counter() - started
    if failure is not None:
        raise PreprocessError(f"{failure['error']} (finished inputs are kept; fix or remove the file, or rerun with "
                              f"--skip-bad to record it and go on)")
    return report
