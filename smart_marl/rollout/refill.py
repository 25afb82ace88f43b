"""Rollout stage, batches of scenes that change: new scenes put in place of finished ones in a
running :class:`~smart_marl.rollout.RolloutState`, so that a batch of many scenes stays full while
its scenes end at different times (the batched environment's refill; :mod:`envs._core`).

* :func:`split_state`: a state started on several scenes at once -> one state per scene (starting
  many scenes together is cheaper; the environment keeps the freshly started state of each scene);
* :func:`stack_states`: states of single scenes -> one state of all of them (a batch's reset);
* :func:`replace_scenes`: some scenes of a running state replaced by the scenes of another state,
  the others untouched (a batch's refill).

Every one of them keeps the numbers: a scene continues exactly as the state it came from would (its
KV cache, road encodings, agent slots and pending step go with it). Agent slots and road pieces are
padded to the largest scene's; the padding is never valid, so the model's neighbourhoods never see
it. States must be in mode ``"cached"`` and of the same model and number of rollouts.
"""

from __future__ import annotations

import copy
from typing import Sequence

import torch

from ..model.motionnet import MotionCache
from ..padding import grow, put_rows
from .engine import RolloutState

_PER_GROUP = {"track_index": -1, "agent_type": 0, "agent_shape": 0.0, "simulated": False, "agent_ids": -1, "pose": 0.0,
              "previous_pose": 0.0, "speed_before": float("nan")}
_PER_SCENE = {"road_pose": 0.0, "road_valid": False, "road_points": 0.0, "road_type": 0, "road_light": 0, "road_x": 0.0}
_STOP_LINES = {"stop_xy": 0.0, "stop_dir": float("nan"), "stop_group": 0, "stop_sign": False, "stop_red": False,
               "stop_go": False, "stop_turn_red": False, "stop_valid": False}
"""Per scene, padded to the most stop lines (states with ``stop_lines``); the slots' served signs go with the slots."""
_STEPS = {"road_light_steps": ("road_pose", 0), "stop_red_steps": ("stop_xy", False), "stop_go_steps": ("stop_xy", False), "stop_turn_red_steps": ("stop_xy", False),
          "light_config_steps": (None, 0)}
"""Per scene and logged token step [B, S, ...]: padded to the most steps by holding each scene's last one, and to the
most road pieces / stop lines (the tensor whose second dimension gives that size) with the fill."""
_CLOCKS = ("scene_clock", "light_config")
"""Per scene [B]: its token steps so far, and (lights="log") the light configuration its road encodings are of."""


_PENDING_FILLS = (0, 0.0, 0.0, False)  # tokens, start pose, end pose, valid of the step not yet run


def _check(states: Sequence[RolloutState]) -> None:
    first = states[0]
    for st in states:
        if st.mode != "cached":
            raise ValueError("batching rollout states needs states in mode 'cached'")
        if st.model is not first.model or st.num_rollouts != first.num_rollouts:
            raise ValueError("batching rollout states needs states of the same model and number of rollouts")
        if st.lights != first.lights:
            raise ValueError("batching rollout states needs states that all see the lights the same way (lights=...)")
        if st.stop_lines != first.stop_lines:
            raise ValueError("batching rollout states needs states that all stop at stop lines, or none")


def _per_group(state: RolloutState) -> dict:
    """The per-slot tensors of ``state`` and their padding (``stop_served`` [G, N, L] also grows with the lines)."""
    return {**_PER_GROUP, "stop_served": False, "stop_stood": 0, "stop_moved": False} if state.stop_lines else _PER_GROUP


def _steps(state: RolloutState) -> dict:
    """The per-scene, per-step tensors of ``state`` (those it has) and what sizes them (:data:`_STEPS`)."""
    return {name: how for name, how in _STEPS.items() if getattr(state, name, None) is not None}


def _held(t: torch.Tensor, steps: int, size: int | None, fill) -> torch.Tensor:
    """``t`` [B, S, K, ...] padded to ``steps`` steps by repeating its last step, then to ``size`` along K with ``fill``."""
    if t.shape[1] < steps:
        t = torch.cat([t, t[:, -1:].expand(-1, steps - t.shape[1], *t.shape[2:])], 1)
    return t if size is None else grow(t, {2: size}, fill)


