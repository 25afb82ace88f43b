"""Rollout stage, the draw: every simulated agent's next token, chosen from the step's logits.

What comes in: a :class:`~smart_marl.rollout.RolloutState` whose next-token logits are computed, and the step's
forced tokens ``[G, N]``: ``-1`` where the token is drawn, a token id where it is imposed, or
:data:`FORCED_LATER` where it will be imposed by a caller that does not know it yet. What goes out: a
:class:`Draw`, the simulated slots' tokens and log-probabilities (the forced-later slots' still to come).

Why "later": SMART draws every agent's next token from one forward pass, and a policy that acts with the
background acts at the same time as it (the environment's simultaneous moves). Drawn before the policy's
tokens are known (:meth:`RolloutState.draw_ahead <smart_marl.rollout.RolloutState.draw_ahead>`), the
background's tokens cannot depend on them, and a shield can test the policy's tokens against where the
background will really be (:mod:`envs._shield`). Collision-aware sampling and the stop lines then see a
forced-later agent as any other neighbour whose token is not known, at constant velocity
(:mod:`~smart_marl.rollout.avoidance`), and collision-aware sampling also where it stands now
(:func:`later_standing_test`: the policy may brake, and a background car close behind it must not drive on
into it); an agent forced with a known token is seen on the frames that token
takes it to. With no forced-later slot a draw is the one :meth:`RolloutState.step
<smart_marl.rollout.RolloutState.step>` makes, bit for bit: the same computation in the same order, the same
random numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..tokens import FRAMES_PER_TOKEN
from ..geometry_torch import bound_length, loose
from .avoidance import excluded_tokens, standing_test, token_reach
from .frames import candidate_frames, token_frames
from .persistence import tilted
from .sampling import sample_tokens
from .stop_lines import stop_line_test

FORCED_LATER = -2
"""A forced-token entry: this slot's token will be imposed at the step, and is not known at the draw."""


@dataclass
class Draw:
    """The tokens of one step, drawn from ``logits`` (the state's, the tensor itself: a draw belongs to the
    logits it was made from) with the forced tokens ``forced`` [G, N]."""

    logits: torch.Tensor  # [G, N, Vmax]
    forced: torch.Tensor  # [G, N] int64, as given (-1 drawn, FORCED_LATER, or a token id)
    rows: torch.Tensor  # [R] the simulated slots, flat indices into G x N
    tokens: torch.Tensor  # [R] int64 (a placeholder on forced-later rows)
    log_probs: torch.Tensor  # [R] under log_softmax(logits / temperature) (a placeholder on forced-later rows)

    def frames(self, state) -> tuple[torch.Tensor, torch.Tensor]:
        """(frames [G, N, 5, 3], known [G, N]): the step's 5 frames of every slot whose token this draw knows
        (drawn, or forced with a known token), placed at ``state``'s poses as the step places them; zeros elsewhere."""
        g, n = state.num_groups, state.num_slots
        forced = self.forced.reshape(-1).index_select(0, self.rows)
        rows, tokens = self.rows[forced != FORCED_LATER], self.tokens[forced != FORCED_LATER]
        out = state.pose.new_zeros(g * n, FRAMES_PER_TOKEN, 3)
        local = state.token_poses[state.agent_type.reshape(-1)[rows], tokens]
        out[rows] = token_frames(local, state.pose.reshape(-1, 3)[rows], state.previous_pose.reshape(-1, 3)[rows], state.interpolation)
        known = torch.zeros(g * n, dtype=torch.bool, device=out.device)
        known[rows] = True
        return out.view(g, n, FRAMES_PER_TOKEN, 3), known.view(g, n)


def check_forced(state, forced_tokens: torch.Tensor, later: bool = False) -> torch.Tensor:
    """``forced_tokens`` on the state's device as int64, refused with a ValueError where a simulated slot's token is
    outside its type's vocabulary (or below -1; :data:`FORCED_LATER` also allowed when ``later``)."""
    forced_tokens = forced_tokens.to(state.device, torch.long)
    if forced_tokens.shape != state.simulated.shape:
        raise ValueError(f"forced tokens must have shape {tuple(state.simulated.shape)}, got {tuple(forced_tokens.shape)}")
    size = state.vocab_sizes.to(state.device)[state.agent_type]
    low = FORCED_LATER if later else -1
    bad = state.simulated & ((forced_tokens >= size) | (forced_tokens < low))
    if bad.any():
        raise ValueError(f"forced token outside its agent type's vocabulary at slots {bad.nonzero()[:5].tolist()}")
    return forced_tokens


