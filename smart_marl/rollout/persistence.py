"""Rollout stage, speed persistence: a vehicle's draw leans toward going on with the change of speed it is in.

What comes in: a :class:`~smart_marl.rollout.RolloutState` (each slot's pose, the pose 0.5 s before it, the speed
of the token before that, ``speed_before``, and the state's ``persistence``), the rows of the slots being drawn,
and their logits. What goes out: the logits the draw ranks and samples from, each vehicle row tilted by

    persistence * change_before * clamp(token_speed - speed_now, -TOKEN_CHANGE_CLIP_MPS, TOKEN_CHANGE_CLIP_MPS)

where ``speed_now`` is the mean speed of the token the vehicle is on, ``change_before`` = ``speed_now`` less the
mean speed of the token before it (m/s per 0.5 s, clamped to +-:data:`CHANGE_CLIP_MPS`) and ``token_speed`` each
candidate token's mean speed. A vehicle that has been speeding up leans toward the tokens that speed it up, one
that has been slowing toward those that slow it, in proportion; one at a steady speed draws as the model says.
The log-probabilities a draw reports stay the model's (as with the tokens collision-aware sampling takes out):
the KL to the prior, the likelihood of a rollout and an environment's ``prior_logits`` do not see the tilt.

Why: teacher-forced on scenes of its own kind, the prior continues about a quarter of an acceleration it has
just made (+0.22 m/s predicted at the next token against +0.94 logged) and 60% of a deceleration
(``docs/experiments/2026-11-27-speeding-up.md``): it reads its speed off the token it is on, hardly the change
across tokens, and in closed loop a change of speed dies out. A model trained with the change as an input took it
up slowly on the CPU; this tilt is the same correction made at the draw. Measured on the 7 scoreable shared real
scenes over twelve seeds (``docs/experiments/2026-11-29-speed-persistence.md``), the default 0.25 raises the
realism meta-metric from 0.7224 to 0.7284 (kinematic +0.008, map-based +0.013); 0.5 gains less, and tilts that
favour speeding up over slowing buy speed with realism. The clamp keeps the tilt bounded: a token moves at most
``1.5 * persistence * 3`` nats up or down, so the tilt reorders the model's likely tokens, and a token more than twice
that below another never overtakes it.
"""

from __future__ import annotations

import torch

from ..config_files import check_value, number
from ..scenario import AgentType
from ..tokens import FRAMES_PER_TOKEN, MOTION_TYPES

DEFAULT_PERSISTENCE = 0.25
"""The tilt's strength (1/(m/s)^2) unless told otherwise (rollouts, both environments, what-if, ``smart-marl
eval``); 0 turns it off (the model's distribution as it is)."""
CHANGE_CLIP_MPS = 3.0
"""The change of speed over the last token (m/s per 0.5 s) is clamped to +- this: larger ones are rare, and
usually a token mismatch, not a driver."""
TOKEN_CHANGE_CLIP_MPS = 1.5
"""A candidate token's change of speed is clamped to +- this in the tilt (module docstring)."""
TOKEN_S = 0.5
_VEHICLE = MOTION_TYPES.index(AgentType.VEHICLE)


persistence_rule = number(0.0)
"""The rule (:mod:`smart_marl.config_files`) of a persistence: a finite number >= 0."""


def check_persistence(persistence) -> float:
    """``persistence`` as a float, refused with a ValueError naming it unless a finite number >= 0."""
    return float(check_value("persistence", persistence, persistence_rule, ValueError))


def mean_speed(end: torch.Tensor, start: torch.Tensor) -> torch.Tensor:
    """The mean speed (m/s) of tokens from poses ``start`` to ``end`` [..., 3]: NaN where a pose is NaN."""
    return torch.linalg.vector_norm(end[..., :2] - start[..., :2], dim=-1) / TOKEN_S


def speed_before_history(valid: torch.Tensor, start: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """[G, N] the mean speed of the history's token before the current one (valid [G, N, S], start / end
    [G, N, S, 3]; NaN where that token or the current one is missing, or the history has one step)."""
    if valid.shape[2] < 2:
        return torch.full(valid.shape[:2], float("nan"), device=start.device)
    ok = valid[:, :, -1] & valid[:, :, -2]
    return torch.where(ok, mean_speed(end[:, :, -2], start[:, :, -2]), torch.full_like(ok, float("nan"), dtype=start.dtype))


def token_speeds(token_poses: torch.Tensor) -> torch.Tensor:
    """[types, Vmax] every token's mean speed (token_poses [types, Vmax, 6, 3], the start at frame 0)."""
    return mean_speed(token_poses[:, :, FRAMES_PER_TOKEN], token_poses[:, :, 0])


def tilted(state, rows: torch.Tensor, row_logits: torch.Tensor) -> torch.Tensor:
    """``row_logits`` [R, V] of the flat slots ``rows`` with each vehicle's tilt added (module docstring); the same
    tensor when ``state.persistence`` is 0 or no row has a change of speed to go on with."""
    if state.persistence == 0.0 or not len(rows):
        return row_logits
    now = mean_speed(state.pose.reshape(-1, 3).index_select(0, rows), state.previous_pose.reshape(-1, 3).index_select(0, rows))
    change = (now - state.speed_before.reshape(-1).index_select(0, rows)).clamp(-CHANGE_CLIP_MPS, CHANGE_CLIP_MPS)
    vehicle = state.agent_type.reshape(-1).index_select(0, rows) == _VEHICLE
    at = (vehicle & torch.isfinite(change) & (change != 0)).nonzero().squeeze(1)
    if not len(at):
        return row_logits
    speeds = state.token_speeds[_VEHICLE, : row_logits.shape[1]]
    towards = (speeds[None, :] - now.index_select(0, at)[:, None]).clamp(-TOKEN_CHANGE_CLIP_MPS, TOKEN_CHANGE_CLIP_MPS)
    out = row_logits.clone()
    out[at] += state.persistence * change.index_select(0, at)[:, None] * towards
    return out


__all__ = ["CHANGE_CLIP_MPS", "DEFAULT_PERSISTENCE", "TOKEN_CHANGE_CLIP_MPS", "check_persistence", "mean_speed", "persistence_rule",
           "speed_before_history", "tilted", "token_speeds"]
