"""Every value a user can give is checked (issue 34): the one set of rules (smart_marl.config_files) and the
issue's examples at the command line, in configs, checkpoints, vocabularies, scene files and what-if scripts.
Each example ends in a named error (exit 1 or 2 with one ``error:`` line, or a SmartMarlError naming the
argument and the value) or a documented meaning, pinned here."""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from smart_marl.config_files import (MAX_SEED, check_value, flag, integer, interval, number, one_of, output_dir_problem,
                                     probabilities, sequence, strict_json)
from smart_marl.errors import ScenarioReadError, SmartMarlError, UsageError
from test_commands_consistency import _exit_code as _run  # (exit code, stdout, stderr) of the command line

SAMPLES = Path(__file__).resolve().parents[1] / "smart_marl" / "samples" / "sumo_samples.smsc"
WOMD = "womd_tfrecord/motion_data_one_scenario.tfrecord"


# ------------------------------------------------------------------------------ the rules
@pytest.mark.parametrize("rule, value, problem", [
    (integer(1, 10), "abc", "must be an integer, got 'abc' (allowed: 1..10)"),
    (integer(1, 10), 2.7, "must be an integer, got 2.7"),
    (integer(1, 10), 2.0, "must be an integer, got 2.0"),
    (integer(1, 10), True, "must be an integer, got True"),
    (integer(1, 10), float("nan"), "must be an integer, got nan"),
    (integer(1, 10), 0, "must be at least 1, got 0"),
    (integer(1, 10, "the limit"), 11, "must be at most 10 (the limit), got 11"),
    (number(0.0, 1.0, low_open=True), "hot", "must be a finite number, got 'hot' (allowed: > 0.0 and <= 1.0)"),
    (number(0.0, 1.0), float("inf"), "must be a finite number, got inf"),
    (number(0.0, 1.0), np.float32("nan"), "must be a finite number, got"),
    (number(0.0, 1.0), False, "must be a finite number, got False"),
    (number(0.0, 1.0, low_open=True), 0, "must be > 0.0, got 0"),
    (flag, "false", "must be true or false, got 'false'"),
    (flag, 0, "must be true or false, got 0"),
    (one_of("a", "b"), ["a"], "must be one of 'a', 'b', got ['a']"),
    (sequence(integer(0), length=2), [1, "x"], "[1] must be an integer, got 'x'"),
    (interval(0.0, 1.0), (0.6, 0.2), "must be a range (low, high) with low <= high"),
    (probabilities(2), (0.5, 0.6), "must add up to 1"),
])
def test_a_rule_names_the_value_and_what_is_allowed(rule, value, problem):
    assert problem in rule(value)


@pytest.mark.parametrize("rule, value", [(integer(1, 10), 10), (integer(1), np.int64(3)), (number(0.0), np.float32(2.5)),
                                         (flag, np.bool_(True)), (integer(0, MAX_SEED), MAX_SEED), (probabilities(2), (0.3, 0.7))])
def test_a_rule_takes_the_values_it_allows(rule, value):
    assert rule(value) is None


def test_check_value_raises_the_callers_error_naming_the_argument():
    with pytest.raises(UsageError, match=r"^train config: lr must be <= 1.0, got 1e\+30$"):
        check_value("lr", 1e30, number(0.0, 1.0), UsageError, "train config")


def test_strict_json_writes_json_never_nan_or_infinity():
    text = strict_json({"meta_metric": float("inf"), "likelihoods": {"a": np.float32("nan"), "b": np.float64(0.5)},
                        "n": np.int64(3), "ok": True})
    assert json.loads(text) == {"meta_metric": None, "likelihoods": {"a": None, "b": 0.5}, "n": 3, "ok": True}
    assert "Infinity" not in text and "NaN" not in text


def test_an_output_folder_below_a_file_or_under_proc_is_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    assert "is a file, not a folder" in output_dir_problem(tmp_path / "file" / "below" / "deeper")
    assert "under /proc or /sys" in output_dir_problem("/proc/self/nosuch")
    assert output_dir_problem(tmp_path / "new" / "folder") is None


