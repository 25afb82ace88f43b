"""SUMO traffic, its parked cars: static vehicles along the kerbs of a recording
(:func:`add_parked_vehicles`), dropped where they would overlap a recorded agent or each other.
Re-exported by :mod:`.sumo_sim`.
"""

from __future__ import annotations

import math

import numpy as np

from ..scenario import AgentType, wrap_angle
from .sumo_lanes import lane_shape, quantize, rotation_matrix
from .sumo_run import Recording


PARKED_SLOT_M = 7.0  # kerb length per parked-car slot
PARKED_END_MARGIN_M = 10.0  # no parked car within this distance of either end of an edge (junctions, crossings)
PARKED_GAP_M = 0.25  # between the kerbside lane's edge and a parked car's side
PARKED_MIN_SPACING_M = 5.5  # between two parked cars' centres (kerbs meet at corners and across narrow roads)
PARKED_CLEARANCE_M = 0.3  # a car is dropped where an agent's centre comes within its half width plus this of it


def add_parked_vehicles(rec: Recording, net, rotation_rad: float, occupancy: float, rng: np.random.Generator) -> Recording:
    """``rec`` with parked cars added: static vehicles, valid on every recorded frame, beside the
    kerbside lane (the rightmost lane of the map: one that cars or bicycles may use) of every normal
    edge, one per :data:`PARKED_SLOT_M` slot with probability ``occupancy`` (none within
    :data:`PARKED_END_MARGIN_M` of an edge's ends), their side :data:`PARKED_GAP_M` past the lane's
    edge, parallel to it with a little jitter. SUMO's traffic never sees them (they are outside its
    lanes), so a car is dropped wherever a recorded agent (a walker on the sidewalk, a vehicle cutting
    the kerb) comes near it on any frame: its centre within its half width plus
    :data:`PARKED_CLEARANCE_M` of the car's box. Real WOMD scenes are mostly parked cars
    (``benchmarks/scene_statistics.py``: ``vehicle_parked_share`` 0.68, generated scenes without them
    0.28); the README's "Parked cars" section has what they change."""
    if occupancy <= 0.0:
        return rec
    rot = rotation_matrix(rotation_rad)
    rows = []  # (x, y, z, heading, length, width, height)
    for edge in net.getEdges():
        if edge.getFunction() not in ("", "normal"):
            continue
        kerb = next((lane for lane in edge.getLanes() if lane.allows("passenger") or lane.allows("bicycle")), None)
        if kerb is None:
            continue
        pts = lane_shape(kerb)
        pts[:, :2] = pts[:, :2] @ rot.T
        seg = np.diff(pts, axis=0)
        seg_len = np.linalg.norm(seg[:, :2], axis=1)
        cum = np.concatenate([[0.0], np.cumsum(seg_len)])
        usable = cum[-1] - 2 * PARKED_END_MARGIN_M
        if usable < PARKED_SLOT_M:
            continue
        slots = PARKED_END_MARGIN_M + (np.arange(int(usable // PARKED_SLOT_M)) + 0.5) * PARKED_SLOT_M
        slots = slots[rng.random(len(slots)) < occupancy]
        for u in slots + rng.uniform(-0.8, 0.8, len(slots)):
            i = int(np.clip(np.searchsorted(cum, u) - 1, 0, len(seg) - 1))
            if seg_len[i] < 1e-6:
                continue
            t = seg[i, :2] / seg_len[i]
            length, width, height = rng.uniform(4.0, 5.2), rng.uniform(1.75, 2.0), rng.uniform(1.4, 1.8)
            offset = kerb.getWidth() / 2 + PARKED_GAP_M + width / 2 + rng.uniform(-0.1, 0.2)
            at = pts[i] + (u - cum[i]) / seg_len[i] * seg[i]
            rows.append((at[0] + t[1] * offset, at[1] - t[0] * offset, at[2] + height / 2,  # to the right of travel
                         math.atan2(t[1], t[0]) + rng.normal(0.0, 0.03), length, width, height))
    if not rows:
        return rec
    car = np.array(rows)  # (P, 7)
    keep = _clear_of_agents(car, rec) & _clear_of_each_other(car)
    car = car[keep]
    if not len(car):
        return rec
    p, t = len(car), rec.valid.shape[1]
    center = quantize(np.broadcast_to(car[:, None, :3], (p, t, 3)))
    return Recording(
        sumo_ids=rec.sumo_ids + [f"parked{k}" for k in range(p)],
        types=np.concatenate([rec.types, np.full(p, AgentType.VEHICLE, np.int8)]),
        size=np.concatenate([rec.size, car[:, 4:7]]),
        center=np.concatenate([rec.center, center]),
        heading=np.concatenate([rec.heading, np.broadcast_to(wrap_angle(car[:, 3:4]), (p, t))]),
        velocity=np.concatenate([rec.velocity, np.zeros((p, t, 2))]),
        speed=np.concatenate([rec.speed, np.zeros((p, t))]),
        valid=np.concatenate([rec.valid, np.ones((p, t), bool)]),
        signal_states=rec.signal_states, start_time_s=rec.start_time_s)


def _clear_of_agents(car: np.ndarray, rec: Recording) -> np.ndarray:
    """[P] whether no recorded agent's centre comes within its half width plus the clearance of each
    parked car's box (car rows as in :func:`add_parked_vehicles`) on any valid frame."""
    ok = np.ones(len(car), bool)
    xy = np.where(rec.valid[..., None], rec.center[..., :2], np.nan)  # (A, T, 2)
    lo, hi = np.nanmin(xy, axis=1), np.nanmax(xy, axis=1)  # (A, 2) each agent's extent
    reach = 0.5 * rec.size[:, 1] + PARKED_CLEARANCE_M  # (A,)
    for k, (x, y, _, heading, length, width, _) in enumerate(car):
        r = 0.5 * math.hypot(length, width) + reach
        near = np.flatnonzero(np.all((lo - r[:, None] <= (x, y)) & ((x, y) <= hi + r[:, None]), axis=1))
        if not len(near):
            continue
        d = xy[near] - (x, y)  # (n, T, 2)
        c, s = math.cos(heading), math.sin(heading)
        along, across = d[..., 0] * c + d[..., 1] * s, -d[..., 0] * s + d[..., 1] * c
        inside = (np.abs(along) < 0.5 * length + reach[near, None]) & (np.abs(across) < 0.5 * width + reach[near, None])
        ok[k] = not inside.any()
    return ok


def _clear_of_each_other(car: np.ndarray) -> np.ndarray:
    """[P] keeps a parked car unless an earlier kept one's centre is within :data:`PARKED_MIN_SPACING_M`
    of its own."""
    keep = np.zeros(len(car), bool)
    for k in range(len(car)):
        kept = car[keep]
        keep[k] = not len(kept) or bool(np.min(np.linalg.norm(kept[:, :2] - car[k, :2], axis=1)) >= PARKED_MIN_SPACING_M)
    return keep
