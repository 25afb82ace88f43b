"""SUMO traffic: demand, one simulation, and the scenes cut from it.

Stage: the traffic half of the SUMO source (traffic simulator -> **Scenario**). For one simulation
(:func:`simulate_scenes`): a random network (:mod:`.sumo_net`), random vehicle types with varied
driver parameters (:func:`random_vehicle_types`), routes for cars, trucks, buses and bicycles and
walks for pedestrians (:func:`write_demand`), a libsumo run at 0.1 s steps with a warm-up, every
agent's state recorded per step (:class:`Recording`), cars parked along the kerbs
(:func:`add_parked_vehicles`), then several 9.1 s scenes cut around moving vehicles chosen as the
self-driving car (:func:`cut_scene`). The demand lives in :mod:`.sumo_demand`, the smoothed headings and
walkers' sway in :mod:`.sumo_motion`, the parked cars in :mod:`.sumo_parked` (all re-exported here).

Routes: by default each vehicle follows a random walk over the network (:func:`random_walk`) that
goes straight on at a junction with ``SumoConfig.straight_probability`` and otherwise turns, from a
start drawn in proportion to road length, until a dead end (the network's fringe) or about 25 m per
simulated second; ``routes="trips"`` (the first generator's) gives random origin-destination trips
that SUMO routes by shortest path, which turn at most junctions of a small network.

Conversions: SUMO gives a vehicle's front-bumper centre and an angle in degrees clockwise from
north; a track holds the box centre (front minus half the length along the heading) and the
heading in radians counter-clockwise from +x; the velocity is the speed along the heading.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config_files import (check_fields, check_value, flag, integer, interval, is_number, number, one_of, optional,
                            probabilities, sequence)
from ..errors import UsageError
from ..scenario import CURRENT_FRAME, DT_S, AgentType, SceneFrame, Scenario, TrafficLights, Tracks, wrap_angle
from .sumo_net import (
    JUNCTION_TYPES, SIGNAL_OF_CHAR, SPEEDS_MPS, NetworkMap, NetworkSpec, build_network, network_map, quantize, random_network_spec,
    require_sumo, rotation_matrix, sumo_binary,
)
from .sumo_demand import EdgeGraph, edge_graph, random_vehicle_types, random_walk, write_demand  # noqa: F401  (re-exported)
from .sumo_motion import WALKER_JITTER_DOF, WALKER_JITTER_MAX_RAD, smooth_heading, smooth_walkers, sway_walkers  # noqa: F401
from .sumo_parked import (  # noqa: F401  (re-exported)
    PARKED_CLEARANCE_M, PARKED_END_MARGIN_M, PARKED_GAP_M, PARKED_MIN_SPACING_M, PARKED_SLOT_M, add_parked_vehicles,
)

SCENE_FRAMES = 91
SOURCE = "sumo"


class SumoConfigError(UsageError):
    """A SumoConfig value the generator cannot use (names the field, the value and what it takes)."""


MIN_SPEED_LIMIT_MPS, MAX_SPEED_LIMIT_MPS = 1.35, 55.6
"""The speed limits a network may get (5-200 km/h): netgenerate crashes on limits near 0."""

@dataclass(frozen=True)
class SumoConfig:
    """Everything that shapes the generated scenes. The defaults are tuned toward real WOMD traffic
    (``benchmarks/scene_statistics.py``: fewer junctions per kilometre, routes that mostly go straight
    on, calmer drivers; see the README's SUMO section); :meth:`legacy` gives the first generator's
    traffic, which the embedded prior was trained on."""

    scenes_per_sim: int = 8  # scenes cut from one simulation (different times, different egos)
    scene_spacing_s: float = 4.0  # time between the starts of two scenes of one simulation
    warmup_s: float = 40.0  # simulated before the first scene so that traffic is established
    radius_m: float = 80.0  # agents within this distance of the self-driving car are kept
    map_radius_m: float = 100.0  # map features within this distance of the self-driving car's path are kept
    max_agents: int = 128
    max_predict: int = 8  # tracks to predict: the self-driving car and the nearest fully valid agents
    pedestrians: bool = True
    bicycles: bool = True
    sublane: bool = False  # SUMO's sub-lane model (--lateral-resolution): 2.5x slower than the default
    lateral_resolution_m: float = 0.8
    lane_change_duration_s: tuple[float, float] = (2.0, 4.5)  # without sub-lanes: continuous lane changes
    demand_scale: float = 2.5  # multiplies the random departure rates (2.5: WOMD-like vehicles per scene and leader shares)
    # --- the traffic's character (legacy() lists the first generator's values)
    length_scale: float = 2.0  # multiplies every block length of the random networks (1: 60-180 m grid blocks)
    kind_weights: tuple[float, float, float] = (0.45, 0.2, 0.35)  # grid, spider, rand
    junction_weights: tuple[float, ...] = (0.3, 0.5, 0.1, 0.08, 0.02)  # over sumo_net.JUNCTION_TYPES
    speed_levels_mps: tuple[float, ...] = SPEEDS_MPS  # the networks' default speed limits to draw from
    speed_weights: tuple[float, ...] | None = (0.3, 0.3, 0.2, 0.15, 0.05)  # over speed_levels_mps; None: uniform
    tls_guess_probability: float = 0.2  # share of unsignalised networks that get lights at busy junctions
    lane_width_m: tuple[float, float] | None = (3.2, 3.8)  # lane width range; None: SUMO's 3.2 m
    routes: str = "walk"  # "walk": random walks that mostly go straight on; "trips": random origin-destination trips
    straight_probability: float = 0.9  # "walk": the chance of going straight on at a junction
    driver_sigma: tuple[float, float] = (0.0, 0.4)  # Krauss/IDM driver imperfection (random dawdling)
    driver_accel_mps2: tuple[float, float] = (1.8, 3.5)  # cars' maximum acceleration
    driver_decel_mps2: tuple[float, float] = (2.5, 4.5)  # cars' comfortable deceleration
    car_follow_weights: tuple[float, float, float] = (0.5, 0.3, 0.2)  # Krauss, IDM, EIDM
    lc_speed_gain: tuple[float, float] = (0.1, 1.5)  # eagerness to change lanes for speed
    max_lane_piece_m: float | None = 50.0  # map lanes longer than this are cut into linked pieces (WOMD-like); None: whole
    walker_sway_m: float = 0.15  # std of the sideways sway of walking pedestrians (sway_walkers; 0: SUMO's straight lines)
    walker_sway_s: float = 1.0  # time scale of that sway (seconds)
    walker_jitter_rad: float = 0.01  # scale of walking pedestrians' heavy-tailed heading jitter (sway_walkers; 0: none)
    walker_jitter_s: float = 0.15  # time scale of that jitter (seconds)
    cyclist_sway_m: float = 0.0  # std of cyclists' sideways sway (sway_walkers without jitter; 0: SUMO's lane lines)
    cyclist_sway_s: float = 0.7  # time scale of that sway (seconds)
    # parked cars beside the kerbside lanes (add_parked_vehicles): per simulation, the share of ~7 m kerb
    # slots that hold one is drawn from this range (real WOMD scenes: two thirds of the vehicles are parked)
    parked_occupancy: tuple[float, float] = (0.2, 0.9)
    # emergency stops (EmergencyStops, issue 33): from the warm-up on, each moving car starts a hard stop at this
    # rate (per vehicle and minute; 0: none, the default), braking at a deceleration drawn from
    # emergency_decel_mps2 to a standstill, standing for emergency_hold_s, then driving on; SUMO's drivers
    # behind it answer with their own car-following model (the data of followers that brake for a leader)
    emergency_stop_rate_per_min: float = 0.0
    emergency_decel_mps2: tuple[float, float] = (4.0, 8.0)
    emergency_hold_s: tuple[float, float] = (1.0, 4.0)

    @classmethod
    def legacy(cls, **changes) -> "SumoConfig":
        """The first generator's traffic (the embedded prior's training data): 60-180 m blocks, half of
        the networks signalised, random origin-destination trips, sigma up to 0.7, decel 3.5-5.5 m/s^2.
        The same seed gives the same scenes as that generator did. ``changes`` override fields."""
        return cls(**{**LEGACY_TRAFFIC, **changes})

    def __post_init__(self) -> None:
        if not all(is_number(v) for v in (self.walker_sway_m, self.walker_jitter_rad, self.walker_sway_s, self.walker_jitter_s,
                                          self.cyclist_sway_m, self.cyclist_sway_s)):
            check_fields(self, SUMO_RULES, "SUMO", SumoConfigError)  # names the one that is not a number
        if not (self.walker_sway_m >= 0 and self.walker_jitter_rad >= 0 and self.walker_sway_s > 0 and self.walker_jitter_s > 0
                and self.cyclist_sway_m >= 0 and self.cyclist_sway_s > 0):
            raise SumoConfigError(f"SumoConfig: walker_sway_m, walker_jitter_rad and cyclist_sway_m must be >= 0, their time scales > 0; "
                             f"got {self.walker_sway_m}, {self.walker_jitter_rad}, {self.cyclist_sway_m}, {self.walker_sway_s}, "
                             f"{self.walker_jitter_s}, {self.cyclist_sway_s}")
        check_value("parked_occupancy", self.parked_occupancy, sequence(number(), length=2), SumoConfigError, "SUMO config")
        lo, hi = self.parked_occupancy
        if not 0.0 <= lo <= hi <= 1.0:
            raise SumoConfigError(f"SumoConfig: parked_occupancy must be a range within [0, 1] (low <= high); got {self.parked_occupancy}")
        check_fields(self, SUMO_RULES, "SUMO", SumoConfigError)
        if not (self.emergency_stop_rate_per_min >= 0 and 0 < self.emergency_decel_mps2[0] <= self.emergency_decel_mps2[1]
                and 0 <= self.emergency_hold_s[0] <= self.emergency_hold_s[1]):
            raise SumoConfigError(f"SumoConfig: emergency_stop_rate_per_min must be >= 0, emergency_decel_mps2 a positive range and "
                                  f"emergency_hold_s a range >= 0; got {self.emergency_stop_rate_per_min}, {self.emergency_decel_mps2}, "
                                  f"{self.emergency_hold_s}")
        if self.speed_weights is not None and len(self.speed_weights) != len(self.speed_levels_mps):
            raise SumoConfigError(f"SumoConfig: speed_weights has {len(self.speed_weights)} entries for "
                             f"{len(self.speed_levels_mps)} speed_levels_mps; give one weight per level (or None)")

    def sim_duration_s(self) -> float:
        return self.warmup_s + (self.scenes_per_sim - 1) * self.scene_spacing_s + SCENE_FRAMES * DT_S + 0.5


_SECONDS = number(0.0, 3600.0, low_open=True, why="an hour")
SUMO_RULES = {
    "scenes_per_sim": integer(1, 64), "scene_spacing_s": _SECONDS, "warmup_s": number(0.0, 3600.0, why="an hour"),
    "radius_m": number(0.0, 1000.0, low_open=True, why="a kilometre around the self-driving car"),
    "map_radius_m": number(0.0, 2000.0, low_open=True), "max_agents": integer(1, 1024), "max_predict": integer(1, 128),
    "pedestrians": flag, "bicycles": flag, "sublane": flag, "lateral_resolution_m": number(0.05, 10.0),
    "lane_change_duration_s": interval(0.0, 60.0, low_open=True),
    "demand_scale": number(0.0, 100.0, low_open=True, why="a hundred times the demand jams every network"),
    "length_scale": number(0.1, 10.0), "kind_weights": probabilities(3), "junction_weights": probabilities(len(JUNCTION_TYPES)),
    "speed_levels_mps": sequence(number(MIN_SPEED_LIMIT_MPS, MAX_SPEED_LIMIT_MPS, why="200 km/h"), min_length=1, max_length=64),
    "speed_weights": optional(probabilities()), "tls_guess_probability": number(0.0, 1.0),
    "lane_width_m": optional(interval(2.0, 6.0)), "routes": one_of("walk", "trips"), "straight_probability": number(0.0, 1.0),
    "driver_sigma": interval(0.0, 1.0), "driver_accel_mps2": interval(0.0, 10.0, low_open=True),
    "driver_decel_mps2": interval(0.0, 10.0, low_open=True), "car_follow_weights": probabilities(3),
    "lc_speed_gain": interval(0.0, 100.0), "max_lane_piece_m": optional(number(1.0, 10_000.0)),
    "walker_sway_m": number(0.0, 5.0), "walker_sway_s": _SECONDS, "walker_jitter_rad": number(0.0, 3.2),
    "walker_jitter_s": _SECONDS, "cyclist_sway_m": number(0.0, 5.0), "cyclist_sway_s": _SECONDS,
    "parked_occupancy": interval(0.0, 1.0),
    "emergency_stop_rate_per_min": number(0.0, 60.0, why="a hard stop every second for every car"),
    "emergency_decel_mps2": interval(0.0, 20.0, low_open=True), "emergency_hold_s": interval(0.0, 600.0),
}
"""What each SumoConfig field takes (:mod:`smart_marl.config_files` rules), checked when a config is made."""


LEGACY_TRAFFIC: dict[str, Any] = dict(
    length_scale=1.0, kind_weights=(0.45, 0.2, 0.35), junction_weights=(0.5, 0.25, 0.1, 0.07, 0.08), speed_weights=None,
    tls_guess_probability=0.4, lane_width_m=None, routes="trips", straight_probability=0.7, driver_sigma=(0.05, 0.7),
    driver_accel_mps2=(1.8, 3.5), driver_decel_mps2=(3.5, 5.5), car_follow_weights=(0.5, 0.3, 0.2),
    lc_speed_gain=(0.3, 3.0), max_lane_piece_m=None, demand_scale=1.0, walker_sway_m=0.0,
    walker_jitter_rad=0.0, parked_occupancy=(0.0, 0.0))
"""The :class:`SumoConfig` fields that differ between the first generator and the tuned defaults."""


# ------------------------------------------------------------------------------------ recording
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


# ------------------------------------------------------------------------------------ scenes
def scene_candidates(rec: Recording, start: int, min_speed_mps: float = 2.0) -> np.ndarray:
    """Indices of vehicles that can be the self-driving car of the scene starting at frame ``start``:
    valid on all 91 frames and moving at the current frame."""
    stop = start + SCENE_FRAMES
    if stop > rec.valid.shape[1]:
        return np.zeros(0, np.int64)
    ok = (rec.types == AgentType.VEHICLE) & rec.valid[:, start:stop].all(axis=1)
    ok &= rec.speed[:, start + CURRENT_FRAME] >= min_speed_mps
    return np.flatnonzero(ok)


def cut_scene(rec: Recording, nmap: NetworkMap, start: int, ego: int, config: SumoConfig, scenario_id: str,
              metadata: dict[str, Any]) -> Scenario:
    """The 91-frame Scenario starting at recorded frame ``start`` with agent ``ego`` as the self-driving
    car: every agent that comes within ``radius_m`` of it on some frame (nearest first, at most
    ``max_agents``), the map within ``map_radius_m``, the signals of the lanes kept."""
    s = slice(start, start + SCENE_FRAMES)
    cur = start + CURRENT_FRAME
    valid = rec.valid[:, s]
    center = rec.center[:, s]
    ego_xy = rec.center[ego, s, :2]  # [T, 2]
    dist = np.linalg.norm(center[..., :2] - ego_xy[None], axis=-1)
    dist = np.where(valid, dist, np.inf).min(axis=1)
    near = np.flatnonzero(dist <= config.radius_m)
    near = near[near != ego]
    near = near[np.argsort(dist[near], kind="stable")][: config.max_agents - 1]
    index = np.concatenate([[ego], np.sort(near)])
    origin = rec.center[ego, cur].copy()

    v = valid[index]
    pos = np.where(v[..., None], center[index] - origin, 0.0).astype(np.float32)
    heading = np.where(v, rec.heading[index, s], 0.0)
    velocity = np.where(v[..., None], rec.velocity[index, s], 0.0)
    size = np.where(v[..., None], rec.size[index][:, None, :], 0.0)
    tracks = Tracks(ids=index + 1, types=rec.types[index], position=pos, heading=heading.astype(np.float32),
                    velocity=velocity.astype(np.float32), size=size.astype(np.float32), valid=v)

    road_map, kept_lanes = nmap.crop(ego_xy[::10], config.map_radius_m, origin)
    lanes = sorted(int(k) for k in kept_lanes if int(k) in rec.signal_states)
    if lanes:
        states = np.stack([rec.signal_states[k][s] for k in lanes], axis=1)
        stops = np.stack([nmap.signal_stop_points[k] for k in lanes]) - origin
        lights = TrafficLights(lane_ids=lanes, states=states, present=np.ones(states.shape, bool),
                               stop_points=stops.astype(np.float32))
    else:
        lights = TrafficLights.empty(SCENE_FRAMES)

    # tracks to predict: the self-driving car and the nearest agents valid on every frame
    full = np.flatnonzero(v.all(axis=1))
    full = full[np.argsort(np.linalg.norm(pos[full, CURRENT_FRAME, :2], axis=-1), kind="stable")]
    predict = full[: config.max_predict]
    return Scenario(
        scenario_id=scenario_id, source=SOURCE, timestamps_s=np.arange(SCENE_FRAMES) * DT_S,
        current_frame=CURRENT_FRAME, tracks=tracks, road_map=road_map, traffic_lights=lights, sdc_index=0,
        predict_indices=np.sort(predict), frame=SceneFrame(float(origin[0]), float(origin[1]), float(origin[2]), 0.0),
        metadata={**metadata, "start_time_s": round(rec.start_time_s + start * DT_S, 1),
                  "sdc_sumo_id": rec.sumo_ids[ego]},
    )


def network_spec(rng: np.random.Generator, config: SumoConfig) -> NetworkSpec:
    """The random network of one simulation, drawn from ``rng`` with the config's network knobs."""
    return random_network_spec(rng, pedestrians=config.pedestrians, bicycles=config.bicycles,
                               length_scale=config.length_scale, kind_weights=config.kind_weights,
                               junction_weights=config.junction_weights, speed_weights=config.speed_weights,
                               tls_guess_probability=config.tls_guess_probability, lane_width_m=config.lane_width_m,
                               speed_levels_mps=config.speed_levels_mps)


