"""Benchmark of the environment stage: how fast the environment steps, the PettingZoo env
(``envs.smart_traffic_v0``, one scene) and the batched TorchRL env (``envs.smart_traffic_batched_v0``,
many scenes in one SMART forward) side by side in one run, on the same scenes and prior.

Prints one JSON line per configuration:

* ``env`` ``"pettingzoo"`` or ``"batched"``, ``num_scenes`` (1 for the PettingZoo env), ``background``;
* ``agent_steps_per_s``: every agent present in a scene advanced by one 0.5 s token step (the
  scene's simulated agents, not only the controlled ones), over the time spent in ``step``;
  ``controlled_agent_steps_per_s``; ``env_steps_per_s`` (scene-steps);
* ``outside_forward_share``: the share of the step's time spent outside the prior's forward (the
  model's incremental step and heads; sampling, collision-aware token exclusion, dynamics, events,
  rewards, observations and TorchRL's bookkeeping count as outside);
* ``reset_ms_per_scene``: time of the resets / refills per scene started (after a warm-up pass
  that starts every scene's prior once: both envs keep freshly started prior states);
* ``rss_mb``: the process's resident memory (every configuration's env is alive: the last lines carry all);
* ``speedup_vs_pettingzoo``: agent-steps/s against the PettingZoo line of the same run (medians), and
  ``speedup_per_repeat``: the ratio within each repeat (the repeats interleave every configuration);
* ``forward_us_per_agent_step``: the prior's forward alone, per agent-step (microseconds), and on the
  batched lines ``speedup_bound_forward_only``: the speed-up the batched env would reach if nothing
  but its forward took time (the PettingZoo env's whole step per agent-step over the batched forward's),
  the ceiling that work outside the forward cannot lift.

Actions: each controlled agent takes its prior's most likely token; ``terminate_on=()`` so that an
episode runs its full horizon. Scenes: ``--scenes`` (default: the shared real scenes with a moving
vehicle to control, ../shared/data), cycled to fill the batch. Prior: ``--prior`` (default the
embedded one). Medians of ``--repeats`` timed runs. ``--traffic-control both``: every configuration with the
background's traffic control and speed persistence (the envs' defaults) and without either, interleaved; each line carries ``traffic_control`` and
its speed-up is against the PettingZoo env with the same setting, the "on" lines ``agent_steps_per_s_vs_off``.

    .venv/bin/python benchmarks/env_throughput.py [--num-scenes 1,8,32,128] [--steps 32] [--threads 2] [--device cpu]
        [--traffic-control on|off|both]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"


def real_scenes():
    """The shared real scenes (every format) that the metrics' horizon fits: 91 frames."""
    from smart_marl.readers import read_scenarios

    out = []
    for sub in ("womd_tfrecord", "gpudrive_json", "nocturne_json", "scenarionet/waymo", "smart_pkl"):
        folder = SHARED / sub
        if folder.is_dir():
            for path in sorted(folder.iterdir()):
                if path.suffix in (".tfrecord", ".json", ".pkl") and "sim_agents" not in path.name:
                    try:
                        out.extend(s for s in read_scenarios(path) if s.tracks.num_frames == 91)
                    except Exception as exc:  # noqa: BLE001 - a benchmark skips what it cannot read, and says so
                        print(json.dumps({"skipped": str(path), "why": str(exc)[:120]}), file=sys.stderr)
    return out


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def present_agents(core) -> int:
    return int(core.present.sum())


def time_pettingzoo(env, scene_indices, steps: int) -> dict:
    """Step time over ``steps`` env steps cycling through the scenes (resets timed apart)."""
    import numpy as np

    step_s = reset_s = forward_s = 0.0
    agent_steps = ctrl_steps = done_steps = resets = 0
    k = 0
    while done_steps < steps:
        t0 = time.perf_counter()
        obs, infos = env.reset(seed=k, options={"scene_index": scene_indices[k % len(scene_indices)]})
        reset_s += time.perf_counter() - t0
        resets += 1
        k += 1
        while env.agents and done_steps < steps:
            actions = {a: int(np.argmax(infos[a]["prior_logits"])) for a in env.agents}
            moving = present_agents(env.core)
            f0 = env.core.timing["forward_s"]
            t0 = time.perf_counter()
            obs, _, _, _, infos = env.step(actions)
            step_s += time.perf_counter() - t0
            forward_s += env.core.timing["forward_s"] - f0
            done_steps += 1
            agent_steps += moving
            ctrl_steps += len(actions)
    return dict(step_s=step_s, reset_s=reset_s, resets=resets, agent_steps=agent_steps, ctrl_steps=ctrl_steps, env_steps=done_steps,
                forward_s=forward_s)


