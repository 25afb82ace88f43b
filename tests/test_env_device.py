"""Both faces of the environment take ``device=``: a name this machine cannot run on is a named error
up front, and on a CUDA machine (skipped elsewhere) the prior, the state and what the batched env
returns stay on the GPU while the PettingZoo env returns numpy as always (issue 32 item 2)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs import smart_traffic_v0
from envs.errors import EnvConfigError, EnvConfigTypeError

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py
CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
SMALL = dict(scenarios="embedded", prior="embedded", controlled="sdc", horizon_steps=3)


@pytest.mark.parametrize("device, error, message", [
    ("cuda:7" if torch.cuda.is_available() else "cuda", EnvConfigError, "device: "),
    ("tpu", EnvConfigError, "not a torch device"),
    (3, EnvConfigTypeError, "device must be a string"),
])
def test_a_device_this_machine_cannot_run_on_is_refused_before_anything_loads(device, error, message):
    with pytest.raises(error, match=message):
        smart_traffic_v0.parallel_env(**SMALL, device=device)


def test_an_explicit_cpu_device_is_the_default():
    env = smart_traffic_v0.parallel_env(**SMALL, device=torch.device("cpu"))
    obs, _ = env.reset(seed=0)
    assert env.core.pose.device.type == "cpu" and all(isinstance(o, np.ndarray) for o in obs.values())


@CUDA
def test_the_pettingzoo_env_runs_on_cuda_and_returns_numpy():
    env = smart_traffic_v0.parallel_env(**SMALL, device="cuda")
    obs, _ = env.reset(seed=0)
    assert env.core.pose.device.type == "cuda" and next(env.model.parameters()).device.type == "cuda"
    steps = 0
    while env.agents:
        obs, rewards, *_ = env.step({a: env.action_space(a).sample() for a in env.agents})
        assert all(isinstance(o, np.ndarray) and np.isfinite(o).all() for o in obs.values())
        steps += 1
    assert steps == 3


@CUDA
def test_the_batched_env_passes_its_spec_check_on_cuda_and_keeps_every_tensor_there():
    pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")
    from torchrl.envs.utils import check_env_specs

    from envs import smart_traffic_batched_v0

    env = smart_traffic_batched_v0.SmartTrafficBatchedEnv(scenarios="embedded", prior="embedded", num_scenes=4, max_agents=2,
                                                          horizon_steps=3, device="cuda")
    check_env_specs(env, seed=0)
    td = env.rollout(5, break_when_any_done=False)
    leaves = td.flatten_keys().values()
    assert all(t.device.type == "cuda" for t in leaves if isinstance(t, torch.Tensor))
    assert td["agents", "observation", "observation"].isfinite().all()
