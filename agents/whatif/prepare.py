"""What-if scenarios, preparation: a :class:`~agents.whatif.edits.WhatIf` applied to a scene.

Stage: agents (what-if). What comes in: a Scenario, a WhatIf and (for agents inserted with given
tokens) the motion vocabulary. What goes out: a :class:`Prepared`: the edited scene (scene edits:
removed and inserted tracks, traffic-light states) and what the rollout must do step by step
(forced-token scripts, removals, light overrides), plus which agents the comparison looks at
(affected agents, the vehicles behind a braking one, those approaching an overridden light).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from smart_marl.scenario import DT_S, TYPICAL_BOX_M, AgentType, Scenario, SignalState, TrafficLights, Tracks, wrap_angle
from smart_marl.tokens import FRAMES_PER_TOKEN, TOKEN_S, compose_poses

from .. import scripted
from .edits import KIND_OF, AgentRef, Placement, WhatIf, WhatIfError, check_edit

_ADDABLE = (AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST)
"""The types an edit may add; without ``size_m`` one gets its type's :data:`~smart_marl.scenario.TYPICAL_BOX_M`."""
FOLLOWER_REACH_M = 60.0
"""Vehicles up to this far behind a braking, stopping or stalled vehicle, in its lane (|lateral| <
2 m, heading within 30 degrees), count as its followers."""




# ------------------------------------------------------------------------------ preparation
@dataclass
class Script:
    """One agent's forced tokens: from ``start_step`` on, toward ``path`` (computed at the onset by
    ``make_path(pose [G, 3], speed [G]) -> [G, T, 3]``, frames after the onset) or given ``tokens``."""

    track_id: int
    start_step: int
    make_path: Any = None
    tokens: list | None = None
    then: str = "hold"
    end_step: int | None = None  # steps after the onset it lasts; None: until the path (or the tokens) ends, then ``then``
    path: np.ndarray | None = None


@dataclass
class Prepared:
    """A what-if applied to a scene: the edited scene and what the rollout must do step by step."""

    scene: Scenario
    scripts: list[Script]
    removals: list[tuple[int, list[int]]]  # (step, track ids) removed from the running rollout
    lights: list[tuple[int, np.ndarray, int]]  # (step, lane indices into traffic_lights, SignalState)
    affected: dict[int, str]  # track id -> what happened to it ("brake", "inserted", "removed", ...)
    followers: dict[int, list[int]]  # braking/stopping/stalled track id -> track ids of the vehicles behind it
    onset_step: dict[int, int]  # affected track id -> step its edit starts
    approaching: list[tuple[int, list[int]]] = dataclasses.field(default_factory=list)  # (step, vehicles heading for an overridden light)


def _step_of(at_s: float, path, i) -> int:
    """The token step an edit at ``at_s`` seconds (checked finite and >= 0 by :func:`check_edit`) starts at."""
    return int(round(float(at_s) / TOKEN_S))


def _track_index(scene: Scenario, ref: AgentRef, path, i) -> int:
    if isinstance(ref, str) and ref.lower() == "sdc":
        if scene.sdc_index < 0:
            raise WhatIfError(path, "agent 'sdc': this scene has no self-driving car (or it was removed)", i)
        return int(scene.sdc_index)
    if isinstance(ref, str) and "_" in ref:  # "vehicle_1234" names, as the env uses
        ref = ref.rsplit("_", 1)[1]
    try:
        tid = int(ref)
    except (TypeError, ValueError):
        raise WhatIfError(path, f"agent {ref!r} is neither a track id nor 'sdc'", i) from None
    hit = np.flatnonzero(scene.tracks.ids == tid)
    if not len(hit):
        raise WhatIfError(path, f"agent {tid} is not a track of scene {scene.scenario_id} (or it was removed)", i)
    return int(hit[0])


def _current_pose(scene: Scenario, index: int) -> np.ndarray:
    tr, cf = scene.tracks, scene.current_frame
    return np.array([tr.position[index, cf, 0], tr.position[index, cf, 1], tr.heading[index, cf]], np.float64)


