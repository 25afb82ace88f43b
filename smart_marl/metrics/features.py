"""Per-step features of the realism metrics, for the log and for every rollout at once.

Stage: metrics. Input: a :class:`~.inputs.LoggedScene` and aligned :class:`~.inputs.Rollouts`;
output: :class:`Features` arrays ``[B, E, 80]`` (B = 1 for the log, R for the rollouts; E evaluated
agents; the 80 simulated steps) plus the per-rollout displacement errors. Vectorised over
rollouts, agents and steps (numpy, float64).

How each feature is made (the official rules; docs/wosac_metrics.md):
* every trajectory is the 11 logged history steps + the 80 simulated ones; the simulated steps keep
  the logged size at step 10 and are all valid, the history keeps the logged sizes and validity;
* kinematics: central differences over the 91 steps padded with NaN, then steps 11-90;
* distance to the nearest object between rounded boxes (:mod:`smart_marl.geometry`), every
  simulated agent counting as an "other"; collision when < 0;
* time to collision with the object followed, 2D speeds from the same central difference;
* distance to the road edge: the worst of the 4 bottom corners; offroad when > 0;
* traffic-light violation (2025 rules): crossing a red light's stop point along one's nearest lane.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import geometry
from ..scenario import wrap_angle
from .config import CURRENT_STEP, NUM_STEPS, STEP_S
from .inputs import LoggedScene, Rollouts, Signals

_FUTURE = slice(CURRENT_STEP + 1, NUM_STEPS)
STOP_STATES = (1, 4)  # ARROW_STOP, STOP


@dataclass(frozen=True)
class Features:
    """Features ``[B, E, 80]`` of the evaluated agents on the simulated steps; ``ade`` [B, E]."""

    valid: np.ndarray
    linear_speed: np.ndarray
    linear_acceleration: np.ndarray
    angular_speed: np.ndarray
    angular_acceleration: np.ndarray
    distance_to_nearest_object: np.ndarray
    collision_per_step: np.ndarray
    time_to_collision: np.ndarray
    distance_to_road_edge: np.ndarray
    offroad_per_step: np.ndarray
    traffic_light_violation_per_step: np.ndarray | None
    ade: np.ndarray


# ------------------------------------------------------------------------------- kinematics
def central_diff(values: np.ndarray, pad_value: float = np.nan) -> np.ndarray:
    """(v[t+1] - v[t-1]) / 2 along the last axis, padded once at each end."""
    out = np.full(values.shape, pad_value, dtype=np.float64)
    out[..., 1:-1] = (values[..., 2:] - values[..., :-2]) / 2.0
    return out


def central_and(valid: np.ndarray) -> np.ndarray:
    """valid[t-1] and valid[t+1] along the last axis; the ends are False."""
    out = np.zeros(valid.shape, bool)
    out[..., 1:-1] = valid[..., 2:] & valid[..., :-2]
    return out


def kinematic_features(x, y, z, heading, step_s: float = STEP_S):
    """Linear speed, linear acceleration, angular speed, angular acceleration [..., T] (the official
    central differences: the speed is the 3D norm, the angular ones wrap twice the half difference)."""
    dpos = np.stack([central_diff(x), central_diff(y), central_diff(z)], axis=0)
    speed = np.sqrt((dpos ** 2).sum(axis=0)) / step_s
    accel = central_diff(speed) / step_s
    dh_step = wrap_angle(central_diff(heading) * 2) / 2
    dh = dh_step / step_s
    d2h_step = wrap_angle(central_diff(dh_step) * 2) / 2
    d2h = d2h_step / step_s ** 2
    return speed, accel, dh, d2h


def kinematic_validity(valid: np.ndarray):
    """Masks of speeds (central ``and`` once) and accelerations (twice)."""
    speed_valid = central_and(valid)
    return speed_valid, central_and(speed_valid)


# ------------------------------------------------------------------------------- trajectories
def _trajectories(scene: LoggedScene, rollouts: Rollouts | None):
    """Full 91-step trajectories [B, A, 91]: the log (B = 1) or history + rollouts (B = R)."""
    a = scene.num_agents
    hist = slice(0, CURRENT_STEP + 1)
    # sizes: logged per step on the history, the logged size at the current step afterwards (for
    # the log too: the official code rebuilds the logged future like a rollout)
    size = np.empty((a, NUM_STEPS, 3))
    size[:, hist] = scene.size[:, hist]
    size[:, _FUTURE] = scene.size[:, CURRENT_STEP : CURRENT_STEP + 1]
    if rollouts is None:
        return (scene.position[None], scene.heading[None], size[None], scene.valid[None])
    r = rollouts.num_rollouts
    pos = np.empty((r, a, NUM_STEPS, 3))
    pos[:, :, hist] = scene.position[None, :, hist]
    pos[:, :, _FUTURE, 0] = rollouts.x
    pos[:, :, _FUTURE, 1] = rollouts.y
    pos[:, :, _FUTURE, 2] = rollouts.z
    heading = np.empty((r, a, NUM_STEPS))
    heading[:, :, hist] = scene.heading[None, :, hist]
    heading[:, :, _FUTURE] = rollouts.heading
    valid = np.ones((a, NUM_STEPS), bool)
    valid[:, hist] = scene.valid[:, hist]
    return pos, heading, np.broadcast_to(size, (r,) + size.shape), np.broadcast_to(valid, (r,) + valid.shape)


# ------------------------------------------------------------------------- nearest object
def distance_to_nearest_object(xy, length, width, heading, valid, evaluated: np.ndarray, candidates: int = 6):
    """Signed distance [B, E, T] from each evaluated box to the nearest other valid box (rounded
    corners). Inputs [B, A, T] (xy [B, A, T, 2]); invalid evaluated boxes get 1e10, and so does a
    box with no valid other. Exact, with pruning: only the ``candidates`` others with the smallest
    lower bound are measured, unless a row's bound shows the nearest may be elsewhere (then all)."""
    big = geometry.EXTREMELY_LARGE_DISTANCE_M
    e_idx = evaluated
    b, a, t = valid.shape
    exy = xy[:, e_idx]  # [B, E, T, 2]
    el, ew = length[:, e_idx], width[:, e_idx]
    # pairs laid out [B, E, T, A]
    dxy = xy.transpose(0, 2, 1, 3)[:, None] - exy[:, :, :, None, :]  # [B, E, T, A, 2]
    dc = np.sqrt((dxy ** 2).sum(-1))
    ol, ow = length.transpose(0, 2, 1)[:, None], width.transpose(0, 2, 1)[:, None]  # [B, 1, T, A]
    lb, ub = geometry.box_distance_bounds(dc, el[..., None], ew[..., None], ol, ow)
    pair_valid = valid[:, e_idx][..., None] & valid.transpose(0, 2, 1)[:, None]
    pair_valid = pair_valid & (np.arange(a)[None, :] != e_idx[:, None])[None, :, None, :]
    lb = np.where(pair_valid, lb, np.inf)
    k = min(candidates, a)
    if k < a:
        part = np.argpartition(lb, k - 1, axis=-1)
        cand = part[..., :k]
        rest_lb = np.take_along_axis(lb, part[..., k:], axis=-1).min(axis=-1)
    else:
        cand = np.broadcast_to(np.arange(a), lb.shape)
        rest_lb = np.full(lb.shape[:-1], np.inf)
    result = _exact_min_distance(xy, length, width, heading, e_idx, cand, np.take_along_axis(pair_valid, cand, -1))
    bad = result > rest_lb  # the nearest may be outside the candidates
    if bad.any():
        bi, ei, ti = np.nonzero(bad)
        full = np.broadcast_to(np.arange(a), (len(bi), a))
        sub = _exact_min_distance_rows(xy, length, width, heading, e_idx, bi, ei, ti, full, pair_valid[bi, ei, ti])
        result[bi, ei, ti] = sub
    return result


