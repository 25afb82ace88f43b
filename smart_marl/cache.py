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
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator

from tqdm import tqdm

from .errors import ScenarioReadError, SmartMarlError
from .readers import expand_paths, read_scenarios
from .readers.scene_cache import (
    MANIFEST, MANIFEST_KIND, SHARD_SUFFIX, ShardReader, atomic_write, is_cache_dir, read_manifest, scene_entry, write_manifest,
    write_shard,
)
from .scenario import Scenario

__all__ = [
    "MANIFEST", "MANIFEST_KIND", "SHARD_SUFFIX", "PreprocessError", "PreprocessReport", "SceneCache", "ShardReader",
    "is_cache_dir", "preprocess", "scene_entry", "write_manifest", "write_shard",
]


# ------------------------------------------------------------------------------------ the dataset
class SceneCache:
    """A preprocessed cache folder as a map-style dataset of Scenarios.

    ``SceneCache(dir)[i]`` is the i-th scene of the manifest; ``shard_paths()`` lists the shard
    files. Safe to hand to DataLoader workers: open shards are not pickled, each process opens its
    own.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        self.manifest = read_manifest(self.root)
        self.scenes: list[dict[str, Any]] = [s for shard in self.manifest["shards"] for s in shard["scenes"]]
        self._locations = [(k, j) for k, shard in enumerate(self.manifest["shards"]) for j in range(len(shard["scenes"]))]
        self._readers: dict[int, ShardReader] = {}
        if not self.scenes:
            raise ScenarioReadError(self.root, "the scene cache holds no scene")

    def shard_paths(self) -> list[Path]:
        return [self.root / shard["file"] for shard in self.manifest["shards"]]

    def __len__(self) -> int:
        return len(self._locations)

    def __getitem__(self, i: int) -> Scenario:
        k, j = self._locations[i]
        reader = self._readers.get(k)
        if reader is None:
            reader = self._readers[k] = ShardReader(self.root / self.manifest["shards"][k]["file"])
        return reader[j]

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
        shards.append({"file": name, "scenes": [scene_entry(s, name) for s in pending]})
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


def _load_marker(out_dir: Path, path: str) -> dict[str, Any] | None:
    marker_path = out_dir / "parts" / f"{_input_key(path)}.json"
    if not marker_path.is_file():
        return None
    try:
        marker = json.loads(marker_path.read_text())
    except ValueError:
        return None
    if marker.get("stamp") != _input_stamp(path):
        return None  # the input changed since: convert it again
    if not all((out_dir / shard["file"]).is_file() for shard in marker["shards"]):
        return None
    return marker


def _write_manifest(out_dir: Path, inputs: list[str], markers: dict[str, dict], skipped: list[dict]) -> None:
    """The manifest of a preprocess run: the shards of every finished input, in input order."""
    shards = [{"file": shard["file"], "input": markers[path]["input"], "scenes": shard["scenes"]}
              for path in inputs if markers.get(path) for shard in markers[path]["shards"]]
    write_manifest(out_dir, shards, inputs=[os.path.abspath(p) for p in inputs], skipped=skipped)


class PreprocessError(SmartMarlError):
    """An input file was bad and ``skip_bad`` was off."""


def preprocess(sources: Iterable[str | os.PathLike] | str, out: str | os.PathLike, workers: int = 1,
               scenes_per_shard: int = 64, skip_bad: bool = False, reader_format: str | None = None,
               progress: bool = True) -> PreprocessReport:
    """Convert every scene file under ``sources`` into a scene cache at ``out``.

    Resumable: inputs whose marker exists (and whose size and mtime did not change) are not read
    again. A bad input stops the run with :class:`PreprocessError` (what was finished stays, so a
    rerun continues) unless ``skip_bad``, which reports it, records it in the manifest and goes on.
    """
    started = time.perf_counter()
    out_dir = Path(out)
    (out_dir / "parts").mkdir(parents=True, exist_ok=True)
    for stale in list(out_dir.glob(".*.tmp-*")) + list((out_dir / "parts").glob(".*.tmp-*")):
        stale.unlink()  # left by a killed run
    inputs = expand_paths(sources if not isinstance(sources, (str, os.PathLike)) else [sources])
    if not inputs:
        raise ScenarioReadError(os.fspath(out), "no input scene files found")
    report = PreprocessReport(files=len(inputs))
    markers: dict[str, dict] = {}
    todo = []
    for path in inputs:
        marker = _load_marker(out_dir, path)
        if marker is None:
            todo.append(path)
        else:
            markers[path] = marker
    report.files_done_before = len(markers)

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
            with ProcessPoolExecutor(max_workers=workers) as pool:
                futures = [pool.submit(_process_file, p, os.fspath(out_dir), scenes_per_shard, reader_format) for p in todo]
                for future in as_completed(futures):
                    if not handle(future.result()):
                        for f in futures:
                            f.cancel()
                        break
    finally:
        bar.close()
        _write_manifest(out_dir, inputs, markers, report.skipped)
    for marker in markers.values():
        report.shards += len(marker["shards"])
        report.scenes += sum(len(s["scenes"]) for s in marker["shards"])
    report.seconds = time.perf_counter() - started
    if failure is not None:
        raise PreprocessError(f"{failure['error']} (finished inputs are kept; fix or remove the file, or rerun with "
                              f"--skip-bad to record it and go on)")
    return report