def _to_local(scene: Scenario, edit: Placement, points, path, i) -> np.ndarray:
    """Points [K, 2] or poses [K, 3] of an edit -> poses [K, 3] in the scene's local frame (heading 0
    in the edit's frame when only points are given)."""
    a = np.asarray(points, np.float64)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] not in (2, 3) or not np.isfinite(a).all():
        raise WhatIfError(path, f"expected a list of [x, y] or [x, y, heading] points, got shape {a.shape}", i)
    out = np.zeros((len(a), 3))
    if edit.relative_to is not None:
        o = _current_pose(scene, _track_index(scene, edit.relative_to, path, i))
        c, s = math.cos(o[2]), math.sin(o[2])
        out[:, 0] = o[0] + c * a[:, 0] - s * a[:, 1]
        out[:, 1] = o[1] + s * a[:, 0] + c * a[:, 1]
        out[:, 2] = o[2] + (a[:, 2] if a.shape[1] == 3 else 0.0)
    elif edit.frame == "local":
        out[:, :2] = a[:, :2]
        out[:, 2] = a[:, 2] if a.shape[1] == 3 else 0.0
    elif edit.frame == "source":
        out[:, :2] = scene.frame.from_source(a[:, :2])
        out[:, 2] = (a[:, 2] - scene.frame.heading) if a.shape[1] == 3 else 0.0
    else:
        raise WhatIfError(path, f"frame must be 'source' or 'local', got {edit.frame!r}", i)
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def _agent_type(name: str, path, i) -> AgentType:
    found = [t for t in _ADDABLE if t.name.lower() == str(name).lower()]
    if not found:
        raise WhatIfError(path, f"type must be vehicle, pedestrian or cyclist, got {name!r}", i)
    return found[0]


def _add_track(scene: Scenario, track_id: int, agent_type: AgentType, future: np.ndarray, size_m, history_speed_mps: float) -> Scenario:
    """A new track: ``future`` [F, 3] poses for frames current, current + 1, ... (held after its end);
    history at ``history_speed_mps`` straight back along the first heading."""
    tr, cf, t = scene.tracks, scene.current_frame, scene.num_frames
    pose = np.zeros((t, 3))
    n_future = t - cf
    fut = future[:n_future]
    if len(fut) < n_future:
        fut = np.concatenate([fut, np.repeat(fut[-1:], n_future - len(fut), 0)], 0)
    pose[cf:] = fut
    back = DT_S * np.arange(cf, 0, -1)  # seconds before the current frame for frames 0..cf-1
    h0 = future[0, 2]
    pose[:cf, 0] = future[0, 0] - history_speed_mps * back * math.cos(h0)
    pose[:cf, 1] = future[0, 1] - history_speed_mps * back * math.sin(h0)
    pose[:cf, 2] = h0
    vel = np.gradient(pose[:, :2], DT_S, axis=0) if t > 1 else np.zeros((t, 2))
    cur_valid = tr.valid[:, cf]
    z = float(np.median(tr.position[cur_valid, cf, 2])) if cur_valid.any() else 0.0
    size = np.asarray(size_m, np.float32)
    new = Tracks(
        ids=np.concatenate([tr.ids, [track_id]]), types=np.concatenate([tr.types, [int(agent_type)]]),
        position=np.concatenate([tr.position, np.concatenate([pose[:, :2], np.full((t, 1), z)], 1)[None].astype(np.float32)]),
        heading=np.concatenate([tr.heading, pose[None, :, 2].astype(np.float32)]),
        velocity=np.concatenate([tr.velocity, vel[None].astype(np.float32)]),
        size=np.concatenate([tr.size, np.broadcast_to(size, (1, t, 3)).astype(np.float32)]),
        valid=np.concatenate([tr.valid, np.ones((1, t), bool)]),
    )
    return dataclasses.replace(scene, tracks=new)


