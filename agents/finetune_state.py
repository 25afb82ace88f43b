"""Fine-tuning stage, resuming a run: what a fine-tuning run keeps after every iteration so that the same
command, started again after a crash, a kill or a time limit, goes on from the last finished iteration
and ends where the uninterrupted run ends, bit for bit (:func:`save_run_state`, :func:`load_run_state`).

What goes out, after every iteration, in ``OUT/checkpoints/``: ``resume.safetensors`` (the loss module's
tensors: the actor's and the critic's weights and buffers; Adam's moments; the torch, numpy and Python RNG
states as integer tensors) and ``resume.json`` (the iteration, frames, seconds and scenes seen so far, the
scene pool's place in its order, the optimizer's settings, the run's config), each written to a temporary
name and renamed, JSON last; under ``torchrun`` every process keeps its own (``resume_rank{R}.*``).
What comes in on a start: those files when they are there (else the run starts afresh). They are plain
tensors and JSON: nothing in them is executed when read, and a file that is not this run's state (another
config, another network, malformed) is refused with a :class:`~agents.finetune_config.FinetuneError`
naming the file, before anything trains.

Why the resumed run is exact: every iteration collects from a full reset of the batched env, its prior's
sampler seeded from (seed, rank, iteration) (:func:`episode_seed`), so at an iteration's start the env is a
function of the scene pool's order alone, which is saved; everything else that draws (the policy's actions,
the minibatch order) draws from the global RNGs, which are saved too. A resumed run may change only the
fields of :data:`RESUMABLE_CHANGES` (more iterations, a time limit, the evaluation, the logging).
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from smart_marl.config_files import is_integer, is_number
from smart_marl.model.checkpoint import CheckpointError, rng_problem
from smart_marl.train_state import check_optimizer_state, rng_state, set_rng_state

from .finetune_config import FinetuneConfig, FinetuneError

FORMAT, VERSION = "smart-marl-finetune-state", 1
RESUMABLE_CHANGES = ("iterations", "time_limit_s", "eval_episodes", "eval_seed", "eval_scenes", "eval_num_scenes", "eval_rules",
                     "tensorboard", "checkpoint_every", "out_dir")
"""The config fields a resumed run may set differently from the run it resumes: none of them changes what an
iteration does (``out_dir``: the folder may have been moved)."""


@dataclass
class Progress:
    """Where a run stands after its last finished iteration."""

    iteration: int = 0
    frames: int = 0
    seconds: float = 0.0  # training time so far (the log's ``seconds``; ``time_limit_s`` counts it)
    seen: set = field(default_factory=set)  # training scenes (pool indices) played so far


def episode_seed(seed: int, rank: int, iteration: int) -> int:
    """The seed of the prior's sampler for iteration ``iteration`` (1-based) of process ``rank``."""
    return int(np.random.SeedSequence([int(seed), int(rank), int(iteration)]).generate_state(1)[0])


def state_paths(out_dir: str | Path, rank: int) -> tuple[Path, Path]:
    """(JSON, safetensors) of process ``rank``'s resume state in ``out_dir``."""
    stem = Path(out_dir) / "checkpoints" / ("resume" if rank == 0 else f"resume_rank{rank}")
    return stem.with_name(stem.name + ".json"), stem.with_name(stem.name + ".safetensors")


def save_run_state(out_dir: str | Path, rank: int, world: int, cfg: FinetuneConfig, loss: torch.nn.Module,
                   optimizer: torch.optim.Optimizer, pool, progress: Progress) -> None:
    """Process ``rank``'s state after iteration ``progress.iteration`` (module docstring)."""
    meta_path, tensor_path = state_paths(out_dir, rank)
    meta_path.parent.mkdir(parents=True, exist_ok=True)
    tensors = {f"loss.{k}": v.detach().cpu().clone().contiguous() for k, v in loss.state_dict().items()}
    opt = optimizer.state_dict()
    for i, entry in opt["state"].items():
        tensors.update({f"optim.{i}.{name}": torch.as_tensor(v).detach().cpu().clone() for name, v in entry.items()})
    rng = rng_state()
    tensors["rng.torch"], tensors["rng.numpy_keys"] = rng["torch"], rng["numpy"]["keys"]
    tensors["rng.python_internal"] = rng["python"]["internal"]
    tensors.update({f"rng.cuda.{i}": t for i, t in enumerate(rng.get("cuda", []))})
    meta = {"format": FORMAT, "version": VERSION, "rank": rank, "world": world, "config": cfg.to_dict(),
            "iteration": progress.iteration, "frames": progress.frames, "seconds": progress.seconds, "seen": sorted(progress.seen),
            "pool": pool.order_state(),
            "optimizer": {"param_groups": [{k: list(v) if isinstance(v, tuple) else v for k, v in g.items()} for g in opt["param_groups"]],
                          "state": {str(i): sorted(entry) for i, entry in opt["state"].items()}},
            "rng": {"numpy": {k: v for k, v in rng["numpy"].items() if k != "keys"},
                    "python": {"version": rng["python"]["version"], "gauss_next": rng["python"]["gauss_next"]},
                    "cuda": len(rng.get("cuda", []))}}
    tmp = tensor_path.with_name(tensor_path.name + ".tmp")
    save_file(tensors, str(tmp))
    tmp.replace(tensor_path)
    tmp = meta_path.with_name(meta_path.name + ".tmp")
    tmp.write_text(json.dumps(meta, indent=1))
    tmp.replace(meta_path)


