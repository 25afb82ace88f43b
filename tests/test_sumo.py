"""SUMO-generated scenes: maps, tracks, determinism, the generate-sumo command and the WOMD round trip.

Two small simulations (a grid and a spider network, seed 0) are generated once per session, a few
seconds of CPU; the command test runs one more simulation in two worker processes.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

pytest.importorskip("libsumo", reason="SUMO is an optional extra: pip install 'smart-marl[sumo]'")
pytest.importorskip("sumolib", reason="SUMO is an optional extra: pip install 'smart-marl[sumo]'")
pytest.importorskip("shapely", reason="the SUMO source needs shapely (smart-marl[sumo])")

from smart_marl.scenario import AgentType, LaneType, LinkType, MapFeatureType, Scenario, SignalState, wrap_angle  # noqa: E402
from smart_marl.sources.sumo import SumoConfig, generate_scenes, simulate_scenes  # noqa: E402

SMALL_FIELDS = dict(scenes_per_sim=4, warmup_s=20.0, scene_spacing_s=3.0)
SMALL = SumoConfig(**SMALL_FIELDS)

# physical bounds per type: speed (m/s), |acceleration| (m/s^2), |yaw rate| (rad/s), displacement per frame (m)
BOUNDS = {
    AgentType.VEHICLE: dict(speed=45.0, accel=10.0, yaw_rate=3.0, step=4.5),
    AgentType.CYCLIST: dict(speed=12.0, accel=5.0, yaw_rate=3.0, step=1.2),
    AgentType.PEDESTRIAN: dict(speed=3.0, accel=8.0, yaw_rate=2 * np.pi + 1e-3, step=0.3),
}


@pytest.fixture(scope="module")
def scenes() -> list[Scenario]:
    out = simulate_scenes(0, 0, SMALL) + simulate_scenes(0, 1, SMALL)
    assert len(out) >= 6
    return out


@pytest.fixture(scope="module")
def without_parked_cars() -> list[Scenario]:
    """Simulation 0 of seed 0 as in ``scenes``, without parked cars (two tests compare against it)."""
    from dataclasses import replace

    return simulate_scenes(0, 0, replace(SMALL, parked_occupancy=(0.0, 0.0)))


def lane_polylines(scenario: Scenario) -> dict[int, np.ndarray]:
    rm = scenario.road_map
    return {int(rm.ids[i]): rm.feature_points(i)[:, :2].astype(np.float64) for i in rm.indices_of(MapFeatureType.LANE)}


# ----------------------------------------------------------------------------------------- maps
def test_networks_vary_between_simulations(scenes):
    kinds = {s.metadata["network"]["kind"] for s in scenes}
    assert kinds == {"grid", "spider"}  # seed 0: simulation 0 is a grid, simulation 1 a spider web
    assert all(s.metadata["network"]["rotation_rad"] != 0 for s in scenes)


def test_every_lane_has_a_polyline_and_a_speed_limit(scenes):
    assert sum(len(s.road_map.indices_of(MapFeatureType.LANE)) for s in scenes) > 20 * len(scenes)
    for s in scenes:
        rm = s.road_map
        lanes = rm.indices_of(MapFeatureType.LANE)
        assert len(lanes) >= 4  # a scene on a long road far from junctions holds few lane pieces
        assert np.all(np.diff(rm.point_offsets)[lanes] >= 2)
        assert np.all(rm.speed_limit_mph[lanes] > 5) and np.all(rm.speed_limit_mph[lanes] < 80)
        assert set(np.unique(rm.subtypes[lanes])) <= {LaneType.SURFACE_STREET, LaneType.BIKE_LANE}


def test_successor_starts_where_its_predecessor_ends(scenes):
    checked = 0
    for s in scenes:
        lanes = lane_polylines(s)
        for a, b in s.road_map.links[s.road_map.link_types == LinkType.SUCCESSOR]:
            gap = np.linalg.norm(lanes[int(a)][-1] - lanes[int(b)][0])
            assert gap < 0.5, f"{s.scenario_id}: lane {a} ends {gap:.2f} m from its successor {b}"
            checked += 1
    assert checked > 500


def test_predecessor_links_are_the_reverse_of_successor_links(scenes):
    for s in scenes:
        rm = s.road_map
        succ = {(int(a), int(b)) for a, b in rm.links[rm.link_types == LinkType.SUCCESSOR]}
        pred = {(int(b), int(a)) for a, b in rm.links[rm.link_types == LinkType.PREDECESSOR]}
        assert succ == pred and succ
        left = {(int(a), int(b)) for a, b in rm.links[rm.link_types == LinkType.LEFT_NEIGHBOR]}
        right = {(int(b), int(a)) for a, b in rm.links[rm.link_types == LinkType.RIGHT_NEIGHBOR]}
        assert left == right  # b is a's left neighbour exactly when a is b's right neighbour


def test_neighbouring_lanes_run_side_by_side(scenes):
    s = scenes[0]
    lanes = lane_polylines(s)
    links = s.road_map.links[s.road_map.link_types == LinkType.LEFT_NEIGHBOR]
    assert len(links)
    for a, b in links:
        mid = lanes[int(a)][len(lanes[int(a)]) // 2]
        d = np.linalg.norm(lanes[int(b)] - mid, axis=1).min()
        assert 1.0 < d < 5.0  # one lane width apart, roughly


def _side_of_nearest_edge(points: np.ndarray, edges: list[np.ndarray]):
    """For each point: a value that is positive when it lies on the left of its nearest road-edge
    polyline (the normal of the nearest segment, or at a vertex the sum of both segments' unit
    normals), its distance to that polyline, and whether the nearest point is an open polyline end
    (where left and right are undefined)."""
    a = np.concatenate([e[:-1] for e in edges])
    b = np.concatenate([e[1:] for e in edges])
    first = np.concatenate([np.arange(len(e) - 1) == 0 for e in edges])
    last = np.concatenate([np.arange(len(e) - 1) == len(e) - 2 for e in edges])
    ab = b - a
    normal = np.stack([-ab[:, 1], ab[:, 0]], 1) / np.maximum(np.linalg.norm(ab, axis=1), 1e-12)[:, None]  # left
    t = np.clip((((points[:, None] - a[None]) * ab[None]).sum(-1)) / np.maximum((ab ** 2).sum(-1), 1e-12)[None], 0, 1)
    d = np.linalg.norm(points[:, None] - (a[None] + t[..., None] * ab[None]), axis=-1)
    k = d.argmin(axis=1)
    tk = t[np.arange(len(points)), k]
    n = normal[k].copy()
    at_start, at_end = tk <= 0.0, tk >= 1.0
    n[at_start & ~first[k]] += normal[k[at_start & ~first[k]] - 1]
    n[at_end & ~last[k]] += normal[k[at_end & ~last[k]] + 1]
    open_end = (at_start & first[k]) | (at_end & last[k])
    foot = a[k] + tk[:, None] * ab[k]
    return ((points - foot) * n).sum(1), d[np.arange(len(points)), k], open_end


def test_road_edges_enclose_the_lanes(scenes):
    """Road edges are oriented with the drivable area on their left: every lane point near the scene's
    centre lies on the left of its nearest road-edge segment, at least a few decimetres inside."""
    for s in scenes:
        rm = s.road_map
        edges = [rm.feature_points(i)[:, :2].astype(np.float64) for i in rm.indices_of(MapFeatureType.ROAD_EDGE)]
        assert edges
        points = np.concatenate(list(lane_polylines(s).values()))
        points = points[np.linalg.norm(points, axis=1) < 60.0]
        side, dist, open_end = _side_of_nearest_edge(points, edges)
        assert (~open_end).sum() > 0.9 * len(points)
        side, dist = side[~open_end], dist[~open_end]
        assert np.all(side > 0), f"{s.scenario_id}: {(side <= 0).sum()} lane points outside the road edges"
        assert dist.min() > 0.3


def test_crosswalks_exist_when_pedestrians_walk(scenes):
    with_crosswalks = 0
    for s in scenes:
        assert s.metadata["network"]["crossings"]
        crosswalks = s.road_map.indices_of(MapFeatureType.CROSSWALK)
        with_crosswalks += len(crosswalks) > 0  # every junction has them; a scene far from junctions has none
        for i in crosswalks:
            poly = s.road_map.feature_points(i)[:, :2]
            assert len(poly) >= 4
            x, y = poly[:, 0], poly[:, 1]
            area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
            assert 5.0 < area < 200.0  # a few metres wide, a road wide
    assert with_crosswalks >= len(scenes) // 2


def test_traffic_lights_control_map_lanes_at_their_start(scenes):
    lit = [s for s in scenes if len(s.traffic_lights.lane_ids)]
    assert lit  # the grid has traffic lights
    for s in lit:
        tl = s.traffic_lights
        lanes = lane_polylines(s)
        assert tl.present.all()
        assert set(np.unique(tl.states)) <= {SignalState.GO, SignalState.CAUTION, SignalState.STOP,
                                              SignalState.FLASHING_STOP, SignalState.FLASHING_CAUTION}
        for lane_id, stop in zip(tl.lane_ids, tl.stop_points):
            assert np.allclose(lanes[int(lane_id)][0], stop[:2], atol=1e-3)
        # signals change over a cycle: some lane sees GO and STOP across the 16 traffic-light frames it has
        assert SignalState.GO in tl.states and SignalState.STOP in tl.states


# ----------------------------------------------------------------------------------------- tracks
def test_scene_layout_matches_womd(scenes):
    for s in scenes:
        assert s.source == "sumo" and s.num_frames == 91 and s.current_frame == 10
        assert np.allclose(s.timestamps_s, np.arange(91) * 0.1)
        assert s.sdc_index == 0 and s.tracks.valid[0].all()
        assert np.all(s.tracks.position[0, 10] == 0)  # the local frame's origin is the SDC at the current frame
        assert np.linalg.norm(s.tracks.velocity[0, 10]) >= 2.0  # the SDC is moving
        assert 0 in s.predict_indices and len(s.predict_indices) <= 8
        assert {AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST} >= set(np.unique(s.tracks.types).tolist())


def test_every_agent_comes_within_the_radius_of_the_sdc(scenes):
    for s in scenes:
        tr = s.tracks
        d = np.linalg.norm(tr.position[..., :2] - tr.position[0:1, :, :2], axis=-1)
        closest = np.where(tr.valid, d, np.inf).min(axis=1)
        assert np.all(closest <= SMALL.radius_m + 1e-3)


def _kinematics(s: Scenario):
    tr = s.tracks
    pos = tr.position[..., :2].astype(np.float64)
    both = tr.valid[:, 1:] & tr.valid[:, :-1]
    step = np.linalg.norm(np.diff(pos, axis=1), axis=-1)
    speed = np.linalg.norm(tr.velocity.astype(np.float64), axis=-1)
    accel = np.abs(np.diff(speed, axis=1)) / 0.1
    yaw_rate = np.abs(wrap_angle(np.diff(tr.heading.astype(np.float64), axis=1))) / 0.1
    return both, step, speed, accel, yaw_rate


@pytest.mark.parametrize("agent_type", [AgentType.VEHICLE, AgentType.CYCLIST, AgentType.PEDESTRIAN])
def test_tracks_are_physical_per_type(scenes, agent_type):
    """No teleports; speeds, accelerations and yaw rates within physical bounds for the type."""
    bound = BOUNDS[agent_type]
    frames = 0
    for s in scenes:
        both, step, speed, accel, yaw_rate = _kinematics(s)
        of_type = (s.tracks.types == agent_type)[:, None]
        m = both & of_type
        frames += int(m.sum())
        assert step[m].max(initial=0) <= bound["step"], f"{s.scenario_id}: a {agent_type.name} jumped {step[m].max():.2f} m"
        assert speed[s.tracks.valid & of_type].max(initial=0) <= bound["speed"]
        assert accel[m].max(initial=0) <= bound["accel"], f"{s.scenario_id}: {agent_type.name} accel {accel[m].max():.1f}"
        assert yaw_rate[m].max(initial=0) <= bound["yaw_rate"], f"{s.scenario_id}: {agent_type.name} yaw rate {yaw_rate[m].max():.2f}"
    assert frames > 200  # the scenes hold this type at all


def test_boxes_move_along_their_heading(scenes):
    """SUMO's angle (degrees clockwise from north) becomes a counter-clockwise heading from +x: moving
    vehicles travel where they point, and their velocity agrees with their displacement."""
    angles, ratios = [], []
    for s in scenes:
        tr = s.tracks
        d = np.diff(tr.position[..., :2].astype(np.float64), axis=1)
        moving = (tr.valid[:, 1:] & tr.valid[:, :-1] & (np.linalg.norm(d, axis=-1) > 0.5)
                  & (tr.types == AgentType.VEHICLE)[:, None])
        angles.append(np.abs(wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - tr.heading[:, :-1]))[moving])
        v = 0.5 * (tr.velocity[:, 1:] + tr.velocity[:, :-1])
        ratios.append((np.linalg.norm(d, axis=-1) / 0.1 / np.maximum(np.linalg.norm(v, axis=-1), 1e-6))[moving])
    angles, ratios = np.concatenate(angles), np.concatenate(ratios)
    assert np.median(angles) < 0.01 and np.percentile(angles, 99) < 0.3
    assert abs(np.median(ratios) - 1.0) < 0.02


def test_vehicle_sizes_come_from_their_types(scenes):
    for s in scenes:
        size = s.tracks.box_size()
        veh = s.tracks.types == AgentType.VEHICLE
        assert np.all((size[veh, 0] >= 3.8) & (size[veh, 0] <= 13.0) & (size[veh, 1] >= 1.7) & (size[veh, 1] <= 2.6))
        ped = s.tracks.types == AgentType.PEDESTRIAN
        assert np.all(size[ped, 0] <= 0.8)


# ------------------------------------------------------------------------------- determinism, files
def test_same_seed_gives_the_same_scenes(scenes):
    again = simulate_scenes(0, 0, SMALL)
    first = [s for s in scenes if s.metadata["sim_index"] == 0]
    assert [s.scenario_id for s in again] == [s.scenario_id for s in first]
    assert all(a.equals(b, ignore=()) for a, b in zip(again, first))


def test_womd_tfrecord_of_a_generated_scene_reads_back_identical(scenes, tmp_path):
    from smart_marl.readers.womd import write_womd_tfrecord
    from smart_marl import read_scenarios

    path = tmp_path / "sumo.tfrecord"
    assert write_womd_tfrecord(scenes[:3], path) == 3
    back = list(read_scenarios(path))
    assert len(back) == 3
    for a, b in zip(scenes[:3], back):
        assert a.equals(b, ignore=("source", "metadata")), a.differences(b)


def test_generate_sumo_command_writes_a_cache_that_reads_back(tmp_path):
    """Two worker processes, read back through read_scenarios and SceneCache, equal to an in-process
    generation with the same seed (the worker count does not change the scenes)."""
    from smart_marl import read_scenarios
    from smart_marl.cache import SceneCache
    from smart_marl.cli import main

    out = tmp_path / "cache"
    rc = main(["generate-sumo", "--scenes", "3", "--scenes-per-sim", "2", "--out", str(out), "--workers", "2",
               "--seed", "7", "--quiet"])
    assert rc == 0
    cache = SceneCache(out)
    assert len(cache) == 3 and cache.manifest["num_scenes"] == 3
    via_reader = list(read_scenarios(out))
    expected = list(generate_scenes(3, seed=7, config=SumoConfig(scenes_per_sim=2)))
    for got, again, want in zip(cache, via_reader, expected):
        arrays, meta = got.to_arrays()
        Scenario.from_arrays(arrays, meta, validate=True)  # passes the Scenario's validation
        assert got.equals(want, ignore=()) and again.equals(want, ignore=())
    assert [e["scenario_id"] for e in cache.scenes] == ["sumo-7-000000-00", "sumo-7-000000-01", "sumo-7-000001-00"]
    # --straight-walkers: the same simulations with pedestrians on SUMO's straight lines; vehicles are untouched
    rc = main(["generate-sumo", "--scenes", "2", "--scenes-per-sim", "2", "--out", str(tmp_path / "straight"),
               "--workers", "1", "--seed", "7", "--quiet", "--straight-walkers"])
    assert rc == 0
    differ = 0
    for straight, swayed in zip(SceneCache(tmp_path / "straight"), cache):
        vehicles = straight.tracks.types == AgentType.VEHICLE
        np.testing.assert_array_equal(straight.tracks.position[vehicles], swayed.tracks.position[vehicles])
        walkers = straight.tracks.types == AgentType.PEDESTRIAN
        differ += int(walkers.any() and not np.array_equal(straight.tracks.heading[walkers], swayed.tracks.heading[walkers]))
    assert differ > 0  # the scenes hold walkers, and only their tracks changed
    with pytest.raises(ValueError, match="walker_sway_m, walker_jitter_rad and cyclist_sway_m must be >= 0"):
        SumoConfig(walker_sway_m=-0.1)


def test_missing_sumo_names_the_extra(monkeypatch):
    from smart_marl.sources.sumo_net import SumoUnavailableError, require_sumo

    monkeypatch.setitem(sys.modules, "libsumo", None)
    with pytest.raises(SumoUnavailableError, match=r"smart-marl\[sumo\]"):
        require_sumo()


def test_generated_scenes_render_with_the_project_renderer(scenes):
    pytest.importorskip("matplotlib")
    from smart_marl.render import render_scenario_frame

    image = render_scenario_frame(scenes[0], scenes[0].current_frame, size_px=200)
    assert image.shape == (200, 200, 3) and image.dtype == np.uint8
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 10  # map and agents, not a blank canvas


def test_all_way_stop_junctions_get_stop_signs_at_lane_ends(tmp_path):
    import dataclasses

    from smart_marl.sources.sumo_net import build_network, network_map, random_network_spec

    spec = dataclasses.replace(random_network_spec(np.random.default_rng(1)), kind="grid", junction_type="allway_stop",
                               params={"x-number": 3, "y-number": 3, "x-length": 100, "y-length": 100,
                                       "attach-length": 50}, tls_guess=False)
    nmap = network_map(build_network(spec, tmp_path / "net.net.xml"), spec.rotation_rad)
    assert nmap.stats["traffic_lights"] == 0 and nmap.stats["stop_signs"] > 0
    center = nmap.stop_sign_points[0, :2]
    road_map, _ = nmap.crop(center[None], 60.0, np.array([*center, 0.0]))
    lanes = {
        int(road_map.ids[i]): road_map.feature_points(i)[:, :2] for i in road_map.indices_of(MapFeatureType.LANE)}
    links = road_map.links[road_map.link_types == LinkType.STOP_SIGN_LANE]
    assert len(links) == len(road_map.indices_of(MapFeatureType.STOP_SIGN)) > 0
    for sign, lane in links:
        point = road_map.feature_points(int(np.flatnonzero(road_map.ids == sign)[0]))[0, :2]
        assert np.allclose(point, lanes[int(lane)][-1], atol=1e-3)  # the sign stands where its lane ends


def test_a_simulation_sumo_refuses_yields_no_scene_with_a_warning(monkeypatch):
    from smart_marl.sources import sumo_sim

    class TraCIException(Exception):  # the name libsumo's exception has
        pass

    def refuse(*args, **kwargs):
        raise TraCIException("The tls '238' is not known")

    monkeypatch.setattr(sumo_sim, "run_simulation", refuse)
    with pytest.warns(UserWarning, match="simulation 3 .* failed and yields no scene"):
        assert sumo_sim.simulate_scenes(7, 3) == []


# ------------------------------------------------------------------------------- tuned vs first generator
def test_legacy_config_draws_the_first_generators_networks():
    """SumoConfig.legacy() keeps the first generator's random draws: the network of seed 1001,
    simulation 0 is the one that generator recorded in the scenes' metadata (the embedded prior's data)."""
    from smart_marl.sources.sumo_sim import network_spec, sim_seed

    recorded = {"kind": "rand", "params": {"iterations": 47, "min-distance": 74.6, "max-distance": 137.8,
                                           "min-angle": 35.1, "bidi-probability": 0.85},
                "lanes": 2, "random_lanenumber": True, "speed_mps": 13.89, "junction_type": "traffic_light",
                "tls_guess": False, "sidewalks": True, "crossings": True, "bikelanes": True, "perturb_m": 0.0,
                "rotation_rad": -0.4067, "seed": 742415235}
    rng = np.random.default_rng(sim_seed(1001, 0))
    assert network_spec(rng, SumoConfig.legacy()).to_metadata() == recorded
    tuned = network_spec(np.random.default_rng(sim_seed(1001, 0)), SumoConfig())
    assert tuned.params["min-distance"] == pytest.approx(2 * 74.6, abs=0.1)  # same draw, blocks twice as long
    assert 3.2 <= tuned.lane_width_m <= 3.8


def test_speed_limits_are_drawn_from_the_configured_levels_and_weights():
    """``generate-sumo --speed-limits 50,90 --speed-weights 1,3``: km/h become m/s, the weights are
    normalised, and the networks' limits are drawn from those levels in those proportions."""
    from smart_marl.commands.generate_sumo import speed_changes
    from smart_marl.sources.sumo_sim import network_spec

    changes = speed_changes((50.0, 90.0), (1.0, 3.0))
    assert changes == {"speed_levels_mps": (13.89, 25.0), "speed_weights": (0.25, 0.75)}
    assert speed_changes((50.0, 90.0), None)["speed_weights"] is None and speed_changes(None, None) == {}
    config = SumoConfig(**changes)
    drawn = [network_spec(np.random.default_rng(i), config).speed_mps for i in range(400)]
    assert set(drawn) == {13.89, 25.0}
    assert drawn.count(25.0) / len(drawn) == pytest.approx(0.75, abs=0.06)
    with pytest.raises(ValueError, match="speed_weights has 5 entries for 2 speed_levels_mps"):
        SumoConfig(speed_levels_mps=(13.89, 25.0))  # the default weights are for the default five levels


