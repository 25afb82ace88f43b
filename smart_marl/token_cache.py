"""Pre-tokenized training data: scenes -> the arrays a training step reads, computed once.

A teacher-forced training sample without token noise is a pure function of the scene, the two
vocabularies, the road-type set and the road crop radius, except for the road pieces hidden for the
road task, which are drawn per sample. So the rolling matching and the road-piece matching can be
done once, here, instead of in every DataLoader worker of every run. A token cache is a folder:

* ``tokens-*.npz``: one shard per input file, the :func:`~smart_marl.model.batch.scene_tensors`
  arrays of its scenes concatenated along agents, road pieces and successor pairs, with offsets;
  token ids as int16, road piece points (in the piece's frame) in whole millimetres as int16, every
  pose exact (a token's start pose as the bitwise difference from the pose the agent reached at
  the step before, mostly zeros), in an LZMA-compressed ``.npz``; about 25 kB per SUMO scene;
* ``token_cache.json``: the manifest (vocabulary content hashes, road types, crop radius, shards and
  scenario ids). Shards are written atomically and a rerun skips inputs already done.

:class:`TokenCache` reads such a folder as a dataset whose items are what
:class:`smart_marl.train.TokenizedScenes` gives for the same scenes, to that rounding;
``smart-marl train data=DIR`` uses it when ``DIR`` is a token cache. The shards are about 20x smaller than the scenes, which is what lets a training set travel to a rented GPU.
"""

from __future__ import annotations

import io
import json
import os
import sys
import time
import zipfile
from concurrent.futures import as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from .errors import ScenarioReadError, SmartMarlError, regular_file_problem
from .model.batch import RoadSettings, scene_road, scene_tensors
from .readers import expand_paths, read_scenarios
from .readers.scene_cache import atomic_write
from .tokens.motion import MotionVocabulary, tokenize_motion
from .tokens.road import RoadVocabulary
from .workers import worker_pool

__all__ = ["MANIFEST", "TokenCache", "TokenCacheError", "is_token_cache", "pretokenize"]

MANIFEST = "token_cache.json"
MANIFEST_EVERY = 50  # files: how often a run writes its manifest (what a rerun skips)
KIND = "smart-marl token cache"
VERSION = 1

_AGENT = ("agent_tokens", "agent_valid", "agent_type", "agent_shape", "agent_start_pose", "agent_pose",
          "target_tokens", "target_valid")
_ROAD = ("road_points", "road_pose", "road_type", "road_light", "road_token")
_STORED = {"agent_tokens": np.int16, "target_tokens": np.int16, "agent_type": np.int8, "road_type": np.int16,
           "road_light": np.int8, "road_token": np.int16, "road_pairs": np.int32}
_READ = {"agent_tokens": np.int64, "target_tokens": np.int64, "agent_type": np.int64, "road_type": np.int64,
         "road_light": np.int64, "road_token": np.int64, "road_pairs": np.int64}
_MM = 1000.0  # road points: stored units per metre (poses stay exact: the loss feels 0.5 mm of a pose)
_INT16_MAX_M = 32.0  # road points are in their piece's frame: a few metres


def _quantize(name: str, value: np.ndarray) -> np.ndarray:
    if name == "road_points":
        v = np.asarray(value, np.float64)
        if len(v) and np.abs(v).max() > _INT16_MAX_M:
            raise TokenCacheError(f"a road piece reaches {np.abs(v).max():.1f} m from its own origin (at most {_INT16_MAX_M} m is stored)")
        return np.round(v * _MM).astype(np.int16)
    return np.asarray(value).astype(_STORED[name], copy=False) if name in _STORED else np.asarray(value)


def _dequantize(name: str, value: np.ndarray) -> np.ndarray:
    if name == "road_points":
        return (value / _MM).astype(np.float32)
    return value.astype(_READ[name]) if name in _READ else value.copy()


