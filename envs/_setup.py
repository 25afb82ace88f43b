"""Environment stage, setting up: the arguments both faces of the environment share, turned into
what the core needs: the prior (a model and its motion vocabulary), the scenes, and which agents
of a scene are controlled.

``controlled`` selections: ``"sdc"``, ``"predict"`` (the tracks to predict), ``"vehicles"``,
``"all"``, ``"moving_vehicles"`` (vehicles whose logged position moves more than
``MOVING_MIN_ROUTE_M`` from the current frame to their last valid frame: parked cars are left to
the background; and not already inside another agent's box at the current frame, as the collision event measures
it: a log artefact, such as two simulated cars standing overlapped in a junction, that collides at the first step
whatever the policy does), a list of track ids or names, or a callable(scene) -> [N] bool mask. Only
vehicles, pedestrians and cyclists present at the current frame can be controlled;
``max_agents`` keeps the nearest to the self-driving car.
"""

from __future__ import annotations

import os
from typing import Iterable

import numpy as np

from smart_marl.embedded import sample_scenarios
from smart_marl.geometry import colliding
from smart_marl.model.checkpoint import CheckpointError, load_prior
from smart_marl.readers import read_scenarios
from smart_marl.scenario import AgentType, Scenario
from smart_marl.tokens import MotionVocabulary

from ._scene import SceneStatic
from .errors import EnvConfigError

SELECTIONS = ("sdc", "predict", "vehicles", "all", "moving_vehicles")
MOVING_MIN_ROUTE_M = 10.0


def load_env_prior(prior, motion_vocab: MotionVocabulary | None, device="cpu"):
    """(model or None, motion vocabulary) from the ``prior`` argument
    (:func:`smart_marl.model.checkpoint.load_prior`: a path, a model or Checkpoint, ``"embedded"``)."""
    if prior is None:
        if motion_vocab is None:
            raise EnvConfigError("prior=None needs motion_vocab=...: the action spaces are the vocabulary's tokens")
        return None, motion_vocab
    try:
        model, vocab = load_prior(prior, device)
    except CheckpointError as exc:
        raise EnvConfigError(f"prior: {exc}") from exc
    vocab = motion_vocab if motion_vocab is not None else vocab
    sizes = tuple(vocab[t].size if t in vocab.types else 0 for t in range(3))
    if sizes != tuple(int(v) for v in model.config.motion_vocab_sizes):
        raise EnvConfigError(f"motion_vocab sizes {sizes} do not match the prior's {tuple(model.config.motion_vocab_sizes)}")
    return model, vocab


def load_scenes(scenarios) -> list[Scenario]:
    """Every scene of ``scenarios``: a path (:func:`~smart_marl.readers.read_scenarios`), a Scenario,
    a list of Scenario or ``"embedded"`` (the package's sample scenes)."""
    if isinstance(scenarios, Scenario):
        return [scenarios]
    if isinstance(scenarios, str) and scenarios == "embedded":
        return sample_scenarios()
    if isinstance(scenarios, (str, os.PathLike)):
        scenes = list(read_scenarios(scenarios))
    elif isinstance(scenarios, Iterable):
        scenes = list(scenarios)
        bad = [type(s).__name__ for s in scenes if not isinstance(s, Scenario)]
        if bad:
            raise EnvConfigError(f"scenarios: a list must hold Scenario objects, got {bad[:3]}")
    else:
        raise EnvConfigError(f"scenarios must be a path, a Scenario, a list of Scenario or 'embedded', got {type(scenarios).__name__}")
    if not scenes:
        raise EnvConfigError(f"scenarios: no scene in {scenarios!r}")
    return scenes


def moving_vehicles_mask(scenario: Scenario, min_route_m: float = MOVING_MIN_ROUTE_M) -> np.ndarray:
    """[N] bool: vehicles present at the current frame whose logged position moves more than
    ``min_route_m`` between the current frame and their last valid frame, and whose box does not overlap another
    present agent's there (:func:`overlapping_at_start`)."""
    tr, cf = scenario.tracks, scenario.current_frame
    last = tr.valid.shape[1] - 1 - np.argmax(tr.valid[:, ::-1], axis=1)  # [N] last valid frame
    route_m = np.linalg.norm(tr.position[np.arange(tr.num_tracks), last, :2] - tr.position[:, cf, :2], axis=1)
    moving = tr.valid[:, cf] & (tr.types == int(AgentType.VEHICLE)) & (route_m > min_route_m)
    return moving & ~overlapping_at_start(scenario, np.flatnonzero(moving))


