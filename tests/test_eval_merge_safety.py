"""``smart-marl eval --out/--merge`` on hostile run folders: a run writes only inside the run folder
the user named (or at the exact ``--write-submission`` path of its command line), never replaces a
file it did not create, and refuses a bad chunk or a bad place to write with an error naming the
file, before anything is written (:mod:`smart_marl.metrics.sharding`, "Where a run writes").

The property pinned everywhere: after a refusal, every file inside and outside the run folder is
byte for byte what it was, with the same modification time."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from smart_marl.embedded import sample_scenarios
from smart_marl.metrics.submission import ScenarioRolloutArrays, open_submission, write_rollouts
from smart_marl.readers.scene_cache import write_shard

from helpers import run_eval

POLICY = ["--policy", "random", "--rollouts", "2", "--seed", "3", "--json"]
PREFIX = Path("sub") / "submission.binproto"  # inside the run folder: run.json keeps it relative
PARTS = [f"submission.binproto-{i:05d}-of-00002" for i in range(2)]
CHUNK0 = Path("shard-00000-of-00002") / "chunk-000000"


def _snapshot(folder: Path) -> dict[str, tuple]:
    """Every entry below ``folder``: a file's bytes and modification time, a link's target, a folder."""
    found = {}
    for path in sorted(folder.rglob("*")):
        st = path.lstat()
        key = str(path.relative_to(folder))
        if path.is_symlink():
            found[key] = ("link", os.readlink(path))
        elif path.is_dir():
            found[key] = ("dir",)
        else:
            found[key] = (path.read_bytes(), st.st_mtime_ns)
    return found


def _edit_run_json(run: Path, **fields) -> None:
    record = json.loads((run / "run.json").read_text())
    record.update(fields)
    (run / "run.json").write_text(json.dumps(record, indent=1))


@pytest.fixture(scope="module")
def scenes(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("scenes")
    write_shard(folder / "a.smsc", sample_scenarios()[:2])
    return folder


@pytest.fixture(scope="module")
def original(scenes, tmp_path_factory) -> Path:
    """A finished and merged run of 2 shards, 1 scene per chunk, its submission inside it (sub/)."""
    run = tmp_path_factory.mktemp("original") / "run"
    for i in range(2):
        code, _, err = run_eval(["--scenes", str(scenes), *POLICY, "--out", str(run), "--shard", f"{i}/2", "--chunk-size", "1",
                              "--write-submission", str(run / PREFIX)])
        assert code == 0, err
    code, out, err = run_eval(["--merge", str(run), "--json"])
    assert code == 0, err
    assert sorted(p.name for p in (run / "sub").iterdir()) == PARTS
    return run


@pytest.fixture
def run(original, tmp_path) -> Path:
    """A copy of the finished run, without its merged files (result.json, the submission)."""
    copy = tmp_path / "copy" / "run"
    shutil.copytree(original, copy)
    (copy / "result.json").unlink()
    shutil.rmtree(copy / "sub")
    return copy


def _refused(argv: list[str], says: str, *folders: Path, code: int = 1) -> None:
    """The command exits with ``code`` naming ``says``, and nothing in ``folders`` changed."""
    before = [_snapshot(f) for f in folders]
    got, _, err = run_eval(argv)
    assert got == code and says in err, err
    assert "Traceback" not in err
    assert [_snapshot(f) for f in folders] == before


# ------------------------------------------------------------------------------ where a merge writes
def test_a_copied_run_folder_merges_into_the_copy_and_leaves_the_original_untouched(original, run):
    untouched = _snapshot(original)
    code, out, err = run_eval(["--merge", str(run), "--json"])
    assert code == 0, err
    assert json.loads(out) == json.loads((original / "result.json").read_text())
    assert sorted(p.name for p in (run / "sub").iterdir()) == PARTS
    for i, part in enumerate(PARTS):  # the copy's parts are the copy's chunks
        assert (run / "sub" / part).read_bytes() == (run / f"shard-0000{i}-of-00002" / "chunk-000000.binproto").read_bytes()
    assert _snapshot(original) == untouched
    # merged again: its parts are its own, kept as they are
    parts = _snapshot(run / "sub")
    assert run_eval(["--merge", str(run), "--json"])[0] == 0
    assert _snapshot(run / "sub") == parts and _snapshot(original) == untouched


def test_an_older_runs_absolute_prefix_is_read_only_inside_the_run_folder(original, run):
    """Older versions kept the prefix as an absolute path: inside the (copied) folder it is taken;
    the original's, outside the copy, is refused naming run.json and the path."""
    _edit_run_json(run, submission_prefix=str(original / PREFIX))
    _refused(["--merge", str(run)], f"{run / 'run.json'}: submission_prefix {str(original / PREFIX)!r} leads outside the run "
                                    f"folder {run}", original, run)
    _edit_run_json(run, submission_prefix=str(run / PREFIX))
    assert run_eval(["--merge", str(run), "--json"])[0] == 0
    assert sorted(p.name for p in (run / "sub").iterdir()) == PARTS


