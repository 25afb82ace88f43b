"""``smart-marl vocab build SRC... --sizes 512,1024,2048 --out DIR [--seed S] [--tolerance T]``: build
motion-token vocabularies (k-disks per agent type, one file pair per size; a size ``V/P/C`` gives
vehicles, pedestrians and cyclists their own sizes) and a road-token vocabulary from scene files,
folders or globs (tokens stage; the files are what checkpoints refer to)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from ..model.checkpoint import load_checkpoint, save_checkpoint
from ..model.transfer import transfer_motion_vocabulary
from ..readers import expand_paths, read_scenarios
from ..tokens import (
    build_motion_vocabulary, build_road_vocabulary, collect_snippets, load_motion_vocabulary, road_pieces, save_motion_vocabulary,
    save_road_vocabulary,
)
from ..tokens.motion import MOTION_TYPES
from ..config_files import check_value, integer, number
from ..errors import UsageError
from ..model.smart import MAX_VOCAB_SIZE
from .arguments import bounded_int, motion_types, output_dir, output_file, seed

MOTION_SIZE_RULE = integer(1, MAX_VOCAB_SIZE, "the largest vocabulary")
"""A motion vocabulary size ``vocab build --sizes`` takes."""


def register(subparsers) -> None:
    p = subparsers.add_parser("vocab", help="build motion and road token vocabularies from scenes",
                              description="Motion and road token vocabularies (k-disks, SMART sec. 3.1).")
    sub = p.add_subparsers(dest="vocab_command", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build vocabularies from scene files",
                       description="Collect 0.5 s motion snippets (every fully valid 6-frame window) of vehicles, "
                                   "pedestrians and cyclists and the 5 m road pieces of every scene, then build "
                                   "k-disks vocabularies. Writes DIR/motion_SIZE.{npz,json} per size and "
                                   "DIR/road_SIZE.{npz,json}.")
    b.add_argument("sources", nargs="+", metavar="SRC", help="scene files, folders or globs (any supported format)")
    b.add_argument("--sizes", default="512,1024,2048",
                   help="motion vocabulary sizes, comma-separated; each N (every type) or VEH/PED/CYC (per type), e.g. 1024/512/512")
    b.add_argument("--tolerance", default="0", metavar="T",
                   help="k-disks disk radius in metres, T or VEH/PED/CYC; 0 (default): the radius that covers every "
                        "snippet is searched; smaller: the tokens go to the common motions first (e.g. 0.05/0/0)")
    b.add_argument("--road-size", type=bounded_int(0, MAX_VOCAB_SIZE, "the largest vocabulary"), default=1024, help="road vocabulary size (0: no road vocabulary)")
    b.add_argument("--out", required=True, type=lambda text: Path(output_dir(text)), help="output folder")
    b.add_argument("--seed", type=seed, default=0, help="random seed of k-disks (default 0)")
    b.add_argument("--stride", type=bounded_int(1, 1000), default=1, help="frames between the starts of collected snippets")
    b.add_argument("--no-progress", action="store_true", help="no progress bars")
    b.set_defaults(func=run_build)
    t = sub.add_parser("transfer", help="a checkpoint moved onto another motion vocabulary (warm start for training)",
                       description="Write a copy of CHECKPOINT that speaks the motion vocabulary --motion-vocab: the same "
                                   "weights, each new token's head row taken from the old token nearest it (its bias lowered "
                                   "by log of the new tokens sharing that old one; smart_marl.model.transfer). Train from it "
                                   "with `smart-marl train ... motion_vocab=V road_vocab=<its road vocabulary> --init OUT.json`.")
    t.add_argument("checkpoint", metavar="CHECKPOINT", help="a checkpoint's .json, or 'embedded'")
    t.add_argument("--motion-vocab", required=True, metavar="V", help="the new motion vocabulary (.npz)")
    t.add_argument("--out", required=True, type=lambda text: Path(output_file(text)), metavar="NAME", help="the new checkpoint (writes NAME.json, .safetensors...)")
    t.add_argument("--types", type=motion_types, default=None, metavar="TYPE[,TYPE]",
                   help="only these agent types (vehicle, pedestrian, cyclist) take the new vocabulary; the others keep "
                        "the checkpoint's tokens and head rows (default: every type)")
    t.set_defaults(func=run_transfer)


def _per_type(text: str, flag: str, cast, rule) -> tuple:
    """``N`` (every motion type) or ``VEH/PED/CYC`` -> one value per type, each checked with ``rule``."""
    try:
        values = tuple(cast(v) for v in text.split("/"))
    except ValueError:
        raise UsageError(f"argument {flag}: {text!r} is not N or VEH/PED/CYC") from None
    if len(values) == 1:
        values = values * len(MOTION_TYPES)
    if len(values) != len(MOTION_TYPES):
        raise UsageError(f"argument {flag}: {text!r} gives {len(values)} values; give one, or three (VEH/PED/CYC)")
    for v in values:
        check_value(f"argument {flag}:", v, rule, UsageError)
    return values


def run_build(args) -> int:
    sizes = [_per_type(s.strip(), "--sizes", int, MOTION_SIZE_RULE) for s in str(args.sizes).split(",") if s.strip()]
    if not sizes:
        raise UsageError(f"argument --sizes: no size in {args.sizes!r} (e.g. 512,1024 or 1024/512/512)")
    tolerance = _per_type(str(args.tolerance), "--tolerance", float, number(0.0, 100.0, why="metres"))
    files = expand_paths(args.sources)
    parts = {t: [] for t in MOTION_TYPES}
    road_parts, scenes = [], []
    t0 = time.time()
    for path in files:
        for sc in read_scenarios(path):
            snip, prov = collect_snippets([sc], stride=args.stride)
            for t in MOTION_TYPES:
                parts[t].append(snip[t])
            entry = prov["scenes"][0]
            entry["path"] = path
            scenes.append(entry)
            if args.road_size:
                road_parts.append(road_pieces(sc.road_map, sc.traffic_lights).local)
    snippets = {t: np.concatenate(p) if p else np.zeros((0, 6, 3), np.float32) for t, p in parts.items()}
    provenance = {"sources": [str(s) for s in args.sources], "files": files, "scenes": scenes,
                  "snippet_stride_frames": args.stride,
                  "snippets": {t.name.lower(): int(len(v)) for t, v in snippets.items()}}
    print(f"read {len(scenes)} scenes from {len(files)} files in {time.time() - t0:.1f}s: snippets "
          + ", ".join(f"{k} {v}" for k, v in provenance["snippets"].items()), file=sys.stderr)
    for size in sizes:  # k-disks runs in time proportional to the size: more tokens than motions would run for minutes
        for t, n in zip(MOTION_TYPES, size):
            have = len(snippets[t])
            if have and n > have:
                raise UsageError(f"argument --sizes: {n} {t.name.lower()} tokens from {have} {t.name.lower()} snippets: a "
                                 f"vocabulary has at most as many tokens as the motions it is built from (give more scenes, "
                                 f"or per-type sizes VEH/PED/CYC)")
    args.out.mkdir(parents=True, exist_ok=True)
    for size in sizes:
        vocab = build_motion_vocabulary(snippets, dict(zip(MOTION_TYPES, size)), seed=args.seed, provenance=provenance,
                                        progress=not args.no_progress, tolerance_m=dict(zip(MOTION_TYPES, tolerance)))
        name = str(size[0]) if len(set(size)) == 1 else "-".join(str(v) for v in size)
        npz, js = save_motion_vocabulary(vocab, args.out / f"motion_{name}")
        print(json.dumps({"kind": "motion", "path": str(npz), "sizes": vocab.sizes(), "content_hash": vocab.content_hash(),
                          "tolerance_m": {t.name.lower(): round(v.tolerance_m, 5) for t, v in vocab.types.items()}}), flush=True)
    if args.road_size:
        local = np.concatenate(road_parts) if road_parts else np.zeros((0, 11, 2), np.float32)
        road = build_road_vocabulary(local, args.road_size, seed=args.seed,
                                     provenance={"files": files, "pieces": int(len(local))}, progress=not args.no_progress)
        npz, js = save_road_vocabulary(road, args.out / f"road_{args.road_size}")
        print(json.dumps({"kind": "road", "path": str(npz), "size": road.size, "content_hash": road.content_hash(),
                          "tolerance_m": round(road.tolerance_m, 5)}), flush=True)
    return 0


def run_transfer(args) -> int:
    ck = load_checkpoint(args.checkpoint)
    moved = transfer_motion_vocabulary(ck, load_motion_vocabulary(args.motion_vocab), args.types)
    meta = save_checkpoint(args.out, moved.model, moved.motion_vocab, moved.road_vocab, step=0,
                           data={"transferred_from": str(ck.path), "motion_vocab": moved.motion_vocab.content_hash()})
    print(json.dumps({"checkpoint": str(meta), "from": str(ck.path), "motion_sizes": moved.motion_vocab.sizes(),
                      "road_vocab": str(meta.with_name(meta.stem + ".road_vocab.npz"))}), flush=True)
    return 0
