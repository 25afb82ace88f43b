"""SUMO traffic, its demand: random vehicle types with varied driver parameters
(:func:`random_vehicle_types`), the routes and walks of one simulation (:func:`write_demand`) and
the random walks over the network that vehicles follow (:class:`EdgeGraph`, :func:`random_walk`).
Re-exported by :mod:`.sumo_sim`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from .sumo_config import SumoConfig
from .sumo_net import turn_angle


def _u(rng: np.random.Generator, lo: float, hi: float) -> str:
    return f"{rng.uniform(lo, hi):.3f}"


def random_vehicle_types(rng: np.random.Generator, config: SumoConfig) -> list[dict[str, str]]:
    """vType attribute dicts: several car variants, a truck, a bus, bicycles and pedestrians, each with
    its own driver (speed factor and deviation, imperfection, reaction time, gaps, lane-change style)."""
    types = []
    lc_model = "SL2015" if config.sublane else "LC2013"

    def driver(kind: str) -> dict[str, str]:
        d = {"sigma": _u(rng, *config.driver_sigma), "tau": _u(rng, 0.6, 1.6), "minGap": _u(rng, 1.2, 3.0),
             "speedFactor": _u(rng, 0.85, 1.2), "speedDev": _u(rng, 0.03, 0.2),
             "carFollowModel": str(rng.choice(["Krauss", "IDM", "EIDM"], p=list(config.car_follow_weights))),
             "laneChangeModel": lc_model, "lcStrategic": _u(rng, 0.3, 2.0), "lcCooperative": _u(rng, 0.2, 1.0),
             "lcSpeedGain": _u(rng, *config.lc_speed_gain), "lcKeepRight": _u(rng, 0.2, 2.0), "lcAssertive": _u(rng, 1.0, 3.0),
             "lcImpatience": _u(rng, 0.0, 0.8), "emergencyDecel": "9.0"}
        if config.sublane:
            d["maxSpeedLat"] = _u(rng, 0.6, 1.4)
            d["latAlignment"] = str(rng.choice(["center", "center", "right", "arbitrary"]))
        if d["carFollowModel"] == "EIDM":
            d["sigma"] = "0"  # EIDM models imperfection itself
        return d

    for k in range(int(rng.integers(3, 7))):
        types.append({"id": f"car{k}", "vClass": "passenger", "length": _u(rng, 3.8, 5.2), "width": _u(rng, 1.7, 2.0),
                      "height": _u(rng, 1.4, 1.9), "accel": _u(rng, *config.driver_accel_mps2), "decel": _u(rng, *config.driver_decel_mps2), **driver("car")})
    types.append({"id": "truck", "vClass": "truck", "length": _u(rng, 7.0, 12.0), "width": _u(rng, 2.3, 2.55),
                  "height": _u(rng, 3.0, 4.0), "accel": _u(rng, 0.8, 1.5), "decel": _u(rng, 3.0, 4.5), **driver("truck")})
    types.append({"id": "bus", "vClass": "bus", "length": _u(rng, 10.0, 13.0), "width": "2.5", "height": "3.2",
                  "accel": _u(rng, 0.8, 1.4), "decel": _u(rng, 3.0, 4.0), **driver("bus")})
    if config.bicycles:
        for k in range(2):
            d = driver("bike")
            d.update(speedFactor=_u(rng, 0.7, 1.1), minGap=_u(rng, 0.5, 1.5))
            types.append({"id": f"bike{k}", "vClass": "bicycle", "length": _u(rng, 1.6, 1.9), "width": _u(rng, 0.55, 0.75),
                          "height": _u(rng, 1.6, 1.9), "accel": _u(rng, 0.8, 1.5), "decel": _u(rng, 2.0, 3.5),
                          "maxSpeed": _u(rng, 4.0, 7.5), **d})
    if config.pedestrians:
        for k in range(2):
            types.append({"id": f"ped{k}", "vClass": "pedestrian", "length": _u(rng, 0.4, 0.8), "width": _u(rng, 0.5, 0.8),
                          "height": _u(rng, 1.5, 1.9), "maxSpeed": _u(rng, 1.1, 1.7), "speedDev": _u(rng, 0.05, 0.2)})
    return types


def write_demand(path: Path, net, types: list[dict[str, str]], rng: np.random.Generator, config: SumoConfig,
                 duration_s: float) -> dict[str, int]:
    """A route file: the vTypes and random trips (vehicles, bicycles) and walks (pedestrians), sorted by
    departure. SUMO routes the trips itself at insertion; unroutable ones are dropped. Returns counts."""
    edges = [e for e in net.getEdges() if e.getFunction() == ""]

    def edges_for(vclass: str) -> list[str]:
        return [e.getID() for e in edges if any(lane.allows(vclass) for lane in e.getLanes()) and e.getLength() > 5]

    total_km = sum(e.getLength() * len(e.getLanes()) for e in edges) / 1000.0
    car_types = [t["id"] for t in types if t["vClass"] == "passenger"]
    rate_scale = config.demand_scale * float(rng.uniform(0.5, 1.5))
    # departures per second per lane-km of network
    streams = [("veh", "passenger", car_types, 0.065 * total_km * rate_scale),
               ("veh", "truck", ["truck"], 0.003 * total_km * rate_scale),
               ("veh", "bus", ["bus"], 0.0015 * total_km * rate_scale)]
    if config.bicycles:
        streams.append(("veh", "bicycle", ["bike0", "bike1"], 0.008 * total_km * rate_scale))
    if config.pedestrians:
        streams.append(("person", "pedestrian", ["ped0", "ped1"], 0.02 * total_km * rate_scale))
    rows: list[tuple[float, str]] = []
    counts: dict[str, int] = {}
    for kind, vclass, type_ids, per_s in streams:
        pool = edges_for(vclass)
        if len(pool) < 2 or per_s <= 0:
            continue
        # a burst at the start (the network fills quickly) then a Poisson stream
        n = int(rng.poisson(per_s * duration_s)) + int(per_s * 12)
        departs = np.sort(np.concatenate([rng.uniform(0, 3, int(per_s * 12)), rng.uniform(0, duration_s, n - int(per_s * 12))]))
        graph = edge_graph(net, vclass) if kind == "veh" and config.routes == "walk" else None
        if graph is not None:  # walks start anywhere along the roads: edges drawn in proportion to their length
            weight = np.array([graph.length_m[e] for e in pool])
            starts = rng.choice(len(pool), len(departs), p=weight / weight.sum())
        for k, depart in enumerate(departs):
            a, b = rng.choice(len(pool), 2, replace=False)
            if graph is not None:
                a = starts[k]
            vtype = type_ids[int(rng.integers(len(type_ids)))]
            vid = f"{vclass}{k}"
            if kind == "veh" and graph is not None:
                route = " ".join(random_walk(graph, pool[a], rng, config.straight_probability, duration_s * 25.0))
                rows.append((depart, f'<vehicle id="{vid}" type="{vtype}" depart="{depart:.1f}" departLane="best" '
                                     f'departSpeed="max" departPos="random"><route edges="{route}"/></vehicle>'))
            elif kind == "veh":
                rows.append((depart, f'<trip id="{vid}" type="{vtype}" depart="{depart:.1f}" from="{pool[a]}" to="{pool[b]}" '
                                     f'departLane="best" departSpeed="max" departPos="random"/>'))
            else:
                rows.append((depart, f'<person id="{vid}" type="{vtype}" depart="{depart:.1f}" departPos="random">'
                                     f'<walk from="{pool[a]}" to="{pool[b]}" arrivalPos="random"/></person>'))
        counts[vclass] = len(departs)
    rows.sort(key=lambda r: r[0])
    with open(path, "w") as f:
        f.write("<routes>\n")
        for t in types:
            attrs = " ".join(f"{k}={quoteattr(v)}" for k, v in t.items())
            f.write(f"  <vType {attrs}/>\n")
        for _, row in rows:
            f.write(f"  {row}\n")
        f.write("</routes>\n")
    return counts


@dataclass
class EdgeGraph:
    """The edges a vehicle class may take after each edge, with the turn angle (radians, 0: straight on)."""

    length_m: dict[str, float]
    successors: dict[str, list[tuple[str, float]]]


def edge_graph(net, vclass: str) -> EdgeGraph:
    """The :class:`EdgeGraph` of a sumolib network for ``vclass``: a successor is reachable by a
    connection whose lanes both allow the class; its turn is :func:`~.sumo_net.turn_angle`."""
    lengths, successors = {}, {}
    for edge in net.getEdges():
        if edge.getFunction() != "":
            continue
        lengths[edge.getID()] = edge.getLength()
        out = []
        for to_edge, conns in edge.getOutgoing().items():
            if to_edge.getFunction() != "":
                continue
            if any(c.getFromLane().allows(vclass) and c.getToLane().allows(vclass) for c in conns):
                out.append((to_edge.getID(), turn_angle(edge, to_edge)))
        successors[edge.getID()] = sorted(out)
    return EdgeGraph(lengths, successors)


def random_walk(graph: EdgeGraph, start: str, rng: np.random.Generator, straight_probability: float,
                max_length_m: float, straight_rad: float = math.radians(35.0)) -> list[str]:
    """A route from ``start``: at each junction the straight-on successor (the one that turns least,
    if it turns less than ``straight_rad``) with probability ``straight_probability``, otherwise one of
    the others; it ends at a dead end or after ``max_length_m``. No edge is taken twice."""
    route, length, seen = [start], 0.0, {start}
    while length < max_length_m:
        options = [(e, turn) for e, turn in graph.successors.get(route[-1], []) if e not in seen]
        if not options:
            break
        turns = np.abs([turn for _, turn in options])
        straight = int(turns.argmin())
        if turns[straight] < straight_rad and len(options) > 1:
            others = [k for k in range(len(options)) if k != straight]
            pick = straight if rng.random() < straight_probability else others[int(rng.integers(len(others)))]
        else:
            pick = int(rng.integers(len(options)))
        route.append(options[pick][0])
        seen.add(route[-1])
        length += graph.length_m[route[-1]]
    return route
