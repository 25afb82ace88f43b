"""``smart-marl demo``: the README's main command, on embedded defaults (no data on disk needed).

The package's own sample scenes (generated with SUMO, shipped inside the package) are simulated
closed-loop by the embedded SMART prior: 8 s of every agent, several rollouts per scene. The demo
writes a bird's-eye-view animation of one rollout next to the logged scene and prints the realism
table (the sim-agents metrics) of the prior next to constant velocity and log replay on the same
scenes.

Without the ``render`` extra (matplotlib, imageio) the demo says the animation needs it and still
prints the realism table.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ..embedded import EMBEDDED, sample_scenarios
from ..metrics import aggregate, logged_scene, score_rollouts
from ..metrics.baselines import policy_rollouts
from ..model.checkpoint import load_prior, read_meta, resolve_checkpoint_path
from ..render import BevRenderer, EpisodeRecorder
from ..rollout import rollout
from .arguments import device, output_dir, rollouts, seed
from .eval import format_table, prior_rollouts


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="simulate the built-in sample scenes with the embedded SMART prior",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("--out", default="out/demo", type=output_dir, help="output folder (default: out/demo)")
    p.add_argument("--rollouts", type=rollouts, default=32, help="rollouts per scene (default 32, as the metrics expect)")
    p.add_argument("--seed", type=seed, default=0, help="random seed of the rollouts (default 0)")
    p.add_argument("--checkpoint", default=None, help="a SMART checkpoint instead of the embedded prior")
    p.add_argument("--device", default="cpu", type=device, help="torch device (default cpu)")
    p.add_argument("--format", choices=("mp4", "gif"), default="mp4", help="animation format (default mp4)")
    p.set_defaults(func=run)


def _animation_frames(scenario, result, group: int, size_px: int = 480):
    """BEV frames: the logged history up to the current frame, then rollout ``group``'s future."""
    tr, cf = scenario.tracks, scenario.current_frame
    renderer = BevRenderer(scenario, size_px=size_px, view_radius_m=50.0)
    future = result.trajectory[group]  # [A, T, 4] source frame
    local_xy = scenario.frame.from_source(future[..., :3])[..., :2]
    local_h = future[..., 3] - scenario.frame.heading
    alive = result.has_trajectory[group]
    sizes = tr.size[:, cf, :2]
    controlled = np.zeros(tr.num_tracks, bool)
    frames = []
    for f in range(cf + 1):
        frames.append(renderer.render(tr.position[:, f, :2], tr.heading[:, f], tr.size[:, f, :2], tr.valid[:, f], tr.types,
                                      controlled=controlled, ego_index=scenario.sdc_index,
                                      text=f"{scenario.scenario_id}  log  t={f / 10:.1f} s"))
    trail = [tr.position[:, max(0, cf - 9) : cf + 1, :2]]
    for k in range(local_xy.shape[1]):
        history = np.concatenate([trail[0], local_xy[:, max(0, k - 9) : k + 1]], axis=1)[:, -10:]
        frames.append(renderer.render(local_xy[:, k], local_h[:, k], sizes, alive, tr.types, controlled=controlled,
                                      ego_index=scenario.sdc_index, trajectories=history,
                                      text=f"{scenario.scenario_id}  SMART rollout  t={(cf + 1 + k) / 10:.1f} s"))
    renderer.close()
    return frames


def _render_extra_missing() -> str | None:
    """Why the animation cannot be written (the ``render`` extra, matplotlib and imageio, is not
    installed), or None."""
    try:
        import imageio  # noqa: F401
        import matplotlib  # noqa: F401
    except ImportError as exc:
        return f"the animation needs the render extra (pip install 'smart-marl[render]'): {exc}"
    return None


def _write_animation(prior, first, out: Path, args) -> None:
    """One closed-loop rollout of ``first`` written as a BEV animation next to its logged history."""
    t1 = time.perf_counter()
    result = rollout(prior, first, num_rollouts=1, num_steps=16, seed=args.seed, device=args.device)
    print(f"closed-loop rollout of {first.scenario_id} ({int(result.simulated[0].sum())} agents simulated): "
          f"{time.perf_counter() - t1:.2f} s")
    video = out / f"{first.scenario_id}_rollout.{args.format}"
    recorder = EpisodeRecorder(video, fps=10)
    recorder.extend(_animation_frames(first, result, 0))
    recorder.write()
    print(f"wrote {video}")


def run(args) -> int:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    spec = args.checkpoint or EMBEDDED
    prior = load_prior(spec, args.device)
    scenes = sample_scenarios()
    print(f"SMART prior: {spec} ({prior.model.config.name}, step {read_meta(resolve_checkpoint_path(spec)).get('step', 0)}); "
          f"{len(scenes)} sample scenes; {args.rollouts} rollouts of 8 s each")

    missing = _render_extra_missing()
    if missing:  # the realism table needs no render extra: it is still computed
        print(f"smart-marl demo: {missing}; no animation written", file=sys.stderr)
    else:
        _write_animation(prior, scenes[0], out, args)

    tables = {}
    for policy in ("prior", "constant_velocity", "log_replay"):
        results = []
        for scenario in scenes:
            if policy == "prior":
                rollouts = prior_rollouts(prior, scenario, args.rollouts, args.seed, args.device)
            else:
                rollouts = policy_rollouts(policy, scenario, args.rollouts, args.seed)
            results.append(score_rollouts(logged_scene(scenario), rollouts, "2024", where=f"demo {policy}"))
        tables[policy] = aggregate(results, "2024")
    print()
    print(format_table(tables["prior"]))
    print()
    keys = ("meta_metric", "kinematic", "interactive", "map_based", "min_ade")
    print(f"{'policy':<20}" + "".join(f"{k:>13}" for k in keys))
    for policy, table in tables.items():
        print(f"{policy:<20}" + "".join(f"{table[k]:>13.4f}" for k in keys))
    (out / "realism.json").write_text(json.dumps({p: {k: t[k] for k in keys + ("likelihoods",)} for p, t in tables.items()},
                                                 indent=1))
    print(f"\nrealism (2024 rules) of the sample scenes written to {out / 'realism.json'}; "
          f"total {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return 0
