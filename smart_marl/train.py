"""Training stage: SMART next-token training (paper sec. 3.3 and appendix), single process or DDP.

What comes in: scenes (a scene cache, or any path :func:`smart_marl.readers.read_scenarios` reads,
converted on the fly), motion and road vocabularies (files, or built from the training scenes with
the tokenizer's k-disks builders) and a :class:`TrainConfig`. What goes out: a run folder with
checkpoints (:mod:`smart_marl.model.checkpoint`), ``train.csv`` / ``val.csv`` and TensorBoard logs.

The loop: AdamW (weight decay 0.1 on matrices), learning rate 2e-4 with optional linear warm-up and
cosine annealing to 0 at ``max_steps``, gradient clipping, bf16 autocast on CUDA. Tokenization
(rolling matching with top-k token noise, road tokens) runs in DataLoader workers
(:class:`TokenizedScenes`); one training step sees a padded batch of several scenes. With
``catk_top_k = K > 0`` the motion tokens are closed-loop instead (CAT-K, :mod:`smart_marl.catk`):
the current model rolls each batch's scenes out from their current frame, every step taking among
its top-K tokens the one closest to the log, and trains on those sequences with targets that lead
back to the log (usually as fine-tuning of a teacher-forced run, ``init=CHECKPOINT``).

Determinism and resume: the data order is a function of (seed, global sample position) only
(:class:`EpochBatchSampler`), each sample's token noise is seeded by its position, and the
checkpoint holds the model, optimizer, scheduler and RNG states and the step. A run killed at any
moment and started again with the same output folder continues from its last checkpoint, drops
the log rows written after it, and ends where an uninterrupted run ends.

Distributed: under ``torchrun`` (``WORLD_SIZE`` > 1) the model is wrapped in DDP (NCCL on GPU,
gloo on CPU), each rank reads its own slice of every global batch, losses are normalised by the
global token count (so the averaged gradient equals the single-process gradient of the union)
and rank 0 writes checkpoints and logs.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch
import torch.distributed as dist
from tqdm import tqdm

from .cpu_memory import keep_freed_memory
from .model.batch import SmartBatch, collate_scenes
from .model.checkpoint import (CheckpointError, VocabularyMismatchError, checkpoint_paths, load_checkpoint, load_train_state,
                               save_checkpoint)
from .model.losses import NextTokenLoss, summarise
from .model.precision import autocast, return_gradients, training_copy, uses_training_copy
from .model.smart import SMART, SmartConfig, get_config
from .runlog import RunLog
from .scenario import Scenario
from .token_cache import TokenCache, is_token_cache
from .tokens import MotionVocabulary
from .tokens.road import RoadVocabulary
from .tokens.vocab_io import load_motion_vocabulary, load_road_vocabulary, save_motion_vocabulary, save_road_vocabulary
from .train_config import (  # noqa: F401  (re-exported: the config's names are imported from smart_marl.train)
    _TRAIN_RULES, MAX_BATCH_SIZE, MAX_STEPS, MAX_WORKERS, ROAD_KEEP_RADIUS_RULE, NonFiniteLossError, TrainConfig, TrainConfigError,
    TrainError, check_train_config, load_train_config, road_keep_radius,
)
from .train_state import check_train_state, rng_state, set_rng_state
from .train_data import (  # noqa: F401  (re-exported: the data's names are imported from smart_marl.train)
    EpochBatchSampler, MixedScenes, TokenizedScenes, build_vocabularies, closed_loop_batch, make_loader, open_scenes,
    training_scenes, _check_token_cache_config,
)


# ------------------------------------------------------------------------------------ model
def _unmatched(prefixes, names: list[str]) -> list:
    """The prefixes of ``prefixes`` that no name of ``names`` starts with."""
    return [p for p in prefixes if not any(n.startswith(p) for n in names)]


def freeze_except(model: torch.nn.Module, prefixes) -> int:
    """Freeze every parameter of ``model`` whose name starts with none of ``prefixes``; returns how many
    parameters (elements) still train. A prefix that names no parameter is an error."""
    names = [n for n, _ in model.named_parameters()]
    unknown = _unmatched(prefixes, names)
    if unknown:
        raise TrainConfigError(f"train_only: no model parameter starts with {unknown} (e.g. {names[:3]}, ..., {names[-1]})")
    trained = 0
    for name, param in model.named_parameters():
        param.requires_grad_(any(name.startswith(p) for p in prefixes))
        trained += param.numel() if param.requires_grad else 0
    return trained


# ------------------------------------------------------------------------------ distributed
@dataclass
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    started: bool = False  # this run started the process group (and ends it: leave_distributed)

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def init_distributed(device: torch.device) -> DistInfo:
    """Join the process group torchrun describes (WORLD_SIZE, RANK, LOCAL_RANK); single process otherwise."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return DistInfo()
    started = not dist.is_initialized()
    if started:
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return DistInfo(rank=dist.get_rank(), world_size=dist.get_world_size(), local_rank=int(os.environ.get("LOCAL_RANK", "0")),
                    started=started)


