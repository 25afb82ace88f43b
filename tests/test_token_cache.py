"""The token cache: the same training items and losses as tokenizing on the fly, resumable, clear errors."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from smart_marl.cli import main as cli_main
from smart_marl.embedded import SAMPLES_DIR
from smart_marl.model.batch import RoadSettings, collate_scenes
from smart_marl.model.checkpoint import load_checkpoint, save_checkpoint
from smart_marl.model.losses import NextTokenLoss
from smart_marl.readers import read_scenarios
from smart_marl.token_cache import TokenCache, TokenCacheError, is_token_cache, pretokenize
from smart_marl.train import TokenizedScenes, TrainConfigError, load_train_config, train

RADIUS = 30.0
SUMO = RoadSettings("sumo")  # the embedded prior's road types
MM = 1e-3


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """Four of the package's SUMO sample scenes, in two input files, pretokenized with the embedded prior's vocabularies."""
    tmp = tmp_path_factory.mktemp("tokens")
    ck = load_checkpoint("embedded")
    scenes = list(read_scenarios(SAMPLES_DIR))[:4]
    from smart_marl.readers.scene_cache import write_shard

    files = [tmp / "a.smsc", tmp / "b.smsc"]
    write_shard(files[0], scenes[:3])
    write_shard(files[1], scenes[3:])
    out = tmp / "cache"
    manifest = pretokenize([str(f) for f in files], out, ck.motion_vocab, ck.road_vocab, SUMO, RADIUS, workers=1, progress=False)
    return ck, scenes, files, out, manifest


def _close(name: str, a: np.ndarray, b: np.ndarray) -> None:
    assert a.shape == b.shape and a.dtype == b.dtype, (name, a.shape, b.shape, a.dtype, b.dtype)
    if name != "road_points":  # only road piece points (in the piece's frame) are rounded, to the millimetre
        assert np.array_equal(a, b), name
    else:
        assert np.abs(a - b).max(initial=0) <= 0.5 * MM + 1e-6, name


def test_items_are_the_on_the_fly_items_road_points_to_a_millimetre(setup):
    ck, scenes, _, out, manifest = setup
    assert is_token_cache(out) and manifest["num_scenes"] == 4 and len(manifest["shards"]) == 2
    ref = TokenizedScenes(scenes, ck.motion_vocab, ck.road_vocab, 3, 0, 0.15, RADIUS, road=SUMO)
    cache = TokenCache(out, seed=3, road_mask_prob=0.15)
    assert [cache.scenario_id(i) for i in range(4)] == [s.scenario_id for s in scenes]
    for i in range(4):
        for position in (i, 100 + i):  # the hidden road pieces follow (seed, position), as on the fly
            a, b = ref[(i, position)], cache[(i, position)]
            assert a.keys() == b.keys()
            for name in a:
                _close(name, a[name], b[name])
    assert cache[(0, 1)]["road_masked"].any() and not np.array_equal(cache[(0, 1)]["road_masked"], cache[(0, 2)]["road_masked"])


def test_a_batch_from_the_cache_has_the_same_loss(setup):
    ck, scenes, _, out, _ = setup
    ref = TokenizedScenes(scenes, ck.motion_vocab, ck.road_vocab, 0, 0, 0.15, RADIUS, road=SUMO)
    cache = TokenCache(out, seed=0, road_mask_prob=0.15)
    keys = [(i, 7 * i) for i in range(4)]
    loss = NextTokenLoss(ck.model.eval(), 0.1)
    with torch.no_grad():
        a = loss(collate_scenes([ref[k] for k in keys]))
        b = loss(collate_scenes([cache[k] for k in keys]))
    for name in ("motion_loss", "road_loss"):
        assert abs(float(a[name]) - float(b[name])) <= 1e-4 * abs(float(a[name])), (name, float(a[name]), float(b[name]))
    assert float(a["road_tokens"]) > 0 and float(a["vehicle_tokens"]) > 0


def test_a_rerun_skips_done_inputs_and_refuses_other_settings(setup):
    ck, _, files, out, _ = setup
    shard = out / setup[4]["shards"][0]["file"]
    before = shard.stat().st_mtime_ns
    again = pretokenize([str(f) for f in files], out, ck.motion_vocab, ck.road_vocab, SUMO, RADIUS, progress=False)
    assert again["num_scenes"] == 4 and shard.stat().st_mtime_ns == before
    with pytest.raises(TokenCacheError, match="road_keep_radius_m"):
        pretokenize([str(f) for f in files], out, ck.motion_vocab, ck.road_vocab, SUMO, 20.0, progress=False)


# a pretokenize run that dies without cleaning up (SIGKILL, out of memory) half-way through its inputs
_KILLED_RUN = """
import os, sys
from smart_marl import token_cache
from smart_marl.model.batch import RoadSettings
from smart_marl.model.checkpoint import load_checkpoint

token_cache.MANIFEST_EVERY = 1
tokenize = token_cache._tokenize_file

def dies_at_the_second_file(path, *args):
    if path == sys.argv[2]:
        os._exit(9)  # no finally clause runs: the manifest is what the run wrote before
    return tokenize(path, *args)

