"""``smart-marl eval``: sim-agents realism metrics of rollouts, from a submission file or a policy.

Stage: metrics (the end of the data flow). ``--submission FILE`` scores the rollouts a
``SimAgentsChallengeSubmission`` file holds; ``--policy NAME`` first generates them
(constant_velocity, log_replay, random, or ``prior``: closed-loop rollouts of the SMART prior, the
package's embedded checkpoint unless ``--checkpoint`` names another). Prints a table
per feature and category plus the meta-metric and minADE, or one JSON object with ``--json``;
``--write-submission OUT`` saves policy rollouts as an uploadable submission file.

A scene the metrics cannot score (not 91 frames with the current frame at 10, no evaluated agent)
is skipped with a warning naming the file and the scene, and listed under ``skipped`` in the JSON;
a file that cannot be read stops the job (exit 1) unless ``--skip-bad``, which skips it the same
way. A submission must hold WOSAC's 32 rollouts per scenario (exit 1 otherwise) unless
``--any-rollout-count``, which scores it with a warning.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from tqdm import tqdm

from ..errors import ScenarioReadError
from ..metrics import SceneNotScorableError, aggregate, logged_scene, score_rollouts
from ..metrics.baselines import policy_rollouts
from ..metrics.config import get_rules
from ..metrics.inputs import RolloutError, Rollouts
from ..metrics.submission import ScenarioRolloutArrays, check_against_scene, rollouts_from_submission, write_rollouts
from ..model.checkpoint import EMBEDDED, load_prior
from ..readers import expand_paths, read_scenarios
from ..rollout import DEFAULT_TOP_K, rollout
from .arguments import collision_avoidance_flag, device, non_negative_int, positive_int, positive_number, reader_formats

POLICY_CHOICES = ("constant_velocity", "log_replay", "random", "prior")
WOSAC_ROLLOUTS = 32
"""Rollouts per scenario the challenge requires (a submission with another count is refused)."""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval", help="sim-agents realism metrics (WOSAC 2024/2025) of a submission file or a baseline policy",
        description="Score rollouts of the scenes in PATH with the Waymo Open Sim Agents Challenge realism metrics "
                    "(same numbers as the official package). Rollouts come from --submission FILE or are "
                    "generated with --policy.")
    p.add_argument("--scenes", required=True, metavar="PATH", help="scene file, folder or glob (91-step WOMD-like scenes)")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--submission", metavar="FILE", help="a SimAgentsChallengeSubmission file (.binproto)")
    src.add_argument("--policy", choices=POLICY_CHOICES, help="generate rollouts with a baseline policy")
    p.add_argument("--checkpoint", metavar="C", help="model checkpoint for --policy prior (default: the embedded prior)")
    p.add_argument("--device", default="cpu", type=device, help="torch device for --policy prior (default cpu)")
    p.add_argument("--top-k", type=non_negative_int, default=None, metavar="K",
                   help=f"--policy prior samples among its K most likely tokens (default {DEFAULT_TOP_K}; 0: all of them)")
    p.add_argument("--temperature", type=positive_number, default=None, metavar="T",
                   help="--policy prior samples from softmax(logits / T) (default 1)")
    collision_avoidance_flag(p, "--policy prior")
    p.add_argument("--rollouts", type=positive_int, default=32, help="rollouts per scene for --policy (default 32)")
    p.add_argument("--seed", type=int, default=0, help="random seed for --policy (default 0)")
    p.add_argument("--rules", choices=("2024", "2025"), default="2025", help="challenge rules (default 2025)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--write-submission", metavar="OUT", help="with --policy: also write the rollouts as a submission file")
    p.add_argument("--format", default=None, choices=reader_formats(), help="force a scene reader instead of detecting the format")
    p.add_argument("--skip-bad", action="store_true", help="skip scene files that cannot be read, with a warning (default: stop)")
    p.add_argument("--any-rollout-count", action="store_true",
                   help=f"score a submission that does not hold {WOSAC_ROLLOUTS} rollouts per scenario, with a warning "
                        f"(its numbers are not comparable with WOSAC's)")
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
    submitted = rollouts_from_submission(args.submission) if args.submission else None
    results, written, skipped = [], [], []
    prior = None
    for path, scenario in tqdm(_scenes(args, skipped), desc="eval", unit="scene", file=sys.stderr, disable=None):
        try:
            scene = logged_scene(scenario)
        except SceneNotScorableError as exc:
            _warn(f"{path}: skipped: {exc}")
            skipped.append({"path": path, "scenario_id": scenario.scenario_id, "reason": str(exc)})
            continue
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
            rollouts = arrays.to_rollouts(scenario.frame)
            where = args.submission
        elif args.policy == "prior":
            if prior is None:
                prior = load_prior(args.checkpoint or EMBEDDED, args.device)
            rollouts = prior_rollouts(prior, scenario, args.rollouts, args.seed, args.device,
                                      DEFAULT_TOP_K if args.top_k is None else args.top_k, args.temperature or 1.0,
                                      avoid_collisions=args.avoid_collisions)
            where = f"--policy prior ({args.checkpoint or 'embedded'})"
        else:
            rollouts = policy_rollouts(args.policy, scenario, args.rollouts, args.seed)
            where = f"--policy {args.policy}"
        if args.policy and args.write_submission:
            written.append(ScenarioRolloutArrays(scenario.scenario_id, rollouts.object_ids,
                                                     rollouts.to_source(scenario.frame).astype("float32")))
        results.append(score_rollouts(scene, rollouts, args.rules, where=where))
    if not results:
        print(f"smart-marl eval: error: no scene in {args.scenes} could be scored ({len(skipped)} skipped)", file=sys.stderr)
        return 1
    if args.write_submission:
        write_rollouts(args.write_submission, written, description=f"smart-marl policy {args.policy}")
    out = aggregate(results, args.rules)
    if args.json:
        keys = ("meta_metric", "kinematic", "interactive", "map_based", "min_ade", "likelihoods", "num_scenarios", "rules")
        print(json.dumps({**{k: out[k] for k in keys}, "skipped": skipped}))
    else:
        print(format_table(out))
        if skipped:
            print(f"{len(skipped)} scene(s) or file(s) skipped (see the warnings)")
    return 0


def prior_rollouts(prior, scenario, num_rollouts: int, seed: int, device: str = "cpu", top_k: int = DEFAULT_TOP_K,
                   temperature: float = 1.0, avoid_collisions: bool = True):
    """WOSAC rollouts of one scene by the SMART prior (top-k sampling, ``top_k`` 0: the whole
    distribution; collision-aware unless ``avoid_collisions`` is False): 16 token steps (80 frames)
    of every agent valid at the current frame (the engine simulates vehicles, pedestrians and
    cyclists and moves agents of type OTHER at constant velocity), as
    :class:`~smart_marl.metrics.inputs.Rollouts`."""
    result = rollout(prior, scenario, num_rollouts=num_rollouts, num_steps=16, seed=seed, device=device, top_k=top_k,
                     temperature=temperature, avoid_collisions=avoid_collisions)
    agents = np.flatnonzero(result.has_trajectory[0])
    return Rollouts.from_source(result.agent_ids[0, agents], result.trajectory[:, agents], scenario.frame)