# ---------------------------------------------------------------------- the command line
@pytest.mark.parametrize("argv, names", [
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--seed", "-1"], "--seed: must be at least 0, got -1"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--radius", "-5"], "--radius: must be > 0.0, got -5.0"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--radius", "nan"], "--radius: must be a finite number, got nan"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--demand-scale", "inf"], "--demand-scale: must be a finite number"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "inf"], "--speed-limits: every value must be a finite"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "0.001"], "--speed-limits: every value must be >= 5"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--speed-limits", "50,30", "--speed-weights", "inf,1"],
     "--speed-weights: every value must be a finite number, got inf"),
    (["generate-sumo", "--scenes", "1", "--out", "OUT", "--workers", "100000"], "--workers: must be at most"),
    (["vocab", "build", "SRC", "--out", "OUT", "--tolerance", "nan"], "--tolerance: must be a finite number, got nan"),
    (["vocab", "build", "SRC", "--out", "OUT", "--sizes", "100000"], "--sizes: must be at most 8192 (the largest vocabulary)"),
    (["vocab", "build", "SRC", "--out", "OUT", "--sizes", "7000/16/16"], "--sizes: 7000 vehicle tokens from 6359"),
    (["vocab", "build", "SRC", "--out", "OUT", "--seed", "2.5"], "--seed: '2.5' is not an integer"),
    (["vocab", "transfer", "embedded", "--motion-vocab", "V", "--out", "FILE/below/name"], "--out: "),
    (["vocab", "build", "SRC", "--out", "FILE/below"], "--out: "),
    (["pretokenize", "SRC", "--out", "OUT", "--road-keep-radius", "nan"], "--road-keep-radius: must be a finite number"),
    (["preprocess", "SRC", "--out", "/proc/self/nosuch"], "--out: /proc/self/nosuch is under /proc or /sys"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--seed", "-1"], "--seed: must be at least 0"),
    (["eval", "--scenes", "SRC", "--policy", "random", "--rollouts", "100000"], "--rollouts: must be at most 1024"),
    (["eval", "--scenes", "SRC", "--policy", "prior", "--temperature", "1e-9"], "--temperature: must be >= 0.001"),
    (["finetune", "--evaluate", "CKPT", "--episodes", "0"], "--episodes: must be at least 1, got 0"),
    (["finetune", "--evaluate", "CKPT", "--episodes", "-3"], "--episodes: must be at least 1, got -3"),
    (["train", "--config", "smart-1m", "--out", "OUT", "lr=1e30"], "lr must be <= 1.0"),
    (["train", "--config", "smart-1m", "--out", "OUT", "model.agent_neighbours=-1"], "agent_neighbours must be at least 1"),
    (["train", "--config", "smart-1m", "--out", "OUT", "model.hidden_dim=-64"], "hidden_dim must be at least 1, got -64"),
    (["train", "--config", "smart-1m", "--out", "OUT", "model.temporal_window_tokens=0"], "temporal_window_tokens must be at least 1"),
    (["train", "--config", "smart-1m", "--out", "OUT", "model.agent_radius_m=NaN"], "agent_radius_m must be a finite number"),
    (["train", "--config", "smart-1m", "--out", "OUT", "model.hidden_dim=8192", "model.head_dim=1024"],
     "more than the limit of 1e+09"),
    (["train", "--config", "smart-1m", "--out", "OUT", "batch_size=100000"], "batch_size must be at most 1024"),
    (["train", "--config", "smart-1m", "--out", "OUT", "seed=-1"], "seed must be at least 0"),
    (["train", "--config", "smart-1m", "--out", "OUT", "--seed", "1", "lr=abc"], "lr must be a finite number, got 'abc'"),
    (["train", "--config", "smart-1m", "--out", "OUT", "--seed", "1", "--nope"], "unrecognized arguments: --nope"),
    (["finetune", "--config", "tiny", "temperature=0", "--print-config"], "temperature must be >= 0.001, got 0"),
    (["finetune", "--config", "tiny", "hidden=1000000000", "--print-config"], "hidden must be at most 4096"),
    (["finetune", "--config", "tiny", "reward.collision=NaN", "--print-config"], "reward term 'collision' must be a finite number"),
    (["whatif", "SRC", "--script", "SRC", "--out", "OUT", "--seed", "abc"], "--seed: 'abc' is not an integer"),
], ids=lambda a: " ".join(a) if isinstance(a, list) else None)
def test_the_issues_bad_arguments_exit_2_with_one_error_line_naming_them(argv, names, tmp_path, capsys):
    (tmp_path / "FILE").write_text("a file, not a folder")
    src = tmp_path / "SRC.smsc"
    shutil.copy(SAMPLES, src)
    swap = {"OUT": str(tmp_path / "OUT"), "SRC": str(src), "CKPT": str(tmp_path / "no-checkpoint"), "V": str(tmp_path / "v")}
    argv = [swap.get(a, a.replace("FILE", str(tmp_path / "FILE"))) for a in argv]
    code, _, err = _run(argv, capsys)
    assert code == 2, err
    errors = [line for line in err.splitlines() if "error:" in line]
    assert len(errors) == 1 and errors[0].startswith("smart-marl") and names in errors[0], err
    assert not (tmp_path / "OUT").exists()


