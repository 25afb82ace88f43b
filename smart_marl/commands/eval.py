"""``smart-marl eval``: sim-agents realism metrics of rollouts, from a submission file or a policy.

Stage: metrics (the end of the data flow). ``--submission FILE`` scores the rollouts a
``SimAgentsChallengeSubmission`` file holds; ``--policy NAME`` first generates them
(constant_velocity, log_replay, random, or ``prior``: closed-loop rollouts of the SMART prior, the
package's embedded checkpoint unless ``--checkpoint`` names another). Prints a table
per feature and category plus the meta-metric and minADE, or one JSON object with ``--json``;
``--write-submission OUT`` saves policy rollouts as an uploadable submission file.

Every scene is scored through a 91-frame, 10 Hz window (``--window``, :mod:`smart_marl.metrics.windows`):
``current`` (default) the one at the scene's own current frame (the nearest that fits when it does not),
``all`` every window that fits with an agent to evaluate (each its own scenario ``SCENEID@FRAME``), or an
integer current frame;
scenes at other rates are resampled to 10 Hz. A scene the metrics cannot score (no window fits, a
rate that cannot be resampled, no evaluated agent)
is skipped with a warning naming the file and the scene, and listed under ``skipped`` in the JSON;
a file that cannot be read stops the job (exit 1) unless ``--skip-bad``, which skips it the same
way. A submission must hold WOSAC's 32 rollouts per scenario (exit 1 otherwise) unless
``--any-rollout-count``, which scores it with a warning. ``--submission`` also takes a submission
split in files (their prefix ``PREFIX`` for ``PREFIX-00000-of-000NN``..., or their folder).

At challenge scale (``--out RUN``): the scenes are split over shards (``--shard I/N``, or the
RANK/WORLD_SIZE of ``torchrun``), each shard keeps its results chunk by chunk in RUN (a rerun
skips finished chunks), and ``--merge RUN`` gives the numbers of a single-process run and writes the
submission in files (:mod:`smart_marl.metrics.sharding`; docs/evaluation_at_scale.md).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from datetime import timedelta
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..config_files import strict_json
from ..errors import ScenarioReadError, UsageError
from ..metrics import SceneNotScorableError, aggregate, score_rollouts
from ..metrics.baselines import policy_rollouts
from ..metrics.config import get_rules
from ..metrics.inputs import RolloutError, Rollouts
from ..metrics.windows import EVALUATED_RULE, Window, parse_window, scene_windows
from ..metrics.run_files import RunDirError, metrics_record, plan_submission, write_submission_parts, write_whole
from ..metrics.sharding import (RunDir, SceneSlot, Shard, check_result_target, input_digest, merge_run, parse_shard, run_shard,
                                scene_slots, shard_from_torchrun)
from ..metrics.submission import (ScenarioRolloutArrays, build_submission, check_against_scene, open_submission,
                                  submission_files, write_rollouts)
from ..model.checkpoint import EMBEDDED, checkpoint_paths, load_prior, resolve_checkpoint_path
from ..readers import expand_paths, read_scenarios
from ..readers.scene_cache import file_sha256
from ..rollout import DEFAULT_TOP_K, rollout
from ..rollout.persistence import DEFAULT_PERSISTENCE
from ..version import __version__
from .arguments import (bounded_int, collision_avoidance_flag, device, output_dir, output_file, reader_formats, rollouts, seed,
                        lights_option, persistence_option, precision_option, stop_lines_flag, temperature, top_k)

POLICY_CHOICES = ("constant_velocity", "log_replay", "random", "prior")
WOSAC_ROLLOUTS = 32
"""Rollouts per scenario the challenge requires (a submission with another count is refused)."""
DEFAULT_CHUNK_SIZE = 64
"""Scenes per chunk of an ``--out`` run: the unit of resuming, and of the submission's files (about
2 MB of rollouts per WOMD scene with 32 rollouts: ~130 MB files, far below protobuf's 2 GiB)."""
MAX_CHUNK_SIZE = 1000
"""The most scenes per chunk (``--chunk-size``): a chunk's submission file is one protobuf message, which cannot exceed
2 GiB, and 1,000 WOMD scenes' 32 rollouts take about 2 GB."""

