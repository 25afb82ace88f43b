"""Which agents ``controlled="moving_vehicles"`` (the env's and fine-tuning's default) hands to a policy: vehicles that
move along the log, and not one that already overlaps another agent's box at the current frame (a log artefact such as
two SUMO cars standing overlapped in a junction: it collides at the first step whatever the policy does)."""

from __future__ import annotations

import dataclasses

import numpy as np

from envs._setup import moving_vehicles_mask, overlapping_at_start, select_controlled
from envs._scene import scene_static
from smart_marl.geometry import colliding


def _moved_onto(scene, mover: int, onto: int):
    """``scene`` with track ``mover`` placed at track ``onto``'s pose at the current frame."""
    tr, cf = scene.tracks, scene.current_frame
    position, heading = tr.position.copy(), tr.heading.copy()
    position[mover, cf], heading[mover, cf] = position[onto, cf], heading[onto, cf]
    return dataclasses.replace(scene, tracks=dataclasses.replace(tr, position=position, heading=heading))


def test_a_moving_vehicle_inside_another_box_at_the_start_is_not_controlled(sample_scenes):
    scene = sample_scenes[2]  # sumo-7-000000-02: 44 tracks
    moving = moving_vehicles_mask(scene)
    assert not overlapping_at_start(scene).any()  # the generated sample scene has no such pair
    tr, cf = scene.tracks, scene.current_frame
    mover = int(np.flatnonzero(moving)[0])
    onto = int(next(i for i in np.flatnonzero(tr.valid[:, cf] & ~moving) if i != mover))  # a present agent not selected
    edited = _moved_onto(scene, mover, onto)
    over = overlapping_at_start(edited)
    assert over[mover] and over[onto] and over.sum() == 2
    size = tr.box_size()
    pose = np.concatenate([edited.tracks.position[:, cf, :2], edited.tracks.heading[:, cf, None]], -1)[:, None]
    assert np.array_equal(over, colliding(pose, tr.valid[:, cf, None], size[:, 0], size[:, 1]))  # the collision event's test
    expected = moving.copy()
    expected[mover] = False
    assert np.array_equal(moving_vehicles_mask(edited), expected)  # only it leaves the selection
    chosen = select_controlled("moving_vehicles", scene_static(edited), max_agents=None)
    assert mover not in chosen.tolist() and len(chosen) == expected.sum()
