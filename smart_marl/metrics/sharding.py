"""Evaluation at challenge scale: the scenes of a run split over shards, results kept chunk by chunk
so that a killed run resumes, and one merge that gives the numbers of a single-process run.

Stage: metrics, the driver side of the evaluation branch (``smart-marl eval --out``). In: the scene
files, a shard ``I/N`` and the run's config; out: a run folder of per-chunk results, merged into the
realism numbers of :func:`~smart_marl.metrics.likelihood.aggregate` and, when rollouts are kept, a
submission split in files (:mod:`.submission`).

* **Which scene goes where.** The input's scenes are numbered in reading order (files in the order
  :func:`~smart_marl.readers.expand_paths` lists them, records in file order), from 0 over the whole
  input; scene ``k`` belongs to shard ``k mod N`` (:class:`Shard`). The rule depends on the input
  alone, so every machine and every rerun agrees on it. :func:`scene_slots` numbers the scenes
  without decoding them where the format allows it (WOMD TFRecords: records are CRC-checked, not
  parsed; scene-cache shards: the header): a shard decodes only its own scenes.
* **The run folder** (:class:`RunDir`)::

      RUN/run.json                          the run's config (scenes, policy, rules...): every shard
                                            and the merge compare theirs with it
      RUN/shard-00001-of-00004/chunk-000000.json       metrics of the chunk's scenes (+ skipped ones)
      RUN/shard-00001-of-00004/chunk-000000.binproto   with rollouts kept: the chunk's submission file
      RUN/shard-00001-of-00004/done.json    the shard finished (its chunks, the input's scene count)
      RUN/result.json                       the merge: what ``eval --json`` prints

  A chunk is ``chunk_size`` consecutive scenes of one shard; its files are written atomically
  (temporary file, fsync, rename; the ``.binproto`` before the ``.json``, which marks the chunk
  done), so a killed run leaves whole chunks only and a rerun skips them without decoding their scenes.
* **The merge** (:func:`merge_run`) checks that every shard finished with the same config and the
  same input, that the chunks cover exactly each shard's scenes, puts the scenes back in input
  order and aggregates them: the per-scene numbers are stored with full float precision (JSON
  keeps every digit), so the merged numbers equal a single-process run's bit for bit.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

from ..errors import ScenarioReadError, SmartMarlError, UsageError, check_regular_file
from ..readers import detect_format, read_scenarios, tfrecord
from ..readers.scene_cache import ShardReader, atomic_write
from ..readers.womd import decode_scenario
from ..scenario import Scenario
from .likelihood import ScenarioMetrics

RUN_FILE = "run.json"
RESULT_FILE = "result.json"
DONE_FILE = "done.json"
RUN_KIND = "smart_marl_eval_run"
FORMAT_VERSION = 1
_SHARD_DIR = re.compile(r"^shard-(\d{5})-of-(\d{5})$")
_CHUNK_FILE = re.compile(r"^chunk-(\d{6})\.json$")


class RunDirError(SmartMarlError):
    """A run folder that does not hold what this run or this merge expects (the message names the file)."""


# ------------------------------------------------------------------------------------------ shards
@dataclass(frozen=True)
class Shard:
    """Shard ``index`` of ``count``: the scenes whose number k has ``k % count == index``."""

    index: int
    count: int

    def __post_init__(self):
        if not 0 <= self.index < self.count:
            raise UsageError(f"shard {self.index}/{self.count}: the index must be in 0..{self.count - 1}")

    def owns(self, ordinal: int) -> bool:
        return ordinal % self.count == self.index

    @property
    def dirname(self) -> str:
        return f"shard-{self.index:05d}-of-{self.count:05d}"

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """``--shard I/N`` (argparse type): shard I (from 0) of N."""
    m = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r} is not I/N (shard I of N, I from 0, e.g. 0/4)")
    index, count = int(m.group(1)), int(m.group(2))
    if count < 1 or count > 99999:
        raise argparse.ArgumentTypeError(f"{text!r}: N must be in 1..99999")
    if index >= count:
        raise argparse.ArgumentTypeError(f"{text!r}: I must be in 0..{count - 1} (shards count from 0)")
    return Shard(index, count)


def shard_from_torchrun(environ=os.environ) -> Shard | None:
    """The shard of a process launched by ``torchrun`` (``RANK`` of ``WORLD_SIZE``), None outside torchrun."""
    rank, world = environ.get("RANK"), environ.get("WORLD_SIZE")
    if rank is None and world is None:
        return None
    try:
        return parse_shard(f"{rank}/{world}")
    except (argparse.ArgumentTypeError, TypeError) as exc:
        raise UsageError(f"RANK={rank!r} and WORLD_SIZE={world!r} (set by torchrun) do not name a shard: {exc}") from None


# ------------------------------------------------------------------------------------ scene slots
@dataclass(frozen=True)
class SceneSlot:
    """Scene number ``ordinal`` of the input: record ``record`` of file ``file_index`` (``path``);
    ``load()`` decodes it (a :class:`ScenarioReadError` naming the file and record when it cannot).
    Loading is cheapest while the stream stands at the slot (a scene-cache shard is still open)."""

    ordinal: int
    file_index: int
    path: str
    record: int
    load: Callable[[], Scenario]


def _decode_womd(payload: bytes, path: str, record: int) -> Scenario:
    try:
        return decode_scenario(payload, path=path, record=record)
    except ScenarioReadError:
        raise
    except SmartMarlError as exc:
        raise ScenarioReadError(path, str(exc), record=record) from exc
    except Exception as exc:  # noqa: BLE001 - whatever a hostile record provokes, the error names it
        raise ScenarioReadError(path, f"the womd reader failed on it: {type(exc).__name__}: {exc}", record=record) from exc


class _CacheShard:
    """A scene-cache shard open while its slots stream by; a slot loaded later opens it again."""

    def __init__(self, path: str):
        self.path = path
        self.reader: ShardReader | None = ShardReader(path)

    def __len__(self) -> int:
        return len(self.reader)

    def scene(self, i: int) -> Scenario:
        reader = self.reader or ShardReader(self.path)
        try:
            arrays, meta = reader[i].to_arrays()  # copied out of the memory map, as the scene-cache reader does
            return Scenario.from_arrays({k: v.copy() for k, v in arrays.items()}, meta, validate=False)
        finally:
            if reader is not self.reader:
                reader.close()

    def close(self) -> None:
        if self.reader is not None:
            self.reader.close()
            self.reader = None


def _file_records(path: str, format: str | None) -> Iterator[tuple[int, Callable[[], Scenario]]]:
    name = format or detect_format(path)
    check_regular_file(path)
    if name == "womd":
        for record, payload in enumerate(tfrecord.iter_records(path)):
            yield record, (lambda p=payload, r=record: _decode_womd(p, path, r))
    elif name == "scene_cache":
        shard = _CacheShard(path)
        try:
            for record in range(len(shard)):
                yield record, (lambda r=record: shard.scene(r))
        finally:
            shard.close()
    else:  # one scene per file in the other formats: decoding it is reading it
        for record, scenario in enumerate(read_scenarios(path, format=name)):
            yield record, (lambda s=scenario: s)


def scene_slots(paths: Iterable[str], format: str | None = None,
                on_bad_file: Callable[[int, str, int, ScenarioReadError], None] | None = None) -> Iterator[SceneSlot]:
    """Every scene of ``paths`` (files, in this order) as a numbered :class:`SceneSlot`, decoded
    only when its ``load`` is called. A file that cannot be read (its format, a corrupt TFRecord
    frame) raises :class:`ScenarioReadError`, or, with ``on_bad_file(file_index, path, records_read,
    error)``, is reported there and the stream goes on with the next file: the scenes read before
    the failure keep their numbers, so every shard numbers the input the same way."""
    ordinal = 0
    for file_index, path in enumerate(paths):
        records = 0
        try:
            for record, load in _file_records(path, format):
                yield SceneSlot(ordinal, file_index, path, record, load)
                ordinal += 1
                records += 1
        except ScenarioReadError as exc:
            if on_bad_file is None:
                raise
            on_bad_file(file_index, path, records, exc)


def input_digest(paths: list[str]) -> dict:
    """What identifies an input across machines: the files' names relative to their common folder
    and their sizes (a moved copy of the data set matches; a changed file list does not)."""
    root = os.path.commonpath([os.path.dirname(os.path.abspath(p)) for p in paths]) if paths else ""
    h = hashlib.sha256()
    for p in paths:
        h.update(f"{os.path.relpath(os.path.abspath(p), root)}\t{os.path.getsize(p)}\n".encode())
    return {"files": len(paths), "sha256": h.hexdigest()}


# ------------------------------------------------------------------------------------- run folder
def _config_id(config: dict) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()[:16]


def _read_json(path: Path) -> dict:
    try:
        check_regular_file(path, RunDirError)
        data = json.loads(path.read_text())
    except RunDirError:
        raise
    except (OSError, ValueError, RecursionError) as exc:
        raise RunDirError(f"{path}: cannot read it as JSON ({type(exc).__name__}: {exc})") from exc
    if not isinstance(data, dict):
        raise RunDirError(f"{path}: not a JSON object")
    return data


def _write_json(path: Path, data: dict) -> None:
    atomic_write(path, [json.dumps(data, separators=(",", ":")).encode()])


def _create_once(path: Path, payload: bytes) -> bool:
    """Write ``path`` whole unless it exists (then False): a complete temporary file hard-linked to
    its name, so that shards starting at the same time never read a half-written file."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    atomic_write(tmp, [payload])
    try:
        os.link(tmp, path)
        return True
    except FileExistsError:
        return False
    except OSError:  # a file system without hard links: exclusive creation, then the content
        try:
            with open(path, "xb") as f:
                f.write(payload)
            return True
        except FileExistsError:
            return False
    finally:
        tmp.unlink(missing_ok=True)


