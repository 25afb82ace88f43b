"""Helpers of the benchmark scripts that decide what a figure measures."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

from smart_marl.scenario import AgentType

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_drop_parked_leaves_out_exactly_the_vehicles_that_stand_all_log(sample_scenes):
    """prior_speed_drift --drop-parked: the parked vehicles (on every frame, < 0.5 m over the log) go, every
    other track stays as it was, the self-driving car included."""
    drift = _load("prior_speed_drift")
    scene = sample_scenes[0]  # sumo-7-000000-00: 22 tracks, most of its vehicles stand at lights or parked
    tr = scene.tracks
    out = drift.without_parked(scene)
    moved = np.linalg.norm(tr.position[:, -1, :2] - tr.position[:, 0, :2], axis=-1)
    parked = (tr.types == int(AgentType.VEHICLE)) & tr.valid.all(1) & (moved < 0.5)
    parked[scene.sdc_index] = False
    assert parked.sum() >= 5
    assert out.num_tracks == scene.num_tracks - parked.sum()
    assert set(out.tracks.ids.tolist()) == set(tr.ids[~parked].tolist())
    assert out.tracks.ids[out.sdc_index] == tr.ids[scene.sdc_index]
    kept = np.flatnonzero(~parked)
    np.testing.assert_array_equal(out.tracks.position, tr.position[kept])


def test_scene_pack_round_trips_the_sample_scenes_within_its_grids(tmp_path):
    """benchmarks/scene_pack.py (how scenes travel to a lent GPU): unpacked scenes are the packed ones, in
    order, with every metric array within half a grid step and everything else equal."""
    from envs._pool import ScenePool

    pack = _load("scene_pack")
    info = pack.pack(["embedded"], str(tmp_path / "s.npz.xz"), count=None)
    assert pack.unpack(str(tmp_path / "s.npz.xz"), str(tmp_path / "cache")) == {"scenes": info["scenes"]}
    before, after = ScenePool("embedded"), ScenePool(str(tmp_path / "cache"))
    assert len(after) == len(before) == info["scenes"] >= 2
    for i in range(len(before)):
        (a, meta_a), (b, meta_b) = before.scenario(i).to_arrays(), after.scenario(i).to_arrays()
        assert meta_a == meta_b and a.keys() == b.keys()
        for name in a:
            if name in pack.GRIDS:
                step = pack.GRIDS[name][0]
                np.testing.assert_allclose(b[name], a[name], rtol=0, atol=step * 0.51 + 1e-4, err_msg=name)
            else:
                np.testing.assert_array_equal(b[name], a[name], err_msg=name)
