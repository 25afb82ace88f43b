"""Benchmark of a prior's kinematics in closed loop: do the agents it drives keep their speed?

For each set of scenes (``--set NAME=PATH ...``; by default every shared real scene of 91 frames at
10 Hz, and the package's SUMO sample scenes) and each agent type, the agents moving at the current
frame (vehicles > 5 m/s, cyclists > 2 m/s, pedestrians > 0.5 m/s; simulated by the prior), the mean
speed in the prior's rollouts against the logged mean speed of the same agents at several horizons
(both from 10 Hz position differences, over the agents logged at that frame); and the
teacher-forced bias of the model's most likely next token (logged history as input): mean speed
of the argmax token over the mean speed of the target token, for the same moving agents at every
step; and for vehicles, the same by the speed of the input token, with the mean speed of the
renormalised top-k distribution as well (does the model pull fast or slow vehicles toward the
speeds of its training data?). And, in the last second of the rollout (7-8 s), the same agents split
by what their log does against their speed at the current frame (speeds up by more than 20%, keeps
within 20%, slows by more than 20%): does the rollout fall short where the log slows down, keeps
going, or speeds up?

Output (stdout, one JSON object per line)::

    {"kind": "horizon", "set": "real", "type": "vehicle", "t_s": 2.0, "rollout_mps": ..., "log_mps": ..., "ratio": ..., "agents": ...}
    {"kind": "teacher_forced", "set": "real", "type": "vehicle", "argmax_mps": ..., "target_mps": ..., "ratio": ..., "rows": ...}
    {"kind": "teacher_forced_by_speed", "set": "real", "type": "vehicle", "input_mps": [15.0, null], "target_mps": ...,
     "argmax_ratio": ..., "top_k_mean_ratio": ..., "rows": ...}
    {"kind": "late_by_log_trend", "set": "real", "type": "vehicle", "log_trend": "speeds_up", "agents": ...,
     "now_mps": ..., "log_mps": ..., "rollout_mps": ..., "ratio": ...}
    {"kind": "trend_by_horizon", "set": "real", "type": "vehicle", "log_trend": "speeds_up", "t_s": 2.0, "agents": ...,
     "rollout_mps": ..., "log_mps": ..., "ratio": ...}   (the same groups at every horizon)
    {"kind": "past_trend_by_horizon", "set": "real", "type": "vehicle", "past_trend": "accelerating", "t_s": 2.0, ...}
     (groups by what the agent did in the second before the current frame: no regression to the mean built in)
    {"kind": "teacher_forced_dv", "set": "real", "type": "vehicle", "bin": "slope", "slope": ..., ...}
    {"kind": "teacher_forced_dv", "set": "real", "type": "vehicle", "bin": [0.8, 0.95], "predicted_dv_mps": ...,
     "target_dv_mps": ..., "rows": ...}   (is the predicted speed change over a token the one that follows?)
    {"kind": "teacher_forced_first_by_past", "set": "real", "type": "vehicle", "past_trend": "accelerating",
     "vehicles": ..., "change_last_0_5s_mps": ..., "predicted_dv_mps": ..., "logged_dv_mps": ...}
     (the first token after the current frame: does the model go on with the change it sees?)

A prior with no drift has ratios near 1 at every horizon (the log itself slows down where the
traffic does, which the rollout should follow, not exceed).

    .venv/bin/python benchmarks/prior_speed_drift.py [--prior PATH] [--set real=GLOB ...] [--rollouts 8] [--top-k 5]
        [--drop-parked]

``--log-steps S``: every agent follows its log for the first S token steps (S x 0.5 s), then the prior drives:
do vehicles whose log has started to slow by then go on slowing (what the prior misses is the start), or not?

``--drop-parked`` leaves every scene's parked vehicles out (logged on every frame, moving less than 0.5 m):
the difference to a run without it is how much the parked cars slow the prior's moving traffic.

Measured figures are in docs/model_card.md and docs/experiments/.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from smart_marl.commands.arguments import collision_avoidance_flag, persistence_option, stop_lines_flag
from smart_marl.model.batch import collate_scenes, scene_road, scene_tensors
from smart_marl.model.checkpoint import load_checkpoint, load_prior
from smart_marl.model.losses import TREND_BAND  # "keeps": within this share of the speed now (the training weights' band)
from smart_marl.readers import read_scenarios
from smart_marl.rollout import DEFAULT_TOP_K, RolloutState, collect_result
from smart_marl.scenario import AgentType
from smart_marl.tokens.motion import MOTION_TYPES, tokenize_motion

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REAL_91_FRAMES = ["womd_tfrecord/*.tfrecord", "smart_pkl/*.pkl", "scenarionet/waymo/sd_training*.pkl", "gpudrive_json/*.json",
                  "nocturne_json/*.json"]
SUMO_SAMPLES = ROOT / "smart_marl" / "samples"
HORIZONS_S = (0.5, 1.0, 2.0, 4.0, 6.0, 8.0)
MOVING_MPS = {AgentType.VEHICLE: 5.0, AgentType.PEDESTRIAN: 0.5, AgentType.CYCLIST: 2.0}
NUM_FRAMES = 80  # 16 tokens of 5 frames
SPEED_BINS_MPS = (0.0, 1.0, 5.0, 9.0, 12.0, 15.0, 1e9)  # vehicles' teacher-forced bias by input-token speed
DV_MOVING_MPS = 3.0  # teacher_forced_dv: vehicle tokens whose input token is faster than this
SATURATED = 0.95  # teacher_forced_dv leaves out input tokens at least this share of the fastest token's speed
LATE_FRAMES = 10  # the last second of the rollout (7-8 s): the frames of late_by_log_trend
PARKED_M = 0.5  # --drop-parked: a vehicle logged on every frame that moves less than this over the log is parked
TRENDS = ("speeds_up", "keeps", "slows")  # log's late mean speed against the speed now: above, within, below the band


def _speeds_from_positions(xy: np.ndarray, start_xy: np.ndarray) -> np.ndarray:
    """Speeds [..., T] from positions [..., T, 2] and the position before the first one [..., 2]."""
    return np.linalg.norm(np.diff(np.concatenate([start_xy[..., None, :], xy], -2), axis=-2), axis=-1) / 0.1


def rollout_xy(res, scene, agents) -> np.ndarray:
    """[R, A', T, 2] the rollouts' positions of tracks ``agents`` in the scene's frame (the frame of its tracks:
    a :class:`~smart_marl.rollout.RolloutResult` is in the source frame), float64."""
    return scene.frame.from_source(res.trajectory[:, agents, :, :2].astype(np.float64))


PAST_TRENDS = ("accelerating", "steady", "decelerating")
"""Groups by what an agent did before the current frame (its speed over the last 0.5 s against the 0.5 s before:
more than 10% up, within 10%, more than 10% down): information the model has, unlike the log's trend after it."""
PAST_BAND = 0.1


