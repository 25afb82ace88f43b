"""Traffic statistics of a set of scenes: how real logs and generated scenes compare.

Stage: a check beside the sources (Scenario -> numbers). Pure numpy functions of a
:class:`~smart_marl.Scenario` that say what its traffic and its map look like, so that a generator
(:mod:`.sumo`) can be tuned toward real logs. ``benchmarks/scene_statistics.py`` prints them for
several sets of scenes side by side.

:func:`scene_samples` turns one scene into named samples; :class:`StatisticsAccumulator` pools them
over scenes and :meth:`~StatisticsAccumulator.summary` reduces each to numbers. Every statistic is
listed in :data:`STATISTICS` with its kind:

* ``distribution``: a float sample per item (frame, vehicle, lane point...) -> p10, p50, p90, mean;
* ``share``: a boolean per item -> the share that is true;
* ``rate``: a pair (count, exposure) per item -> sum(count) / sum(exposure).

Conventions (the same for every source, so that the columns compare):

* **Speed** is measured from the box centres, not from the source's velocity field: central
  differences of positions (one-sided at a track's ends), then a centred moving average over
  :data:`SPEED_SMOOTHING_FRAMES` valid frames (0.5 s). Longitudinal **acceleration** is the central
  difference of that smoothed speed over +-2 frames (0.4 s), **jerk** the same difference of the
  acceleration; a value exists only where every frame it uses is valid.
* A vehicle is **stopped** below :data:`STOPPED_MPS` (0.5 m/s) and **moving** above
  :data:`MOVING_MPS` (2 m/s); the slow-down statistics follow the vehicles faster than
  :data:`FAST_MPS` (5 m/s) at the scene's current frame for the next 4 and 8 s.
* The **leader** of a vehicle is the nearest vehicle whose centre is ahead of it (in its heading's
  frame) within a corridor of +-:data:`LEADER_CORRIDOR_M` laterally, heading within 45 degrees;
  the **gap** is bumper to bumper (centre distance minus half of both lengths), the **time
  headway** the gap over the follower's speed. Leaders farther than :data:`LEADER_RANGE_M` count as
  none. Sampled every 5 frames. On curves a straight corridor misses some leaders.
* **Lane changes** are found from the geometry of the lane centre lines only (GPUDrive/Nocturne
  maps have no lane topology): each moving vehicle frame is matched to the nearest lane centre line
  within :data:`LANE_MATCH_M` whose direction is within 30 degrees of the heading; a switch from
  lane a to lane b moves the vehicle one lane to the side when, where it switched, b runs
  alongside a (directions within 15 degrees) 2-6 m to its side (a successor lane
  starts where its predecessor ends: 0 m; diverging lanes part slowly); lane positions held less
  than 1 s are dropped (a brief swerve). Lanes cut into short pieces (WOMD's, and SUMO's with
  ``max_lane_piece_m``) count the same as whole ones.
* The **yaw rate** is the wrapped heading difference of consecutive valid frames over 0.1 s,
  averaged over 5 frames, on moving frames; **turning** is a yaw rate above 0.1 rad/s.
* **Density** and the map counts are taken within :data:`NEAR_SDC_M` (50 m) of the self-driving
  car at the current frame, so that scenes cut with different radii compare; scenes without a
  self-driving car (Nocturne JSON) have none of these samples.
* **Lane width** is the lateral distance from a lane's centre line to the nearest other lane
  centre line beside it in the same direction (within 10 degrees, 1.5-6 m away), sampled every
  2 m; **curvature** is the heading change over +-2 m of a lane resampled every metre, per metre of
  lane (bicycle lanes left out of both).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..geometry import frame_steps
from ..scenario import DT_S, AgentType, LaneType, MapFeatureType, Scenario, wrap_angle

STOPPED_MPS = 0.5
MOVING_MPS = 2.0
FAST_MPS = 5.0
SPEED_SMOOTHING_FRAMES = 5
LEADER_CORRIDOR_M = 1.8
LEADER_RANGE_M = 60.0
LANE_MATCH_M = 3.0
NEAR_SDC_M = 50.0
TURNING_RAD_PER_S = 0.1

# name -> (kind, description). The order is the table's.
STATISTICS: dict[str, tuple[str, str]] = {
    "scene_duration_s": ("distribution", "scene duration"),
    "vehicles_per_scene": ("distribution", "vehicles valid at the current frame"),
    "pedestrians_per_scene": ("distribution", "pedestrians valid at the current frame"),
    "cyclists_per_scene": ("distribution", "cyclists valid at the current frame"),
    "vehicles_within_50m_of_sdc": ("distribution", "vehicles within 50 m of the SDC (current frame)"),
    "pedestrians_within_50m_of_sdc": ("distribution", "pedestrians within 50 m of the SDC (current frame)"),
    "cyclists_within_50m_of_sdc": ("distribution", "cyclists within 50 m of the SDC (current frame)"),
    "moving_vehicles_within_50m_of_sdc": ("distribution", "vehicles within 50 m of the SDC that move (> 2 m/s) in the scene"),
    "vehicle_speed_mps": ("distribution", "vehicle speed, all valid frames"),
    "vehicle_speed_moving_mps": ("distribution", "vehicle speed, frames above 2 m/s"),
    "vehicle_accel_mps2": ("distribution", "vehicle longitudinal acceleration, moving frames"),
    "vehicle_abs_jerk_mps3": ("distribution", "vehicle |jerk|, moving frames"),
    "vehicle_hard_brake_share": ("share", "moving frames braking harder than 2 m/s^2"),
    "vehicle_stopped_time_share": ("share", "vehicle frames below 0.5 m/s"),
    "vehicle_stopped_time_share_of_movers": ("share", "frames below 0.5 m/s of vehicles that move (> 2 m/s) in the scene"),
    "vehicle_parked_share": ("share", "vehicles (valid >= 2 s) never above 2 m/s"),
    "vehicle_moving_then_stops_share": ("share", "vehicles above 2 m/s at some frame that are below 0.5 m/s at another"),
    "fast_vehicle_stops_within_8s_share": ("share", "vehicles > 5 m/s at the current frame that stop (< 0.5 m/s) in the next 8 s"),
    "fast_vehicle_speed_ratio_4s": ("distribution", "speed 4 s after the current frame / speed at it (vehicles > 5 m/s)"),
    "fast_vehicle_speed_ratio_8s": ("distribution", "speed 8 s after the current frame / speed at it (vehicles > 5 m/s)"),
    "fast_vehicle_speeds_up_20pct_8s_share": ("share", "vehicles > 5 m/s whose speed 8 s later is > 120% of it"),
    "fast_vehicle_slows_20pct_8s_share": ("share", "vehicles > 5 m/s whose speed 8 s later is < 80% of it"),
    "fast_vehicle_slows_50pct_8s_share": ("share", "vehicles > 5 m/s whose speed 8 s later is < 50% of it"),
    "sdc_speed_mps": ("distribution", "SDC speed at the current frame"),
    "sdc_speed_ratio_8s": ("distribution", "SDC speed 8 s later / at the current frame (SDC > 5 m/s)"),
    "has_leader_share": ("share", "moving vehicle frames with a leader within 60 m"),
    "leader_gap_m": ("distribution", "bumper gap to the leader (within 60 m)"),
    "time_headway_s": ("distribution", "time headway to the leader (within 60 m)"),
    "lane_changes_per_vehicle_minute": ("rate", "lane changes per minute of moving vehicle time"),
    "vehicle_abs_yaw_rate_radps": ("distribution", "|yaw rate| of moving vehicles"),
    "vehicle_turning_share": ("share", "moving vehicle frames with |yaw rate| > 0.1 rad/s"),
    "pedestrian_speed_mps": ("distribution", "pedestrian speed, all valid frames"),
    "pedestrian_moving_share": ("share", "pedestrian frames above 0.5 m/s"),
    "pedestrian_abs_yaw_rate_radps": ("distribution", "|yaw rate| of walking pedestrians (heading change over 0.5 s)"),
    "cyclist_speed_mps": ("distribution", "cyclist speed, all valid frames"),
    "cyclist_moving_share": ("share", "cyclist frames above 0.5 m/s"),
    "lanes_within_50m_of_sdc": ("distribution", "lane centre lines with a point within 50 m of the SDC"),
    "signal_lanes_within_50m_of_sdc": ("distribution", "lanes with a traffic light within 50 m of the SDC"),
    "stop_signs_within_50m_of_sdc": ("distribution", "stop signs within 50 m of the SDC"),
    "lane_width_m": ("distribution", "lateral distance to the next lane centre line in the same direction"),
    "lane_abs_curvature_per_m": ("distribution", "|curvature| of lane centre lines, per metre of lane"),
    "lane_sharp_curve_share": ("share", "metres of lane with a radius below 50 m"),
    "lane_length_m": ("distribution", "length of a lane centre-line feature"),
    "lane_speed_limit_mph": ("distribution", "lane speed limit where the source has one"),
}


# --------------------------------------------------------------------------------- kinematics
def _masked_window_mean(values: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Centred mean of ``values`` [A, T] over ``window`` frames, valid frames only (0 where none)."""
    k = window // 2
    w = valid.astype(np.float64)
    cs = np.cumsum(np.pad(np.where(valid, values, 0.0), ((0, 0), (k + 1, k))), axis=1)
    cw = np.cumsum(np.pad(w, ((0, 0), (k + 1, k))), axis=1)
    total = cw[:, window:] - cw[:, :-window]
    return np.where(valid, (cs[:, window:] - cs[:, :-window]) / np.maximum(total, 1.0), 0.0)


