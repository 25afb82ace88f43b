"""``smart-marl train --config FILE|NAME [key=value ...] [--init CHECKPOINT]``: train SMART.

Runs :func:`smart_marl.train.train`; the same command works under ``torchrun --nproc_per_node=N``.
Running it again with the same ``out_dir`` resumes from the run's last checkpoint.
"""

from __future__ import annotations

import json

from ..config_files import apply_command_flags, strict_json
from ..train import load_train_config, train
from .arguments import device_or_auto, output_dir, seed


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a SMART model by next-token prediction (resumes when out_dir holds a run)",
        description="Train SMART on scenes (a scene cache, or files/folders/globs any reader reads). The config is a JSON/TOML "
                    "file of TrainConfig fields or a model name (smart-1m, smart-7m, smart-26m, smart-101m); key=value "
                    "overrides follow (model.FIELD=... sets a model field), e.g. data=cache/ out_dir=runs/a max_steps=1000. "
                    "Under torchrun it trains with DDP.")
    p.add_argument("--config", required=True, help="training config file (.json/.toml) or a model config name")
    p.add_argument("overrides", nargs="*", metavar="KEY=VALUE", help="config overrides, values parsed as JSON when they parse")
    p.add_argument("--init", default=None, metavar="CHECKPOINT", help="start from these weights (fine-tuning)")
    p.add_argument("--out", default=None, type=output_dir, metavar="DIR", help="run folder (the config's out_dir; default runs/smart)")
    p.add_argument("--seed", type=seed, default=None, help="random seed (the config's seed; default 0)")
    p.add_argument("--device", default=None, type=device_or_auto,
                   help="torch device (the config's device; default auto: cuda when available)")
    p.add_argument("--print-config", action="store_true", help="print the resolved config and exit")
    p.set_defaults(func=run)


def run(args) -> int:
    cfg = load_train_config(args.config, args.overrides)
    if args.init:
        cfg.init = args.init
    apply_command_flags(cfg, args)
    if args.print_config:
        print(json.dumps(cfg.to_dict(), indent=1))
        return 0
    result = train(cfg)
    if result.checkpoint is not None:
        summary = {"step": result.step, "resumed_from": result.resumed_from, "checkpoint": str(result.checkpoint),
                   "train": result.last_train, "val": result.last_val}
        print(strict_json(summary))
    return 0