def draw_tokens(state, forced_tokens: torch.Tensor | None) -> Draw:
    """The step's draw (module docstring): top-k sampling with the state's temperature and generator, tokens
    excluded by collision-aware sampling and the stop lines where they are on, vehicles' logits tilted by speed
    persistence (:mod:`~smart_marl.rollout.persistence`; the log-probabilities are the model's)."""
    logits = state.logits()
    g, n = state.num_groups, state.num_slots
    sim = state.simulated
    rows = sim.reshape(-1).nonzero().squeeze(1)
    forced_rows = forced_tokens.reshape(-1)[rows] if forced_tokens is not None else None
    row_logits = logits.reshape(g * n, -1).index_select(0, rows)  # (index_select: 2.5x faster than logits[rows] on the CPU)
    model_logits, row_logits = row_logits, tilted(state, rows, row_logits)  # ranked and sampled tilted, scored as the model's
    v, k = row_logits.shape[1], state.top_k
    # the top k + 1, ranked once for the collision check and the sampler (both read them)
    top = torch.topk(row_logits, k + 1, dim=-1) if 0 < k < v and (state.avoid_collisions or state.temperature == 1.0) else None
    exclude = None
    pick = torch.ones(len(rows), dtype=torch.bool, device=state.device) if forced_rows is None else forced_rows == -1
    also = stop_test = stop_line_test(state, rows[pick]) if state.stop_lines else None
    standing = None if not state.avoid_collisions or forced_tokens is None else later_standing_test(state, rows[pick], forced_tokens)
    if standing is not None:
        also = standing if stop_test is None else (lambda r, tok: stop_test(r, tok) | standing(r, tok))
    if state.avoid_collisions or also is not None:
        known = known_frames = None
        if forced_tokens is not None:  # the forced agents' frames of this step, seen by the others' check
            known = sim & (forced_tokens >= 0)
            kg, ks = known.nonzero(as_tuple=True)
            if len(kg):  # placed where they are forced only (a few of the slots)
                local = state.token_poses[state.agent_type[kg, ks], forced_tokens[kg, ks]]
                known_frames = state.pose.new_zeros(g, n, FRAMES_PER_TOKEN, 3)
                known_frames[kg, ks] = token_frames(local, state.pose[kg, ks], state.previous_pose[kg, ks], state.interpolation)
            else:
                known = None
        exclude = torch.zeros(row_logits.shape, dtype=torch.bool, device=state.device)
        at = pick.nonzero().squeeze(1)
        exclude[pick] = excluded_tokens(row_logits.index_select(0, at), rows[at], state.pose, state.previous_pose, state.agent_shape,
                                        sim if state.avoid_collisions else torch.zeros_like(sim),
                                        state.agent_type, state.token_poses, state.top_k, state.interpolation,
                                        known_frames=known_frames, known=known, also=also,
                                        top=None if top is None else (top.values[at], top.indices[at]),
                                        vocab_sizes=state.vocab_sizes)
    # forced-later rows take a placeholder (token 0, in every type's vocabulary) until their token is given
    given = None if forced_rows is None else torch.where(forced_rows == FORCED_LATER, torch.zeros_like(forced_rows), forced_rows)
    tokens, log_probs = sample_tokens(row_logits, state.generator, state.top_k, state.temperature, given, exclude,
                                      None if top is None else (top.values, top.indices), state.log_probs_of, scored=model_logits)
    forced = forced_tokens if forced_tokens is not None else torch.full((g, n), -1, dtype=torch.long, device=state.device)
    return Draw(logits=logits, forced=forced, rows=rows, tokens=tokens, log_probs=log_probs)


