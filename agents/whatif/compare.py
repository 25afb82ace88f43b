"""What-if scenarios, the comparison: the what-if against its unperturbed baseline.

Stage: agents (what-if). :func:`run_whatif` prepares the what-if (:mod:`.prepare`), rolls out the
baseline and the what-if with the same seeds (:mod:`.simulate`) and compares them (:func:`compare`):
collisions, minimum distances and speeds of the affected agents, speeds of the vehicles behind a
braking or stalled one and of those approaching an overridden light, and sim-agents realism. The
geometry is the project's one geometry module (:func:`smart_marl.geometry.colliding`,
:func:`smart_marl.geometry.min_box_distance`), the realism its metrics (:mod:`smart_marl.metrics`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smart_marl.config_files import check_value, integer
from smart_marl.geometry import colliding, min_box_distance
from smart_marl.metrics import Rollouts, score_scenario
from smart_marl.metrics.config import CURRENT_STEP, NUM_SIMULATION_STEPS, NUM_STEPS
from smart_marl.model.checkpoint import EMBEDDED, load_prior
from smart_marl.model.precision import precision_problem
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.rollout import DEFAULT_TOP_K, temperature_rule
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE, persistence_rule
from smart_marl.scenario import AgentType, Scenario
from smart_marl.tokens import FRAMES_PER_TOKEN, TOKEN_S

from .edits import KIND_OF, MAX_ROLLOUTS, MAX_STEPS, WhatIf, WhatIfError
from .prepare import Prepared, prepare
from .simulate import SimRollouts, simulate


@dataclass
class WhatIfResult:
    whatif: WhatIf
    prepared: Prepared
    baseline: SimRollouts
    perturbed: SimRollouts
    table: list[dict]


def run_whatif(prior, scene: Scenario, whatif: WhatIf, num_rollouts: int = 8, seed: int = 0, num_steps: int = 16,
               top_k: int = DEFAULT_TOP_K, temperature: float = 1.0, device="cpu", realism: bool = True,
               avoid_collisions: bool = True, stop_lines: bool = True, lights: str = "log", precision: str = "float32",
               persistence: float = DEFAULT_PERSISTENCE) -> WhatIfResult:
    """The what-if and its unperturbed baseline (same seed, same number of rollouts) on one scene,
    and the comparison table (:func:`compare`). ``prior``: a SMART model, Checkpoint, checkpoint
    path, or None for the embedded prior; ``avoid_collisions=False``: the prior's agents sample
    plainly (the weights' own answer to the what-if; scripted agents are never restricted); ``stop_lines``
    and ``lights``: the prior's traffic control and the light states it sees (:mod:`smart_marl.rollout.stop_lines`; by
    default on, the log's clock: a light a script overrides holds from its step on); ``precision``: the prior's arithmetic
    (:mod:`smart_marl.model.precision`); ``persistence``: the prior's vehicles' speed persistence
    (:mod:`smart_marl.rollout.persistence`; 0: off)."""
    if isinstance(num_steps, bool) or not isinstance(num_steps, int) or not 1 <= num_steps <= MAX_STEPS:
        raise WhatIfError(whatif.path, f"num_steps must be 1..{MAX_STEPS} token steps of 0.5 s, got {num_steps!r}")
    for name, value, rule in (("num_rollouts", num_rollouts, integer(1, MAX_ROLLOUTS, "32x WOSAC's 32")),
                              ("top_k", top_k, integer(0, MAX_VOCAB_SIZE, "the largest vocabulary: a larger k is every token")),
                              ("temperature", temperature, temperature_rule), ("precision", precision, precision_problem),
                              ("persistence", persistence, persistence_rule)):
        check_value(name, value, rule, lambda problem: WhatIfError(whatif.path, problem))
    end_s = num_steps * TOKEN_S
    for i, edit in enumerate(whatif.edits):  # an onset after the rollout's end would be found only after simulating
        at_s = getattr(edit, "at_s", 0.0)
        if isinstance(at_s, (int, float)) and round(float(at_s) / TOKEN_S) >= num_steps:
            raise WhatIfError(whatif.path, f"{KIND_OF[type(edit)]}: at_s {at_s} is at or after the rollout's end ({num_steps} "
                                           f"steps = {end_s:g} s): give more steps (--steps) or an earlier at_s", i)
    model, vocab = load_prior(EMBEDDED if prior is None else prior, device)
    prepared = prepare(scene, whatif, vocab)  # every edit checked against the scene and the vocabulary before any rollout
    base_prep = Prepared(scene=scene, scripts=[], removals=[], lights=[], affected={}, followers={}, onset_step={})
    rules = dict(avoid_collisions=avoid_collisions, stop_lines=stop_lines, lights=lights, precision=precision,
                 persistence=persistence)
    baseline = simulate(model, vocab, base_prep, num_rollouts, seed, num_steps, top_k, temperature, device, scripted_on=False, **rules)
    perturbed = simulate(model, vocab, prepared, num_rollouts, seed, num_steps, top_k, temperature, device, **rules)
    return WhatIfResult(whatif, prepared, baseline, perturbed, compare(baseline, perturbed, prepared, realism=realism))


def box_size_m(scene: Scenario) -> np.ndarray:
    return scene.tracks.box_size()[:, :2].astype(np.float64)


def agent_min_distance_m(sim: SimRollouts, index: int) -> np.ndarray:
    """[R] minimum rounded-box distance (m, negative = overlap) between track ``index`` and any
    other present track over the rollout's frames (NaN when it is never present with another)."""
    size = box_size_m(sim.scene)
    return min_box_distance(sim.poses, sim.present, size[:, 0], size[:, 1], index)


def colliding_agents(sim: SimRollouts) -> np.ndarray:
    """[R, A] bool: the track overlaps another present track (rounded boxes) on some frame."""
    size = box_size_m(sim.scene)
    return colliding(sim.poses, sim.present, size[:, 0], size[:, 1])


def _realism(sim: SimRollouts, common_ids: np.ndarray, original: Scenario) -> float:
    """Sim-agents meta-metric (2025 rules) of the rollouts restricted to ``common_ids``, against the
    original scene's log of those agents; NaN when the scene or rollout is not a WOSAC-shaped one."""
    if original.num_frames != NUM_STEPS or original.current_frame != CURRENT_STEP or sim.poses.shape[2] < NUM_SIMULATION_STEPS:
        return float("nan")
    keep_orig = np.flatnonzero(np.isin(original.tracks.ids, common_ids))
    scene = original.select_tracks(keep_orig)
    cf = scene.current_frame
    sim_agents = np.flatnonzero(scene.tracks.valid[:, cf])
    ids = scene.tracks.ids[sim_agents]
    col = np.searchsorted(sim.track_ids, ids) if np.all(np.diff(sim.track_ids) > 0) else np.array([np.flatnonzero(sim.track_ids == t)[0] for t in ids])
    p = sim.poses[:, col, :NUM_SIMULATION_STEPS]
    if not np.isfinite(p).all():
        return float("nan")
    z = np.broadcast_to(scene.tracks.position[sim_agents, cf, 2].astype(np.float64)[None, :, None], p.shape[:3])
    traj = np.concatenate([p[..., :2], z[..., None], p[..., 2:3]], -1)
    return float(score_scenario(scene, Rollouts.from_array(ids, traj)).meta_metric)


def compare(baseline: SimRollouts, perturbed: SimRollouts, prepared: Prepared, realism: bool = True) -> list[dict]:
    """Rows ``{quantity, agent, baseline, whatif, change}`` (means over rollouts; NaN where the agent
    does not exist in that run): collisions; per affected agent its minimum distance to any other
    agent, mean and final speed and whether it collided; the mean speed of the vehicles behind a
    braking, stopping or stalled one after the onset; and the realism meta-metric of the agents
    present in both runs."""
    rows = []

    def add(quantity, agent, b, w):
        b, w = float(b), float(w)
        rows.append({"quantity": quantity, "agent": agent, "baseline": b, "whatif": w,
                     "change": w - b if np.isfinite(b) and np.isfinite(w) else float("nan")})

    cb, cp = colliding_agents(baseline), colliding_agents(perturbed)
    add("colliding_agents_per_rollout", "all", cb.sum(1).mean(), cp.sum(1).mean())
    veh_b = baseline.scene.tracks.types == AgentType.VEHICLE
    veh_p = perturbed.scene.tracks.types == AgentType.VEHICLE
    add("vehicles_mean_speed_mps", "all vehicles", np.nanmean(baseline.speed_mps()[:, veh_b]), np.nanmean(perturbed.speed_mps()[:, veh_p]))
    col_b = {int(t): k for k, t in enumerate(baseline.track_ids)}
    col_p = {int(t): k for k, t in enumerate(perturbed.track_ids)}
    sb, sp = baseline.speed_mps(), perturbed.speed_mps()
    nan = float("nan")
    for tid, what in prepared.affected.items():
        name = f"{tid} ({what})"
        kb, kp = col_b.get(tid), col_p.get(tid)
        onset = FRAMES_PER_TOKEN * prepared.onset_step.get(tid, 0)

        def mean_speed(s, sim, k):
            if k is None or not sim.present[:, k, onset:].any():
                return nan
            return float(np.nanmean(np.where(sim.present[:, k, onset:], s[:, k, onset:], np.nan)))

        def final_speed(s, sim, k):
            if k is None or not sim.present[:, k, -1].any():
                return nan
            return float(np.nanmean(np.where(sim.present[:, k, -1], s[:, k, -1], np.nan)))

        add("min_distance_m", name, np.nanmean(agent_min_distance_m(baseline, kb)) if kb is not None else nan,
            np.nanmean(agent_min_distance_m(perturbed, kp)) if kp is not None and perturbed.present[:, kp].any() else nan)
        add("mean_speed_after_onset_mps", name, mean_speed(sb, baseline, kb), mean_speed(sp, perturbed, kp))
        add("final_speed_mps", name, final_speed(sb, baseline, kb), final_speed(sp, perturbed, kp))
        add("collided_rate", name, cb[:, kb].mean() if kb is not None else nan,
            cp[:, kp].mean() if kp is not None and perturbed.present[:, kp].any() else nan)
    for tid, behind in prepared.followers.items():
        onset = FRAMES_PER_TOKEN * prepared.onset_step.get(tid, 0)
        fb = [col_b[t] for t in behind if t in col_b]
        fp = [col_p[t] for t in behind if t in col_p]
        if not fb or not fp:
            continue
        add("followers_mean_speed_after_onset_mps", f"{len(fp)} behind {tid}", np.nanmean(sb[:, fb, onset:]), np.nanmean(sp[:, fp, onset:]))
        add("followers_min_speed_mps", f"{len(fp)} behind {tid}", np.nanmean(np.nanmin(sb[:, fb, onset:], axis=-1)),
            np.nanmean(np.nanmin(sp[:, fp, onset:], axis=-1)))
    for step, ids in prepared.approaching:
        onset = FRAMES_PER_TOKEN * step
        fb = [col_b[t] for t in ids if t in col_b]
        fp = [col_p[t] for t in ids if t in col_p]
        if fb and fp:
            add("approaching_mean_speed_after_onset_mps", f"{len(fp)} vehicles at the lights", np.nanmean(sb[:, fb, onset:]),
                np.nanmean(sp[:, fp, onset:]))
    if realism:
        gone = {t for t, w in prepared.affected.items() if w == "removed"}
        common = np.array([t for t in baseline.track_ids if int(t) not in gone and int(t) in col_p], np.int64)
        add("realism_meta_metric", "unedited agents", _realism(baseline, common, baseline.scene),
            _realism(perturbed, common, baseline.scene))
    return rows
