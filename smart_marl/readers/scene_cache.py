"""The project's own scene-cache format (``*.smsc`` shards plus ``manifest.json``), written by
:mod:`smart_marl.cache` (and :mod:`smart_marl.sources.sumo`) and read here, so that
``read_scenarios`` and ``smart-marl info`` take a cache folder or shard like any other source.

A shard holds up to ``scenes_per_shard`` Scenarios as raw little-endian arrays behind a JSON header
(one file: magic, header length, header, 64-byte aligned array data); reading one is an ``mmap``
plus ``np.frombuffer`` views (:class:`ShardReader`): no decoding, no copy until a batch is built.
``manifest.json`` lists every scene (scenario id, source, frames, agent counts per type, shard),
every input and every input that was skipped as bad (:func:`write_manifest`, :func:`read_manifest`),
and each shard's SHA-256 (``sha256``), which a reader checks when it opens the shard (a manifest written
before the checksums has none: its shards are read as before).
"""

from __future__ import annotations

import functools
import hashlib
import json
import math
import mmap
import os
import struct
import tempfile
import time
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from ..errors import ScenarioReadError, check_regular_file
from ..scenario import RoadMap, Scenario, TrafficLights, Tracks
from .common import read_errors

NAME = "scene_cache"
MULTI_SCENE = True  # several scenes per shard: errors name the scene index
MAGIC = b"SMSC0001"
SHARD_SUFFIX = ".smsc"
MANIFEST = "manifest.json"
MANIFEST_KIND = "smart_marl_scene_cache"
_ALIGN = 64


# ------------------------------------------------------------------------------------ shard files
def atomic_write(path: Path, chunks: Iterable[bytes]) -> None:
    """Write ``path`` so that it either holds all of ``chunks`` or does not exist/keeps its old
    content: a new temporary file in the same folder (``mkstemp``: a name that did not exist, so never written
    through a link planted at a guessable name), fsync, rename."""
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as f:
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
    atomic_write(path, [prefix, *blobs])
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
        with read_errors(self.path, i):
            return Scenario.from_arrays(arrays, entry["meta"], validate=True)

    def __iter__(self) -> Iterator[Scenario]:
        for i in range(len(self)):
            yield self[i]

    def content(self) -> memoryview:
        """The shard file's bytes (a view of the memory map)."""
        return memoryview(self._map)

    def close(self) -> None:
        try:
            self._map.close()
        except BufferError:
            pass  # arrays of a scene still view the map (e.g. one that failed its checks): it closes when they go
        self._file.close()


def is_shard(head: bytes) -> bool:
    return head[: len(MAGIC)] == MAGIC


# --------------------------------------------------------------------------------------- manifest
def load_manifest(path: str | os.PathLike) -> Any:
    """The JSON content of a manifest file (not yet checked), a named error when it does not parse."""
    check_regular_file(path)
    try:
        return json.loads(Path(path).read_text())
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ScenarioReadError(path, f"corrupt manifest: {type(exc).__name__}: {exc}") from exc


def is_cache_dir(path: str | os.PathLike) -> bool:
    manifest = Path(path) / MANIFEST
    if not manifest.is_file():
        return False
    try:
        data = load_manifest(manifest)
    except ScenarioReadError:
        return False
    return isinstance(data, dict) and data.get("kind") == MANIFEST_KIND


def shard_name_problem(name: Any) -> str | None:
    """Why a manifest's shard entry does not name a shard file inside the cache folder, or None."""
    if not isinstance(name, str) or not name:
        return f"shard file {name!r} is not a file name"
    if name != os.path.basename(name) or name in (".", "..") or os.path.isabs(name) or "\\" in name:
        return f"shard file {name!r} is not a plain file name inside the cache folder"
    if not name.endswith(SHARD_SUFFIX):
        return f"shard file {name!r} does not end in {SHARD_SUFFIX}"
    return None


def read_manifest(root: str | os.PathLike) -> dict[str, Any]:
    """The manifest of a cache folder, checked: a clear error when it is not one, or when a shard
    entry is not a plain file name inside the folder with a list of scenes (each with a scenario_id)."""
    manifest_path = Path(root) / MANIFEST
    if not manifest_path.is_file():
        raise ScenarioReadError(root, f"not a scene cache: no {MANIFEST} (run `smart-marl preprocess`)")
    manifest = load_manifest(manifest_path)
    if not isinstance(manifest, dict) or manifest.get("kind") != MANIFEST_KIND:
        raise ScenarioReadError(manifest_path, "not a smart-marl scene-cache manifest")
    shards = manifest.get("shards")
    if not isinstance(shards, list):
        raise ScenarioReadError(manifest_path, "corrupt manifest: 'shards' is not a list")
    for k, shard in enumerate(shards):
        if not (isinstance(shard, dict) and isinstance(shard.get("scenes"), list)
                and all(isinstance(e, dict) and isinstance(e.get("scenario_id"), str) for e in shard["scenes"])):
            raise ScenarioReadError(manifest_path, "corrupt manifest: a shard entry needs 'file' and 'scenes' "
                                                   "(each with a scenario_id)", record=f"shards[{k}]")
        problem = shard_name_problem(shard.get("file"))
        if problem:
            raise ScenarioReadError(manifest_path, problem, record=f"shards[{k}]")
        digest = shard.get("sha256")
        if digest is not None and not (isinstance(digest, str) and len(digest) == 64
                                       and all(c in "0123456789abcdef" for c in digest)):
            raise ScenarioReadError(manifest_path, f"sha256 {digest!r} is not a SHA-256 hex digest", record=f"shards[{k}]")
    return manifest