def _place_tokens(vocab_type, pose: np.ndarray, tokens: Sequence[int]) -> np.ndarray:
    """Poses [1 + 5 * len(tokens), 3] of ``tokens`` placed one after another from ``pose``."""
    out, cur = [pose], pose
    for tok in tokens:
        placed = compose_poses(cur, vocab_type.poses[int(tok), 1:].astype(np.float64))
        out.extend(placed)
        cur = placed[-1]
    return np.asarray(out)


def _new_agent(scene: Scenario, e, kind: str, horizon: int, motion_vocab, path, i):
    """(type, then, future poses [F, 3], history speed, size, tokens or None) of an agent an insert, jaywalker or
    stalled_vehicle edit adds to the scene."""
    if kind == "jaywalker":
        atype, then = AgentType.PEDESTRIAN, "release"
        wp = _to_local(scene, e, [e.start, e.end], path, i)[:, :2]
        future = scripted.polyline_path(wp, float(e.speed_mps), horizon, wait_s=float(e.wait_s))
        hist_speed, size, tokens = 0.0, TYPICAL_BOX_M[AgentType.PEDESTRIAN], None
    elif kind == "stalled_vehicle":
        if e.pose is None:
            raise WhatIfError(path, "stalled_vehicle needs 'agent' (an existing vehicle) or 'pose' [x, y, heading]", i)
        atype, then = AgentType.VEHICLE, "hold"
        future = _to_local(scene, e, [list(e.pose)], path, i)[:1]
        hist_speed, size, tokens = 0.0, e.size_m or TYPICAL_BOX_M[AgentType.VEHICLE], None
    else:
        atype = _agent_type(e.type, path, i)
        then = _then(e.then, path, i)
        size = e.size_m or TYPICAL_BOX_M[atype]
        given = [x is not None for x in (e.trajectory, e.path, e.tokens)]
        if sum(given) != 1:
            raise WhatIfError(path, "insert needs exactly one of 'trajectory', 'path' or 'tokens'", i)
        tokens = None
        if e.trajectory is not None:
            future = _to_local(scene, e, e.trajectory, path, i)
            if np.asarray(e.trajectory).shape[-1] == 2:  # headings from the motion
                d = np.diff(future[:, :2], axis=0)
                h = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
                future[:, 2] = np.concatenate([h[:1], h]) if len(h) else 0.0
            hist_speed = float(np.linalg.norm(future[1, :2] - future[0, :2]) / DT_S) if len(future) > 1 else 0.0
        elif e.path is not None:
            wp = _to_local(scene, e, e.path, path, i)[:, :2]
            future = scripted.polyline_path(wp, float(e.speed_mps), horizon, wait_s=float(e.wait_s))
            hist_speed = 0.0 if e.wait_s > 0 else float(e.speed_mps)
        else:
            if motion_vocab is None:
                raise WhatIfError(path, "insert with 'tokens' needs the prior's motion vocabulary", i)
            if e.pose is None:
                raise WhatIfError(path, "insert with 'tokens' needs 'pose' [x, y, heading]", i)
            tokens = [int(t) for t in e.tokens]
            vt = motion_vocab[atype]
            if any(t < 0 or t >= vt.size for t in tokens):
                raise WhatIfError(path, f"tokens outside the {atype.name.lower()} vocabulary [0, {vt.size})", i)
            start = _to_local(scene, e, [list(e.pose)], path, i)[0]
            future = _place_tokens(vt, start, tokens)
            hist_speed = float(e.speed_mps)
    return atype, then, future, hist_speed, size, tokens


def _inserted_script(tid: int, future: np.ndarray, tokens, then: str, horizon: int) -> Script:
    """The script of an added agent: its tokens, or its future poses (held at the end, or run on past it when released)."""
    if tokens is not None:
        return Script(tid, 0, tokens=tokens, then=then)
    fut = future[1:] if len(future) > 1 else future
    end_step = None
    if then == "release":  # released when its motion ends; the target runs on past the end (no sudden stop)
        moving = moving_frames(future)
        end_step = int(math.ceil(moving / FRAMES_PER_TOKEN))
        fut = _extrapolate(future[: moving + 1], horizon + 2 * FRAMES_PER_TOKEN)[1:]
    return Script(tid, 0, then=then, end_step=end_step, make_path=lambda pose, v, fut=fut, n=horizon - 1:
                  np.repeat(_pad_hold(fut, n + 2 * FRAMES_PER_TOKEN)[None], len(pose), 0))


