"""``smart-marl pretokenize SRC... --out DIR``: a token cache for training (see smart_marl.token_cache)."""

from __future__ import annotations

import argparse
import dataclasses
import os

from ..model.checkpoint import EMBEDDED, load_checkpoint
from ..token_cache import pretokenize
from ..train import ROAD_KEEP_RADIUS_RULE, road_keep_radius
from .arguments import checked, output_dir, workers


road_keep_radius_m = checked(ROAD_KEEP_RADIUS_RULE, float, "a number", "road_keep_radius_m")
"""``--road-keep-radius``: what the training config's ``road_keep_radius_m`` takes (-1 or a finite number >= 0)."""


def register(subparsers) -> None:
    p = subparsers.add_parser("pretokenize", help="tokenize scenes once into a token cache for training",
                              description="Rolling matching and road-piece matching of every scene, done once: "
                                          "`smart-marl train data=DIR` then reads the tokens instead of the scenes "
                                          "(noise-free teacher forcing; about 10x smaller than the scenes). "
                                          "Resumable: a rerun skips inputs already done.")
    p.add_argument("sources", nargs="+", metavar="SRC", help="scene files, folders, globs or scene caches")
    p.add_argument("--out", required=True, type=output_dir, help="the token cache folder (created if missing)")
    p.add_argument("--vocab-from", default=EMBEDDED, metavar="CKPT",
                   help="the checkpoint whose vocabularies and road types the training run uses; only these are read, "
                        "the model is not run (default: the embedded prior)")
    p.add_argument("--road-keep-radius", type=road_keep_radius_m, default=-1.0, metavar="M",
                   help="the run's road_keep_radius_m: road pieces farther than M metres from every agent are dropped "
                        "(default -1: the lossless radius of the checkpoint's model config)")
    p.add_argument("--workers", type=workers, default=max(1, min(4, os.cpu_count() or 1)), help="parallel processes")
    p.add_argument("--stop-signs", action=argparse.BooleanOptionalAction, default=None,
                   help="the lanes a stop sign controls carry the light code FLASHING_STOP (or not: --no-stop-signs), "
                        "for a run whose model.stop_signs says so (default: as the checkpoint's model config says)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    ck = load_checkpoint(args.vocab_from)
    keep = road_keep_radius(args.road_keep_radius, ck.model.config)
    road = ck.model.config.road_settings
    if args.stop_signs is not None:
        road = dataclasses.replace(road, stop_signs=args.stop_signs)
    manifest = pretokenize(args.sources, args.out, ck.motion_vocab, ck.road_vocab, road, keep, workers=args.workers,
                           progress=not args.quiet)
    print(f"{manifest['num_scenes']} scenes in {len(manifest['shards'])} shards, road pieces within {keep} m, "
          f"{manifest['seconds']:.1f} s -> {args.out}")
    return 0