SCALE_HELP = """\
at challenge scale (a run folder; docs/evaluation_at_scale.md):
  smart-marl eval --scenes VAL --policy prior --out RUN [--write-submission RUN/submission.binproto]
      one process, resumable: rerun the same command after a crash and it skips the finished chunks
  smart-marl eval --scenes VAL --policy prior --out RUN --shard I/N   (I = 0..N-1, one per process or machine)
  smart-marl eval --merge RUN [--json]
      checks that every shard finished, prints the numbers a single-process run gives, writes RUN/result.json
      and, with rollouts kept, the submission files PREFIX-00000-of-000NN...
  torchrun --standalone --nproc_per_node=N -m smart_marl.cli eval --scenes VAL --policy prior --out RUN
      each rank takes shard RANK/WORLD_SIZE; rank 0 merges when all are done (across machines: torchrun
      --nnodes ... with RUN on a folder every machine shares)
scene k of the input (files in sorted order, records in order) belongs to shard k mod N, on every
machine and every rerun."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval", help="sim-agents realism metrics (WOSAC 2024/2025) of a submission file or a baseline policy",
        description="Score rollouts of the scenes in PATH with the Waymo Open Sim Agents Challenge realism metrics\n"
                    "(same numbers as the official package). Rollouts come from --submission FILE or are\n"
                    "generated with --policy.",
        epilog=SCALE_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", metavar="PATH", help="scene file, folder or glob (any length and rate; see --window); required "
                                                    "but with --merge")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--submission", metavar="FILE",
                     help="a SimAgentsChallengeSubmission file (.binproto), or a submission split in files: their prefix "
                          "(PREFIX for PREFIX-00000-of-000NN...) or their folder")
    src.add_argument("--policy", choices=POLICY_CHOICES, help="generate rollouts with a baseline policy")
    p.add_argument("--checkpoint", metavar="C", help="model checkpoint for --policy prior (default: the embedded prior)")
    p.add_argument("--device", default="cpu", type=device, help="torch device for --policy prior (default cpu)")
    p.add_argument("--top-k", type=top_k, default=None, metavar="K",
                   help=f"--policy prior samples among its K most likely tokens (default {DEFAULT_TOP_K}; 0: all of them)")
    p.add_argument("--temperature", type=temperature, default=None, metavar="T",
                   help="--policy prior samples from softmax(logits / T) (default 1)")
    collision_avoidance_flag(p, "--policy prior")
    stop_lines_flag(p, "--policy prior")
    lights_option(p, "current")
    persistence_option(p, "--policy prior")
    precision_option(p, "--policy prior")
    p.add_argument("--rollouts", type=rollouts, default=32, help="rollouts per scene for --policy (default 32)")
    p.add_argument("--seed", type=seed, default=0, help="random seed for --policy (default 0)")
    p.add_argument("--rules", choices=("2024", "2025"), default="2025", help="challenge rules (default 2025)")
    p.add_argument("--window", type=parse_window, default=None, metavar="current|all|FRAME",
                   help="the 91-frame 10 Hz window of each scene that is scored (1.1 s of history, 8 s of future): "
                        "current (default) at the scene's own current frame, or the nearest window that fits when that "
                        "frame lacks history or future (then named SCENEID@FRAME); all: every window that fits and has "
                        "an agent to evaluate, each scored as its own scenario SCENEID@FRAME; FRAME: the window whose current frame is FRAME (>= 10, "
                        "10 Hz frames). Scenes at 2 Hz, 5 Hz, 20 Hz... are resampled to 10 Hz first. Scenes without "
                        "tracks to predict evaluate " + EVALUATED_RULE.replace("%", "%%") + " (docs/metrics.md)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--write-submission", metavar="OUT", type=output_file,
                   help="with --policy: also write the rollouts as a submission file; with --out (and --merge): the "
                        "submission in files OUT-00000-of-000NN..., one per chunk (RUN/run.json keeps OUT when it lies "
                        "inside RUN; one outside is given again to --merge)")
    p.add_argument("--format", default=None, choices=reader_formats(), help="force a scene reader instead of detecting the format")
    p.add_argument("--skip-bad", action="store_true", help="skip scene files that cannot be read, with a warning (default: stop)")
    p.add_argument("--any-rollout-count", action="store_true",
                   help=f"score a submission that does not hold {WOSAC_ROLLOUTS} rollouts per scenario, with a warning "
                        f"(its numbers are not comparable with WOSAC's)")
    scale = p.add_argument_group("challenge scale (see below)")
    scale.add_argument("--out", metavar="RUN", type=output_dir, help="run folder: results kept per chunk (a rerun resumes), merged with --merge")
    scale.add_argument("--shard", type=parse_shard, metavar="I/N",
                       help="with --out: score shard I of N (I from 0; scene k goes to shard k mod N); default: "
                            "RANK/WORLD_SIZE under torchrun, else 0/1")
    scale.add_argument("--chunk-size", type=bounded_int(1, MAX_CHUNK_SIZE, "a 2 GB submission file"), default=None, metavar="K",
                       help=f"with --out: scenes per chunk, the unit of resuming and of the submission files "
                            f"(default {DEFAULT_CHUNK_SIZE}, at most {MAX_CHUNK_SIZE})")
    scale.add_argument("--merge", metavar="RUN", help="merge a finished --out run: print its numbers, write RUN/result.json "
                                                      "and the submission files")
    p.set_defaults(func=run)


def format_table(result: dict) -> str:
    rules = get_rules(result["rules"])
    lines = [f"sim-agents realism ({result['rules']} rules), {result['num_scenarios']} scenario(s)",
             f"{'feature':<30} {'likelihood':>10} {'weight':>7}"]
    for cat, members in rules.categories().items():
        for m in members:
            lines.append(f"{m:<30} {result['likelihoods'][m]:>10.4f} {rules.features[m].weight:>7.2f}")
        lines.append(f"{'  = ' + cat:<30} {result[cat]:>10.4f}")
    lines.append(f"{'realism meta-metric':<30} {result['meta_metric']:>10.4f}")
    lines.append(f"{'minADE (m)':<30} {result['min_ade']:>10.4f}")
    return "\n".join(lines)


def _warn(message: str) -> None:
    print(f"smart-marl eval: warning: {message}", file=sys.stderr, flush=True)


def _scenes(args, skipped: list[dict]):
    """(path, Scenario) of every scene of ``--scenes``; with ``--skip-bad`` a file that cannot be
    read is recorded in ``skipped`` (with what was read of it kept) instead of stopping the job."""
    for path in expand_paths(args.scenes):
        try:
            for scenario in read_scenarios(path, format=args.format):
                yield path, scenario
        except ScenarioReadError as exc:
            if not args.skip_bad:
                raise
            _warn(f"skipped the bad file {path}: {exc}")
            skipped.append({"path": path, "scenario_id": None, "reason": str(exc)})


def run(args) -> int:
    problem = _scale_problem(args)
    if problem:
        print(f"smart-marl eval: error: {problem}", file=sys.stderr)
        return 2
    if args.merge:
        return merge_command(args)
    for given, flag in ((args.checkpoint, "--checkpoint"), (args.top_k is not None, "--top-k"),
                        (args.temperature is not None, "--temperature")):
        if given and args.policy != "prior":
            print(f"smart-marl eval: error: {flag} only applies to --policy prior", file=sys.stderr)
            return 2
    if args.write_submission and not args.policy:
        print("smart-marl eval: error: --write-submission needs --policy", file=sys.stderr)
        return 2
    if args.any_rollout_count and not args.submission:
        print("smart-marl eval: error: --any-rollout-count applies to --submission", file=sys.stderr)
        return 2
    if args.policy and args.rollouts != WOSAC_ROLLOUTS:
        _warn(f"--rollouts {args.rollouts}: WOSAC scores {WOSAC_ROLLOUTS} rollouts per scene; these numbers are not comparable")
    if args.out:
        return run_sharded(args)
    submitted = open_submission(args.submission) if args.submission else None
    results, written, skipped = [], [], []
    models: dict = {}
    for path, scenario in tqdm(_scenes(args, skipped), desc="eval", unit="scene", file=sys.stderr, disable=None):
        for window, scene, problem in _logged_windows(args, path, scenario):
            if problem is not None:
                skipped.append({"path": path, "scenario_id": window, "reason": problem})
                continue
            rollouts, where = _rollouts_of(args, window, scene, submitted, models)
            if args.policy and args.write_submission:
                written.append(_submission_arrays(window, rollouts))
            results.append(score_rollouts(scene, rollouts, args.rules, where=where))
    if not results:
        print(f"smart-marl eval: error: no scene in {args.scenes} could be scored ({len(skipped)} skipped)", file=sys.stderr)
        return 1
    if args.write_submission:
        write_rollouts(args.write_submission, written, description=_submission_description(args.policy))
    print_result(args, aggregate(results, args.rules), skipped)
    return 0


def _windows(args, scenario) -> list[Window]:
    """The scoring windows ``--window`` asks for (:class:`SceneNotScorableError` when the scene has none)."""
    return scene_windows(scenario, args.window or "current")


def _logged_windows(args, path: str, scenario, windows: list[Window] | None = None):
    """``(window Scenario, its LoggedScene, None)`` for every window of a scene to score, or ``(scenario id,
    None, reason)`` for a scene or window the metrics cannot score (warned about here)."""
    try:
        windows = _windows(args, scenario) if windows is None else windows
    except SceneNotScorableError as exc:
        _warn(f"{path}: skipped: {exc}")
        yield scenario.scenario_id, None, str(exc)
        return
    for window in windows:
        if window.shifted and not getattr(args, "_warned_shift", False):
            args._warned_shift = True
            _warn(f"{path}: scenario {scenario.scenario_id}: {window.shifted} (said once per run; such windows' ids "
                  "carry @FRAME)")
        try:
            yield window.scenario, window.logged(), None
        except SceneNotScorableError as exc:
            _warn(f"{path}: skipped: {exc}")
            yield window.scenario.scenario_id, None, str(exc)


def result_json(out: dict, skipped: list[dict]) -> dict:
    """The object ``--json`` prints: the aggregated numbers and the skipped scenes."""
    keys = ("meta_metric", "kinematic", "interactive", "map_based", "min_ade", "likelihoods", "num_scenarios", "rules")
    return {**{k: out[k] for k in keys}, "skipped": skipped}


def print_result(args, out: dict, skipped: list[dict]) -> None:
    if args.json:
        print(strict_json(result_json(out, skipped)))  # NaN/inf as null: JSON, not Infinity
    else:
        print(format_table(out))
        if skipped:
            print(f"{len(skipped)} scene(s) or file(s) skipped (see the warnings)")


def _submission_description(policy: str) -> str:
    return f"smart-marl policy {policy}"


def _submission_arrays(scenario, rollouts) -> ScenarioRolloutArrays:
    return ScenarioRolloutArrays(scenario.scenario_id, rollouts.object_ids, rollouts.to_source(scenario.frame).astype("float32"))


def _rollouts_of(args, scenario, scene, submitted, models: dict):
    """(rollouts to score for one scene, where they come from): the submission's (checked against
    the scene), or the policy's (``models`` keeps the prior once loaded)."""
    if submitted is not None:
        arrays = submitted.get(scenario.scenario_id)
        if arrays is None:
            raise RolloutError(f"{args.submission}: no rollouts for scenario {scenario.scenario_id} "
                               f"(the file has {sorted(submitted)[:5]})")
        count = arrays.trajectories.shape[0]
        if count != WOSAC_ROLLOUTS:
            if not args.any_rollout_count:
                raise RolloutError(f"{args.submission}: scenario {scenario.scenario_id}: {count} rollouts (joint scenes), "
                                   f"WOSAC requires {WOSAC_ROLLOUTS} (--any-rollout-count scores it anyway)")
            _warn(f"{args.submission}: scenario {scenario.scenario_id}: {count} rollouts instead of WOSAC's "
                  f"{WOSAC_ROLLOUTS}; scored anyway, not comparable with WOSAC numbers")
        check_against_scene(arrays, scene, args.submission)
        return arrays.to_rollouts(scenario.frame), args.submission
    if args.policy == "prior":
        if "prior" not in models:
            models["prior"] = load_prior(args.checkpoint or EMBEDDED, args.device)
        rollouts = prior_rollouts(models["prior"], scenario, args.rollouts, args.seed, args.device,
                                  DEFAULT_TOP_K if args.top_k is None else args.top_k, args.temperature or 1.0,
                                  avoid_collisions=args.avoid_collisions, stop_lines=args.stop_lines, lights=args.lights,
                                  precision=args.precision, persistence=args.persistence)
        return rollouts, f"--policy prior ({args.checkpoint or 'embedded'})"
    return policy_rollouts(args.policy, scenario, args.rollouts, args.seed), f"--policy {args.policy}"