def _override_lights(scene: Scenario, e, step: int, path, i) -> tuple[Scenario, np.ndarray, int]:
    """(the scene with the lights of a traffic_light edit's lanes set from ``step`` on, those lanes' indices, the state)."""
    tl = scene.traffic_lights
    if not len(tl.lane_ids):
        raise WhatIfError(path, f"scene {scene.scenario_id} has no traffic lights to override", i)
    try:
        code = int(SignalState[str(e.state).upper()])
    except KeyError:
        raise WhatIfError(path, f"state must be one of {', '.join(s.name.lower() for s in SignalState)}, got {e.state!r}", i) from None
    if isinstance(e.lanes, str) and e.lanes == "all":
        lanes = np.arange(len(tl.lane_ids))
    else:
        want = np.asarray(e.lanes if isinstance(e.lanes, (list, tuple)) else [e.lanes], np.int64)
        missing = want[~np.isin(want, tl.lane_ids)]
        if len(missing):
            raise WhatIfError(path, f"lanes {missing.tolist()} have no traffic light in this scene (lanes with one: "
                                    f"{tl.lane_ids[:20].tolist()}{'...' if len(tl.lane_ids) > 20 else ''})", i)
        lanes = np.flatnonzero(np.isin(tl.lane_ids, want))
    first = scene.current_frame + FRAMES_PER_TOKEN * step
    states, present = tl.states.copy(), tl.present.copy()
    states[first:, lanes] = code
    present[first:, lanes] = True
    scene = dataclasses.replace(scene, traffic_lights=TrafficLights(tl.lane_ids, states, present, tl.stop_points))
    return scene, lanes, code


def _check_one_script_each(scripts: list[Script], edit_of_script: list[int], whatif: WhatIf, path) -> None:
    """One agent follows one script: a second would silently win or be dropped, so it is an error naming both edits."""
    first: dict[int, int] = {}
    for sc, i in zip(scripts, edit_of_script):
        if sc.track_id in first and first[sc.track_id] != i:
            j = first[sc.track_id]
            raise WhatIfError(path, f"{KIND_OF[type(whatif.edits[i])]}: agent {sc.track_id} is already driven by edit {j} "
                                    f"({KIND_OF[type(whatif.edits[j])]}); an agent takes one scripted edit", i)
        first.setdefault(sc.track_id, i)


