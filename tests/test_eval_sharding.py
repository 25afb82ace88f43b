"""``smart-marl eval`` at challenge scale: sharded runs (``--shard I/N``, torchrun ranks), resuming a
killed run, the merge, and submissions split in files.

The property pinned everywhere: whatever the split and however often a run was interrupted, the
merged numbers are exactly (bit for bit, the JSON compared as a whole) those of one plain
``smart-marl eval`` over the same scenes, and the merged submission holds exactly its rollouts."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from smart_marl.embedded import sample_scenarios
from smart_marl.errors import ScenarioReadError
from smart_marl.metrics.sharding import Shard, parse_shard, scene_slots, shard_from_torchrun
from smart_marl.metrics.submission import (ScenarioRolloutArrays, SubmissionReader, open_submission, rollouts_from_submission,
                                           submission_files, write_rollouts, write_submission_shards)
from smart_marl.readers import expand_paths, read_scenarios
from smart_marl.readers.scene_cache import write_shard
from smart_marl.readers.womd import write_womd_tfrecord

from helpers import run_eval

ROOT = Path(__file__).resolve().parents[1]
POLICY = ["--policy", "random", "--rollouts", "2", "--seed", "3", "--json"]


def _ok(argv: list[str]) -> dict | None:
    code, out, err = run_eval(argv)
    assert code == 0, err
    return json.loads(out) if out.strip() else None


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    """The package's 4 sample scenes as two files of two formats: a scene-cache shard (scenes 0, 1)
    and a WOMD TFRecord (scenes 2, 3), so both record-level paths of the shard assignment run."""
    folder = tmp_path_factory.mktemp("scenes")
    scenes = sample_scenarios()
    write_shard(folder / "a.smsc", scenes[:2])
    write_womd_tfrecord(scenes[2:], folder / "b.tfrecord")
    return folder


@pytest.fixture(scope="module")
def plain(scene_dir, tmp_path_factory) -> tuple[dict, Path]:
    """One plain single-process run: its JSON and its submission file."""
    sub = tmp_path_factory.mktemp("plain") / "plain.binproto"
    return _ok(["--scenes", str(scene_dir), *POLICY, "--write-submission", str(sub)]), sub


def _sharded(scene_dir: Path, run: Path, count: int, *extra: str) -> dict:
    for i in range(count):
        printed = _ok(["--scenes", str(scene_dir), *POLICY, "--out", str(run), "--shard", f"{i}/{count}", *extra])
        assert (printed is None) == (count > 1)  # a shard of several prints nothing; a one-shard run merges at once
    return printed if count == 1 else _ok(["--merge", str(run), "--json"])


# ------------------------------------------------------------------------------ shard assignment
def test_shard_argument_and_torchrun_environment():
    assert parse_shard("2/5") == Shard(2, 5) and parse_shard(" 0 / 1 ") == Shard(0, 1)
    for bad, says in (("3/2", "I must be in 0..1"), ("2/2", "I must be in 0..1"), ("abc", "is not I/N"), ("1/0", "N must be"),
                      ("-1/2", "is not I/N")):
        with pytest.raises(Exception, match=says):
            parse_shard(bad)
    assert shard_from_torchrun({}) is None
    assert shard_from_torchrun({"RANK": "1", "WORLD_SIZE": "4", "LOCAL_RANK": "1"}) == Shard(1, 4)
    with pytest.raises(Exception, match="RANK='4' and WORLD_SIZE='4'"):
        shard_from_torchrun({"RANK": "4", "WORLD_SIZE": "4"})


def test_scenes_are_numbered_in_input_order_and_each_shard_decodes_only_its_own(scene_dir):
    paths = expand_paths(str(scene_dir))
    slots = list(scene_slots(paths))
    assert [(s.ordinal, Path(s.path).name, s.record) for s in slots] == [
        (0, "a.smsc", 0), (1, "a.smsc", 1), (2, "b.tfrecord", 0), (3, "b.tfrecord", 1)]
    # a slot decodes to the very scene the plain reader yields at that place
    for slot, scenario in zip(slots, read_scenarios(paths)):
        (got, got_meta), (want, want_meta) = slot.load().to_arrays(), scenario.to_arrays()
        assert got_meta == want_meta and sorted(got) == sorted(want)
        for name in want:
            np.testing.assert_array_equal(got[name], want[name])
    shards = [Shard(i, 3) for i in range(3)]
    owners = [[s.ordinal for s in scene_slots(paths) if sh.owns(s.ordinal)] for sh in shards]
    assert owners == [[0, 3], [1], [2]]


# ------------------------------------------------------------------------------ merged == plain
@pytest.mark.parametrize("count", [1, 2, 3, 5])
def test_merged_shards_give_exactly_the_single_process_numbers(scene_dir, plain, tmp_path, count):
    """1 shard (a resumable single run), 2, 3 and 5 shards (one shard has no scene): the merged
    JSON equals the plain run's, every float to the last bit."""
    assert _sharded(scene_dir, tmp_path / "run", count, "--chunk-size", "1") == plain[0]
    assert json.loads((tmp_path / "run" / "result.json").read_text()) == plain[0]


