"""The pruned kernels of the environment's step give exactly what the plain computation gives: the
collision-aware sampler's pair bound (:func:`smart_marl.rollout.avoidance.frames_collide` against
:func:`~smart_marl.rollout.avoidance.boxes_overlap_near` on every pair). Each case is built so that a
bound cut too tight would drop pairs that do overlap."""

from __future__ import annotations

import math

import pytest
import torch

from smart_marl.rollout.avoidance import boxes_overlap_near, frames_collide

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def _crowd(seed: int, r: int = 40, c: int = 12, f: int = 5, k: int = 16, spread: float = 12.0, headings: int = 5):
    """Random rows: paths of c candidates from the row's centre (straight, curved, long and short),
    and k others moving over the frames (``headings`` 1: a held heading; 5: one per frame)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    own_xy = (u(r, 2) - 0.5) * spread
    own_half = torch.stack([0.4 + 2.2 * u(r), 0.4 + 0.8 * u(r)], -1)
    h0 = (u(r, 1, 1) - 0.5) * 2 * math.pi
    speed = 12 * u(r, c, 1) ** 2  # up to 12 m a step
    turn = (u(r, c, 1) - 0.5) * 1.5
    s = torch.arange(1, f + 1, dtype=torch.float64) / f
    heading = h0 + turn * s
    step = speed * s
    frames = torch.stack([own_xy[:, None, None, 0] + step * heading.cos(), own_xy[:, None, None, 1] + step * heading.sin(), heading], -1)
    now = own_xy[:, None] + (u(r, k, 2) - 0.5) * spread
    move = (u(r, k, 2) - 0.5) * 10
    other_xy = now[:, None] + s[None, :, None, None] * move[:, None]  # [R, F, K, 2]
    other_h = (u(r, headings, k) - 0.5) * 2 * math.pi
    other_half = torch.stack([0.4 + 2.2 * u(r, k), 0.4 + 0.8 * u(r, k)], -1)
    ok = u(r, k) < 0.85
    gap = (now - own_xy[:, None]).norm(dim=-1) - move.norm(dim=-1)
    return frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok


def _plain(frames, own_half, other_xy, other_h, other_half, ok):
    """Every (row, path, frame, other) through boxes_overlap_near: [R, c]."""
    hit = boxes_overlap_near(frames[..., None, :2], frames[..., None, 2], own_half[:, None, None, None], other_xy[:, None],
                             other_h[:, None], other_half[:, None, None], where=ok[:, None, None])
    return hit.flatten(2).any(-1)


@pytest.mark.parametrize("seed,spread,headings,k", [(0, 30.0, 5, 16), (1, 12.0, 1, 3), (2, 50.0, 5, 16), (3, 8.0, 1, 1)])
def test_the_pair_bound_of_the_sampler_keeps_every_colliding_pair(seed, spread, headings, k):
    frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok = _crowd(seed, k=k, spread=spread, headings=headings)
    want = _plain(frames, own_half, other_xy, other_h, other_half, ok)
    got = frames_collide(frames, own_xy, own_half, other_xy, other_h.cos(), other_h.sin(), other_half, gap, ok)
    assert 0.05 < want.double().mean() < 0.95, want.double().mean()  # both outcomes are exercised
    assert torch.equal(got, want)


def test_the_pair_bound_fails_when_the_gap_is_overstated():
    """The check above would notice a bound that is too tight: with the others' travel left out of
    their gap (a wrong bound), pairs that do collide are dropped."""
    frames, own_xy, own_half, other_xy, other_h, other_half, gap, ok = _crowd(0, spread=30.0)
    want = _plain(frames, own_half, other_xy, other_h, other_half, ok)
    wrong_gap = (other_xy[:, 0] - own_xy[:, None]).norm(dim=-1)  # distance on the first frame, travel ignored
    got = frames_collide(frames, own_xy, own_half, other_xy, other_h.cos(), other_h.sin(), other_half, wrong_gap, ok)
    assert not torch.equal(got, want)
