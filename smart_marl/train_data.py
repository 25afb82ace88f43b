"""Training stage, its data: the run's scenes (:func:`open_scenes`, :class:`MixedScenes`), their
token arrays made in DataLoader workers (:class:`TokenizedScenes`), the deterministic batch order
(:class:`EpochBatchSampler`), closed-loop (CAT-K) batches, the loader and the vocabularies built
from the scenes. Re-exported by :mod:`smart_marl.train`.
"""

from __future__ import annotations

import os
from typing import Any, Iterator, Sequence

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from .cache import SceneCache, is_cache_dir
from .braking import braking_leaders, with_braking_leaders
from .catk import catk_tokens, drifted
from .model.batch import RoadArrays, RoadSettings, SmartBatch, collate_scenes, scene_road, scene_tensors
from .model.smart import SMART, SmartConfig
from .readers import read_scenarios
from .scenario import AgentType, Scenario
from .token_cache import TokenCache
from .tokens import MotionVocabulary, build_motion_vocabulary, collect_snippets, tokenize_motion
from .tokens.road import RoadVocabulary, build_road_vocabulary, road_pieces
from .train_config import TrainConfig, TrainConfigError, TrainError


def open_scenes(path: str) -> Sequence[Scenario]:
    """A map-style sequence of scenes: a :class:`~smart_marl.cache.SceneCache` for a cache folder,
    else every scene that ``read_scenarios`` yields for the path (read once, kept in memory)."""
    if not path:
        raise TrainError("no training data given (set data=PATH: a scene cache folder, scene files, a folder or a glob)")
    scenes: Sequence[Scenario] = SceneCache(path) if os.path.isdir(path) and is_cache_dir(path) else list(read_scenarios(path))
    if len(scenes) == 0:
        raise TrainError(f"{path}: the dataset is empty (no scene to train on)")
    return scenes


class MixedScenes(Sequence):
    """``main`` followed by ``extra`` repeated ``repeat`` times: a few scenes (real ones next to
    thousands of simulated ones) get a chosen share of the samples without copying them. Index
    ``i < len(main)`` is ``main[i]``, so validating on the first training scenes still sees ``main``."""

    def __init__(self, main: Sequence[Scenario], extra: Sequence[Scenario], share: float) -> None:
        if not 0.0 < share < 1.0:
            raise TrainConfigError(f"extra_data_share must be in (0, 1), got {share}")
        self.main, self.extra = main, extra
        self.repeat = max(1, round(share / (1.0 - share) * len(main) / len(extra)))

    @property
    def share(self) -> float:
        """The share of samples that actually come from ``extra``."""
        return len(self.extra) * self.repeat / len(self)

    def __len__(self) -> int:
        return len(self.main) + len(self.extra) * self.repeat

    def __getitem__(self, index: int) -> Scenario:
        if not -len(self) <= index < len(self):
            raise IndexError(f"scene index {index} out of range for {len(self)} samples")
        index %= len(self)
        return self.main[index] if index < len(self.main) else self.extra[(index - len(self.main)) % len(self.extra)]



def _check_token_cache_config(cfg: "TrainConfig") -> None:
    """A token cache holds noise-free, teacher-forced tokens made with given vocabularies: refuse a
    run that would need anything else from it."""
    wrong = [f"token_noise_topk={cfg.token_noise_topk}"] if cfg.token_noise_topk and cfg.token_noise_topk > 1 else []
    wrong += [f"catk_top_k={cfg.catk_top_k}"] if cfg.catk_top_k > 0 else []
    wrong += ["extra_data=" + cfg.extra_data] if cfg.extra_data else []
    if wrong:
        raise TrainConfigError(f"data={cfg.data} is a token cache (noise-free teacher-forced tokens, one folder): "
                               f"it cannot serve {', '.join(wrong)}; train on the scenes instead")
    if not (cfg.motion_vocab or cfg.init):
        raise TrainConfigError(f"data={cfg.data} is a token cache: name its vocabularies (motion_vocab=, road_vocab=) "
                               "or an init checkpoint that has them; they cannot be built from tokens")


def training_scenes(cfg: "TrainConfig") -> Sequence[Scenario]:
    """The run's scenes: ``data``, with ``extra_data`` mixed in at ``extra_data_share`` when given."""
    scenes = open_scenes(cfg.data)
    return MixedScenes(scenes, open_scenes(cfg.extra_data), cfg.extra_data_share) if cfg.extra_data else scenes