def time_batched(env, steps: int) -> dict:
    """Step time over ``steps`` batched steps (every scene steps once per batched step); refills timed apart."""
    from torchrl.envs.utils import step_mdp

    core = env.core
    td = env.reset()
    step_s = reset_s = 0.0
    agent_steps = ctrl_steps = env_steps = refills = 0
    forward_steps = 0.0
    for _ in range(steps):
        logits = td["agents", "observation", "prior_logits"]
        td["agents", "action"] = logits.argmax(-1)
        moving = present_agents(core)
        live = int(core.live.sum())
        f0 = core.timing["forward_s"]
        t0 = time.perf_counter()
        td = env.step(td)
        if core.device.type == "cuda":
            torch.cuda.synchronize(core.device)
        step_s += time.perf_counter() - t0
        forward_steps += core.timing["forward_s"] - f0
        agent_steps += moving
        ctrl_steps += live
        env_steps += env.num_scenes
        td = step_mdp(td)
        done = td["done"].reshape(-1)
        if bool(done.any()):
            refills += int(done.sum())
            t0 = time.perf_counter()
            td = env.reset(td.set("_reset", td["done"].clone()))
            if core.device.type == "cuda":
                torch.cuda.synchronize(core.device)
            reset_s += time.perf_counter() - t0
    return dict(step_s=step_s, reset_s=reset_s, resets=refills, agent_steps=agent_steps, ctrl_steps=ctrl_steps, env_steps=env_steps,
                forward_s=forward_steps)


def summarise(runs: list[dict]) -> dict:
    med = lambda key: statistics.median(r[key] for r in runs)  # noqa: E731
    rates = [r["agent_steps"] / r["step_s"] for r in runs]
    return dict(agent_steps_per_s=round(statistics.median(rates), 1),
                controlled_agent_steps_per_s=round(statistics.median(r["ctrl_steps"] / r["step_s"] for r in runs), 1),
                env_steps_per_s=round(statistics.median(r["env_steps"] / r["step_s"] for r in runs), 2),
                outside_forward_share=round(1.0 - med("forward_s") / med("step_s"), 3),
                forward_us_per_agent_step=round(1e6 * statistics.median(r["forward_s"] / r["agent_steps"] for r in runs), 1),
                reset_ms_per_scene=round(1000 * statistics.median(r["reset_s"] / max(r["resets"], 1) for r in runs), 1),
                agent_steps_per_s_runs=[round(x, 1) for x in rates])