def leave_distributed(info: DistInfo) -> None:
    """After a run's last collective: wait for every rank, and end the process group if the run
    started it. A rank that exits with the group alive can abort ("terminate called without an
    active exception", SIGABRT) while process 0 still writes its files."""
    if info.enabled:
        dist.barrier()
        if info.started:
            dist.destroy_process_group()


def resolve_device(name: str, info: DistInfo | None = None) -> torch.device:
    """The run's device: ``auto`` is CUDA when available; a CUDA device without an index is this process's
    (LOCAL_RANK, 0 outside torchrun), as ``torch.cuda.set_device`` needs an index."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda" and device.index is None:
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


# ---------------------------------------------------------------------------------- one step
def make_optimizer(model: torch.nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """AdamW; weight decay on matrices only (not on biases, norms, 1-d embeddings). The fused
    implementation (one kernel over every parameter) on the CPU and CUDA: the same update, at a fifth
    of the per-parameter loop's time on the CPU (smart-7m: 9 vs 27 ms a step). ``lr_scale``: the
    parameters under each prefix learn at that multiple of ``lr`` (the first matching prefix; groups of
    their own, scheduled as the rest)."""
    scales = dict(cfg.lr_scale or {})
    named = [(n, p) for n, p in model.named_parameters() if p.requires_grad]
    unknown = _unmatched(scales, [n for n, _ in named])
    if unknown:
        raise TrainConfigError(f"lr_scale: no trained parameter starts with {unknown}")
    # (scale, decayed) -> parameters; the two groups at the base rate first and always (a resumed run's optimizer has them)
    groups: dict[tuple[float, bool], list] = {(1.0, True): [], (1.0, False): []}
    for name, param in named:
        scale = next((float(v) for k, v in scales.items() if name.startswith(k)), 1.0)
        groups.setdefault((scale, param.dim() >= 2), []).append(param)
    fused = all(p.device.type in ("cpu", "cuda") for _, p in named) or None
    return torch.optim.AdamW([{"params": ps, "weight_decay": cfg.weight_decay if decay else 0.0, "lr": cfg.lr * scale}
                              for (scale, decay), ps in groups.items()], lr=cfg.lr, betas=tuple(cfg.betas), fused=fused)


def make_scheduler(optimizer: torch.optim.Optimizer, cfg: TrainConfig) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up over ``warmup_steps``, then cosine annealing to 0 at ``max_steps``."""
    warm, total = max(int(cfg.warmup_steps), 0), max(int(cfg.max_steps), 1)

    def factor(step: int) -> float:
        if step < warm:
            return (step + 1) / warm
        progress = min((step - warm) / max(total - warm, 1), 1.0)
        return 0.5 * (1.0 + math.cos(math.pi * progress))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def train_step(loss_module: torch.nn.Module, optimizer: torch.optim.Optimizer, scheduler, batch: SmartBatch, grad_clip: float,
               info: DistInfo, device: torch.device, amp: bool, precision: str = "float32") -> dict[str, float]:
    """One optimizer step on one (per-rank) batch; returns summed metric counts and losses of this rank.

    Losses are normalised by the global number of target tokens / world size, so the gradient DDP
    averages is that of the union of the ranks' batches."""
    batch = batch.to(device, non_blocking=True)
    counts = torch.tensor([float(batch.target_valid.sum()), float(_road_targets(batch))], device=device)
    if info.enabled:
        dist.all_reduce(counts)
    norms = (counts / info.world_size).clamp(min=1.0 / info.world_size)
    optimizer.zero_grad(set_to_none=True)
    if uses_training_copy(precision, device, info.enabled):  # smart_marl.model.precision decides
        work = training_copy(loss_module)
        out = work(batch, motion_normaliser=norms[0], road_normaliser=norms[1])
        out["loss"].backward()
        return_gradients(loss_module, work)
    else:
        with autocast(precision, device, amp):
            out = loss_module(batch, motion_normaliser=norms[0], road_normaliser=norms[1])
        out["loss"].backward()
    grad_norm = torch.nn.utils.clip_grad_norm_(loss_module.parameters(), grad_clip) if grad_clip and grad_clip > 0 else torch.zeros(())
    bad = (~torch.isfinite(out["loss"].detach().float()) | ~torch.isfinite(grad_norm.detach().float())).float().reshape(1)
    if info.enabled:  # every rank stops, or none
        dist.all_reduce(bad, op=dist.ReduceOp.MAX)
    if bool(bad.item()):
        raise NonFiniteLossError(f"the loss is {float(out['loss'].detach()):g} and the gradient norm {float(grad_norm):g} "
                                 f"(non-finite: the learning rate or the data is off)")
    optimizer.step()
    scheduler.step()
    res = {k: float(v.detach()) for k, v in out.items()}
    res["grad_norm"] = float(grad_norm)
    return res


