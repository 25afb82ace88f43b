"""SUMO traffic, its configuration: :class:`SumoConfig` (every knob of the generator), what each
field takes (:data:`SUMO_RULES`), the first generator's values (:data:`LEGACY_TRAFFIC`) and the
error a value the generator cannot use raises. Re-exported by :mod:`.sumo_sim`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..config_files import (check_fields, check_value, flag, integer, interval, is_number, number, one_of, optional,
                            probabilities, sequence)
from ..errors import UsageError
from ..scenario import DT_S
from .sumo_net import JUNCTION_TYPES, SPEEDS_MPS


SCENE_FRAMES = 91


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