def speed_from_positions_mps(position_xy: np.ndarray, valid: np.ndarray, dt_s: float = DT_S,
                             smoothing_frames: int = SPEED_SMOOTHING_FRAMES) -> np.ndarray:
    """Speed [A, T] from box centres [A, T, 2]: central differences where both neighbours are valid,
    one-sided where one is, then a centred moving average over ``smoothing_frames`` valid frames.
    0 where invalid (and where a frame has no valid neighbour)."""
    step, has = frame_steps(np.asarray(position_xy, np.float64), valid)
    raw = np.linalg.norm(step, axis=-1) / dt_s
    return _masked_window_mean(raw, has, smoothing_frames)


def central_difference(values: np.ndarray, valid: np.ndarray, half_span: int = 2,
                       dt_s: float = DT_S) -> tuple[np.ndarray, np.ndarray]:
    """(d values / dt, where it exists) [A, T]: (v[t + h] - v[t - h]) / (2 h dt) where every frame
    from t - h to t + h is valid."""
    values = np.asarray(values, np.float64)
    a, t = values.shape
    out = np.zeros((a, t))
    ok = np.zeros((a, t), bool)
    if t <= 2 * half_span:
        return out, ok
    run = np.ones((a, t - 2 * half_span), bool)
    for k in range(2 * half_span + 1):
        run &= valid[:, k:t - 2 * half_span + k]
    out[:, half_span:t - half_span] = (values[:, 2 * half_span:] - values[:, :t - 2 * half_span]) / (2 * half_span * dt_s)
    ok[:, half_span:t - half_span] = run
    return np.where(ok, out, 0.0), ok