def test_junction_weights_set_how_often_each_junction_kind_is_drawn():
    """``generate-sumo --junction-weights 0,0,1,3,0``: normalised, and the networks' junction kinds follow them."""
    from smart_marl.commands.generate_sumo import junction_changes
    from smart_marl.sources.sumo_sim import network_spec

    changes = junction_changes((0.0, 0.0, 1.0, 3.0, 0.0))
    assert changes == {"junction_weights": (0.0, 0.0, 0.25, 0.75, 0.0)} and junction_changes(None) == {}
    drawn = [network_spec(np.random.default_rng(i), SumoConfig(**changes)).junction_type for i in range(400)]
    assert set(drawn) == {"priority_stop", "allway_stop"}
    assert drawn.count("allway_stop") / len(drawn) == pytest.approx(0.75, abs=0.06)


def test_random_walk_goes_straight_on_and_stops_at_a_dead_end():
    from smart_marl.sources.sumo_sim import EdgeGraph, random_walk

    # a -> b (straight) or c (left); b -> d (straight) or e (right); d and e are dead ends; c -> a would loop
    graph = EdgeGraph(length_m={k: 100.0 for k in "abcde"},
                      successors={"a": [("b", 0.05), ("c", 1.5)], "b": [("d", -0.02), ("e", -1.5)],
                                  "c": [("a", 1.5)], "d": [], "e": []})
    rng = np.random.default_rng(0)
    assert random_walk(graph, "a", rng, 1.0, 1e4) == ["a", "b", "d"]
    assert random_walk(graph, "a", rng, 0.0, 1e4) == ["a", "c"]  # always turns; c's only way on is back to a
    assert random_walk(graph, "a", rng, 1.0, 50.0) == ["a", "b"]  # ends after max_length_m
    routes = [tuple(random_walk(graph, "a", np.random.default_rng(k), 0.8, 1e4)) for k in range(400)]
    straight = sum(r[:2] == ("a", "b") for r in routes) / len(routes)
    assert 0.74 < straight < 0.86


