"""Carry many scenes to a lent GPU machine: pack a scene cache into one small file, unpack it there.

A lent machine takes 64 MiB of files in all; a generated scene is ~300 KB in a scene cache, so 1,000 of
them do not travel as they are. ``pack`` rounds every metric array to a grid (positions, sizes and road
points 1 cm, velocities 1 cm/s, headings 1e-4 rad), stores the rounded values as integer differences
along time (tracks) or along the polyline (road points), and xz-compresses the lot: ~15-25 KB a scene.
``unpack`` inverts it into a scene cache (shards + manifest), every scene validated as any reader's.
The copy is lossy by those grids, nothing else; the scene ids say which scenes they are.

    python benchmarks/scene_pack.py pack data/rl_train --out gpu_scenes_ft/train.npz.xz --count 2000
    python benchmarks/scene_pack.py unpack gpu_scenes_ft/train.npz.xz /tmp/train
"""

from __future__ import annotations

import argparse
import io
import json
import lzma
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# array name -> (grid step, axis along which differences are taken)
GRIDS = {
    "tracks.position": (0.01, 1), "tracks.velocity": (0.01, 1), "tracks.size": (0.01, 1), "tracks.heading": (1e-4, 1),
    "road_map.points": (0.01, 0), "traffic_lights.stop_points": (0.01, 0),
}
SCENES_PER_SHARD = 8


def _encode(name: str, a: np.ndarray) -> np.ndarray:
    if name not in GRIDS or a.size == 0:
        return a
    step, axis = GRIDS[name]
    q = np.round(a.astype(np.float64) / step).astype(np.int64)
    return np.diff(q, axis=axis, prepend=0).astype(np.int32)


def _decode(name: str, a: np.ndarray) -> np.ndarray:
    if name not in GRIDS or a.size == 0:
        return a
    step, axis = GRIDS[name]
    return (np.cumsum(a.astype(np.int64), axis=axis) * step).astype(np.float32)


def pack(sources: list[str], out: str, count: int | None) -> dict:
    from envs._pool import ScenePool

    pool = ScenePool(sources)
    n = len(pool) if count is None else min(count, len(pool))
    arrays: dict[str, np.ndarray] = {}
    for i in range(n):
        scene_arrays, meta = pool.scenario(i).to_arrays()
        for name, a in scene_arrays.items():
            arrays[f"{i}/{name}"] = _encode(name, np.asarray(a))
        arrays[f"{i}/meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_bytes(lzma.compress(buf.getvalue(), preset=9 | lzma.PRESET_EXTREME))
    return {"scenes": n, "bytes": Path(out).stat().st_size}


def unpack(packed: str, out: str) -> dict:
    from smart_marl.readers.scene_cache import scene_entry, write_manifest, write_shard
    from smart_marl.scenario import Scenario

    with np.load(io.BytesIO(lzma.decompress(Path(packed).read_bytes())), allow_pickle=False) as z:
        per_scene: dict[int, list[str]] = {}  # scene -> its array names, in one pass over the file's names
        for key in z.files:
            i, name = key.split("/", 1)
            per_scene.setdefault(int(i), []).append(name)
        scenes = []
        for i in sorted(per_scene):
            arrays = {name: _decode(name, z[f"{i}/{name}"]) for name in per_scene[i] if name != "meta"}
            scenes.append(Scenario.from_arrays(arrays, json.loads(z[f"{i}/meta"].tobytes()), validate=True))
    n = len(scenes)
    Path(out).mkdir(parents=True, exist_ok=True)
    shards = []
    for s in range(0, n, SCENES_PER_SHARD):
        name = f"packed-{s // SCENES_PER_SHARD:06d}.smsc"
        part = scenes[s : s + SCENES_PER_SHARD]
        write_shard(Path(out) / name, part)
        shards.append({"file": name, "input": packed, "scenes": [scene_entry(sc, name) for sc in part]})
    write_manifest(out, shards, inputs=[packed])
    return {"scenes": n}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("pack")
    a.add_argument("sources", nargs="+", help="scene caches or any scene files, in this order")
    a.add_argument("--out", required=True)
    a.add_argument("--count", type=int, default=None)
    b = sub.add_parser("unpack")
    b.add_argument("packed")
    b.add_argument("out")
    args = p.parse_args()
    t0 = time.perf_counter()
    info = pack(args.sources, args.out, args.count) if args.cmd == "pack" else unpack(args.packed, args.out)
    print(json.dumps({"cmd": args.cmd, **info, "seconds": round(time.perf_counter() - t0, 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