def yaw_rate_radps(heading: np.ndarray, valid: np.ndarray, dt_s: float = DT_S, window: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(yaw rate [A, T], where it exists): wrapped heading differences of consecutive valid frames
    over ``dt_s``, averaged over ``window`` of them."""
    heading = np.asarray(heading, np.float64)
    both = valid[:, 1:] & valid[:, :-1]
    rate = np.where(both, wrap_angle(np.diff(heading, axis=1)) / dt_s, 0.0)
    smooth = _masked_window_mean(rate, both, window)
    out = np.zeros(heading.shape)
    ok = np.zeros(heading.shape, bool)
    out[:, 1:] = smooth
    ok[:, 1:] = both
    return out, ok


# --------------------------------------------------------------------------------- leaders
def leader_gaps(position_xy: np.ndarray, heading: np.ndarray, length_m: np.ndarray, valid: np.ndarray,
                corridor_m: float = LEADER_CORRIDOR_M, range_m: float = LEADER_RANGE_M,
                max_heading_diff_rad: float = np.pi / 4) -> np.ndarray:
    """For each vehicle [A] at one frame: the bumper gap (m) to its leader (see the module docstring),
    ``inf`` when there is none within ``range_m``. ``position_xy`` [A, 2], ``heading`` [A],
    ``length_m`` [A], ``valid`` [A]."""
    xy = np.asarray(position_xy, np.float64)
    h = np.asarray(heading, np.float64)
    d = xy[None, :, :] - xy[:, None, :]  # [i, j, 2]: j seen from i
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    lon = c * d[..., 0] + s * d[..., 1]
    lat = -s * d[..., 0] + c * d[..., 1]
    same_way = np.abs(wrap_angle(h[None, :] - h[:, None])) < max_heading_diff_rad
    gap = lon - 0.5 * (length_m[:, None] + length_m[None, :])
    ok = (valid[:, None] & valid[None, :] & ~np.eye(len(h), dtype=bool) & (lon > 0) & (np.abs(lat) < corridor_m)
          & same_way & (gap <= range_m))
    gap = np.where(ok, np.maximum(gap, 0.0), np.inf)
    return gap.min(axis=1) if len(h) else np.zeros(0)


# --------------------------------------------------------------------------------- lanes
def _vehicle_lanes(scenario: Scenario) -> list[np.ndarray]:
    """The centre lines [n, 2] (float64) of the map's lanes that are not bicycle lanes."""
    rm = scenario.road_map
    out = []
    for i in rm.indices_of(MapFeatureType.LANE):
        if rm.subtypes[i] == LaneType.BIKE_LANE:
            continue
        pts = rm.feature_points(i)[:, :2].astype(np.float64)
        if len(pts) >= 2:
            out.append(pts)
    return out


def resample_polyline(points: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points every ``spacing_m`` metres of arc length along a polyline [n, 2] (its start included)."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return points[:1]
    at = np.arange(0.0, s[-1] + 1e-9, spacing_m)
    return np.stack([np.interp(at, s, points[:, 0]), np.interp(at, s, points[:, 1])], axis=1)


def _segment_table(lanes: list[np.ndarray]):
    """Every segment of every lane: start [S, 2], end [S, 2], lane index [S], unit direction [S, 2]."""
    starts = np.concatenate([p[:-1] for p in lanes])
    ends = np.concatenate([p[1:] for p in lanes])
    lane_of = np.concatenate([np.full(len(p) - 1, k) for k, p in enumerate(lanes)])
    vec = ends - starts
    length = np.linalg.norm(vec, axis=1)
    keep = length > 1e-6
    starts, ends, lane_of, vec, length = starts[keep], ends[keep], lane_of[keep], vec[keep], length[keep]
    return starts, ends, lane_of, vec / length[:, None]


def _project(q: np.ndarray, starts: np.ndarray, ends: np.ndarray):
    """Distance [Q, S] from points [Q, 2] to segments and the projection parameter in [0, 1]."""
    ab = ends - starts
    t = ((q[:, None] - starts[None]) * ab[None]).sum(-1) / np.maximum((ab ** 2).sum(-1), 1e-12)[None]
    t = np.clip(t, 0.0, 1.0)
    foot = starts[None] + t[..., None] * ab[None]
    return np.linalg.norm(q[:, None] - foot, axis=-1), t


def match_lanes(xy: np.ndarray, heading: np.ndarray, lanes: list[np.ndarray], max_dist_m: float = LANE_MATCH_M,
                max_heading_diff_rad: float = np.radians(30.0), segments=None, chunk: int = 32) -> np.ndarray:
    """For each point [Q, 2] with a heading [Q]: the index of the nearest lane centre line within
    ``max_dist_m`` whose local direction is within ``max_heading_diff_rad`` of the heading, -1 if none.
    ``segments``: ``_segment_table(lanes)`` when the caller has it already."""
    if not lanes or not len(xy):
        return np.full(len(xy), -1)
    starts, ends, lane_of, unit = segments if segments is not None else _segment_table(lanes)
    seg_lo, seg_hi = np.minimum(starts, ends), np.maximum(starts, ends)
    out = np.full(len(xy), -1)
    direction = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    for c in range(0, len(xy), chunk):
        q = xy[c:c + chunk]
        lo, hi = q.min(axis=0) - max_dist_m, q.max(axis=0) + max_dist_m
        near = np.flatnonzero((seg_lo <= hi).all(axis=1) & (seg_hi >= lo).all(axis=1))
        if not len(near):
            continue
        dist, _ = _project(q, starts[near], ends[near])
        aligned = direction[c:c + chunk] @ unit[near].T >= np.cos(max_heading_diff_rad)
        dist = np.where(aligned & (dist <= max_dist_m), dist, np.inf)
        k = dist.argmin(axis=1)
        found = np.isfinite(dist[np.arange(len(k)), k])
        out[c:c + chunk] = np.where(found, lane_of[near[k]], -1)
    return out


def _foot_on_lane(q: np.ndarray, lane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nearest point, unit direction there) of a lane centre line [n, 2] to a point [2]."""
    starts, ends = lane[:-1], lane[1:]
    dist, t = _project(q[None], starts, ends)
    k = int(dist[0].argmin())
    seg = ends[k] - starts[k]
    return starts[k] + t[0, k] * seg, seg / max(float(np.linalg.norm(seg)), 1e-12)


def count_lane_changes(lane_index: np.ndarray, xy: np.ndarray, lanes: list[np.ndarray], min_run_frames: int = 10,
                       min_sep_m: float = 2.0, max_sep_m: float = 6.0,
                       max_heading_diff_rad: float = np.radians(15.0)) -> int:
    """Lane changes in one vehicle's sequence of matched lanes [T] (-1: unmatched or not counted) with
    its positions [T, 2] (see the module docstring). Each switch from lane a to lane b moves the
    vehicle's lane position one to the left or right when b runs alongside a (directions within
    ``max_heading_diff_rad``) ``min_sep_m``-``max_sep_m`` to its side, measured across a's direction
    between the vehicle's nearest points on a and b; any other switch (a successor, which starts where
    its predecessor ends, a lane cut into pieces as WOMD's are, diverging lanes) leaves it. Lane
    positions held less than ``min_run_frames`` matched frames (a brief swerve) are dropped; the lane
    changes are the steps between the positions that remain."""
    position, current, previous = [], 0, -1
    for t in np.flatnonzero(np.asarray(lane_index) >= 0):
        k = int(lane_index[t])
        if previous >= 0 and k != previous:
            foot_a, unit_a = _foot_on_lane(xy[t], lanes[previous])
            foot_b, unit_b = _foot_on_lane(xy[t], lanes[k])
            if float(unit_a @ unit_b) >= np.cos(max_heading_diff_rad):
                d = foot_b - foot_a
                side = float(unit_a[0] * d[1] - unit_a[1] * d[0])  # > 0: b is on a's left
                if min_sep_m <= abs(side) <= max_sep_m:
                    current += 1 if side > 0 else -1
        position.append(current)
        previous = k
    kept = []  # lane positions held at least min_run_frames
    t = 0
    while t < len(position):
        u = t
        while u < len(position) and position[u] == position[t]:
            u += 1
        if u - t >= min_run_frames and not (kept and kept[-1] == position[t]):
            kept.append(position[t])
        t = u
    return int(sum(abs(b - a) for a, b in zip(kept[:-1], kept[1:])))


def lane_widths_m(lanes: list[np.ndarray], spacing_m: float = 2.0, min_m: float = 1.5, max_m: float = 6.0,
                  max_heading_diff_rad: float = np.radians(10.0), chunk: int = 16) -> np.ndarray:
    """Lane width samples: from points every ``spacing_m`` along each lane, the lateral distance to the
    nearest other lane's centre line beside it in the same direction (between ``min_m`` and ``max_m``)."""
    if len(lanes) < 2:
        return np.zeros(0)
    lanes = [resample_polyline(p, 1.0) for p in lanes]
    lanes = [p for p in lanes if len(p) >= 2]
    if len(lanes) < 2:
        return np.zeros(0)
    starts, ends, lane_of, unit = _segment_table(lanes)
    seg_lo, seg_hi = np.minimum(starts, ends), np.maximum(starts, ends)
    out = []
    for k, lane in enumerate(lanes):
        step = max(int(round(spacing_m)), 1)
        q = lane[:-1:step]
        d_q = unit[lane_of == k][::step][: len(q)]  # lane resampled every metre: its segment k starts at point k
        q = q[: len(d_q)]
        for c in range(0, len(q), chunk):
            qc, dc = q[c:c + chunk], d_q[c:c + chunk]
            lo, hi = qc.min(axis=0) - max_m, qc.max(axis=0) + max_m
            near = (lane_of != k) & (seg_lo <= hi).all(axis=1) & (seg_hi >= lo).all(axis=1)
            if not near.any():
                continue
            dist, _ = _project(qc, starts[near], ends[near])
            aligned = dc @ unit[near].T >= np.cos(max_heading_diff_rad)
            dist = np.where(aligned & (dist >= min_m) & (dist <= max_m), dist, np.inf)
            best = dist.min(axis=1)
            out.append(best[np.isfinite(best)])
    return np.concatenate(out) if out else np.zeros(0)


def lane_curvatures_per_m(lane: np.ndarray, half_span_m: float = 2.0) -> np.ndarray:
    """|curvature| (1/m) along a lane resampled every metre: the heading change over +-``half_span_m``
    divided by its arc length. Empty for lanes shorter than 2 * half_span_m + 1 m."""
    q = resample_polyline(lane, 1.0)
    h = int(round(half_span_m))
    if len(q) < 2 * h + 2:
        return np.zeros(0)
    seg = np.diff(q, axis=0)
    heading = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    return np.abs(heading[2 * h:] - heading[:-2 * h]) / (2 * h)


def polyline_length_m(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points[:, :2], axis=0), axis=1).sum())


