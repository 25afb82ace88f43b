"""``smart-marl generate-sumo --scenes N --out DIR``: training scenes from the SUMO traffic simulator
(see smart_marl.sources.sumo), written as a scene cache or as WOMD TFRecords."""

from __future__ import annotations

import os

from ..errors import SmartMarlError, UsageError
from ..sources.sumo import SumoConfig, SumoUnavailableError, generate_to_dir
from ..sources.sumo_net import JUNCTION_TYPES
from ..sources.sumo_sim import MAX_SPEED_LIMIT_MPS, MIN_SPEED_LIMIT_MPS
from ..config_files import number
from .arguments import bounded_int, bounded_number, numbers_list, output_dir, seed, workers

speed_limits_kmh = numbers_list(number(round(MIN_SPEED_LIMIT_MPS * 3.6), round(MAX_SPEED_LIMIT_MPS * 3.6),
                                       why="km/h; netgenerate fails on limits near 0"), "speed_limits_kmh")
"""``--speed-limits``: comma-separated km/h, each within the limits a SUMO network takes (5-200)."""
MAX_SCENES = 10**6
"""The most scenes one ``generate-sumo`` makes (``--scenes``): ~290 KB a scene in a scene cache, ~290 GB."""
MAX_RELATIVE_WEIGHT = 1e6
"""The largest ``--speed-weights`` / ``--junction-weights`` entry: the weights are divided by their sum, which overflows
to inf (every probability 0) with entries near 1e308; a million to one already makes the rarest never drawn."""
relative_weights = numbers_list(number(0.0, MAX_RELATIVE_WEIGHT, low_open=True, why="a million to one"), "relative_weights")
"""Comma-separated weights, each in (0, :data:`MAX_RELATIVE_WEIGHT`] (normalised by their sum)."""
_DEFAULT_JUNCTION_WEIGHTS = SumoConfig.__dataclass_fields__["junction_weights"].default


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "generate-sumo", help="generate scenes with the SUMO traffic simulator (needs smart-marl[sumo])",
        description="Simulate random road networks with varied traffic (cars, trucks, buses, bicycles, pedestrians) "
                    "in SUMO and cut 9.1 s scenes (91 frames at 10 Hz, current frame 10) around moving vehicles, "
                    "written straight into a scene cache (default) or as WOMD TFRecords. Same seed, same scenes.")
    p.add_argument("--scenes", type=bounded_int(1, MAX_SCENES, "~290 GB of scene cache"), required=True,
                   help=f"number of scenes to generate (at most {MAX_SCENES:,})")
    p.add_argument("--out", required=True, type=output_dir, help="output folder (created if missing)")
    p.add_argument("--workers", type=workers, default=max(1, min(4, os.cpu_count() or 1)),
                   help="parallel processes, one SUMO simulation each")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the networks and traffic (default 0)")
    p.add_argument("--format", choices=("cache", "womd"), default="cache",
                   help="cache: scene-cache shards + manifest.json; womd: WOMD scenario TFRecords")
    p.add_argument("--scenes-per-sim", type=bounded_int(1, 64), default=8, help="scenes cut from each simulation")
    p.add_argument("--radius", type=bounded_number(0.0, 1000.0, low_open=True), default=80.0, help="agents within this many metres of the SDC are kept")
    p.add_argument("--no-pedestrians", action="store_true", help="no pedestrians in the simulations")
    p.add_argument("--no-bicycles", action="store_true", help="no bicycles in the simulations")
    p.add_argument("--sublane", action="store_true",
                   help="SUMO's sub-lane model for lateral motion (about 2.5x slower)")
    p.add_argument("--legacy", action="store_true",
                   help="the first generator's traffic (SumoConfig.legacy(): the embedded prior's training data) "
                        "instead of the defaults tuned toward real traffic")
    p.add_argument("--demand-scale", type=bounded_number(0.0, 100.0, low_open=True), default=None, metavar="X",
                   help="multiplies the traffic demand (default: the config's, 2.5 for the tuned traffic, 1 with --legacy)")
    p.add_argument("--speed-limits", type=speed_limits_kmh, default=None, metavar="KMH[,KMH...]",
                   help="the networks' speed limits to draw from, km/h, each 5-200 (default: the config's, 30-70 km/h)")
    p.add_argument("--speed-weights", type=relative_weights, default=None, metavar="W[,W...]",
                   help="their probabilities, one per limit (normalised; default: the config's with the default "
                        "limits, uniform with --speed-limits)")
    p.add_argument("--straight-walkers", action="store_true",
                   help="pedestrians walk SUMO's straight lines, without the sway and heading jitter of the tuned "
                        "generator (the data of the embedded prior's stages 2-4; --legacy implies it)")
    p.add_argument("--no-parked-cars", action="store_true",
                   help="no parked cars beside the kerbs (the tuned generator parks cars on 20-90%% of the kerb, drawn "
                        "per simulation, as real scenes have them; --legacy implies none)")
    p.add_argument("--junction-weights", type=relative_weights, default=None, metavar="W,W,W,W,W",
                   help="how often each junction kind is drawn, one weight per kind of " + ", ".join(JUNCTION_TYPES)
                        + " (normalised; default: the config's, " + ", ".join(map(str, _DEFAULT_JUNCTION_WEIGHTS))
                        + " for the tuned traffic)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def speed_changes(limits_kmh: tuple[float, ...] | None, w: tuple[float, ...] | None) -> dict:
    """SumoConfig changes of ``--speed-limits`` / ``--speed-weights`` (km/h, relative weights)."""
    if limits_kmh is None:
        if w is not None:
            raise UsageError("argument --speed-weights: needs --speed-limits (one weight per limit)")
        return {}
    levels = tuple(round(v / 3.6, 2) for v in limits_kmh)
    if w is None:
        return {"speed_levels_mps": levels, "speed_weights": None}
    if len(w) != len(levels):
        raise UsageError(f"argument --speed-weights: {len(w)} weights for {len(levels)} speed limits")
    return {"speed_levels_mps": levels, "speed_weights": tuple(x / sum(w) for x in w)}


def junction_changes(w: tuple[float, ...] | None) -> dict:
    """SumoConfig changes of ``--junction-weights`` (relative weights, one per junction kind)."""
    if w is None:
        return {}
    if len(w) != len(JUNCTION_TYPES):
        raise UsageError(f"argument --junction-weights: {len(w)} weights for the {len(JUNCTION_TYPES)} junction kinds "
                         f"({', '.join(JUNCTION_TYPES)})")
    return {"junction_weights": tuple(x / sum(w) for x in w)}


def run(args) -> int:
    make_config = SumoConfig.legacy if args.legacy else SumoConfig
    changes = {} if args.demand_scale is None else {"demand_scale": args.demand_scale}
    if args.straight_walkers:
        changes.update(walker_sway_m=0.0, walker_jitter_rad=0.0)
    if args.no_parked_cars:
        changes.update(parked_occupancy=(0.0, 0.0))
    changes.update(speed_changes(args.speed_limits, args.speed_weights))
    changes.update(junction_changes(args.junction_weights))
    config = make_config(scenes_per_sim=args.scenes_per_sim, radius_m=args.radius, pedestrians=not args.no_pedestrians,
                         bicycles=not args.no_bicycles, sublane=args.sublane, **changes)
    try:
        report = generate_to_dir(args.out, args.scenes, seed=args.seed, config=config, workers=args.workers,
                                 fmt=args.format, progress=not args.quiet)
    except SumoUnavailableError as exc:
        raise SmartMarlError(str(exc)) from exc
    print(f"{report.scenes} scenes from {report.simulations} simulations in {report.files} {args.format} files, "
          f"{report.bytes_written / 1e6:.1f} MB, {report.agent_seconds:.0f} agent-seconds in {report.seconds:.1f} s "
          f"-> {args.out}")
    return 0