def _exact_min_distance(xy, length, width, heading, e_idx, cand, cand_valid):
    b, e, t, k = cand.shape
    bi = np.arange(b)[:, None, None, None]
    ti = np.arange(t)[None, None, :, None]
    ei = e_idx[None, :, None, None]
    d = _rounded_distance((bi, ei, ti), (bi, cand, ti), xy, length, width, heading)
    d = np.where(cand_valid, d, geometry.EXTREMELY_LARGE_DISTANCE_M)
    return d.min(axis=-1)


def _rounded_distance(index_a, index_b, xy, length, width, heading):
    """Rounded-box signed distance between boxes ``index_a`` and ``index_b`` (float32 corners as
    the official code makes them; see :func:`smart_marl.geometry.box_corners_float32`)."""
    out = []
    for ix in (index_a, index_b):
        s, lc, wc = geometry.rounded_box_core_float32(length[ix], width[ix])
        corners = geometry.box_corners_float32(xy[ix + (0,)], xy[ix + (1,)], lc, wc, heading[ix])
        out.append((s, corners))
    (sa, ca), (sb, cb) = out
    ca, cb = np.broadcast_arrays(ca, cb)
    return geometry.box_signed_distance(ca, cb) - sa - sb


def _exact_min_distance_rows(xy, length, width, heading, e_idx, bi, ei, ti, others, others_valid):
    b_, e_, t_ = bi[:, None], e_idx[ei][:, None], ti[:, None]
    d = _rounded_distance((b_, e_, t_), (b_, others, t_), xy, length, width, heading)
    d = np.where(others_valid, d, geometry.EXTREMELY_LARGE_DISTANCE_M)
    return d.min(axis=-1)