def prepare(scene: Scenario, whatif: WhatIf, motion_vocab=None) -> Prepared:
    """Apply a what-if's scene edits and list its per-step actions (see the module docstring).
    ``motion_vocab`` is needed only for inserted agents driven by ``tokens``."""
    path = whatif.path
    scripts, removals, lights = [], [], []
    affected, followers, onset, approaching = {}, {}, {}, []
    next_id = int(scene.tracks.ids.max()) + 1 if scene.num_tracks else 1
    horizon = scene.num_frames - scene.current_frame  # frames of script a new track stores
    edit_of_script: list[int] = []  # the edit each script comes from
    for i, e in enumerate(whatif.edits):
        edit_of_script += [i - 1] * (len(scripts) - len(edit_of_script))
        check_edit(e, path, i)
        kind = KIND_OF[type(e)]
        if kind == "remove":
            idx = [_track_index(scene, a, path, i) for a in (e.agents if isinstance(e.agents, (list, tuple)) else [e.agents])]
            ids = [int(scene.tracks.ids[k]) for k in idx]
            step = _step_of(e.at_s, path, i)
            for tid in ids:
                affected[tid], onset[tid] = "removed", step
            if step == 0:
                scene = scene.select_tracks(np.setdiff1d(np.arange(scene.num_tracks), idx))
            else:
                removals.append((step, ids))
        elif kind in ("brake", "stop"):
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            a = float(e.decel_mps2)
            scripts.append(Script(tid, step, make_path=lambda pose, v, a=a, n=horizon: scripted.brake_path(pose, v, a, n), then="hold"))
            affected[tid], onset[tid] = kind, step
            followers[tid] = _followers(scene, k)
        elif kind == "cut_in":
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            lat, dur, spd = float(e.lateral_m), float(e.duration_s), e.speed_mps
            n = int(math.ceil(dur / DT_S))
            n = FRAMES_PER_TOKEN * int(math.ceil(n / FRAMES_PER_TOKEN))
            scripts.append(Script(tid, step, then="release", make_path=lambda pose, v, lat=lat, dur=dur, spd=spd, n=n:
                                   scripted.cut_in_path(pose, v if spd is None else np.full_like(v, spd), lat, dur, n)))
            affected[tid], onset[tid] = "cut_in", step
        elif kind == "follow":
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            if (e.path is None) == (e.tokens is None):
                raise WhatIfError(path, "follow needs exactly one of 'path' or 'tokens'", i)
            if e.tokens is not None:
                _check_tokens(scene, k, e.tokens, motion_vocab, path, i)
                scripts.append(Script(tid, step, tokens=[int(t) for t in e.tokens], then=_then(e.then, path, i)))
            else:
                wp = _to_local(scene, e, e.path, path, i)[:, :2]
                spd = e.speed_mps

                def make(pose, v, wp=wp, spd=spd, n=horizon):
                    speed = float(np.mean(v)) if spd is None else float(spd)
                    p = scripted.polyline_path(wp, speed, n, first_frame=1)
                    return np.repeat(p[None], len(pose), 0)
                scripts.append(Script(tid, step, make_path=make, then=_then(e.then, path, i)))
            affected[tid], onset[tid] = "follow", step
        elif kind in ("insert", "jaywalker", "stalled_vehicle"):
            if kind == "stalled_vehicle" and e.agent is not None:
                if e.pose is not None:
                    raise WhatIfError(path, "stalled_vehicle takes either 'agent' or 'pose', not both", i)
                k = _track_index(scene, e.agent, path, i)
                tid = int(scene.tracks.ids[k])
                scripts.append(Script(tid, 0, make_path=lambda pose, v, n=horizon: scripted.hold_path(pose, n), then="hold"))
                affected[tid], onset[tid] = "stalled", 0
                followers[tid] = _followers(scene, k)
                continue
            tid = int(e.id) if e.id is not None else next_id
            if np.isin(tid, scene.tracks.ids):
                raise WhatIfError(path, f"id {tid} is already a track of the scene", i)
            next_id = max(next_id, tid) + 1
            atype, then, future, hist_speed, size, tokens = _new_agent(scene, e, kind, horizon, motion_vocab, path, i)
            if len(np.asarray(size).reshape(-1)) != 3:
                raise WhatIfError(path, f"size_m must be [length, width, height], got {size}", i)
            scene = _add_track(scene, tid, atype, future, size, hist_speed)
            scripts.append(_inserted_script(tid, future, tokens, then, horizon))
            affected[tid], onset[tid] = {"insert": "inserted", "jaywalker": "jaywalker", "stalled_vehicle": "stalled"}[kind], 0
            if kind == "stalled_vehicle":
                followers[tid] = _followers(scene, scene.num_tracks - 1)
        elif kind == "traffic_light":
            step = _step_of(e.at_s, path, i)
            tl = scene.traffic_lights
            scene, lanes, code = _override_lights(scene, e, step, path, i)
            if step > 0:
                lights.append((step, lanes, code))
            approaching.append((step, _approaching(scene, tl.stop_points[lanes, :2].astype(np.float64))))
        else:  # pragma: no cover
            raise WhatIfError(path, f"kind {kind} not handled", i)
    edit_of_script += [len(whatif.edits) - 1] * (len(scripts) - len(edit_of_script))
    _check_one_script_each(scripts, edit_of_script, whatif, path)
    return Prepared(scene=scene, scripts=scripts, removals=removals, lights=lights, affected=affected, followers=followers,
                    onset_step=onset, approaching=approaching)