def _sizes(name: str, states: Sequence[RolloutState]) -> tuple[int, int | None]:
    """(the most steps, the most pieces or lines, None for [B, S]) of per-step tensor ``name`` among ``states``."""
    of = _STEPS[name][0]
    return (max(getattr(st, name).shape[1] for st in states),
            None if of is None else max(getattr(st, of).shape[1] for st in states))


def _configs_size(states: Sequence[RolloutState]) -> dict[int, int]:
    """The budgets of ``road_x_configs`` [B, K, R, d] among ``states``: the most configurations and road pieces."""
    return {1: max(st.road_x_configs.shape[1] for st in states), 2: max(st.road_pose.shape[1] for st in states)}


def _lines(state: RolloutState) -> dict:
    """The per-scene stop-line tensors of ``state`` (none without ``stop_lines``) and their padding."""
    return _STOP_LINES if state.stop_lines else {}


def _same_phase(states: Sequence[RolloutState]) -> list[RolloutState]:
    """The states, those that have not computed their next logits while another has replaced by a
    fork that has (the originals are not changed)."""
    if all(st._logits is None for st in states):
        return list(states)
    out = []
    for st in states:
        if st._logits is None:
            st = st.fork(0)
            st.logits()
        out.append(st)
    return out


def stack_states(states: Sequence[RolloutState], seed: int) -> RolloutState:
    """One state of the scenes of ``states`` in order (their groups one after the other), with a new
    sampler seeded with ``seed``. The inputs are not changed and share nothing written later."""
    _check(states)
    states = _same_phase(states)
    # one state too goes through the concatenations below (copies): a fork alone would share the tensors that
    # replace_scenes writes in place, and a refill of the result would write into the state it came from
    first = states[0]
    n = max(st.num_slots for st in states)
    pieces = max(st.road_pose.shape[1] for st in states)
    out = first.fork(seed)
    lines = max(st.stop_xy.shape[1] for st in states) if first.stop_lines else 0
    for name, fill in _per_group(first).items():
        setattr(out, name, torch.cat([grow(getattr(st, name), {1: n, 2: lines} if name == "stop_served" else {1: n}, fill)
                                      for st in states]))
    for name, fill in _PER_SCENE.items():
        setattr(out, name, torch.cat([grow(getattr(st, name), {1: pieces}, fill) for st in states]))
    for name, fill in _lines(first).items():
        setattr(out, name, torch.cat([grow(getattr(st, name), {1: lines}, fill) for st in states]))
    for name, (_, fill) in _steps(first).items():
        steps, size = _sizes(name, states)
        setattr(out, name, torch.cat([_held(getattr(st, name), steps, size, fill) for st in states]))
    if first.road_x_configs is not None:
        sizes = _configs_size(states)
        out.road_x_configs = torch.cat([grow(st.road_x_configs, sizes, 0.0) for st in states])
    for name in _CLOCKS:
        if getattr(first, name) is not None:
            setattr(out, name, torch.cat([getattr(st, name) for st in states]))
    if first._logits is not None:
        out._logits = torch.cat([grow(st._logits, {1: n}, float("-inf")) for st in states])
    else:
        out._pending = tuple(torch.cat([grow(st._pending[k], {1: n}, f) for st in states]) for k, f in enumerate(_PENDING_FILLS))
    out.cache = MotionCache.stack([st.cache for st in states])
    out.scenes = [sc for st in states for sc in st.scenes]
    out.num_groups, out.num_slots = sum(st.num_groups for st in states), n
    out.scene_of_group = torch.arange(len(out.scenes), device=out.device).repeat_interleave(out.num_rollouts)
    out.history = []  # mode "cached" reads no history
    return out


