"""``smart-marl info PATH... [--json]``: one line per scene, the first thing to run on a new file."""

from __future__ import annotations

import json
import sys

from ..errors import ScenarioReadError, UsageError
from ..readers import detect_format, expand_paths, read_scenarios
from .arguments import reader_formats


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="describe the scenes in files, folders, globs or a scene cache",
                              description="Print one line (or one JSON object with --json) per scene: source "
                                          "format, scenario id, frames, tracks per type, lanes, lanes with "
                                          "successors, road edges, crosswalks, traffic-light frames.")
    p.add_argument("paths", nargs="+", metavar="PATH", help="a scene file, a folder, a glob or a scene-cache folder")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument("--format", default=None, choices=reader_formats(), help="force a reader instead of detecting the format per file")
    p.set_defaults(func=run)


def format_line(summary: dict, path: str) -> str:
    per_type = summary["tracks_per_type"]
    return (f"{summary['source']:<20} {summary['scenario_id']:<24} frames={summary['frames']:<4} "
            f"tracks={summary['tracks']:<4} (veh {per_type['vehicle']}, ped {per_type['pedestrian']}, "
            f"cyc {per_type['cyclist']}, other {per_type['other']})  lanes={summary['lanes']} "
            f"(with successors {summary['lanes_with_successors']}, with predecessors "
            f"{summary['lanes_with_predecessors']})  road_edges={summary['road_edges']} "
            f"crosswalks={summary['crosswalks']} tl_frames={summary['traffic_light_frames']}  {path}")


def run(args) -> int:
    failures = 0
    for root in args.paths:
        try:
            files = expand_paths(root)
        except ScenarioReadError as exc:
            print(f"smart-marl info: error: {exc}", file=sys.stderr)
            failures += 1
            continue
        if not files:
            raise UsageError(f"{root}: no scene file in this folder (names like *.tfrecord*, *.pkl, *.json, *.parquet, *.smsc)")
        for path in files:
            try:
                fmt = args.format or detect_format(path)
                for scenario in read_scenarios(path, format=fmt):
                    summary = scenario.summary()
                    if args.json:
                        print(json.dumps({"format": fmt, "path": path, **summary}), flush=True)
                    else:
                        print(format_line(summary, path), flush=True)
            except ScenarioReadError as exc:
                print(f"smart-marl info: error: {exc}", file=sys.stderr)
                failures += 1
    return 1 if failures else 0