@pytest.mark.parametrize("prefix", ["../elsewhere/submission.binproto", "ABSOLUTE", "link/submission.binproto",
                                    "sub/../../elsewhere/submission.binproto"])
def test_a_run_json_prefix_leading_outside_the_run_folder_is_refused(run, prefix):
    """Relative with .., absolute, through a link in the folder: refused; the file already at the
    place it names (a victim of the old merge) is neither replaced nor joined by another."""
    elsewhere = run.parent / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / PARTS[0]).write_bytes(b"somebody's file")
    (run / "link").symlink_to(elsewhere)
    value = str(elsewhere / "submission.binproto") if prefix == "ABSOLUTE" else prefix
    _edit_run_json(run, submission_prefix=value)
    _refused(["--merge", str(run)], f"{run / 'run.json'}: submission_prefix {value!r} leads outside the run folder",
             run.parent)


def test_an_existing_file_at_a_submission_path_is_not_replaced(run, tmp_path):
    """At the prefix run.json keeps and at one given on the command line: a file the merge did not
    write stops it before anything is written, naming the file."""
    (run / "sub").mkdir()
    (run / "sub" / PARTS[1]).write_bytes(b"my notes")
    _refused(["--merge", str(run)], f"{run / 'sub' / PARTS[1]}: exists and is not this run's submission file", run)
    given = tmp_path / "upload" / "submission.binproto"
    given.parent.mkdir()
    (given.parent / PARTS[0]).write_bytes(b"an older upload")
    _refused(["--merge", str(run), "--write-submission", str(given)],
             f"{given.parent / PARTS[0]}: exists and is not this run's submission file", run, given.parent)
    # a result.json the merge did not write, or a link planted at its name, is not replaced either
    (run / "sub" / PARTS[1]).unlink()
    (run / "result.json").write_text("my own results")
    _refused(["--merge", str(run)], f"{run / 'result.json'}: exists and is not a merge's result", run)
    (run / "result.json").unlink()
    (run / "result.json").symlink_to(tmp_path / "target.json")
    _refused(["--merge", str(run)], f"{run / 'result.json'}: exists and is not a regular file", run, tmp_path)


def test_a_prefix_outside_the_run_folder_is_written_only_when_the_merge_names_it(scenes, tmp_path):
    run, prefix = tmp_path / "run", tmp_path / "upload" / "submission.binproto"
    for i in range(2):
        code, _, err = run_eval(["--scenes", str(scenes), *POLICY, "--out", str(run), "--shard", f"{i}/2", "--chunk-size", "1",
                              "--write-submission", str(prefix)])
        assert code == 0 and "lies outside the run folder" in err, err
    assert "submission_prefix" not in json.loads((run / "run.json").read_text())
    code, _, err = run_eval(["--merge", str(run), "--json"])
    assert code == 0 and "the submission was not written" in err and not prefix.parent.exists()
    assert run_eval(["--merge", str(run), "--json", "--write-submission", str(prefix)])[0] == 0
    assert sorted(open_submission(prefix)) == sorted(s.scenario_id for s in sample_scenarios()[:2])


