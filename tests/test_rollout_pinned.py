"""The embedded prior's rollouts are pinned: a short rollout of a fixed seed gives exactly these
tokens. Refactors of the model, the KV-cached step or the rollout engine must not change them.

Pinned here: 2 rollouts x 4 token steps, seed 7, top-k 5, of the embedded prior
(``smart_marl/checkpoints/embedded``) on the real WOMD scene 637f20cafde22ff8 (skipped when
``../shared/data`` is absent), with the default rules (collision-aware sampling, traffic control and speed
persistence) and without any ("-plain"), and on the package's first SUMO sample scene (always runs). The
tokens of every simulated agent are pinned exactly (a SHA-256 of the int64 array, agents in track
order, plus the first agents' tokens written out); log-probabilities to 1e-5 (relative) and the
agents' summed path length to 1 mm.

When the pin legitimately changes (the embedded prior is retrained or re-exported, or the
vocabulary, sampler or history tokenization is changed on purpose), regenerate it with

    .venv/bin/python tests/test_rollout_pinned.py

which prints the new ``PINS`` dict to paste below, and say in the commit why the rollouts changed.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from smart_marl.embedded import sample_scenarios
from smart_marl.model.checkpoint import load_embedded
from smart_marl.readers import read_scenarios
from smart_marl.rollout import rollout
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE

WOMD_SCENE = "womd_tfrecord/motion_data_one_scenario.tfrecord"
SETTINGS = dict(num_rollouts=2, num_steps=4, top_k=5, seed=7)

PINS = {  # regenerated when collision-aware sampling became the default (stage 5 prior, 2026-11-25; the SUMO pin
    # did not move: no token of its first 4 steps collides); same settings
    "womd-637f20cafde22ff8": {  # re-pinned 2026-11-29, third time: speed persistence became the default
        # (smart_marl.rollout.persistence, 0.25): vehicles that were speeding up or slowing lean toward going on with it
        # (path 944.60 -> 943.04 m; the first four agents draw as before); with persistence 0 the pin of before comes back
        # exactly (the plain pin below is drawn with it off and did not move)
        "simulated": 50,
        "tokens_sha256": "8083568eaed682a3dcd9bc73547fd52fb3fe5769f2487d09aacc0152ab6df6f9",
        "first_tokens": [[[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [0, 1, 1, 1]],
                         [[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [1, 0, 1, 1]]],
        "log_prob_sum": -615.2929181307554,
        "path_length_m": 943.0432663798164,
    },
    "womd-637f20cafde22ff8-plain": {  # the stage-5 pin, unchanged (no rule, no persistence)
        "simulated": 50,
        "tokens_sha256": "8f8c0e0e871a0c47e2e35a97137d2409c852bad1c83445b58d3ebecfb0d27de7",
        "first_tokens": [[[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [0, 1, 1, 1]],
                         [[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [1, 0, 1, 1]]],
        "log_prob_sum": -606.4080134108663,
        "path_length_m": 938.9321361192233,
    },
    "sumo-sample-0": {  # re-pinned 2026-11-29: traffic control became the default (stop_lines=True, issue 55): the
        # first agent draws differently from its third token on, under the rule (path 44.30 -> 42.80 m over 22 agents)
        "simulated": 22,
        "tokens_sha256": "8cbadddf31cd712fb34893b5cbd7b788028d8fc020e0b039e9aea082bb509c22",
        "first_tokens": [[[122, 73, 146, 232], [5, 5, 5, 5], [5, 5, 5, 5], [32, 5, 5, 5]],
                         [[122, 139, 4, 621], [5, 32, 5, 5], [5, 5, 5, 5], [5, 5, 5, 5]]],
        "log_prob_sum": -149.41906360536814,
        "path_length_m": 42.80118131582195,
    },
}


def _summary(scene, avoid_collisions: bool = True) -> dict:
    """What is pinned of one scene's rollout (computed on one torch thread): with the default rules, or ``-plain``
    with none (no collision-aware sampling, no traffic control, no speed persistence: the model and the sampler alone)."""
    result = rollout(load_embedded(), scene, **SETTINGS, avoid_collisions=avoid_collisions, stop_lines=avoid_collisions,
                     persistence=DEFAULT_PERSISTENCE if avoid_collisions else 0.0)
    sim = result.simulated[0]  # [A] the same agents are simulated in every rollout of a scene
    tokens = np.ascontiguousarray(result.tokens[:, sim], np.int64)  # [R, simulated, steps]
    return {
        "simulated": int(sim.sum()),
        "tokens_sha256": hashlib.sha256(tokens.tobytes()).hexdigest(),
        "first_tokens": tokens[:, :4].tolist(),
        "log_prob_sum": float(result.log_probs[:, sim].astype(np.float64).sum()),
        "path_length_m": float(np.linalg.norm(np.diff(result.trajectory[:, sim, :, :2], axis=2), axis=-1).sum()),
    }


def _check(name: str, scene) -> None:
    got, pin = _summary(scene, avoid_collisions=not name.endswith("-plain")), PINS[name]
    assert got["simulated"] == pin["simulated"]
    assert got["first_tokens"] == pin["first_tokens"]
    assert got["tokens_sha256"] == pin["tokens_sha256"], "the rollout's tokens changed (see the module docstring)"
    assert got["log_prob_sum"] == pytest.approx(pin["log_prob_sum"], rel=1e-5)
    assert got["path_length_m"] == pytest.approx(pin["path_length_m"], abs=1e-3)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def test_embedded_prior_rollout_of_a_real_womd_scene_is_pinned(shared_data):
    _check("womd-637f20cafde22ff8", next(iter(read_scenarios(shared_data / WOMD_SCENE))))


def test_embedded_prior_rollout_of_a_real_womd_scene_sampled_plainly_is_pinned(shared_data):
    _check("womd-637f20cafde22ff8-plain", next(iter(read_scenarios(shared_data / WOMD_SCENE))))


def test_embedded_prior_rollout_of_a_sample_scene_is_pinned():
    _check("sumo-sample-0", sample_scenarios()[0])


if __name__ == "__main__":  # print fresh pins (see the module docstring)
    import pprint

    torch.set_num_threads(1)
    data = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    scenes = {"sumo-sample-0": sample_scenarios()[0]}
    if (data / WOMD_SCENE).is_file():
        scenes["womd-637f20cafde22ff8"] = scenes["womd-637f20cafde22ff8-plain"] = next(iter(read_scenarios(data / WOMD_SCENE)))
    pprint.pprint({name: _summary(sc, avoid_collisions=not name.endswith("-plain")) for name, sc in scenes.items()},
                  sort_dicts=False, width=120)
