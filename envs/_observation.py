"""Environment stage, observations: the simulated state of ``B`` scenes -> one fixed-size vector per
controlled agent, in that agent's own frame (its current pose: x forward, y left, metres, radians),
all scenes and agents at once.

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

import torch

from smart_marl.geometry_torch import block_bounds, block_lower_bound, kept, squared_length
from smart_marl.model.layers import smallest_k
from smart_marl.scenario import SignalState

from ._scene_batch import SceneBatch, gather_tracks
from .errors import EnvConfigError

PAST_OFFSETS_FRAMES = (5, 10, 15, 20)  # 0.5 s .. 2.0 s ago
HISTORY_FRAMES = max(PAST_OFFSETS_FRAMES) + 1  # frames of pose history the environment keeps
NUM_MAP_TYPES = 7
ROAD_BLOCK = 8
"""Road points per block of the nearest-road-point search's bound (:func:`nearest_road_points`)."""
ROAD_CANDIDATES = 64
"""Blocks of smallest bound whose points every observation measures first."""
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


def _to_local(origin: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """Points xy [..., K, 2] into the frames of origin poses [..., 3]."""
    c, s = origin[..., 2].cos()[..., None], origin[..., 2].sin()[..., None]
    d = xy - origin[..., None, :2]
    return torch.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)