def test_train_overrides_after_an_option_are_overrides(capsys):
    code, out, _ = _run(["train", "--config", "smart-1m", "data=x", "--seed", "3", "max_steps=7", "lr=0.001", "--print-config"],
                        capsys)
    cfg = json.loads(out)
    assert code == 0 and (cfg["seed"], cfg["max_steps"], cfg["lr"], cfg["data"]) == (3, 7, 0.001, "x")


@pytest.mark.parametrize("kind", ["fifo", "urandom", "proc"])
def test_eval_submission_that_is_not_a_regular_file_is_refused_at_once(kind, tmp_path, capsys):
    """A FIFO blocked forever and a link to /dev/urandom read forever (issue 34): both are refused, as /proc files are."""
    path = tmp_path / "sub.binproto"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "urandom":
        path.symlink_to("/dev/urandom")
    else:
        path = Path("/proc/self/status")
    code, _, err = _run(["eval", "--scenes", str(SAMPLES), "--submission", str(path)], capsys)
    errors = [line for line in err.splitlines() if "error:" in line]
    assert code == 1 and len(errors) == 1 and str(path) in errors[0] and "not a regular" in errors[0], err


def test_eval_json_prints_null_where_a_metric_is_not_finite(shared_data, monkeypatch, capsys):
    from smart_marl.commands import eval as eval_command

    real = eval_command.aggregate
    monkeypatch.setattr(eval_command, "aggregate", lambda results, rules: {**real(results, rules), "min_ade": float("inf")})
    code, out, _ = _run(["eval", "--scenes", str(shared_data / WOMD), "--policy", "constant_velocity", "--rollouts", "2",
                         "--json"], capsys)
    result = json.loads(out)  # json.loads takes Infinity; what is printed must not hold it
    assert code == 0 and result["min_ade"] is None and "Infinity" not in out and math.isfinite(result["meta_metric"])


def test_generate_sumo_starts_no_more_workers_than_simulations_it_needs(monkeypatch):
    """24 workers were started for one scene (issue 34): the pool is capped by the simulations still needed."""
    from concurrent.futures import Future

    from smart_marl.sources import sumo
    from smart_marl.sources.sumo_sim import SumoConfig

    started = []

    class Pool:
        def __init__(self, workers):
            started.append(workers)

        def submit(self, fn, seed, sim, config):
            future = Future()
            future.set_result([f"scene-{sim}-{k}" for k in range(config.scenes_per_sim)])
            return future

        def shutdown(self, **kwargs):
            pass

    monkeypatch.setattr(sumo, "worker_pool", Pool)
    monkeypatch.setattr(sumo, "simulate_scenes", lambda seed, sim, config: [f"scene-{sim}-{k}" for k in range(config.scenes_per_sim)])
    config = SumoConfig(scenes_per_sim=8)
    for wanted, pool in ((1, []), (20, [3])):
        started.clear()
        sims = sumo._simulations(0, config, 24, lambda: wanted)
        next(sims)
        sims.close()
        assert started == pool


