"""SUMO traffic, one run: libsumo at 0.1 s steps with every vehicle and person recorded per step
(:func:`run_simulation` -> :class:`Recording`), SUMO's front-bumper poses turned into box centres and
headings, and random hard stops of moving cars during the run (:class:`EmergencyStops`).
Re-exported by :mod:`.sumo_sim`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..scenario import DT_S, AgentType, wrap_angle
from .sumo_config import SumoConfig
from .sumo_motion import smooth_heading, smooth_walkers, sway_walkers
from .sumo_net import SIGNAL_OF_CHAR, NetworkMap, quantize, require_sumo, rotation_matrix, sumo_binary


_TYPE_OF_VCLASS = {"passenger": AgentType.VEHICLE, "truck": AgentType.VEHICLE, "bus": AgentType.VEHICLE,
                   "delivery": AgentType.VEHICLE, "bicycle": AgentType.CYCLIST, "pedestrian": AgentType.PEDESTRIAN}


@dataclass
class Recording:
    """Every agent's SUMO state on every recorded step, as dense arrays [A, T] (source frame)."""

    sumo_ids: list[str]
    types: np.ndarray  # [A] int8 AgentType
    size: np.ndarray  # [A, 3] length, width, height
    center: np.ndarray  # [A, T, 3] box centre, source frame, quantised
    heading: np.ndarray  # [A, T] radians, source frame
    velocity: np.ndarray  # [A, T, 2] m/s, source frame
    speed: np.ndarray  # [A, T] m/s
    valid: np.ndarray  # [A, T]
    signal_states: dict[int, np.ndarray] = field(default_factory=dict)  # lane id -> [T] SignalState
    start_time_s: float = 0.0


class EmergencyStops:
    """Hard stops of random moving cars during a SUMO run (``SumoConfig.emergency_stop_rate_per_min``): from
    ``start_step`` on, every 0.1 s step each moving car (vehicle class passenger, faster than 3 m/s, not stopping
    already) starts one with probability rate / 600; it brakes at a deceleration drawn from
    ``emergency_decel_mps2`` (SUMO's ``slowDown`` to 0 over v / decel, the car's own decel limits lifted for it),
    stands for a time drawn from ``emergency_hold_s`` and is then released to its car-following model. Its own
    random stream, so the network and demand of a seed do not change with it."""

    def __init__(self, config: SumoConfig, rng: np.random.Generator, start_step: int) -> None:
        self.config, self.rng, self.start_step = config, rng, int(start_step)
        self.until: dict[str, int] = {}  # vehicle -> step at which it is released
        self.p = config.emergency_stop_rate_per_min * DT_S / 60.0

    def step(self, sumo, step: int) -> None:
        for vid, end in list(self.until.items()):
            if step >= end:
                del self.until[vid]
                try:
                    sumo.vehicle.setSpeed(vid, -1.0)
                    sumo.vehicle.setDecel(vid, float(sumo.vehicle.getParameter(vid, "smart_marl.decel") or 4.5))
                except Exception:  # the vehicle has left the network
                    pass
        if step < self.start_step - 50:  # 5 s before recording starts, so that some stops are under way then
            return
        ids = [v for v in sumo.vehicle.getIDList() if v not in self.until]
        if not ids:
            return
        draw = self.rng.random(len(ids)) < self.p
        for vid in np.asarray(ids)[draw]:
            vid = str(vid)
            if sumo.vehicle.getVehicleClass(vid) != "passenger":
                continue
            v = sumo.vehicle.getSpeed(vid)
            if v < 3.0:
                continue
            decel = float(self.rng.uniform(*self.config.emergency_decel_mps2))
            hold = float(self.rng.uniform(*self.config.emergency_hold_s))
            stop_s = v / decel
            sumo.vehicle.setParameter(vid, "smart_marl.decel", str(sumo.vehicle.getDecel(vid)))
            sumo.vehicle.setDecel(vid, decel)
            sumo.vehicle.slowDown(vid, 0.0, stop_s)
            sumo.vehicle.setSpeed(vid, 0.0)
            self.until[vid] = step + int(round((stop_s + hold) / DT_S))