def _rotate(heading: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Vectors v [..., K, 2] into frames of heading [...]."""
    c, s = heading.cos()[..., None], heading.sin()[..., None]
    return torch.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], -1)


def _nearest(d2: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices [..., k] of the k smallest finite entries of each row of ``d2`` [..., M] (nearest first)
    and their validity; rows with fewer than k entries are padded with invalid index 0."""
    m = d2.shape[-1]
    kk = min(k, m)
    if kk == 0:
        return d2.new_zeros((*d2.shape[:-1], k), dtype=torch.long), torch.zeros((*d2.shape[:-1], k), dtype=torch.bool, device=d2.device)
    val, idx = smallest_k(d2, kk)  # ties lowest index first: the same agents however the scene is padded
    ok = torch.isfinite(val)
    if kk < k:
        pad = (*d2.shape[:-1], k - kk)
        idx = torch.cat([idx, idx.new_zeros(pad)], -1)
        ok = torch.cat([ok, torch.zeros(pad, dtype=torch.bool, device=d2.device)], -1)
    return idx.masked_fill(~ok, 0), ok


def nearest_road_points(scenes: SceneBatch, xy: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(indices, valid) [B, C, k] of the ``k`` road points of each scene nearest to ``xy`` [B, C, 2]
    (nearest first, ties lowest index first; invalid index 0 where a scene has fewer), as
    :func:`_nearest` on the squared distance to every road point, measured on few: no point of a block
    (:func:`~smart_marl.geometry_torch.block_bounds`, ``ROAD_BLOCK`` consecutive points, kept until a
    refill rewrites the road) is nearer than the block's bound; every point of the ``ROAD_CANDIDATES``
    blocks of smallest bound is measured, and where the k-th nearest of them is nearer than every
    other block's bound, they hold the k nearest; elsewhere every block whose bound is within that
    distance is measured."""
    b, c = xy.shape[:2]
    p = scenes.road_xy.shape[1]
    kb = max(ROAD_CANDIDATES, -(-k // ROAD_BLOCK))
    if p <= kb * ROAD_BLOCK:  # a small map: every point
        d2 = squared_length(scenes.road_xy[:, None] - xy[:, :, None]).masked_fill(~scenes.road_valid[:, None], float("inf"))
        return _nearest(d2, k)
    centre, radius = kept(scenes, "_road_blocks", (scenes.road_xy, scenes.road_valid),
                          lambda i=slice(None): block_bounds(scenes.road_xy[i, :, None], scenes.road_valid[i], ROAD_BLOCK), ROAD_BLOCK,
                          by_rows=True)
    nb = centre.shape[1]
    bound = block_lower_bound(xy, centre, radius)  # [B, C, nb]
    lb, blk = torch.topk(bound, min(kb + 1, nb), dim=-1, largest=False)
    rest = lb[..., kb] if kb < nb else torch.full((b, c), float("inf"), dtype=xy.dtype, device=xy.device)
    scene = torch.arange(b, device=xy.device)[:, None].expand(b, c).reshape(-1)
    idx, ok, kth = _nearest_in_road_blocks(scenes, xy.reshape(b * c, 2), scene, blk[..., :kb].sort(dim=-1).values.reshape(b * c, kb), k)
    idx, ok, kth = idx.view(b, c, k), ok.view(b, c, k), kth.view(b, c)
    qb, qc = (~((kth < rest) | (rest == float("inf")))).nonzero(as_tuple=True)
    if len(qb):  # a point outside the candidate blocks may be among the k nearest
        need = bound[qb, qc] <= kth[qb, qc, None]  # [U, nb]
        count = need.sum(-1)
        blocks = torch.where(need, torch.arange(nb, device=xy.device), nb).sort(dim=-1).values
        lo = 0
        while lo < nb:  # rows needing about as many blocks together
            hi = min(2 * max(lo, kb), nb)
            i = ((count > lo) & (count <= hi)).nonzero().squeeze(1)
            if len(i):
                idx[qb[i], qc[i]], ok[qb[i], qc[i]], _ = _nearest_in_road_blocks(scenes, xy[qb[i], qc[i]], qb[i], blocks[i, :hi], k)
            lo = hi
    return idx, ok


def _nearest_in_road_blocks(scenes: SceneBatch, xy: torch.Tensor, scene: torch.Tensor, blocks: torch.Tensor,
                            k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(indices [U, k], valid [U, k], distance of the k-th [U], ``inf`` if fewer) of the k road points of
    scenes ``scene`` [U] nearest to ``xy`` [U, 2] among the points of blocks ``blocks`` [U, m]
    (ascending; ``nb`` or more: none)."""
    p = scenes.road_xy.shape[1]
    pts = (blocks[..., None] * ROAD_BLOCK + torch.arange(ROAD_BLOCK, device=xy.device)).flatten(1)  # [U, m * block], ascending
    inside = pts < p
    pts = torch.where(inside, pts, torch.zeros_like(pts))
    flat = (scene[:, None] * p + pts).reshape(-1)  # rows of the flattened road (one index: a fast gather)
    near = scenes.road_xy.reshape(-1, 2).index_select(0, flat).view(*pts.shape, 2)
    valid = scenes.road_valid.reshape(-1).index_select(0, flat).view(pts.shape)
    d2 = squared_length(near - xy[:, None]).masked_fill(~(inside & valid), float("inf"))
    val, sub = smallest_k(d2, k)
    ok = torch.isfinite(val)
    return pts.gather(-1, sub).masked_fill(~ok, 0), ok, val[:, -1].sqrt()


def _one_hot(index: torch.Tensor, size: int, dtype) -> torch.Tensor:
    return torch.nn.functional.one_hot(index.clamp(0, size - 1), size).to(dtype)


def _light_codes(states: torch.Tensor) -> torch.Tensor:
    """[..., 4] one-hot red / yellow / green / unknown of SignalState codes [...]."""
    red = sum(states == int(s) for s in _RED)
    yellow = sum(states == int(s) for s in _YELLOW)
    green = sum(states == int(s) for s in _GREEN)
    known = red + yellow + green
    return torch.stack([red, yellow, green, known == 0], -1)


def build_observations(cfg: ObservationConfig, scenes: SceneBatch, ctrl_track: torch.Tensor, pose: torch.Tensor,
                       velocity: torch.Tensor, present: torch.Tensor, hist_pose: torch.Tensor, hist_valid: torch.Tensor,
                       progress_m: torch.Tensor, frame: torch.Tensor, time_fraction: torch.Tensor) -> torch.Tensor:
    """Observation vectors [B, C, D] (float32) of the controlled tracks ``ctrl_track`` [B, C] (-1: a
    padded slot, all zeros).

    pose [B, N, 3], velocity [B, N, 2] (local scene frame), present [B, N], hist_pose [B, N, H, 3]
    (oldest first, last = now), hist_valid [B, N, H], progress_m [B, C] (route progress of each
    controlled track), frame [B] the simulated 10 Hz frame (lights are read there), time_fraction [B].
    """
    b, c = ctrl_track.shape
    dtype, dev = pose.dtype, pose.device
    real = ctrl_track >= 0
    lay = {name: (off, size) for name, off, size in observation_layout(cfg)}
    parts: dict[str, torch.Tensor] = {}
    me = gather_tracks(pose, ctrl_track)  # [B, C, 3]
    h0 = me[..., 2]
    my_vel = gather_tracks(velocity, ctrl_track)
    my_type = gather_tracks(scenes.types, ctrl_track)
    parts["ego_speed"] = my_vel.norm(dim=-1, keepdim=True)
    parts["ego_velocity"] = _rotate(h0, my_vel[..., None, :])[..., 0, :]
    parts["ego_size"] = gather_tracks(scenes.box_size, ctrl_track)[..., :2]
    parts["ego_type"] = _one_hot(my_type, 3, dtype)
    past_idx = hist_pose.shape[2] - 1 - torch.tensor(PAST_OFFSETS_FRAMES, device=dev)
    past = gather_tracks(hist_pose, ctrl_track)[:, :, past_idx]  # [B, C, 4, 3] (the controlled tracks first: fewer copied)
    pv = gather_tracks(hist_valid, ctrl_track)[:, :, past_idx]
    pxy = _to_local(me, past[..., :2])
    dh = past[..., 2] - h0[..., None]
    ego_past = torch.stack([torch.ones_like(dh), pxy[..., 0], pxy[..., 1], dh.cos(), dh.sin()], -1)
    parts["ego_past"] = ego_past * pv[..., None]

    # K nearest other agents
    k = cfg.num_agents
    d2 = squared_length(pose[:, None, :, :2] - me[:, :, None, :2])  # [B, C, N]
    others = present[:, None, :] & (torch.arange(pose.shape[1], device=dev)[None, None] != ctrl_track[..., None])
    idx, ok = _nearest(d2.masked_fill(~others, float("inf")), k)  # [B, C, K]
    other_pose = pose.gather(1, idx.reshape(b, -1, 1).expand(-1, -1, 3)).view(b, c, k, 3)
    oxy = _to_local(me, other_pose[..., :2])
    odh = other_pose[..., 2] - h0[..., None]
    ov = _rotate(h0, velocity.gather(1, idx.reshape(b, -1, 1).expand(-1, -1, 2)).view(b, c, k, 2))
    osize = scenes.box_size.gather(1, idx.reshape(b, -1, 1).expand(-1, -1, 3)).view(b, c, k, 3)[..., :2]
    otype = _one_hot(scenes.types.gather(1, idx.reshape(b, -1)).view(b, c, k), 4, dtype)
    feats = torch.cat([torch.ones_like(odh)[..., None], oxy, odh.cos()[..., None], odh.sin()[..., None], ov, osize, otype], -1)
    parts["agents"] = feats * ok[..., None]

    # M nearest road points
    m = cfg.num_road_points
    ridx, rok = nearest_road_points(scenes, me[..., :2], m)  # [B, C, M]
    rxy = _to_local(me, scenes.road_xy.gather(1, ridx.reshape(b, -1, 1).expand(-1, -1, 2)).view(b, c, m, 2))
    rtype = _one_hot(scenes.road_type.gather(1, ridx.reshape(b, -1)).view(b, c, m), NUM_MAP_TYPES, dtype)
    parts["road"] = torch.cat([torch.ones_like(rxy[..., :1]), rxy, rtype], -1) * rok[..., None]

    # logged goal and route progress
    length = gather_tracks(scenes.route_length_m, ctrl_track)
    gxy = _to_local(me, gather_tracks(scenes.goal_xy, ctrl_track)[..., None, :])[..., 0, :]
    has_goal = gather_tracks(scenes.route_valid, ctrl_track).any(-1)
    frac = torch.where(length > 0, progress_m / length.clamp(min=1e-9), torch.ones_like(length))
    goal = torch.stack([torch.ones_like(length), gxy[..., 0], gxy[..., 1], gxy.norm(dim=-1), frac,
                        (length - progress_m).clamp(min=0.0)], -1)
    parts["goal"] = goal * has_goal[..., None]

    # traffic lights ahead
    nl = cfg.num_lights
    f = torch.minimum(frame, scenes.num_frames - 1)
    state = scenes.light_state.gather(1, f[:, None, None].expand(-1, 1, scenes.light_state.shape[2]))[:, 0]  # [B, L]
    lpresent = scenes.light_present.gather(1, f[:, None, None].expand(-1, 1, scenes.light_present.shape[2]))[:, 0]
    lxy = _to_local(me, scenes.light_xy[:, None].expand(b, c, -1, 2))  # [B, C, L, 2]
    ld2 = squared_length(lxy)
    ahead = (lxy[..., 0] > 0) & (ld2 <= cfg.light_radius_m ** 2) & (lpresent & scenes.light_valid)[:, None]
    lidx, lok = _nearest(ld2.masked_fill(~ahead, float("inf")), nl)  # [B, C, nl]
    codes = _light_codes(state.gather(1, lidx.reshape(b, -1)).view(b, c, nl)).to(dtype)
    sel = lxy.gather(2, lidx[..., None].expand(-1, -1, -1, 2))
    parts["lights"] = torch.cat([torch.ones_like(sel[..., :1]), sel, codes], -1) * lok[..., None]
    parts["time"] = time_fraction.to(dtype)[:, None, None].expand(b, c, 1)

    out = torch.zeros(b, c, observation_size(cfg), dtype=dtype, device=dev)
    for name, (off, size) in lay.items():
        out[..., off:off + size] = parts[name].reshape(b, c, size).to(dtype)
    return (out * real[..., None]).to(torch.float32)


__all__ = ["HISTORY_FRAMES", "NUM_MAP_TYPES", "ObservationConfig", "PAST_OFFSETS_FRAMES", "build_observations", "observation_layout",
           "observation_size"]