class TokenizedScenes(Dataset):
    """Scenes -> per-scene token arrays (:func:`scene_tensors`), in DataLoader workers.

    An item key is ``(scene index, sample position)``; the position seeds the token noise and the
    road mask, so a sample is the same whichever worker makes it. Road arrays (static per scene)
    and, without noise, motion tokens are cached per worker (bounded). With ``closed_loop`` the
    motion tokens depend on the model being trained: an item is then the scene, its road arrays and
    its position, and :func:`closed_loop_batch` makes the batch in the training process."""

    def __init__(self, scenes: Sequence[Scenario], motion_vocab: MotionVocabulary, road_vocab: RoadVocabulary, seed: int,
                 noise_topk: int, road_mask_prob: float, road_keep_radius_m: float | None, cache_size: int = 512,
                 closed_loop: bool = False, road: RoadSettings = RoadSettings()) -> None:
        self.scenes, self.motion_vocab, self.road_vocab, self.road_settings = scenes, motion_vocab, road_vocab, road
        self.seed, self.noise_topk, self.road_mask_prob = seed, noise_topk, road_mask_prob
        self.road_keep_radius_m, self.cache_size, self.closed_loop = road_keep_radius_m, cache_size, closed_loop
        self._roads: dict[int, RoadArrays] = {}
        self._motion: dict[int, Any] = {}

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, key) -> dict[str, np.ndarray]:
        index, position = key if isinstance(key, tuple) else (key, 0)
        scenario = self.scenes[index]
        road = self._roads.get(index)
        if road is None:
            road = scene_road(scenario, self.road_vocab, self.road_settings)
            if len(self._roads) < self.cache_size:
                self._roads[index] = road
        if self.closed_loop:
            return {"scenario": scenario, "road": road, "position": int(position)}
        rng = np.random.default_rng([self.seed, int(position)])
        tokens = None
        if self.noise_topk <= 1:
            tokens = self._motion.get(index)
            if tokens is None:
                tokens = tokenize_motion(scenario, self.motion_vocab)
                if len(self._motion) < self.cache_size:
                    self._motion[index] = tokens
        return scene_tensors(scenario, self.motion_vocab, road, noise_topk=self.noise_topk, road_mask_prob=self.road_mask_prob,
                             rng=rng, motion_tokens=tokens, road_keep_radius_m=self.road_keep_radius_m)


class EpochBatchSampler(Sampler):
    """Global batch g (g = 0, 1, ...) takes sample positions [g * B * W, (g + 1) * B * W) of an
    endless stream of per-epoch permutations (seeded by (seed, epoch)); rank r reads its slice of
    B. Yields lists of (scene index, sample position), starting at ``start_batch``."""

    def __init__(self, num_scenes: int, batch_size: int, seed: int, start_batch: int, num_batches: int, rank: int = 0,
                 world_size: int = 1, shuffle: bool = True) -> None:
        self.n, self.b, self.seed, self.start, self.count = num_scenes, batch_size, seed, start_batch, num_batches
        self.rank, self.world, self.shuffle = rank, world_size, shuffle
        self._perms: dict[int, np.ndarray] = {}

    def _scene_at(self, position: int) -> int:
        epoch, within = divmod(position, self.n)
        if not self.shuffle:
            return within
        perm = self._perms.get(epoch)
        if perm is None:
            perm = self._perms[epoch] = np.random.default_rng([self.seed, epoch, 7]).permutation(self.n)
            if len(self._perms) > 4:
                self._perms.pop(min(self._perms))
        return int(perm[within])

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[list[tuple[int, int]]]:
        for g in range(self.start, self.start + self.count):
            first = (g * self.world + self.rank) * self.b
            yield [(self._scene_at(p), p) for p in range(first, first + self.b)]