def main() -> int:
    from envs._arguments import shield_option
    from envs._shield import DEFAULT_SHIELD_CHECKS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenes", default=None, help="scenes (any path read_scenarios reads; default: the shared real scenes)")
    p.add_argument("--prior", default="embedded")
    p.add_argument("--num-scenes", default="1,8,32,128", help="batch sizes of the batched env")
    p.add_argument("--steps", type=int, default=32, help="timed steps per configuration and repeat, at least (more where it takes "
                   "more for every scene to be played once)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--horizon", type=int, default=16)
    p.add_argument("--background", default="prior", choices=("prior", "log", "constant_velocity"))
    p.add_argument("--controlled", default="moving_vehicles")
    p.add_argument("--max-agents", type=int, default=4)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--device", default="cpu")
    p.add_argument("--shield", nargs="?", type=shield_option, const=DEFAULT_SHIELD_CHECKS, default=(),
                   help="the controlled agents' shield (envs._shield), checked to the top 3: its checks joined with '+' "
                   "(alone: collision+offroad, shield=True)")
    p.add_argument("--traffic-control", default="on", choices=("on", "off", "both"),
                   help="the background's traffic control and speed persistence (stop_lines=True, lights='log', "
                        "persistence 0.25: the envs' defaults) or none (stop_lines=False, lights='current', persistence 0); "
                        "both: side by side in one run, each against the PettingZoo env with the same setting (default on)")
    p.add_argument("--stop-lines", dest="traffic_control", action="store_const", const="on",
                   help="--traffic-control on (kept for older command lines)")
    args = p.parse_args()
    checks = args.shield
    torch.set_num_threads(args.threads)

    from envs import smart_traffic_batched_v0, smart_traffic_v0
    from envs._setup import load_scenes
    from smart_marl.model.checkpoint import load_prior
    from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE

    scenes = load_scenes(args.scenes) if args.scenes else real_scenes()
    model, vocab = load_prior(args.prior, args.device)
    settings = {"on": dict(stop_lines=True, lights="log", persistence=DEFAULT_PERSISTENCE),
                "off": dict(stop_lines=False, lights="current", persistence=0.0)}
    chosen = ["on", "off"] if args.traffic_control == "both" else [args.traffic_control]
    kw = dict(prior=model, motion_vocab=vocab, controlled=args.controlled, max_agents=args.max_agents, background=args.background,
              horizon_steps=args.horizon, terminate_on=(), device=args.device,
              **(dict(shield=list(checks), reference_top_k=3) if checks else {}))
    common = dict(benchmark="env_throughput", background=args.background, shield="+".join(checks) or False,
                  prior=args.prior, controlled=args.controlled,
                  max_agents=args.max_agents, horizon_steps=args.horizon, torch_threads=args.threads, device=args.device,
                  cpu=platform.processor() or platform.machine(), scenes=len(scenes))
    if args.device.startswith("cuda"):
        common["gpu"] = torch.cuda.get_device_name(args.device)

    # the PettingZoo env: one scene at a time, the scenes with an agent to control
    pz = {c: smart_traffic_v0.parallel_env(scenarios=scenes, observation="dict", **kw, **settings[c]) for c in chosen}
    usable = []
    for i in range(len(scenes)):
        try:
            pz[chosen[0]].reset(seed=0, options={"scene_index": i})
            usable.append(i)
        except Exception:  # noqa: BLE001 - no agent to control in this scene
            pass
    for env in pz.values():
        env.PRIOR_STATE_CACHE = env.core.prior_cache_size = len(usable)  # keep every scene's prior, as the batched env does
        time_pettingzoo(env, usable, len(usable) * args.horizon)  # warm-up: every scene's prior started once
    pool = [scenes[i] for i in usable]
    sizes = [int(x) for x in args.num_scenes.split(",")]
    batched = {}
    for c in chosen:
        for b in sizes:
            env = smart_traffic_batched_v0.SmartTrafficBatchedEnv(scenarios=pool, num_scenes=b, scene_order="sequential", **kw,
                                                                  **settings[c])
            time_batched(env, max(args.horizon, len(pool) * args.horizon // b))  # warm-up: every scene's prior started once
            batched[c, b] = env
    # the repeats interleave the configurations, so that a load that comes and goes weighs on all of them alike
    runs = {**{("pettingzoo", c): [] for c in chosen}, **{key: [] for key in batched}}
    # every repeat plays every scene at least once on each env (the PettingZoo env starts from the first scene each
    # time; the batched env goes on through the pool): both are timed on the same scenes, not on the first few
    every = len(usable) * args.horizon
    for _ in range(args.repeats):
        for c in chosen:
            runs["pettingzoo", c].append(time_pettingzoo(pz[c], usable, max(args.steps, every)))
            for b in sizes:
                runs[c, b].append(time_batched(batched[c, b], max(args.steps, -(-every // b))))
    for c in chosen:
        rules = dict(traffic_control=c, **settings[c])
        base = summarise(runs["pettingzoo", c])
        print(json.dumps(dict(env="pettingzoo", num_scenes=1, **base, rss_mb=round(rss_mb()), **rules, **common)), flush=True)
        for b in sizes:
            line = dict(env="batched", num_scenes=b, **summarise(runs[c, b]), rss_mb=round(rss_mb()), **rules, **common)
            line["speedup_vs_pettingzoo"] = round(line["agent_steps_per_s"] / base["agent_steps_per_s"], 2)
            ratios = [(r["agent_steps"] / r["step_s"]) / (p["agent_steps"] / p["step_s"])
                      for r, p in zip(runs[c, b], runs["pettingzoo", c])]
            line["speedup_per_repeat"] = [round(x, 2) for x in ratios]
            line["speedup_bound_forward_only"] = round(1e6 / base["agent_steps_per_s"] / line["forward_us_per_agent_step"], 2)
            if c == "on" and "off" in chosen:  # the rules' cost, side by side
                off = summarise(runs["off", b])["agent_steps_per_s"]
                line["agent_steps_per_s_vs_off"] = round(line["agent_steps_per_s"] / off, 3)
            print(json.dumps(line), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
