"""A user's first import (issue 15 item 8): ``pip install smart-marl`` brings what
``from envs import smart_traffic_v0`` needs, and the dev extra brings the test tools."""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from importlib.metadata import packages_distributions
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def _names(requirements: list[str]) -> set[str]:
    import re

    return {re.split(r"[<>=!~\[ ;]", r, maxsplit=1)[0].strip().lower() for r in requirements}


CORE = _names(PYPROJECT["project"]["dependencies"])
EXTRAS = {name: _names(reqs) for name, reqs in PYPROJECT["project"]["optional-dependencies"].items()}


def test_the_environment_and_its_spaces_come_with_the_core_install():
    assert {"pettingzoo", "gymnasium"} <= CORE
    assert "torchrl" not in CORE and "torchrl" in EXTRAS["rl"]  # the env never imports it (next test)
    assert "hypothesis" in EXTRAS["dev"] and "pytest" in EXTRAS["dev"]


#: the TorchRL face of the batched core is the one environment module that needs the rl extra
TORCHRL_FACE = "smart_traffic_batched_v0.py"


def _top_level_imports(path: Path) -> set[str]:
    imported = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            imported.add(node.module.split(".")[0])
    return imported


def test_the_torchrl_environment_needs_only_the_rl_extra():
    dists = packages_distributions()
    third_party = {m for m in _top_level_imports(ROOT / "envs" / TORCHRL_FACE)
                   if m not in sys.stdlib_module_names and m not in ("smart_marl", "envs", "__future__")}
    needed = {d.lower() for m in third_party for d in dists.get(m, [m])}
    assert "torchrl" in needed and needed <= CORE | EXTRAS["rl"], sorted(needed - CORE - EXTRAS["rl"])


def test_every_package_the_environment_imports_on_load_is_a_core_dependency():
    """Top-level imports of envs/*.py (not the lazy ones inside functions; not the TorchRL face) map to
    core distributions."""
    dists = packages_distributions()
    imported = set().union(*(_top_level_imports(p) for p in (ROOT / "envs").glob("*.py") if p.name != TORCHRL_FACE))
    third_party = {m for m in imported if m not in sys.stdlib_module_names and m not in ("smart_marl", "envs", "__future__")}
    needed = {d.lower() for m in third_party for d in dists.get(m, [m])}
    assert {"pettingzoo", "gymnasium"} <= needed
    assert needed <= CORE, f"envs imports {sorted(needed - CORE)} on load, which are not core dependencies"


def test_the_environment_imports_and_steps_with_every_optional_extra_missing():
    """In a process where no optional package can be imported (torchrl, pyarrow, matplotlib, SUMO,
    yaml...), ``from envs import smart_traffic_v0`` works and an episode runs."""
    optional = sorted({"torchrl", "tensordict", "pyarrow", "matplotlib", "imageio", "imageio_ffmpeg", "sumolib", "libsumo",
                       "shapely", "yaml", "tensorboard", "crc32c", "hypothesis", "pytest"})
    code = f"""
import sys
for name in {optional!r}:
    sys.modules[name] = None  # importing it now raises ImportError
from envs import smart_traffic_v0
env = smart_traffic_v0.parallel_env(scenarios="embedded", prior="embedded", controlled="sdc", background="log", horizon_steps=2,
                                    terminate_on=())  # no event ends it early: exactly horizon_steps steps
obs, infos = env.reset(seed=0)
steps = 0
while env.agents:
    env.step({{a: env.action_space(a).sample() for a in env.agents}})
    steps += 1
print("steps", steps)
"""
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.split() == ["steps", "2"]