def _road_targets(batch: SmartBatch) -> int:
    b, r = batch.road_masked.shape
    flat = batch.road_pairs + (torch.arange(b)[:, None, None] * r).to(batch.road_pairs.device)
    masked = batch.road_masked.reshape(-1)
    return int((batch.road_pair_valid & masked[flat[..., 1]] & ~masked[flat[..., 0]]).sum())


@torch.no_grad()
def evaluate_sums(model: SMART, batches, device: torch.device, label_smoothing: float = 0.0, amp: bool = True,
                  precision: str = "float32") -> dict[str, float]:
    """Summed teacher-forced losses and counts over batches (combine ranks by adding them)."""
    was = model.training
    model.eval()
    module = NextTokenLoss(model, label_smoothing)
    names = ("vehicle", "pedestrian", "cyclist")
    keys = ["loss", "motion_loss", "road_loss", "road_tokens", "road_top1"] + [f"{t}_{k}" for t in names for k in ("tokens", "top1", "top5")]
    sums: dict[str, float] = dict.fromkeys(keys, 0.0)  # the same keys on every rank, even one without a batch
    for batch in batches:
        batch = batch.to(device)
        with autocast(precision, device, amp):
            out = module(batch, motion_normaliser=1.0, road_normaliser=1.0)  # sums, not means
        for k, v in out.items():
            sums[k] = sums.get(k, 0.0) + float(v)
    model.train(was)
    return sums


def finish_metrics(sums: Mapping[str, float]) -> dict[str, float]:
    """Means from :func:`evaluate_sums`: ``motion_loss`` and ``road_loss`` per token, top-1/top-5 accuracies."""
    res = summarise(dict(sums))
    m_tok = sum(sums.get(f"{t}_tokens", 0.0) for t in ("vehicle", "pedestrian", "cyclist"))
    res["motion_loss"] = sums.get("motion_loss", 0.0) / max(m_tok, 1.0)
    res["road_loss"] = sums.get("road_loss", 0.0) / max(sums.get("road_tokens", 0.0), 1.0)
    res["motion_tokens"] = m_tok
    return res


def evaluate(model: SMART, batches, device: torch.device, label_smoothing: float = 0.0, amp: bool = True) -> dict[str, float]:
    """Teacher-forced next-token metrics (see :func:`finish_metrics`) of one process's batches."""
    return finish_metrics(evaluate_sums(model, batches, device, label_smoothing, amp))


# --------------------------------------------------------------------------------------- logs
TRAIN_COLUMNS = ["step", "loss", "motion_loss", "road_loss", "motion_top1_acc", "motion_top5_acc", "vehicle_top1_acc",
                 "vehicle_top5_acc", "pedestrian_top1_acc", "pedestrian_top5_acc", "cyclist_top1_acc", "cyclist_top5_acc",
                 "road_top1_acc", "grad_norm", "tokens_per_s", "scenes_per_s", "lr"]