def test_tuned_defaults_slow_fewer_moving_vehicles_than_the_first_generator(scenes):
    """The point of the tuning (benchmarks/scene_statistics.py has the full table): on the same seeds,
    fewer of the vehicles moving faster than 5 m/s at the current frame lose half their speed within 8 s
    than with the first generator's traffic, and moving vehicles spend less time stopped."""
    from smart_marl.sources.scene_stats import summarize

    legacy = simulate_scenes(0, 0, SumoConfig.legacy(**SMALL_FIELDS)) + simulate_scenes(0, 1, SumoConfig.legacy(**SMALL_FIELDS))
    tuned, _ = summarize(scenes)
    old, _ = summarize(legacy)
    key = "fast_vehicle_slows_50pct_8s_share"
    assert tuned[key]["n"] >= 30 and old[key]["n"] >= 30
    assert tuned[key]["share"] < old[key]["share"]
    assert tuned["vehicle_stopped_time_share_of_movers"]["share"] < old["vehicle_stopped_time_share_of_movers"]["share"]


def _walker_tracks(frames: int = 91):
    """Two smoothed walkers: one walking 1.3 m/s along +x, one standing still."""
    t = np.arange(frames) * 0.1
    xy = np.zeros((2, frames, 2))
    xy[0, :, 0] = 1.3 * t
    xy[1] = [4.0, 2.0]
    return xy, np.ones((2, frames), bool), np.zeros((2, frames))


