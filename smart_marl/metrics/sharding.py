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
  same input, that the chunks cover exactly each shard's scenes, and every chunk itself (its
  metrics finite and complete, its ``.binproto`` a non-empty submission of exactly its scenes), puts
  the scenes back in input order and aggregates them: the per-scene numbers are stored with full
  float precision (JSON keeps every digit), so the merged numbers equal a single-process run's bit
  for bit. Nothing is written before every chunk has passed.
* **Where a run writes.** Inside the run folder the user named (links resolved: a symlinked shard
  folder or prefix leading out is refused), or at the exact path given on the command line
  (``--write-submission``); never replacing a file the command did not create (a submission part
  is replaced by nothing: one identical to its chunk is kept, any other file refuses the merge);
  every file written whole (a temporary file in the same folder, then a rename or a link). The one
  path ``run.json`` keeps, the submission prefix, is relative to the run folder; one that resolves
  outside it (an older run's absolute prefix, an edited file) is refused naming run.json and the path.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import re
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable, Iterator

from ..config_files import is_integer
from ..errors import ScenarioReadError, SmartMarlError, UsageError, check_regular_file
from ..readers import detect_format, read_scenarios, tfrecord
from ..readers.scene_cache import ShardReader
from ..readers.womd import decode_scenario
from ..scenario import Scenario
from .config import RULES
from .likelihood import ScenarioMetrics
from .run_files import RunDirError, check_chunk_submission, file_mode, file_problem, metrics_from_record, write_whole

RUN_FILE = "run.json"
RESULT_FILE = "result.json"
DONE_FILE = "done.json"
RUN_KIND = "smart_marl_eval_run"
FORMAT_VERSION = 1
_SHARD_DIR = re.compile(r"^shard-(\d{5})-of-(\d{5})$")
_CHUNK_FILE = re.compile(r"^chunk-(\d{6})\.json$")


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
        check_regular_file(path, file_problem)
        data = json.loads(path.read_text())
    except RunDirError:
        raise
    except (OSError, ValueError, RecursionError) as exc:
        raise RunDirError(f"{path}: cannot read it as JSON ({type(exc).__name__}: {exc})") from exc
    if not isinstance(data, dict):
        raise RunDirError(f"{path}: not a JSON object")
    return data


def _json_bytes(data: dict, indent: int | None = None) -> bytes:
    """JSON of a run file (a scene's non-finite number is kept as Python writes it: the merge refuses it, naming it)."""
    return json.dumps(data, indent=indent, separators=None if indent else (",", ":")).encode()


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

    # --- where the run writes
    def within(self, folder: str | os.PathLike) -> bool:
        """Whether ``folder`` (links followed as far as they exist) is the run folder or lies below it."""
        real_root, real = os.path.realpath(self.root), os.path.realpath(folder)
        return real == real_root or real.startswith(real_root.rstrip(os.sep) + os.sep)

    def writable(self, path: Path) -> Path:
        """``path``, a file of the run's layout, once checked: below the run folder (no link in the
        folder leads out of it) and, when it exists, a regular file (a link, folder or FIFO planted
        at one of the run's names is refused, not replaced)."""
        if not self.within(path.parent):
            raise RunDirError(f"{path}: lies outside the run folder {self.root} (a link leads out of it); "
                              "a run writes only inside its folder")
        mode = file_mode(path)
        if mode is None:
            return path
        if not stat.S_ISREG(mode):
            raise RunDirError(f"{path}: exists and is not a regular file (a link, a folder...): the run does not replace it")
        return path

    def make_dir(self, folder: Path) -> None:
        """Create ``folder`` (and the folders above it) below the run folder; RunDirError when a link leads it out."""
        if not self.within(folder):
            raise RunDirError(f"{folder}: lies outside the run folder {self.root} (a link leads out of it); "
                              "a run writes only inside its folder")
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirError(f"{folder}: cannot create the folder: {exc.strerror or exc}") from exc

    def stored_prefix(self, prefix: str | os.PathLike) -> str | None:
        """What run.json keeps of a ``--write-submission`` prefix: its path relative to the run
        folder, or None when it lies outside (a merge then needs the prefix on its command line)."""
        path = Path(prefix)
        if not self.within(path.parent):
            return None
        return os.path.relpath(os.path.join(os.path.realpath(path.parent), path.name), os.path.realpath(self.root))

    def submission_prefix(self, record: dict) -> Path | None:
        """The submission prefix run.json keeps (relative to the run folder; an older run's absolute
        one is taken when it lies inside the folder), as a path below ``root``; None when it keeps
        none. RunDirError naming run.json and the path when it leads out of the folder."""
        value = record.get("submission_prefix")
        if value is None:
            return None
        where = self.root / RUN_FILE
        if not isinstance(value, str) or not value or "\0" in value:
            raise RunDirError(f"{where}: submission_prefix must be a file name below the run folder, got {value!r}")
        path = self.root / value  # an absolute value stays absolute
        if path.name in ("", ".", "..") or not self.within(path.parent):
            raise RunDirError(f"{where}: submission_prefix {value!r} leads outside the run folder {self.root}; "
                              "a merge writes only inside the run folder or where its command line says: "
                              "give --write-submission PREFIX (or correct run.json)")
        return self.root / os.path.relpath(os.path.join(os.path.realpath(path.parent), path.name), os.path.realpath(self.root))

    # --- config
    def start(self, config: dict, extra: dict | None = None) -> dict:
        """Create the folder and its ``run.json``, or check that the one there has this ``config``
        (RunDirError naming the file and the first difference otherwise). ``extra``: informative
        fields kept in run.json but not compared (the submission prefix). Returns run.json."""
        if self.root.exists() and not self.root.is_dir():
            raise RunDirError(f"{self.root}: --out must be a folder (it is a file)")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirError(f"{self.root}: cannot create the run folder: {exc.strerror or exc}") from exc
        path = self.writable(self.root / RUN_FILE)
        record = {"kind": RUN_KIND, "version": FORMAT_VERSION, "id": _config_id(config), "config": config, **(extra or {})}
        if write_whole(path, _json_bytes(record, indent=1), replace=False):  # the first shard to start writes it
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
        config = record["config"]  # the fields the merge computes with: a hand-made run.json gets an error, not a traceback
        count, size, rules = config.get("num_shards"), config.get("chunk_size"), config.get("rules")
        for key, ok, want in (("num_shards", is_integer(count) and 1 <= count <= 99999, "an integer in 1..99999"),
                              ("chunk_size", is_integer(size) and size >= 1, "an integer >= 1"),
                              ("rules", isinstance(rules, str) and rules in RULES, f"one of {sorted(RULES)}"),
                              ("keep_rollouts", isinstance(config.get("keep_rollouts"), bool), "true or false")):
            if not ok:
                raise RunDirError(f"{path}: config.{key} must be {want}, got {config.get(key)!r}")
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
        """Store a finished chunk: its submission file first (when given), then the JSON that marks it
        done (a ``.binproto`` left without its JSON by a killed try is this run's, and replaced)."""
        self.make_dir(self.shard_dir(shard))
        if submission is not None:
            write_whole(self.writable(self.chunk_path(shard, chunk, ".binproto")), submission)
        write_whole(self.writable(self.chunk_path(shard, chunk)),
                    _json_bytes({"run": run_id, "shard": str(shard), "chunk": chunk, "scenes": scenes, "skipped": skipped}))

    def write_done(self, run_id: str, shard: Shard, chunks: int, num_slots: int, bad_files: list[dict]) -> None:
        self.make_dir(self.shard_dir(shard))  # a shard may own no scene at all
        write_whole(self.writable(self.shard_dir(shard) / DONE_FILE),
                    _json_bytes({"run": run_id, "shard": str(shard), "chunks": chunks, "num_slots": num_slots,
                                 "bad_files": bad_files}))

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


def run_shard(run: RunDir, run_id: str, shard: Shard, slots: Iterable[SceneSlot], chunk_size: int,
              score: Callable[[SceneSlot], tuple[dict | None, dict | None, object]],
              pack: Callable[[list], bytes] | None = None, progress: Callable[[Iterable], Iterable] = iter) -> dict:
    """Compute shard ``shard`` of a run, chunk by chunk, skipping the chunks a previous try finished.

    ``score(slot)`` returns ``(scene, skipped, rollouts)``: the scene's record (``{"ordinal",
    "metrics": metrics_record(...)}``) or None, a skip record or None, and what ``pack`` turns into
    the chunk's submission bytes (None when rollouts are not kept). Returns counts of the work done
    (``computed`` / ``resumed`` scenes, ``chunks``, ``num_slots``: the scenes of the whole input);
    the caller writes ``done.json``, since it knows the stream's bad files."""
    run.make_dir(run.shard_dir(shard))  # a shard folder linked out of the run folder: refused before any work
    done_before = {int(m.group(1)) for p in run.shard_dir(shard).iterdir() if (m := _CHUNK_FILE.match(p.name))}
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
    """Check that every shard of ``run`` finished and covers its scenes, and every chunk holds what
    it should (:func:`metrics_from_record`, :func:`check_chunk_submission`), and put the results in
    input order. Reads only: a run that fails a check has nothing written."""
    record = run.load()
    config, run_id = record["config"], record["id"]
    count = config["num_shards"]
    keep = config["keep_rollouts"]
    source = config.get("source")
    rollouts = source.get("rollouts") if isinstance(source, dict) and is_integer(source.get("rollouts")) else None
    header, header_file = None, None
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
                scenes.append((entry["ordinal"], metrics_from_record(entry.get("metrics"), where, config["rules"])))
                seen.append(entry["ordinal"])
            for entry in data["skipped"]:
                if not (isinstance(entry, dict) and all(isinstance(entry.get(k), int) for k in ("ordinal", "file_index", "record"))
                        and all(k in entry for k in ("path", "scenario_id", "reason"))):
                    raise RunDirError(f"{where}: a skipped scene without its number, place or reason")
                skipped.append(((entry["file_index"], entry["record"], 0), {k: entry[k] for k in ("path", "scenario_id", "reason")}))
                seen.append(entry["ordinal"])
            if keep and data["scenes"]:
                part = run.chunk_path(shard, c, ".binproto")
                ids = [entry["metrics"]["scenario_id"] for entry in data["scenes"]]
                this = check_chunk_submission(part, ids, rollouts)
                if header is None:
                    header, header_file = this, part
                elif this != header:
                    raise RunDirError(f"{part}: its submission header differs from {header_file}'s: the chunks of a run "
                                      "share it; delete the chunk's .json to compute the chunk again")
                chunks_out.append(part)
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


# ----------------------------------------------------------------------------- the merge's files
def check_result_target(run: RunDir) -> Path:
    """``RUN/result.json``, once checked that writing it replaces nothing but an earlier merge's result."""
    path = run.writable(run.root / RESULT_FILE)
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError, RecursionError):
            old = None
        if not (isinstance(old, dict) and {"meta_metric", "num_scenarios", "rules", "skipped"} <= set(old)):
            raise RunDirError(f"{path}: exists and is not a merge's result; the merge does not replace a file it did not "
                              "write (move it away)")
    return path