def _previous_pose_bits(pose: np.ndarray) -> np.ndarray:
    """The bits of each agent's pose at the step before ([N, S, 3] float32 -> uint32; zeros at step 0)."""
    prev = np.zeros(pose.shape, np.uint32)
    prev[:, 1:] = np.ascontiguousarray(pose[:, :-1], dtype=np.float32).view(np.uint32)
    return prev


def _write_npz_lzma(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` (a zip of ``.npy`` members) whose members are LZMA-compressed: ``np.load`` reads it."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_LZMA) as zf:
        for name, value in arrays.items():
            with zf.open(f"{name}.npy", "w") as f:
                np.lib.format.write_array(f, np.ascontiguousarray(value), allow_pickle=False)
    return buf.getvalue()


class TokenCacheError(SmartMarlError, ValueError):
    """A token cache that cannot be read, or that does not fit the run that reads it."""


def is_token_cache(path: str | os.PathLike) -> bool:
    return os.path.isdir(path) and (Path(path) / MANIFEST).is_file()


# ------------------------------------------------------------------------------------- writing
def _shard_name(index: int, source: str) -> str:
    return f"tokens-{index:06d}-{Path(source).stem[:60]}.npz"


def _pack(items: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate per-scene arrays along their first axis, with ``*_offsets`` [n + 1] per group."""
    out: dict[str, np.ndarray] = {}
    for group, names, count in (("agent", _AGENT, "agent_type"), ("road", _ROAD, "road_token"), ("pair", ("road_pairs",), "road_pairs")):
        sizes = [len(it[count]) for it in items]
        out[f"{group}_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        for name in names:
            out[name] = np.concatenate([_quantize(name, it[name]) for it in items])
    start = np.ascontiguousarray(out["agent_start_pose"], dtype=np.float32).view(np.uint32)
    out["agent_start_pose"] = start ^ _previous_pose_bits(out["agent_pose"])  # exact, and zero where start == reached
    return out


def _tokenize_file(source: str, out_dir: str, index: int, motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary,
                   road_settings: RoadSettings, road_keep_radius_m: float | None) -> dict[str, Any]:
    items, ids = [], []
    for scenario in read_scenarios(source):
        road = scene_road(scenario, road_vocab, road_settings)
        tokens = tokenize_motion(scenario, motion_vocab)
        items.append(scene_tensors(scenario, motion_vocab, road, road_mask_prob=0.0, motion_tokens=tokens,
                                   road_keep_radius_m=road_keep_radius_m))
        ids.append(scenario.scenario_id)
    name = _shard_name(index, source)
    if items:
        try:
            packed = _pack(items)
        except TokenCacheError as exc:
            raise TokenCacheError(f"{source}: {exc}") from None
        atomic_write(Path(out_dir) / name, [_write_npz_lzma(packed)])
    return {"source": source, "file": name if items else None, "scenario_ids": ids}


_DEFAULTS = {"stop_signs": False}  # settings that caches made before they existed were made with


def _settings(motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary, road: RoadSettings,
              road_keep_radius_m: float | None) -> dict[str, Any]:
    """What a token cache's content depends on besides its scenes (kept in its manifest)."""
    return {"motion_vocab": motion_vocab.content_hash(), "road_vocab": road_vocab.content_hash(), "road_types": road.types,
            "road_keep_radius_m": None if road_keep_radius_m is None else float(road_keep_radius_m),
            "stop_signs": bool(road.stop_signs)}


def pretokenize(sources, out_dir: str | os.PathLike, motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary,
                road: RoadSettings = RoadSettings(), road_keep_radius_m: float | None = None, workers: int = 1,
                progress: bool = True) -> dict[str, Any]:
    """Tokenize every scene of ``sources`` (files, folders, globs, scene caches) into a token cache
    in ``out_dir``; returns the manifest. Resumable: shards already in the folder (of an earlier run
    with the same settings) are kept. ``road_keep_radius_m`` is the training run's crop radius
    (``TrainConfig.road_keep_radius_m`` as resolved, e.g. 30); ``road`` the model's
    :attr:`SmartConfig.road_settings <smart_marl.model.SmartConfig.road_settings>`."""
    largest = max([motion_vocab[t].size for t in range(3)] + [road_vocab.size])
    if largest > np.iinfo(np.int16).max:
        raise TokenCacheError(f"a vocabulary of {largest} tokens: token ids are stored as int16 (at most 32767 tokens)")
    files = expand_paths(sources)
    if not files:
        raise TokenCacheError(f"{sources}: no scene files found")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = {"kind": KIND, "version": VERSION, **_settings(motion_vocab, road_vocab, road, road_keep_radius_m)}
    done: dict[str, dict] = {}
    if (out / MANIFEST).is_file():
        old = _read_manifest(out)
        differ = [k for k in settings if old.get(k, _DEFAULTS.get(k)) != settings[k]]
        if differ:
            raise TokenCacheError(f"{out}: a token cache made with other settings ({', '.join(differ)}); use another --out")
        done = {s["source"]: s for s in old["shards"]}
    todo = [(i, f) for i, f in enumerate(files) if f not in done or not (out / str(done[f]["file"])).is_file()]
    started = time.perf_counter()
    bar = tqdm(total=len(files), initial=len(files) - len(todo), desc="pretokenize", unit="file", disable=not progress,
               file=sys.stderr)
    results = {f: s for f, s in done.items() if f in files}

    def manifest() -> dict[str, Any]:
        shards = [results[f] for f in files if f in results and results[f]["file"]]
        return {**settings, "num_scenes": sum(len(s["scenario_ids"]) for s in shards), "shards": shards}

    def write_manifest() -> None:
        atomic_write(out / MANIFEST, [json.dumps(manifest(), indent=1).encode()])

    def collect(finished) -> None:
        for n, res in enumerate(finished, 1):
            results[res["source"]] = res
            bar.update(1)
            if n % MANIFEST_EVERY == 0:  # a run that is killed hard keeps most of its work
                write_manifest()

    try:
        args = (os.fspath(out), motion_vocab, road_vocab, road, road_keep_radius_m)
        if workers <= 1:
            collect(_tokenize_file(f, args[0], i, *args[1:]) for i, f in todo)
        else:
            pool = worker_pool(workers, spawn=True)
            try:
                futures = [pool.submit(_tokenize_file, f, args[0], i, *args[1:]) for i, f in todo]
                collect(future.result() for future in as_completed(futures))
            finally:  # on an error or an interrupt, queued files are dropped, not waited for
                pool.shutdown(wait=True, cancel_futures=True)
    except ScenarioReadError as exc:
        raise TokenCacheError(f"pretokenize stopped at a bad input: {exc}") from exc
    finally:
        bar.close()
        write_manifest()
    result = manifest()
    result["seconds"] = time.perf_counter() - started
    return result


# ------------------------------------------------------------------------------------- reading
def _read_manifest(root: Path) -> dict[str, Any]:
    path = root / MANIFEST
    problem = regular_file_problem(path)
    if problem:
        raise TokenCacheError(f"{path}: not a readable token cache manifest ({problem})")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise TokenCacheError(f"{path}: not a readable token cache manifest ({exc})") from exc
    if not isinstance(data, dict) or data.get("kind") != KIND:
        raise TokenCacheError(f"{path}: not a token cache manifest (kind {data.get('kind') if isinstance(data, dict) else None!r})")
    if data.get("version") != VERSION:
        raise TokenCacheError(f"{path}: token cache version {data.get('version')!r}, this package reads {VERSION}")
    for shard in data.get("shards", []):
        name = shard.get("file")
        if not isinstance(name, str) or Path(name).name != name or not name.endswith(".npz"):
            raise TokenCacheError(f"{path}: shard entry {name!r} is not a plain .npz file name")
    return data


@dataclass
class _Shard:
    arrays: dict[str, np.ndarray]


class TokenCache(Sequence):
    """A token cache folder as a dataset: ``cache[(index, position)]`` is the training item of scene
    ``index`` (see :class:`smart_marl.train.TokenizedScenes`), its hidden road pieces drawn from
    ``(seed, position)`` with ``road_mask_prob``. Shards are read lazily and kept (a few hundred kB
    per scene, in memory)."""

    def __init__(self, root: str | os.PathLike, seed: int = 0, road_mask_prob: float = 0.15):
        self.root = Path(root)
        self.manifest = _read_manifest(self.root)
        self.seed, self.road_mask_prob = seed, road_mask_prob
        self._where = [(s, j) for s, shard in enumerate(self.manifest["shards"]) for j in range(len(shard["scenario_ids"]))]
        self._shards: dict[int, _Shard] = {}

    def __len__(self) -> int:
        return len(self._where)

    def with_seed(self, seed: int) -> "TokenCache":
        other = TokenCache.__new__(TokenCache)
        other.__dict__.update(self.__dict__)
        other.seed, other._shards = seed, self._shards
        return other

    def check(self, motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary, road: RoadSettings,
              road_keep_radius_m: float | None) -> None:
        """:class:`TokenCacheError` when this cache was made with other vocabularies or settings than a run's
        (``road``: the model's :attr:`SmartConfig.road_settings <smart_marl.model.SmartConfig.road_settings>`)."""
        want = _settings(motion_vocab, road_vocab, road, road_keep_radius_m)
        got = {k: self.manifest.get(k, _DEFAULTS.get(k)) for k in want}
        differ = {k: (got[k], v) for k, v in want.items() if got[k] != v}
        if differ:
            raise TokenCacheError(f"{self.root}: token cache made with other settings than this run's "
                                  f"({', '.join(f'{k}: cache {a!r}, run {b!r}' for k, (a, b) in differ.items())}); "
                                  "pretokenize again with the run's vocabularies, model.road_types, model.stop_signs "
                                  "and road_keep_radius_m")

    def _shard(self, s: int) -> _Shard:
        shard = self._shards.get(s)
        if shard is None:
            path = self.root / self.manifest["shards"][s]["file"]
            problem = regular_file_problem(path)
            if problem:
                raise TokenCacheError(f"{path}: unreadable token shard ({problem})")
            try:
                with np.load(path, allow_pickle=False) as z:
                    arrays = {k: z[k] for k in z.files}
            except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
                raise TokenCacheError(f"{path}: unreadable token shard ({exc})") from exc
            n = len(self.manifest["shards"][s]["scenario_ids"])
            if any(len(arrays.get(f"{g}_offsets", ())) != n + 1 for g in ("agent", "road", "pair")):
                raise TokenCacheError(f"{path}: holds another number of scenes than the manifest's {n}")
            shard = self._shards[s] = _Shard(arrays)
        return shard

    def scenario_id(self, index: int) -> str:
        s, j = self._where[index]
        return self.manifest["shards"][s]["scenario_ids"][j]

    def __getitem__(self, key) -> dict[str, np.ndarray]:
        index, position = key if isinstance(key, tuple) else (key, 0)
        s, j = self._where[index]
        a = self._shard(s).arrays
        item: dict[str, np.ndarray] = {}
        for group, names in (("agent", _AGENT), ("road", _ROAD), ("pair", ("road_pairs",))):
            lo, hi = a[f"{group}_offsets"][j], a[f"{group}_offsets"][j + 1]
            for name in names:
                item[name] = _dequantize(name, a[name][lo:hi])
        item["agent_start_pose"] = (item["agent_start_pose"] ^ _previous_pose_bits(item["agent_pose"])).view(np.float32)
        r = len(item["road_token"])
        rng = np.random.default_rng([self.seed, int(position)])
        item["road_valid"] = np.ones(r, bool)
        item["road_masked"] = rng.random(r) < self.road_mask_prob
        item["road_pair_valid"] = np.ones(len(item["road_pairs"]), bool)
        return item