token_cache._tokenize_file = dies_at_the_second_file
ck = load_checkpoint("embedded")
token_cache.pretokenize(sys.argv[1:3], sys.argv[3], ck.motion_vocab, ck.road_vocab, RoadSettings("sumo"), float(sys.argv[4]), progress=False)
"""


def test_a_run_killed_hard_keeps_what_its_manifest_wrote_and_a_rerun_finishes(setup, tmp_path):
    import subprocess
    import sys

    ck, _, files, _, manifest = setup
    out = tmp_path / "killed"
    run = subprocess.run([sys.executable, "-c", _KILLED_RUN, str(files[0]), str(files[1]), str(out), str(RADIUS)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 9, run.stderr[-2000:]
    cache = TokenCache(out)  # the manifest written after the first file: that file's scenes, readable
    assert [s["source"] for s in cache.manifest["shards"]] == [str(files[0])] and len(cache) == 3
    first = out / cache.manifest["shards"][0]["file"]
    before = first.stat().st_mtime_ns
    again = pretokenize([str(f) for f in files], out, ck.motion_vocab, ck.road_vocab, SUMO, RADIUS, progress=False)
    assert first.stat().st_mtime_ns == before  # the rerun kept the first file's shard and tokenized only the second
    assert [s["scenario_ids"] for s in again["shards"]] == [s["scenario_ids"] for s in manifest["shards"]]


def test_a_damaged_shard_is_named(setup, tmp_path):
    _, _, _, out, manifest = setup
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    name = manifest["shards"][1]["file"]
    (copy / name).write_bytes((copy / name).read_bytes()[:200])
    with pytest.raises(TokenCacheError, match=name):
        TokenCache(copy)[3]


def test_training_reads_the_cache_and_refuses_what_it_cannot_serve(setup, tmp_path):
    ck, _, _, out, _ = setup
    base = {"data": str(out), "model": "smart-1m", "model_overrides": {"road_types": "sumo"}, "init": str(ck.path),
            "road_keep_radius_m": RADIUS, "token_noise_topk": 0, "batch_size": 2, "num_workers": 0, "max_steps": 2,
            "log_every": 1, "val_every": 2, "val_scenes": 2, "ckpt_every": 0, "tensorboard": False, "progress": False}
    res = train(load_train_config(base, {"out_dir": str(tmp_path / "run")}))
    assert res.step == 2 and np.isfinite(res.last_train["loss"]) and np.isfinite(res.last_val["motion_loss"])
    with pytest.raises(TrainConfigError, match="token_noise_topk=5"):
        train(load_train_config(base, {"out_dir": str(tmp_path / "noise"), "token_noise_topk": 5}))
    with pytest.raises(TokenCacheError, match="road_keep_radius_m"):
        train(load_train_config(base, {"out_dir": str(tmp_path / "radius"), "road_keep_radius_m": 20.0}))
    with pytest.raises(TokenCacheError, match="stop_signs"):
        train(load_train_config({**base, "model_overrides": {"road_types": "sumo", "stop_signs": True}},
                                {"out_dir": str(tmp_path / "stops")}))


def test_a_cache_from_before_stop_signs_existed_reads_as_made_without_them(setup, tmp_path):
    import json
    import shutil

    ck, _, _, out, _ = setup
    old = tmp_path / "old"
    shutil.copytree(out, old)
    manifest = json.loads((old / "token_cache.json").read_text())
    assert manifest.pop("stop_signs") is False
    (old / "token_cache.json").write_text(json.dumps(manifest))
    cache = TokenCache(old, 0, 0.0)
    cache.check(ck.motion_vocab, ck.road_vocab, SUMO, RADIUS)
    with pytest.raises(TokenCacheError, match="stop_signs: cache False, run True"):
        cache.check(ck.motion_vocab, ck.road_vocab, RoadSettings("sumo", stop_signs=True), RADIUS)


def test_cli_pretokenize(setup, tmp_path, capsys):
    _, _, files, _, _ = setup
    assert cli_main(["pretokenize", str(files[1]), "--out", str(tmp_path / "c"), "--road-keep-radius", "30", "--quiet"]) == 0
    assert "1 scenes in 1 shards" in capsys.readouterr().out
    assert TokenCache(tmp_path / "c").manifest["road_types"] == "sumo"


def test_cli_pretokenize_stop_signs_default_to_the_checkpoints_and_can_be_turned_either_way(setup, tmp_path, capsys):
    _, _, files, _, _ = setup
    ck = load_checkpoint("embedded")  # a copy of its own, turned into a checkpoint whose model reads stop signs
    ck.model.config.stop_signs = True
    with_signs = save_checkpoint(tmp_path / "signs" / "ck", ck.model, ck.motion_vocab, ck.road_vocab)
    made = {}
    for name, flag in (("asked", []), ("off", ["--no-stop-signs"])):
        assert cli_main(["pretokenize", str(files[1]), "--out", str(tmp_path / name), "--vocab-from", str(with_signs),
                         "--road-keep-radius", "30", "--quiet", *flag]) == 0
        made[name] = TokenCache(tmp_path / name).manifest["stop_signs"]
    assert cli_main(["pretokenize", str(files[1]), "--out", str(tmp_path / "on"), "--road-keep-radius", "30", "--quiet",
                     "--stop-signs"]) == 0
    made["on"] = TokenCache(tmp_path / "on").manifest["stop_signs"]
    assert made == {"asked": True, "off": False, "on": True}


def test_worker_processes_write_the_same_shards(setup, tmp_path):
    """Two worker processes (spawned: a forked child of a process that has run torch can hang)."""
    ck, _, files, out, manifest = setup
    two = pretokenize([str(f) for f in files], tmp_path / "two", ck.motion_vocab, ck.road_vocab, SUMO, RADIUS, workers=2,
                      progress=False)
    assert [s["scenario_ids"] for s in two["shards"]] == [s["scenario_ids"] for s in manifest["shards"]]
    for shard in manifest["shards"]:
        a, b = np.load(out / shard["file"]), np.load(tmp_path / "two" / shard["file"])
        assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