def prior_rollouts(prior, scenario, num_rollouts: int, seed: int, device: str = "cpu", top_k: int = DEFAULT_TOP_K,
                   temperature: float = 1.0, avoid_collisions: bool = True, stop_lines: bool = True, lights: str = "current",
                   precision: str = "float32", persistence: float = DEFAULT_PERSISTENCE):
    """WOSAC rollouts of one scene by the SMART prior (top-k sampling, ``top_k`` 0: the whole
    distribution; collision-aware unless ``avoid_collisions`` is False; ``stop_lines`` and ``lights``: the engine's,
    by default traffic control with the lights known up to the current frame; ``precision``: the model's arithmetic,
    :mod:`smart_marl.model.precision`; ``persistence``: the vehicles' speed persistence,
    :mod:`smart_marl.rollout.persistence`): 16 token steps (80 frames)
    of every agent valid at the current frame (the engine simulates vehicles, pedestrians and
    cyclists and moves agents of type OTHER at constant velocity), as
    :class:`~smart_marl.metrics.inputs.Rollouts`."""
    result = rollout(prior, scenario, num_rollouts=num_rollouts, num_steps=16, seed=seed, device=device, top_k=top_k,
                     temperature=temperature, avoid_collisions=avoid_collisions, stop_lines=stop_lines, lights=lights,
                     precision=precision, persistence=persistence)
    agents = np.flatnonzero(result.has_trajectory[0])
    return Rollouts.from_source(result.agent_ids[0, agents], result.trajectory[:, agents], scenario.frame)