def load_run_state(out_dir: str | Path, rank: int, world: int, cfg: FinetuneConfig, loss: torch.nn.Module,
                   optimizer: torch.optim.Optimizer, pool) -> Progress | None:
    """Put process ``rank``'s saved state into ``loss``, ``optimizer``, ``pool`` and the global RNGs and
    return where the run stood; ``None`` (nothing changed) when ``out_dir`` holds no resume state."""
    meta_path, tensor_path = state_paths(out_dir, rank)
    if not meta_path.exists():
        return None

    def refuse(why: str, path: Path = meta_path) -> FinetuneError:
        return FinetuneError(f"{path}: cannot resume this run from it: {why} (start the run in another out_dir, or delete "
                             f"{path.parent} to start this one afresh)")

    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, ValueError, RecursionError) as exc:
        raise refuse(f"not readable JSON ({exc})") from exc
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise refuse(f"not a {FORMAT} file of version {VERSION}")
    for key in ("rank", "world", "iteration", "frames"):
        if not (is_integer(meta.get(key)) and meta[key] >= 0):
            raise refuse(f"its {key!r} is {meta.get(key)!r}, not a whole number >= 0")
    if (meta["rank"], meta["world"]) != (rank, world):
        raise refuse(f"it is process {meta['rank']} of {meta['world']}'s state, this is process {rank} of {world}")
    if meta["iteration"] > cfg.iterations:
        raise refuse(f"it is at iteration {meta['iteration']}, past this run's iterations={cfg.iterations} "
                     f"(raise iterations to train on)")
    saved, now = meta.get("config"), cfg.to_dict()
    if not isinstance(saved, dict):
        raise refuse("it holds no config")
    differ = [f"{k}={now.get(k)!r} (the saved run's: {saved.get(k)!r})" for k in sorted(set(now) | set(saved))
              if k not in RESUMABLE_CHANGES and _canonical(now.get(k)) != _canonical(saved.get(k))]
    if differ:
        raise refuse(f"this command's config differs from the saved run's: {', '.join(differ)}")
    if not (is_number(meta.get("seconds")) and meta["seconds"] >= 0 and isinstance(meta.get("seen"), list)
            and all(is_integer(i) for i in meta["seen"])):
        raise refuse("its seconds or scenes seen are malformed")
    try:
        tensors = load_file(str(tensor_path))
    except (OSError, SafetensorError) as exc:
        raise refuse(f"its tensors are not readable ({exc})", tensor_path) from exc
    try:
        rng = _rng_of(meta, tensors)
        problem = rng_problem(rng)
        if problem:
            raise ValueError(problem)
        opt = _optimizer_state_of(meta, tensors)
        check_optimizer_state(opt, optimizer, tensor_path)
        loss.load_state_dict({k[len("loss."):]: v for k, v in tensors.items() if k.startswith("loss.")}, strict=True)
        if any(not torch.isfinite(v).all() for v in loss.state_dict().values() if v.is_floating_point()):
            raise ValueError("the loss module's tensors hold NaN or infinite values")
        optimizer.load_state_dict(opt)
        pool.set_order_state(meta["pool"])
    except (KeyError, TypeError, ValueError, RuntimeError, IndexError, CheckpointError) as exc:
        raise refuse(f"it is not this run's state ({type(exc).__name__}: {str(exc).splitlines()[0][:300]})", tensor_path) from exc
    set_rng_state(rng)
    return Progress(int(meta["iteration"]), int(meta["frames"]), float(meta["seconds"]), {int(i) for i in meta["seen"]})


def logged_rows(out_dir: str | Path, upto: int) -> list[dict]:
    """The rows of ``OUT/finetune.csv`` up to iteration ``upto``, numbers as numbers (a resumed run's history)."""
    path = Path(out_dir) / "finetune.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        rows = [r for r in csv.DictReader(f) if r.get("iteration", "").isdigit() and int(r["iteration"]) <= upto]
    return [{k: (int(v) if k in ("iteration", "frames", "scenes_seen") else float(v)) for k, v in r.items() if v not in ("", None)}
            for r in rows]


def _canonical(value: Any) -> Any:
    """A config value as its JSON round trip gives it back (tuples are lists)."""
    return json.loads(json.dumps(value))


def _rng_of(meta: dict, tensors: dict) -> dict:
    numpy_meta, python_meta = meta["rng"]["numpy"], meta["rng"]["python"]
    rng = {"torch": tensors["rng.torch"],
           "numpy": {"keys": tensors["rng.numpy_keys"], **numpy_meta},
           "python": {"internal": tensors["rng.python_internal"], **python_meta}}
    if meta["rng"]["cuda"]:
        rng["cuda"] = [tensors[f"rng.cuda.{i}"] for i in range(int(meta["rng"]["cuda"]))]
    gauss = rng["python"]["gauss_next"]
    if gauss is not None and not (isinstance(gauss, float) and math.isfinite(gauss)):
        raise ValueError(f"Python's RNG state has gauss_next {gauss!r}")
    return rng


def _optimizer_state_of(meta: dict, tensors: dict) -> dict:
    groups = meta["optimizer"]["param_groups"]
    groups = [{k: tuple(v) if k == "betas" else v for k, v in g.items()} for g in groups]
    state = {int(i): {name: tensors[f"optim.{i}.{name}"] for name in names} for i, names in meta["optimizer"]["state"].items()}
    return {"state": state, "param_groups": groups}


__all__ = ["Progress", "RESUMABLE_CHANGES", "episode_seed", "load_run_state", "logged_rows", "save_run_state", "state_paths"]
