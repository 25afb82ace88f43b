"""Helpers shared by test modules (imported as ``from helpers import ...``, as ``fuzzing`` and ``model_variants``):
the benchmark scripts loaded as modules (``benchmarks/`` is not a package) and the command line run in-process."""

from __future__ import annotations

import contextlib
import importlib.util
import io
from pathlib import Path

from smart_marl.cli import main

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load_benchmark(name: str):
    """``benchmarks/NAME.py`` as a module."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_eval(argv: list[str]) -> tuple[int, str, str]:
    """``smart-marl eval ARGV`` in this process: (exit code, stdout, stderr); argparse's exits are codes too."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(["eval", *argv])
        except SystemExit as exc:  # argparse's own checks
            code = exc.code
    return code, out.getvalue(), err.getvalue()