def test_walker_sway_turns_walkers_a_little_and_leaves_standing_ones_alone():
    from smart_marl.sources.sumo_sim import sway_walkers

    xy, valid, heading = _walker_tracks()
    out_xy, velocity, out_heading = sway_walkers(xy, valid, heading, np.random.default_rng(0), 0.15, 1.0)
    # the walker now sways: its heading changes by a few hundredths of a radian every 0.5 s, as logged
    # pedestrians' do (median 0.03-0.06 rad in the shared WOMD-derived scenes), and it never leaves its path far
    change = np.abs(wrap_angle(out_heading[0, 5:] - out_heading[0, :-5]))
    assert 0.01 < np.median(change) < 0.12 and change.max() < 0.6
    assert 0.03 < np.abs(out_xy[0, :, 1]).mean() < 0.4 and np.abs(out_xy[0, :, 1]).max() < 0.8
    # it still walks forward at its speed, pointing where it goes
    speed = np.linalg.norm(velocity[0, 1:-1], axis=-1)
    assert abs(np.median(speed) - 1.3) < 0.05
    moving_dir = np.arctan2(velocity[0, 1:-1, 1], velocity[0, 1:-1, 0])
    assert np.abs(wrap_angle(moving_dir - out_heading[0, 1:-1])).max() < 1e-6
    # the standing one does not move or turn
    np.testing.assert_allclose(out_xy[1], xy[1])
    np.testing.assert_allclose(out_heading[1], heading[1])
    # the same generator state gives the same sway; no amplitude, no sway
    again = sway_walkers(xy, valid, heading, np.random.default_rng(0), 0.15, 1.0)
    np.testing.assert_array_equal(again[0], out_xy)
    still = sway_walkers(xy, valid, heading, np.random.default_rng(0), 0.0, 1.0)
    np.testing.assert_allclose(still[0], xy, atol=1e-12)
    np.testing.assert_allclose(still[2][0], 0.0, atol=1e-12)


