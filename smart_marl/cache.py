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

import functools
import hashlib
import json
import math
import mmap
import os
import struct
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from .errors import ScenarioReadError, SmartMarlError, UsageError, check_regular_file, naming
from .scenario import RoadMap, Scenario, TrafficLights, Tracks

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


@functools.lru_cache(maxsize=1)
def _array_dtypes() -> dict[str, str]:
    """The name and little-endian dtype of every array a shard stores per scene (what
    :meth:`Scenario.to_arrays` gives, taken from an empty scene so scenario.py stays their one home)."""
    empty = Scenario(scenario_id="-", source="-", timestamps_s=np.zeros(1), current_frame=0,
                     tracks=Tracks(ids=np.zeros(0, np.int64), types=np.zeros(0, np.int8), position=np.zeros((0, 1, 3)),
                                   heading=np.zeros((0, 1)), velocity=np.zeros((0, 1, 2)), size=np.zeros((0, 1, 3)),
                                   valid=np.zeros((0, 1), bool)),
                     road_map=RoadMap.empty(), traffic_lights=TrafficLights.empty(1))
    return {name: a.dtype.newbyteorder("<").str for name, a in empty.to_arrays()[0].items()}


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


class ShardReader:
    """The Scenarios of one shard, read through a memory map (zero-copy array views).

    Nothing in the header is trusted: every scene must list exactly the arrays a Scenario stores,
    each with its own dtype, a shape, and an offset and byte count that agree with the shape and lie
    inside the file; the scene is then validated as any reader's (:class:`Scenario`). A tampered
    shard raises :class:`ScenarioReadError` naming the file and the scene's index."""

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        check_regular_file(self.path)
        try:
            self._file = open(self.path, "rb")
            self._map = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        except (OSError, ValueError) as exc:
            if getattr(self, "_file", None) is not None:
                self._file.close()
            raise ScenarioReadError(self.path, f"cannot open shard: {exc}") from exc
        try:
            self._entries, self._data_start = self._read_header()
        except ScenarioReadError:
            self.close()
            raise

    def _read_header(self) -> tuple[list, int]:
        if self._map[: len(MAGIC)] != MAGIC:
            raise ScenarioReadError(self.path, "not a smart-marl scene-cache shard (bad magic)")
        start = len(MAGIC) + 8
        if len(self._map) < start:
            raise ScenarioReadError(self.path, f"truncated shard: {len(self._map)} bytes, shorter than its header")
        (header_len,) = struct.unpack_from("<Q", self._map, len(MAGIC))
        if start + header_len > len(self._map):
            raise ScenarioReadError(self.path, f"truncated shard: header of {header_len} bytes runs past the end")
        try:
            entries = json.loads(bytes(self._map[start : start + header_len]))["scenes"]
        except (ValueError, KeyError, TypeError, RecursionError) as exc:
            raise ScenarioReadError(self.path, f"corrupt shard header: {type(exc).__name__}: {exc}") from exc
        if not isinstance(entries, list):
            raise ScenarioReadError(self.path, "corrupt shard header: 'scenes' is not a list")
        return entries, start + header_len

    def __len__(self) -> int:
        return len(self._entries)

    def _array(self, i: int, name: str, spec: Any) -> np.ndarray:
        want = _array_dtypes()[name]
        if not (isinstance(spec, list) and len(spec) == 4):
            raise ScenarioReadError(self.path, f"array {name!r}: corrupt index entry {spec!r}", record=i)
        dtype, shape, offset, nbytes = spec
        if dtype != want:
            raise ScenarioReadError(self.path, f"array {name!r} has dtype {dtype!r}, expected {want!r}", record=i)
        if not (isinstance(shape, list) and all(_is_count(d) for d in shape) and _is_count(offset) and _is_count(nbytes)):
            raise ScenarioReadError(self.path, f"array {name!r}: shape {shape!r}, offset {offset!r} or size {nbytes!r} "
                                               f"is not made of non-negative integers", record=i)
        itemsize = np.dtype(want).itemsize
        count = math.prod(shape)
        if count * itemsize != nbytes:
            raise ScenarioReadError(self.path, f"array {name!r}: {nbytes} bytes do not hold shape {shape} of {want}", record=i)
        if self._data_start + offset + nbytes > len(self._map):
            raise ScenarioReadError(self.path, f"truncated shard: array {name!r} runs past the end of the file", record=i)
        return np.frombuffer(self._map, dtype=np.dtype(want), count=count, offset=self._data_start + offset).reshape(shape)

    def __getitem__(self, i: int) -> Scenario:
        entry = self._entries[i]
        if not (isinstance(entry, dict) and isinstance(entry.get("arrays"), dict) and isinstance(entry.get("meta"), dict)):
            raise ScenarioReadError(self.path, "corrupt shard header: a scene without 'meta' and 'arrays'", record=i)
        names = set(entry["arrays"])
        if names != set(_array_dtypes()):
            odd = sorted(names ^ set(_array_dtypes()))
            raise ScenarioReadError(self.path, f"the scene's arrays are not a Scenario's (missing or unknown: {odd[:5]})", record=i)
        arrays = {name: self._array(i, name, spec) for name, spec in entry["arrays"].items()}
        with naming(self.path, i):
            return Scenario.from_arrays(arrays, entry["meta"], validate=True)

    def __iter__(self) -> Iterator[Scenario]:
        for i in range(len(self)):
            yield self[i]

    def close(self) -> None:
        try:
            self._map.close()
        except BufferError:
            pass  # arrays of a scene still view the map (e.g. one that failed its checks): it closes when they go
        self._file.close()


