"""Model stage, arithmetic precision: the one place that decides what runs in which floating-point format.

``precision`` is ``"float32"`` (every number in float32) or ``"bfloat16"``. In bfloat16:

* inference (rollouts, the environments, ``eval``, what-if, the fine-tuning prior) runs a copy of the model
  whose weights are bfloat16 (:func:`inference_model`, made once per model and kept), so the activations stay
  bfloat16 from layer to layer and no op casts its weights on every call. Kept in float32: geometry (poses,
  the relative-pose features, the motion vocabulary's contours, neighbour search), the Fourier features'
  frequencies and phases (``FourierEmbedding.freqs``: an angle of tens of radians in bfloat16 is off by a
  tenth of a radian), and everything after the heads: logits are float32 before the softmax, the sampler's
  probabilities, the log-probabilities and the KL;
* training autocasts the forward (:func:`autocast`): weights and their gradients stay float32, the matrix
  products run in bfloat16, losses are float32.

What comes in: a name (checked by :func:`check_precision`, which refuses anything else by name), a model.
What goes out: the model to run, a context manager.
"""

from __future__ import annotations

import contextlib
import copy
import weakref

import torch
from torch import nn

PRECISIONS = ("float32", "bfloat16")
DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
FLOAT32_PARAMETERS = ("freqs",)
"""Parameters kept in float32 in a bfloat16 model (by their last name): the Fourier features' frequencies."""

_CONVERTED: "weakref.WeakKeyDictionary[nn.Module, nn.Module]" = weakref.WeakKeyDictionary()


class PrecisionError(ValueError):
    """An unknown precision."""


def check_precision(value, name: str = "precision") -> str:
    """``value`` when it is one of :data:`PRECISIONS`; else :class:`PrecisionError` naming ``name``."""
    if not isinstance(value, str) or value not in PRECISIONS:
        raise PrecisionError(f"{name} must be one of {list(PRECISIONS)}, got {value!r}")
    return value


def precision_problem(value) -> str | None:
    """The config-file rule form of :func:`check_precision`."""
    return None if isinstance(value, str) and value in PRECISIONS else f"must be one of {list(PRECISIONS)}, got {value!r}"


def inference_model(model: nn.Module, precision: str = "float32") -> nn.Module:
    """The model to run inference with at ``precision``: ``model`` itself in float32; in bfloat16 a copy whose
    parameters are bfloat16 (but :data:`FLOAT32_PARAMETERS`; buffers, the vocabulary's geometry, stay float32),
    in eval mode, made on the first call and kept as long as ``model`` lives. The copy is taken of the weights as
    they are then: a model trained further afterwards needs a new call on a new object (or ``model`` itself)."""
    check_precision(precision)
    if precision == "float32":
        return model
    if getattr(model, "precision", "float32") == precision:
        return model
    out = _CONVERTED.get(model)
    if out is None:
        out = copy.deepcopy(model).eval()
        for name, p in out.named_parameters():
            if name.rsplit(".", 1)[-1] not in FLOAT32_PARAMETERS:
                p.data = p.data.to(DTYPES[precision])
            p.requires_grad_(False)
        out.precision = precision
        _CONVERTED[model] = out
    return out


def model_dtype(module: nn.Module) -> torch.dtype:
    """The dtype of ``module``'s activations: that of its (first) linear weights."""
    for m in module.modules():
        if isinstance(m, nn.Linear):
            return m.weight.dtype
    return torch.float32


def autocast(precision: str, device: torch.device | str, amp: bool = False):
    """The context a training forward runs in: bfloat16 autocast on ``device`` for ``"bfloat16"``, and on CUDA
    also with ``amp`` (the trainer's older switch, :class:`~smart_marl.train_config.TrainConfig`); nothing else."""
    check_precision(precision)
    dev = torch.device(device).type
    if precision == "bfloat16" or (amp and dev == "cuda"):
        return torch.autocast(dev, dtype=torch.bfloat16)
    return contextlib.nullcontext()


__all__ = ["DTYPES", "PRECISIONS", "PrecisionError", "autocast", "check_precision", "inference_model", "model_dtype",
           "precision_problem"]