def shard_paths(root: str | os.PathLike) -> list[Path]:
    """The shard files of a cache folder, in manifest order (a clear error when it holds no scene)."""
    shards = read_manifest(root)["shards"]
    if not any(shard["scenes"] for shard in shards):
        raise ScenarioReadError(root, "the scene cache holds no scene")
    return [Path(root) / shard["file"] for shard in shards]


def file_sha256(path: str | os.PathLike) -> str:
    """The SHA-256 (hex) of a file's content, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def open_listed_shard(root: str | os.PathLike, shard: dict[str, Any]) -> ShardReader:
    """A manifest's shard entry opened, checked to hold as many scenes as the entry lists and, when the
    entry records one, to have the content checksum the manifest says."""
    reader = ShardReader(Path(root) / shard["file"])
    if "sha256" in shard and hashlib.sha256(reader.content()).hexdigest() != shard["sha256"]:
        reader.close()
        raise ScenarioReadError(reader.path, "its content differs from the checksum the manifest recorded (sha256): the "
                                             "shard changed after it was written")
    if len(reader) != len(shard["scenes"]):
        reader.close()
        raise ScenarioReadError(reader.path, f"holds {len(reader)} scenes, the manifest lists {len(shard['scenes'])}")
    return reader


def listed_scene(reader: ShardReader, shard: dict[str, Any], j: int) -> Scenario:
    """Scene ``j`` of a shard opened with :func:`open_listed_shard`, checked to be the scene its manifest
    entry lists (the same scenario id)."""
    scenario = reader[j]
    listed = shard["scenes"][j]["scenario_id"]
    if scenario.scenario_id != listed:
        raise ScenarioReadError(reader.path, f"holds scene {scenario.scenario_id!r} where the manifest lists {listed!r}",
                                record=j)
    return scenario


def read_cache(root: str | os.PathLike) -> Iterator[Scenario]:
    """Every scene of a cache folder, in manifest order, checked against the manifest as
    :class:`smart_marl.cache.SceneCache` checks them (a scene missing from a shard, other scenario
    ids, a manifest that lists no scene: :class:`ScenarioReadError`)."""
    manifest = read_manifest(root)
    if not any(shard["scenes"] for shard in manifest["shards"]):
        raise ScenarioReadError(root, "the scene cache holds no scene")
    for shard in manifest["shards"]:
        reader = open_listed_shard(root, shard)
        try:
            for j in range(len(reader)):
                yield Scenario.from_arrays(*_copied(listed_scene(reader, shard, j)), validate=False)
        finally:
            reader.close()


def scene_entry(scenario: Scenario, shard_file: str) -> dict[str, Any]:
    """The manifest entry of one scene written into ``shard_file`` (for :func:`write_manifest`)."""
    summary = scenario.summary()
    return {
        "scenario_id": scenario.scenario_id,
        "source": scenario.source,
        "frames": scenario.num_frames,
        "tracks": scenario.num_tracks,
        "tracks_per_type": summary["tracks_per_type"],
        "shard": shard_file,
    }


def write_manifest(out: str | os.PathLike, shards: list[dict[str, Any]], inputs: Sequence[str] = (),
                   skipped: Sequence[dict[str, str]] = ()) -> None:
    """Write ``manifest.json`` (atomically) for shards written with :func:`write_shard`.
    ``shards``: ``{"file", "input", "scenes": [scene_entry(...)]}``; each gets the ``sha256`` of its file
    (computed here unless the entry has it)."""
    shards = [shard if "sha256" in shard else {**shard, "sha256": file_sha256(Path(out) / shard["file"])} for shard in shards]
    manifest = {
        "kind": MANIFEST_KIND,
        "version": 1,
        "created_unix_s": time.time(),
        "num_scenes": sum(len(s["scenes"]) for s in shards),
        "inputs": list(inputs),
        "shards": list(shards),
        "skipped": list(skipped),
    }
    atomic_write(Path(out) / MANIFEST, [json.dumps(manifest, indent=1).encode()])


# ------------------------------------------------------------------------------- reader plug-in
def sniff(path: str, head: bytes) -> bool:
    return is_shard(head)


def read(path: str) -> Iterator[Scenario]:
    reader = ShardReader(path)
    try:
        for i in range(len(reader)):
            # copy out of the memory map: the reader closes when the stream ends
            yield Scenario.from_arrays(*_copied(reader[i]), validate=False)
    finally:
        reader.close()


def _copied(scenario: Scenario):
    arrays, meta = scenario.to_arrays()
    return {k: v.copy() for k, v in arrays.items()}, meta
