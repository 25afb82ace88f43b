"""Batches of scenes that change (smart_marl.rollout.refill): a scene split out of a batch, stacked into
another or put in place of a finished one continues exactly as the state it came from would. The
references are states started on the scenes directly, stepped with the same forced tokens."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from smart_marl.embedded import sample_scenarios
from smart_marl.model.checkpoint import load_prior
from smart_marl.model.motionnet import MotionCache
from smart_marl.rollout import RolloutState
from smart_marl.rollout.refill import replace_scenes, split_state, stack_states

from model_variants import with_speed_change

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module", params=["embedded", "speed_change"])
def prior_and_scenes(request):
    """The embedded prior, and the same with the speed-change input on and not zero: its cache keeps the
    speed of each slot's last token (``MotionCache.speed``), which splitting, stacking and replacing carry."""
    model, vocab = load_prior("embedded", "cpu")
    if request.param == "speed_change":
        model = with_speed_change(model, 0.5)
    return model, vocab, sample_scenarios()


def _forced(state: RolloutState, k: int) -> torch.Tensor:
    """Tokens that depend only on each slot's track and the step (so every state agrees on them)."""
    f = torch.full((state.num_groups, state.num_slots), -1, dtype=torch.long)
    sim = state.simulated
    f[sim] = (state.track_index[sim] * 7 + 3 * k) % 512
    return f


def _assert_same_rows(got: torch.Tensor, want: torch.Tensor) -> None:
    """Logits of one scene [N_got, V] and [N_want, V]: equal on the reference's slots, -inf beyond."""
    n = want.shape[0]
    fin = torch.isfinite(want)
    assert torch.equal(torch.isfinite(got[:n]), fin)
    torch.testing.assert_close(got[:n][fin], want[fin], rtol=0, atol=2e-5)
    assert torch.isinf(got[n:]).all()


def test_split_then_stack_in_another_order_gives_each_scene_its_own_numbers(prior_and_scenes):
    model, vocab, scenes = prior_and_scenes
    ref = [RolloutState.start(model, sc, seed=0) for sc in scenes]
    parts = split_state(RolloutState.start(model, scenes, seed=0))
    order = [2, 0, 3, 1]
    batch = stack_states([parts[i] for i in order], seed=0)
    assert batch.num_slots == max(p.num_slots for p in parts) and [s.scenario_id for s in batch.scenes] == [scenes[i].scenario_id for i in order]
    for k in range(3):
        logits = batch.logits()
        for row, i in enumerate(order):
            _assert_same_rows(logits[row], ref[i].logits()[0])
        batch.step(_forced(batch, k))
        for r in ref:
            r.step(_forced(r, k))


def test_replacing_a_scene_mid_rollout_leaves_the_others_and_starts_the_new_one_fresh(prior_and_scenes):
    model, vocab, scenes = prior_and_scenes
    batch = RolloutState.start(model, scenes[:2], seed=0)
    keep = RolloutState.start(model, scenes[1], seed=0)
    for k in range(2):
        batch.step(_forced(batch, k))
        keep.step(_forced(keep, k))
    batch.logits()  # the running state has computed its next step, the new one has not: replace brings it there
    fresh = RolloutState.start(model, scenes[2], seed=0)
    replace_scenes(batch, [0], fresh)
    assert fresh._logits is None  # the new state is not changed
    assert batch.scenes[0] is scenes[2] and batch.num_slots >= fresh.num_slots
    ref = RolloutState.start(model, scenes[2], seed=0)
    for k in range(3):
        logits = batch.logits()
        _assert_same_rows(logits[0], ref.logits()[0])
        _assert_same_rows(logits[1], keep.logits()[0])
        forced = torch.full((2, batch.num_slots), -1, dtype=torch.long)
        f_ref, f_keep = _forced(ref, k), _forced(keep, k + 2)
        forced[0, : ref.num_slots], forced[1, : keep.num_slots] = f_ref[0], f_keep[0]
        batch.step(forced)
        ref.step(f_ref)
        keep.step(f_keep)


def test_replace_refuses_states_it_cannot_combine(prior_and_scenes):
    model, vocab, scenes = prior_and_scenes
    batch = RolloutState.start(model, scenes[:2], seed=0)
    with pytest.raises(ValueError, match="rows"):
        replace_scenes(batch, [0, 1], RolloutState.start(model, scenes[2], seed=0))
    with pytest.raises(ValueError, match="distinct"):
        replace_scenes(batch, [5], RolloutState.start(model, scenes[2], seed=0))
    with pytest.raises(ValueError, match="cached"):
        replace_scenes(batch, [0], RolloutState.start(model, scenes[2], seed=0, mode="full"))


def test_the_cache_names_every_tensor_it_keeps_per_slot(prior_and_scenes):
    """Splitting, stacking and replacing carry ``MotionCache.PER_SLOT`` (and ``src``): a per-slot tensor the
    cache gains must be named there."""
    model, vocab, scenes = prior_and_scenes
    cache = RolloutState.start(model, scenes[:2], seed=0).cache
    flat = cache.num_groups * cache.num_slots
    assert cache.road_pose_flat.shape[0] != flat  # no per-scene tensor of the same length to mistake
    per_slot = {f.name for f in dataclasses.fields(cache)
                if isinstance(getattr(cache, f.name), torch.Tensor) and getattr(cache, f.name).shape[0] == flat}
    assert per_slot == set(MotionCache.PER_SLOT)
    assert all(t.shape[0] == flat for t in cache.src)