def past_trend(recent: np.ndarray, earlier: np.ndarray) -> np.ndarray:
    """[...] the index in :data:`PAST_TRENDS` of speeds ``recent`` against ``earlier`` (m/s, the last 0.5 s and the
    0.5 s before: :func:`_half_second_speeds`)."""
    return np.where(recent > (1 + PAST_BAND) * earlier, 0, np.where(recent < (1 - PAST_BAND) * earlier, 2, 1))


class SpeedSums(NamedTuple):
    """One motion type's speed sums over frames cf+1..cf+80 (:data:`NUM_FRAMES`) of the agents moving at the
    current frame; a sum at frame t counts the agents logged at t and t-1. Entries of scenes add up (:meth:`plus`)."""

    sim: np.ndarray  # [T] rollout mean speed, summed over the agents
    log: np.ndarray  # [T] logged speed, summed
    count: np.ndarray  # [T] agents logged at t
    agents: int
    by_trend: np.ndarray  # [3, 4] per log trend (TRENDS): sums of speed now, log and rollout speed at 7-8 s; agents
    trend_frames: np.ndarray  # [3, 3, T] per log trend: sim, log, count at every frame (how the groups get there)
    past_frames: np.ndarray  # [3, 3, T] the same per past trend (PAST_TRENDS)
    past_agents: np.ndarray  # [3] agents per past trend

    @classmethod
    def zeros(cls) -> "SpeedSums":
        t, g = NUM_FRAMES, len(TRENDS)
        return cls(np.zeros(t), np.zeros(t), np.zeros(t), 0, np.zeros((g, 4)), np.zeros((g, 3, t)), np.zeros((g, 3, t)), np.zeros(g))

    def plus(self, other: "SpeedSums") -> "SpeedSums":
        return SpeedSums(*(a + b for a, b in zip(self, other)))


