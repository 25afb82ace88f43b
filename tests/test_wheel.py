"""A wheel that stands alone (issue 35 item 3): the wheel built from this checkout, installed in a
fresh virtual environment outside it, runs the demo, a named fine-tuning config, a shipped what-if
example on the embedded scenes and ``import envs; envs.smart_traffic_v0.parallel_env()``.

How it stays honest without downloading anything: the wheel is built from a copy of the sources
(no ``build/`` left over in the checkout can leak into it) and installed with ``--no-deps`` into a
new venv that does not see the system's site-packages. Its third-party dependencies (torch, pettingzoo,
torchrl...) come from the running environment's site-packages through a ``.pth`` line, which adds
that folder to ``sys.path`` but does not run the ``.pth`` files inside it, so the editable install
of this checkout stays invisible. The test checks that: every ``smart_marl``, ``envs`` and
``agents`` module the commands import lies inside the new venv, no ``sys.path`` entry points into
the checkout, and every core dependency the wheel declares is installed. The commands run with
the working directory in a temporary folder and no ``PYTHONPATH``.

Slow (about two minutes on the shared CPU): ``.ci/run`` runs it with ``-m slow``."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from importlib.util import find_spec
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "README.md", "smart_marl", "envs", "agents")
WHATIF_SCENE = "sumo-7-000000-03"  # the embedded sample scene the shipped what-if examples are written for

pytestmark = pytest.mark.slow


def _run(argv, cwd, env, timeout=1800) -> str:  # a guard against a hang, not a timing check
    proc = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, argv))} exited {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv bin folder, environment, working folder) of a fresh venv holding the wheel."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "build")
    for name in SOURCES:
        (shutil.copytree if (ROOT / name).is_dir() else shutil.copy2)(ROOT / name, src / name,
                                                                     **({"ignore": ignore} if (ROOT / name).is_dir() else {}))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    isolation = [] if find_spec("setuptools") is None else ["--no-build-isolation"]  # offline when setuptools is here
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", *isolation, "-w", str(tmp / "dist"), str(src)], tmp, env)
    wheel = next((tmp / "dist").glob("smart_marl-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"agents/configs/finetune/tiny.json", "agents/whatif/examples/brake_hard.yaml",
            "smart_marl/samples/sumo_samples.smsc", "smart_marl/checkpoints/embedded/smart-1m-sumo.safetensors"} <= names

    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp, env)
    python = venv / "bin" / "python"
    purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp, env).strip())
    (purelib / "_deps_from_the_test_environment.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "--no-index", "-q", str(wheel)], tmp, env)
    work = tmp / "work"
    work.mkdir()
    env = {**env, "PATH": f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}", "OMP_NUM_THREADS": "2"}
    return venv / "bin", env, work


def test_the_wheel_is_what_the_new_venv_imports_and_its_dependencies_are_installed(installed):
    bindir, env, work = installed
    code = """
import json, sys
from importlib import metadata
import smart_marl, envs, agents, agents.finetune, agents.whatif
req = [r for r in metadata.requires("smart-marl") if "extra ==" not in r]
missing = []
for r in req:
    name = r.split(";")[0].split("[")[0]
    for op in "<>=!~ ":
        name = name.split(op)[0]
    try:
        metadata.version(name)
    except metadata.PackageNotFoundError:
        missing.append(name)
print(json.dumps({"files": [m.__file__ for m in (smart_marl, envs, agents, agents.finetune, agents.whatif)],
                  "path": sys.path, "prefix": sys.prefix, "missing": missing, "requires": req}))
"""
    info = json.loads(_run([str(bindir / "python"), "-c", code], work, env))
    venv = Path(info["prefix"]).resolve()
    assert venv == bindir.parent.resolve()
    for f in info["files"]:
        assert Path(f).resolve().is_relative_to(venv), f"{f} is not the installed wheel's"
    deps = Path(sysconfig.get_paths()["purelib"]).resolve()  # the test environment's site-packages, for the dependencies
    assert not any((deps / name).exists() for name in ("smart_marl", "envs", "agents"))  # an editable install: a finder
    inside = [p for p in info["path"] if p and Path(p).resolve().is_relative_to(ROOT) and Path(p).resolve() != deps]
    assert not inside, f"sys.path reaches into the checkout: {inside}"
    assert {"torch", "pettingzoo", "gymnasium"} <= {re.split(r"[<>=!~ \[]", r)[0] for r in info["requires"]}
    assert not info["missing"], f"core dependencies not installed: {info['missing']}"


def test_the_demo_runs_from_the_wheel(installed):
    bindir, env, work = installed
    out = _run([str(bindir / "smart-marl"), "demo", "--rollouts", "2", "--format", "gif", "--out", "demo"], work, env)
    assert out.startswith("SMART prior: embedded (smart-1m")
    assert any((work / "demo").glob("*_rollout.gif"))
    realism = json.loads((work / "demo" / "realism.json").read_text())
    assert set(realism) == {"prior", "constant_velocity", "log_replay"}
    assert realism["prior"]["meta_metric"] > realism["constant_velocity"]["meta_metric"]  # the trained prior shipped


def test_the_named_finetune_config_ships_with_the_wheel(installed):
    bindir, env, work = installed
    cfg = json.loads(_run([str(bindir / "smart-marl"), "finetune", "--config", "tiny", "--print-config"], work, env))
    assert cfg["scenes"] == "embedded" and cfg["num_scenes"] == 2
    _run([str(bindir / "smart-marl"), "finetune", "--config", "tiny", "iterations=1", "eval_episodes=0", "--out", "ft"], work, env)
    assert (work / "ft" / "checkpoints" / "policy_last.json").is_file()
    assert json.loads((work / "ft" / "config.json").read_text())["scenes"] == "embedded"


def test_a_shipped_whatif_example_runs_on_the_embedded_scenes(installed):
    bindir, env, work = installed
    out = _run([str(bindir / "smart-marl"), "whatif", "embedded", "--scenario-id", WHATIF_SCENE, "--script", "brake_hard",
                "--out", "whatif", "--rollouts", "2", "--steps", "4", "--no-realism", "--animation", "none"], work, env)
    assert f"on {WHATIF_SCENE}" in out and "52 (brake)" in out
    assert (work / "whatif" / "table.csv").is_file()


def test_import_envs_then_the_attribute_gives_the_environment(installed):
    bindir, env, work = installed
    code = """
import envs
env = envs.smart_traffic_v0.parallel_env(horizon_steps=2)
obs, infos = env.reset(seed=0)
steps = 0
while env.agents:
    env.step({a: env.action_space(a).sample() for a in env.agents})
    steps += 1
print(len(obs), steps)
"""
    n_obs, steps = map(int, _run([str(bindir / "python"), "-c", code], work, env).split())
    assert n_obs == 1 and 1 <= steps <= 2


def test_the_shipped_fine_tuned_policy_loads_from_the_wheel(installed):
    bindir, env, work = installed
    code = """
from agents.finetune import load_policy
cfg, net, meta = load_policy("embedded")
print(cfg.prior, meta["trained_on"]["num_scenes"], sum(p.numel() for p in net.parameters()) > 0)
"""
    prior, scenes, has_weights = _run([str(bindir / "python"), "-c", code], work, env).split()
    assert prior == "embedded" and int(scenes) >= 1000 and has_weights == "True"