# ------------------------------------------------------------------------------- model configs
@pytest.mark.parametrize("field, value, message", [
    ("agent_neighbours", -1, "agent_neighbours must be at least 1, got -1"),
    ("hidden_dim", -64, "hidden_dim must be at least 1, got -64"),
    ("temporal_window_tokens", 0, "temporal_window_tokens must be at least 1, got 0"),
    ("agent_radius_m", float("nan"), "agent_radius_m must be a finite number, got nan"),
    ("motion_vocab_sizes", [512, 512], "motion_vocab_sizes must be a list of 3 item(s)"),
    ("road_types", "womd", "road_types must be one of 'all', 'sumo', got 'womd'"),
])
def test_a_checkpoint_whose_model_config_is_out_of_range_is_refused(tiny_prior, tmp_path, field, value, message):
    """A checkpoint with agent_radius_m NaN scored minADE 10.3 instead of 3.75 without a word (issue 34)."""
    from smart_marl.model.checkpoint import CheckpointError, load_checkpoint

    copy = tmp_path / "ck"
    copy.mkdir()
    for f in tiny_prior.parent.iterdir():
        shutil.copy(f, copy / f.name)
    meta_path = copy / tiny_prior.name
    meta = json.loads(meta_path.read_text())
    meta["model_config"][field] = value
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(CheckpointError, match="model_config does not make a SMART model") as info:
        load_checkpoint(meta_path)
    assert message in str(info.value)


# ------------------------------------------------------------------------------- SUMO configs
@pytest.mark.parametrize("changes, message", [
    ({"radius_m": float("nan")}, "radius_m must be a finite number, got nan"),
    ({"radius_m": -5.0}, "radius_m must be > 0.0, got -5.0"),
    ({"demand_scale": float("inf")}, "demand_scale must be a finite number, got inf"),
    ({"speed_levels_mps": (float("inf"),)}, "speed_levels_mps [0] must be a finite number, got inf"),
    ({"speed_levels_mps": (0.0003,)}, "speed_levels_mps [0] must be >= 1.35"),
    ({"speed_weights": (float("inf"), 1.0, 0, 0, 0)}, "speed_weights [0] must be a finite number, got inf"),
    ({"car_follow_weights": (1.0, 1.0, 1.0)}, "car_follow_weights must add up to 1"),
    ({"scenes_per_sim": 0}, "scenes_per_sim must be at least 1, got 0"),
    ({"routes": "fly"}, "routes must be one of 'walk', 'trips', got 'fly'"),
])
def test_a_sumo_config_out_of_range_is_a_named_usage_error(changes, message):
    from smart_marl.sources.sumo_sim import SumoConfig, SumoConfigError

    with pytest.raises(SumoConfigError) as info:
        SumoConfig(**changes)
    assert isinstance(info.value, UsageError) and f"SUMO config: {message}" in str(info.value)


# ------------------------------------------------------------------------------ scene files
@pytest.mark.parametrize("speed", [float("inf"), float("nan"), -50.0])
def test_a_womd_lane_with_a_speed_limit_out_of_range_is_a_named_read_error(shared_data, tmp_path, speed):
    """ScenarioNet refused these; WOMD accepted them (issue 34). The one check is the RoadMap's own."""
    from smart_marl.proto.womd import Scenario as ScenarioProto
    from smart_marl.readers import read_scenarios
    from smart_marl.readers.tfrecord import iter_records, write_records

    proto = ScenarioProto.FromString(next(iter(iter_records(shared_data / WOMD))))
    lane = next(f for f in proto.map_features if f.WhichOneof("feature_data") == "lane")
    lane.lane.speed_limit_mph = speed
    path = tmp_path / "bad.tfrecord"
    write_records([proto.SerializeToString()], path)
    with pytest.raises(ScenarioReadError, match=r"speed_limit_mph must be finite and in 0\.\.500 mph"):
        list(read_scenarios(path))


