"""``smart-marl preprocess SRC... --out DIR``: build a scene cache (see smart_marl.cache)."""

from __future__ import annotations

import os

from ..cache import preprocess
from .arguments import bounded_int, output_dir, reader_formats, workers


def register(subparsers) -> None:
    p = subparsers.add_parser("preprocess", help="convert scene files of any format into a scene cache",
                              description="Convert every scene of the given files, folders or globs into compact "
                                          "shards that a DataLoader with workers reads fast. Resumable: a rerun "
                                          "skips inputs already converted; a killed run leaves no partial shard.")
    p.add_argument("sources", nargs="+", metavar="SRC", help="scene files, folders or globs")
    p.add_argument("--out", required=True, type=output_dir, help="the cache folder (created if missing)")
    p.add_argument("--workers", type=workers, default=max(1, min(4, os.cpu_count() or 1)), help="parallel processes")
    p.add_argument("--scenes-per-shard", type=bounded_int(1, 10_000, "a shard is held in memory until it is written"),
                   default=64, help="scenes per shard file (default 64, at most 10,000)")
    p.add_argument("--skip-bad", action="store_true",
                   help="report bad input files, record them in the manifest and go on (default: stop)")
    p.add_argument("--append", action="store_true",
                   help="add these inputs to the cache already in --out (default: refuse a cache of other inputs)")
    p.add_argument("--format", default=None, choices=reader_formats(), help="force a reader instead of detecting the format per file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    report = preprocess(args.sources, args.out, workers=args.workers, scenes_per_shard=args.scenes_per_shard,
                        skip_bad=args.skip_bad, reader_format=args.format, progress=not args.quiet, append=args.append)
    print(f"{report.scenes} scenes in {report.shards} shards from {report.files} files "
          f"({report.files_done_before} already done before this run), {report.bytes_written / 1e6:.1f} MB written "
          f"in {report.seconds:.1f} s -> {args.out}")
    for entry in report.skipped:
        print(f"skipped: {entry['error']}")
    return 0  # with --skip-bad the skipped inputs are reported above and in the manifest
