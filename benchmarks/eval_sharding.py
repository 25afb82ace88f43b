"""Scenes per second of ``smart-marl eval`` in one process against two shards run at once.

Every repeat runs, one after the other on the same scenes (SUMO-generated, or ``--data``):

* ``1proc_1thread``: one process, ``--out RUN`` (one shard, merged at once), 1 torch thread;
* ``2proc_1thread``: ``--shard 0/2`` and ``--shard 1/2`` started together, 1 torch thread each, then
  ``--merge`` (the merge is inside the timed span);
* with ``--two-threads``, also ``1proc_2threads``: one process with 2 torch threads.

Two rates per mode: ``scenes_per_s`` from the wall-clock seconds of the whole commands (process start:
Python, torch, the checkpoint; and the merge), as a user sees them on this many scenes; and
``scoring_scenes_per_s`` from the seconds the shards spent scoring (their ``scored now in X s``
line; with two shards, the slower one), the rate a long run (45k scenes) approaches. One JSON line per
mode (medians over ``--repeats``, every repeat's seconds, and ``cpu_seconds``: the CPU time the
mode's processes used, user + system) and a summary line: the ratios of the medians, whether the
merged numbers equal the one-process numbers exactly, and the load average. Read the ratios with the
machine's state: where other sessions keep the cores busy and the kernel shares the CPU between
sessions (``/proc/sys/kernel/sched_autogroup_enabled``), two processes of one session get no more
CPU than one; equal ``cpu_seconds`` then say the split itself costs little.
Usage: python benchmarks/eval_sharding.py [--scenes 16] [--rollouts 4] [--repeats 3] [--policy prior] [--two-threads]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CLI = [sys.executable, "-m", "smart_marl.cli"]


def _env(threads: int) -> dict:
    return {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}


def _check(proc: subprocess.Popen, what: str) -> tuple[str, float | None]:
    """(stdout, the seconds the shard spent scoring, from its summary line on stderr)."""
    out, err = proc.communicate()
    if proc.returncode != 0:
        raise SystemExit(f"{what} failed ({proc.returncode}):\n{err[-3000:]}")
    m = re.search(r"scored now in ([0-9.]+) s", err)
    return out, float(m.group(1)) if m else None


def one_process(base: list[str], run: Path, threads: int) -> tuple[float, float, dict]:
    t0 = time.perf_counter()
    out, scoring = _check(subprocess.Popen([*base, "--out", str(run)], env=_env(threads), stdout=subprocess.PIPE,
                                           stderr=subprocess.PIPE, text=True), f"1 process, {threads} thread(s)")
    return time.perf_counter() - t0, scoring, json.loads(out)


def two_shards(base: list[str], run: Path) -> tuple[float, float, dict]:
    t0 = time.perf_counter()
    procs = [subprocess.Popen([*base, "--out", str(run), "--shard", f"{i}/2"], env=_env(1), stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in range(2)]
    scoring = max(_check(p, f"shard {i}/2")[1] for i, p in enumerate(procs))
    out, _ = _check(subprocess.Popen([*CLI, "eval", "--merge", str(run), "--json"], env=_env(1), stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True), "merge")
    return time.perf_counter() - t0, scoring, json.loads(out)


def _autogroup() -> bool | None:
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip() == "1"
    except OSError:
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=int, default=16, help="SUMO scenes to generate (default 16)")
    parser.add_argument("--data", default=None, help="score these scenes instead of generated ones")
    parser.add_argument("--policy", default="prior", help="eval --policy (default prior, the embedded checkpoint)")
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--two-threads", action="store_true", help="also one process with 2 torch threads")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="eval_sharding-"))
    try:
        data = args.data
        if data is None:
            data = str(work / "scenes")
            subprocess.run([*CLI, "generate-sumo", "--scenes", str(args.scenes), "--out", data, "--seed", str(args.seed),
                            "--quiet"], check=True, capture_output=True)
        base = [*CLI, "eval", "--scenes", data, "--policy", args.policy, "--rollouts", str(args.rollouts), "--json"]
        modes = ["1proc_1thread", "2proc_1thread"] + (["1proc_2threads"] if args.two_threads else [])
        wall: dict[str, list[float]] = {m: [] for m in modes}
        scoring: dict[str, list[float]] = {m: [] for m in modes}
        cpu: dict[str, list[float]] = {m: [] for m in modes}
        identical, num_scenes, loads = True, None, []
        for r in range(args.repeats):
            for mode in modes:  # side by side: each repeat runs every mode, one after the other
                before = resource.getrusage(resource.RUSAGE_CHILDREN)
                if mode == "2proc_1thread":
                    seconds, scored, result = two_shards(base, work / f"{mode}-{r}")
                else:
                    seconds, scored, result = one_process(base, work / f"{mode}-{r}", 2 if mode == "1proc_2threads" else 1)
                after = resource.getrusage(resource.RUSAGE_CHILDREN)
                cpu[mode].append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
                wall[mode].append(seconds)
                scoring[mode].append(scored)
                if mode == "1proc_1thread":
                    single = result
                elif mode == "2proc_1thread":
                    identical &= result == single
                loads.append(os.getloadavg()[0])
            num_scenes = single["num_scenarios"] + len(single["skipped"])
        rate = {m: num_scenes / statistics.median(ts) for m, ts in wall.items()}
        score_rate = {m: num_scenes / statistics.median(ts) for m, ts in scoring.items()}
        for mode in modes:
            print(json.dumps({"benchmark": "eval_sharding", "mode": mode, "scenes": num_scenes, "policy": args.policy,
                              "rollouts": args.rollouts, "scenes_per_s": round(rate[mode], 4),
                              "scoring_scenes_per_s": round(score_rate[mode], 4),
                              "wall_seconds": [round(t, 2) for t in wall[mode]],
                              "scoring_seconds": [round(t, 2) for t in scoring[mode]],
                              "cpu_seconds": [round(t, 2) for t in cpu[mode]]}), flush=True)
        summary = {
            "benchmark": "eval_sharding", "summary": True, "cpus": os.cpu_count(), "autogroup": _autogroup(),
            "load_average_1min_median": round(statistics.median(loads), 2),
            "ratio_2proc_vs_1proc": round(rate["2proc_1thread"] / rate["1proc_1thread"], 3),
            "scoring_ratio_2proc_vs_1proc": round(score_rate["2proc_1thread"] / score_rate["1proc_1thread"], 3),
            "merged_equals_one_process": identical, "repeats": args.repeats,
            "note": "medians over repeats; scenes_per_s: whole commands (start, merge); scoring: the shards' scoring time",
        }
        if args.two_threads:
            summary["ratio_2proc_vs_1proc_2threads"] = round(rate["2proc_1thread"] / rate["1proc_2threads"], 3)
        print(json.dumps(summary), flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