# ---------------------------------------------------------------------------------- challenge scale
def _scale_problem(args) -> str | None:
    """What is wrong with the combination of --scenes / --policy / --submission / --out / --shard / --merge, or None."""
    if args.merge:
        given = [flag for flag, value in (("--scenes", args.scenes), ("--policy", args.policy), ("--submission", args.submission),
                                          ("--out", args.out), ("--shard", args.shard), ("--chunk-size", args.chunk_size),
                                          ("--window", args.window))
                 if value is not None]
        if given:
            return f"--merge takes the scenes and options from RUN/run.json: leave out {', '.join(given)}"
        return None
    if not args.scenes:
        return "the following arguments are required: --scenes (or --merge RUN)"
    if not (args.policy or args.submission):
        return "one of the arguments --submission --policy is required"
    if not args.out:
        for flag, value in (("--shard", args.shard), ("--chunk-size", args.chunk_size)):
            if value is not None:
                return f"{flag} needs --out RUN (the run folder the shards' results go to)"
        env = shard_from_torchrun()
        if env is not None and env.count > 1:
            return (f"launched by torchrun as rank {env.index} of {env.count}: give --out RUN, the run folder every "
                    "rank writes its shard to")
    return None


def _shard_of(args) -> Shard:
    env = shard_from_torchrun()
    if args.shard is not None:
        if env is not None and env.count > 1 and env != args.shard:
            raise UsageError(f"--shard {args.shard} but torchrun made this process rank {env.index} of {env.count}: "
                             "leave out --shard under torchrun")
        return args.shard
    return env or Shard(0, 1)