def test_a_shard_folder_linked_out_of_the_run_folder_is_not_written_through(scenes, tmp_path):
    run, elsewhere = tmp_path / "run", tmp_path / "elsewhere"
    argv = ["--scenes", str(scenes), *POLICY, "--out", str(run), "--chunk-size", "1"]
    assert run_eval([*argv, "--shard", "0/2"])[0] == 0
    elsewhere.mkdir()
    (run / "shard-00001-of-00002").symlink_to(elsewhere)
    _refused([*argv, "--shard", "1/2"], "lies outside the run folder", elsewhere)
    assert list(elsewhere.iterdir()) == []


# ------------------------------------------------------------------------------------- bad chunks
def _other_submission(path: Path) -> None:
    import numpy as np

    write_rollouts(path, [ScenarioRolloutArrays("not-this-scene", np.array([1]), np.zeros((2, 1, 80, 4), np.float32))],
                   description="smart-marl policy random")


@pytest.mark.parametrize("damage, says", [
    (lambda p: p.write_bytes(b""), "empty (0 bytes)"),
    (lambda p: p.write_bytes(b"garbage!" * 8), "not a SimAgentsChallengeSubmission protobuf"),
    (lambda p: p.write_bytes(p.read_bytes()[:-7]), "not a SimAgentsChallengeSubmission protobuf"),
    (_other_submission, "not the rollouts of its chunk's scenes (scenario 'not-this-scene' where its .json has"),
])
def test_a_bad_chunk_submission_file_is_refused_naming_it_and_nothing_is_written(original, run, damage, says):
    chunk = run / CHUNK0.with_suffix(".binproto")
    chunk.unlink()  # a copy of its own, not the original's file
    shutil.copy(original / CHUNK0.with_suffix(".binproto"), chunk)
    damage(chunk)
    _refused(["--merge", str(run)], f"{chunk}: {says}", run, original)
    assert not (run / "result.json").exists() and not (run / "sub").exists()


@pytest.mark.parametrize("field, value, says", [
    ("meta_metric", float("nan"), "meta_metric is nan, not a finite number"),
    ("min_ade", float("inf"), "min_ade is inf, not a finite number"),
    ("likelihoods.linear_speed", float("-inf"), "likelihoods.linear_speed is -inf, not a finite number"),
    ("ade", "0.5", "ade is '0.5', not a finite number"),
    ("likelihoods.linear_speed", None, "its likelihoods are not the 2025 rules' features (linear_speed is missing)"),
])
def test_non_finite_or_missing_metrics_in_a_chunk_are_refused_naming_it(run, field, value, says):
    path = run / CHUNK0.with_suffix(".json")
    chunk = json.loads(path.read_text())
    metrics = chunk["scenes"][0]["metrics"]
    holder, key = (metrics["likelihoods"], field.split(".")[1]) if "." in field else (metrics, field)
    if value is None:
        del holder[key]
    else:
        holder[key] = value
    path.write_text(json.dumps(chunk))  # Python writes NaN and Infinity, which the merge reads
    _refused(["--merge", str(run), "--json"], f"{path}: scenario {metrics['scenario_id']!r}: {says}", run)


# ------------------------------------------------------------------------------ bad places to write
def test_bad_submission_prefixes_are_refused_with_one_error_line(scenes, run, tmp_path):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    for prefix, says in (("/proc/smart-marl/submission.binproto", "/proc/smart-marl is under /proc or /sys"),
                         (str(a_file / "submission.binproto"), f"{a_file} exists and is not a folder"),
                         (str(tmp_path), f"{tmp_path} is a folder, not a file name")):
        _refused(["--merge", str(run), "--write-submission", prefix], f"argument --write-submission: {says}", run, code=2)
        _refused(["--scenes", str(scenes), *POLICY, "--out", str(tmp_path / "new"), "--write-submission", prefix],
                 f"argument --write-submission: {says}", tmp_path, code=2)
    # run.json's prefix below a file of the run folder
    _edit_run_json(run, submission_prefix="run.json/submission.binproto")
    _refused(["--merge", str(run)], f"the submission prefix of {run / 'run.json'} {run / 'run.json/submission.binproto'}: "
                                    f"{run / 'run.json'} exists and is not a folder", run)