def split_state(state: RolloutState) -> list[RolloutState]:
    """One state per scene of ``state`` (each cut to its own agent slots and road pieces), sharing
    ``state``'s tensors until either steps."""
    _check([state])
    r = state.num_rollouts
    out = []
    for b, sc in enumerate(state.scenes):
        groups = torch.arange(b * r, (b + 1) * r, device=state.device)
        n = max(int((state.track_index[groups] >= 0).sum(1).max()), 1)  # slots are filled from the first
        pieces = max(int(state.road_valid[b].sum()), 1)
        one = copy.copy(state)
        for name in _per_group(state):
            setattr(one, name, getattr(state, name)[groups, :n])
        for name in [*_PER_SCENE, *_lines(state)]:
            setattr(one, name, getattr(state, name)[b : b + 1, :pieces] if name in _PER_SCENE else getattr(state, name)[b : b + 1])
        for name in _steps(state):
            setattr(one, name, getattr(state, name)[b : b + 1, :, :pieces] if name == "road_light_steps" else getattr(state, name)[b : b + 1])
        if state.road_x_configs is not None:
            one.road_x_configs = state.road_x_configs[b : b + 1, :, :pieces]
        for name in _CLOCKS:
            if getattr(state, name) is not None:
                setattr(one, name, getattr(state, name)[b : b + 1])
        if state._logits is not None:
            one._logits = state._logits[groups, :n]
        else:
            one._pending = tuple(t[groups, :n] for t in state._pending)
        one.cache = state.cache.take(groups, torch.tensor([b], device=state.device), n, pieces)
        one.scenes, one.num_groups, one.num_slots = [sc], r, n
        one.scene_of_group = torch.zeros(r, dtype=torch.long, device=state.device)
        one.history = []
        one.generator = torch.Generator(device=state.device).manual_seed(0)
        out.append(one)
    return out


def replace_scenes(state: RolloutState, rows: Sequence[int], new: RolloutState) -> None:
    """Replace scenes ``rows`` of ``state`` by the scenes of ``new``, in order (see the module
    docstring). ``new`` is not changed (when ``state`` has computed its next logits and ``new`` has
    not, a fork of ``new`` computes them). Both must be in mode ``"cached"``, with the same model
    and number of rollouts; ``state``'s sampler (its generator) is kept."""
    rows = [int(b) for b in rows]
    _check([state, new])
    if len(rows) != len(new.scenes):
        raise ValueError(f"replace_scenes: {len(rows)} rows for {len(new.scenes)} new scene(s)")
    if len(set(rows)) != len(rows) or not all(0 <= b < len(state.scenes) for b in rows):
        raise ValueError(f"replace_scenes: rows must be distinct scene indices in 0..{len(state.scenes) - 1}, got {rows}")
    if not rows:
        return
    state._ahead = None  # tokens drawn ahead (draw_ahead) for the scenes that go: the next step draws again
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
    lines = max(state.stop_xy.shape[1], new.stop_xy.shape[1]) if state.stop_lines else 0
    for name, fill in _per_group(state).items():
        setattr(state, name, grow(getattr(state, name), {1: n, 2: lines} if name == "stop_served" else {1: n}, fill))
        put_rows(getattr(state, name), groups, getattr(new, name).to(dev), fill)
    for name, fill in _PER_SCENE.items():
        setattr(state, name, grow(getattr(state, name), {1: pieces}, fill))
        put_rows(getattr(state, name), scenes, getattr(new, name).to(dev), fill)
    for name, fill in _lines(state).items():
        setattr(state, name, grow(getattr(state, name), {1: lines}, fill))
        put_rows(getattr(state, name), scenes, getattr(new, name).to(dev), fill)
    for name, (_, fill) in _steps(state).items():
        steps, size = _sizes(name, [state, new])
        setattr(state, name, _held(getattr(state, name), steps, size, fill))
        put_rows(getattr(state, name), scenes, _held(getattr(new, name).to(dev), steps, size, fill), fill)
    if state.road_x_configs is not None:
        sizes = _configs_size([state, new])
        state.road_x_configs = grow(state.road_x_configs, sizes, 0.0)
        put_rows(state.road_x_configs, scenes, new.road_x_configs.to(dev), 0.0)
    for name in _CLOCKS:
        if getattr(state, name) is not None:
            setattr(state, name, getattr(state, name).clone())
            getattr(state, name)[scenes] = getattr(new, name).to(dev)
    if state._logits is not None:
        state._logits = grow(state._logits, {1: n}, float("-inf"))
        put_rows(state._logits, groups, new._logits.to(dev), float("-inf"))
    else:
        state._pending = tuple(grow(t, {1: n}, f) for t, f in zip(state._pending, _PENDING_FILLS))
        for t, src, f in zip(state._pending, new._pending, _PENDING_FILLS):
            put_rows(t, groups, src.to(dev), f)
    state.cache.replace(groups, scenes, new.cache)
    state.num_slots = n
    for b, sc in zip(rows, new.scenes):
        state.scenes[b] = sc


__all__ = ["replace_scenes", "split_state", "stack_states"]