def _check_tokens(scene: Scenario, index: int, tokens, motion_vocab, path, i) -> None:
    """Tokens an existing agent is to take must be in its type's vocabulary (checked before any rollout)."""
    atype = AgentType(int(scene.tracks.types[index]))
    if atype == AgentType.OTHER:
        raise WhatIfError(path, f"agent {int(scene.tracks.ids[index])} is of type other, which has no motion tokens", i)
    if motion_vocab is not None:
        size = motion_vocab[atype].size
        bad = [int(t) for t in tokens if not 0 <= int(t) < size]
        if bad:
            raise WhatIfError(path, f"tokens {bad[:5]} are outside the {atype.name.lower()} vocabulary [0, {size})", i)


def _then(value: str, path, i) -> str:
    if value not in ("hold", "release"):
        raise WhatIfError(path, f"then must be 'hold' or 'release', got {value!r}", i)
    return value


def _pad_hold(poses: np.ndarray, n: int) -> np.ndarray:
    return poses[:n] if len(poses) >= n else np.concatenate([poses, np.repeat(poses[-1:], n - len(poses), 0)], 0)


def _extrapolate(poses: np.ndarray, n: int) -> np.ndarray:
    """``poses`` [K, 3] continued at their last velocity to ``n`` poses."""
    if len(poses) >= n:
        return poses[:n]
    step = poses[-1] - poses[-2] if len(poses) > 1 else np.zeros(3)
    step[2] = 0.0
    extra = poses[-1] + step * np.arange(1, n - len(poses) + 1)[:, None]
    return np.concatenate([poses, extra], 0)


def moving_frames(future: np.ndarray) -> int:
    """Frames after the current one until the scripted motion has reached its end."""
    d = np.linalg.norm(np.diff(future[:, :2], axis=0), axis=1)
    moving = np.flatnonzero(d > 1e-6)
    return int(moving[-1] + 1) if len(moving) else 0


APPROACH_REACH_M = 40.0
"""Vehicles with an overridden light's stop point up to this far ahead (|lateral| < 3 m) approach it."""


def _approaching(scene: Scenario, stop_points: np.ndarray) -> list[int]:
    """Vehicles at the current frame with one of ``stop_points`` [L, 2] ahead of them, in their lane."""
    tr, cf = scene.tracks, scene.current_frame
    xy = tr.position[:, cf, :2].astype(np.float64)
    h = tr.heading[:, cf].astype(np.float64)
    d = stop_points[None] - xy[:, None]  # (N, L, 2)
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    lon, lat = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    ahead = ((lon > 0) & (lon < APPROACH_REACH_M) & (np.abs(lat) < 3.0)).any(1)
    sel = ahead & tr.valid[:, cf] & (tr.types == AgentType.VEHICLE)
    return [int(t) for t in tr.ids[sel]]


def _followers(scene: Scenario, index: int) -> list[int]:
    """Vehicles behind track ``index`` at the current frame, in its lane (see :data:`FOLLOWER_REACH_M`)."""
    tr, cf = scene.tracks, scene.current_frame
    o = _current_pose(scene, index)
    c, s = math.cos(o[2]), math.sin(o[2])
    d = tr.position[:, cf, :2].astype(np.float64) - o[:2]
    lon, lat = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    dh = np.abs(wrap_angle(tr.heading[:, cf].astype(np.float64) - o[2]))
    sel = tr.valid[:, cf] & (tr.types == AgentType.VEHICLE) & (lon < -1.0) & (lon > -FOLLOWER_REACH_M) & (np.abs(lat) < 2.0) & (dh < math.radians(30))
    sel[index] = False
    order = np.argsort(-lon[sel])  # nearest first
    return [int(x) for x in tr.ids[sel][order]]