def test_walker_jitter_turns_the_body_in_heavy_tailed_flicks_not_the_path():
    """The heading jitter: the path is the swayed one of the same generator state, the heading leaves the
    direction of travel by at most WALKER_JITTER_MAX_RAD, and its frame-to-frame changes are mostly small
    with a heavy tail (logged pedestrians: median 0.10 rad/s, 13% of frames above 0.4 rad/s)."""
    from smart_marl.sources.sumo_sim import WALKER_JITTER_MAX_RAD, sway_walkers

    xy, valid, heading = _walker_tracks(2000)
    plain = sway_walkers(xy, valid, heading, np.random.default_rng(1), 0.15, 1.0)
    out_xy, velocity, out_heading = sway_walkers(xy, valid, heading, np.random.default_rng(1), 0.15, 1.0, 0.01, 0.15)
    np.testing.assert_array_equal(out_xy, plain[0])
    away = np.abs(wrap_angle(out_heading[0] - plain[2][0]))
    assert away.max() <= WALKER_JITTER_MAX_RAD + 1e-9 and away.mean() > 0.005
    rate = np.abs(wrap_angle(np.diff(out_heading[0]))) / 0.1
    assert 0.05 < np.median(rate) < 0.25 and 0.05 < (rate > 0.4).mean() < 0.3
    np.testing.assert_allclose(out_heading[1], heading[1])


