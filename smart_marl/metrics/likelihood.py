"""Likelihood estimators, per-scenario realism scores and their aggregation over scenarios.

Stage: metrics, after :mod:`.features`. The log's feature values are scored under the
distribution the rollouts give (histograms with additive smoothing, or Bernoulli for the
indicators), per evaluated agent, then averaged over valid (agent, step) pairs and
exponentiated; the meta-metric is the weighted sum of the likelihoods, and the three categories
are weighted averages of their features' likelihoods (official formulas).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import Rules, get_rules
from .features import Features, kinematic_validity
from .inputs import SceneNotScorableError


def histogram_bins(values: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin index of each value after clipping to the edges' range: bins are [e_k, e_k+1), the last
    one closed; NaN goes to the last bin (official behaviour)."""
    lo, hi = float(edges[0]), float(edges[-1])
    v = np.clip(values, lo, hi)
    idx = np.searchsorted(edges.astype(np.float64), v, side="right") - 1
    idx = np.clip(idx, 0, len(edges) - 2)
    return np.where(np.isnan(values), len(edges) - 2, idx)


def histogram_log_likelihood(log_values: np.ndarray, sim_values: np.ndarray, edges: np.ndarray,
                             pseudocount: float) -> np.ndarray:
    """log p [E, T] of each logged value under its agent's histogram of all simulated values.

    ``log_values`` [E, T], ``sim_values`` [R, E, T]; each agent's histogram pools its R x T values."""
    nbins = len(edges) - 1
    r, e, t = sim_values.shape
    sim_bins = histogram_bins(sim_values, edges).transpose(1, 0, 2).reshape(e, r * t)
    counts = np.zeros((e, nbins))
    np.add.at(counts, (np.repeat(np.arange(e), r * t), sim_bins.reshape(-1)), 1.0)
    probs = (counts + pseudocount) / (r * t + pseudocount * nbins)
    log_bins = histogram_bins(log_values, edges)
    return np.log(probs[np.arange(e)[:, None], log_bins])


def bernoulli_log_likelihood(log_indicator: np.ndarray, sim_indicator: np.ndarray, pseudocount: float) -> np.ndarray:
    """log p [E] of each agent's logged indicator under the rate of its R simulated indicators
    (``log_indicator`` [E], ``sim_indicator`` [R, E])."""
    r = sim_indicator.shape[0]
    n1 = sim_indicator.sum(axis=0).astype(np.float64)
    p1 = (n1 + pseudocount) / (r + 2 * pseudocount)
    p0 = (r - n1 + pseudocount) / (r + 2 * pseudocount)
    return np.log(np.where(log_indicator, p1, p0))


def _masked_mean(values: np.ndarray, mask: np.ndarray) -> float:
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.where(mask, values, 0.0).sum() / mask.sum())


@dataclass
class ScenarioMetrics:
    """One scenario's realism numbers."""

    scenario_id: str
    rules: str
    likelihoods: dict[str, float]
    meta_metric: float
    min_ade: float
    ade: float
    collision_rate: float
    offroad_rate: float
    num_evaluated: int
    notes: list[str] = field(default_factory=list)


def score_features(log: Features, sim: Features, rules: Rules | str, scenario_id: str = "",
                   evaluated_is_vehicle: np.ndarray | None = None) -> ScenarioMetrics:
    """Likelihoods, meta-metric and minADE from the log's and the rollouts' features."""
    rules = get_rules(rules) if isinstance(rules, str) else rules
    f = rules.features
    valid = log.valid[0]  # [E, 80] logged validity
    if valid.shape[0] == 0:  # every likelihood would be a mean over nothing: NaN
        raise SceneNotScorableError(f"scenario {scenario_id}: no agent to evaluate")
    speed_valid, accel_valid = kinematic_validity(valid)
    lik: dict[str, float] = {}

    def hist(name, mask):
        cfg = f[name]
        ll = histogram_log_likelihood(getattr(log, name)[0], getattr(sim, name), cfg.edges(), cfg.pseudocount)
        lik[name] = float(np.exp(_masked_mean(ll, mask)))

    def bern(name, log_steps, sim_steps, mask):
        cfg = f[name]
        log_ind = np.any(log_steps[0] & mask, axis=-1)
        sim_ind = np.any(sim_steps & mask[None], axis=-1)
        lik[name] = float(np.exp(bernoulli_log_likelihood(log_ind, sim_ind, cfg.pseudocount).mean()))
        return sim_ind

    hist("linear_speed", speed_valid)
    hist("linear_acceleration", accel_valid)
    hist("angular_speed", speed_valid)
    hist("angular_acceleration", accel_valid)
    hist("distance_to_nearest_object", valid)
    sim_collision = bern("collision_indication", log.collision_per_step, sim.collision_per_step, valid)
    vehicle = np.ones(valid.shape[0], bool) if evaluated_is_vehicle is None else np.asarray(evaluated_is_vehicle, bool)
    hist("time_to_collision", valid & vehicle[:, None] if rules.ttc_vehicles_only else valid)
    hist("distance_to_road_edge", valid)
    sim_offroad = bern("offroad_indication", log.offroad_per_step, sim.offroad_per_step, valid)
    if rules.traffic_lights:
        bern("traffic_light_violation", log.traffic_light_violation_per_step, sim.traffic_light_violation_per_step,
             valid & vehicle[:, None])
    meta = float(sum(f[name].weight * lik[name] for name in f))
    per_rollout = sim.ade.mean(axis=1)
    return ScenarioMetrics(
        scenario_id=scenario_id, rules=rules.name, likelihoods=lik, meta_metric=meta,
        min_ade=float(per_rollout.min()), ade=float(sim.ade.mean()),
        collision_rate=float(sim_collision.mean()), offroad_rate=float(sim_offroad.mean()),
        num_evaluated=int(valid.shape[0]),
    )


def aggregate(scenarios: list[ScenarioMetrics], rules: Rules | str) -> dict:
    """Dataset-level numbers: every field averaged over scenarios, then the category scores
    (weighted average of their features' averaged likelihoods) and the averaged meta-metric."""
    rules = get_rules(rules) if isinstance(rules, str) else rules
    if not scenarios:
        raise ValueError("no scenarios to aggregate")
    for s in scenarios:
        if not all(np.isfinite(v) for v in (s.meta_metric, *s.likelihoods.values())):
            raise ValueError(f"scenario {s.scenario_id}: non-finite realism metrics; they would make the average NaN")
    names = list(rules.features)
    lik = {n: float(np.mean([s.likelihoods[n] for s in scenarios])) for n in names}
    out = {"rules": rules.name, "num_scenarios": len(scenarios),
           "meta_metric": float(np.mean([s.meta_metric for s in scenarios]))}
    for cat, members in rules.categories().items():
        w = np.array([rules.features[m].weight for m in members])
        out[cat] = float(np.dot(w, [lik[m] for m in members]) / w.sum())
    out["min_ade"] = float(np.mean([s.min_ade for s in scenarios]))
    out["ade"] = float(np.mean([s.ade for s in scenarios]))
    out["collision_rate"] = float(np.mean([s.collision_rate for s in scenarios]))
    out["offroad_rate"] = float(np.mean([s.offroad_rate for s in scenarios]))
    out["likelihoods"] = lik
    return out