def _run_config(args, paths: list[str], shard: Shard) -> dict:
    """The identity of a run, the same on every shard: what decides its numbers (not where it runs)."""
    if args.submission:
        source = {"submission": input_digest(submission_files(args.submission))}
    else:
        source = {"policy": args.policy, "rollouts": args.rollouts, "seed": args.seed}
        if args.policy == "prior":
            files = checkpoint_paths(resolve_checkpoint_path(args.checkpoint or EMBEDDED))
            source.update(checkpoint={k: file_sha256(files[k]) for k in ("meta", "weights")},
                          top_k=DEFAULT_TOP_K if args.top_k is None else args.top_k,
                          temperature=args.temperature or 1.0, avoid_collisions=args.avoid_collisions,
                          stop_lines=args.stop_lines, lights=args.lights, persistence=args.persistence)
            if args.precision != "float32":  # absent in float32: runs started before the option keep their identity
                source["precision"] = args.precision
    config = {"smart_marl": __version__, "scenes": input_digest(paths), "format": args.format, "rules": args.rules,
              "source": source, "num_shards": shard.count, "chunk_size": args.chunk_size or DEFAULT_CHUNK_SIZE,
              "keep_rollouts": bool(args.write_submission)}
    if (args.window or "current") != "current":  # absent by default: runs started before the option keep their identity
        config["window"] = args.window
    return config


