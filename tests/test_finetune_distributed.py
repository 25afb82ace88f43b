"""Fine-tuning on more than one process (torchrun): every process collects on its own env and the
gradients are averaged, so the processes end with the same policy, which process 0 saves."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("torchrl", reason="the rl extra (torchrl) is not installed")

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import hashlib, json, os, sys
import torch
from agents.finetune import finetune, load_finetune_config
from agents.policy import read_policy

out = sys.argv[1]
cfg = load_finetune_config("tiny", {"out_dir": out, "iterations": 2, "frames_per_batch": 8, "minibatch_size": 8, "ppo_epochs": 1,
                                    "horizon_steps": 2, "eval_episodes": 0, "tensorboard": False, "torch_threads": 1})
result = finetune(cfg)
rank = int(os.environ["RANK"])
digest = hashlib.sha256(b"".join(v.detach().numpy().tobytes() for _, v in sorted(result.policy.state_dict().items()))).hexdigest()
row = {"rank": rank, "digest": digest, "frames": result.history[-1]["frames"], "checkpoint": str(result.checkpoint)}
if rank == 0:
    _, weights = read_policy(result.checkpoint)
    saved = {k[len("actor."):]: v for k, v in weights.items() if k.startswith("actor.")}
    row["saved_digest"] = hashlib.sha256(b"".join(v.numpy().tobytes() for _, v in sorted(saved.items()))).hexdigest()
with open(os.path.join(out, f"rank{rank}.json"), "w") as f:
    json.dump(row, f)
"""


def test_two_processes_under_torchrun_train_one_policy(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2", str(script),
                           str(tmp_path / "run")], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads((tmp_path / "run" / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert rows[0]["digest"] == rows[1]["digest"] == rows[0]["saved_digest"]  # one policy, the one saved
    assert rows[0]["frames"] == rows[1]["frames"] == 2 * 2 * 8  # both processes' scene-steps count
    assert rows[1]["checkpoint"] == "None" and (tmp_path / "run" / "checkpoints" / "policy_last.json").is_file()
    assert len((tmp_path / "run" / "finetune.csv").read_text().splitlines()) == 3  # process 0 logs, once per iteration