def test_a_scenarionet_sdc_id_naming_no_track_is_a_named_read_error(shared_data, tmp_path):
    import pickle

    from smart_marl.readers import read_scenarios
    from smart_marl.readers.safe_pickle import SCENARIONET_GLOBALS, load_restricted

    src = sorted((shared_data / "scenarionet" / "waymo").glob("sd_*.pkl"))[0]
    data = load_restricted(src, SCENARIONET_GLOBALS)  # read as the reader reads it, then written back changed
    assert data["metadata"]["sdc_id"] in data["tracks"]
    data["metadata"]["sdc_id"] = "no-such-track"
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps(data))
    with pytest.raises(ScenarioReadError, match="sdc_id 'no-such-track' names no track"):
        list(read_scenarios(bad))


@pytest.mark.parametrize("damage, message", [
    ("drop_scene", "holds 4 scenes, the manifest lists 3"),
    ("rename_scene", "holds scene .* where the manifest lists 'renamed'"),
    ("no_scene", "the scene cache holds no scene"),
])
def test_read_scenarios_checks_a_cache_manifest_against_its_shards_as_scene_cache_does(tmp_path, damage, message):
    from smart_marl.cache import SceneCache, scene_entry, write_manifest
    from smart_marl.readers import read_scenarios

    cache = tmp_path / "cache"
    cache.mkdir()
    shutil.copy(SAMPLES, cache / "samples.smsc")
    scenes = list(read_scenarios(cache / "samples.smsc"))
    entries = [scene_entry(s, "samples.smsc") for s in scenes]
    if damage == "drop_scene":
        entries = entries[:-1]
    elif damage == "rename_scene":
        entries[1]["scenario_id"] = "renamed"
    else:
        entries = []
    write_manifest(cache, [{"file": "samples.smsc", "input": "x", "scenes": entries}])
    with pytest.raises(ScenarioReadError, match=message):
        list(read_scenarios(cache))
    with pytest.raises(ScenarioReadError, match=message):
        list(SceneCache(cache))


def test_a_shard_changed_after_it_was_written_fails_its_manifest_checksum(tmp_path):
    """Shards carried no content checksum (issue 34): the manifest records each shard's sha256 and a reader
    checks it when it opens the shard."""
    from smart_marl.cache import SceneCache, preprocess
    from smart_marl.readers import read_scenarios

    src = tmp_path / "samples.smsc"
    shutil.copy(SAMPLES, src)
    preprocess([src], tmp_path / "cache", workers=1, progress=False)
    manifest = json.loads((tmp_path / "cache" / "manifest.json").read_text())
    shard = tmp_path / "cache" / manifest["shards"][0]["file"]
    assert len(manifest["shards"][0]["sha256"]) == 64 and len(list(read_scenarios(tmp_path / "cache"))) == 4
    raw = bytearray(shard.read_bytes())
    raw[-1] ^= 0x01  # one bit of the last array: the structure still reads
    shard.write_bytes(bytes(raw))
    for read in (lambda: list(read_scenarios(tmp_path / "cache")), lambda: SceneCache(tmp_path / "cache")[0]):
        with pytest.raises(ScenarioReadError, match="differs from the checksum the manifest recorded"):
            read()


# ----------------------------------------------------------------------------- vocabularies
def _motion_vocab_file(tmp_path, vocab, change) -> Path:
    from smart_marl.tokens import save_motion_vocabulary

    npz, js = save_motion_vocabulary(vocab, tmp_path / "v")
    meta = json.loads(js.read_text())
    change(meta)
    js.write_text(json.dumps(meta))
    return npz


def test_a_vocabulary_file_with_a_type_other_or_size_0_is_a_named_error(womd_vocab, tmp_path):
    from smart_marl.tokens import load_motion_vocabulary
    from smart_marl.tokens.vocab_io import VocabularyFileError

    other = _motion_vocab_file(tmp_path, womd_vocab, lambda m: m["types"].__setitem__("other", m["types"]["vehicle"]))
    with pytest.raises(VocabularyFileError, match="type 'other' has no motion tokens"):
        load_motion_vocabulary(other)
    empty = _motion_vocab_file(tmp_path, womd_vocab, lambda m: m["types"]["vehicle"].__setitem__("size", 0))
    with pytest.raises(VocabularyFileError, match="size 0; a type in a vocabulary has at least one token"):
        load_motion_vocabulary(empty)