VAL_COLUMNS = ["step", "motion_loss", "road_loss", "motion_top1_acc", "motion_top5_acc", "vehicle_top1_acc", "vehicle_top5_acc",
               "pedestrian_top1_acc", "pedestrian_top5_acc", "cyclist_top1_acc", "cyclist_top5_acc", "road_top1_acc"]


# ------------------------------------------------------------------------------------ the run
@dataclass
class TrainResult:
    out_dir: Path
    step: int
    last_train: dict[str, float]
    last_val: dict[str, float]
    checkpoint: Path | None
    resumed_from: int = 0


def _saved_step(meta: Path) -> int | str:
    try:
        return int(json.loads(meta.read_text()).get("step", "?"))
    except (OSError, ValueError, TypeError, AttributeError):
        return "?"


def _vocabularies(cfg: TrainConfig, model_cfg: SmartConfig, scenes, out_dir: Path, info: DistInfo, resuming: bool):
    """The run's vocabularies: the given files; else the ``init`` checkpoint's; else the run folder's
    (resuming); else built from the training scenes (rank 0) and saved in the run folder."""
    run_mv, run_rv = out_dir / "motion_vocab", out_dir / "road_vocab"
    if cfg.motion_vocab or cfg.road_vocab:
        if not (cfg.motion_vocab and cfg.road_vocab):
            raise TrainError("give both motion_vocab and road_vocab, or neither (then both are built from the training scenes)")
        return load_motion_vocabulary(cfg.motion_vocab), load_road_vocabulary(cfg.road_vocab)
    if cfg.init and not resuming:  # fine-tuning: the checkpoint's own vocabularies
        ck = load_checkpoint(cfg.init)
        if info.is_main:
            save_motion_vocabulary(ck.motion_vocab, run_mv)
            save_road_vocabulary(ck.road_vocab, run_rv)
        if info.enabled:
            dist.barrier()
        return ck.motion_vocab, ck.road_vocab
    if not (resuming and (out_dir / "motion_vocab.json").is_file()):
        if info.is_main:
            if cfg.progress:
                print(f"building vocabularies (k-disks, motion {model_cfg.motion_vocab_sizes}, road {model_cfg.road_vocab_size}) "
                      f"from {min(cfg.vocab_scenes, len(scenes))} scenes -> {out_dir}", file=sys.stderr)
            mv, rv = build_vocabularies(scenes, model_cfg, cfg.vocab_scenes, cfg.vocab_seed)
            save_motion_vocabulary(mv, run_mv)
            save_road_vocabulary(rv, run_rv)
        if info.enabled:
            dist.barrier()
    return load_motion_vocabulary(run_mv), load_road_vocabulary(run_rv)


def _start(cfg: TrainConfig) -> tuple[torch.device, DistInfo]:
    """The run's device and process group (the CUDA device selected, or the CPU allocator tuned)."""
    device = resolve_device(cfg.device)
    info = init_distributed(device)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    else:
        keep_freed_memory()  # a CPU step reuses its freed gigabytes instead of faulting them in again
    return device, info


def _run_data(cfg: TrainConfig, scenes: Sequence[Scenario] | None) -> tuple[TokenCache | None, Sequence[Scenario] | TokenCache]:
    """The token cache ``data`` names (None when it is scenes) and what the run trains on: the scenes
    given, else the token cache, else the training scenes; an empty dataset is an error."""
    tokens = TokenCache(cfg.data, cfg.seed, cfg.road_mask_prob) if scenes is None and is_token_cache(cfg.data) else None
    if tokens is not None:
        _check_token_cache_config(cfg)
    scenes = scenes if scenes is not None else tokens if tokens is not None else training_scenes(cfg)
    if len(scenes) == 0:
        raise TrainError(f"{cfg.data or 'the scenes given'}: the dataset is empty (no scene to train on)")
    return tokens, scenes