def _describe_difference(mine: dict, theirs: dict, prefix: str = "") -> str:
    for key in sorted(set(mine) | set(theirs)):
        a, b = mine.get(key), theirs.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            if a != b:
                return _describe_difference(a, b, f"{prefix}{key}.")
        elif a != b:
            return f"{prefix}{key} is {b!r} there, {a!r} here"
    return "they differ"


class RunDir:
    """The folder of one sharded evaluation run (layout in the module docstring). ``config`` (the
    run's identity: input digest, rollout source, rules, shard count, chunk size...) is a plain
    JSON-able dict; every file of the run carries its id, so a file of another run is refused."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    # --- config
    def start(self, config: dict, extra: dict | None = None) -> dict:
        """Create the folder and its ``run.json``, or check that the one there has this ``config``
        (RunDirError naming the file and the first difference otherwise). ``extra``: informative
        fields kept in run.json but not compared (the submission prefix). Returns run.json."""
        if self.root.exists() and not self.root.is_dir():
            raise RunDirError(f"{self.root}: --out must be a folder (it is a file)")
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / RUN_FILE
        record = {"kind": RUN_KIND, "version": FORMAT_VERSION, "id": _config_id(config), "config": config, **(extra or {})}
        if _create_once(path, json.dumps(record, indent=1).encode()):  # the first shard to start writes it
            return record
        existing = self.load()
        theirs = existing["config"].get("num_shards")
        if theirs != config.get("num_shards"):
            raise RunDirError(f"{path}: this run is split in {theirs} shard(s), not {config.get('num_shards')}: "
                              f"a shard of another split cannot join it (give it another --out)")
        if existing["config"] != config:
            raise RunDirError(f"{path}: this folder holds another run ({_describe_difference(config, existing['config'])}); "
                              "give this one another --out, or rerun with the same options")
        return existing

    def load(self) -> dict:
        """``run.json``, checked."""
        path = self.root / RUN_FILE
        if not self.root.is_dir():
            raise RunDirError(f"{self.root}: no such run folder")
        if not path.exists():
            raise RunDirError(f"{self.root}: not an eval run folder (no {RUN_FILE}; it is written by `smart-marl eval --out`)")
        record = _read_json(path)
        if record.get("kind") != RUN_KIND or not isinstance(record.get("config"), dict):
            raise RunDirError(f"{path}: not an eval run file (kind {record.get('kind')!r})")
        if record.get("version") != FORMAT_VERSION:
            raise RunDirError(f"{path}: run format version {record.get('version')!r}; this smart-marl reads version {FORMAT_VERSION}")
        if record.get("id") != _config_id(record["config"]):
            raise RunDirError(f"{path}: its id does not match its config (edited by hand?)")
        return record

    # --- chunks
    def shard_dir(self, shard: Shard) -> Path:
        return self.root / shard.dirname

    def chunk_path(self, shard: Shard, chunk: int, suffix: str = ".json") -> Path:
        return self.shard_dir(shard) / f"chunk-{chunk:06d}{suffix}"

    def read_chunk(self, run_id: str, shard: Shard, chunk: int, need_rollouts: bool) -> dict | None:
        """A finished chunk (checked: this run's, this shard's), or None when it is not there yet."""
        path = self.chunk_path(shard, chunk)
        if not path.exists():
            return None
        data = _read_json(path)
        if data.get("run") != run_id:
            raise RunDirError(f"{path}: a chunk of another run (run id {data.get('run')!r}, this run is {run_id!r}); "
                              "an output folder holds one run")
        if data.get("shard") != str(shard) or data.get("chunk") != chunk:
            raise RunDirError(f"{path}: says it is chunk {data.get('chunk')!r} of shard {data.get('shard')!r}")
        if not isinstance(data.get("scenes"), list) or not isinstance(data.get("skipped"), list):
            raise RunDirError(f"{path}: not a chunk file (no 'scenes' and 'skipped' lists)")
        if need_rollouts and data["scenes"] and not self.chunk_path(shard, chunk, ".binproto").is_file():
            raise RunDirError(f"{path}: its rollouts ({self.chunk_path(shard, chunk, '.binproto').name}) are missing; "
                              "delete the chunk's .json to compute it again")
        return data

    def write_chunk(self, run_id: str, shard: Shard, chunk: int, scenes: list[dict], skipped: list[dict],
                    submission: bytes | None = None) -> None:
        """Store a finished chunk: its submission file first (when given), then the JSON that marks it done."""
        self.shard_dir(shard).mkdir(parents=True, exist_ok=True)
        if submission is not None:
            atomic_write(self.chunk_path(shard, chunk, ".binproto"), [submission])
        _write_json(self.chunk_path(shard, chunk),
                    {"run": run_id, "shard": str(shard), "chunk": chunk, "scenes": scenes, "skipped": skipped})

    def write_done(self, run_id: str, shard: Shard, chunks: int, num_slots: int, bad_files: list[dict]) -> None:
        self.shard_dir(shard).mkdir(parents=True, exist_ok=True)  # a shard may own no scene at all
        _write_json(self.shard_dir(shard) / DONE_FILE, {"run": run_id, "shard": str(shard), "chunks": chunks,
                                                        "num_slots": num_slots, "bad_files": bad_files})

    def read_done(self, run_id: str, shard: Shard) -> dict | None:
        path = self.shard_dir(shard) / DONE_FILE
        if not path.exists():
            return None
        data = _read_json(path)
        if data.get("run") != run_id or data.get("shard") != str(shard):
            raise RunDirError(f"{path}: the end mark of another run or shard (run {data.get('run')!r}, shard {data.get('shard')!r})")
        if not (isinstance(data.get("chunks"), int) and isinstance(data.get("num_slots"), int)
                and isinstance(data.get("bad_files"), list)):
            raise RunDirError(f"{path}: not a shard's end mark (no chunks, num_slots, bad_files)")
        return data


# --------------------------------------------------------------------------- per-scene results
def metrics_record(metrics: ScenarioMetrics) -> dict:
    return dataclasses.asdict(metrics)


def metrics_from_record(record: dict, where: str) -> ScenarioMetrics:
    names = {f.name for f in dataclasses.fields(ScenarioMetrics)}
    numbers = ("meta_metric", "min_ade", "ade", "collision_rate", "offroad_rate", "num_evaluated")
    if not (isinstance(record, dict) and set(record) == names and isinstance(record["likelihoods"], dict)
            and all(_is_number(v) for v in (*(record[k] for k in numbers), *record["likelihoods"].values()))
            and isinstance(record["scenario_id"], str) and isinstance(record["notes"], list)):
        raise RunDirError(f"{where}: a scene's metrics are not a ScenarioMetrics record")
    return ScenarioMetrics(**record)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def run_shard(run: RunDir, run_id: str, shard: Shard, slots: Iterable[SceneSlot], chunk_size: int,
              score: Callable[[SceneSlot], tuple[dict | None, dict | None, object]],
              pack: Callable[[list], bytes] | None = None, progress: Callable[[Iterable], Iterable] = iter) -> dict:
    """Compute shard ``shard`` of a run, chunk by chunk, skipping the chunks a previous try finished.

    ``score(slot)`` returns ``(scene, skipped, rollouts)``: the scene's record (``{"ordinal",
    "metrics": metrics_record(...)}``) or None, a skip record or None, and what ``pack`` turns into
    the chunk's submission bytes (None when rollouts are not kept). Returns counts of the work done
    (``computed`` / ``resumed`` scenes, ``chunks``, ``num_slots``: the scenes of the whole input);
    the caller writes ``done.json``, since it knows the stream's bad files."""
    done_before = {int(m.group(1)) for p in (run.shard_dir(shard).iterdir() if run.shard_dir(shard).is_dir() else ())
                   if (m := _CHUNK_FILE.match(p.name))}
    for c in sorted(done_before):
        run.read_chunk(run_id, shard, c, pack is not None)  # refuse a foreign or broken chunk before any work
    computed = resumed = 0
    current, scenes, skipped, kept = -1, [], [], []

    def flush():
        if current >= 0 and current not in done_before:
            run.write_chunk(run_id, shard, current, scenes, skipped, pack(kept) if pack is not None else None)

    position, num_slots = 0, 0

    def owned():
        nonlocal num_slots
        for slot in slots:
            num_slots = slot.ordinal + 1
            if shard.owns(slot.ordinal):
                yield slot

    for slot in progress(owned()):
        chunk = position // chunk_size
        position += 1
        if chunk != current:
            flush()
            current, scenes, skipped, kept = chunk, [], [], []
        if chunk in done_before:
            resumed += 1
            continue
        scene, skip, rollouts = score(slot)
        if scene is not None:
            scenes.append(scene)
            if rollouts is not None:
                kept.append(rollouts)
        if skip is not None:
            skipped.append(skip)
        computed += 1
    flush()
    return {"computed": computed, "resumed": resumed, "chunks": current + 1, "scenes": position, "num_slots": num_slots}


