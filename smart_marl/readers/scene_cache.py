"""Reader for the project's own scene-cache shards (``*.smsc``, see smart_marl.cache), so that
``read_scenarios`` and ``smart-marl info`` take a cache folder like any other source."""

from __future__ import annotations

from typing import Iterator

from ..cache import ShardReader, is_shard
from ..scenario import Scenario

NAME = "scene_cache"
MULTI_SCENE = True  # several scenes per shard: errors name the scene index


def sniff(path: str, head: bytes) -> bool:
    return is_shard(head)


def read(path: str) -> Iterator[Scenario]:
    reader = ShardReader(path)
    try:
        for i in range(len(reader)):
            # copy out of the memory map: the reader closes when the stream ends
            yield Scenario.from_arrays(*_copied(reader[i]), validate=False)
    finally:
        reader.close()


def _copied(scenario: Scenario):
    arrays, meta = scenario.to_arrays()
    return {k: v.copy() for k, v in arrays.items()}, meta
