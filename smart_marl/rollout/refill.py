"""Rollout stage, refilling a batch: new scenes put in place of finished ones in a running
:class:`~smart_marl.rollout.RolloutState`, so that a batch of many scenes stays full while its
scenes end at different times (the batched environment's refill; :mod:`envs._core`).

What comes in: a running state (mode ``"cached"``), the rows (scenes) to replace and a state
started on the new scenes with the same model, vocabulary and number of rollouts (e.g. a fork of
a freshly started state kept per scene). What goes out: the running state, whose replaced scenes
now continue exactly as the new state would (their KV cache, road encodings, agent slots and
pending step are the new state's), and whose other scenes are untouched. Agent slots and road
pieces grow to the larger of the two states; the padding is never valid, so the model's
neighbourhoods never see it.
"""

from __future__ import annotations

from typing import Sequence

import torch

from ..padding import grow, put_rows
from .engine import RolloutState

_PER_GROUP = {"track_index": -1, "agent_type": 0, "agent_shape": 0.0, "simulated": False, "agent_ids": -1, "pose": 0.0,
              "previous_pose": 0.0}
_PER_SCENE = {"road_pose": 0.0, "road_valid": False, "road_points": 0.0, "road_type": 0, "road_light": 0, "road_x": 0.0}


def replace_scenes(state: RolloutState, rows: Sequence[int], new: RolloutState) -> None:
    """Replace scenes ``rows`` of ``state`` by the scenes of ``new``, in order (see the module
    docstring). ``new`` is not changed (when ``state`` has computed its next logits and ``new`` has
    not, a fork of ``new`` computes them). Both must be in mode ``"cached"``, with the same model
    and number of rollouts; ``state``'s sampler (its generator) is kept."""
    rows = [int(b) for b in rows]
    if state.mode != "cached" or new.mode != "cached":
        raise ValueError("replace_scenes needs states in mode 'cached'")
    if new.model is not state.model:
        raise ValueError("replace_scenes needs a state of the same model")
    if len(rows) != len(new.scenes) or new.num_rollouts != state.num_rollouts:
        raise ValueError(f"replace_scenes: {len(rows)} rows for {len(new.scenes)} new scene(s) of {new.num_rollouts} rollout(s) "
                         f"each (this state has {state.num_rollouts})")
    if len(set(rows)) != len(rows) or not all(0 <= b < len(state.scenes) for b in rows):
        raise ValueError(f"replace_scenes: rows must be distinct scene indices in 0..{len(state.scenes) - 1}, got {rows}")
    if not rows:
        return
    if state._logits is not None and new._logits is None:
        new = new.fork(0)  # the fork's own cache takes the pending step; ``new`` stays as it was
        new.logits()
    elif state._logits is None and new._logits is not None:
        raise ValueError("replace_scenes: the new state has taken a step this state has not")
    dev = state.device
    r = state.num_rollouts
    scenes = torch.tensor(rows, dtype=torch.long, device=dev)
    groups = (scenes[:, None] * r + torch.arange(r, device=dev)).reshape(-1)
    n = max(state.num_slots, new.num_slots)
    pieces = max(state.road_pose.shape[1], new.road_pose.shape[1])
    for name, fill in _PER_GROUP.items():
        setattr(state, name, grow(getattr(state, name), {1: n}, fill))
        put_rows(getattr(state, name), groups, getattr(new, name).to(dev), fill)
    for name, fill in _PER_SCENE.items():
        setattr(state, name, grow(getattr(state, name), {1: pieces}, fill))
        put_rows(getattr(state, name), scenes, getattr(new, name).to(dev), fill)
    if state._logits is not None:
        state._logits = grow(state._logits, {1: n}, float("-inf"))
        put_rows(state._logits, groups, new._logits.to(dev), float("-inf"))
    else:
        fills = (0, 0.0, 0.0, False)
        state._pending = tuple(grow(t, {1: n}, f) for t, f in zip(state._pending, fills))
        for t, src, f in zip(state._pending, new._pending, fills):
            put_rows(t, groups, src.to(dev), f)
    state.cache.replace(groups, scenes, new.cache)
    state.num_slots = n
    for b, sc in zip(rows, new.scenes):
        state.scenes[b] = sc


__all__ = ["replace_scenes"]
