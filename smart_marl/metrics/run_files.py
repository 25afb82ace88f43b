"""Metrics stage, the files of an evaluation run (:mod:`.sharding`): what a chunk holds, checked before a merge
takes it (its metrics records, its submission file), and the one way the run writes a file where it belongs.

In: a chunk's records and files, a merged submission's prefix; out: checked :class:`~.likelihood.ScenarioMetrics`,
the plan of the submission's files, and those files written whole, never over a file the run did not create
(:class:`RunDirError` naming the file otherwise). The rules themselves are in :mod:`.sharding`'s docstring.
"""

from __future__ import annotations

import dataclasses
import filecmp
import math
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..config_files import is_integer, output_file_problem
from ..errors import ScenarioReadError, SmartMarlError, check_regular_file, on_kernel_file_system
from ..readers.submission import read_submission
from .config import RULES
from .likelihood import ScenarioMetrics
from .submission import submission_shard_name


class RunDirError(SmartMarlError):
    """A run folder that does not hold what this run or this merge expects, or a place it may not
    write (the message names the file)."""


def file_problem(path, problem: str) -> RunDirError:
    """The ``error`` of :func:`~smart_marl.errors.check_regular_file` for a run's files."""
    return RunDirError(f"{path}: {problem}")


def write_whole(path: Path, payload: bytes, replace: bool = True) -> bool:
    """Write ``path`` whole: a new temporary file in its folder (never a name that exists, so never
    through a planted link), fsync, then a rename onto ``path`` (``replace``) or a hard link to it,
    which never replaces a file (False when ``path`` exists). A file system without hard links gets
    ``path`` created exclusively, then filled. A failure is a :class:`RunDirError` naming ``path``."""
    if on_kernel_file_system(path.parent):
        raise RunDirError(f"{path}: under /proc or /sys (a kernel file system, not a place to write results)")
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise RunDirError(f"{path}: cannot write it: {exc.strerror or exc}") from exc
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(payload)
            f.flush()
            os.fsync(f.fileno())
        if replace:
            os.replace(tmp, path)
            return True
        try:
            os.link(tmp, path)
            return True
        except FileExistsError:
            return False
        except OSError:  # no hard links here: exclusive creation, then the content
            try:
                with open(path, "xb") as f:
                    f.write(payload)
                return True
            except FileExistsError:
                return False
    except OSError as exc:
        raise RunDirError(f"{path}: cannot write it: {exc.strerror or exc}") from exc
    finally:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass


def metrics_record(metrics: ScenarioMetrics) -> dict:
    return dataclasses.asdict(metrics)


def metrics_from_record(record: dict, where: str, rules: str | None = None) -> ScenarioMetrics:
    """A scene's metrics as a chunk stores them, checked: every field of :class:`ScenarioMetrics`,
    every number finite (the merge averages them: one NaN would make the run's numbers NaN), and,
    with ``rules``, those rules with a likelihood for each of their features, nothing else."""
    names = {f.name for f in dataclasses.fields(ScenarioMetrics)}
    numbers = ("meta_metric", "min_ade", "ade", "collision_rate", "offroad_rate", "num_evaluated")
    if not (isinstance(record, dict) and set(record) == names and isinstance(record["likelihoods"], dict)
            and isinstance(record["scenario_id"], str) and isinstance(record["rules"], str)
            and isinstance(record["notes"], list)):
        raise RunDirError(f"{where}: a scene's metrics are not a ScenarioMetrics record")
    scene = f"{where}: scenario {record['scenario_id']!r}"
    for name, value in (*((k, record[k]) for k in numbers), *((f"likelihoods.{k}", v) for k, v in record["likelihoods"].items())):
        if not _is_number(value) or not math.isfinite(value):
            raise RunDirError(f"{scene}: {name} is {value!r}, not a finite number")
    if not is_integer(record["num_evaluated"]) or record["num_evaluated"] < 1:
        raise RunDirError(f"{scene}: num_evaluated is {record['num_evaluated']!r}, not a count of agents >= 1")
    if rules is not None:
        if record["rules"] != rules:
            raise RunDirError(f"{scene}: scored with the {record['rules']!r} rules, the run uses {rules!r}")
        want = set(RULES[rules].features)
        if set(record["likelihoods"]) != want:
            odd = sorted(set(record["likelihoods"]) ^ want)
            raise RunDirError(f"{scene}: its likelihoods are not the {rules} rules' features ({odd[0]} "
                              f"{'is missing' if odd[0] in want else 'is not one'})")
    return ScenarioMetrics(**record)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_chunk_submission(path: Path, scenario_ids: list[str], rollouts: int | None = None) -> bytes:
    """A chunk's ``.binproto`` checked before it joins a merged submission: a regular, non-empty
    file that parses as a ``SimAgentsChallengeSubmission`` holding the rollouts of exactly
    ``scenario_ids`` (the scenes its ``.json`` lists, in that order), each with ``rollouts`` joint
    scenes when given. Returns its header (the message without its rollouts, serialized), which
    every chunk of a run shares; RunDirError naming the file otherwise."""
    hint = "delete the chunk's .json to compute the chunk again"
    check_regular_file(path, file_problem)
    if os.path.getsize(path) == 0:
        raise RunDirError(f"{path}: empty (0 bytes), not a chunk's submission file; {hint}")
    try:
        message = read_submission(path)
    except ScenarioReadError as exc:
        raise RunDirError(f"{exc}; {hint}") from exc
    got = [sr.scenario_id for sr in message.scenario_rollouts]
    if got != scenario_ids:
        i = next((i for i, (a, b) in enumerate(zip(got, scenario_ids)) if a != b), min(len(got), len(scenario_ids)))
        what = (f"scenario {got[i]!r} where its .json has {scenario_ids[i]!r}" if i < min(len(got), len(scenario_ids))
                else f"{len(got)} scenario(s) where its .json has {len(scenario_ids)}")
        raise RunDirError(f"{path}: not the rollouts of its chunk's scenes ({what}); {hint}")
    if rollouts is not None:
        odd = next((sr for sr in message.scenario_rollouts if len(sr.joint_scenes) != rollouts), None)
        if odd is not None:
            raise RunDirError(f"{path}: scenario {odd.scenario_id!r} has {len(odd.joint_scenes)} rollouts, "
                              f"the run makes {rollouts}; {hint}")
    message.ClearField("scenario_rollouts")
    return message.SerializeToString(deterministic=True)


