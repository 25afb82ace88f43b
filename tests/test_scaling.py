"""Scaling laws (issue 59): the power-law fits recover known exponents from synthetic points, refuse what they
cannot fit, and the scaling command runs a tiny grid end to end (resumable: a second call trains nothing)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from smart_marl.scaling import PAPER_EXPONENT, fit_power_law, fit_pure_power_law

ROOT = Path(__file__).resolve().parents[1]


def test_the_fit_with_an_irreducible_term_recovers_a_known_law_exactly():
    x = np.geomspace(1e5, 1e8, 6)
    fit = fit_power_law(x, 1.7 + 9.0 * x ** -0.25)
    assert fit.exponent == pytest.approx(-0.25, abs=1e-6)
    assert fit.irreducible == pytest.approx(1.7, rel=1e-6) and fit.coefficient == pytest.approx(9.0, rel=1e-5)
    assert fit.dof == 3 and fit.exponent_se < 1e-6
    assert fit.predict([1e6])[0] == pytest.approx(1.7 + 9.0 * 1e6 ** -0.25, rel=1e-9)


def test_with_noise_the_exponent_lies_within_its_standard_errors():
    rng = np.random.default_rng(1)
    x = np.geomspace(1e5, 1e9, 8)
    hits = 0
    for _ in range(20):
        loss = (2.0 + 30.0 * x ** -0.3) * np.exp(rng.normal(0, 0.003, len(x)))
        fit = fit_power_law(x, loss)
        hits += abs(fit.exponent + 0.3) <= 2.5 * fit.exponent_se
    assert hits >= 17  # about 95% within two and a half standard errors


def test_the_pure_power_law_is_a_line_in_log_log_the_papers_form():
    x = np.array([1e6, 7e6, 2.7e7, 1e8])
    fit = fit_pure_power_law(x, 5.0 * x ** PAPER_EXPONENT)
    assert fit.exponent == pytest.approx(PAPER_EXPONENT, abs=1e-9) and fit.irreducible == 0.0 and fit.dof == 2
    noisy = fit_pure_power_law(x, 5.0 * x ** PAPER_EXPONENT * np.array([1.01, 0.99, 1.0, 1.005]))
    assert noisy.exponent_se > 0 and abs(noisy.exponent - PAPER_EXPONENT) < 3 * noisy.exponent_se


def test_three_points_leave_no_degree_of_freedom_for_an_error():
    fit = fit_power_law([1e5, 1e6, 1e7], [4.0, 3.5, 3.3])
    assert fit.dof == 0 and fit.exponent_se == float("inf") and fit.exponent < 0


@pytest.mark.parametrize("x, loss", [([1, 2], [1.0]), ([1], [1.0]), ([1, 1], [2.0, 1.0]), ([1, -2], [2.0, 1.0]),
                                     ([1, 2], [2.0, float("nan")]), ([1, 2], [0.0, 1.0])])
def test_points_a_power_law_cannot_fit_are_refused(x, loss):
    with pytest.raises(ValueError):
        fit_power_law(x, loss)
    with pytest.raises(ValueError):
        fit_pure_power_law(x, loss)


def test_the_scaling_command_runs_a_tiny_grid_and_resumes_without_training_again(tmp_path):
    """Widths 8 and 16 on a token cache of the four shared WOMD scenes (one shard each), data sizes of 1 and 2
    shards, two steps each: every run a JSON line with its parameters, tokens and held-out losses, the fits and the
    PNG; run again, nothing is trained."""
    shared = ROOT.parent / "shared" / "data"
    files = sorted((shared / "womd_tfrecord").glob("*.tfrecord")) + sorted((shared / "smart_pkl").glob("*.pkl"))
    if len(files) < 4:
        pytest.skip("the shared WOMD scenes are not there")
    tokens = tmp_path / "tokens"
    made = subprocess.run([sys.executable, "-m", "smart_marl.cli", "pretokenize", *map(str, files), "--out", str(tokens), "--quiet"],
                          capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert made.returncode == 0, made.stderr[-2000:]
    out = tmp_path / "runs"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "scaling_laws.py"), "--tokens", str(tokens), "--val", "embedded",
           "--real-val", "embedded", "--out", str(out), "--widths", "8,16", "--data-shards", "1,2", "--data-width", "8",
           "--steps", "2", "--batch-size", "1", "--threads", "1"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert first.returncode == 0, first.stderr[-2000:]
    lines = [json.loads(line) for line in first.stdout.splitlines()]
    runs = [r for r in lines if r["kind"] == "run"]
    assert [r["run"] for r in runs] == ["w8_s4", "w16_s4", "w8_s1", "w8_s2"]  # sizes on every shard, then data
    for r in runs:
        assert r["parameters"] > 0 and r["train_target_tokens"] > 0
        assert np.isfinite(r["val_loss_generated"]) and np.isfinite(r["val_loss_real"])
    sizes = {r["width"]: r["parameters"] for r in runs if r["axis"] == "size"}
    assert sizes[16] > sizes[8]
    data = sorted((r["train_scenes"], r["train_target_tokens"]) for r in runs if r["axis"] == "data")
    assert [n for n, _ in data] == [1, 2] and data[0][1] < data[1][1]
    fits = [r for r in lines if r["kind"] == "fit"]
    assert {f["axis"] for f in fits} == {"size", "data"} and all(f["paper_exponent"] == PAPER_EXPONENT for f in fits)
    assert (out / "scaling.png").stat().st_size > 1000 and (out / "fit.json").is_file()
    trained = sorted(p.stat().st_mtime_ns for p in out.glob("*/checkpoints/last.safetensors"))
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert again.returncode == 0, again.stderr[-2000:]
    assert sorted(p.stat().st_mtime_ns for p in out.glob("*/checkpoints/last.safetensors")) == trained
    assert [json.loads(line)["run"] for line in again.stdout.splitlines() if '"run"' in line] == [r["run"] for r in runs]