def _model_config(cfg: TrainConfig) -> SmartConfig:
    """The SMART config the run's ``model`` and ``model_overrides`` name (with the run's dropout)."""
    base = cfg.model if isinstance(cfg.model, (str, dict)) else str(cfg.model)
    try:
        return get_config(base, **{"dropout": cfg.dropout, **cfg.model_overrides})
    except ValueError as exc:
        raise TrainError(str(exc)) from exc


def _fit_vocabularies(model_cfg: SmartConfig, mv: MotionVocabulary, rv: RoadVocabulary, cfg: TrainConfig, info: DistInfo) -> SmartConfig:
    """``model_cfg`` with the vocabularies' sizes (a note when they differ from the config's)."""
    sizes = tuple(mv[t].size for t in range(3))
    if sizes != model_cfg.motion_vocab_sizes or rv.size != model_cfg.road_vocab_size:
        if cfg.progress and info.is_main:
            print(f"note: vocabulary sizes {sizes} / road {rv.size} differ from the config's {model_cfg.motion_vocab_sizes} / "
                  f"{model_cfg.road_vocab_size}; the model takes the vocabulary's sizes", file=sys.stderr)
        model_cfg = dataclasses.replace(model_cfg, motion_vocab_sizes=sizes, road_vocab_size=rv.size)
    return model_cfg


def _build_model(cfg: TrainConfig, model_cfg: SmartConfig, mv: MotionVocabulary, rv: RoadVocabulary, resuming: bool,
                 device: torch.device) -> SMART:
    """The run's model on ``device``: seeded fresh weights, or the ``init`` checkpoint's when fine-tuning
    (its vocabularies must be the run's), frozen but for ``train_only``."""
    torch.manual_seed(cfg.seed)
    model = SMART(model_cfg, [torch.from_numpy(mv[t].contour) for t in range(3)])
    if cfg.init and not resuming:
        ck = load_checkpoint(cfg.init)
        if ck.meta["vocabularies"]["motion"]["content_hash"] != mv.content_hash() or \
                ck.meta["vocabularies"]["road"]["content_hash"] != rv.content_hash():
            raise VocabularyMismatchError(cfg.init, "its vocabularies are not this run's (pass the checkpoint's vocabulary files "
                                                    "as motion_vocab=/road_vocab=, or train from scratch)")
        differ = {k: (v, model_cfg.to_dict().get(k)) for k, v in ck.model.config.to_dict().items()
                  if k != "dropout" and model_cfg.to_dict().get(k) != v}
        fresh = _load_init_weights(model, ck.model.state_dict(), cfg.init, bool(differ))
        if differ:  # other behaviour (e.g. road_types), or an input the checkpoint lacks: say so, the run's config wins
            added = f"; parameters it lacks start as a fresh model's: {fresh}" if fresh else ""
            warnings.warn(f"{cfg.init}: the run's model config differs from the checkpoint's in {sorted(differ)} "
                          f"(checkpoint, run: {differ}){added}; pass model.KEY=VALUE to keep the checkpoint's", stacklevel=3)
    model.to(device)
    if cfg.train_only:
        freeze_except(model, cfg.train_only)
    return model


def _load_init_weights(model: SMART, weights: dict[str, torch.Tensor], path: str, configs_differ: bool) -> list[str]:
    """Load an ``init`` checkpoint's ``weights`` into the run's ``model``; the modules of the model the
    checkpoint has no weights for (an input the run's config switches on, e.g. ``speed_change_input``) keep
    their fresh initialisation, which is allowed only where the configs differ. Weights the model has no
    place for, or of another shape, are an error naming the checkpoint. Returns the fresh modules' names."""
    try:
        missing, unexpected = model.load_state_dict(weights, strict=False)
    except RuntimeError as exc:  # weights of another shape
        raise CheckpointError(path, f"its weights do not fit the run's model: {exc}") from exc
    if unexpected or (missing and not configs_differ):
        raise CheckpointError(path, f"its weights do not fit the run's model (the model's modules it has no weights for: "
                                    f"{_modules(missing)}; its modules the model lacks: {_modules(unexpected)}): pass the "
                                    f"checkpoint's model.KEY=VALUE settings")
    return _modules(missing)


def _modules(parameters: Sequence[str]) -> list[str]:
    return sorted({_module_of(k) for k in parameters})


