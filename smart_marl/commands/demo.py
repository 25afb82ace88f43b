"""``smart-marl demo``: the README's main command, on embedded defaults (no data on disk needed).

Until the SMART prior and the environment exist, the demo exercises what does exist end to end on
synthetic scenes the package makes itself: Scenario -> WOMD TFRecord (GZIP) -> Scenario (checked
exact) -> scene cache -> DataLoader with workers, and prints what it did. It says so: it is not
the simulation demo yet.
"""

from __future__ import annotations

import time
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the pipeline end to end on built-in synthetic scenes",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("--out", default="out/demo", help="output folder (default: out/demo)")
    p.add_argument("--scenes", type=int, default=8, help="how many synthetic scenes")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(func=run)


def run(args) -> int:
    import torch

    from ..cache import SceneCache, preprocess
    from ..commands.info import format_line
    from ..readers import read_scenarios
    from ..readers.womd import write_womd_tfrecord
    from ..synthetic import synthetic_scenario

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print("smart-marl demo: synthetic scenes through the data pipeline (the SMART simulation demo comes with the "
          "trained prior; see README).")
    scenes = [synthetic_scenario(seed=args.seed + i) for i in range(args.scenes)]
    record_path = out / "synthetic.tfrecord.gz"
    t0 = time.perf_counter()
    write_womd_tfrecord(scenes, record_path, compress=True)
    back = list(read_scenarios(record_path))
    exact = len(back) == len(scenes) and all(a.equals(b, ignore=("source", "metadata")) for a, b in zip(scenes, back))
    print(f"wrote {len(scenes)} scenes as WOMD Scenario TFRecord (GZIP) to {record_path} and read them back: "
          f"{'identical' if exact else 'DIFFERENT'} ({time.perf_counter() - t0:.2f} s)")
    for scenario in back:
        print("  " + format_line(scenario.summary(), str(record_path)))
    report = preprocess([record_path], out / "cache", workers=1, progress=False)
    cache = SceneCache(out / "cache")
    loader = torch.utils.data.DataLoader(cache, batch_size=4, num_workers=2, collate_fn=list)
    t0 = time.perf_counter()
    seen = sum(len(batch) for batch in loader)
    print(f"scene cache at {out / 'cache'}: {report.scenes} scenes in {report.shards} shard(s); a DataLoader with 2 "
          f"workers read {seen} scenes in {time.perf_counter() - t0:.2f} s")
    return 0 if exact and seen == len(scenes) else 1
