"""Environment stage, observations: the simulated state of a scene -> one fixed-size vector per
controlled agent, in that agent's own frame (its current pose: x forward, y left, metres, radians).

Layout (``observation_layout(config)`` gives every block's name, offset and size; defaults
K = 8 agents, M = 32 road points, L = 2 traffic lights: 473 floats):

====================  ==========  ===============================================================
block                 size        content
====================  ==========  ===============================================================
ego_speed             1           speed (m/s)
ego_velocity          2           velocity in the agent's frame (m/s)
ego_size              2           box length, width (m)
ego_type              3           one-hot vehicle, pedestrian, cyclist
ego_past              5 x 4       the agent's own poses 0.5, 1.0, 1.5, 2.0 s ago: valid, x, y,
                                  cos(dheading), sin(dheading)
agents                13 x K      the K nearest other agents present (nearest first): valid, x, y,
                                  cos(dheading), sin(dheading), vx, vy (agent's frame, m/s),
                                  length, width, one-hot type (vehicle, pedestrian, cyclist, other)
road                  10 x M      the M nearest road points (~2 m apart along every map polyline):
                                  valid, x, y, one-hot MapFeatureType (7)
goal                  6           valid, x, y of the logged goal (the track's last logged
                                  position), distance (m), route progress (fraction of the
                                  logged route), remaining route (m)
lights                7 x L       the L nearest signalised stop points ahead (x > 0, within
                                  ``light_radius_m``): valid, x, y, one-hot red / yellow / green /
                                  unknown (the log's state at the simulated frame)
time                  1           elapsed fraction of the horizon
====================  ==========  ===============================================================

Invalid slots are all zeros. The ``"dict"`` observation wraps this vector as ``"observation"``
and adds ``"action_mask"`` (the tokens the env's reference allows: every token of the agent's
vocabulary, or the prior's top-k with ``reference_top_k``, set by the env) and, when the
environment has a prior, ``"prior_logits"`` (the prior's logits of the agent's next token).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import EnvConfigError

from smart_marl.scenario import SignalState

PAST_OFFSETS_FRAMES = (5, 10, 15, 20)  # 0.5 s .. 2.0 s ago
HISTORY_FRAMES = max(PAST_OFFSETS_FRAMES) + 1  # frames of pose history the environment keeps
NUM_MAP_TYPES = 7
_RED = {SignalState.ARROW_STOP, SignalState.STOP, SignalState.FLASHING_STOP}
_YELLOW = {SignalState.ARROW_CAUTION, SignalState.CAUTION, SignalState.FLASHING_CAUTION}
_GREEN = {SignalState.ARROW_GO, SignalState.GO}


@dataclass(frozen=True)
class ObservationConfig:
    """What the observation holds. ``kind``: "vector" (a Box) or "dict" (adds action_mask and,
    with a prior, prior_logits)."""

    kind: str = "vector"
    num_agents: int = 8
    num_road_points: int = 32
    num_lights: int = 2
    light_radius_m: float = 60.0

    def __post_init__(self) -> None:
        if self.kind not in ("vector", "dict"):
            raise EnvConfigError(f"observation kind must be 'vector' or 'dict', got {self.kind!r}")


def observation_layout(cfg: ObservationConfig) -> list[tuple[str, int, int]]:
    """[(block name, offset, size)] of the observation vector."""
    blocks = [("ego_speed", 1), ("ego_velocity", 2), ("ego_size", 2), ("ego_type", 3), ("ego_past", 5 * len(PAST_OFFSETS_FRAMES)),
              ("agents", 13 * cfg.num_agents), ("road", (3 + NUM_MAP_TYPES) * cfg.num_road_points), ("goal", 6),
              ("lights", 7 * cfg.num_lights), ("time", 1)]
    out, offset = [], 0
    for name, size in blocks:
        out.append((name, offset, size))
        offset += size
    return out


def observation_size(cfg: ObservationConfig) -> int:
    name, offset, size = observation_layout(cfg)[-1]
    return offset + size


def _to_local(origin: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Points xy [C, K, 2] into the frames of origin poses [C, 3]."""
    c, s = np.cos(origin[:, 2])[:, None], np.sin(origin[:, 2])[:, None]
    d = xy - origin[:, None, :2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def _rotate(origin_heading: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(origin_heading)[:, None], np.sin(origin_heading)[:, None]
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], -1)