def test_merged_submission_files_hold_exactly_the_plain_rollouts(scene_dir, plain, tmp_path):
    """The prefix inside the run folder: run.json keeps it (relative to the folder) and ``--merge RUN`` writes there."""
    prefix = tmp_path / "run" / "sub" / "submission.binproto"
    merged = _sharded(scene_dir, tmp_path / "run", 2, "--chunk-size", "1", "--write-submission", str(prefix))
    assert merged == plain[0]
    assert json.loads((tmp_path / "run" / "run.json").read_text())["submission_prefix"] == "sub/submission.binproto"
    files = submission_files(prefix)
    assert [Path(f).name for f in files] == [f"submission.binproto-{i:05d}-of-00004" for i in range(4)]
    reader = open_submission(prefix)
    assert reader.header.description == "smart-marl policy random" and reader.header.submission_type == 1
    single = rollouts_from_submission(plain[1])
    assert sorted(reader) == sorted(single)
    for sid, want in single.items():
        got = reader[sid]
        np.testing.assert_array_equal(got.object_ids, want.object_ids)
        np.testing.assert_array_equal(got.trajectories, want.trajectories)
    # every file is a whole submission with the same header; and scoring the sharded set gives the same numbers
    assert len({SubmissionReader([f]).header.SerializeToString() for f in files}) == 1
    assert _ok(["--scenes", str(scene_dir), "--submission", str(prefix), "--json", "--any-rollout-count"]) == plain[0]
    assert _ok(["--scenes", str(scene_dir), "--submission", str(prefix.parent), "--json", "--any-rollout-count"]) == plain[0]


def test_skipped_files_and_scenes_merge_in_input_order(tmp_path, scene_dir):
    """A bad file and an unscorable scene (with --skip-bad): the merged 'skipped' list and numbers
    equal the plain run's."""
    folder = tmp_path / "scenes"
    folder.mkdir()
    shutil.copy(scene_dir / "a.smsc", folder / "a.smsc")
    (folder / "b.json").write_text('{"objects": [{"position": []}], "roads": []}')
    write_shard(folder / "c.smsc", [sample_scenarios()[2].window(0, 11), sample_scenarios()[3]])  # an 11-frame scene first
    argv = ["--scenes", str(folder), *POLICY, "--skip-bad"]
    want = _ok(argv)
    assert [Path(s["path"]).name for s in want["skipped"]] == ["b.json", "c.smsc"] and want["num_scenarios"] == 3
    for count in (2, 3):
        run = tmp_path / f"run{count}"
        for i in range(count):
            _ok([*argv, "--out", str(run), "--shard", f"{i}/{count}", "--chunk-size", "1"])
        assert _ok(["--merge", str(run), "--json"]) == want


# ---------------------------------------------------------------------------------------- resume
def test_a_failed_run_resumes_from_its_finished_chunks_and_ends_as_an_uninterrupted_one(scene_dir, plain, tmp_path,
                                                                                         monkeypatch):
    """A failure injected at the 3rd scene (chunks of 2): the first chunk is kept; the rerun scores only
    the 2 scenes of the unfinished chunk and merges to the uninterrupted numbers."""
    import smart_marl.commands.eval as eval_module

    real, calls = eval_module.score_rollouts, []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("injected failure")
        return real(*args, **kwargs)

    monkeypatch.setattr(eval_module, "score_rollouts", failing)
    run = tmp_path / "run"
    argv = ["--scenes", str(scene_dir), *POLICY, "--out", str(run), "--chunk-size", "2"]
    with pytest.raises(RuntimeError, match="injected failure"):
        run_eval(argv)
    shard_dir = run / "shard-00000-of-00001"
    assert sorted(p.name for p in shard_dir.iterdir()) == ["chunk-000000.json"]
    calls.clear()
    assert _ok(argv) == plain[0]
    assert len(calls) == 2  # the finished chunk was not computed again
    calls.clear()
    assert _ok(argv) == plain[0] and calls == []  # a finished run only merges again


