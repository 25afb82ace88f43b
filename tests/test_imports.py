"""The project's modules form no import cycle: the import graph (every import of a project module,
at module level or inside a function) is acyclic, project modules are imported at the top of files
(the exceptions, optional extras, are listed), the layering rule smart_marl <- envs <- agents holds,
and every module imports in a fresh interpreter whatever the order."""

from __future__ import annotations

import ast
import json
import random
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("smart_marl", "envs", "agents")
LAYER = {"smart_marl": 0, "envs": 1, "agents": 2}  # a module may import its own layer and those below

# Function-level imports of project modules that stay there on purpose: the module they import
# needs an optional extra, and the importer works (or says what to install) without it.
OPTIONAL_EXTRA_IMPORTS = {
    ("agents.commands.finetune", "agents.evaluate"),  # torchrl, pettingzoo (the env and rl extras)
    ("agents.commands.finetune", "agents.finetune"),
    ("agents.commands.finetune", "agents.select_policy"),
}


def _module_files() -> dict[str, Path]:
    """Dotted name -> file of every module of the three packages (a package is its __init__)."""
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


MODULES = _module_files()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _imports(name: str) -> list[tuple[str, bool]]:
    """(project module imported, at module level) for every import statement of module ``name``."""
    tree = ast.parse(MODULES[name].read_text())
    package = name if _is_package(name) else name.rpartition(".")[0]
    top = {id(n) for n in tree.body} | {id(n) for stmt in tree.body if isinstance(stmt, ast.If) for n in stmt.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            # "from pkg import sub" imports the submodule pkg.sub; "from pkg import name", pkg itself
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:  # "import a.b.c" of a project module: the module itself
                target = target.rpartition(".")[0]
            if target:
                out.append((target, id(node) in top))
    return out


def _ancestors(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:i]) for i in range(1, len(parts))]


def _graph() -> dict[str, set[str]]:
    """module -> the project modules that importing it executes first: what it imports, and the
    packages (``__init__``) of those that are not already being imported as its own ancestors."""
    graph = {}
    for name in MODULES:
        mine = set(_ancestors(name))
        edges = set()
        for target, _ in _imports(name):
            for dep in [*_ancestors(target), target]:
                if dep != name and dep not in mine and dep in MODULES:
                    edges.add(dep)
        graph[name] = edges
    return graph


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state:
                found = visit(nxt)
                if found:
                    return found
        stack.pop()
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state:
            found = visit(node)
            if found:
                return found
    return None


def test_the_import_graph_of_the_project_modules_has_no_cycle():
    assert len(MODULES) > 80
    cycle = _find_cycle(_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_a_cycle_is_found_when_there_is_one():
    assert _find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert _find_cycle({"a": {"b"}, "b": set()}) is None


def test_project_modules_are_imported_at_the_top_of_files():
    inside = sorted({(name, target) for name in MODULES for target, top in _imports(name) if not top})
    assert set(inside) <= OPTIONAL_EXTRA_IMPORTS, f"function-level imports of project modules: {inside}"


def test_imports_go_one_way_smart_marl_envs_agents():
    upward = sorted({(name, target) for name in MODULES for target, _ in _imports(name)
                     if LAYER[target.split(".")[0]] > LAYER[name.split(".")[0]]})
    assert not upward, f"imports against the layering smart_marl <- envs <- agents: {upward}"


_IMPORT_ALL = """
import importlib, json, sys
order, skipped = json.loads(sys.argv[1]), []
for name in order:
    try:
        importlib.import_module(name)
    except ModuleNotFoundError as exc:  # an optional extra that is not installed: not a cycle
        if (exc.name or "").split(".")[0] in ("smart_marl", "envs", "agents"):
            raise
        skipped.append(name)
print(json.dumps(skipped))
"""


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_module_imports_in_a_fresh_interpreter_in_a_random_order(seed):
    order = sorted(MODULES)
    random.Random(seed).shuffle(order)
    proc = subprocess.run([sys.executable, "-c", _IMPORT_ALL, json.dumps(order)], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    skipped = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(skipped) < len(order) // 2, f"most modules need extras that are not installed: {skipped}"
