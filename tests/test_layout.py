"""One job per file (issue 35): no source file of the three packages is longer than 600 lines and no
function or method in them longer than 100 lines, so that a module reads as one job and a function
as one step of it. Counted from the files as text (lines) and their syntax trees (a function's
first line, decorators excluded, to its last), without importing anything."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("smart_marl", "envs", "agents")
MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 100


def _source_files() -> list[Path]:
    """Every .py file of the three packages."""
    return [path for pkg in PACKAGES for path in sorted((ROOT / pkg).rglob("*.py"))]


def _long_functions(path: Path, root: Path = ROOT) -> list[str]:
    """``file:line name (n lines)`` of every function or method of ``path`` over the limit (file relative to ``root``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            lines = node.end_lineno - node.lineno + 1
            if lines > MAX_FUNCTION_LINES:
                out.append(f"{path.relative_to(root)}:{node.lineno} {node.name} ({lines} lines)")
    return out


def test_every_package_has_source_files():
    files = _source_files()
    assert len(files) > 80
    assert {f.relative_to(ROOT).parts[0] for f in files} == set(PACKAGES)


def test_no_source_file_is_longer_than_600_lines():
    long = [f"{path.relative_to(ROOT)} ({n} lines)" for path in _source_files()
            if (n := len(path.read_text(encoding="utf-8").splitlines())) > MAX_FILE_LINES]
    assert not long, f"files over {MAX_FILE_LINES} lines (split them along their jobs): " + ", ".join(long)


def test_no_function_is_longer_than_100_lines():
    long = [entry for path in _source_files() for entry in _long_functions(path)]
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines (cut them into named steps): " + ", ".join(long)


def test_a_function_one_line_over_the_limit_is_named(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_LINES))  # the def line + 100 = 101 lines
    sample = tmp_path / "probe.py"
    sample.write_text(f"class A:\n    def short(self):\n        return 1\n\n\ndef long():\n{body}\n", encoding="utf-8")
    assert _long_functions(sample, tmp_path) == [f"probe.py:6 long ({MAX_FUNCTION_LINES + 1} lines)"]
