"""``smart-marl whatif SCENE --script FILE.yaml --out DIR``: a scripted what-if scenario against the
unperturbed rollouts with the same seeds (agents stage: :mod:`agents.whatif`).

Writes ``DIR/whatif.gif`` (or ``.mp4``; baseline left, what-if right, rollout 0), ``DIR/table.csv``
(collisions, minimum distances and speeds of the affected agents, speeds of the vehicles behind a
braking or stalled one, realism) and prints the table.

Registered through the ``smart_marl.commands`` entry point (see :mod:`agents.commands`).
"""

from __future__ import annotations

from pathlib import Path

from smart_marl.commands.arguments import (bounded_int, collision_avoidance_flag, device, lights_option, output_dir, rollouts, seed,
                                          persistence_option, precision_option, stop_lines_flag)
from smart_marl.embedded import scene_sources
from smart_marl.errors import SmartMarlError
from smart_marl.readers import read_scenarios

from ..whatif import MAX_STEPS, example_scripts, format_table, load_script, render_comparison, run_whatif, script_path, write_table_csv


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "whatif", help="run a scripted what-if scenario (remove/insert agents, brake, cut-in, lights) against the baseline",
        description="Apply a what-if script (YAML; the package ships one per kind, agents/whatif/examples/) to one scene, "
                    "roll out the SMART prior with and without it (same seeds) and write a side-by-side animation and a "
                    "table of what changed.")
    p.add_argument("scene", metavar="SCENE", help="a scene file, folder or glob, or 'embedded' (the package's sample "
                                                  "scenes); the first scene, or --scenario-id")
    p.add_argument("--script", required=True, metavar="FILE", help="the what-if script (.yaml), or the name of a shipped "
                                                                    f"example ({', '.join(example_scripts())})")
    p.add_argument("--out", required=True, type=output_dir, metavar="DIR", help="output folder (created if missing)")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the rollouts (default 0)")
    p.add_argument("--rollouts", type=rollouts, default=8, help="rollouts per run (default 8)")
    p.add_argument("--steps", type=bounded_int(1, MAX_STEPS, "32 s"), default=16, help="token steps of 0.5 s (default 16: 8 s; at most 64)")
    p.add_argument("--checkpoint", metavar="C", default=None, help="SMART checkpoint (default: the embedded prior)")
    p.add_argument("--device", default="cpu", type=device, help="torch device the model runs on (default cpu)")
    p.add_argument("--scenario-id", default=None, help="pick this scene when SCENE holds several")
    p.add_argument("--animation", choices=("gif", "mp4", "none"), default="gif", help="animation format (default gif)")
    p.add_argument("--no-realism", action="store_true", help="skip the realism metric (faster)")
    collision_avoidance_flag(p, "the prior (both runs)")
    stop_lines_flag(p, "the prior (both runs)")
    lights_option(p, "log")
    persistence_option(p, "the prior (both runs)")
    precision_option(p, "the prior (both runs)")
    p.set_defaults(func=run)


def run(args) -> int:
    script = load_script(script_path(args.script))  # every edit's values checked here, before the scene is read
    scene = None
    for sc in read_scenarios(scene_sources(args.scene)):
        if args.scenario_id is None or sc.scenario_id == args.scenario_id:
            scene = sc
            break
    if scene is None:
        raise SmartMarlError(f"{args.scene}: no scene" + (f" with id {args.scenario_id}" if args.scenario_id else ""))
    result = run_whatif(args.checkpoint, scene, script, num_rollouts=args.rollouts, seed=args.seed, num_steps=args.steps,
                        device=args.device, realism=not args.no_realism, avoid_collisions=args.avoid_collisions,
                        stop_lines=args.stop_lines, lights=args.lights, precision=args.precision,
                        persistence=args.persistence)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = write_table_csv(result.table, out / "table.csv")
    print(f"what-if '{script.name}' on {scene.scenario_id}: {args.rollouts} rollouts, seed {args.seed}")
    print(format_table(result.table))
    print(f"table -> {csv_path}")
    if args.animation != "none":
        anim = render_comparison(result, out / f"whatif.{args.animation}")
        print(f"animation -> {anim}")
    return 0
