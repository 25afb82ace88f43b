"""The fine-tuned policy that ships with the package (issue 32 item 3; its card: docs/policy_card.md):
one call loads it, it goes with the embedded prior (the digest it was saved with), and it drives the
batched environment on the package's sample scenes, near its reference but not equal to it."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents.finetune import load_policy  # noqa: E402
from agents.policy import prior_digest  # noqa: E402
from agents.prior_policy import kl_to_prior  # noqa: E402
from envs.smart_traffic_batched_v0 import SmartTrafficBatchedEnv  # noqa: E402
from smart_marl.model.checkpoint import load_prior  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture(scope="module")
def shipped():
    return load_policy("embedded")


def test_the_shipped_policy_loads_in_one_call_and_goes_with_the_embedded_prior(shipped):
    cfg, net, meta = shipped
    assert cfg.prior == "embedded" and cfg.scenes == "embedded"
    assert meta["prior_sha256"] == prior_digest(load_prior("embedded")[0])
    assert meta["trained_on"]["num_scenes"] >= 1000 and meta["trained_on"]["scenes_seen"] >= 900
    assert sum(p.numel() for p in net.parameters()) > 0


def test_the_shipped_policy_drives_the_sample_scenes_near_its_reference(shipped):
    cfg, net, _ = shipped
    model, vocab = load_prior("embedded")
    env = SmartTrafficBatchedEnv(scenarios="embedded", prior=model, motion_vocab=vocab, num_scenes=4, controlled="moving_vehicles",
                                 max_agents=cfg.max_agents, horizon_steps=4, reference_top_k=cfg.reference_top_k, shield=cfg.shield,
                                 scene_order="sequential")
    td = env.reset()
    kls = []
    with torch.no_grad():
        for _ in range(4):
            obs, prior = td["agents", "observation", "observation"], td["agents", "observation", "prior_logits"]
            logits = net(obs, prior)
            mask = td["agents", "mask"]
            assert torch.isfinite(logits[mask]).any(-1).all()
            logp = torch.log_softmax(logits, -1)
            kls.append(kl_to_prior(logp, prior, cfg.temperature, cfg.reference_top_k)[mask])
            td["agents", "action"] = logits.argmax(-1)
            td = env.step(td)["next"]
    kl = torch.cat(kls)
    # fine-tuned: it moved away from the shielded prior's top 16 (the second run ended at a KL of 0.69 per step), but not far
    assert len(kl) > 0 and 1e-3 < float(kl.mean()) < 3.0, float(kl.mean())


def test_a_policy_trained_on_a_gpu_loads_on_the_cpu(tmp_path):
    """A checkpoint's config says the device it trained on; loading it does not ask for that device."""
    import json
    import shutil

    from agents.policy import resolve_policy_path

    src = resolve_policy_path("embedded")
    stem = src.with_suffix("") if src.suffix in (".json", ".safetensors") else src
    for suffix in (".json", ".safetensors"):
        shutil.copy(stem.with_name(stem.name + suffix), tmp_path / f"gpu{suffix}")
    meta = json.loads((tmp_path / "gpu.json").read_text())
    meta["config"]["device"] = "cuda:3"
    (tmp_path / "gpu.json").write_text(json.dumps(meta))
    cfg, net, _ = load_policy(tmp_path / "gpu.json")
    assert cfg.device == "cpu" and all(p.device.type == "cpu" for p in net.parameters())


def test_the_shipped_policy_evaluates_in_one_call_with_its_shield():
    """The card's ``evaluate_checkpoint("embedded")``: the package's sample scenes after its first two, the rows
    of the evaluation, the shielded prior's top 16 as the reference."""
    from agents.finetune import evaluate_checkpoint

    result = evaluate_checkpoint("embedded", episodes=1)
    assert result["reference"] == "prior top-16"
    rows = result["rows"]
    assert {"expert (log)", "prior top-16", "fine-tuned"} <= set(rows)
    tuned = rows["fine-tuned"]
    assert tuned["agent_episodes"] > 0 and 0.0 <= tuned["goal_rate"] <= 1.0 and 0.0 < tuned["kl_to_reference"] < float("inf")


def test_the_shield_config_is_the_shipped_policys_recipe(shipped):
    """The named config ``shield`` (its card's recipe) builds the shipped policy's network, with its shield and beta."""
    from agents.finetune import load_finetune_config
    from agents.finetune_config import POLICY_NETWORK_FIELDS

    cfg, _, _ = shipped
    recipe = load_finetune_config("shield")
    assert {k: getattr(recipe, k) for k in POLICY_NETWORK_FIELDS} == {k: getattr(cfg, k) for k in POLICY_NETWORK_FIELDS}
    assert (recipe.shield, recipe.beta, recipe.num_scenes) == (cfg.shield, cfg.beta, 2000)