def rollout_speeds(ck, scene, num_rollouts: int, top_k: int, temperature: float, seed: int,
                   avoid_collisions: bool = True, log_steps: int = 0, stop_lines: bool = False) -> dict:
    """Per motion type, the :class:`SpeedSums` of the prior's rollouts of ``scene`` against its log, the first
    ``log_steps`` token steps of every agent its log's (:func:`rollout_from_log`)."""
    return speed_sums(rollout_from_log(ck, scene, log_steps, num_rollouts=num_rollouts, seed=seed, top_k=top_k,
                                       temperature=temperature, avoid_collisions=avoid_collisions, stop_lines=stop_lines), scene)


def rollout_from_log(model_or_checkpoint, scene, log_steps: int = 0, num_steps: int = NUM_FRAMES // 5, tracks=None, **kwargs):
    """:func:`~smart_marl.rollout.rollout` of one scene (its loop: ``kwargs`` go to
    :meth:`RolloutState.start <smart_marl.rollout.RolloutState.start>`) in which every agent (or the track indices
    ``tracks`` alone) follows its tokenized log for the first ``log_steps`` token steps (:func:`logged_tokens`) and
    the prior drives the rest."""
    state = RolloutState.start(model_or_checkpoint, [scene], **kwargs)
    logged = logged_tokens(state, scene, log_steps) if log_steps else None
    if logged is not None and tracks is not None:
        logged[:, ~torch.from_numpy(np.isin(state.track_index.cpu().numpy(), np.asarray(tracks, np.int64)))] = -1
    forced = (lambda st, k, last: logged[k] if k < len(logged) else None) if log_steps else None  # noqa: E731
    return collect_result(state, state.run(num_steps, before_step=forced))


def log_steps_flag(ap: argparse.ArgumentParser) -> None:
    """``--log-steps S`` (:func:`rollout_from_log`), for the benchmarks that roll scenes out."""
    ap.add_argument("--log-steps", type=int, default=0,
                    help="the first this many token steps (0.5 s each) of every agent follow its log, then the prior drives")


def vehicle_rollout_arguments(ap: argparse.ArgumentParser, rollouts: int) -> None:
    """The arguments of the benchmarks that follow vehicles through rollouts of scene sets (``slowing_causes.py``,
    ``departures.py``): the prior, the sets, rollouts, seed, sampling, top-k, threads, lights, a scene cap, stop lines."""
    ap.add_argument("--prior", default="embedded")
    ap.add_argument("--set", dest="sets", action="append", metavar="NAME=PATH[,PATH...]",
                    help="a named set of scenes; repeatable (default: the shared real 91-frame scenes)")
    ap.add_argument("--rollouts", type=int, default=rollouts)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--sampling", default="default", choices=("default", "plain"))
    ap.add_argument("--top-k", type=int, default=DEFAULT_TOP_K, help="the prior's top-k (0: the whole distribution)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--lights", default="current", choices=("current", "log"),
                    help="the light states the prior sees: the current frame's, held, or the log's at every step")
    ap.add_argument("--max-scenes", type=int, default=0, help="the first N scenes of each set (0: all)")
    stop_lines_flag(ap)
    persistence_option(ap)


def vehicle_rollout_sets(args):
    """For :func:`vehicle_rollout_arguments`' ``args``: (the prior, {set name: scenes}, the keyword arguments of
    :func:`rollout_from_log`, the fields every JSON line carries); sets threads."""
    torch.set_num_threads(args.threads)
    model, _ = load_prior(args.prior)
    sets = scene_sets(args.sets or [f"real={','.join(str(SHARED / p) for p in REAL_91_FRAMES)}"])
    sets = {name: scenes[: args.max_scenes] if args.max_scenes else scenes for name, scenes in sets.items()}
    rollout_kwargs = dict(num_steps=NUM_FRAMES // 5, num_rollouts=args.rollouts, top_k=args.top_k, seed=args.seed,
                          avoid_collisions=args.sampling == "default", lights=args.lights, stop_lines=args.stop_lines,
                          persistence=args.persistence)
    common = {"prior": args.prior, "sampling": args.sampling, "top_k": args.top_k, "seed": args.seed, "rollouts": args.rollouts,
              "lights": args.lights, "stop_lines": args.stop_lines, "persistence": args.persistence}
    return model, sets, rollout_kwargs, common


def logged_tokens(state: RolloutState, scene, steps: int) -> torch.Tensor:
    """[steps, G, N] the logged token (rolling matching over the whole log with ``state``'s vocabulary, as
    training's targets) of each of ``state``'s slots for the first ``steps`` token steps after the current frame,
    ``-1`` (drawn) where the log has none: forced, they replay the tokenized log."""
    mt = tokenize_motion(scene, state.vocab)
    i0 = int(np.flatnonzero(mt.boundaries == scene.current_frame)[0])
    track = state.track_index.cpu().numpy()
    has = track >= 0
    out = np.full((steps, *track.shape), -1, np.int64)
    for k in range(min(steps, mt.num_steps - i0)):
        out[k][has] = np.where(mt.valid[track[has], i0 + k], mt.ids[track[has], i0 + k], -1)
    return torch.from_numpy(out)


def _half_second_speeds(tr, a: int, cf: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each of the first ``a`` tracks' mean speed over the last 0.5 s before the current frame and over the 0.5 s
    before that, and whether both are logged."""
    pos, valid = tr.position[:a, :, :2], tr.valid[:a]
    now = np.linalg.norm(pos[:, cf] - pos[:, cf - 5], axis=-1) / 0.5
    before = np.linalg.norm(pos[:, cf - 5] - pos[:, cf - 10], axis=-1) / 0.5
    return now, before, valid[:, cf] & valid[:, cf - 5] & valid[:, cf - 10]


def speed_sums(res, scene) -> dict:
    """Per motion type, the :class:`SpeedSums` of a one-scene :class:`~smart_marl.rollout.RolloutResult` of
    :data:`NUM_FRAMES` frames (``res`` may come from elsewhere, e.g. ``benchmarks/reactivity.py``)."""
    num_rollouts = res.trajectory.shape[0]
    tr, cf = scene.tracks, scene.current_frame
    a = res.agent_types.shape[1]
    frames = np.arange(cf + 1, cf + 1 + NUM_FRAMES)
    v_now = np.linalg.norm(tr.position[:a, cf, :2] - tr.position[:a, cf - 1, :2], axis=-1) / 0.1
    v_now = np.where(tr.valid[:a, cf] & tr.valid[:a, cf - 1], v_now, 0.0)
    recent, earlier, has_past = _half_second_speeds(tr, a, cf) if cf >= 10 else (v_now, v_now, np.zeros(a, bool))
    out = {}
    for t in MOTION_TYPES:
        moving = res.simulated[0] & (res.agent_types[0] == int(t)) & (v_now > MOVING_MPS[t])
        if not moving.any():
            continue
        ok = tr.valid[:a][moving][:, frames] & tr.valid[:a][moving][:, frames - 1]  # [M, T] logged at t and t - 1
        log_speed = _speeds_from_positions(tr.position[:a][moving][:, frames, :2], tr.position[:a][moving][:, cf, :2])
        sim = _speeds_from_positions(rollout_xy(res, scene, moving), np.broadcast_to(tr.position[:a][moving][:, cf, :2],
                                                                                      (num_rollouts, int(moving.sum()), 2)))
        sim_mean = sim.mean(0)  # [M, T] over the rollouts
        late = ok & (np.arange(NUM_FRAMES) >= NUM_FRAMES - LATE_FRAMES)
        n_late = late.sum(1)
        log_late = np.where(late, log_speed, 0.0).sum(1) / np.maximum(n_late, 1)
        sim_late = np.where(late, sim_mean, 0.0).sum(1) / np.maximum(n_late, 1)
        now = v_now[moving]
        trend = np.where(log_late > (1 + TREND_BAND) * now, 0, np.where(log_late < (1 - TREND_BAND) * now, 2, 1))
        counted = n_late * 2 >= LATE_FRAMES
        groups = [counted & (trend == c) for c in range(len(TRENDS))]
        by_trend = np.array([[now[m].sum(), log_late[m].sum(), sim_late[m].sum(), m.sum()] for m in groups])
        trend_before = past_trend(recent[moving], earlier[moving])
        past = [has_past[moving] & (trend_before == g) for g in range(len(PAST_TRENDS))]
        frame_sums = lambda m: [np.where(ok[m], x[m], 0.0).sum(0) for x in (sim_mean, log_speed)] + [ok[m].sum(0)]  # noqa: E731
        out[t] = SpeedSums(np.where(ok, sim_mean, 0.0).sum(0), np.where(ok, log_speed, 0.0).sum(0), ok.sum(0), int(moving.sum()),
                           by_trend, np.array([frame_sums(m) for m in groups]), np.array([frame_sums(m) for m in past]),
                           np.array([m.sum() for m in past], float))
    return out


def trend_horizon_rows(sums: SpeedSums) -> list[dict]:
    """Rows of summed :class:`SpeedSums`: per group and horizon, the rollout and logged mean speed of the group's
    agents logged then, and their ratio; ``kind: "trend_by_horizon"`` for the log's trends after the current
    frame (:data:`TRENDS`, the groups of ``late_by_log_trend``), ``"past_trend_by_horizon"`` for the agents' own
    trend before it (:data:`PAST_TRENDS`: chosen on what the model sees, so free of the regression to the mean
    that choosing on the log's outcome builds into the first)."""
    rows = []
    for kind, key, names, counts, frames in (("trend_by_horizon", "log_trend", TRENDS, sums.by_trend[:, 3], sums.trend_frames),
                                             ("past_trend_by_horizon", "past_trend", PAST_TRENDS, sums.past_agents, sums.past_frames)):
        for name, count, (r, lg, n) in zip(names, counts, frames):
            for h in HORIZONS_S:
                k = int(round(h * 10)) - 1
                if count and n[k]:
                    rows.append({"kind": kind, key: name, "t_s": h, "rollout_mps": round(r[k] / n[k], 3), "log_mps": round(lg[k] / n[k], 3),
                                 "ratio": round(r[k] / max(lg[k], 1e-9), 3), "agents": int(count)})
    return rows


DV_QUANTILES = (0.0, 0.05, 0.2, 0.4, 0.6, 0.8, 0.95, 1.0)
"""Bins of the predicted speed change (quantiles) of the ``teacher_forced_dv`` rows."""


def dv_calibration_rows(predicted: np.ndarray, target: np.ndarray, saturated: np.ndarray | None = None) -> list[dict]:
    """``kind: "teacher_forced_dv"`` rows: the model's predicted speed change over a token (the top-k mean
    token's speed less the input token's) against the logged one (the target token's less the input's), per
    quantile bin of the prediction (:data:`DV_QUANTILES`), and the slope of the logged change on the predicted
    one (1: calibrated; below 1: the model predicts larger changes than follow). ``saturated``: rows whose input
    token is about the vocabulary's fastest (a vehicle as fast or faster: its logged change cannot be up), left
    out and counted."""
    if saturated is not None:
        predicted, target, left_out = predicted[~saturated], target[~saturated], int(saturated.sum())
    else:
        left_out = 0
    if len(predicted) < 2:
        return []
    rows = [{"kind": "teacher_forced_dv", "bin": "slope", "slope": round(float(np.polyfit(predicted, target, 1)[0]), 3),
             "predicted_sd": round(float(predicted.std()), 3), "target_sd": round(float(target.std()), 3), "rows": int(len(predicted)),
             "saturated_rows_left_out": left_out}]
    edges = np.quantile(predicted, DV_QUANTILES)
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        m = (predicted >= lo) & ((predicted < hi) if i < len(edges) - 2 else (predicted <= hi))
        if m.any():
            rows.append({"kind": "teacher_forced_dv", "bin": [DV_QUANTILES[i], DV_QUANTILES[i + 1]],
                         "predicted_dv_mps": round(float(predicted[m].mean()), 3), "target_dv_mps": round(float(target[m].mean()), 3),
                         "rows": int(m.sum())})
    return rows


class TeacherForced(NamedTuple):
    """:func:`teacher_forced_bias`'s sums of one scene (they add up over scenes)."""

    moving: dict  # {type: [sum of argmax-token speeds, sum of target-token speeds, rows]}, the agents moving now, every step
    by_speed: np.ndarray  # [bins, 4] vehicles by input-token speed (SPEED_BINS_MPS): argmax, top-k mean, target speed sums; rows
    dv: np.ndarray  # [R, 3] predicted and logged speed change of the vehicles' future tokens; input token saturated (0 / 1)
    first_by_past: np.ndarray  # [3, 6] per past trend: vehicles, sums of input speed, speed change over the last 0.5 s,
    #                           predicted change of the first future token (top-k mean, full softmax), its logged change


@torch.no_grad()
def teacher_forced_bias(ck, scene, top_k: int = 5) -> TeacherForced:
    """Teacher-forced speed bias of the model's next token on the logged history (:class:`TeacherForced`).

    ``moving`` over the agents moving at the current frame, every step; ``by_speed`` for vehicles by the speed of
    their input token over every step with a logged input token; ``dv`` the vehicles' tokens from the first after
    the current frame on whose input token is faster than 3 m/s (:func:`dv_calibration_rows`), with whether the
    input token is within 5% of the fastest vehicle token's speed; ``first_by_past`` the first token after the
    current frame of the vehicles moving faster than 5 m/s, grouped by their speed change over the second before
    (:data:`PAST_TRENDS`): does the model go on with a change it sees?"""
    mv = ck.motion_vocab
    mt = tokenize_motion(scene, mv)
    d = scene_tensors(scene, mv, scene_road(scene, ck.road_vocab, ck.model.config.road_settings), noise_topk=0, road_mask_prob=0.0, rng=0, motion_tokens=mt)
    b = collate_scenes([d])
    feats, _ = ck.model(b)
    logits = ck.model.motion_logits(feats, b.agent_type)
    keep = np.flatnonzero(mt.valid.any(1))
    tr, cf = scene.tracks, scene.current_frame
    v_now = np.where(tr.valid[keep, cf] & tr.valid[keep, cf - 1],
                     np.linalg.norm(tr.position[keep, cf, :2] - tr.position[keep, cf - 1, :2], axis=-1) / 0.1, 0.0)
    out = {}
    bins = np.zeros((len(SPEED_BINS_MPS) - 1, 4))
    dv, first = np.zeros((0, 3)), np.zeros((len(PAST_TRENDS), 6))
    first_step = cf // 5 - 1  # target_tokens[s] is the motion over frames 5(s+1)..5(s+2): this one starts at the current frame
    for t in MOTION_TYPES:
        token_mps = torch.from_numpy(mv[t].poses[:, -1, :2]).norm(dim=-1) / 0.5
        lg, tgt = logits[int(t)][0], b.target_tokens[0]
        is_type = torch.from_numpy(tr.types[keep] == int(t))[:, None]
        moving = torch.from_numpy(v_now > MOVING_MPS[t])[:, None] & is_type & b.target_valid[0]
        if moving.any():
            pred = lg.argmax(-1)[moving]
            out[t] = (float(token_mps[pred].sum()), float(token_mps[tgt[moving]].sum()), int(moving.sum()))
        if t != AgentType.VEHICLE:
            continue
        prev = torch.cat([torch.full_like(tgt[:, :1], -1), tgt[:, :-1]], 1)  # the input token of each step
        rows = is_type & b.target_valid[0] & (prev >= 0)
        lr = lg[rows]
        top, idx = lr.topk(min(top_k or lr.shape[-1], lr.shape[-1]), -1)  # 0 / None: the full softmax
        cols = np.stack([token_mps[lr.argmax(-1)].numpy(), (torch.softmax(top, -1) * token_mps[idx]).sum(-1).numpy(),
                         token_mps[tgt[rows]].numpy(), (torch.softmax(lr, -1) * token_mps).sum(-1).numpy()], 1)
        vin = token_mps[prev[rows]].numpy()
        which = np.digitize(vin, SPEED_BINS_MPS[1:-1])
        for i in range(len(bins)):
            sel = which == i
            bins[i, :3] += cols[sel, :3].sum(0)
            bins[i, 3] += sel.sum()
        step = torch.arange(rows.shape[1])[None].expand_as(rows)[rows].numpy()
        saturated = vin >= SATURATED * float(token_mps.max())
        future = (step >= first_step) & (vin > DV_MOVING_MPS)
        dv = np.stack([cols[future, 1] - vin[future], cols[future, 2] - vin[future], saturated[future]], 1)
        if cf >= 10:  # the first future token by past trend
            recent, earlier, has_past = (x[keep] for x in _half_second_speeds(tr, tr.num_tracks, cf))
            trend = past_trend(recent, earlier)
            agent = np.nonzero(rows.numpy())[0]
            at = (step == first_step) & ~saturated & has_past[agent] & (recent[agent] > MOVING_MPS[t])
            for g in range(len(PAST_TRENDS)):
                m = at & (trend[agent] == g)
                first[g] += [m.sum(), vin[m].sum(), (recent - earlier)[agent][m].sum(), (cols[m, 1] - vin[m]).sum(),
                             (cols[m, 3] - vin[m]).sum(), (cols[m, 2] - vin[m]).sum()]
    return TeacherForced(out, bins, dv, first)


def first_token_rows(first: np.ndarray) -> list[dict]:
    """``kind: "teacher_forced_first_by_past"`` rows of summed :attr:`TeacherForced.first_by_past`."""
    rows = []
    for name, (n, vin, before, pred, full, logged) in zip(PAST_TRENDS, first):
        if n:
            rows.append({"kind": "teacher_forced_first_by_past", "past_trend": name, "vehicles": int(n), "input_mps": round(vin / n, 3),
                         "change_last_0_5s_mps": round(before / n, 3), "predicted_dv_mps": round(pred / n, 3),
                         "full_softmax_dv_mps": round(full / n, 3), "logged_dv_mps": round(logged / n, 3)})
    return rows


def without_parked(scene):
    """``scene`` without its parked vehicles: those logged on every frame that end the log within
    :data:`PARKED_M` of where they started (``--drop-parked``: do parked cars slow the prior's traffic?)."""
    tr = scene.tracks
    moved = np.linalg.norm(tr.position[:, -1, :2] - tr.position[:, 0, :2], axis=-1)
    parked = (tr.types == int(AgentType.VEHICLE)) & tr.valid.all(1) & (moved < PARKED_M)
    if scene.sdc_index >= 0:
        parked[scene.sdc_index] = False
    return scene.select_tracks(np.flatnonzero(~parked))


def scene_sets(specs: list[str] | None) -> dict[str, list]:
    """NAME=PATH specs -> {name: [Scenario]}; by default the shared real 91-frame scenes and the SUMO samples."""
    if not specs:
        specs = [f"real={','.join(str(SHARED / p) for p in REAL_91_FRAMES)}", f"sumo_samples={SUMO_SAMPLES}"]
    sets = {}
    for spec in specs:
        name, _, paths = spec.partition("=")
        scenes = [sc for sc in read_scenarios(paths.split(",")) if sc.num_frames >= sc.current_frame + 1 + NUM_FRAMES]
        sets[name] = scenes
    return sets


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prior", default="embedded", help="checkpoint path, or 'embedded'")
    ap.add_argument("--set", dest="sets", action="append", metavar="NAME=PATH[,PATH...]",
                    help="a named set of scenes (files, folders, globs); repeatable (default: real shared scenes, SUMO samples)")
    ap.add_argument("--max-scenes", type=int, default=0, help="at most this many scenes per set (0: all)")
    ap.add_argument("--rollouts", type=int, default=8)
    ap.add_argument("--top-k", type=int, default=DEFAULT_TOP_K)
    ap.add_argument("--temperature", type=float, default=1.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--drop-parked", action="store_true",
                    help="leave the parked vehicles (logged on every frame, moving less than 0.5 m) out of every scene")
    log_steps_flag(ap)
    collision_avoidance_flag(ap)
    stop_lines_flag(ap)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    ck = load_checkpoint(args.prior)  # a path or "embedded"
    ck.model.eval()
    for set_name, scenes in scene_sets(args.sets).items():
        if args.max_scenes:
            scenes = scenes[: args.max_scenes]
        if args.drop_parked:
            scenes = [without_parked(sc) for sc in scenes]
        roll = {t: SpeedSums.zeros() for t in MOTION_TYPES}
        tf = {t: np.zeros(3) for t in MOTION_TYPES}
        tf_bins = np.zeros((len(SPEED_BINS_MPS) - 1, 4))
        dvs, first = [], np.zeros((len(PAST_TRENDS), 6))
        for scene in scenes:
            for t, sums in rollout_speeds(ck, scene, args.rollouts, args.top_k, args.temperature, args.seed,
                                          args.avoid_collisions, args.log_steps, args.stop_lines).items():
                roll[t] = roll[t].plus(sums)
            forced = teacher_forced_bias(ck, scene, args.top_k)
            for t, v in forced.moving.items():
                tf[t] += v
            tf_bins += forced.by_speed
            dvs.append(forced.dv)
            first += forced.first_by_past
        common = {"set": set_name, "scenes": len(scenes), "rollouts": args.rollouts, "top_k": args.top_k,
                  "temperature": args.temperature, "prior": args.prior, "avoid_collisions": args.avoid_collisions, "stop_lines": args.stop_lines,
                  "drop_parked": args.drop_parked, "log_steps": args.log_steps}
        for t in MOTION_TYPES:
            s = roll[t]
            r, lg, n, m, by_trend = s.sim, s.log, s.count, s.agents, s.by_trend
            if m == 0:
                continue
            for h in HORIZONS_S:
                k = int(round(h * 10)) - 1
                if n[k] == 0:
                    continue
                print(json.dumps({"kind": "horizon", "type": t.name.lower(), "t_s": h, "rollout_mps": round(r[k] / n[k], 3),
                                  "log_mps": round(lg[k] / n[k], 3), "ratio": round(r[k] / max(lg[k], 1e-9), 3),
                                  "agents": m, "logged_at_t": int(n[k]), **common}), flush=True)
            for row in trend_horizon_rows(roll[t]):
                print(json.dumps({**row, "type": t.name.lower(), **common}), flush=True)
            for name, (now, log_late, sim_late, count) in zip(TRENDS, by_trend):
                if count:
                    print(json.dumps({"kind": "late_by_log_trend", "type": t.name.lower(), "log_trend": name, "agents": int(count),
                                      "now_mps": round(now / count, 3), "log_mps": round(log_late / count, 3),
                                      "rollout_mps": round(sim_late / count, 3), "ratio": round(sim_late / max(log_late, 1e-9), 3),
                                      **common}), flush=True)
            s = tf[t]
            if s[2]:
                print(json.dumps({"kind": "teacher_forced", "type": t.name.lower(), "argmax_mps": round(s[0] / s[2], 3),
                                  "target_mps": round(s[1] / s[2], 3), "ratio": round(s[0] / max(s[1], 1e-9), 3),
                                  "rows": int(s[2]), **common}), flush=True)
        for (lo, hi), (am, tk, tgt, n) in zip(zip(SPEED_BINS_MPS[:-1], SPEED_BINS_MPS[1:]), tf_bins):
            if n:
                print(json.dumps({"kind": "teacher_forced_by_speed", "type": "vehicle", "input_mps": [lo, hi if hi < 1e9 else None],
                                  "target_mps": round(tgt / n, 3), "argmax_ratio": round(am / max(tgt, 1e-9), 3),
                                  "top_k_mean_ratio": round(tk / max(tgt, 1e-9), 3), "rows": int(n), **common}), flush=True)
        dv = np.concatenate(dvs) if dvs else np.zeros((0, 3))
        for row in dv_calibration_rows(dv[:, 0], dv[:, 1], dv[:, 2] > 0) + first_token_rows(first):
            print(json.dumps({**row, "type": "vehicle", **common}), flush=True)


if __name__ == "__main__":
    main()
