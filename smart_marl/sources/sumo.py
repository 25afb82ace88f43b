"""Scenes generated with the SUMO traffic simulator: unlimited multi-agent traffic for training.

Stage: a source, the first stage of the data flow (a traffic simulator -> **Scenario** -> scene
cache). Needs the optional extra ``pip install "smart-marl[sumo]"`` (eclipse-sumo, libsumo,
sumolib, shapely); nothing is imported until it is used.

* :func:`generate_scenes` yields Scenarios: each simulation (:func:`~.sumo_sim.simulate_scenes`)
  builds a random network (grid, spider or random topology; 1-4 lanes; traffic lights, priority,
  stop and right-before-left junctions; sidewalks, crossings, bike lanes), random demand of cars,
  trucks, buses, bicycles and pedestrians with varied driver parameters, runs SUMO at 0.1 s steps
  after a warm-up and cuts several 9.1 s scenes (91 frames, current frame 10) around moving
  vehicles chosen as the self-driving car, with every agent within ``radius_m``. Simulations run in
  parallel processes; the scenes come out in the same order whatever the number of workers.
* :func:`generate_to_dir` writes them straight into a scene cache (one shard per simulation and a
  manifest, readable by :class:`~smart_marl.cache.SceneCache` and :func:`~smart_marl.read_scenarios`)
  or as WOMD TFRecords (one file per simulation).

What the maps hold (lanes with topology, road edges, crosswalks, stop signs, traffic lights) is
described in :mod:`.sumo_net`; the tracks (box centres, headings, smoothed walkers) in
:mod:`.sumo_sim`. Scenario ids are ``sumo-{seed}-{simulation:06d}-{scene:02d}``: the same seed gives
the same scenes. ``metadata`` holds the network kind and its parameters, the demand, the
simulation's seed and the scene's start time.
"""

from __future__ import annotations

import os
import sys
import time
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from tqdm import tqdm

from ..readers.scene_cache import MANIFEST, SHARD_SUFFIX, scene_entry, write_manifest, write_shard
from ..readers.womd import write_womd_tfrecord
from ..scenario import DT_S, Scenario
from ..workers import worker_pool
from .sumo_net import INSTALL_HINT, SumoUnavailableError, require_sumo
from .sumo_sim import SCENE_FRAMES, SumoConfig, simulate_scenes

__all__ = ["SumoConfig", "SumoUnavailableError", "INSTALL_HINT", "generate_scenes", "generate_to_dir",
           "GenerateReport", "simulate_scenes", "SCENE_FRAMES"]


def _simulations(seed: int, config: SumoConfig, workers: int, remaining) -> Iterator[tuple[int, list[Scenario]]]:
    """(simulation index, its scenes) for simulations 0, 1, ... in order. ``remaining()`` is the number
    of scenes still wanted: no more simulations are started than it needs (plus none spare), nor more
    worker processes than there are simulations to run."""
    workers = min(workers, -(-max(remaining(), 1) // config.scenes_per_sim))
    if workers <= 1:
        sim = 0
        while True:
            yield sim, simulate_scenes(seed, sim, config)
            sim += 1
    pool = worker_pool(workers)
    pending: dict[int, Future] = {}
    sim = 0
    try:
        while True:
            wanted = -(-max(remaining(), 1) // config.scenes_per_sim)  # simulations still needed, rounded up
            while len(pending) < min(2 * workers, max(wanted, 1)):
                nxt = sim + len(pending)
                pending[nxt] = pool.submit(simulate_scenes, seed, nxt, config)
            yield sim, pending.pop(sim).result()
            sim += 1
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def generate_scenes(num_scenes: int, seed: int = 0, config: SumoConfig | None = None, workers: int = 1,
                    progress: bool = False) -> Iterator[Scenario]:
    """Yield ``num_scenes`` SUMO scenes (see the module docstring). Deterministic in ``seed``: the
    same seed and config give the same scenes, whatever ``workers``."""
    require_sumo()
    config = config or SumoConfig()
    bar = tqdm(total=num_scenes, unit="scene", desc="generate-sumo", disable=not progress, file=sys.stderr)
    produced = 0
    try:
        if num_scenes <= 0:
            return
        for _, scenes in _simulations(seed, config, workers, lambda: num_scenes - produced):
            for scenario in scenes:
                yield scenario
                produced += 1
                bar.update(1)
                if produced >= num_scenes:
                    return
    finally:
        bar.close()


@dataclass
class GenerateReport:
    scenes: int = 0
    simulations: int = 0
    files: int = 0
    bytes_written: int = 0
    agent_seconds: float = 0.0  # valid agent frames x 0.1 s, summed over the scenes
    seconds: float = 0.0


def generate_to_dir(out: str | os.PathLike, num_scenes: int, seed: int = 0, config: SumoConfig | None = None,
                    workers: int = 1, fmt: str = "cache", progress: bool = True) -> GenerateReport:
    """Generate ``num_scenes`` scenes into ``out``: a scene cache (``fmt="cache"``: one shard per
    simulation, ``sumo-{seed}-{sim}.smsc``, plus ``manifest.json``) or WOMD TFRecords (``fmt="womd"``:
    ``sumo-{seed}-{sim}.tfrecord``)."""
    if fmt not in ("cache", "womd"):
        raise ValueError(f"unknown format {fmt!r}: use 'cache' or 'womd'")
    require_sumo()
    config = config or SumoConfig()
    started = time.perf_counter()
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    report = GenerateReport()
    shards: list[dict[str, Any]] = []
    bar = tqdm(total=num_scenes, unit="scene", desc="generate-sumo", disable=not progress, file=sys.stderr)
    try:
        if num_scenes > 0:
            for sim, scenes in _simulations(seed, config, workers, lambda: num_scenes - report.scenes):
                report.simulations += 1
                scenes = scenes[: num_scenes - report.scenes]
                if not scenes:
                    continue
                if fmt == "cache":
                    name = f"sumo-{seed}-{sim:06d}{SHARD_SUFFIX}"
                    report.bytes_written += write_shard(out_dir / name, scenes)
                    shards.append({"file": name, "input": f"sumo:seed={seed}:simulation={sim}",
                                   "scenes": [scene_entry(s, name) for s in scenes]})
                else:
                    path = out_dir / f"sumo-{seed}-{sim:06d}.tfrecord"
                    write_womd_tfrecord(scenes, path)
                    report.bytes_written += path.stat().st_size
                report.files += 1
                report.scenes += len(scenes)
                report.agent_seconds += sum(float(s.tracks.valid.sum()) for s in scenes) * DT_S
                bar.update(len(scenes))
                if report.scenes >= num_scenes:
                    break
    finally:
        bar.close()
    if fmt == "cache":
        write_manifest(out_dir, shards, inputs=[f"sumo:seed={seed}"])
        assert (out_dir / MANIFEST).is_file()
    report.seconds = time.perf_counter() - started
    return report