# ------------------------------------------------------------------------------------------ merge
@dataclass
class MergedRun:
    """A finished run, put back together: every scored scene's metrics and every skip, in input order,
    and the chunk submission files in (shard, chunk) order (empty when rollouts were not kept)."""

    record: dict
    metrics: list[ScenarioMetrics]
    skipped: list[dict]
    submission_chunks: list[Path]


def merge_run(run: RunDir) -> MergedRun:
    """Check that every shard of ``run`` finished and covers its scenes, and put the results in input order."""
    record = run.load()
    config, run_id = record["config"], record["id"]
    count = config["num_shards"]
    keep = bool(config.get("keep_rollouts"))
    for p in sorted(run.root.iterdir()):
        m = _SHARD_DIR.match(p.name)
        if m and int(m.group(2)) != count:
            raise RunDirError(f"{p}: a shard of a {int(m.group(2))}-way split, but this run is split {count} ways "
                              f"({run.root / RUN_FILE}); an output folder holds one split")
    scenes: list[tuple[int, ScenarioMetrics]] = []
    skipped: list[tuple[tuple, dict]] = []
    bad_files: dict[int, dict] = {}
    chunks_out: list[Path] = []
    num_slots = None
    for i in range(count):
        shard = Shard(i, count)
        done = run.read_done(run_id, shard)
        if done is None:
            have = len([p for p in run.shard_dir(shard).glob("chunk-*.json")]) if run.shard_dir(shard).is_dir() else 0
            raise RunDirError(f"{run.shard_dir(shard)}: shard {shard} has not finished ({have} chunk(s) done); "
                              f"run `smart-marl eval ... --out {run.root} --shard {shard}` (it resumes)")
        if num_slots is None:
            num_slots = done["num_slots"]
        elif done["num_slots"] != num_slots:
            raise RunDirError(f"{run.shard_dir(shard) / DONE_FILE}: read {done['num_slots']} scenes in the input, "
                              f"shard 0/{count} read {num_slots}: the shards did not see the same input")
        for bad in done["bad_files"]:
            if not (isinstance(bad, dict) and isinstance(bad.get("file_index"), int) and isinstance(bad.get("records_read"), int)
                    and isinstance(bad.get("path"), str) and isinstance(bad.get("reason"), str)):
                raise RunDirError(f"{run.shard_dir(shard) / DONE_FILE}: a bad-file entry without file_index, records_read, path, reason")
            bad_files.setdefault(bad["file_index"], bad)
        seen = []
        for c in range(done["chunks"]):
            data = run.read_chunk(run_id, shard, c, keep)
            where = str(run.chunk_path(shard, c))
            if data is None:
                raise RunDirError(f"{where}: missing, though {run.shard_dir(shard) / DONE_FILE} lists {done['chunks']} chunks")
            for entry in data["scenes"]:
                if not (isinstance(entry, dict) and isinstance(entry.get("ordinal"), int)):
                    raise RunDirError(f"{where}: a scene without its number")
                scenes.append((entry["ordinal"], metrics_from_record(entry.get("metrics"), where)))
                seen.append(entry["ordinal"])
            for entry in data["skipped"]:
                if not (isinstance(entry, dict) and all(isinstance(entry.get(k), int) for k in ("ordinal", "file_index", "record"))
                        and all(k in entry for k in ("path", "scenario_id", "reason"))):
                    raise RunDirError(f"{where}: a skipped scene without its number, place or reason")
                skipped.append(((entry["file_index"], entry["record"], 0), {k: entry[k] for k in ("path", "scenario_id", "reason")}))
                seen.append(entry["ordinal"])
            if keep and data["scenes"]:
                chunks_out.append(run.chunk_path(shard, c, ".binproto"))
        expected = list(range(i, num_slots, count))
        if sorted(seen) != expected:
            missing = sorted(set(expected) - set(seen))
            raise RunDirError(f"{run.shard_dir(shard)}: its chunks hold {len(seen)} scenes, the shard has {len(expected)}"
                              + (f" (scene {missing[0]} is missing)" if missing else " (some twice or foreign)"))
    for bad in bad_files.values():
        skipped.append(((bad["file_index"], bad["records_read"], 1), {"path": bad["path"], "scenario_id": None, "reason": bad["reason"]}))
    scenes.sort(key=lambda x: x[0])
    skipped.sort(key=lambda x: x[0])
    return MergedRun(record, [m for _, m in scenes], [s for _, s in skipped], chunks_out)


def link_or_copy(source: Path, target: Path) -> None:
    """``target`` becomes a copy of ``source`` (a hard link where the file system allows it), atomically."""
    tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}")
    try:
        try:
            os.link(source, tmp)
        except OSError:
            atomic_write(tmp, [source.read_bytes()])
        os.replace(tmp, target)
    finally:
        if tmp.exists():
            tmp.unlink()