def sim_seed(seed: int, sim_index: int) -> int:
    """The seed of simulation ``sim_index`` of a run seeded with ``seed`` (independent of workers)."""
    return int(np.random.SeedSequence([int(seed), int(sim_index)]).generate_state(1)[0] & 0x7FFFFFFF)


def scenario_id(seed: int, sim_index: int, k: int) -> str:
    return f"sumo-{seed}-{sim_index:06d}-{k:02d}"


def simulate_scenes(seed: int, sim_index: int, config: SumoConfig = SumoConfig(),
                    workdir: str | os.PathLike | None = None) -> list[Scenario]:
    """One simulation: a random network and demand (from ``seed`` and ``sim_index``), SUMO at 0.1 s
    steps, then up to ``config.scenes_per_sim`` scenes cut at different times around different
    moving vehicles. Fewer scenes when too few vehicles qualify (e.g. a jammed network)."""
    _, sumolib, _ = require_sumo()
    s = sim_seed(seed, sim_index)
    rng = np.random.default_rng(s)
    spec = network_spec(rng, config)
    with tempfile.TemporaryDirectory(prefix="smart-marl-sumo-", dir=workdir) as tmp:
        tmp = Path(tmp)
        net_path = build_network(spec, tmp / "net.net.xml")
        nmap = network_map(net_path, spec.rotation_rad, config.max_lane_piece_m)
        net = sumolib.net.readNet(os.fspath(net_path))
        types = random_vehicle_types(rng, config)
        duration = config.sim_duration_s()
        counts = write_demand(tmp / "demand.rou.xml", net, types, rng, config, duration)
        lane_change_s = float(rng.uniform(*config.lane_change_duration_s))
        try:
            rec = run_simulation(net_path, tmp / "demand.rou.xml", duration, config.warmup_s, s, config, nmap,
                                 spec.rotation_rad, lane_change_s)
        except Exception as exc:
            # SUMO now and then refuses a network netgenerate made (e.g. "The tls '238' is not known"):
            # that simulation yields no scene, said out loud, and generation goes on with the next one.
            if type(exc).__name__ not in ("TraCIException", "FatalTraCIError"):
                raise
            try:
                require_sumo()[2].close()
            except Exception:
                pass
            warnings.warn(f"SUMO simulation {sim_index} (seed {seed}) failed and yields no scene: {exc}")
            return []
        # its own random stream: the traffic and the choice of self-driving cars do not change with it
        parked_rng = np.random.default_rng([s, 0x9a7])
        occupancy = float(parked_rng.uniform(*config.parked_occupancy))
        rec = add_parked_vehicles(rec, net, spec.rotation_rad, occupancy, parked_rng)
    metadata = {"generator": "smart_marl.sources.sumo", "seed": int(seed), "sim_index": int(sim_index),
                "sim_seed": s, "network": spec.to_metadata(), "network_stats": nmap.stats, "demand": counts,
                "sublane": config.sublane, "lane_change_duration_s": None if config.sublane else round(lane_change_s, 2),
                "parked_occupancy": round(occupancy, 3), "parked_vehicles": sum(i.startswith("parked") for i in rec.sumo_ids)}
    scenes, used = [], set()
    spacing = int(round(config.scene_spacing_s / DT_S))
    for k in range(config.scenes_per_sim):
        start = k * spacing
        candidates = [c for c in scene_candidates(rec, start) if c not in used]
        if not candidates:
            continue
        ego = int(candidates[int(rng.integers(len(candidates)))])
        used.add(ego)
        scenes.append(cut_scene(rec, nmap, start, ego, config, scenario_id(seed, sim_index, k), metadata))
    return scenes
