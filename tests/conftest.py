"""Shared fixtures. Real scenes come from ../shared/data beside the project; tests that need them
skip with a reason when that folder is absent (it is never copied into the repository). Tests that
need only *some* scene use the package's embedded samples (``sample_scenes`` and friends below).

``SMART_MARL_SHARED_DATA=PATH`` points the real-scene tests at another folder; a folder that does
not exist (``SMART_MARL_SHARED_DATA=/nonexistent pytest``) runs the suite as a user without the
shared data runs it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

SHARED_DATA = Path(os.environ.get("SMART_MARL_SHARED_DATA") or Path(__file__).resolve().parents[1].parent / "shared" / "data")

# One torch (OpenMP) thread for the whole run, this process and the commands and workers it starts:
# on a shared 2-core machine torch's threads fighting other processes make small-model steps about
# 10x slower (an eval of a tiny prior on one sample scene: 218 s with the default threads, 21 s with
# one, while other jobs loaded the machine). Set OMP_NUM_THREADS yourself to run with more.
os.environ.setdefault("OMP_NUM_THREADS", "1")


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The ../shared/data folder, or a skip when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"../shared/data is absent ({SHARED_DATA}): real-scene tests need it")
    return SHARED_DATA


@pytest.fixture(scope="session", autouse=True)
def _torch_threads_from_the_environment():
    """torch's thread count as OMP_NUM_THREADS says (1 unless set; see above), also when torch was
    imported before this file set it."""
    import torch

    threads = os.environ["OMP_NUM_THREADS"]
    if threads.isdigit() and int(threads) > 0:
        torch.set_num_threads(int(threads))


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module of small-model tests, whatever OMP_NUM_THREADS says: on a shared
    2-core machine, torch's threads fighting other processes make these small steps about 10x slower
    (and the pinned rollouts are pinned on one thread)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


WOMD_RECORDS = ("womd_tfrecord/motion_data_one_scenario.tfrecord", "womd_tfrecord/womd_scenario_input.tfrecord")


@pytest.fixture(scope="session")
def womd_scenes(shared_data):
    """The two real WOMD records' scenes, in this order: 637f20cafde22ff8 (83 tracks), ee519cf571686d19 (257)."""
    from smart_marl.readers import read_scenarios

    return [sc for record in WOMD_RECORDS for sc in read_scenarios(shared_data / record)]


@pytest.fixture(scope="session")
def kdisks_vocab():
    """Factory ``kdisks_vocab(scenes, size=32)``: k-disks motion vocabulary (seed 0) from the scenes' snippets (stride 1)."""
    from smart_marl.tokens import build_motion_vocabulary, collect_snippets

    def build(scenes, size=32):
        snippets, _ = collect_snippets(scenes, stride=1)
        return build_motion_vocabulary(snippets, size, seed=0, progress=False)

    return build


@pytest.fixture(scope="session")
def embedded_prior():
    """(model, motion vocabulary) of the package's embedded prior, on the CPU."""
    from smart_marl.model.checkpoint import load_prior

    return load_prior("embedded", "cpu")


@pytest.fixture(scope="session")
def sample_scenes():
    """The package's embedded sample scenes (smart_marl.embedded; SUMO, 91 frames, current frame 10):
    sumo-7-000000-00 .. -03 with 22, 25, 44 and 10 tracks (vehicles, pedestrians and cyclists; no OTHER).
    Tests that need *some* real-looking scene use these, so they run without ../shared/data."""
    from smart_marl.embedded import sample_scenarios

    return sample_scenarios()


@pytest.fixture(scope="session")
def sample_scene_file(sample_scenes, tmp_path_factory) -> Path:
    """The first sample scene (sumo-7-000000-00, 22 tracks) alone in a scene file, for commands that
    take a path."""
    from smart_marl.cache import write_shard

    path = tmp_path_factory.mktemp("sample_scene") / "sumo-7-000000-00.smsc"
    write_shard(path, sample_scenes[:1])
    return path


@pytest.fixture(scope="session")
def sample_vocab(sample_scenes, kdisks_vocab):
    """32 k-disks tokens per type from the four sample scenes (the sample-scene twin of ``womd_vocab``)."""
    return kdisks_vocab(sample_scenes)


@pytest.fixture(scope="session")
def sample_model(sample_vocab):
    """The tiny random model (:func:`_tiny_smart`) over ``sample_vocab``."""
    return _tiny_smart(sample_vocab)


@pytest.fixture(scope="session")
def womd_vocab(womd_scenes, kdisks_vocab):
    """32 k-disks tokens per type from both WOMD scenes (what the env, what-if and fine-tuning tests use)."""
    return kdisks_vocab(womd_scenes)


# The env, what-if and fine-tuning mechanics tests share these under short names: the real WOMD scenes,
# their 32-token vocabulary and the tiny random model over it (a test module defines its own
# ``scenes`` / ``vocab`` / ``model`` to mean something else, as tests/test_rollout.py does).
@pytest.fixture(scope="module")
def scenes(womd_scenes):
    return womd_scenes


@pytest.fixture(scope="module")
def vocab(womd_vocab):
    return womd_vocab


@pytest.fixture(scope="module")
def model(vocab, tiny_smart):
    return tiny_smart(vocab)


def _tiny_smart(vocab):
    """A small randomly initialised SMART model (eval mode, seed 0) over ``vocab``'s motion tokens."""
    import torch

    from smart_marl.model.smart import SMART, get_config

    sizes = tuple(int(vocab[t].contour.shape[0]) for t in range(3))
    cfg = get_config(dict(hidden_dim=16, num_heads=2, head_dim=8, num_road_layers=1, num_agent_blocks=1,
                          motion_vocab_sizes=sizes, road_vocab_size=8, num_freq_bands=4, dropout=0.0,
                          agent_neighbours=8, map_neighbours=8, road_neighbours=4))
    torch.manual_seed(0)
    return SMART(cfg, motion_contours=[vocab[t].contour for t in range(3)]).eval()


@pytest.fixture(scope="session")
def tiny_smart():
    """Factory ``tiny_smart(vocab) -> SMART``: a small random model for tests of mechanics (shapes,
    equalities, commands), never of behaviour."""
    return _tiny_smart


@pytest.fixture(scope="session")
def save_tiny_prior(tmp_path_factory):
    """Factory ``save_tiny_prior(vocab) -> Path``: the tiny random model over ``vocab`` saved as a
    checkpoint (with a placeholder road vocabulary) in a fresh temporary folder; returns its JSON path."""
    import numpy as np

    from smart_marl.model.checkpoint import save_checkpoint
    from smart_marl.tokens.road import RoadVocabulary

    def save(vocab):
        road_vocab = RoadVocabulary(points=np.zeros((8, 11, 2), np.float32), tolerance_m=0.0, requested_size=8)
        return save_checkpoint(tmp_path_factory.mktemp("tiny_prior") / "prior", _tiny_smart(vocab), vocab, road_vocab)

    return save


@pytest.fixture(scope="session")
def tiny_prior(sample_scenes, save_tiny_prior):
    """The tiny random checkpoint over a 16-token uniform-grid vocabulary from the package's sample
    scenes. Returns the checkpoint's JSON path."""
    from smart_marl.tokens import collect_snippets, uniform_grid_vocabulary

    snippets, _ = collect_snippets(sample_scenes)
    return save_tiny_prior(uniform_grid_vocabulary(snippets, 16))