# ------------------------------------------------------------------------- time to collision
def time_to_collision(xy, length, width, heading, valid, evaluated: np.ndarray, step_s: float = STEP_S):
    """Time to collision [B, E, T] with the followed object (inputs [B, A, T] over the full
    trajectory; the speeds are 2D central differences, NaN at both ends)."""
    speed = kinematic_features(xy[..., 0], xy[..., 1], np.zeros_like(xy[..., 0]), heading, step_s)[0]
    tr = lambda v: np.moveaxis(v, 1, 2)  # [B, T, A]
    x, y, l, w, h, s, v = (tr(a) for a in (xy[..., 0], xy[..., 1], length, width, heading, speed, valid))
    e = evaluated
    ttc = geometry.time_to_collision(x[..., e], y[..., e], l[..., e], w[..., e], h[..., e], s[..., e],
                                     x, y, l, w, h, s, v)  # [B, T, E]
    return np.moveaxis(ttc, 2, 1)


# ---------------------------------------------------------------------------- road edges
def distance_to_road_edge(xyz, length, width, height, heading, valid, evaluated, segments):
    """Signed distance [B, E, T] of the evaluated boxes to the road edge (max over the 4 bottom
    corners; -1e10 where the box is invalid). Without road edges: -1e10 everywhere (the official
    package refuses such scenes; here every box then counts as on road)."""
    e = evaluated
    big = geometry.EXTREMELY_LARGE_DISTANCE_M
    if segments.num_segments == 0:
        return np.full(valid[:, e].shape, -big)
    ex = xyz[:, e]
    d = geometry.box_distance_to_road_edge(ex[..., 0], ex[..., 1], ex[..., 2], length[:, e], width[:, e], height[:, e],
                                           heading[:, e], segments)
    return np.where(valid[:, e], d, -big)