def _sumo_args(net_path: Path, route_path: Path, duration_s: float, seed: int, config: SumoConfig,
               lane_change_s: float) -> list[str]:
    """The SUMO command line of one run: 0.1 s steps, no teleports, collisions only warned of, sublane or lane-change model."""
    args = [sumo_binary("sumo"), "-n", os.fspath(net_path), "-r", os.fspath(route_path), "--step-length", f"{DT_S}",
            "--begin", "0", "--end", f"{duration_s:.1f}", "--seed", str(seed), "--no-step-log", "true",
            "--no-warnings", "true", "--ignore-route-errors", "true", "--time-to-teleport", "-1",
            "--collision.action", "warn", "--collision.check-junctions", "false", "--max-depart-delay", "3",
            "--xml-validation", "never", "--duration-log.disable", "true", "--verbose", "false",
            "--default.speeddev", "0.1"]
    if config.sublane:
        args += ["--lateral-resolution", f"{config.lateral_resolution_m}"]
    else:
        args += ["--lanechange.duration", f"{lane_change_s:.2f}"]
    return args


def _box_centres(front: np.ndarray, heading: np.ndarray, length: np.ndarray, height: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[A, T, 3] box centres from front-bumper centres: half the length back along the heading, half the height up, quantised."""
    center = front.copy()
    center[..., 0] -= 0.5 * length[:, None] * np.cos(heading)
    center[..., 1] -= 0.5 * length[:, None] * np.sin(heading)
    center[..., 2] += 0.5 * height[:, None]  # box centre height
    return quantize(np.where(valid[..., None], center, 0.0))


def _signal_states(tls_ids: list[str], tls_lengths: list[int], signals: list[str], nmap: NetworkMap) -> dict[int, np.ndarray]:
    """Signal states per controlled lane id ([T] SignalState): SUMO link index k of a light -> its k-th state character."""
    signal_states: dict[int, np.ndarray] = {}
    if tls_ids and signals:
        chars = np.frombuffer("".join(signals).encode(), np.uint8).reshape(len(signals), -1)
        column = 0
        for t, n in zip(tls_ids, tls_lengths):
            for link_index, lane_id in enumerate(nmap.signal_links[t][:n]):
                if lane_id >= 0:
                    signal_states[int(lane_id)] = SIGNAL_OF_CHAR[chars[:, column + link_index]]
            column += n
    return signal_states


def run_simulation(net_path: Path, route_path: Path, duration_s: float, record_from_s: float, seed: int,
                   config: SumoConfig, nmap: NetworkMap, rotation_rad: float, lane_change_s: float = 3.0) -> Recording:
    """Run SUMO (libsumo, 0.1 s steps) and record every vehicle and person from ``record_from_s`` on."""
    _, _, libsumo = require_sumo()
    from traci import constants as tc

    args = _sumo_args(net_path, route_path, duration_s, seed, config, lane_change_s)
    variables = (tc.VAR_POSITION3D, tc.VAR_ANGLE, tc.VAR_SPEED)
    libsumo.start(args)
    try:
        tls_ids = [t for t in libsumo.trafficlight.getIDList() if t in nmap.signal_links]
        tls_lengths = [len(libsumo.trafficlight.getRedYellowGreenState(t)) for t in tls_ids]
        index_of: dict[str, int] = {}
        info: list[tuple[int, float, float, float]] = []  # type, length, width, height
        rows_frame: list[int] = []
        rows_agent: list[int] = []
        rows_values: list[tuple] = []
        signals: list[str] = []
        first_record = int(round(record_from_s / DT_S))
        total_steps = int(round(duration_s / DT_S))
        step = 0
        stops = EmergencyStops(config, np.random.default_rng([seed, 0xE5]), first_record) if config.emergency_stop_rate_per_min > 0 else None
        while step < total_steps:
            libsumo.simulationStep()
            step += 1
            if stops is not None:
                stops.step(libsumo, step)
            for vid in libsumo.simulation.getDepartedIDList():
                libsumo.vehicle.subscribe(vid, variables)
            for pid in libsumo.simulation.getDepartedPersonIDList():
                libsumo.person.subscribe(pid, variables)
            if step < first_record:
                continue
            frame = step - first_record
            for domain, prefix in ((libsumo.vehicle, "v:"), (libsumo.person, "p:")):
                for sid, values in domain.getAllSubscriptionResults().items():
                    key = prefix + sid
                    a = index_of.get(key)
                    if a is None:
                        a = index_of[key] = len(info)
                        vclass = domain.getVehicleClass(sid) if prefix == "v:" else "pedestrian"
                        info.append((_TYPE_OF_VCLASS.get(vclass, AgentType.OTHER), domain.getLength(sid),
                                     domain.getWidth(sid), domain.getHeight(sid)))
                    rows_frame.append(frame)
                    rows_agent.append(a)
                    pos = values[tc.VAR_POSITION3D]
                    rows_values.append((pos[0], pos[1], pos[2], values[tc.VAR_ANGLE], values[tc.VAR_SPEED]))
            states = [libsumo.trafficlight.getRedYellowGreenState(t) for t in tls_ids]
            signals.append("".join(st.ljust(n, "O")[:n] for st, n in zip(states, tls_lengths)))
    finally:
        libsumo.close()

    num_frames = total_steps - first_record + 1
    num_agents = len(info)
    fr = np.asarray(rows_frame, np.int64)
    ag = np.asarray(rows_agent, np.int64)
    vals = np.asarray(rows_values, np.float64).reshape(-1, 5)
    info_arr = np.asarray(info, np.float64).reshape(-1, 4)
    valid = np.zeros((num_agents, num_frames), bool)
    valid[ag, fr] = True
    front = np.zeros((num_agents, num_frames, 3))
    front[ag, fr] = vals[:, :3]
    angle = np.zeros((num_agents, num_frames))
    angle[ag, fr] = vals[:, 3]
    speed = np.zeros((num_agents, num_frames))
    speed[ag, fr] = vals[:, 4]
    heading = np.pi / 2 - np.radians(angle) + rotation_rad
    heading = wrap_angle(heading)
    rot = rotation_matrix(rotation_rad)
    front[..., :2] = front[..., :2] @ rot.T
    riders = np.flatnonzero(info_arr[:, 0] != AgentType.PEDESTRIAN)
    heading[riders] = smooth_heading(heading[riders], valid[riders])
    velocity = speed[..., None] * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    peds = np.flatnonzero(info_arr[:, 0] == AgentType.PEDESTRIAN)
    if len(peds):
        front[peds, :, :2], velocity[peds], heading[peds] = smooth_walkers(front[peds, :, :2], valid[peds], heading[peds])
        speed[peds] = np.linalg.norm(velocity[peds], axis=-1)
    cycs = np.flatnonzero(info_arr[:, 0] == AgentType.CYCLIST)
    # (agents, their own random stream, sway m, sway s, jitter rad, jitter s, full sway from this speed)
    for agents, stream, *sway, walking_mps in (
            (peds, 0x5a7, config.walker_sway_m, config.walker_sway_s, config.walker_jitter_rad, config.walker_jitter_s, 1.0),
            (cycs, 0xc7c, config.cyclist_sway_m, config.cyclist_sway_s, 0.0, 0.15, 2.0)):
        if len(agents) and (sway[0] > 0 or sway[2] > 0):
            front[agents, :, :2], velocity[agents], heading[agents] = sway_walkers(
                front[agents, :, :2], valid[agents], heading[agents], np.random.default_rng([seed, stream]), *sway,
                walking_mps=walking_mps)
            speed[agents] = np.linalg.norm(velocity[agents], axis=-1)
    center = _box_centres(front, heading, info_arr[:, 1], info_arr[:, 3], valid)

    signal_states = _signal_states(tls_ids, tls_lengths, signals, nmap)
    return Recording(sumo_ids=list(index_of), types=info_arr[:, 0].astype(np.int8), size=info_arr[:, 1:4],
                     center=center, heading=heading, velocity=velocity, speed=speed, valid=valid, signal_states=signal_states,
                     start_time_s=first_record * DT_S)
