"""The scene cache: Scenarios from any source, preprocessed into compact shards for fast training reads.

Second stage of the data flow (logs -> Scenario -> **scene cache** -> tokens). A cache is a folder:

* ``*.smsc`` shards, each holding up to ``scenes_per_shard`` Scenarios as raw little-endian arrays
  behind a JSON header (one file: magic, header length, header, 64-byte aligned array data). Reading
  one is an ``mmap`` plus ``np.frombuffer`` views: no decoding, no copy until a batch is built.
* ``parts/*.json``: one marker per finished input file (its shards and scenes). A preprocess run
  that is killed leaves no half-written shard (shards and markers are written to a temporary
  name and renamed) and a rerun skips every input that already has a marker.
* ``manifest.json``: every scene (scenario id, source, frames, agent counts per type, shard),
  every input file and every input that was skipped as bad, with the reason.

:class:`SceneCache` is a map-style dataset (``len`` and ``[i]``) that a ``torch.utils.data.DataLoader``
reads with workers (use ``collate_fn=list`` or a collate of your own); each worker opens the
shards lazily.
"""

from __future__ import annotations

import hashlib
import json
import mmap
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from .errors import ScenarioReadError, SmartMarlError
from .scenario import Scenario

MAGIC = b"SMSC0001"
SHARD_SUFFIX = ".smsc"
MANIFEST = "manifest.json"
MANIFEST_KIND = "smart_marl_scene_cache"
_ALIGN = 64


# ------------------------------------------------------------------------------------ shard files
def _atomic_write(path: Path, chunks: Iterable[bytes]) -> None:
    """Write ``path`` so that it either holds all of ``chunks`` or does not exist/keeps its old
    content: a temporary file in the same folder, fsync, rename."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with open(tmp, "wb") as f:
            for chunk in chunks:
                f.write(chunk)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_shard(path: str | os.PathLike, scenarios: Sequence[Scenario]) -> int:
    """Write Scenarios into one shard file atomically; returns the file's size in bytes."""
    path = Path(path)
    entries, blobs, offset = [], [], 0
    for scenario in scenarios:
        arrays, meta = scenario.to_arrays()
        index = {}
        for name, array in arrays.items():
            data = np.ascontiguousarray(array).astype(array.dtype.newbyteorder("<"), copy=False)
            raw = data.tobytes()
            index[name] = [data.dtype.str, list(data.shape), offset, len(raw)]
            blobs.append(raw)
            pad = (-len(raw)) % _ALIGN
            blobs.append(b"\0" * pad)
            offset += len(raw) + pad
        entries.append({"meta": meta, "arrays": index})
    header = json.dumps({"scenes": entries}, separators=(",", ":")).encode()
    head_len = len(MAGIC) + 8 + len(header)
    head_pad = (-head_len) % _ALIGN
    prefix = MAGIC + struct.pack("<Q", len(header) + head_pad) + header + b" " * head_pad
    _atomic_write(path, [prefix, *blobs])
    return len(prefix) + offset