# ---------------------------------------------------------------------------- traffic lights
def _quirky_lane_distance(q, start, end):
    """The official lane-matching distance |(q - start) + (end - start) * clip(t)| (plus sign kept)."""
    sp = q - start
    se = end - start
    denom = (se ** 2).sum(-1)
    num = (sp * se).sum(-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(denom > 0, num / np.where(denom > 0, denom, 1.0), 0.0)
    tc = np.clip(t, 0.0, 1.0)[..., None]
    return np.sqrt(((sp + se * tc) ** 2).sum(-1))


def _quirky_lane_distance_cols(q, cols, idx):
    """:func:`_quirky_lane_distance` of points q [n, 2] to candidate segments idx [n, k], per component."""
    sx, sy, ex, ey = (c[idx] for c in cols)
    px, py = q[:, 0, None] - sx, q[:, 1, None] - sy
    denom = ex * ex + ey * ey
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (px * ex + py * ey) / denom
    t = np.where(denom > 0, np.clip(t, 0.0, 1.0), 0.0)
    dx, dy = px + ex * t, py + ey * t
    return np.sqrt(dx * dx + dy * dy)


def _nearest_lane(q: np.ndarray, lanes, cell_m: float = 2.0) -> np.ndarray:
    """Lane index [N] of the nearest lane segment (official distance, first on ties) for points [N, 2].

    Exact with pruning: |sp| <= d <= |sp| + |se| (t > 0 only when sp.se > 0, and then the plus sign
    only lengthens sp), so per cell of points only segments whose start is close enough are measured."""
    nl, p, _ = lanes.points.shape
    start = lanes.points[:, :-1].reshape(-1, 2)
    end = lanes.points[:, 1:].reshape(-1, 2)
    seg_valid = lanes.point_valid[:, :-1].reshape(-1)
    keep = np.flatnonzero(seg_valid)  # only segments with a valid start count
    start, end = start[keep], end[keep]
    seg_len = np.sqrt(((end - start) ** 2).sum(-1))
    cols = (start[:, 0].copy(), start[:, 1].copy(), (end - start)[:, 0].copy(), (end - start)[:, 1].copy())
    uq, q_of = np.unique(q, axis=0, return_inverse=True)  # repeated points (identical rollouts) once
    q_of = q_of.reshape(-1)
    cells = np.floor(uq / cell_m).astype(np.int64)
    _, inv = np.unique(cells[:, 0] * 2_000_003 + cells[:, 1], return_inverse=True)
    inv = inv.reshape(-1)
    nc = int(inv.max()) + 1
    lo = np.full((nc, 2), np.inf)
    hi = np.full((nc, 2), -np.inf)
    np.minimum.at(lo, inv, uq)
    np.maximum.at(hi, inv, uq)
    ref = 0.5 * (lo + hi)
    rad = 0.5 * np.sqrt(((hi - lo) ** 2).sum(-1))
    best = np.empty(len(uq), np.int64)
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(nc + 1))
    chunk = max(1, int(4_000_000 // max(len(start), 1)))
    for c0 in range(0, nc, chunk):
        c1 = min(nc, c0 + chunk)
        dref = geometry.pairwise_distance(ref[c0:c1], start)  # [C, S]
        ub = (dref + seg_len[None]).min(axis=1) + rad[c0:c1]
        cand_mask = dref - rad[c0:c1, None] <= ub[:, None] + 1e-9
        counts = cand_mask.sum(1)
        by_count = np.argsort(counts, kind="stable")
        gb = geometry.group_by_count(counts[by_count])
        for g0, g1 in zip(gb[:-1], gb[1:]):
            cells_g = by_count[g0:g1]
            kmax = max(int(counts[cells_g].max()), 1)
            cand = np.argsort(~cand_mask[cells_g], axis=1, kind="stable")[:, :kmax]
            cvalid = np.arange(kmax)[None] < counts[cells_g][:, None]
            local = np.full(c1 - c0, -1)
            local[cells_g] = np.arange(len(cells_g))
            qi = order[bounds[c0]:bounds[c1]]
            qi = qi[local[inv[qi] - c0] >= 0]
            cell_of_q = local[inv[qi] - c0]
            cq, vq = cand[cell_of_q], cvalid[cell_of_q]
            d = np.where(vq, _quirky_lane_distance_cols(uq[qi], cols, cq), np.inf)
            best[qi] = cq[np.arange(len(qi)), np.argmin(d, axis=1)]
    return keep[best[q_of]] // (p - 1)


def traffic_light_violation(xy, valid, evaluated, lanes, signals) -> np.ndarray:
    """Red-light violations [B, E, T] of the evaluated agents over the full trajectory (xy
    [B, A, T, 2]); all False without lanes or signals. A violation at t: the agent's nearest lane
    (official lane distance, quirks kept) has a STOP / ARROW_STOP signal at t, and the agent went
    from behind the stop point (t-1) to beyond it (t) along that lane's stop-point segment."""
    e = evaluated
    exy = xy[:, e]  # [B, E, T, 2]
    b, ne, t, _ = exy.shape
    out = np.zeros((b, ne, t), bool)
    if lanes is None or signals is None or not len(signals.lane_ids):
        return out
    lane_of = _nearest_lane(exy.reshape(-1, 2), lanes).reshape(b, ne, t)
    current_lane_id = lanes.ids[lane_of]  # [B, E, T]
    nl, p, _ = lanes.points.shape
    for j, lane_id in enumerate(signals.lane_ids):
        match = np.flatnonzero(lanes.ids == lane_id)
        if not len(match):
            continue
        stop_state = np.isin(signals.states[:, j], STOP_STATES)  # [T]
        if not stop_state.any():
            continue
        li = int(match[0])
        pts, pv = lanes.points[li], lanes.point_valid[li]
        stop = signals.stop_points[j]
        d = _quirky_lane_distance(stop[None], pts[:-1], pts[1:])
        d = np.where(pv[:-1], d, geometry.EXTREMELY_LARGE_DISTANCE_M)
        s = int(np.argmin(d))
        a0, a1 = pts[s], pts[s + 1]
        se = a1 - a0
        len2 = float(se @ se)
        stop_t = float((stop - a0) @ se) / len2 if len2 > 0 else 0.0
        obj_t = ((exy - a0) @ se) / len2 if len2 > 0 else np.zeros(exy.shape[:-1])
        behind = obj_t < stop_t
        ahead = obj_t > stop_t
        crossed = np.zeros((b, ne, t), bool)
        crossed[..., 1:] = behind[..., :-1] & ahead[..., 1:]
        out |= valid[:, e] & (current_lane_id == lane_id) & stop_state[None, None] & crossed
    return out


# -------------------------------------------------------------------------------- features
def compute_features(scene: LoggedScene, rollouts: Rollouts | None = None, traffic_lights: bool = True) -> Features:
    """Features of the log (``rollouts`` None: B = 1, logged validity) or of aligned rollouts (B = R)."""
    pos, heading, size, valid = _trajectories(scene, rollouts)
    e = scene.evaluated
    length, width, height = size[..., 0], size[..., 1], size[..., 2]
    speed, accel, dh, d2h = kinematic_features(pos[:, e][..., 0], pos[:, e][..., 1], pos[:, e][..., 2], heading[:, e])
    fut = _FUTURE
    # interactive and map features only on the simulated steps (every step is independent of the
    # others for them, except TTC speeds which use the neighbouring steps: computed on all steps)
    dist = distance_to_nearest_object(pos[:, :, fut, :2], length[:, :, fut], width[:, :, fut], heading[:, :, fut],
                                      valid[:, :, fut], e)
    ttc = time_to_collision(pos[..., :2], length, width, heading, valid, e)[..., fut]
    road = distance_to_road_edge(pos[:, :, fut], length[:, :, fut], width[:, :, fut], height[:, :, fut],
                                 heading[:, :, fut], valid[:, :, fut], e, scene.road_edges)
    tlv = None
    if traffic_lights:
        tsl = slice(CURRENT_STEP, NUM_STEPS)
        tlv = traffic_light_violation(pos[:, :, tsl, :2], valid[:, :, tsl], e, scene.lanes, _signals_window(scene, tsl))[..., 1:]
    # displacement error against the log, over all 91 steps where the log is valid
    log_valid = scene.valid[e]  # [E, 91]
    err = np.sqrt(((pos[:, e] - scene.position[None, e]) ** 2).sum(-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        ade = np.where(log_valid[None], err, 0.0).sum(-1) / log_valid.sum(-1)[None]
    out_valid = (scene.valid[e] if rollouts is None else np.ones_like(scene.valid[e]))[None, :, fut]
    return Features(
        valid=np.broadcast_to(out_valid, dist.shape),
        linear_speed=speed[..., fut], linear_acceleration=accel[..., fut],
        angular_speed=dh[..., fut], angular_acceleration=d2h[..., fut],
        distance_to_nearest_object=dist, collision_per_step=dist < 0.0,
        time_to_collision=ttc, distance_to_road_edge=road, offroad_per_step=road > 0.0,
        traffic_light_violation_per_step=tlv, ade=ade,
    )


def _signals_window(scene: LoggedScene, window: slice):
    sig = scene.signals
    if sig is None:
        return None
    return Signals(sig.lane_ids, sig.states[window], sig.stop_points)
