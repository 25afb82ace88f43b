"""Training stage, its configuration: :class:`TrainConfig` (every knob of a run), what each field
takes (``_TRAIN_RULES``, checked by :func:`check_train_config`), :func:`load_train_config` (a file,
a model config name or a dict, plus ``key=value`` overrides) and the errors a run that cannot start
raises. Re-exported by :mod:`smart_marl.train`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

from .config_files import (MAX_DISTANCE_M, MAX_GRAD_NORM, MAX_LOSS_WEIGHT, MAX_SCENE_COUNT, MAX_TIME_LIMIT_S, apply_overrides,
                           check_fields, device_problem, flag, integer, number, optional, output_dir_problem, read_config_file,
                           text)
from .config_files import seed as seed_rule
from .errors import SmartMarlError, UsageError
from .model.precision import precision_problem
from .model.smart import MAX_VOCAB_SIZE, NAMED_CONFIGS, ModelConfigError, SmartConfig, get_config


class TrainError(SmartMarlError, ValueError):
    """A training run that cannot start: bad config, no data, mismatched vocabulary."""


class TrainConfigError(TrainError, UsageError):
    """A config key or value that is not a valid TrainConfig (the command line exits with 2)."""


class NonFiniteLossError(TrainError):
    """A training step whose loss or gradient is NaN or infinite: the run stops before the optimizer
    takes the step, so the weights and the last checkpoint on disk stay the last good ones."""


@dataclass
class TrainConfig:
    """Every knob of a training run (CleanRL style: all in one place)."""

    model: str | dict = "smart-1m"  # a named config or a dict of SmartConfig fields (may name a base)
    model_overrides: dict = field(default_factory=dict)  # SmartConfig fields, e.g. {"hidden_dim": 32}
    data: str = ""  # scene cache folder, or files / folder / glob that read_scenarios reads
    val_data: str | None = None  # None: validate on the first training scenes, without noise
    extra_data: str | None = None  # more scenes mixed into `data` (e.g. a few real scenes next to simulated ones)
    extra_data_share: float = 0.1  # about this share of the samples come from extra_data (its scenes repeated)
    out_dir: str = "runs/smart"
    motion_vocab: str | None = None  # vocabulary file (NAME.npz/.json); None: build from the training scenes
    road_vocab: str | None = None
    vocab_scenes: int = 1000  # scenes the vocabularies are built from, when built
    vocab_seed: int = 0
    batch_size: int = 4  # scenes per step per rank
    num_workers: int = 2
    max_steps: int = 1000
    time_limit_s: float | None = None  # end after the step that passes this many seconds (the lr schedule still spans max_steps)
    lr: float = 2e-4
    weight_decay: float = 0.1
    betas: tuple = (0.9, 0.999)
    warmup_steps: int = 0
    grad_clip: float = 1.0
    dropout: float = 0.1
    label_smoothing: float = 0.1
    speed_trend_weights: tuple | None = None  # (speeds up, keeps, slows): loss weights of vehicles by their 8 s speed trend (model.losses.speed_trend_weights); None: off
    token_noise_topk: int = 5  # top-k noisy rolling matching; 0 or 1: off
    train_only: tuple | None = None  # parameter-name prefixes that train, the rest frozen (e.g. ["motion_heads.1"]: the pedestrian head); None: all
    lr_scale: dict | None = None  # parameter-name prefix -> multiplier of lr (e.g. {"motion_net.speed_change": 10}: a new module learns faster); None: one rate
    catk_top_k: int = 0  # > 0: closed-loop targets (CAT-K, smart_marl.catk) from the model's top-K tokens; 0: teacher forcing
    catk_max_drift_m: float | None = None  # CAT-K: tokens starting farther than this from the log are no targets (smart_marl.catk.drifted); None: all are
    catk_avoid: bool = False  # CAT-K keeps gaps: candidates and targets that would run into a neighbour are taken out (needs catk_top_k)
    brake_leaders: float = 0.0  # CAT-K with catk_avoid: share of leaders with a follower that brake hard (smart_marl.braking) in a training scene
    road_mask_prob: float = 0.15  # share of road pieces hidden for the road next-token task
    road_keep_radius_m: float | None = -1.0  # crop roads to this distance from agents; -1: lossless radius from the model config
    cache_scenes: int = 4096  # per data worker: scenes whose road arrays (and noise-free motion tokens) are kept (~0.2 MB each)
    log_every: int = 10
    val_every: int = 500
    val_scenes: int = 16
    ckpt_every: int = 500
    seed: int = 0
    device: str = "auto"  # auto: cuda when available
    amp: bool = True  # bf16 autocast on CUDA (the older switch; precision="bfloat16" autocasts on any device)
    precision: str = "bfloat16"  # mixed precision: a bfloat16 working copy on the CPU, autocast on a GPU; "float32": none
    # (smart_marl.model.precision; bfloat16 the default since 2026-12-06: 1.15-1.31x the tokens/s on the CPU)
    init: str | None = None  # checkpoint whose weights start the run (fine-tuning)
    tensorboard: bool = True
    progress: bool = True

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------- config
def load_train_config(config: str | Mapping[str, Any] | None = None, overrides: Sequence[str] | Mapping[str, Any] = ()) -> TrainConfig:
    """A :class:`TrainConfig` from a JSON/TOML file, a model config name (``smart-7m``) or a dict,
    plus ``key=value`` overrides (values parsed as JSON when they parse; ``model.FIELD=...`` sets a
    model field)."""
    values: dict[str, Any] = {}
    if isinstance(config, Mapping):
        values.update(config)
    elif config:
        p = Path(config)
        if p.is_file():
            values.update(read_config_file(p, "training", TrainError))
        elif config in NAMED_CONFIGS:
            values["model"] = config
        else:
            raise TrainError(f"unknown config {config!r}: neither a file nor a model config name ({', '.join(NAMED_CONFIGS)})")
    values = apply_overrides(values, overrides, TrainConfig, "model_overrides", "model", "training", TrainConfigError)
    cfg = TrainConfig(**values)
    check_train_config(cfg)
    return cfg


def _trend_weights(value) -> str | None:
    if value is None:
        return None
    if not (isinstance(value, (list, tuple)) and len(value) == 3) or any(number(0.0, MAX_LOSS_WEIGHT)(w) for w in value):
        return (f"must be three numbers in [0, {MAX_LOSS_WEIGHT:g}] (speeds up, keeps its speed, slows; loss weights) or null, "
                f"got {value!r}")
    return None


def _prefixes(value) -> str | None:
    if value is None:
        return None
    if not (isinstance(value, (list, tuple)) and value and all(isinstance(v, str) and v for v in value)):
        return f"must be a non-empty list of parameter-name prefixes (e.g. [\"motion_heads.1\"]) or null, got {value!r}"
    return None


def _lr_scale(value) -> str | None:
    if value is None:
        return None
    if not (isinstance(value, dict) and value and all(isinstance(k, str) and k for k in value)) or any(
            number(0.0, 1000.0, low_open=True)(v) for v in value.values()):
        return f"must be a non-empty mapping of parameter-name prefixes to multipliers in (0, 1000] or null, got {value!r}"
    return None


def _betas(value) -> str | None:
    if not (isinstance(value, (list, tuple)) and len(value) == 2) or any(number(0.0, 1.0, high_open=True)(b) for b in value):
        return f"must be two numbers in [0, 1), got {value!r}"
    return None


ROAD_KEEP_RADIUS_RULE = lambda v: (number(-1.0, MAX_DISTANCE_M)(v)  # noqa: E731
                                   or (None if v == -1 or v >= 0 else f"must be -1 (lossless) or >= 0, got {v}"))
"""What ``road_keep_radius_m`` (and ``pretokenize --road-keep-radius``) takes: -1 (the lossless radius of the
model config) or a finite distance >= 0 in metres."""
MAX_BATCH_SIZE = 1024
"""The most scenes one training step takes per rank."""
MAX_STEPS = 10**9
"""The most optimizer steps a run takes."""
MAX_WORKERS = 4 * (os.cpu_count() or 1)
"""The most DataLoader workers: 4 per CPU of this machine (more only wait for a CPU)."""
MAX_CACHE_SCENES = 100_000
"""The most scenes a data worker keeps (``cache_scenes``): ~0.2 MB of road arrays and tokens a scene, ~20 GB in
each worker."""
_TOP_K = integer(0, MAX_VOCAB_SIZE, "the largest vocabulary: a larger k is every token")
_EVERY = integer(0, MAX_STEPS, "the most steps: a longer period never comes")
_TRAIN_RULES = {
    "model_overrides": lambda v: None if isinstance(v, dict) else f"must be a mapping, got {v!r}",
    "data": text, "val_data": optional(text), "extra_data": optional(text),
    "extra_data_share": number(0.0, 1.0, low_open=True, high_open=True), "out_dir": lambda v: text(v) or output_dir_problem(v),
    "motion_vocab": optional(text), "road_vocab": optional(text),
    "vocab_scenes": integer(1, MAX_SCENE_COUNT, "20x WOMD's training split"), "vocab_seed": seed_rule,
    "batch_size": integer(1, MAX_BATCH_SIZE, "scenes per step a machine holds"),
    "num_workers": integer(0, MAX_WORKERS, "4 processes per CPU of this machine"),
    "max_steps": integer(1, MAX_STEPS, "a billion steps"),
    "time_limit_s": optional(number(0.0, MAX_TIME_LIMIT_S, low_open=True, why="30 days; null: no limit")),
    "lr": number(0.0, 1.0, low_open=True, why="larger diverges at once"),
    "weight_decay": number(0.0, 10.0, why="AdamW shrinks every weight by lr x weight_decay a step"), "betas": _betas,
    "warmup_steps": integer(0, MAX_STEPS, "a billion steps"),
    "grad_clip": number(0.0, MAX_GRAD_NORM, why="a larger clip never clips; 0: no clip"),
    "dropout": number(0.0, 1.0, high_open=True), "label_smoothing": number(0.0, 1.0, high_open=True),
    "speed_trend_weights": _trend_weights, "train_only": _prefixes, "lr_scale": _lr_scale,
    "token_noise_topk": _TOP_K, "catk_top_k": _TOP_K, "catk_avoid": flag, "brake_leaders": number(0.0, 1.0),
    "catk_max_drift_m": optional(number(0.0, MAX_DISTANCE_M, low_open=True, why="metres, farther than any scene reaches")),
    "cache_scenes": integer(0, MAX_CACHE_SCENES, "~0.2 MB a scene: ~20 GB a worker"), "road_mask_prob": number(0.0, 1.0),
    "road_keep_radius_m": optional(ROAD_KEEP_RADIUS_RULE),
    "log_every": integer(1, MAX_STEPS, "the most steps: a longer period never comes"), "val_every": _EVERY,
    "val_scenes": integer(0, MAX_SCENE_COUNT, "20x WOMD's training split"), "ckpt_every": _EVERY, "seed": seed_rule,
    "device": lambda v: None if v == "auto" else device_problem(v), "amp": flag, "precision": precision_problem, "init": optional(text),
    "tensorboard": flag, "progress": flag,
}
"""What each TrainConfig field takes (``model`` is checked against the named configs); each number bounded on both
sides (issue 56), its upper bound named with what breaks above it."""


def check_train_config(cfg: TrainConfig) -> None:
    """:class:`TrainConfigError` naming the first field whose value a run cannot use (``lr=abc``,
    ``batch_size=0``, ``max_steps=-1``, a ``device`` this machine has not, an ``out_dir`` that is a file...)."""
    if isinstance(cfg.model, str):
        if cfg.model not in NAMED_CONFIGS:
            raise TrainConfigError(f"unknown model config {cfg.model!r}; known: {', '.join(NAMED_CONFIGS)}")
    elif not isinstance(cfg.model, dict):
        raise TrainConfigError(f"training config: model must be a config name or a mapping of SMART fields, got {cfg.model!r}")
    check_fields(cfg, _TRAIN_RULES, "training", TrainConfigError)
    if cfg.catk_max_drift_m is not None and cfg.catk_top_k <= 0:
        raise TrainConfigError(f"training config: catk_max_drift_m={cfg.catk_max_drift_m} drops CAT-K targets: it needs catk_top_k > 0")
    if cfg.catk_avoid and cfg.catk_top_k <= 0:
        raise TrainConfigError("training config: catk_avoid=true keeps the gaps of CAT-K rollouts: it needs catk_top_k > 0")
    if cfg.brake_leaders > 0 and not cfg.catk_avoid:
        raise TrainConfigError(f"training config: brake_leaders={cfg.brake_leaders} makes leaders brake where their followers' "
                               "logs drive on: it needs catk_avoid=true (targets that keep gaps) and catk_top_k > 0")
    try:  # the model fields (model=, model.FIELD=) make a SMART config of sane size
        get_config(cfg.model, **{"dropout": cfg.dropout, **cfg.model_overrides})
    except ModelConfigError as exc:
        raise TrainConfigError(f"training config: model: {exc}") from exc



def road_keep_radius(value: float | None, model_cfg: SmartConfig) -> float | None:
    """``TrainConfig.road_keep_radius_m`` resolved: a negative value is the lossless radius of the
    model config (map-agent radius + RoadNet layers x road radius); None keeps every piece."""
    if value is not None and value < 0:
        return model_cfg.map_radius_m + model_cfg.num_road_layers * model_cfg.road_radius_m
    return value
