"""A fine-tuning run (``smart-marl finetune``) killed with SIGKILL in the middle of an iteration, then
started again with the same command, resumes after the last iteration it finished (it does not train the
earlier ones again) and ends at the same policy, bit for bit, as the run that was never interrupted, with
the same log (one row per iteration, the same numbers). What it resumes from: ``OUT/checkpoints/resume.*``
(agents.finetune_state), written after every iteration.

Slow (about 40 s on the shared 2-core CPU: three short runs of the ``tiny`` config): ``.ci/run`` runs it
with ``-m slow``."""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

from agents.policy import read_policy  # noqa: E402

pytestmark = pytest.mark.slow

ITERATIONS = 6
KILLED_IN = 4  # the iteration the second run is killed inside
OVERRIDES = [f"iterations={ITERATIONS}", "checkpoint_every=1", "eval_episodes=0", "tensorboard=false", "torch_threads=1"]
LOG_COLUMNS_THAT_VARY = {"seconds"}  # wall-clock time: the only column two identical runs may differ in


def finetune_command(out_dir: Path) -> list[str]:
    return [sys.executable, "-m", "smart_marl.cli", "finetune", "--config", "tiny", *OVERRIDES, f"out_dir={out_dir}"]


def log_rows(out_dir: Path) -> list[dict]:
    with open(out_dir / "finetune.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_a_run_killed_inside_an_iteration_and_started_again_ends_at_the_uninterrupted_runs_policy(tmp_path):
    """The uninterrupted run, then the same command killed (SIGKILL) once iteration ``KILLED_IN - 1``'s checkpoint
    is written plus half of an iteration's duration (so inside iteration ``KILLED_IN``: its checkpoint and log row
    are not there yet), then the same command again: it resumes after iteration ``KILLED_IN - 1`` and every
    checkpoint's tensors equal the uninterrupted run's."""
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    subprocess.run(finetune_command(whole), check=True, capture_output=True, text=True, timeout=600)
    rows = log_rows(whole)
    assert [int(r["iteration"]) for r in rows] == list(range(1, ITERATIONS + 1))
    iteration_s = float(rows[KILLED_IN - 1]["seconds"]) - float(rows[KILLED_IN - 2]["seconds"])

    state = killed / "checkpoints" / "resume.json"  # written (renamed into place) last of an iteration's files

    def state_iteration() -> int:
        return json.loads(state.read_text())["iteration"] if state.is_file() else 0

    proc = subprocess.Popen(finetune_command(killed), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 300
        while state_iteration() < KILLED_IN - 1:
            assert proc.poll() is None, f"the run ended ({proc.returncode}) before iteration {KILLED_IN - 1}'s checkpoint"
            assert time.monotonic() < deadline, "no checkpoint after 300 s"
            time.sleep(0.02)
        time.sleep(0.5 * iteration_s)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    # killed inside iteration KILLED_IN: it had finished the one before and not this one
    assert not (killed / "checkpoints" / f"policy_{KILLED_IN:04d}.json").exists(), "killed too late: between iterations"
    assert [int(r["iteration"]) for r in log_rows(killed)] == list(range(1, KILLED_IN))

    kept = {i: (killed / "checkpoints" / f"policy_{i:04d}.safetensors").stat().st_mtime_ns for i in range(1, KILLED_IN)}
    again = subprocess.run(finetune_command(killed), check=True, capture_output=True, text=True, timeout=600)
    assert f"resuming {killed} after iteration {KILLED_IN - 1} of {ITERATIONS}" in again.stdout
    assert all((killed / "checkpoints" / f"policy_{i:04d}.safetensors").stat().st_mtime_ns == t for i, t in kept.items()), \
        "the started-again run trained the finished iterations again"

    names = [f"policy_{i:04d}" for i in range(1, ITERATIONS + 1)] + ["policy_last"]
    for name in names:
        _, expected = read_policy(whole / "checkpoints" / name)
        _, got = read_policy(killed / "checkpoints" / name)
        assert expected.keys() == got.keys(), name
        differ = [k for k in expected if not torch.equal(expected[k], got[k])]
        assert not differ, f"{name}: tensors differ from the uninterrupted run's: {differ}"
    strip = lambda rs: [{k: v for k, v in r.items() if k not in LOG_COLUMNS_THAT_VARY} for r in rs]  # noqa: E731
    assert strip(log_rows(killed)) == strip(rows), "the log of the started-again run differs from the uninterrupted run's"