def test_vocab_transfer_to_a_vocabulary_without_every_type_is_a_named_error(tiny_prior, womd_vocab, tmp_path, capsys):
    from smart_marl.tokens import MotionVocabulary, save_motion_vocabulary
    from smart_marl.tokens.motion import MOTION_TYPES

    vehicles_only = MotionVocabulary(types={MOTION_TYPES[0]: womd_vocab.types[MOTION_TYPES[0]]})
    npz, _ = save_motion_vocabulary(vehicles_only, tmp_path / "veh")
    code, _, err = _run(["vocab", "transfer", str(tiny_prior), "--motion-vocab", str(npz), "--out", str(tmp_path / "moved")],
                        capsys)
    assert code == 1 and "no tokens for pedestrian, cyclist" in err and not (tmp_path / "moved.json").exists()
    code, _, err = _run(["vocab", "transfer", str(tiny_prior), "--motion-vocab", str(npz), "--types", "vehicle",
                         "--out", str(tmp_path / "moved")], capsys)
    assert code == 0, err  # the documented way: only the types the vocabulary has


# ------------------------------------------------------------------------------ what-if scripts
def test_a_yaml_alias_bomb_is_refused_with_the_limit_named(tmp_path):
    from agents.whatif import WhatIfError, load_script

    lines = ["a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    lines += [f"a{k}: &a{k} [{', '.join([f'*a{k - 1}'] * 10)}]" for k in range(1, 8)]
    path = tmp_path / "bomb.yaml"
    path.write_text("\n".join(lines) + "\nedits: [{kind: remove, agents: *a7}]\n")
    with pytest.raises(WhatIfError, match="expands to more than 100000 values through its aliases"):
        load_script(path)
    path.write_text("edits: &e [{kind: remove, agents: *e}]\n")
    with pytest.raises(WhatIfError, match="recursive alias"):
        load_script(path)


@pytest.mark.parametrize("edit, message", [
    ({"kind": "insert", "path": [[0, 0], [10, 0]], "speed_mps": 1.0e30}, "insert: speed_mps must be <= 100.0 (360 km/h)"),
    ({"kind": "stalled_vehicle", "pose": [0, 0, 0], "size_m": [1e30, 1e30, 1e30]}, "size_m must be 3 finite positive numbers"),
    ({"kind": "insert", "path": [[1e30, 0], [10, 0]]}, "path must hold finite numbers within"),
    ({"kind": "brake", "agent": 1609, "decel_mps2": 1e9}, "decel_mps2 must be <= 20.0"),
    ({"kind": "cut_in", "agent": 1609, "lateral_m": 1e6}, "lateral_m must be <= 20.0"),
])
def test_what_if_numbers_that_would_reach_the_model_as_nan_are_refused(edit, message):
    from agents.whatif import WhatIf, WhatIfError

    with pytest.raises(WhatIfError, match="edit 0: ") as info:
        WhatIf.from_dict({"edits": [edit]})
    assert message in str(info.value)


def test_two_scripted_edits_on_one_agent_are_a_named_error(womd_scenes, womd_vocab):
    """A brake and a cut-in on one agent: the brake was silently dropped (issue 34)."""
    from agents.whatif import Brake, CutIn, WhatIf, WhatIfError, prepare

    with pytest.raises(WhatIfError, match=r"edit 1: cut_in: agent 1609 is already driven by edit 0 \(brake\)"):
        prepare(womd_scenes[0], WhatIf([Brake(agent=1609, at_s=1.0), CutIn(agent="vehicle_1609", at_s=2.0)]), womd_vocab)


def test_the_errors_here_are_smart_marl_errors():
    from agents.whatif import WhatIfError
    from smart_marl.model.smart import ModelConfigError
    from smart_marl.sources.sumo_sim import SumoConfigError

    assert all(issubclass(e, SmartMarlError) for e in (WhatIfError, ModelConfigError, SumoConfigError, UsageError))