class ShardReader:
    """The Scenarios of one shard, read through a memory map (zero-copy array views)."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        try:
            self._file = open(self.path, "rb")
            self._map = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError) as exc:
            raise ScenarioReadError(self.path, f"cannot open shard: {exc}") from exc
        if self._map[: len(MAGIC)] != MAGIC:
            raise ScenarioReadError(self.path, "not a smart-marl scene-cache shard (bad magic)")
        start = len(MAGIC) + 8
        if len(self._map) < start:
            raise ScenarioReadError(self.path, f"truncated shard: {len(self._map)} bytes, shorter than its header")
        (header_len,) = struct.unpack_from("<Q", self._map, len(MAGIC))
        if start + header_len > len(self._map):
            raise ScenarioReadError(self.path, f"truncated shard: header of {header_len} bytes runs past the end")
        try:
            self._entries = json.loads(bytes(self._map[start : start + header_len]))["scenes"]
        except (ValueError, KeyError) as exc:
            raise ScenarioReadError(self.path, f"corrupt shard header: {exc}") from exc
        self._data_start = start + header_len

    def __len__(self) -> int:
        return len(self._entries)

    def __getitem__(self, i: int) -> Scenario:
        entry = self._entries[i]
        arrays = {}
        for name, (dtype, shape, offset, nbytes) in entry["arrays"].items():
            count = int(np.prod(shape)) if shape else 1
            try:
                arrays[name] = np.frombuffer(self._map, dtype=np.dtype(dtype), count=count,
                                             offset=self._data_start + offset).reshape(shape)
            except ValueError as exc:
                raise ScenarioReadError(self.path, f"truncated or corrupt array {name!r}: {exc}", record=i) from exc
        # Arrays were validated when the shard was written; skip re-validation on the hot path.
        return Scenario.from_arrays(arrays, entry["meta"], validate=False)

    def __iter__(self) -> Iterator[Scenario]:
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        self._map.close()
        self._file.close()


def is_shard(head: bytes) -> bool:
    return head[: len(MAGIC)] == MAGIC


# ------------------------------------------------------------------------------------ the dataset
def is_cache_dir(path: str | os.PathLike) -> bool:
    manifest = Path(path) / MANIFEST
    if not manifest.is_file():
        return False
    try:
        return json.loads(manifest.read_text()).get("kind") == MANIFEST_KIND
    except ValueError:
        return False


class SceneCache:
    """A preprocessed cache folder as a map-style dataset of Scenarios.

    ``SceneCache(dir)[i]`` is the i-th scene of the manifest; ``shard_paths()`` lists the shard
    files. Safe to hand to DataLoader workers: open shards are not pickled, each process opens its
    own.
    """

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        manifest_path = self.root / MANIFEST
        if not manifest_path.is_file():
            raise ScenarioReadError(self.root, f"not a scene cache: no {MANIFEST} (run `smart-marl preprocess`)")
        self.manifest = json.loads(manifest_path.read_text())
        if self.manifest.get("kind") != MANIFEST_KIND:
            raise ScenarioReadError(manifest_path, "not a smart-marl scene-cache manifest")
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


def _scene_entry(scenario: Scenario, shard_file: str) -> dict[str, Any]:
    summary = scenario.summary()
    return {
        "scenario_id": scenario.scenario_id,
        "source": scenario.source,
        "frames": scenario.num_frames,
        "tracks": scenario.num_tracks,
        "tracks_per_type": summary["tracks_per_type"],
        "shard": shard_file,
    }


def _process_file(path: str, out: str, scenes_per_shard: int, reader_format: str | None) -> dict[str, Any]:
    """Convert one input file into shards plus its marker. Runs in a worker process."""
    from .readers import read_scenarios

    out_dir = Path(out)
    key = _input_key(path)
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(path).name)[:60]
    shards, scenes, pending, nbytes = [], [], [], 0

    def flush() -> None:
        nonlocal nbytes
        name = f"{stem}-{key[:8]}-{len(shards):04d}{SHARD_SUFFIX}"
        nbytes += write_shard(out_dir / name, pending)
        shards.append({"file": name, "scenes": [_scene_entry(s, name) for s in pending]})
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
    _atomic_write(out_dir / "parts" / f"{key}.json", [json.dumps(marker).encode()])
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
    shards = []
    for path in inputs:
        marker = markers.get(path)
        if marker:
            for shard in marker["shards"]:
                shards.append({"file": shard["file"], "input": marker["input"], "scenes": shard["scenes"]})
    manifest = {
        "kind": MANIFEST_KIND,
        "version": 1,
        "created_unix_s": time.time(),
        "num_scenes": sum(len(s["scenes"]) for s in shards),
        "inputs": [os.path.abspath(p) for p in inputs],
        "shards": shards,
        "skipped": skipped,
    }
    _atomic_write(out_dir / MANIFEST, [json.dumps(manifest, indent=1).encode()])


def scene_entry(scenario: Scenario, shard_file: str) -> dict[str, Any]:
    """The manifest entry of one scene written into ``shard_file`` (for :func:`write_manifest`)."""
    return _scene_entry(scenario, shard_file)


def write_manifest(out: str | os.PathLike, shards: list[dict[str, Any]], inputs: Sequence[str] = (),
                   skipped: Sequence[dict[str, str]] = ()) -> None:
    """Write ``manifest.json`` for shards written with :func:`write_shard` by a producer other than
    :func:`preprocess` (e.g. a simulator). ``shards``: ``{"file", "input", "scenes": [scene_entry(...)]}``."""
    manifest = {
        "kind": MANIFEST_KIND,
        "version": 1,
        "created_unix_s": time.time(),
        "num_scenes": sum(len(s["scenes"]) for s in shards),
        "inputs": list(inputs),
        "shards": list(shards),
        "skipped": list(skipped),
    }
    _atomic_write(Path(out) / MANIFEST, [json.dumps(manifest, indent=1).encode()])


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
    from tqdm import tqdm

    from .readers import expand_paths

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
            from concurrent.futures import ProcessPoolExecutor, as_completed

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
