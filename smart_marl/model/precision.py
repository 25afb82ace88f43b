"""Model stage, arithmetic precision: the one place that decides what runs in which floating-point format.

``precision`` is ``"float32"`` (every number in float32) or ``"bfloat16"``. In bfloat16:

* inference (rollouts, the environments, ``eval``, what-if, the fine-tuning prior) runs a copy of the model
  whose weights are bfloat16 (:func:`inference_model`, made once per model and kept), so the activations stay
  bfloat16 from layer to layer and no op casts its weights on every call. Kept in float32: geometry (poses,
  the relative-pose features, the motion vocabulary's contours, neighbour search), the Fourier features'
  frequencies and phases (``FourierEmbedding.freqs``: an angle of tens of radians in bfloat16 is off by a
  tenth of a radian), and everything after the heads: logits are float32 before the softmax, the sampler's
  probabilities, the log-probabilities and the KL;
* training on the CPU runs forward and backward on a bfloat16 working copy of the model (:func:`training_copy`),
  loaded from the float32 weights before each step, whose gradients go back to the float32 weights as float32
  (:func:`return_gradients`): the optimizer, its state and every checkpoint stay float32 (mixed precision with
  master weights); the logits are float32 before the losses. On a GPU, and in a distributed run, training
  autocasts the forward (:func:`autocast`) instead;
* in training on the CPU, every bfloat16 product runs at a padded row count (:func:`bucket_rows`), so that the
  kernels oneDNN builds for each shape are built once and reused.

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


def _bfloat16_copy(model: nn.Module) -> nn.Module:
    """A copy of ``model`` whose parameters are bfloat16 but :data:`FLOAT32_PARAMETERS` (buffers as they are)."""
    out = copy.deepcopy(model)
    for name, p in out.named_parameters():
        if name.rsplit(".", 1)[-1] not in FLOAT32_PARAMETERS:
            p.data = p.data.to(torch.bfloat16)
    return out


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
        out = _bfloat16_copy(model).eval().requires_grad_(False)
        out.precision = precision
        _CONVERTED[model] = out
    return out


def pads_rows(weight: torch.Tensor) -> bool:
    """Whether products with ``weight`` have their rows padded to :func:`bucket_rows`: bfloat16 on the CPU with
    gradients on (training). Inference is left unpadded: a rollout's steps repeat their shapes (after the first
    step, 4-6 new kernels a step on the sample scenes), a run with inference padded was no faster (cached step
    0.91-1.07x float32's against 0.89-1.04x unpadded, 2026-12-06, one run each), and unpadded it gives the rollouts
    measured before (the realism and top-token figures of the model card) bit for bit."""
    return weight.dtype == torch.bfloat16 and weight.device.type == "cpu" and torch.is_grad_enabled()


def bucket_rows(n: int) -> int:
    """The row count that a bfloat16 product of ``n`` rows runs at on the CPU: ``n`` rounded up to one of eight
    sizes per doubling (at most an eighth more rows; at least 16).

    Why: oneDNN, which runs PyTorch's bfloat16 products on the CPU, builds a kernel for every new shape and keeps
    the last 1,024. Building one costs about 0.55 ms on this project's CPU (a [5000, 64] x [64, 64] product: 0.69
    ms with a new shape, 0.14 ms with a known one); float32 products (MKL) build nothing. The row counts of a
    step (agents, road pieces, a Fourier feature's distinct values) change from batch to batch, so unpadded every
    bfloat16 product of a training step built a kernel, and bfloat16 training ran no faster than float32."""
    if n <= 16:
        return 16
    step = 1 << (n.bit_length() - 4)
    return -(-n // step) * step


def pad_rows(t: torch.Tensor, n: int) -> torch.Tensor:
    """``t`` [m, ...] with zero rows appended up to ``n`` rows (``t`` itself when ``m >= n``)."""
    extra = n - t.shape[0]
    return t if extra <= 0 else torch.cat([t, t.new_zeros(extra, *t.shape[1:])])


def uses_training_copy(precision: str, device: torch.device | str, distributed: bool = False) -> bool:
    """Whether a training step at ``precision`` on ``device`` runs on a bfloat16 working copy
    (:func:`training_copy`): bfloat16 on the CPU in one process; elsewhere the forward autocasts."""
    return check_precision(precision) == "bfloat16" and torch.device(device).type == "cpu" and not distributed


_WORKING: "weakref.WeakKeyDictionary[nn.Module, nn.Module]" = weakref.WeakKeyDictionary()


def training_copy(module: nn.Module) -> nn.Module:
    """``module``'s bfloat16 working copy for one training step, its weights set to ``module``'s now (rounded to
    bfloat16; :data:`FLOAT32_PARAMETERS` copied as they are) and its mode ``module``'s. Made on the first call and
    kept as long as ``module`` lives; run forward and backward on it, then :func:`return_gradients`."""
    work = _WORKING.get(module)
    if work is None:
        work = _WORKING[module] = _bfloat16_copy(module)
    work.train(module.training)
    with torch.no_grad():
        for w, m in zip(work.parameters(), module.parameters()):
            w.copy_(m)
            w.grad = None
    return work


def return_gradients(module: nn.Module, work: nn.Module) -> None:
    """The gradients of ``work`` (:func:`training_copy`) set on ``module``'s parameters, as float32."""
    for w, m in zip(work.parameters(), module.parameters()):
        m.grad = None if w.grad is None else w.grad.to(m.dtype)
        w.grad = None


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


__all__ = ["DTYPES", "PRECISIONS", "PrecisionError", "autocast", "bucket_rows", "check_precision", "inference_model",
           "model_dtype", "pad_rows", "pads_rows", "precision_problem", "return_gradients", "training_copy",
           "uses_training_copy"]