def _module_of(parameter: str) -> str:
    """The module a parameter name belongs to, without the index of a layer in a sequence:
    ``motion_net.speed_change.0.weight`` -> ``motion_net.speed_change``."""
    parts = parameter.split(".")[:-1]
    while parts and parts[-1].isdigit():
        parts.pop()
    return ".".join(parts) or parameter


def _resume(cfg: TrainConfig, last: Path, model: SMART, optimizer: torch.optim.Optimizer, scheduler, mv: MotionVocabulary,
            rv: RoadVocabulary, device: torch.device) -> int:
    """Load the last checkpoint's weights and training state (optimizer, scheduler, RNGs) into the run; its step."""
    ck = load_checkpoint(last, motion_vocab=mv, road_vocab=rv, map_location=device, dropout=cfg.dropout,
                         **{k: v for k, v in cfg.model_overrides.items() if k not in ("motion_vocab_sizes", "road_vocab_size")})
    model.load_state_dict(ck.model.state_dict())
    st = load_train_state(last)
    check_train_state(st, optimizer, cfg.max_steps, checkpoint_paths(last)["train_state"])
    optimizer.load_state_dict(st["optimizer"])
    scheduler.load_state_dict(st["scheduler"])
    set_rng_state(st["rng"])
    return int(st["step"])


def _out_of_time(started: float, limit_s: float | None, info, device: torch.device) -> bool:
    """Whether the run has passed ``limit_s`` seconds (``TrainConfig.time_limit_s``); every rank stops at
    the same step (the first rank's clock decides)."""
    if limit_s is None:
        return False
    over = time.perf_counter() - started > limit_s
    if not info.enabled:
        return over
    flag = torch.tensor([over], dtype=torch.int32, device=device)
    dist.broadcast(flag, 0)
    return bool(flag.item())


def _datasets(cfg: TrainConfig, tokens: TokenCache | None, scenes, mv: MotionVocabulary, rv: RoadVocabulary,
              model_cfg: SmartConfig, keep: float | None):
    """(training set, validation scenes, validation set): token caches checked against the run's
    vocabularies, or :class:`TokenizedScenes` (noisy and maybe closed-loop for training, clean for validation)."""
    noise = cfg.token_noise_topk if cfg.token_noise_topk and cfg.token_noise_topk > 1 else 0
    if cfg.catk_top_k < 0:
        raise TrainError(f"catk_top_k must be >= 0 (0: teacher forcing), got {cfg.catk_top_k}")
    if tokens is not None:  # pre-tokenized: the same items, without the rolling matching
        tokens.check(mv, rv, model_cfg.road_settings, keep)
        val_scenes = val_set = TokenCache(cfg.val_data, cfg.seed + 1, cfg.road_mask_prob) if cfg.val_data else tokens.with_seed(cfg.seed + 1)
        val_set.check(mv, rv, model_cfg.road_settings, keep)
        return tokens, val_scenes, val_set
    train_set = TokenizedScenes(scenes, mv, rv, cfg.seed, noise, cfg.road_mask_prob, keep, cache_size=cfg.cache_scenes,
                                closed_loop=cfg.catk_top_k > 0, road=model_cfg.road_settings)
    val_scenes = open_scenes(cfg.val_data) if cfg.val_data else scenes
    val_set = TokenizedScenes(val_scenes, mv, rv, cfg.seed + 1, 0, cfg.road_mask_prob, keep, road=model_cfg.road_settings)
    return train_set, val_scenes, val_set


def _data_info(cfg: TrainConfig, scenes, mv: MotionVocabulary, rv: RoadVocabulary) -> dict[str, Any]:
    """What the checkpoints record of the run's data: paths, scene counts, the extra scenes' share, vocabulary hashes."""
    return {"data": cfg.data, "val_data": cfg.val_data, "num_scenes": len(scenes),
            **({"extra_data": cfg.extra_data, "extra_scenes": len(scenes.extra), "extra_share": round(scenes.share, 4)}
               if isinstance(scenes, MixedScenes) else {}),
            "motion_vocab": mv.content_hash(), "road_vocab": rv.content_hash()}