def test_generated_pedestrians_sway_like_logged_ones_unless_switched_off(scenes):
    """With the default sway, walking pedestrians' heading changes over 0.5 s as logged WOMD-derived ones do
    (scene statistic pedestrian_abs_yaw_rate_radps, median 0.04-0.09 rad/s in ../shared/data); without
    sway and jitter they walk SUMO's straight lines (median 0)."""
    from smart_marl.sources.scene_stats import summarize

    swayed, _ = summarize(scenes)
    straight, _ = summarize(simulate_scenes(0, 0, SumoConfig(**SMALL_FIELDS, walker_sway_m=0.0, walker_jitter_rad=0.0)))
    key = "pedestrian_abs_yaw_rate_radps"
    assert swayed[key]["n"] > 200 and straight[key]["n"] > 200
    assert 0.03 < swayed[key]["p50"] < 0.15
    assert straight[key]["p50"] < 0.005


def test_cyclist_sway_is_off_by_default_and_turns_only_the_cyclists(without_parked_cars):
    """``cyclist_sway_m`` (default 0: cyclists ride SUMO's lane lines) sways moving cyclists as
    :func:`sway_walkers` sways pedestrians, without the heading jitter; vehicles keep their tracks."""
    from smart_marl.sources.scene_stats import yaw_rate_radps

    # without parked cars: a swaying cyclist keeps other kerb slots free (add_parked_vehicles), which would
    # change the parked cars between the two
    swayed = simulate_scenes(0, 0, SumoConfig(**SMALL_FIELDS, cyclist_sway_m=0.22, cyclist_sway_s=0.65, parked_occupancy=(0.0, 0.0)))
    plain = without_parked_cars  # SumoConfig(**SMALL_FIELDS, parked_occupancy=(0.0, 0.0))
    assert len(plain) == len(swayed)
    rates = {"plain": [], "swayed": []}
    for a, b in zip(plain, swayed):
        vehicles = a.tracks.types == AgentType.VEHICLE
        np.testing.assert_array_equal(a.tracks.position[vehicles], b.tracks.position[vehicles])
        for name, s in (("plain", a), ("swayed", b)):
            cyc = s.tracks.types == AgentType.CYCLIST
            speed = np.linalg.norm(s.tracks.velocity[cyc], axis=-1)
            yaw, ok = yaw_rate_radps(s.tracks.heading[cyc], s.tracks.valid[cyc])
            rates[name].append(np.abs(yaw[ok & (speed > 2.0)]))
    plain_rates, swayed_rates = np.concatenate(rates["plain"]), np.concatenate(rates["swayed"])
    assert len(swayed_rates) > 100
    assert np.median(plain_rates) < 0.005 < 0.02 < np.median(swayed_rates) < 0.2


