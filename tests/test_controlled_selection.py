"""Which agents ``controlled="moving_vehicles"`` (the env's and fine-tuning's default) hands to a policy: vehicles that
move along the log, and not one that already overlaps another agent's box at the current frame (a log artefact such as
two SUMO cars standing overlapped in a junction: it collides at the first step whatever the policy does)."""

from __future__ import annotations

import dataclasses

import numpy as np

from envs._setup import moving_vehicles_mask, overlapping_at_start, select_controlled
from envs._scene import scene_static


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
    # just clear of it, behind it along its heading by the two half lengths and 0.3 m: not inside, so still selected
    size, h = tr.box_size(), float(tr.heading[onto, cf])
    step = (size[mover, 0] + size[onto, 0]) / 2 + 0.3
    position = edited.tracks.position.copy()
    position[mover, cf, :2] -= step * np.array([np.cos(h), np.sin(h)], np.float32)
    clear = dataclasses.replace(edited, tracks=dataclasses.replace(edited.tracks, position=position))
    assert not overlapping_at_start(clear).any() and moving_vehicles_mask(clear)[mover]
    expected = moving.copy()
    expected[mover] = False
    assert np.array_equal(moving_vehicles_mask(edited), expected)  # only it leaves the selection
    chosen = select_controlled("moving_vehicles", scene_static(edited), max_agents=None)
    assert mover not in chosen.tolist() and len(chosen) == expected.sum()