def _nearest(d2: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices [C, k] of the k smallest finite entries per row (nearest first) and their validity."""
    c, n = d2.shape
    if n == 0 or k == 0:
        return np.zeros((c, k), np.int64), np.zeros((c, k), bool)
    kk = min(k, n)
    part = np.argpartition(d2, kk - 1, axis=1)[:, :kk] if kk < n else np.broadcast_to(np.arange(n), (c, n)).copy()
    order = np.argsort(np.take_along_axis(d2, part, 1), axis=1, kind="stable")
    idx = np.take_along_axis(part, order, 1)
    ok = np.isfinite(np.take_along_axis(d2, idx, 1))
    if kk < k:
        idx = np.concatenate([idx, np.zeros((c, k - kk), np.int64)], 1)
        ok = np.concatenate([ok, np.zeros((c, k - kk), bool)], 1)
    return idx, ok


def build_observations(cfg: ObservationConfig, static, ctrl: np.ndarray, pose: np.ndarray, velocity: np.ndarray,
                       present: np.ndarray, hist_pose: np.ndarray, hist_valid: np.ndarray, progress_m: np.ndarray,
                       light_state: np.ndarray, light_present: np.ndarray, time_fraction: float) -> np.ndarray:
    """Observation vectors [C, D] (float32) of the controlled tracks ``ctrl`` [C].

    pose [N, 3], velocity [N, 2] (local scene frame), present [N], hist_pose [N, H, 3] (oldest
    first, last = now), hist_valid [N, H], progress_m [C] (route progress of each controlled
    track), light_state / light_present [L] at the simulated frame.
    """
    c = len(ctrl)
    out = np.zeros((c, observation_size(cfg)), np.float64)
    if c == 0:
        return out.astype(np.float32)
    lay = {name: (off, size) for name, off, size in observation_layout(cfg)}
    me = pose[ctrl]  # [C, 3]
    h0 = me[:, 2]

    def put(name: str, values: np.ndarray) -> None:
        off, size = lay[name]
        out[:, off : off + size] = values.reshape(c, size)

    v_local = _rotate(h0, velocity[ctrl][:, None])[:, 0]
    put("ego_speed", np.linalg.norm(velocity[ctrl], axis=1))
    put("ego_velocity", v_local)
    put("ego_size", static.box_size[ctrl, :2])
    put("ego_type", np.eye(3)[np.clip(static.types[ctrl], 0, 2)])
    past_idx = hist_pose.shape[1] - 1 - np.asarray(PAST_OFFSETS_FRAMES)
    past = hist_pose[ctrl][:, past_idx]  # [C, 4, 3]
    pv = hist_valid[ctrl][:, past_idx]
    pxy = _to_local(me, past[..., :2])
    dh = past[..., 2] - h0[:, None]
    put("ego_past", np.where(pv[..., None], np.stack([np.ones_like(dh), pxy[..., 0], pxy[..., 1], np.cos(dh), np.sin(dh)], -1), 0.0))

    # K nearest other agents
    d2 = np.sum((pose[None, :, :2] - me[:, None, :2]) ** 2, -1)  # [C, N]
    d2 = np.where(present[None, :], d2, np.inf)
    d2[np.arange(c), ctrl] = np.inf
    idx, ok = _nearest(d2, cfg.num_agents)
    oxy = _to_local(me, pose[idx][..., :2])
    odh = pose[idx][..., 2] - h0[:, None]
    ov = _rotate(h0, velocity[idx])
    otype = np.eye(4)[np.clip(static.types[idx], 0, 3)]
    feats = np.concatenate([np.ones((c, cfg.num_agents, 1)), oxy, np.cos(odh)[..., None], np.sin(odh)[..., None], ov,
                            static.box_size[idx][..., :2], otype], -1)
    put("agents", np.where(ok[..., None], feats, 0.0))

    # M nearest road points
    m = cfg.num_road_points
    if len(static.road_xy) and m:
        rd2 = np.sum((static.road_xy[None] - me[:, None, :2]) ** 2, -1)  # [C, P]
        ridx, rok = _nearest(rd2, m)
        rxy = _to_local(me, static.road_xy[ridx])
        rtype = np.eye(NUM_MAP_TYPES)[np.clip(static.road_type[ridx], 0, NUM_MAP_TYPES - 1)]
        put("road", np.where(rok[..., None], np.concatenate([np.ones((c, m, 1)), rxy, rtype], -1), 0.0))

    # logged goal and route progress
    length = static.route_length_m[ctrl]
    gxy = _to_local(me, static.goal_xy[ctrl][:, None])[:, 0]
    has_goal = static.route_valid[ctrl].any(1)
    frac = np.where(length > 0, progress_m / np.maximum(length, 1e-9), 1.0)
    goal = np.stack([np.ones(c), gxy[:, 0], gxy[:, 1], np.linalg.norm(gxy, axis=1), frac, np.maximum(length - progress_m, 0.0)], -1)
    put("goal", np.where(has_goal[:, None], goal, 0.0))

    # traffic lights ahead
    nl = cfg.num_lights
    if len(static.light_xy) and nl:
        lxy = _to_local(me, np.broadcast_to(static.light_xy[None], (c, *static.light_xy.shape)))
        ld2 = np.sum(lxy ** 2, -1)
        ahead = (lxy[..., 0] > 0) & (ld2 <= cfg.light_radius_m ** 2) & light_present[None]
        lidx, lok = _nearest(np.where(ahead, ld2, np.inf), nl)
        st = light_state[lidx]
        onehot = np.stack([np.isin(st, list(_RED)), np.isin(st, list(_YELLOW)), np.isin(st, list(_GREEN)),
                           ~np.isin(st, list(_RED | _YELLOW | _GREEN))], -1).astype(np.float64)
        sel = np.take_along_axis(lxy, lidx[..., None], 1)
        put("lights", np.where(lok[..., None], np.concatenate([np.ones((c, nl, 1)), sel, onehot], -1), 0.0))
    put("time", np.full(c, float(time_fraction)))
    return out.astype(np.float32)