# ------------------------------------------------------------------------------------ parked cars
class _FakeLane:
    def __init__(self, shape, width=3.2, cars=True):
        self._shape, self._width, self._cars = shape, width, cars

    def allows(self, vclass):
        return self._cars or vclass == "pedestrian"  # a sidewalk otherwise

    def getShape(self):
        return self._shape

    def getWidth(self):
        return self._width


class _FakeEdge:
    def __init__(self, lanes):
        self._lanes = lanes

    def getFunction(self):
        return ""

    def getLanes(self):
        return self._lanes


class _FakeNet:
    def __init__(self, edges):
        self._edges = edges

    def getEdges(self):
        return self._edges


def _recording(center, types, size):
    from smart_marl.sources.sumo_sim import Recording

    a, t = center.shape[:2]
    return Recording(sumo_ids=[f"a{i}" for i in range(a)], types=np.asarray(types, np.int8), size=np.asarray(size, float),
                     center=center, heading=np.zeros((a, t)), velocity=np.zeros((a, t, 2)), speed=np.zeros((a, t)),
                     valid=np.ones((a, t), bool))


def test_parked_cars_line_the_kerb_to_the_right_of_travel_and_clear_of_every_agent():
    """A 100 m edge along +x with a sidewalk (no cars) then a car lane 3.2 m wide on y = 0: at full
    occupancy, parked cars every ~7 m beside the car lane on the right of travel (y < 0), parallel to
    it, none within 10 m of the ends, and none where a recorded walker passes."""
    from smart_marl.sources.sumo_sim import PARKED_END_MARGIN_M, PARKED_GAP_M, add_parked_vehicles

    edge = _FakeEdge([_FakeLane([(0.0, -3.0), (100.0, -3.0)], 2.0, cars=False), _FakeLane([(0.0, 0.0), (100.0, 0.0)])])
    frames = 50
    walker = np.zeros((1, frames, 3))
    walker[0, :, 0] = 50.0  # crosses the kerb at x = 50, from y = -6 to y = 0
    walker[0, :, 1] = np.linspace(-6.0, 0.0, frames)
    rec = _recording(walker, [AgentType.PEDESTRIAN], [[0.5, 0.5, 1.7]])
    out = add_parked_vehicles(rec, _FakeNet([edge]), 0.0, 1.0, np.random.default_rng(0))
    parked = np.arange(1, len(out.sumo_ids))
    assert out.sumo_ids[0] == "a0" and all(out.sumo_ids[k].startswith("parked") for k in parked)
    assert len(parked) >= 8
    assert out.valid[parked].all() and np.all(out.speed[parked] == 0) and np.all(out.center[parked] == out.center[parked, :1])
    assert np.all(out.types[parked] == AgentType.VEHICLE)
    x, y = out.center[parked, 0, 0], out.center[parked, 0, 1]
    width = out.size[parked, 1]
    inner_side = -y - width / 2  # distance of the car's side nearest the lane from the lane's centre line
    assert np.all(inner_side >= 1.6 + PARKED_GAP_M - 0.1 - 1e-6) and np.all(inner_side <= 1.6 + PARKED_GAP_M + 0.2 + 1e-6)
    assert np.all(np.abs(wrap_angle(out.heading[parked, 0])) < 0.15)
    assert x.min() >= PARKED_END_MARGIN_M - 1.0 and x.max() <= 100.0 - PARKED_END_MARGIN_M + 1.0
    assert not np.any(np.abs(x - 50.0) < out.size[parked, 0] / 2 + 0.25 + 0.3)  # the walker's crossing stays free
    gaps = np.diff(np.sort(x))
    assert gaps.min() >= 5.5 and np.median(gaps) < 8.0


