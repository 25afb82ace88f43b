"""Evaluations that compare rows in one environment (issue 58, "comparisons in one environment"),
agents/evaluate.py: with the shield on, the table leads with the shielded prior at the policy's own top-k
and the shielded prior top-3, keeps those two with the shield off as extra rows of another environment
(last, named so), says which environment every row ran in, and compares the fine-tuned row only with a
prior row of its own environment. The embedded prior on the package's sample scenes, a short horizon."""

from __future__ import annotations

import math

import pytest

pytest.importorskip("pettingzoo", reason="the env extra (pettingzoo) is not installed")
pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents.evaluate import (LEAD_TOP_K, ShieldOff, evaluate_policies, format_table, lead_row,  # noqa: E402
                             same_environment_policies, shield_label)
from agents.policy import ExpertTensorPolicy, FinetunedTensorPolicy, PriorTensorPolicy  # noqa: E402
from envs._core import CoreScene, TrafficCore  # noqa: E402
from envs._shield import DEFAULT_SHIELD_CHECKS as SHIELD_CHECKS  # noqa: E402
from smart_marl.scenario import AgentType  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


class _Tuned(PriorTensorPolicy):
    """A stand-in for a fine-tuned policy (its name), acting as the prior top-16."""

    name = FinetunedTensorPolicy.name

    def __init__(self):
        super().__init__(top_k=16)
        self.name = FinetunedTensorPolicy.name


def _finetune_rows(shield, reference_top_k=16, top_k=6):
    """The fine-tuning evaluation's rows (expert, prior at the reference's and the background's k, full softmax,
    fine-tuned) as :func:`agents.finetune.evaluation_policies` builds them, in one environment."""
    policies = {ExpertTensorPolicy.name: ExpertTensorPolicy()}
    for k in dict.fromkeys((reference_top_k, top_k, None)):
        p = PriorTensorPolicy(top_k=k)
        policies[p.name] = p
    policies[FinetunedTensorPolicy.name] = _Tuned()
    return policies, same_environment_policies(policies, shield, reference_top_k)


def test_a_shielded_table_leads_with_the_shielded_prior_at_the_policys_k_and_at_top_3_and_ends_with_them_unshielded():
    policies, rows = _finetune_rows(SHIELD_CHECKS)
    assert list(rows) == ["prior top-16", "prior top-3", "expert (log)", "prior top-6", "prior full softmax", "fine-tuned",
                          "prior top-16, shield off", "prior top-3, shield off"]
    assert rows["prior top-16"] is policies["prior top-16"]  # the row that was there already, moved first
    assert rows["prior top-3"].top_k == LEAD_TOP_K and not isinstance(rows["prior top-3"], ShieldOff)
    off = rows["prior top-3, shield off"]
    assert isinstance(off, ShieldOff) and off.policy is rows["prior top-3"] and off.top_k == 3
    # a policy of the top 3: one lead row, once in each environment
    _, rows = _finetune_rows(SHIELD_CHECKS, reference_top_k=3)
    assert list(rows) == ["prior top-3", "expert (log)", "prior top-6", "prior full softmax", "fine-tuned", "prior top-3, shield off"]


def test_without_the_shield_the_rows_stay_as_they_were():
    policies, rows = _finetune_rows(())
    assert list(rows) == list(policies) == ["expert (log)", "prior top-16", "prior top-6", "prior full softmax", "fine-tuned"]
    assert shield_label(()) == "off" and shield_label(SHIELD_CHECKS) == "on" and shield_label(("offroad",)) == "offroad"


# ------------------------------------------------------------------------------- on a core
@pytest.fixture(scope="module")
def setting(embedded_prior, sample_scenes):
    """(model, vocab, core scenes): the embedded prior and the sample scenes' moving vehicles (up to 4 each)."""
    from envs._scene import scene_static
    from envs._setup import select_controlled

    model, vocab = embedded_prior
    scenes = []
    for i, sc in enumerate(sample_scenes[:2]):
        st = scene_static(sc)
        scenes.append(CoreScene(st, select_controlled("moving_vehicles", st, 4), key=("eval", i)))
    return model, vocab, scenes