def closed_loop_batch(model: SMART, items: list[dict], motion_vocab: MotionVocabulary, top_k: int, road_mask_prob: float,
                      road_keep_radius_m: float | None, seed: int, device: torch.device, avoid: bool = False,
                      brake_leaders: float = 0.0, max_drift_m: float | None = None) -> SmartBatch:
    """The training batch of closed-loop items (:class:`TokenizedScenes` with ``closed_loop``): CAT-K
    token sequences under the current ``model`` (:func:`smart_marl.catk.catk_tokens`, keeping gaps with
    ``avoid``), then the usual per-scene tensors (the road mask seeded by the sample position) and
    padding. ``brake_leaders`` > 0: that share of each scene's leaders brake hard first
    (:func:`smart_marl.braking.braking_leaders`, seeded by the sample position); a braking leader is
    scripted, so its tokens from the onset on are inputs, not targets (else every car would learn to
    stop for no reason). ``max_drift_m``: a token that starts farther than this from the log is no
    target (:func:`smart_marl.catk.drifted`)."""
    edits = [braking_leaders(it["scenario"], np.random.default_rng([seed, it["position"], 11]), brake_leaders) for it in items]
    scenes = [with_braking_leaders(it["scenario"], e) for it, e in zip(items, edits)]
    tokens = catk_tokens(model, scenes, [it["road"] for it in items], motion_vocab, top_k, device, avoid=avoid)
    out = []
    for sc, it, mt, e in zip(scenes, items, tokens, edits):
        arrays = scene_tensors(sc, motion_vocab, it["road"], road_mask_prob=road_mask_prob,
                               rng=np.random.default_rng([seed, it["position"]]), motion_tokens=mt,
                               road_keep_radius_m=road_keep_radius_m)
        drop = drifted(sc, mt, max_drift_m) if max_drift_m is not None else np.zeros(mt.ids.shape, bool)
        for track, frame, _ in e:  # the scripted leader: every token ending after its onset
            drop[track, int(np.searchsorted(mt.boundaries[1:], frame)):] = True
        out.append(without_targets(arrays, mt, drop))
    return collate_scenes(out)


def without_targets(arrays: dict[str, np.ndarray], tokens, drop: np.ndarray) -> dict[str, np.ndarray]:
    """``arrays`` (:func:`~smart_marl.model.batch.scene_tensors` of a scene tokenized as ``tokens``) with
    the tokens ``drop`` [tracks, S] says not predicted: token ``k`` of a track is the target at position
    ``k - 1``, which is masked."""
    if not drop[:, 1:].any():
        return arrays
    rows = np.flatnonzero(tokens.valid.any(1))  # the tracks scene_tensors keeps, in order
    target_valid = arrays["target_valid"].copy()
    target_valid[:, :-1] &= ~drop[rows, 1:]
    return {**arrays, "target_valid": target_valid}


def _item_list(items: list) -> list:
    return items


def make_loader(dataset: TokenizedScenes | TokenCache, sampler: EpochBatchSampler, num_workers: int, pin_memory: bool, seed: int) -> DataLoader:
    closed_loop = getattr(dataset, "closed_loop", False)
    return DataLoader(dataset, batch_sampler=sampler, collate_fn=_item_list if closed_loop else collate_scenes,
                      num_workers=num_workers, pin_memory=pin_memory and not closed_loop,
                      generator=torch.Generator().manual_seed(seed),  # leaves the global RNG alone (exact resume)
                      persistent_workers=False, prefetch_factor=2 if num_workers else None)


def build_vocabularies(scenes: Sequence[Scenario], model_cfg: SmartConfig, num_scenes: int, seed: int,
                       progress: bool = False) -> tuple[MotionVocabulary, RoadVocabulary]:
    """Motion (k-disks per type) and road (k-disks) vocabularies of the config's sizes from the
    first ``num_scenes`` scenes, with the tokenizer's builders."""
    subset = [scenes[i] for i in range(min(num_scenes, len(scenes)))]
    snippets, prov = collect_snippets(subset)
    sizes = dict(zip((0, 1, 2), model_cfg.motion_vocab_sizes))
    mv = build_motion_vocabulary({AgentType(k): v for k, v in snippets.items()}, {AgentType(k): v for k, v in sizes.items()},
                                 seed=seed, provenance=prov, progress=progress)
    local = np.concatenate([road_pieces(s.road_map).local for s in subset])
    rv = build_road_vocabulary(local, model_cfg.road_vocab_size, seed=seed, progress=progress,
                               provenance={"scenes": [s.scenario_id for s in subset]})
    return mv, rv