# --------------------------------------------------------------------------------- one scene
def _population_samples(put, scenario: Scenario, xy: np.ndarray, valid: np.ndarray, speed: np.ndarray, veh: np.ndarray,
                        ped: np.ndarray, cyc: np.ndarray, dt: float) -> None:
    """The scene's duration and its agents at the current frame: in the scene, and within 50 m of the self-driving car."""
    cur = scenario.current_frame
    put("scene_duration_s", [scenario.num_frames * dt])
    at_cur = valid[:, cur]
    put("vehicles_per_scene", [int((veh & at_cur).sum())])
    put("pedestrians_per_scene", [int((ped & at_cur).sum())])
    put("cyclists_per_scene", [int((cyc & at_cur).sum())])
    sdc = scenario.sdc_index
    if 0 <= sdc < scenario.tracks.num_tracks and valid[sdc, cur]:
        d = np.linalg.norm(xy[:, cur] - xy[sdc, cur], axis=-1)
        near = at_cur & (d <= NEAR_SDC_M)
        near[sdc] = False
        put("vehicles_within_50m_of_sdc", [int((near & veh).sum())])
        put("pedestrians_within_50m_of_sdc", [int((near & ped).sum())])
        put("cyclists_within_50m_of_sdc", [int((near & cyc).sum())])
        movers = (valid & (speed > MOVING_MPS)).any(axis=1)
        put("moving_vehicles_within_50m_of_sdc", [int((near & veh & movers).sum())])