def later_standing_test(state, rows: torch.Tensor, forced_tokens: torch.Tensor):
    """An ``also`` of :func:`~smart_marl.rollout.avoidance.excluded_tokens` for sampling rows ``rows`` [M] (flat slot
    indices): a token whose frames overlap, standing where it is now, an agent of the same group forced later (a
    controlled agent, whose token comes with the policy's: it may drive on, which the main rule checks at constant
    velocity, or brake; :func:`~smart_marl.rollout.avoidance.standing_test`, the prior's boxes). None where no slot
    is forced later, so a draw without them is the plain step's."""
    later = state.simulated & (forced_tokens == FORCED_LATER)
    if not bool(later.any()) or not len(rows):
        return None
    g, n = later.shape
    width = int(later.sum(1).max())
    lg, ls = later.nonzero(as_tuple=True)
    place = (later.long().cumsum(1) - 1)[lg, ls]  # each later slot's place among its group's
    slot = torch.zeros(g, width, dtype=torch.long, device=later.device)
    valid = torch.zeros(g, width, dtype=torch.bool, device=later.device)
    slot[lg, place], valid[lg, place] = ls, True
    gi, si = rows // n, rows % n
    other = slot[gi]  # [M, W]
    half = state.agent_shape[..., :2].to(state.pose.dtype) / 2
    own_pose, other_pose = state.pose[gi, si], state.pose[gi[:, None], other]
    own_half, other_half = half[gi, si], half[gi[:, None], other]
    types = state.agent_type[gi, si]
    # only the others a token of the row can reach (the farthest token of its type, both half diagonals)
    reach = token_reach(state.token_poses).amax(-1)[types]  # [M]
    apart = bound_length(other_pose[..., :2] - own_pose[:, None, :2])
    radii = bound_length(own_half)[:, None] + bound_length(other_half)
    ok = valid[gi] & (other != si[:, None]) & (apart < loose(reach[:, None] + radii))
    if not bool(ok.any()):
        return None
    test = standing_test(own_pose, own_half, other_pose, other_half, ok)
    near = ok.any(-1)
    own = (types, own_pose, state.previous_pose.reshape(-1, 3).index_select(0, rows), state.token_poses)

    def also(r: torch.Tensor, tok: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(tok.shape, dtype=torch.bool, device=tok.device)
        at = near[r].nonzero().squeeze(1)
        if len(at):
            out[at] = test(r[at], candidate_frames(*own, r[at], tok[at], state.interpolation))
        return out
    return also


def complete(state, draw: Draw, forced_tokens: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """(tokens [R], log-probabilities [R]) of ``draw`` with its forced-later slots' tokens ``forced_tokens`` [G, N]
    filled in. Refused (ValueError) when ``forced_tokens`` does not force exactly the slots the draw left to
    later, with any token, and every slot it forced already, with the same token."""
    later = draw.forced == FORCED_LATER
    given = torch.full_like(draw.forced, -1) if forced_tokens is None else forced_tokens
    sim = state.simulated
    wrong = sim & torch.where(later, given < 0, given != draw.forced)
    if bool(wrong.any()):
        raise ValueError("the step's forced tokens differ from those the tokens were drawn ahead with (draw_ahead) at slots "
                         f"{wrong.nonzero()[:5].tolist()}: force a token exactly where draw_ahead had FORCED_LATER")
    tokens, log_probs = draw.tokens.clone(), draw.log_probs.clone()
    at = (later.reshape(-1).index_select(0, draw.rows)).nonzero().squeeze(1)
    if len(at):
        tok = given.reshape(-1).index_select(0, draw.rows.index_select(0, at))
        row_logits = draw.logits.reshape(-1, draw.logits.shape[-1]).index_select(0, draw.rows.index_select(0, at))
        if state.temperature != 1.0:
            row_logits = row_logits / state.temperature
        tokens[at] = tok
        log_probs[at] = torch.log_softmax(row_logits, dim=-1).gather(1, tok[:, None]).squeeze(1).to(log_probs.dtype)
    return tokens, log_probs


__all__ = ["Draw", "FORCED_LATER", "check_forced", "complete", "draw_tokens", "later_standing_test"]
