"""A policy checkpoint is checked whole before it is used (hostile-input review, finding 1): every tensor of
the network its config builds, with its shape, none extra, all floating point and finite; its sizes, digest and
config bounded. Each tampered copy of the shipped policy is refused with a FinetuneError naming the file and
the field or tensor, before the prior is loaded."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from safetensors.torch import load_file, save_file  # noqa: E402

from agents.finetune import load_policy  # noqa: E402
from agents.finetune_config import FinetuneConfigError, FinetuneError, load_finetune_config  # noqa: E402
from agents.policy import policy_files  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


@pytest.fixture
def copy(tmp_path):
    """A copy of the shipped policy in tmp_path: (its json path, meta, weights); the package's files are only read."""
    jsrc, wsrc = policy_files("embedded")
    shutil.copy(jsrc, tmp_path / "p.json")
    shutil.copy(wsrc, tmp_path / "p.safetensors")
    return tmp_path / "p.json", json.loads(jsrc.read_text()), load_file(str(wsrc))


def tampered(copy, meta_change=None, weights_change=None):
    jpath, meta, weights = copy
    if meta_change:
        meta_change(meta)
        jpath.write_text(json.dumps(meta))
    if weights_change:
        weights_change(weights)
        save_file(weights, str(jpath.with_suffix(".safetensors")))
    return jpath


def refused(jpath, pattern):
    with pytest.raises(FinetuneError, match=pattern) as info:
        load_policy(jpath)
    return str(info.value)


def test_an_untampered_copy_loads_with_the_shipped_weights(copy):
    jpath, _, weights = copy
    _, net, _ = load_policy(jpath)
    torch.testing.assert_close(net.state_dict()["f.params.0.weight"],
                               weights["actor.f.params.0.weight"], rtol=0, atol=0)


@pytest.mark.parametrize("name", ["actor.f.params.2.weight", "actor.motion_features", "critic.v.params.4.bias"])
def test_a_missing_tensor_is_refused_by_name(copy, name):
    jpath = tampered(copy, weights_change=lambda w: w.pop(name))
    refused(jpath, rf"p\.safetensors: tensor {name} is missing")


def test_an_extra_tensor_is_refused_by_name(copy):
    jpath = tampered(copy, weights_change=lambda w: w.__setitem__("actor.backdoor", torch.zeros(3)))
    refused(jpath, r"p\.safetensors: tensor actor\.backdoor is not a tensor of the network of its config")


def test_a_tensor_of_another_shape_is_refused_with_both_shapes(copy):
    jpath = tampered(copy, weights_change=lambda w: w.__setitem__("actor.f.params.0.weight", torch.zeros(128, 472)))
    refused(jpath, r"p\.safetensors: tensor actor\.f\.params\.0\.weight has shape \[128, 472\], .* needs \[128, 473\]")


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_a_non_finite_weight_is_refused_by_tensor(copy, bad):
    def poison(w):
        w["actor.f.params.4.weight"][0, 0] = bad
    refused(tampered(copy, weights_change=poison), r"p\.safetensors: tensor actor\.f\.params\.4\.weight holds NaN or infinite")


def test_an_integer_tensor_is_refused(copy):
    jpath = tampered(copy, weights_change=lambda w: w.__setitem__("actor.f.params.0.bias", torch.zeros(128, dtype=torch.int64)))
    refused(jpath, r"p\.safetensors: tensor actor\.f\.params\.0\.bias is int64; a policy's tensors are floating point")


@pytest.mark.parametrize("field, value, pattern", [
    ("vocab_size", 10**12, r"vocab_size must be at most 8192"),
    ("obs_dim", 10**12, r"obs_dim must be at most 65536"),
    ("obs_dim", 0, r"obs_dim must be at least 1"),
    ("n_agents", 10**12, r"n_agents must be at most 1024"),
    ("n_agents", 8, r"n_agents 8 is not its config's max_agents 4"),
    ("config", "hidden=128", r"config must be a mapping of fine-tuning config fields, got 'hidden=128'"),
    ("prior_sha256", 5, r"prior_sha256 must be a sha256 digest \(64 lowercase hex digits\), got 5"),
    ("prior_sha256", "b9b0", r"prior_sha256 must be a sha256 digest"),
])
def test_a_meta_field_out_of_range_is_refused_naming_the_file_and_field(copy, field, value, pattern):
    refused(tampered(copy, meta_change=lambda m: m.__setitem__(field, value)), r"p\.json: " + pattern)


@pytest.mark.parametrize("field, value, pattern", [
    ("lr", 1e18, r"lr must be <= 1\.0 \(Adam moves every weight by about lr a step\), got 1e\+18"),
    ("hidden", 10**12, r"hidden must be at most 4096"),
    ("obs_scale", "0.1", r"obs_scale must be a finite number"),
])
def test_a_config_value_out_of_range_is_refused_naming_the_file_and_field(copy, field, value, pattern):
    refused(tampered(copy, meta_change=lambda m: m["config"].__setitem__(field, value)), r"p\.json: fine-tuning config: " + pattern)


def test_a_config_of_another_network_than_the_weights_is_refused_naming_it(copy):
    message = refused(tampered(copy, meta_change=lambda m: m["config"].__setitem__("actor_head", "per_token")), r"p\.safetensors: tensor")
    assert "actor_head='per_token'" in message


def test_the_learning_rate_is_bounded_in_the_fine_tuning_config():
    assert load_finetune_config("tiny", {"lr": 1.0}).lr == 1.0
    for lr in (1e18, 1.5, 0.0, -1e-3):
        with pytest.raises(FinetuneConfigError, match=r"fine-tuning config: lr must be"):
            load_finetune_config("tiny", {"lr": lr})
