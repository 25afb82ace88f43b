"""Traffic and map statistics of sets of scenes side by side: real logs vs generated scenes.

Prints one JSON line per (set, statistic) and then a markdown table with one column per set. The
statistics and their conventions (how speed is smoothed, what a leader, a lane change or a lane
width is) are in smart_marl/sources/scene_stats.py. A set is ``NAME=PATH[,PATH...]`` (anything
read_scenarios reads: WOMD records, pickles, JSON, a scene cache such as generate-sumo's output).

The default real set ("real") is every shared real scene (../shared/data next to the repository)
with 91 frames at 10 Hz: the WOMD records, the SMART pickles, the 9.1 s ScenarioNet Waymo scenes,
GPUDrive and Nocturne JSON, deduplicated by scenario id. ``--other`` adds a column of the rest
(nuScenes, Argoverse 2, the 20 s Waymo scene).

Usage:
  python benchmarks/scene_statistics.py --set sumo_before=/tmp/sumo_before --set sumo_after=/tmp/sumo_after
  python benchmarks/scene_statistics.py --no-real --set a=DIR --max-scenes 100
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from smart_marl import read_scenarios
from smart_marl.sources.scene_stats import STATISTICS, StatisticsAccumulator

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REAL_91 = ["womd_tfrecord", "smart_pkl", "scenarionet/waymo", "gpudrive_json", "nocturne_json"]
REAL_OTHER = ["scenarionet/waymo", "scenarionet/nuscenes", "av2"]


def _is_91_at_10hz(scenario) -> bool:
    return scenario.num_frames == 91 and bool(np.allclose(np.diff(scenario.timestamps_s), 0.1, atol=1e-3))


def collect(name: str, paths: list[str], keep=None, max_scenes: int | None = None,
            bootstrap: int = 0) -> tuple[dict, int, float]:
    """(summary, scenes, seconds) of the scenes under ``paths`` that ``keep`` accepts, deduplicated by id."""
    acc = StatisticsAccumulator()
    seen: set[str] = set()
    started = time.perf_counter()
    for scenario in read_scenarios(paths):
        if scenario.scenario_id in seen or (keep is not None and not keep(scenario)):
            continue
        seen.add(scenario.scenario_id)
        acc.add(scenario)
        if max_scenes and acc.scenes >= max_scenes:
            break
    return acc.summary(bootstrap=bootstrap), acc.scenes, time.perf_counter() - started


def _fmt(x: float) -> str:
    if not math.isfinite(x):
        return "-"
    a = abs(x)
    return f"{x:.0f}" if a >= 100 else f"{x:.1f}" if a >= 10 else f"{x:.2f}" if a >= 0.1 or a == 0 else f"{x:.3f}"


def cell(kind: str, numbers: dict | None) -> str:
    if numbers is None:
        return "-"
    ci = f" ({_fmt(numbers['lo'])}-{_fmt(numbers['hi'])})" if "lo" in numbers else ""
    if kind == "distribution":
        return f"{_fmt(numbers['p50'])} [{_fmt(numbers['p10'])}, {_fmt(numbers['p90'])}] mean {_fmt(numbers['mean'])}{ci}"
    if kind == "share":
        return f"{numbers['share']:.3f}{ci}"
    return f"{numbers['rate']:.3f}{ci}"


def markdown_table(results: dict[str, tuple[dict, int]]) -> str:
    names = list(results)
    lines = ["| statistic | " + " | ".join(f"{n} ({results[n][1]} scenes)" for n in names) + " |",
             "|---|" + "---|" * len(names)]
    for stat, (kind, description) in STATISTICS.items():
        if not any(stat in results[n][0] for n in names):
            continue
        row = [cell(kind, results[n][0].get(stat)) for n in names]
        lines.append(f"| {stat} | " + " | ".join(row) + " |")
    lines.append("")
    lines.append("Distributions: p50 [p10, p90] and mean; shares and rates: one number; in parentheses a 90% "
                 "interval of the mean, share or rate from resampling the scenes. "
                 "Definitions: smart_marl/sources/scene_stats.py.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--set", action="append", default=[], metavar="NAME=PATH[,PATH...]",
                        help="a set of scenes to compare (repeatable)")
    parser.add_argument("--no-real", action="store_true", help="leave out the shared real scenes")
    parser.add_argument("--other", action="store_true",
                        help="add a column of the shared real scenes that are not 91 frames at 10 Hz")
    parser.add_argument("--max-scenes", type=int, default=0, help="at most this many scenes per set (0: all)")
    parser.add_argument("--bootstrap", type=int, default=1000,
                        help="scene resamplings for the 90%% intervals (0: none)")
    parser.add_argument("--markdown", help="also write the table to this file")
    args = parser.parse_args(argv)

    sets: list[tuple[str, list[str], object]] = []
    if not args.no_real:
        if not SHARED.is_dir():
            print(f"no shared real scenes at {SHARED}: use --no-real", file=sys.stderr)
            return 2
        sets.append(("real", [str(SHARED / p) for p in REAL_91], _is_91_at_10hz))
        if args.other:
            sets.append(("real_other", [str(SHARED / p) for p in REAL_OTHER], lambda s: not _is_91_at_10hz(s)))
    for spec in args.set:
        if "=" not in spec:
            parser.error(f"--set {spec!r}: expected NAME=PATH[,PATH...]")
        name, paths = spec.split("=", 1)
        sets.append((name, paths.split(","), None))

    results: dict[str, tuple[dict, int]] = {}
    for name, paths, keep in sets:
        summary, scenes, seconds = collect(name, paths, keep, args.max_scenes or None, args.bootstrap)
        results[name] = (summary, scenes)
        for stat, numbers in summary.items():
            kind = STATISTICS[stat][0]
            print(json.dumps({"benchmark": "scene_statistics", "set": name, "scenes": scenes, "statistic": stat,
                              "kind": kind, **{k: round(v, 4) if isinstance(v, float) else v for k, v in numbers.items()}}),
                  flush=True)
        print(json.dumps({"benchmark": "scene_statistics", "set": name, "scenes": scenes, "seconds": round(seconds, 1)}),
              flush=True)
    table = markdown_table(results)
    print()
    print(table)
    if args.markdown:
        Path(args.markdown).write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
