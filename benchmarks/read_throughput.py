"""Read throughput of the WOMD reader and of the scene cache on the shared real files.

Prints one JSON line per measurement: {"benchmark", "reader", "scenes_per_s", "mb_per_s", ...}, the
median of several repeats. Usage: python benchmarks/read_throughput.py [--repeats 5] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import torch

from smart_marl import read_scenarios
from smart_marl.cache import SceneCache, preprocess

ROOT = Path(__file__).resolve().parents[1]


def _timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _emit(**record) -> None:
    print(json.dumps({"benchmark": "read_throughput", **record}), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "data"))
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    data = Path(args.data)

    womd_files = sorted((data / "womd_tfrecord").glob("*.tfrecord"))
    womd_bytes = sum(f.stat().st_size for f in womd_files)
    n = sum(1 for _ in read_scenarios(womd_files))
    seconds = _timed(lambda: list(read_scenarios(womd_files)), args.repeats)
    _emit(reader="womd_tfrecord", files=len(womd_files), scenes=n, seconds=round(seconds, 4),
          scenes_per_s=round(n / seconds, 2), mb_per_s=round(womd_bytes / 1e6 / seconds, 2))

    sources = [data / d for d in ("womd_tfrecord", "scenarionet", "smart_pkl", "gpudrive_json", "nocturne_json", "av2")]
    src_bytes = sum(f.stat().st_size for src in sources for f in src.rglob("*") if f.is_file())
    n = sum(1 for _ in read_scenarios(sources))
    seconds = _timed(lambda: list(read_scenarios(sources)), max(1, args.repeats // 2))
    _emit(reader="all_sources", scenes=n, seconds=round(seconds, 4), scenes_per_s=round(n / seconds, 2),
          mb_per_s=round(src_bytes / 1e6 / seconds, 2))

    with tempfile.TemporaryDirectory() as tmp:
        report = preprocess(sources, tmp, workers=2, progress=False)
        _emit(reader="preprocess", workers=2, scenes=report.scenes, seconds=round(report.seconds, 3),
              scenes_per_s=round(report.scenes / report.seconds, 2))
        cache = SceneCache(tmp)
        cache_bytes = sum(p.stat().st_size for p in cache.shard_paths())

        def read_all():
            fresh = SceneCache(tmp)
            for i in range(len(fresh)):
                fresh[i].tracks.position.sum()  # touch the data

        seconds = _timed(read_all, args.repeats)
        _emit(reader="scene_cache", scenes=len(cache), cache_mb=round(cache_bytes / 1e6, 2), seconds=round(seconds, 4),
              scenes_per_s=round(len(cache) / seconds, 1), mb_per_s=round(cache_bytes / 1e6 / seconds, 1))

        def loader_all():
            loader = torch.utils.data.DataLoader(SceneCache(tmp), batch_size=8, num_workers=2, collate_fn=list)
            return sum(len(b) for b in loader)

        seconds = _timed(loader_all, args.repeats)
        _emit(reader="scene_cache_dataloader", workers=2, scenes=len(cache), seconds=round(seconds, 4),
              scenes_per_s=round(len(cache) / seconds, 1), note="includes starting 2 worker processes")


if __name__ == "__main__":
    os.environ.setdefault("TQDM_DISABLE", "1")
    main()
