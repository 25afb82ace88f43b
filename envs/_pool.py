"""Environment stage, the scene pool: where the batched environment takes its scenes from, for its
first reset and for every refill.

What comes in: sources (scene-cache folders and ``.smsc`` shards, which are read one scene at a time,
so a pool can be as large as the disk; any other path ``read_scenarios`` reads, ``"embedded"`` or a
list of :class:`~smart_marl.scenario.Scenario`, which are held in memory), an order and a seed. What
goes out: scenes by index (:meth:`ScenePool.static`, each as its :class:`~envs._scene.SceneStatic`,
at most ``max_loaded`` of them kept in memory at once, least recently used dropped first) and the
next indices to play (:meth:`ScenePool.take`: the pool in order, or a fresh permutation of it per
pass with ``order="random"``).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from pathlib import Path
from typing import Sequence

import numpy as np

from smart_marl.cache import SceneCache, ShardReader, is_cache_dir
from smart_marl.embedded import sample_scenarios
from smart_marl.readers import read_scenarios
from smart_marl.scenario import Scenario

from ._core import CoreScene
from ._scene import SceneStatic, scene_static
from ._setup import select_controlled
from .errors import EnvConfigError

ORDERS = ("sequential", "random")


class _Listed:
    """Scenes held in memory."""

    def __init__(self, scenes: list[Scenario]) -> None:
        self.scenes = scenes

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, i: int) -> Scenario:
        return self.scenes[i]


class _Shard:
    """One ``.smsc`` shard, read one scene at a time."""

    def __init__(self, path: Path) -> None:
        self.reader = ShardReader(path)

    def __len__(self) -> int:
        return len(self.reader)

    def __getitem__(self, i: int) -> Scenario:
        return self.reader[i]


def _open(source) -> object:
    """A random-access view (``len`` and ``[i]``) of one source."""
    if isinstance(source, Scenario):
        return _Listed([source])
    if isinstance(source, str) and source == "embedded":
        return _Listed(sample_scenarios())
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if path.is_dir() and is_cache_dir(path):
            cache = SceneCache(path)
            cache.check_shards()  # what can be checked before a run: every shard there, as long as its manifest says
            return cache
        if path.is_file() and path.suffix == ".smsc":
            return _Shard(path)
        scenes = list(read_scenarios(path))
        if not scenes:
            raise EnvConfigError(f"scenarios: no scene in {str(source)!r}")
        return _Listed(scenes)
    raise EnvConfigError(f"scenarios: each source must be a path, a Scenario or 'embedded', got {type(source).__name__}")


class ScenePool:
    """Scenes by index from one or more sources (module docstring)."""

    def __init__(self, sources, order: str = "sequential", seed: int = 0, max_loaded: int = 256,
                 indices: Sequence[int] | None = None) -> None:
        if order not in ORDERS:
            raise EnvConfigError(f"scene_order must be one of {ORDERS}, got {order!r}")
        if isinstance(sources, (str, os.PathLike, Scenario)):
            sources = [sources]
        sources = list(sources)
        if sources and all(isinstance(s, Scenario) for s in sources):
            self._parts = [_Listed(sources)]
        else:
            self._parts = [_open(s) for s in sources]
        self._offsets = np.cumsum([0] + [len(p) for p in self._parts])
        total = int(self._offsets[-1])
        self._index = list(range(total)) if indices is None else [int(i) for i in indices]
        if not self._index:
            raise EnvConfigError("scenarios: the pool holds no scene")
        bad = [i for i in self._index if not 0 <= i < total]
        if bad:
            raise EnvConfigError(f"scenarios: scene indices {bad[:5]} are outside the {total} scenes of the sources")
        self.order, self.max_loaded = order, int(max_loaded)
        self._loaded: OrderedDict[int, SceneStatic] = OrderedDict()
        self.seed(seed)

    def __len__(self) -> int:
        return len(self._index)

    @property
    def num_source_scenes(self) -> int:
        """How many scenes the sources hold (a pool may use some of them: ``indices``)."""
        return int(self._offsets[-1])

    def subset(self, indices: Sequence[int], order: str | None = None, seed: int = 0) -> "ScenePool":
        """A pool of some of this pool's scenes (positions ``indices`` of this pool), sharing its sources."""
        out = ScenePool.__new__(ScenePool)
        out._parts, out._offsets = self._parts, self._offsets
        out._index = [self._index[int(i)] for i in indices]
        if not out._index:
            raise EnvConfigError("scenarios: the pool holds no scene")
        out.order, out.max_loaded = order or self.order, self.max_loaded
        out._loaded = OrderedDict()
        out.seed(seed)
        return out

    def seed(self, seed: int) -> None:
        """Restart the order from its beginning (a new random order for ``seed``)."""
        self._rng = np.random.default_rng(int(seed))
        self._queue: list[int] = []

    def order_state(self) -> dict:
        """Where the pool is in its order, as JSON values (the random generator's state, the scenes left of
        this pass), for :meth:`set_order_state`: a resumed run takes the same scenes next."""
        rng = self._rng.bit_generator.state
        return {"bit_generator": rng["bit_generator"], "state": {k: str(v) for k, v in rng["state"].items()},
                "has_uint32": int(rng["has_uint32"]), "uinteger": int(rng["uinteger"]), "queue": [int(i) for i in self._queue]}

    def set_order_state(self, state: dict) -> None:
        """Continue the order from :meth:`order_state`'s ``state``; :class:`ValueError` (or ``KeyError``,
        ``TypeError``) for a state that is not one of this pool's (another generator, indices outside it)."""
        queue = [int(i) for i in state["queue"]]
        if any(not 0 <= i < len(self) for i in queue):
            raise ValueError(f"the saved order names scenes outside this pool's {len(self)}")
        if state["bit_generator"] != self._rng.bit_generator.state["bit_generator"]:
            raise ValueError(f"the saved order is of a {state['bit_generator']!r} generator")
        rng = np.random.default_rng()
        rng.bit_generator.state = {"bit_generator": state["bit_generator"],
                                   "state": {k: int(v) for k, v in state["state"].items()},
                                   "has_uint32": int(state["has_uint32"]), "uinteger": int(state["uinteger"])}
        self._rng, self._queue = rng, queue

    def scenario(self, i: int) -> Scenario:
        """Scene ``i`` of the pool, read from its source."""
        j = self._index[int(i)]
        k = int(np.searchsorted(self._offsets, j, side="right")) - 1
        return self._parts[k][int(j - self._offsets[k])]

    def static(self, i: int) -> SceneStatic:
        """Scene ``i``'s constants (kept for the ``max_loaded`` most recently used scenes)."""
        st = self._loaded.get(i)
        if st is None:
            st = scene_static(self.scenario(i))
            self._loaded[i] = st
            while len(self._loaded) > self.max_loaded:
                self._loaded.popitem(last=False)
        else:
            self._loaded.move_to_end(i)
        return st

    def take(self, count: int) -> list[int]:
        """The next ``count`` scene indices in the pool's order (it wraps around: a pass over the
        pool is every scene once)."""
        out = []
        while len(out) < count:
            if not self._queue:
                n = len(self)
                self._queue = list(self._rng.permutation(n)) if self.order == "random" else list(range(n))
            out.append(int(self._queue.pop(0)))
        return out

    def scenario_ids(self) -> list[str]:
        """Every scene's id, in pool order (a scene cache's manifest says them without reading a scene)."""
        out = []
        for j in self._index:
            k = int(np.searchsorted(self._offsets, j, side="right")) - 1
            part, local = self._parts[k], int(j - self._offsets[k])
            out.append(part.scenes[local]["scenario_id"] if isinstance(part, SceneCache) else part[local].scenario_id)
        return out


def next_scenes(pool: ScenePool, count: int, controlled, max_agents: int, types) -> tuple[list[int], list]:
    """(pool indices, :class:`~envs._core.CoreScene` s) of the pool's next ``count`` scenes that have an
    agent to control (``controlled``, of the agent ``types`` given, at most ``max_agents``, as
    :func:`envs._setup.select_controlled`); scenes without one are passed over."""
    picked, scenes, skipped = [], [], 0
    while len(scenes) < count:
        (i,) = pool.take(1)
        static = pool.static(i)
        ctrl = select_controlled(controlled, static, max_agents, types)
        if len(ctrl) == 0:
            skipped += 1
            if skipped > len(pool):
                raise EnvConfigError(f"no scene of the pool has an agent to control (controlled={controlled!r}, types {list(types)})")
            continue
        picked.append(i)
        scenes.append(CoreScene(static, ctrl, key=i))
    return picked, scenes


__all__ = ["ORDERS", "ScenePool", "next_scenes"]