def is_shard(head: bytes) -> bool:
    return head[: len(MAGIC)] == MAGIC


# ------------------------------------------------------------------------------------ the dataset
def _read_manifest(path: Path) -> Any:
    try:
        return json.loads(path.read_text())
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ScenarioReadError(path, f"corrupt manifest: {type(exc).__name__}: {exc}") from exc


def is_cache_dir(path: str | os.PathLike) -> bool:
    manifest = Path(path) / MANIFEST
    if not manifest.is_file():
        return False
    try:
        data = _read_manifest(manifest)
    except ScenarioReadError:
        return False
    return isinstance(data, dict) and data.get("kind") == MANIFEST_KIND


def _shard_name_problem(name: Any) -> str | None:
    """Why a manifest's shard entry does not name a shard file inside the cache folder, or None."""
    if not isinstance(name, str) or not name:
        return f"shard file {name!r} is not a file name"
    if name != os.path.basename(name) or name in (".", "..") or os.path.isabs(name) or "\\" in name:
        return f"shard file {name!r} is not a plain file name inside the cache folder"
    if not name.endswith(SHARD_SUFFIX):
        return f"shard file {name!r} does not end in {SHARD_SUFFIX}"
    return None


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
        manifest_path = self.root / MANIFEST
        if not manifest_path.is_file():
            raise ScenarioReadError(self.root, f"not a scene cache: no {MANIFEST} (run `smart-marl preprocess`)")
        self.manifest = _read_manifest(manifest_path)
        if not isinstance(self.manifest, dict) or self.manifest.get("kind") != MANIFEST_KIND:
            raise ScenarioReadError(manifest_path, "not a smart-marl scene-cache manifest")
        shards = self.manifest.get("shards")
        if not isinstance(shards, list):
            raise ScenarioReadError(manifest_path, "corrupt manifest: 'shards' is not a list")
        for k, shard in enumerate(shards):
            if not (isinstance(shard, dict) and isinstance(shard.get("scenes"), list)
                    and all(isinstance(e, dict) and isinstance(e.get("scenario_id"), str) for e in shard["scenes"])):
                raise ScenarioReadError(manifest_path, "corrupt manifest: a shard entry needs 'file' and 'scenes' "
                                                       "(each with a scenario_id)", record=f"shards[{k}]")
            problem = _shard_name_problem(shard.get("file"))
            if problem:
                raise ScenarioReadError(manifest_path, problem, record=f"shards[{k}]")
        self.scenes: list[dict[str, Any]] = [s for shard in shards for s in shard["scenes"]]
        self._locations = [(k, j) for k, shard in enumerate(shards) for j in range(len(shard["scenes"]))]
        self._readers: dict[int, ShardReader] = {}
        if not self.scenes:
            raise ScenarioReadError(self.root, "the scene cache holds no scene")

    def shard_paths(self) -> list[Path]:
        return [self.root / shard["file"] for shard in self.manifest["shards"]]

    def __len__(self) -> int:
        return len(self._locations)

    def _reader(self, k: int) -> ShardReader:
        reader = self._readers.get(k)
        if reader is None:
            shard = self.manifest["shards"][k]
            reader = ShardReader(self.root / shard["file"])
            if len(reader) != len(shard["scenes"]):
                reader.close()
                raise ScenarioReadError(reader.path, f"holds {len(reader)} scenes, the manifest lists {len(shard['scenes'])}")
            self._readers[k] = reader
        return reader

    def __getitem__(self, i: int) -> Scenario:
        k, j = self._locations[i]
        scenario = self._reader(k)[j]
        listed = self.manifest["shards"][k]["scenes"][j]["scenario_id"]
        if scenario.scenario_id != listed:
            raise ScenarioReadError(self._readers[k].path, f"holds scene {scenario.scenario_id!r} where the manifest lists "
                                                           f"{listed!r}", record=j)
        return scenario

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


def _load_marker(out_dir: Path, path: str, check_stamp: bool = True) -> dict[str, Any] | None:
    """The marker of a converted input, or None when there is none or it cannot be used (the input
    changed since, a shard is gone, the marker is not what preprocess writes): convert it again."""
    marker_path = out_dir / "parts" / f"{_input_key(path)}.json"
    if not marker_path.is_file():
        return None
    try:
        marker = json.loads(marker_path.read_text())
        shards = marker["shards"]
        if not (isinstance(shards, list) and all(isinstance(sh, dict) and _shard_name_problem(sh.get("file")) is None
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


class CacheConflictError(PreprocessError, UsageError):
    """``out`` already holds a cache of other inputs (and ``append`` was not asked for), or is not a folder."""


def _previous_run(out_dir: Path) -> tuple[list[str], list[dict]]:
    """(the inputs whose scenes the cache already in ``out_dir`` holds, in order; its skipped
    entries); nothing when there is no cache."""
    manifest_path = out_dir / MANIFEST
    if not manifest_path.is_file():
        return [], []
    manifest = _read_manifest(manifest_path)
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
    from tqdm import tqdm

    from .readers import expand_paths

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
            from concurrent.futures import as_completed

            from .workers import worker_pool

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