def run_sharded(args) -> int:
    """``--out RUN``: score this process's shard chunk by chunk into RUN (resuming a previous try);
    merge at once when the run has one shard, or on rank 0 under torchrun once every rank is done."""
    shard = _shard_of(args)
    if args.device == "cuda" and os.environ.get("LOCAL_RANK"):  # one GPU per torchrun rank
        args.device = f"cuda:{int(os.environ['LOCAL_RANK'])}"
    paths = expand_paths(args.scenes)
    run = RunDir(args.out)
    if args.chunk_size is None and (run.root / "run.json").exists():  # a rerun or another shard: the run's chunk size
        args.chunk_size = run.load()["config"].get("chunk_size")
    prefix = run.stored_prefix(args.write_submission) if args.write_submission else None
    record = run.start(_run_config(args, paths, shard), extra={"submission_prefix": prefix} if prefix else None)
    if args.write_submission and prefix is None and shard.count > 1 and shard_from_torchrun() is None:
        _warn(f"--write-submission {args.write_submission} lies outside the run folder {run.root}, and a run keeps only "
              f"paths inside it: merge with `smart-marl eval --merge {run.root} --write-submission {args.write_submission}`")
    run_id, chunk_size = record["id"], record["config"]["chunk_size"]
    submitted = open_submission(args.submission) if args.submission else None
    models: dict = {}
    bad_files: list[dict] = []

    def on_bad_file(file_index, path, records_read, exc):
        if not args.skip_bad:
            raise exc
        _warn(f"skipped the bad file {path}: {exc}")
        bad_files.append({"file_index": file_index, "records_read": records_read, "path": path, "reason": str(exc)})

    def skip(slot, scenario_id, reason):
        return {"ordinal": slot.ordinal, "file_index": slot.file_index, "record": slot.record, "path": slot.path,
                "scenario_id": scenario_id, "reason": reason}

    def score(slot):
        try:
            loaded = slot.load()
        except ScenarioReadError as exc:
            if not args.skip_bad:
                raise
            _warn(f"skipped a bad scene of {slot.path}: {exc}")
            return None, skip(slot, None, str(exc)), None
        # one window per slot: --window current or FRAME gives one per scene, `all` slots are windows (_window_slots)
        given = [loaded] if isinstance(loaded, Window) else None
        [(scenario, scene, problem)] = _logged_windows(args, slot.path, loaded.scenario if given else loaded, given)
        if problem is not None:
            return None, skip(slot, scenario, problem), None
        rollouts, where = _rollouts_of(args, scenario, scene, submitted, models)
        metrics = score_rollouts(scene, rollouts, args.rules, where=where)
        kept = _submission_arrays(scenario, rollouts) if args.write_submission else None
        return {"ordinal": slot.ordinal, "metrics": metrics_record(metrics)}, None, kept

    def pack(kept: list) -> bytes:
        return build_submission(kept, description=_submission_description(args.policy)).SerializeToString()

    slots = scene_slots(paths, args.format, on_bad_file)
    if args.window == "all":
        slots = _window_slots(args, slots)
    started = time.perf_counter()
    counts = run_shard(run, run_id, shard, slots, chunk_size, score, pack if args.write_submission else None,
                       progress=lambda it: tqdm(it, desc=f"eval {shard}", unit="scene", file=sys.stderr, disable=None))
    run.write_done(run_id, shard, counts["chunks"], counts["num_slots"], bad_files)
    print(f"smart-marl eval: shard {shard}: {counts['scenes']} scene(s) in {counts['chunks']} chunk(s) "
          f"({counts['computed']} scored now in {time.perf_counter() - started:.2f} s, {counts['resumed']} from a previous try) "
          f"-> {run.shard_dir(shard)}", file=sys.stderr, flush=True)
    if shard.count == 1:
        return merge_command(args, run)
    if shard_from_torchrun() is not None:
        return _merge_after_torchrun(args, run)
    print(f"smart-marl eval: when all {shard.count} shards are done: smart-marl eval --merge {run.root}", file=sys.stderr)
    return 0


