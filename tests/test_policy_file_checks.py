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


# ---------------------------------------------------------------------------------------- properties
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

JSON_VALUES = st.recursive(st.none() | st.booleans() | st.integers(-10**15, 10**15) | st.floats(allow_nan=True)
                           | st.text(max_size=8), lambda inner: st.lists(inner, max_size=3)
                           | st.dictionaries(st.text(max_size=5), inner, max_size=3), max_leaves=6)
DTYPES = st.sampled_from([torch.float32, torch.float16, torch.float64, torch.int64, torch.int32, torch.bool, torch.uint8])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(["obs_dim", "vocab_size", "n_agents", "prior_sha256", "config", "format", "extra"]), value=JSON_VALUES)
def test_any_meta_value_loads_or_is_refused_by_name(copy, key, value):
    """Whatever a field of the JSON half holds, loading either gives the policy or a FinetuneError; never another
    exception."""
    jpath, meta, _ = copy
    changed = dict(meta, **{key: value})
    jpath.write_text(json.dumps(changed))
    try:
        load_policy(jpath)
    except FinetuneError:
        pass
    jpath.write_text(json.dumps(meta))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(index=st.integers(0, 10**6), dtype=DTYPES, shape_change=st.sampled_from(["keep", "shorter", "longer"]),
       fill=st.sampled_from([None, float("nan"), float("inf"), -float("inf"), 1e30]))
def test_any_tensor_tampering_loads_only_when_the_tensor_is_still_valid(copy, index, dtype, shape_change, fill):
    """One tensor of the weights changed in shape, content or dtype: the policy loads exactly when that tensor still
    has its shape and is floating point and finite, and is otherwise refused with a FinetuneError naming the file;
    never another exception."""
    jpath, _, weights = copy
    name = sorted(weights)[index % len(weights)]
    t = weights[name].clone()
    if shape_change == "shorter" and t.dim() > 0 and t.shape[0] > 1:
        t = t[:-1]
    elif shape_change == "longer":
        t = torch.cat([t, t[:1]]) if t.dim() > 0 else t.reshape(1)
    if fill is not None:
        t = t.float().fill_(fill)
    if dtype.is_floating_point or torch.isfinite(t.float()).all():  # a non-finite float has no integer value
        t = t.to(dtype)
    valid = t.shape == weights[name].shape and t.is_floating_point() and bool(torch.isfinite(t.float()).all())
    wpath = jpath.with_suffix(".safetensors")
    save_file({**weights, name: t.contiguous()}, str(wpath))
    try:
        load_policy(jpath)
        assert valid, f"{name} {t.dtype} {tuple(t.shape)} loaded"
    except FinetuneError as exc:
        assert not valid and str(wpath) in str(exc), str(exc)
    save_file(weights, str(wpath))