def _vehicle_motion_samples(put, v_speed: np.ndarray, v_valid: np.ndarray, moving: np.ndarray, dt: float) -> None:
    """Vehicles' speeds, accelerations, jerks, hard brakes, stopped time and parked or stopping vehicles."""
    put("vehicle_speed_mps", v_speed[v_valid])
    put("vehicle_speed_moving_mps", v_speed[moving])
    accel, accel_ok = central_difference(v_speed, v_valid, 2, dt)
    jerk, jerk_ok = central_difference(accel, accel_ok, 2, dt)
    put("vehicle_accel_mps2", accel[accel_ok & moving])
    put("vehicle_abs_jerk_mps3", np.abs(jerk[jerk_ok & moving]))
    put("vehicle_hard_brake_share", accel[accel_ok & moving] < -2.0)
    put("vehicle_stopped_time_share", v_speed[v_valid] < STOPPED_MPS)
    long_enough = v_valid.sum(axis=1) >= int(round(2.0 / dt))
    ever_moving = moving.any(axis=1)
    ever_stopped = (v_valid & (v_speed < STOPPED_MPS)).any(axis=1)
    put("vehicle_stopped_time_share_of_movers", v_speed[ever_moving][v_valid[ever_moving]] < STOPPED_MPS)
    put("vehicle_parked_share", ~ever_moving[long_enough])
    put("vehicle_moving_then_stops_share", ever_stopped[ever_moving])