def test_no_parked_cars_at_zero_occupancy_and_the_same_traffic_either_way(scenes, without_parked_cars):
    """parked_occupancy=(0, 0) (the legacy generator's) adds none; with cars parked, the scenes hold
    every track of the scenes without them, frame for frame, the same self-driving cars, map and
    lights: the parked cars have their own random stream and SUMO's traffic never sees them."""
    with_cars = [s for s in scenes if s.metadata["sim_index"] == 0]  # simulate_scenes(0, 0, SMALL)
    without = without_parked_cars
    assert sum(s.metadata["parked_vehicles"] for s in with_cars) > 0
    assert all(s.metadata["parked_vehicles"] == 0 for s in without)
    assert [s.scenario_id for s in with_cars] == [s.scenario_id for s in without]
    for a, b in zip(with_cars, without):
        assert a.num_tracks > b.num_tracks  # the scenes are small enough that max_agents drops no one
        same = np.flatnonzero(np.isin(a.tracks.ids, b.tracks.ids))
        assert len(same) == b.num_tracks
        # the tracks to predict are the nearest fully valid agents, parked cars among them: left out here
        diff = a.select_tracks(same).differences(b)
        assert set(diff) <= {"metadata", "predict_indices", "predict_difficulty"}, diff


def test_no_parked_cars_flag_and_a_bad_occupancy_range(tmp_path):
    from smart_marl.cli import main

    rc = main(["generate-sumo", "--scenes", "2", "--scenes-per-sim", "2", "--out", str(tmp_path / "c"), "--workers", "1",
               "--seed", "7", "--quiet", "--no-parked-cars"])
    assert rc == 0
    from smart_marl.cache import SceneCache

    assert [s.metadata["parked_vehicles"] for s in SceneCache(tmp_path / "c")] == [0, 0]
    with pytest.raises(ValueError, match="parked_occupancy must be a range within"):
        SumoConfig(parked_occupancy=(0.5, 0.2))


def test_generated_parked_cars_never_touch_another_agent(scenes):
    """In generated scenes, a car that stands still on all 91 frames off every lane (a parked one) keeps
    its box clear of every other agent's box on every frame (agents taken as their width across)."""
    checked = 0
    for s in scenes:
        tr = s.tracks
        still = tr.valid.all(1) & (np.ptp(tr.position[..., :2], axis=1).max(-1) == 0) & (tr.types == AgentType.VEHICLE)
        lanes = np.concatenate(list(lane_polylines(s).values()))
        for k in np.flatnonzero(still):
            if np.linalg.norm(lanes - tr.position[k, 0, :2], axis=-1).min() < 1.8:
                continue  # standing in a lane: a queued SUMO vehicle, not a parked car
            checked += 1
            c, sn = np.cos(tr.heading[k, 0]), np.sin(tr.heading[k, 0])
            d = tr.position[:, :, :2] - tr.position[k, 0, :2]
            along, across = d[..., 0] * c + d[..., 1] * sn, -d[..., 0] * sn + d[..., 1] * c
            reach = tr.size[:, :, 1] / 2
            inside = (np.abs(along) < tr.size[k, 0, 0] / 2 + reach) & (np.abs(across) < tr.size[k, 0, 1] / 2 + reach) & tr.valid
            inside[k] = False
            assert not inside.any(), f"{s.scenario_id}: parked track {k} touches track {np.argwhere(inside)[0]}"
    assert checked >= 10