def _checked_step(wrapped, optimizer, scheduler, batch: SmartBatch, cfg: TrainConfig, info: DistInfo, device: torch.device,
                  out_dir: Path, last: Path, step: int) -> dict[str, float]:
    """:func:`train_step`; a non-finite loss names the run, the step and the last good checkpoint."""
    try:
        return train_step(wrapped, optimizer, scheduler, batch, cfg.grad_clip, info, device, cfg.amp, cfg.precision)
    except NonFiniteLossError as exc:
        kept = checkpoint_paths(last)["meta"]
        raise NonFiniteLossError(f"{out_dir}: step {step + 1}: {exc}; the run stopped before the optimizer took that "
                                 f"step: " + (f"the last good checkpoint is {kept} (step {_saved_step(kept)})"
                                              if kept.is_file() else "no checkpoint was written before it")) from None


def _train_row(acc: Mapping[str, float], n_acc: int, scenes_acc: int, t0: float, step: int, lr: float, info: DistInfo,
               device: torch.device) -> dict[str, float]:
    """One ``train.csv`` row: the steps since the last row (begun at ``t0``), summed over the ranks, as per-step
    means and rates."""
    keys = sorted(acc)
    t = torch.tensor([acc[k] for k in keys] + [scenes_acc], dtype=torch.float64, device=device)
    if info.enabled:
        dist.all_reduce(t)
    tot = dict(zip(keys + ["scenes"], t.tolist()))
    seconds = time.perf_counter() - t0
    motion_tokens = tot["vehicle_tokens"] + tot["pedestrian_tokens"] + tot["cyclist_tokens"]
    row = {"step": step, "lr": lr, "tokens_per_s": motion_tokens / seconds, "scenes_per_s": tot["scenes"] / seconds, **summarise(tot)}
    for k in ("loss", "motion_loss", "road_loss", "grad_norm"):
        # per-step means: rank r's loss is (its sum) * world / (global count), so the ranks add up to world * mean
        row[k] = tot[k] / (n_acc * info.world_size)
    return row


def _validate(model: SMART, val_set, val_keys: list, cfg: TrainConfig, info: DistInfo, device: torch.device, step: int) -> dict[str, float]:
    """The validation row at ``step``: teacher-forced metrics of the validation items, summed over the ranks."""
    batches = (collate_scenes([val_set[k] for k in val_keys[i : i + cfg.batch_size]]) for i in range(0, len(val_keys), cfg.batch_size))
    sums = evaluate_sums(model, batches, device, label_smoothing=cfg.label_smoothing, amp=cfg.amp, precision=cfg.precision)
    if info.enabled:
        keys = sorted(sums)
        t = torch.tensor([sums[k] for k in keys], dtype=torch.float64, device=device)
        dist.all_reduce(t)
        sums = dict(zip(keys, t.tolist()))
    return {"step": step, **finish_metrics(sums)}


