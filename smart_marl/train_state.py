"""Training stage, resuming a run: what a saved training state must hold before a run resumes from it
(:func:`check_train_state`), and every RNG's state as plain tensors and numbers (:func:`rng_state`,
:func:`set_rng_state`), so that a state loads with ``torch.load(weights_only=True)``.

What comes in: a training state read by :func:`~smart_marl.model.checkpoint.load_train_state`, the
optimizer it goes into. What goes out: nothing, or :class:`~smart_marl.model.checkpoint.CheckpointError`
naming the file and what is off.
"""

from __future__ import annotations

import random
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from .config_files import is_number
from .model.checkpoint import CheckpointError


def _finite_numbers(values) -> bool:
    return isinstance(values, (list, tuple)) and all(is_number(v) for v in values)


def check_train_state(state: Mapping[str, Any], optimizer: torch.optim.Optimizer, max_steps: int, path: Path) -> None:
    """Before a resumed run trains: the training state (:func:`load_train_state`) fits the optimizer it is
    loaded into (as many parameter groups and parameters, moment tensors of the parameters' shapes,
    finite learning rates and moments), its scheduler is a LambdaLR's, and its step lies within the run
    (0..max_steps); else :class:`CheckpointError` naming the file and what is off."""
    step = state["step"]
    if not 0 <= step <= max_steps:
        raise CheckpointError(path, f"the training state is at step {step}, outside this run's 0..max_steps={max_steps} "
                                    f"(raise max_steps to train on, or start a new out_dir)")
    check_optimizer_state(state["optimizer"], optimizer, path)
    groups = optimizer.param_groups
    sched = state["scheduler"]
    last = sched.get("last_epoch")
    if not (isinstance(last, int) and not isinstance(last, bool) and 0 <= last <= max(step, 0) + 1):
        raise CheckpointError(path, f"the scheduler state's last_epoch {last!r} does not match the state's step {step}")
    for key in ("base_lrs", "_last_lr"):
        if key in sched and not (_finite_numbers(sched[key]) and len(sched[key]) == len(groups)):
            raise CheckpointError(path, f"the scheduler state's {key} {sched.get(key)!r} is not one finite learning rate "
                                        f"per parameter group")
    if "base_lrs" not in sched:
        raise CheckpointError(path, "the scheduler state has no base_lrs (not a LambdaLR state)")


def check_optimizer_state(saved: Mapping[str, Any], optimizer: torch.optim.Optimizer, path: Path) -> None:
    """A saved optimizer ``state_dict`` fits ``optimizer`` (as many parameter groups and parameters, moment
    tensors of the parameters' shapes, finite learning rates and moments); else :class:`CheckpointError`
    naming the file ``path`` and what is off."""
    groups = optimizer.param_groups
    saved_groups = saved["param_groups"]
    if len(saved_groups) != len(groups) or not all(isinstance(g, dict) for g in saved_groups):
        raise CheckpointError(path, f"the optimizer state has {len(saved_groups)} parameter group(s), this run's optimizer "
                                    f"{len(groups)} (another model, or train_only differs)")
    params = [p for g in groups for p in g["params"]]
    for k, (g, sg) in enumerate(zip(groups, saved_groups)):
        ids = sg.get("params")
        if not isinstance(ids, list) or len(ids) != len(g["params"]):
            raise CheckpointError(path, f"the optimizer state's parameter group {k} does not hold this model's "
                                        f"{len(g['params'])} parameters")
        for key in ("lr", "weight_decay", "eps"):
            if key in sg and not (is_number(sg[key]) and sg[key] >= 0):
                raise CheckpointError(path, f"the optimizer state's parameter group {k} has {key} {sg[key]!r}, "
                                            f"not a finite number >= 0")
        if "betas" in sg and not (_finite_numbers(sg["betas"]) and len(sg["betas"]) == 2):
            raise CheckpointError(path, f"the optimizer state's parameter group {k} has betas {sg['betas']!r}")
    order = [i for sg in saved_groups for i in sg["params"]]
    shapes = {i: p.shape for i, p in zip(order, params)}
    for i, entry in saved["state"].items():
        if i not in shapes or not isinstance(entry, dict):
            raise CheckpointError(path, f"the optimizer state holds moments of parameter {i!r}, which no group lists")
        for name, value in entry.items():
            if not isinstance(value, torch.Tensor):
                raise CheckpointError(path, f"the optimizer state's {name} of parameter {i} is a {type(value).__name__}, "
                                            f"not a tensor")
            if name != "step" and tuple(value.shape) != tuple(shapes[i]):
                raise CheckpointError(path, f"the optimizer state's {name} of parameter {i} has shape {list(value.shape)}, "
                                            f"the parameter {list(shapes[i])}")
            if value.is_floating_point() and not bool(torch.isfinite(value).all()):
                raise CheckpointError(path, f"the optimizer state's {name} of parameter {i} holds NaN or infinite values")


def rng_state() -> dict[str, Any]:
    """Every RNG's state as tensors and numbers only, so that the training state loads with
    ``torch.load(weights_only=True)`` (:func:`~smart_marl.model.checkpoint.load_train_state`)."""
    _, keys, pos, has_gauss, cached_gaussian = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    state = {"torch": torch.get_rng_state(),
             "numpy": {"keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos), "has_gauss": int(has_gauss),
                       "cached_gaussian": float(cached_gaussian)},
             "python": {"version": int(version), "internal": torch.tensor(internal, dtype=torch.int64), "gauss_next": gauss_next}}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    numpy_state = state["numpy"]
    np.random.set_state(("MT19937", numpy_state["keys"].numpy().astype(np.uint32), numpy_state["pos"],
                         numpy_state["has_gauss"], numpy_state["cached_gaussian"]))
    python_state = state["python"]
    random.setstate((python_state["version"], tuple(int(v) for v in python_state["internal"].tolist()),
                     python_state["gauss_next"]))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
