"""Hostile-input review, findings 2 and 3: a view radius that would make rendering loop or overflow is refused
by the env and by the renderer itself, and ``smart-marl demo`` without the render extra still prints its
realism table and names the extra the animation needs."""

from __future__ import annotations

import json
import sys

import pytest

from envs._arguments import MIN_RENDER_RADIUS_M, check_env_arguments
from envs.errors import EnvConfigError
from smart_marl.embedded import sample_scenarios
from smart_marl.errors import UsageError

ENV_ARGS = dict(background="log", horizon_steps=4, scene_order="random", terminate_on=("goal",), render_mode=None,
                render_modes=["rgb_array"], max_agents=None, top_k=5, temperature=1, reference_top_k=None, render_size_px=64,
                avoid_collisions=True, reward=None, observation="vector", controlled="sdc")


@pytest.mark.parametrize("radius", [1e-10, 1e-300, 0.999, 0.0, -5.0, float("nan")])
def test_the_env_refuses_a_render_radius_below_one_metre_by_name(radius):
    with pytest.raises(EnvConfigError, match=r"render_radius_m must be"):
        check_env_arguments(**ENV_ARGS, render_radius_m=radius)
    assert check_env_arguments(**ENV_ARGS, render_radius_m=MIN_RENDER_RADIUS_M)["render_radius_m"] == 1.0


@pytest.mark.parametrize("radius", [1e-10, 1e-300, 0.5, float("nan"), float("inf"), "60"])
def test_the_renderer_itself_refuses_a_radius_that_would_loop_or_overflow(radius):
    pytest.importorskip("matplotlib", reason="the render extra is not installed")
    from smart_marl.render import BevRenderer

    with pytest.raises(UsageError, match=r"BevRenderer: view_radius_m must be"):
        BevRenderer(sample_scenarios()[0], size_px=64, view_radius_m=radius)


def test_the_narrowest_view_renders_a_frame_of_its_size():
    pytest.importorskip("matplotlib", reason="the render extra is not installed")
    from smart_marl.render import MIN_VIEW_RADIUS_M, render_scenario_frame

    image = render_scenario_frame(sample_scenarios()[0], size_px=64, view_radius_m=MIN_VIEW_RADIUS_M)
    assert image.shape == (64, 64, 3) and image.dtype.name == "uint8"


def test_demo_without_the_render_extra_prints_its_table_and_names_the_extra(tmp_path, capsys, monkeypatch):
    """As a wheel installed with only the rl extra: every ``import matplotlib...`` fails."""
    from smart_marl.cli import main

    for name in [n for n in sys.modules if n == "matplotlib" or n.startswith("matplotlib.")] + ["matplotlib"]:
        monkeypatch.setitem(sys.modules, name, None)  # None in sys.modules: the import raises ModuleNotFoundError
    with pytest.raises(ModuleNotFoundError):
        import matplotlib  # noqa: F401
    out_dir = tmp_path / "demo"
    assert main(["demo", "--out", str(out_dir), "--rollouts", "1", "--format", "gif"]) == 0
    captured = capsys.readouterr()
    assert "the animation needs the render extra (pip install 'smart-marl[render]')" in captured.err
    assert "matplotlib" in captured.err and "realism meta-metric" in captured.out
    assert not list(out_dir.glob("*_rollout.*"))
    assert set(json.loads((out_dir / "realism.json").read_text())) == {"prior", "constant_velocity", "log_replay"}


def test_a_refused_fine_tuning_run_writes_nothing(tmp_path):
    """A run refused while it sets up (here its scenes: a folder without any) leaves no OUT folder or OUT/config.json."""
    from agents.finetune import finetune
    from agents.finetune_config import load_finetune_config
    from smart_marl.errors import SmartMarlError

    empty, out = tmp_path / "no_scenes", tmp_path / "out"
    empty.mkdir()
    cfg = load_finetune_config("tiny", {"scenes": str(empty), "out_dir": str(out), "eval_episodes": 0, "tensorboard": False})
    with pytest.raises(SmartMarlError):
        finetune(cfg)
    assert not out.exists()


def test_a_scene_pool_refuses_a_cache_whose_manifest_lists_fewer_scenes_than_its_shard_when_it_is_built(tmp_path):
    """Checked when the pool is made, not at the first refill that reaches the shard (hours into a run)."""
    from envs._pool import ScenePool
    from smart_marl.errors import ScenarioReadError
    from smart_marl.readers.scene_cache import scene_entry, write_manifest, write_shard

    scenes = sample_scenarios()[:3]
    for name, listed in (("whole", scenes), ("short", scenes[:2])):
        folder = tmp_path / name
        folder.mkdir()
        write_shard(folder / "a.smsc", scenes)
        write_manifest(folder, [{"file": "a.smsc", "input": "samples", "scenes": [scene_entry(sc, "a.smsc") for sc in listed]}])
    assert len(ScenePool(str(tmp_path / "whole"))) == 3
    with pytest.raises(ScenarioReadError, match="holds 3 scenes, the manifest lists 2"):
        ScenePool(str(tmp_path / "short"))