def train(cfg: TrainConfig, scenes: Sequence[Scenario] | None = None,
          on_step: Callable[[int], None] | None = None) -> TrainResult:
    """Run (or resume) a training run in ``cfg.out_dir``; see the module docstring. ``on_step(step)``
    is called at the end of every step (after its log rows and checkpoint)."""
    check_train_config(cfg)
    device, info = _start(cfg)
    out_dir = Path(cfg.out_dir)
    last = out_dir / "checkpoints" / "last"
    resuming = checkpoint_paths(last)["meta"].is_file()
    if info.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
    tokens, scenes = _run_data(cfg, scenes)
    model_cfg = _model_config(cfg)
    mv, rv = _vocabularies(cfg, model_cfg, scenes, out_dir, info, resuming)
    model_cfg = _fit_vocabularies(model_cfg, mv, rv, cfg, info)
    model = _build_model(cfg, model_cfg, mv, rv, resuming, device)
    loss_module = NextTokenLoss(model, cfg.label_smoothing, cfg.speed_trend_weights)
    optimizer = make_optimizer(model, cfg)
    scheduler = make_scheduler(optimizer, cfg)
    step = _resume(cfg, last, model, optimizer, scheduler, mv, rv, device) if resuming else 0
    resumed_from = step
    wrapped = loss_module
    if info.enabled:
        wrapped = torch.nn.parallel.DistributedDataParallel(loss_module, device_ids=[device.index] if device.type == "cuda" else None)

    keep = road_keep_radius(cfg.road_keep_radius_m, model_cfg)
    train_set, val_scenes, val_set = _datasets(cfg, tokens, scenes, mv, rv, model_cfg, keep)
    n_val = min(cfg.val_scenes, len(val_scenes))
    val_keys = [(i, i) for i in range(info.rank, n_val, info.world_size)]
    pin = device.type == "cuda"

    log = RunLog(out_dir, {"train": TRAIN_COLUMNS, "val": VAL_COLUMNS}, "step", step, cfg.tensorboard) if info.is_main else None
    if log is not None and log.note and cfg.progress:
        print(f"note: {log.note}", file=sys.stderr)
    data_info = _data_info(cfg, scenes, mv, rv)

    def save(tag: str, metrics: dict) -> Path | None:
        if not info.is_main:
            return None
        state = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "rng": rng_state(), "step": step}
        return save_checkpoint(out_dir / "checkpoints" / tag, model, mv, rv, step=step, metrics=metrics, data=data_info,
                               train_config=cfg.to_dict(), train_state=state)

    sampler = EpochBatchSampler(len(scenes), cfg.batch_size, cfg.seed, step, max(cfg.max_steps - step, 0), info.rank, info.world_size)
    loader = make_loader(train_set, sampler, cfg.num_workers, pin, cfg.seed + step)
    bar = tqdm(total=cfg.max_steps, initial=step, desc="train", dynamic_ncols=True) if cfg.progress and info.is_main else None
    last_train: dict[str, float] = {}
    last_val: dict[str, float] = {}
    acc: dict[str, float] = {}
    t0, n_acc, scenes_acc = time.perf_counter(), 0, 0
    started = t0
    model.train()
    ckpt_path = None
    for batch in loader:
        if getattr(train_set, "closed_loop", False):
            batch = closed_loop_batch(model, batch, mv, cfg.catk_top_k, cfg.road_mask_prob, keep, cfg.seed, device,
                                      avoid=cfg.catk_avoid, brake_leaders=cfg.brake_leaders, max_drift_m=cfg.catk_max_drift_m)
        lr = scheduler.get_last_lr()[0]
        res = _checked_step(wrapped, optimizer, scheduler, batch, cfg, info, device, out_dir, last, step)
        step += 1
        for k, v in res.items():
            acc[k] = acc.get(k, 0.0) + v
        n_acc += 1
        scenes_acc += batch.num_scenes
        if step % cfg.log_every == 0 or step == cfg.max_steps:
            row = last_train = _train_row(acc, n_acc, scenes_acc, t0, step, lr, info, device)
            if log is not None:
                log.write("train", row)
            if bar is not None:
                bar.set_postfix(loss=f"{row['loss']:.3f}", top1=f"{row['motion_top1_acc']:.3f}", tok_s=f"{row['tokens_per_s']:.0f}")
            acc, n_acc, scenes_acc, t0 = {}, 0, 0, time.perf_counter()
        if cfg.val_every and step % cfg.val_every == 0:
            last_val = _validate(model, val_set, val_keys, cfg, info, device, step)
            if log is not None:
                log.write("val", last_val)
        if cfg.ckpt_every and step % cfg.ckpt_every == 0 and step != cfg.max_steps:
            ckpt_path = save("last", {"train": last_train, "val": last_val})
        if bar is not None:
            bar.update(1)
        if on_step is not None:
            on_step(step)
        if _out_of_time(started, cfg.time_limit_s, info, device):
            break
    if bar is not None:
        bar.close()
    if step > resumed_from or not resuming:
        if cfg.val_every and step % cfg.val_every != 0:
            last_val = _validate(model, val_set, val_keys, cfg, info, device, step)
            if log is not None:
                log.write("val", {"step": step, **last_val})
        ckpt_path = save("last", {"train": last_train, "val": last_val})
        if info.is_main:
            save("final", {"train": last_train, "val": last_val})
    if log is not None:
        log.close()
    leave_distributed(info)
    return TrainResult(out_dir=out_dir, step=step, last_train=last_train, last_val=last_val, checkpoint=ckpt_path, resumed_from=resumed_from)
