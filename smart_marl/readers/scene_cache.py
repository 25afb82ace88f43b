"""The project's own scene-cache format (``*.smsc`` shards plus ``manifest.json``), written by
:mod:`smart_marl.cache` (and :mod:`smart_marl.sources.sumo`) and read here, so that
``read_scenarios`` and ``smart-marl info`` take a cache folder or shard like any other source.

A shard holds up to ``scenes_per_shard`` Scenarios as raw little-endian arrays behind a JSON header
(one file: magic, header length, header, 64-byte aligned array data); reading one is an ``mmap``
plus ``np.frombuffer`` views (:class:`ShardReader`): no decoding, no copy until a batch is built.
``manifest.json`` lists every scene (scenario id, source, frames, agent counts per type, shard),
every input and every input that was skipped as bad (:func:`write_manifest`, :func:`read_manifest`).
"""

from __future__ import annotations

import json
import mmap
import os
import struct
import time
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence

import numpy as np

from ..errors import ScenarioReadError
from ..scenario import Scenario

NAME = "scene_cache"
MAGIC = b"SMSC0001"
SHARD_SUFFIX = ".smsc"
MANIFEST = "manifest.json"
MANIFEST_KIND = "smart_marl_scene_cache"
_ALIGN = 64


# ------------------------------------------------------------------------------------ shard files
def atomic_write(path: Path, chunks: Iterable[bytes]) -> None:
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
    atomic_write(path, [prefix, *blobs])
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


# --------------------------------------------------------------------------------------- manifest
def is_cache_dir(path: str | os.PathLike) -> bool:
    manifest = Path(path) / MANIFEST
    if not manifest.is_file():
        return False
    try:
        return json.loads(manifest.read_text()).get("kind") == MANIFEST_KIND
    except ValueError:
        return False


def read_manifest(root: str | os.PathLike) -> dict[str, Any]:
    """The manifest of a cache folder (a clear error when it is not one)."""
    manifest_path = Path(root) / MANIFEST
    if not manifest_path.is_file():
        raise ScenarioReadError(root, f"not a scene cache: no {MANIFEST} (run `smart-marl preprocess`)")
    manifest = json.loads(manifest_path.read_text())
    if manifest.get("kind") != MANIFEST_KIND:
        raise ScenarioReadError(manifest_path, "not a smart-marl scene-cache manifest")
    return manifest


def shard_paths(root: str | os.PathLike) -> list[Path]:
    """The shard files of a cache folder, in manifest order (a clear error when it holds no scene)."""
    shards = read_manifest(root)["shards"]
    if not any(shard["scenes"] for shard in shards):
        raise ScenarioReadError(root, "the scene cache holds no scene")
    return [Path(root) / shard["file"] for shard in shards]


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
    ``shards``: ``{"file", "input", "scenes": [scene_entry(...)]}``."""
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
