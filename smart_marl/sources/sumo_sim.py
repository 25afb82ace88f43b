"""SUMO traffic: demand, one simulation, and the scenes cut from it.

Stage: the traffic half of the SUMO source (traffic simulator -> **Scenario**). For one simulation
(:func:`simulate_scenes`): a random network (:mod:`.sumo_net`), random vehicle types with varied
driver parameters (:func:`random_vehicle_types`), routes for cars, trucks, buses and bicycles and
walks for pedestrians (:func:`write_demand`), a libsumo run at 0.1 s steps with a warm-up, every
agent's state recorded per step (:class:`Recording`), cars parked along the kerbs
(:func:`add_parked_vehicles`), then several 9.1 s scenes cut around moving vehicles chosen as the
self-driving car (:func:`cut_scene`). The config lives in :mod:`.sumo_config`, the demand in
:mod:`.sumo_demand`, the run and its recording in :mod:`.sumo_run`, the smoothed headings and walkers' sway in
:mod:`.sumo_motion`, the parked cars in :mod:`.sumo_parked` (all re-exported here).

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
from pathlib import Path
from typing import Any

import numpy as np

from ..scenario import CURRENT_FRAME, DT_S, AgentType, SceneFrame, Scenario, TrafficLights, Tracks
from .sumo_config import (  # noqa: F401  (re-exported: the generator's config is imported from here)
    LEGACY_TRAFFIC, MAX_SPEED_LIMIT_MPS, MIN_SPEED_LIMIT_MPS, SCENE_FRAMES, SUMO_RULES, SumoConfig, SumoConfigError,
)
from .sumo_demand import EdgeGraph, edge_graph, random_vehicle_types, random_walk, write_demand  # noqa: F401  (re-exported)
from .sumo_motion import WALKER_JITTER_DOF, WALKER_JITTER_MAX_RAD, smooth_heading, smooth_walkers, sway_walkers  # noqa: F401
from .sumo_net import NetworkMap, NetworkSpec, build_network, network_map, random_network_spec, require_sumo
from .sumo_parked import (  # noqa: F401  (re-exported)
    PARKED_CLEARANCE_M, PARKED_END_MARGIN_M, PARKED_GAP_M, PARKED_MIN_SPACING_M, PARKED_SLOT_M, add_parked_vehicles,
)
from .sumo_run import EmergencyStops, Recording, run_simulation  # noqa: F401  (re-exported; simulate_scenes calls run_simulation from here)

SOURCE = "sumo"


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