def test_a_killed_process_resumes_to_the_uninterrupted_result(scene_dir, plain, tmp_path):
    """SIGKILL a real eval process once its first chunk is on disk; the rerun equals an uninterrupted run."""
    run = tmp_path / "run"
    argv = [sys.executable, "-m", "smart_marl.cli", "eval", "--scenes", str(scene_dir), *POLICY, "--out", str(run),
            "--chunk-size", "1"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(argv, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = run / "shard-00000-of-00001" / "chunk-000000.json"
    deadline = time.monotonic() + 300
    while not first.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    assert first.exists(), "the process ended before writing its first chunk"
    done = sorted(p.name for p in first.parent.glob("chunk-*.json"))
    assert not (first.parent / "done.json").exists() and len(done) < 4, f"killed too late to test resuming: {done}"
    result = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout) == plain[0]
    assert f"{len(done)} from a previous try" in result.stderr


def test_torchrun_ranks_take_their_shards_and_rank0_merges(scene_dir, plain, tmp_path):
    """``torchrun --nproc_per_node=2``: each rank scores shard RANK/WORLD_SIZE; rank 0 prints the merged numbers."""
    torchrun = shutil.which("torchrun", path=os.path.dirname(sys.executable))
    if torchrun is None:
        pytest.skip("torchrun is not installed beside this Python")
    run = tmp_path / "run"
    proc = subprocess.Popen([torchrun, "--standalone", "--nproc_per_node=2", "-m", "smart_marl.cli", "eval",
                             "--scenes", str(scene_dir), *POLICY, "--out", str(run)],
                            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:  # torchrun and its workers, all in the session started for them
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 0, stderr
    assert json.loads(stdout) == plain[0]
    assert sorted(p.name for p in run.iterdir() if p.is_dir()) == ["shard-00000-of-00002", "shard-00001-of-00002"]


def test_prior_rollouts_do_not_depend_on_the_split(tiny_prior, tmp_path, one_torch_thread):
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    write_shard(scenes / "s.smsc", sample_scenarios()[:3])
    argv = ["--scenes", str(scenes), "--policy", "prior", "--checkpoint", str(tiny_prior), "--rollouts", "2", "--json"]
    want = _ok(argv)
    for i in range(2):
        _ok([*argv, "--out", str(tmp_path / "run"), "--shard", f"{i}/2"])
    assert _ok(["--merge", str(tmp_path / "run"), "--json"]) == want


# ---------------------------------------------------------------------------------------- errors
@pytest.mark.parametrize("argv, says", [
    (["--shard", "3/2", "--out", "R"], "argument --shard: '3/2': I must be in 0..1"),
    (["--shard", "abc", "--out", "R"], "argument --shard: 'abc' is not I/N"),
    (["--shard", "1/2"], "--shard needs --out RUN"),
    (["--chunk-size", "4"], "--chunk-size needs --out RUN"),
    (["--chunk-size", "0", "--out", "R"], "--chunk-size"),
])
def test_bad_scale_arguments_exit_2_naming_the_argument(argv, says, scene_dir):
    code, _, err = run_eval(["--scenes", str(scene_dir), *POLICY, *argv])
    assert code == 2 and says in err


def test_merge_takes_nothing_but_its_run(capsys):
    code, _, err = run_eval(["--merge", "R", "--scenes", "x", "--policy", "random"])
    assert code == 2 and "--merge takes the scenes and options from RUN/run.json: leave out --scenes, --policy" in err
    code, _, err = run_eval(["--merge", "/nonexistent/run"])
    assert code == 1 and "/nonexistent/run: no such run folder" in err


def test_torchrun_without_out_or_with_another_shard_is_refused(scene_dir, monkeypatch, tmp_path):
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    code, _, err = run_eval(["--scenes", str(scene_dir), *POLICY])
    assert code == 2 and "launched by torchrun as rank 1 of 2: give --out RUN" in err
    code, _, err = run_eval(["--scenes", str(scene_dir), *POLICY, "--out", str(tmp_path / "r"), "--shard", "0/2"])
    assert code == 2 and "--shard 0/2 but torchrun made this process rank 1 of 2" in err


def test_a_run_folder_refuses_another_config_split_or_foreign_chunk(scene_dir, tmp_path):
    run = tmp_path / "run"
    base = ["--scenes", str(scene_dir), *POLICY, "--out", str(run), "--chunk-size", "1"]
    _ok([*base, "--shard", "0/2"])
    # another seed: another run
    code, _, err = run_eval(["--scenes", str(scene_dir), "--policy", "random", "--rollouts", "2", "--seed", "4", "--json",
                          "--out", str(run), "--shard", "1/2"])
    assert code == 1 and f"{run / 'run.json'}: this folder holds another run (source.seed is 3 there, 4 here)" in err
    # another split
    code, _, err = run_eval([*base, "--shard", "1/3"])
    assert code == 1 and "this run is split in 2 shard(s), not 3" in err
    # merging before every shard is done names the missing shard and the command that finishes it
    code, _, err = run_eval(["--merge", str(run)])
    assert code == 1 and "shard-00001-of-00002: shard 1/2 has not finished (0 chunk(s) done)" in err and "--shard 1/2" in err
    # a chunk copied in from another run is refused, naming it
    other = tmp_path / "other"
    _ok(["--scenes", str(scene_dir), "--policy", "random", "--rollouts", "2", "--seed", "4", "--json", "--out", str(other),
         "--chunk-size", "1", "--shard", "1/2"])
    (run / "shard-00001-of-00002").mkdir()
    shutil.copy(other / "shard-00001-of-00002" / "chunk-000000.json", run / "shard-00001-of-00002" / "chunk-000000.json")
    code, _, err = run_eval([*base, "--shard", "1/2"])
    assert code == 1 and "shard-00001-of-00002/chunk-000000.json: a chunk of another run" in err
    # a shard folder of another split beside this run's shards
    shutil.rmtree(run / "shard-00001-of-00002")
    _ok([*base, "--shard", "1/2"])
    code, _, err = run_eval(["--merge", str(run), "--write-submission", str(tmp_path / "sub.binproto")])
    assert code == 1 and "this run did not keep its rollouts (run it with --write-submission)" in err
    (run / "shard-00000-of-00003").mkdir()
    code, _, err = run_eval(["--merge", str(run)])
    assert code == 1 and "shard-00000-of-00003: a shard of a 3-way split, but this run is split 2 ways" in err


# ----------------------------------------------------------------------------- sharded submissions
def _arrays(sid: str, seed: int) -> ScenarioRolloutArrays:
    rng = np.random.default_rng(seed)
    return ScenarioRolloutArrays(sid, np.array([4, 9, 2]), rng.normal(0, 100, (3, 3, 80, 4)).astype(np.float32))


def test_sharded_submission_reads_back_lazily_and_refuses_incomplete_or_mixed_sets(tmp_path):
    groups = [[_arrays("s0", 0), _arrays("s1", 1)], [_arrays("s2", 2)], [_arrays("s3", 3)]]
    prefix = tmp_path / "submission.binproto"
    names = write_submission_shards(prefix, groups, account_name="me", description="d")
    assert [Path(n).name for n in names] == [f"submission.binproto-{i:05d}-of-00003" for i in range(3)]
    back = rollouts_from_submission(prefix)
    assert list(back) == ["s0", "s1", "s2", "s3"]
    for g in groups:
        for a in g:
            np.testing.assert_array_equal(back[a.scenario_id].trajectories, a.trajectories)
    # a missing file, a duplicated scenario, a different header: errors naming the file
    Path(names[1]).rename(tmp_path / "aside")
    with pytest.raises(ScenarioReadError, match=r"submission\.binproto-00001-of-00003: missing: the submission has 2 of its 3"):
        open_submission(prefix)
    write_rollouts(names[1], [_arrays("s0", 5)], account_name="me", description="d")
    with pytest.raises(ScenarioReadError, match=r"00001-of-00003: scenario s0 appears twice \(also in .*00000-of-00003\)"):
        open_submission(prefix)
    write_rollouts(names[1], [_arrays("s2", 2)], account_name="someone else", description="d")
    with pytest.raises(ScenarioReadError, match=r"00001-of-00003: its header differs from .*00000-of-00003's \(account_name\)"):
        open_submission(prefix)
    with pytest.raises(ScenarioReadError, match="no such file, and no submission shards"):
        open_submission(tmp_path / "nothing.binproto")


def test_lazy_reader_agrees_with_the_whole_file_parse_on_the_official_submission(shared_data):
    path = shared_data / "womd_tfrecord" / "sim_agents_test_submission.binproto"
    lazy, whole = open_submission(path), rollouts_from_submission(path)
    assert list(lazy) == list(whole) == ["637f20cafde22ff8"]
    np.testing.assert_array_equal(lazy["637f20cafde22ff8"].trajectories, whole["637f20cafde22ff8"].trajectories)
    assert lazy.header.account_name == "test" and lazy.header.unique_method_name == "test"


def test_lazy_reader_names_a_file_that_is_not_a_submission(tmp_path):
    bad = tmp_path / "bad.binproto"
    bad.write_bytes(b"\x0a\xff\xff\xff\x0f")  # field 1 declaring far more bytes than the file has
    with pytest.raises(ScenarioReadError, match=r"bad\.binproto: not a SimAgentsChallengeSubmission protobuf"):
        open_submission(bad)