def _window_slots(args, slots):
    """``--window all`` at scale: one slot per window, numbered over the whole input, so that the shards split
    windows (not scenes) and the merge orders them as a single-process run does. Every shard reads every scene
    to count its windows; a scene that cannot be read or has no window keeps one slot, which is scored (skipped)
    as before."""
    ordinal = 0
    for slot in slots:
        try:
            windows = _windows(args, slot.load())
        except (ScenarioReadError, SceneNotScorableError):
            windows = None
        for window in windows or [None]:
            load = slot.load if window is None else (lambda w=window: w)
            yield SceneSlot(ordinal, slot.file_index, slot.path, slot.record, load)
            ordinal += 1


def _merge_after_torchrun(args, run: RunDir) -> int:
    """Under torchrun: wait for every rank (a gloo barrier: torch.distributed), then rank 0 merges."""
    import torch.distributed as dist

    dist.init_process_group("gloo", timeout=timedelta(hours=MERGE_WAIT_HOURS))
    try:
        dist.barrier()
        return merge_command(args, run) if dist.get_rank() == 0 else 0
    finally:
        dist.destroy_process_group()


MERGE_WAIT_HOURS = 24
"""How long rank 0 of a torchrun launch waits for the slowest rank before giving up (the shards
stay on disk; ``--merge`` merges them later)."""


def merge_command(args, run: RunDir | None = None) -> int:
    """``--merge RUN``: the numbers of a finished run (printed as a single-process run prints them,
    and kept in RUN/result.json) and, when its rollouts were kept, the submission in files: at the
    ``--write-submission`` prefix of this command line, else at the one run.json keeps (inside RUN).
    Every chunk and every file to write is checked first: a refusal leaves everything as it was."""
    run = run or RunDir(args.merge)
    merged = merge_run(run)
    config = merged.record["config"]
    if not merged.metrics:
        print(f"smart-marl eval: error: no scene of the run {run.root} could be scored ({len(merged.skipped)} skipped)",
              file=sys.stderr)
        return 1
    if args.write_submission and not config["keep_rollouts"]:
        raise RunDirError(f"{run.root / 'run.json'}: this run did not keep its rollouts (run it with --write-submission)")
    out = aggregate(merged.metrics, config["rules"])
    result = result_json(out, merged.skipped)
    result_path = check_result_target(run)
    parts = []
    if config["keep_rollouts"]:
        if args.write_submission:
            parts = plan_submission(Path(args.write_submission), merged.submission_chunks, "--write-submission")
        elif (prefix := run.submission_prefix(merged.record)) is not None:
            parts = plan_submission(prefix, merged.submission_chunks, f"the submission prefix of {run.root / 'run.json'}")
        else:
            _warn(f"the submission was not written: its prefix lies outside the run folder {run.root}, which run.json does "
                  f"not keep; give `--merge {run.root} --write-submission PREFIX`")
    write_whole(result_path, strict_json(result).encode() + b"\n")
    if parts:
        write_submission_parts(parts)
        print(f"smart-marl eval: wrote the submission of {len(merged.metrics)} scenario(s) in {len(parts)} file(s) "
              f"{parts[0].target} ...", file=sys.stderr)
    print_result(args, out, merged.skipped)
    return 0