def _slow_down_samples(put, scenario: Scenario, speed: np.ndarray, valid: np.ndarray, v_speed: np.ndarray,
                       v_valid: np.ndarray, has_sdc: bool, dt: float) -> None:
    """How vehicles moving fast at the current frame (and the self-driving car) slow down, stop or speed up 4 and 8 s on."""
    cur, sdc = scenario.current_frame, scenario.sdc_index
    f4, f8 = cur + int(round(4.0 / dt)), cur + int(round(8.0 / dt))
    fast = v_valid[:, cur] & (v_speed[:, cur] > FAST_MPS)
    if f4 < scenario.num_frames:
        ok4 = fast & v_valid[:, f4]
        put("fast_vehicle_speed_ratio_4s", v_speed[ok4, f4] / v_speed[ok4, cur])
    if f8 < scenario.num_frames:
        ok8 = fast & v_valid[:, f8]
        ratio8 = v_speed[ok8, f8] / v_speed[ok8, cur]
        put("fast_vehicle_speed_ratio_8s", ratio8)
        put("fast_vehicle_speeds_up_20pct_8s_share", ratio8 > 1.2)
        put("fast_vehicle_slows_20pct_8s_share", ratio8 < 0.8)
        put("fast_vehicle_slows_50pct_8s_share", ratio8 < 0.5)
        window = slice(cur + 1, f8 + 1)
        seen = fast & (v_valid[:, window].sum(axis=1) >= int(round(4.0 / dt)))
        stops = (v_valid[:, window] & (v_speed[:, window] < STOPPED_MPS)).any(axis=1)
        put("fast_vehicle_stops_within_8s_share", stops[seen])
    if has_sdc and scenario.tracks.types[sdc] == AgentType.VEHICLE:
        put("sdc_speed_mps", [speed[sdc, cur]])
        if f8 < scenario.num_frames and speed[sdc, cur] > FAST_MPS and valid[sdc, f8]:
            put("sdc_speed_ratio_8s", [speed[sdc, f8] / speed[sdc, cur]])


def _leader_samples(put, scenario: Scenario, xy: np.ndarray, valid: np.ndarray, vi: np.ndarray, v_speed: np.ndarray,
                    moving: np.ndarray) -> None:
    """Moving vehicles' leaders every 5 frames: whether there is one, the gap to it and the time headway."""
    if len(vi) <= 1:
        return
    length = scenario.tracks.box_size()[vi, 0].astype(np.float64)
    heading = scenario.tracks.heading[vi].astype(np.float64)
    for t in range(0, scenario.num_frames, 5):
        gap = leader_gaps(xy[vi, t], heading[:, t], length, valid[vi, t])
        follower = moving[:, t]
        put("has_leader_share", np.isfinite(gap[follower]))
        with_leader = follower & np.isfinite(gap)
        put("leader_gap_m", gap[with_leader])
        put("time_headway_s", gap[with_leader] / v_speed[with_leader, t])


