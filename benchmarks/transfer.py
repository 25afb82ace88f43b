"""Transfer across datasets (issue 59; the paper's SMART-zeroshot and SMART**): a prior's realism on every dataset
with real scenes in ``../shared/data`` and on held-out generated scenes, next to the constant-velocity and
log-replay rows, each scored the same way: ``smart-marl eval --policy ... --rules 2024 --rollouts 32 --json``
through its default window (:mod:`smart_marl.metrics.windows`: the scene's own current frame, or the nearest
window that fits; other rates resampled to 10 Hz).

One JSON line per (dataset, row): the meta-metric, its three parts, minADE, the scenes scored and skipped (with
why), how the scored scenes' evaluated agents were chosen (``evaluated``: scenes per
:data:`~smart_marl.metrics.windows.EVALUATED_BY`: the tracks to predict, or the rule anchored on the self-driving car
or on the farthest-moving agent), the command. Then the markdown table the docs carry. Rows: ``prior`` (the
embedded prior, trained on generated scenes only: zero-shot on every real dataset), ``few-shot`` (``--few-shot
CKPT``: a checkpoint tuned on some real scenes; its training scenes are left out of the datasets it is scored on with
``--exclude``), ``constant_velocity``, ``log_replay``.

    .venv/bin/python benchmarks/transfer.py --generated data/scaling_val [--few-shot runs/fewshot/checkpoints/final]
    .venv/bin/python benchmarks/transfer.py --datasets "Nocturne JSON" "GPUDrive JSON"   # some of DATASETS only
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DATASETS = {"WOMD (tfrecord)": "womd_tfrecord/*.tfrecord", "WOMD (SMART pickles)": "smart_pkl", "WOMD (ScenarioNet)": "scenarionet/waymo",
            "nuScenes (ScenarioNet)": "scenarionet/nuscenes", "Argoverse 2": "av2", "GPUDrive JSON": "gpudrive_json",
            "Nocturne JSON": "nocturne_json"}


def evaluated_by(scenes: str) -> dict[str, int]:
    """Scenes (windows) per way their evaluated agents are chosen in eval's default window, over the scenes that have any."""
    from smart_marl.errors import SmartMarlError
    from smart_marl.metrics.windows import evaluated_by as chosen_by, scene_windows
    from smart_marl.readers import expand_paths, read_scenarios

    counts: dict[str, int] = {}
    for path in expand_paths(scenes):
        try:
            scenarios = list(read_scenarios(path))
        except SmartMarlError:  # what eval --skip-bad skips
            continue
        for scenario in scenarios:
            try:
                windows = scene_windows(scenario)
            except SmartMarlError:
                continue
            for window in windows:
                how = chosen_by(window)
                if how is not None:
                    counts[how] = counts.get(how, 0) + 1
    return dict(sorted(counts.items()))


def score(scenes: str, policy: str, rollouts: int, seed: int, checkpoint: str | None = None) -> dict:
    cmd = [sys.executable, "-m", "smart_marl.cli", "eval", "--scenes", scenes, "--policy", "prior" if checkpoint else policy,
           "--rules", "2024", "--rollouts", str(rollouts), "--seed", str(seed), "--json", "--skip-bad"]
    if checkpoint:
        cmd += ["--checkpoint", checkpoint]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    shown = " ".join(c if c != sys.executable else "python" for c in cmd)
    if done.returncode != 0:
        return {"error": (done.stderr.strip().splitlines() or ["?"])[-1][:300], "command": shown}
    out = json.loads(done.stdout)
    return {k: out[k] for k in ("meta_metric", "kinematic", "interactive", "map_based", "min_ade", "num_scenarios")} | {
        "skipped": len(out.get("skipped", [])), "skip_reasons": sorted({s["reason"][:80] for s in out.get("skipped", [])}),
        "command": shown}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--generated", default=None, help="held-out generated scenes (a scene cache)")
    p.add_argument("--few-shot", default=None, metavar="CKPT", help="a checkpoint tuned on some real scenes")
    p.add_argument("--few-shot-trained-on", nargs="*", default=[], metavar="DATASET",
                   help="the DATASETS names the few-shot checkpoint trained on: its row there is marked (in-sample)")
    p.add_argument("--rollouts", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--datasets", nargs="+", choices=list(DATASETS), default=list(DATASETS), metavar="NAME",
                   help="only these of the shared datasets (default: all): " + ", ".join(DATASETS))
    args = p.parse_args()
    sets = {name: str(SHARED / rel) for name, rel in DATASETS.items() if name in args.datasets}
    if args.generated:
        sets["generated (held-out)"] = args.generated
    rows = [("prior (zero-shot on real)", "prior", None)]
    if args.few_shot:
        rows.append(("few-shot", "prior", args.few_shot))
    rows += [("constant velocity", "constant_velocity", None), ("log replay", "log_replay", None)]
    table: dict = {}
    for name, scenes in sets.items():
        chosen = evaluated_by(scenes)
        for label, policy, ckpt in rows:
            line = {"benchmark": "transfer", "dataset": name, "row": label, "rollouts": args.rollouts, "seed": args.seed,
                    "rules": "2024", **score(scenes, policy, args.rollouts, args.seed, ckpt), "evaluated": chosen}
            if ckpt and name in args.few_shot_trained_on:
                line["in_sample"] = True
            print(json.dumps(line), flush=True)
            table[name, label] = line
    labels = [r[0] for r in rows]
    print("\n| dataset | scenes | " + " | ".join(labels) + " |", file=sys.stderr)
    print("|---|---|" + "---|" * len(labels), file=sys.stderr)
    for name in sets:
        first = table[name, labels[0]]
        cells = []
        for label in labels:
            r = table[name, label]
            cell = "-" if "meta_metric" not in r else f"{r['meta_metric']:.4f}" + (" (in-sample)" if r.get("in_sample") else "")
            cells.append(cell)
        count = first.get("num_scenarios", 0)
        print(f"| {name} | {count} (+{first.get('skipped', 0)} skipped) | " + " | ".join(cells) + " |", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