def overlapping_at_start(scenario: Scenario, query: np.ndarray | None = None) -> np.ndarray:
    """[N] bool: the tracks (of ``query``, default all) whose rounded box overlaps another present track's at the current
    frame, the test the collision event makes (:func:`smart_marl.geometry.colliding` on the boxes the events measure,
    :meth:`~smart_marl.scenario.Tracks.box_size`)."""
    tr, cf = scenario.tracks, scenario.current_frame
    out = np.zeros(tr.num_tracks, bool)
    query = np.arange(tr.num_tracks) if query is None else np.asarray(query, np.int64)
    if len(query):
        pose = np.concatenate([tr.position[:, cf, :2], tr.heading[:, cf, None]], -1)[:, None]  # [N, 1, 3]
        size = tr.box_size()
        out[query] = colliding(pose, tr.valid[:, cf, None], size[:, 0], size[:, 1], query)
    return out


def controlled_mask(controlled, static: SceneStatic) -> np.ndarray:
    """[N] bool of the tracks the ``controlled`` selection picks (module docstring; before max_agents)."""
    sc = static.scenario
    n = static.num_tracks
    if callable(controlled) and not isinstance(controlled, str):
        mask = np.asarray(controlled(sc), bool)
        if mask.shape != (n,):
            raise EnvConfigError(f"controlled: the callable must return a [{n}] bool mask for scene {sc.scenario_id}, got {mask.shape}")
        return mask & static.controllable
    mask = np.zeros(n, bool)
    if controlled == "sdc":
        if sc.sdc_index >= 0:
            mask[sc.sdc_index] = True
        return mask & static.controllable
    if controlled == "predict":
        mask[np.asarray(sc.predict_indices, np.int64)] = True
        return mask & static.controllable
    if controlled == "vehicles":
        return static.controllable & (static.types == int(AgentType.VEHICLE))
    if controlled == "moving_vehicles":
        return static.controllable & moving_vehicles_mask(sc)
    if controlled == "all":
        return static.controllable.copy()
    if isinstance(controlled, str):
        raise EnvConfigError(f"controlled must be one of {SELECTIONS}, a list of track ids or names, or a callable(scene) -> "
                             f"mask; got {controlled!r}")
    ids = {int(i): k for k, i in enumerate(sc.tracks.ids)}
    for item in controlled:
        k = static.name_to_track.get(item) if isinstance(item, str) else ids.get(int(item))
        if k is None:
            raise EnvConfigError(f"controlled: {item!r} is not a track of scene {sc.scenario_id}")
        if not static.controllable[k]:
            raise EnvConfigError(f"controlled: {static.names[k]} of scene {sc.scenario_id} cannot be controlled (only vehicles, "
                                 f"pedestrians and cyclists present at the current frame can)")
        mask[k] = True
    return mask


def select_controlled(controlled, static: SceneStatic, max_agents: int | None, types=None) -> np.ndarray:
    """The controlled tracks [C] of a scene in track order: the selection (:func:`controlled_mask`),
    of the agent ``types`` given (default: any), at most ``max_agents`` of them (the nearest to the
    self-driving car, or to their centroid when the scene has none). May be empty."""
    mask = controlled_mask(controlled, static)
    if types is not None:
        mask &= np.isin(static.types, [int(t) for t in types])
    ctrl = np.flatnonzero(mask)
    if max_agents is not None and len(ctrl) > max_agents:
        sc = static.scenario
        cf = sc.current_frame
        ref = sc.tracks.position[sc.sdc_index, cf, :2] if sc.sdc_index >= 0 else sc.tracks.position[ctrl, cf, :2].mean(0)
        d = np.linalg.norm(sc.tracks.position[ctrl, cf, :2] - ref, axis=1)
        ctrl = np.sort(ctrl[np.argsort(d, kind="stable")[:max_agents]])
    return ctrl


__all__ = ["MOVING_MIN_ROUTE_M", "SELECTIONS", "controlled_mask", "load_env_prior", "load_scenes", "moving_vehicles_mask",
           "overlapping_at_start", "select_controlled"]