def _lane_change_samples(put, scenario: Scenario, xy: np.ndarray, vi: np.ndarray, moving: np.ndarray,
                         lanes: list[np.ndarray], dt: float) -> None:
    """Lane changes per minute of every vehicle moving on at least 10 frames, each frame matched to a lane."""
    if not (lanes and len(vi)):
        return
    rows = []
    heading = scenario.tracks.heading[vi].astype(np.float64)
    segments = _segment_table(lanes)
    for k in range(len(vi)):
        frames = np.flatnonzero(moving[k])
        if len(frames) < 10:
            continue
        matched = np.full(scenario.num_frames, -1)
        matched[frames] = match_lanes(xy[vi[k], frames], heading[k, frames], lanes, segments=segments)
        rows.append((count_lane_changes(matched, xy[vi[k]], lanes), len(frames) * dt / 60.0))
    if rows:
        put("lane_changes_per_vehicle_minute", np.asarray(rows, np.float64).reshape(-1, 2))


def _map_samples(put, scenario: Scenario, xy: np.ndarray, has_sdc: bool, lanes: list[np.ndarray]) -> None:
    """The map: lanes, stop signs and signalled lanes near the self-driving car; lane widths, curvatures, lengths, limits."""
    rm = scenario.road_map
    lane_idx = rm.indices_of(MapFeatureType.LANE)
    if has_sdc:
        center = xy[scenario.sdc_index, scenario.current_frame]
        pts_feature = rm.point_feature_index()
        near_pt = np.linalg.norm(rm.points[:, :2].astype(np.float64) - center, axis=1) <= NEAR_SDC_M
        near_features = np.zeros(rm.num_features, bool)
        near_features[pts_feature[near_pt]] = True
        put("lanes_within_50m_of_sdc", [int(near_features[lane_idx].sum())])
        put("stop_signs_within_50m_of_sdc", [int(near_features[rm.indices_of(MapFeatureType.STOP_SIGN)].sum())])
        tl = scenario.traffic_lights
        if len(tl.lane_ids):
            lit = np.isin(rm.ids, np.asarray(tl.lane_ids)[tl.present.any(axis=0)])
            put("signal_lanes_within_50m_of_sdc", [int((near_features & lit).sum())])
        else:
            put("signal_lanes_within_50m_of_sdc", [0])
    put("lane_width_m", lane_widths_m(lanes))
    curv = [lane_curvatures_per_m(p) for p in lanes]
    curv = np.concatenate(curv) if curv else np.zeros(0)
    put("lane_abs_curvature_per_m", curv)
    put("lane_sharp_curve_share", curv > 1.0 / 50.0)
    put("lane_length_m", [polyline_length_m(rm.feature_points(i)) for i in lane_idx])
    limits = rm.speed_limit_mph[lane_idx]
    put("lane_speed_limit_mph", limits[limits > 0])


def scene_samples(scenario: Scenario) -> dict[str, np.ndarray]:
    """The samples of every statistic of :data:`STATISTICS` that this scene has (see the module
    docstring): float arrays for distributions, boolean arrays for shares, [n, 2] (count, exposure)
    for rates."""
    tr = scenario.tracks
    cur = scenario.current_frame
    dt = float(np.median(np.diff(scenario.timestamps_s))) if scenario.num_frames > 1 else DT_S
    xy = tr.position[..., :2].astype(np.float64)
    valid = np.asarray(tr.valid, bool)
    types = np.asarray(tr.types)
    speed = speed_from_positions_mps(xy, valid, dt)
    out: dict[str, np.ndarray] = {}

    def put(name: str, values) -> None:
        assert name in STATISTICS, name
        values = np.asarray(values)
        if name in out:
            values = np.concatenate([out[name], values])
        out[name] = values

    veh, ped, cyc = (types == kind for kind in (AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST))
    sdc = scenario.sdc_index
    has_sdc = 0 <= sdc < tr.num_tracks and valid[sdc, cur]
    _population_samples(put, scenario, xy, valid, speed, veh, ped, cyc, dt)
    v_speed, v_valid = speed[veh], valid[veh]
    moving = v_valid & (v_speed > MOVING_MPS)
    _vehicle_motion_samples(put, v_speed, v_valid, moving, dt)
    _slow_down_samples(put, scenario, speed, valid, v_speed, v_valid, has_sdc, dt)
    vi = np.flatnonzero(veh)
    _leader_samples(put, scenario, xy, valid, vi, v_speed, moving)
    if len(vi):  # yaw rate and turning (moving frames)
        yaw, yaw_ok = yaw_rate_radps(tr.heading[vi], v_valid, dt)
        m = yaw_ok & moving
        put("vehicle_abs_yaw_rate_radps", np.abs(yaw[m]))
        put("vehicle_turning_share", np.abs(yaw[m]) > TURNING_RAD_PER_S)
    lanes = _vehicle_lanes(scenario)
    _lane_change_samples(put, scenario, xy, vi, moving, lanes, dt)
    # pedestrians and cyclists
    put("pedestrian_speed_mps", speed[ped][valid[ped]])
    put("pedestrian_moving_share", speed[ped][valid[ped]] > STOPPED_MPS)
    if ped.any():
        yaw, yaw_ok = yaw_rate_radps(tr.heading[ped], valid[ped], dt)
        walking = yaw_ok & (speed[ped] > STOPPED_MPS)
        put("pedestrian_abs_yaw_rate_radps", np.abs(yaw[walking]))
    put("cyclist_speed_mps", speed[cyc][valid[cyc]])
    put("cyclist_moving_share", speed[cyc][valid[cyc]] > STOPPED_MPS)
    _map_samples(put, scenario, xy, has_sdc, lanes)
    return out