@dataclass(frozen=True)
class SubmissionPart:
    """File ``target`` of a merged submission, a copy of the chunk file ``chunk``; ``present``: the
    target is already that copy (an earlier merge's link or copy), nothing to write."""

    chunk: Path
    target: Path
    present: bool


def plan_submission(prefix: Path, chunks: list[Path], what: str) -> list[SubmissionPart]:
    """The files ``PREFIX-00000-of-000NN``... of a merged submission (``what``: where the prefix comes
    from, for messages), checked before anything is written: a place a file can be written (not
    under /proc, no file where a folder should be), and no existing file there but an identical copy
    of its chunk, which is kept. RunDirError naming the file otherwise."""
    if len(chunks) > 99999:
        raise RunDirError(f"{what} {prefix}: the run has {len(chunks)} chunks; a submission is split in 99999 files at most")
    problem = output_file_problem(os.fspath(prefix))
    if problem:
        raise RunDirError(f"{what} {prefix}: {problem}")
    plan = []
    for i, chunk in enumerate(chunks):
        target = Path(submission_shard_name(prefix, i, len(chunks)))
        plan.append(SubmissionPart(chunk, target, _same_file(chunk, target)))
    return plan


def file_mode(path: Path) -> int | None:
    """``os.lstat(path).st_mode`` (links not followed), None where nothing is there; RunDirError naming ``path`` when
    it cannot be looked at."""
    try:
        return os.lstat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise RunDirError(f"{path}: {exc.strerror or exc}") from exc


def _same_file(chunk: Path, target: Path) -> bool:
    """Whether ``target`` holds ``chunk`` already (False: it does not exist); RunDirError when it is another file."""
    mode = file_mode(target)
    if mode is None:
        return False
    if stat.S_ISREG(mode) and (os.path.samefile(chunk, target) or filecmp.cmp(chunk, target, shallow=False)):
        return True
    raise RunDirError(f"{target}: exists and is not this run's submission file (not a copy of {chunk}); the merge does "
                      "not replace a file it did not write: move it away or give another --write-submission")


def write_submission_parts(plan: list[SubmissionPart]) -> None:
    """Write the files of :func:`plan_submission`: each a hard link to its chunk where the file
    system allows it, else a whole copy; never replacing a file (one that appeared meanwhile is an error)."""
    for part in plan:
        if part.present:
            continue
        try:
            part.target.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RunDirError(f"{part.target.parent}: cannot create the folder: {exc.strerror or exc}") from exc
        try:
            os.link(part.chunk, part.target)
            continue
        except FileExistsError:
            written = False
        except OSError:  # another file system, or one without hard links: a copy
            written = write_whole(part.target, part.chunk.read_bytes(), replace=False)
        if not written and not _same_file(part.chunk, part.target):
            raise RunDirError(f"{part.target}: changed while the merge ran; not replaced")


__all__ = ["RunDirError", "SubmissionPart", "file_mode", "file_problem", "check_chunk_submission", "metrics_from_record", "metrics_record",
           "plan_submission", "write_submission_parts", "write_whole"]
