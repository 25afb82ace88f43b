"""Rollout stage, the history: a scene's tracks up to the current frame -> the model's inputs for them (motion tokens
by rolling matching, the poses they start and end at, who is simulated).

In: a :class:`~smart_marl.scenario.Scenario` (frames up to the current one are all that is read) and the motion
vocabulary; out: a :class:`SceneHistory` per scene, which :class:`~smart_marl.rollout.RolloutState` pads and batches
(the module docstring of :mod:`~smart_marl.rollout.engine`, step 1, says how the last step is re-anchored).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from ..scenario import Scenario
from ..tokens import TOKEN_S, MotionVocabulary, token_boundaries, tokenize_tracks
from ..tokens.motion import match_token_ends


@dataclass
class SceneHistory:
    """One scene's model inputs up to the current frame (numpy), ``N`` slots x ``S`` history steps."""

    track_index: np.ndarray  # [N] int64, the slot's track in the scene
    tokens: np.ndarray  # [N, S] int64
    valid: np.ndarray  # [N, S] bool
    start_pose: np.ndarray  # [N, S, 3] float32
    end_pose: np.ndarray  # [N, S, 3] float32
    agent_type: np.ndarray  # [N] int64, 0..2
    agent_shape: np.ndarray  # [N, 3] float32
    simulated: np.ndarray  # [N] bool, valid at the current frame


def scene_history(scenario: Scenario, vocab: MotionVocabulary) -> SceneHistory:
    """Tokenize a scene's history (frames up to the current one only; see the module docstring)."""
    tr = scenario.tracks
    cf = scenario.current_frame
    bounds = token_boundaries(cf, cf + 1)  # ends at the current frame
    mt = tokenize_tracks(tr.position[:, : cf + 1], tr.heading[:, : cf + 1], tr.valid[:, : cf + 1], tr.types, vocab, bounds)
    s = max(mt.num_steps, 1)
    ids, valid = np.zeros((tr.num_tracks, s), np.int64), np.zeros((tr.num_tracks, s), bool)
    start, end = np.zeros((tr.num_tracks, s, 3), np.float32), np.zeros((tr.num_tracks, s, 3), np.float32)
    if mt.num_steps:
        ids[:], valid[:], start[:], end[:] = mt.ids, mt.valid, mt.start_pose, mt.reached[:, 1:]
    is_motion = np.isin(tr.types, [int(t) for t in vocab.types])
    sim = is_motion & tr.valid[:, cf]
    keep = np.flatnonzero(is_motion & (valid.any(1) | sim))
    ids, valid, start, end, sim = ids[keep], valid[keep], start[keep], end[keep], sim[keep]
    types = tr.types[keep].astype(np.int64)
    cur = np.concatenate([tr.position[keep, cf, :2], tr.heading[keep, cf, None]], -1).astype(np.float64)  # [N, 3]
    # agents that appeared less than a token ago: a synthetic last token matching the logged velocity
    late = sim & ~valid[:, -1]
    if late.any():
        c, sn = np.cos(cur[late, 2]), np.sin(cur[late, 2])
        vel = tr.velocity[keep[late], cf].astype(np.float64)
        target = np.stack([c * vel[:, 0] + sn * vel[:, 1], -sn * vel[:, 0] + c * vel[:, 1]], -1) * TOKEN_S
        rows = np.flatnonzero(late)
        for t in np.unique(types[late]):  # per type present (at most 3), vectorised over agents
            sel = types[late] == t
            ends = vocab[int(t)].poses[:, -1].astype(np.float64)  # [V, 3]
            tok = match_token_ends(ends, target[sel])
            le = ends[tok]
            h0 = cur[late][sel, 2] - le[:, 2]
            start_xy = cur[late][sel, :2] - np.stack([np.cos(h0) * le[:, 0] - np.sin(h0) * le[:, 1],
                                                      np.sin(h0) * le[:, 0] + np.cos(h0) * le[:, 1]], -1)
            r = rows[sel]
            ids[r, -1] = tok
            start[r, -1] = np.concatenate([start_xy, h0[:, None]], -1)
            valid[r, -1] = True
    end[sim, -1] = cur[sim]  # re-anchor at the logged current pose
    hist = np.where(tr.valid[keep, : cf + 1, None], tr.size[keep, : cf + 1], np.nan)
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            shape = np.nan_to_num(np.nanmedian(hist, axis=1)).astype(np.float32)
    return SceneHistory(track_index=keep.astype(np.int64), tokens=ids, valid=valid, start_pose=start.astype(np.float32),
                        end_pose=end.astype(np.float32), agent_type=types, agent_shape=shape.reshape(-1, 3), simulated=sim)


__all__ = ["SceneHistory", "scene_history"]