# --------------------------------------------------------------------------------- pooling
@dataclass
class StatisticsAccumulator:
    """Pools :func:`scene_samples` over scenes; :meth:`summary` reduces them."""

    samples: dict[str, list[np.ndarray]] = field(default_factory=dict)
    scenes: int = 0

    def add(self, scenario: Scenario) -> None:
        for name, values in scene_samples(scenario).items():
            self.samples.setdefault(name, []).append(values)
        self.scenes += 1

    def summary(self, bootstrap: int = 0, seed: int = 0) -> dict[str, dict[str, float]]:
        """Statistic name -> numbers: ``n`` (items) and p10/p50/p90/mean for a distribution, ``share``
        for a share, ``rate`` (and ``exposure``) for a rate. Statistics without samples are left out.

        With ``bootstrap`` > 0, also ``lo`` and ``hi``: a 90% interval of the mean, share or rate
        from that many resamplings of the scenes (with replacement; items of one scene are not
        independent, so the scene is the unit): how far a number may move with other scenes."""
        out: dict[str, dict[str, float]] = {}
        rng = np.random.default_rng(seed)
        for name, (kind, _) in STATISTICS.items():
            parts = [np.asarray(p) for p in self.samples.get(name, []) if len(p)]
            if not parts:
                continue
            values = np.concatenate(parts)
            if kind == "distribution":
                values = values.astype(np.float64)
                p10, p50, p90 = np.percentile(values, [10, 50, 90])
                out[name] = {"n": int(len(values)), "p10": float(p10), "p50": float(p50), "p90": float(p90),
                             "mean": float(values.mean())}
                num = np.array([p.astype(np.float64).sum() for p in parts])
                den = np.array([len(p) for p in parts], np.float64)
                key = "mean"
            elif kind == "share":
                out[name] = {"n": int(len(values)), "share": float(values.astype(bool).mean())}
                num = np.array([p.astype(bool).sum() for p in parts], np.float64)
                den = np.array([len(p) for p in parts], np.float64)
                key = "share"
            else:
                exposure = float(values[:, 1].sum())
                out[name] = {"n": int(len(values)), "exposure": exposure,
                             "rate": float(values[:, 0].sum() / exposure) if exposure > 0 else float("nan")}
                num = np.array([p[:, 0].sum() for p in parts])
                den = np.array([p[:, 1].sum() for p in parts])
                key = "rate"
            if bootstrap > 0:
                pick = rng.integers(0, len(parts), (bootstrap, len(parts)))
                with np.errstate(invalid="ignore", divide="ignore"):
                    resampled = num[pick].sum(axis=1) / den[pick].sum(axis=1)
                resampled = resampled[np.isfinite(resampled)]
                if len(resampled):
                    lo, hi = np.percentile(resampled, [5, 95])
                    out[name].update(lo=float(lo), hi=float(hi), scenes=len(parts))
            assert key in out[name]
        return out


def summarize(scenarios) -> tuple[dict[str, dict[str, float]], int]:
    """(:meth:`StatisticsAccumulator.summary`, number of scenes) of an iterable of Scenarios."""
    acc = StatisticsAccumulator()
    for scenario in scenarios:
        acc.add(scenario)
    return acc.summary(), acc.scenes