def _core(setting, shield):
    model, vocab, _ = setting
    return TrafficCore(model, vocab, "prior", horizon_steps=4, terminate_on=(), record=True, prior_cache_size=4, shield=shield,
                       shield_top_k=16)


def _evaluate(setting, core, policies):
    model, vocab, scenes = setting
    return evaluate_policies(core, scenes, policies, [5, 6], num_envs=3, vocab_size=vocab[AgentType.VEHICLE].size, num_agents=4,
                             reference_top_k=16)


def test_a_shield_off_row_runs_in_the_environment_without_the_shield_and_the_others_with_it(setting, monkeypatch):
    """On a shielded core the :class:`ShieldOff` row is the row the same policy gets on a core without the shield
    (same scenes, seeds and waves), the shield is asked for nothing during it, the shielded rows are asked, and the
    core keeps its shield afterwards; every row says which environment it ran in."""
    import envs._core

    calls = []
    shield = envs._core.unsafe_tokens
    monkeypatch.setattr(envs._core, "unsafe_tokens", lambda *a: calls.append(1) or shield(*a))
    core = _core(setting, SHIELD_CHECKS)
    prior3 = PriorTensorPolicy(top_k=3)
    result = _evaluate(setting, core, {"prior top-3, shield off": ShieldOff(prior3)})
    assert calls == [] and core.shield == SHIELD_CHECKS
    result.update(rows={**_evaluate(setting, core, {"prior top-3": prior3})["rows"], **result["rows"]})
    assert calls and core.shield == SHIELD_CHECKS
    plain = _evaluate(setting, _core(setting, ()), {"prior top-3": prior3})
    rows = result["rows"]
    assert rows["prior top-3, shield off"]["shield"] == [] and rows["prior top-3"]["shield"] == list(SHIELD_CHECKS)
    assert plain["shield"] == [] and result["shield"] == list(SHIELD_CHECKS)
    off, on, ref = rows["prior top-3, shield off"], rows["prior top-3"], plain["rows"]["prior top-3"]
    assert {k: v for k, v in off.items() if k != "shield"} == {k: v for k, v in ref.items() if k != "shield"}
    assert off["agent_episodes"] == on["agent_episodes"] > 0
    table = format_table(result)
    assert "environment: shield on" in table and "rows with shield off ran in another environment" in table
    assert [line.split()[-13] for line in table.splitlines()[3:5]] == ["on", "off"]  # the shield column


def _row(goal, collision, offroad, meta, shield):
    nan = math.nan
    return {"goal_rate": goal, "collision_rate": collision, "offroad_rate": offroad, "progress_m": 10.0, "return": 1.0,
            "kl_to_reference": 0.1, "kl_to_full_prior": 0.2, "agent_episodes": 8, "steps": 32, "rear_ended_rate": 0.0,
            "front_collision_rate": 0.0, "side_collision_rate": 0.0, "meta_metric": meta, "kinematic": nan, "interactive": nan,
            "map_based": nan, "min_ade": nan, "shield": list(shield)}


def test_the_table_compares_the_fine_tuned_row_with_the_first_prior_row_of_its_own_environment():
    """Made-up rows: an unshielded prior listed first is not the fine-tuned row's baseline; the shielded prior at its
    top-k is, and the last line says so with the ratios of the two rows."""
    on = list(SHIELD_CHECKS)
    result = {"scenes": ["a"], "seeds": [1], "reference": "prior top-16", "rules": "2024", "realism_scenes": [], "shield": on,
              "rows": {"prior top-16, shield off": _row(0.5, 0.2, 0.1, 0.70, []), "prior top-16": _row(0.4, 0.02, 0.01, 0.75, on),
                       "prior top-3": _row(0.45, 0.01, 0.01, 0.76, on), "fine-tuned": _row(0.6, 0.03, 0.0, 0.74, on)}}
    assert lead_row(result) == "prior top-16"
    last = format_table(result).splitlines()[-1]
    assert last == ("fine-tuned against prior top-16 in the same environment (shield on): goal 1.50x, collision + offroad 1.00x, "
                    "realism -0.0100")
    result["rows"]["prior top-16"]["shield"] = []  # no prior of the fine-tuned row's environment but the top 3
    assert lead_row(result) == "prior top-3"
    del result["rows"]["fine-tuned"]
    assert lead_row(result) is None and "same environment" not in format_table(result)
