"""The embedded prior's rollouts are pinned: a short rollout of a fixed seed gives exactly these
tokens. Refactors of the model, the KV-cached step or the rollout engine must not change them.

Pinned here: 2 rollouts x 4 token steps, seed 7, top-k 5, of the embedded prior
(``smart_marl/checkpoints/embedded``) on the real WOMD scene 637f20cafde22ff8 (skipped when
``../shared/data`` is absent) and on the package's first SUMO sample scene (always runs). The
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

WOMD_SCENE = "womd_tfrecord/motion_data_one_scenario.tfrecord"
SETTINGS = dict(num_rollouts=2, num_steps=4, top_k=5, seed=7)

PINS = {  # path lengths regenerated when the 10 Hz frames became a Hermite curve between token ends (same tokens)
    "womd-637f20cafde22ff8": {
        "simulated": 50,
        "tokens_sha256": "eaee5faf29792565b7fb4aa7b704baa85c7d58012ce89aab449e168eb4b05d84",
        "first_tokens": [[[1, 1, 1, 1], [1, 1, 1, 1], [1, 1, 1, 1], [0, 1, 1, 1]],
                         [[1, 0, 1, 359], [1, 1, 1, 1], [1, 1, 1, 1], [1, 0, 1, 1]]],
        "log_prob_sum": -782.0386544018984,
        "path_length_m": 910.8709253607675,
    },
    "sumo-sample-0": {
        "simulated": 22,
        "tokens_sha256": "90f54f1ebbe92c311ee6ed9bd24c412f546c0ea22b7b214c47c097a6595703ec",
        "first_tokens": [[[19, 19, 17, 987], [5, 5, 5, 5], [5, 5, 5, 5], [254, 5, 5, 254]],
                         [[19, 68, 987, 19], [5, 254, 5, 5], [23, 23, 254, 5], [5, 5, 5, 5]]],
        "log_prob_sum": -167.4817026257515,
        "path_length_m": 42.2130381992899,
    },
}


def _summary(scene) -> dict:
    """What is pinned of one scene's rollout (computed on one torch thread)."""
    result = rollout(load_embedded(), scene, **SETTINGS)
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
    got, pin = _summary(scene), PINS[name]
    assert got["simulated"] == pin["simulated"]
    assert got["first_tokens"] == pin["first_tokens"]
    assert got["tokens_sha256"] == pin["tokens_sha256"], "the rollout's tokens changed (see the module docstring)"
    assert got["log_prob_sum"] == pytest.approx(pin["log_prob_sum"], rel=1e-5)
    assert got["path_length_m"] == pytest.approx(pin["path_length_m"], abs=1e-3)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # see tests/conftest.py


def test_embedded_prior_rollout_of_a_real_womd_scene_is_pinned(shared_data):
    _check("womd-637f20cafde22ff8", next(iter(read_scenarios(shared_data / WOMD_SCENE))))


def test_embedded_prior_rollout_of_a_sample_scene_is_pinned():
    _check("sumo-sample-0", sample_scenarios()[0])


if __name__ == "__main__":  # print fresh pins (see the module docstring)
    import pprint

    torch.set_num_threads(1)
    data = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    scenes = {"sumo-sample-0": sample_scenarios()[0]}
    if (data / WOMD_SCENE).is_file():
        scenes["womd-637f20cafde22ff8"] = next(iter(read_scenarios(data / WOMD_SCENE)))
    pprint.pprint({name: _summary(sc) for name, sc in scenes.items()}, sort_dicts=False, width=120)
