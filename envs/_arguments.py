"""Environment stage, arguments: the checks of what a user gives the environment's constructor and
``reset``, before any state is built (issue 34).

Pure functions, no env state: :func:`check_env_arguments` takes the constructor's keyword values and
returns them normalised (ints as ``int``, the reward as a :class:`~envs._reward.RewardConfig`, the
observation as an :class:`~envs._observation.ObservationConfig`, ``terminate_on`` as a frozenset...);
:func:`check_reset_arguments` takes ``reset``'s ``seed`` and ``options`` and returns the seed and the
scene index asked for. Every refusal is an :class:`~envs.errors.EnvConfigError` (a
:class:`~envs.errors.EnvConfigTypeError` for a value of the wrong type) naming the argument, the value
and what is allowed, through the project's one set of value rules (:mod:`smart_marl.config_files`).

What each argument takes (the documented meanings):

* ``horizon_steps``: an integer in 1..:data:`MAX_HORIZON_STEPS` (not 2.7, not True, not "16");
* ``max_agents``: None (every controllable agent) or an integer in 1..:data:`MAX_AGENT_SLOTS`;
* ``top_k``: an integer in 0..:data:`~smart_marl.model.smart.MAX_VOCAB_SIZE`, or None; 0 and None: the background
  samples from the whole distribution;
* ``temperature``: a finite number in :data:`smart_marl.rollout.TEMPERATURE_RANGE`;
* ``reference_top_k``: None (the full softmax) or an integer in 1..:data:`~smart_marl.model.smart.MAX_VOCAB_SIZE`;
* ``terminate_on``: a list, tuple or set of event names (a bare string is refused);
* ``reward``: None, a RewardConfig or a dict of weights, every weight a finite number within +-:data:`MAX_REWARD_WEIGHT`,
  ``goal_radius_m`` in [0, :data:`~smart_marl.config_files.MAX_DISTANCE_M`], ``headway_s`` in (0, :data:`MAX_HEADWAY_S`],
  ``ttc_s`` in (0, :data:`MAX_TTC_S`];
* ``observation``: "vector", "dict" or an ObservationConfig with sizes in range;
* ``render_size_px``: an integer in 16..:data:`MAX_RENDER_SIZE_PX`; ``render_radius_m`` a finite number in
  [:data:`MIN_RENDER_RADIUS_M`, :data:`MAX_RENDER_RADIUS_M`];
* ``avoid_collisions``, ``stop_lines``: True or False (not the string "false");
* ``lights``: "log" or "current" (:data:`smart_marl.rollout.LIGHTS`);
* ``persistence``: a finite number >= 0 (:mod:`smart_marl.rollout.persistence`; 0: off);
* ``precision``: the prior's arithmetic, "float32" or "bfloat16" (:mod:`smart_marl.model.precision`);
* ``shield``: True (the collision and offroad checks, :data:`envs._shield.DEFAULT_SHIELD_CHECKS`), False / None / an
  empty list (none), or a list of check names of :data:`envs._shield.SHIELD_CHECKS` ("gap" and "joint" among them) (a bare string is one name), normalised to a tuple in ``SHIELD_CHECKS`` order;
* ``controlled``: "sdc", "predict", "vehicles", "all", "moving_vehicles", a callable, or a list of track
  ids (integers) and agent names (strings);
* ``reset(seed)``: None or an integer in 0..2**63 - 1; ``reset(options)``: None or a dict; its key
  ``scene_index`` (when present) an integer in 0..number of scenes - 1; other keys are ignored, as
  Gymnasium environments ignore options they do not know (PettingZoo's API test passes some).
"""

from __future__ import annotations

import argparse
import dataclasses
import numbers
from collections.abc import Iterable, Mapping
from typing import Any

from smart_marl.config_files import (MAX_DISTANCE_M, Rule, check_value, device_problem, flag, integer, is_integer, number, one_of,
                                     optional, seed, shown)
from smart_marl.model.precision import PRECISIONS
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.render.bev import MIN_VIEW_RADIUS_M
from smart_marl.rollout import LIGHTS, temperature_rule
from smart_marl.rollout.persistence import DEFAULT_PERSISTENCE, persistence_rule

from ._dynamics import BACKGROUNDS
from ._observation import ObservationConfig
from ._reward import TERMINATION_EVENTS, RewardConfig
from ._setup import SELECTIONS
from ._shield import DEFAULT_SHIELD_CHECKS, SHIELD_CHECKS
from .errors import EnvConfigError, EnvConfigTypeError

MAX_HORIZON_STEPS = 10_000
"""The longest episode, in 0.5 s token steps (5,000 s): an episode keeps every step's poses."""
MAX_RENDER_SIZE_PX = 4096
"""The largest rendered frame's side (a 4096 x 4096 RGB frame is 50 MB)."""
MAX_RENDER_RADIUS_M = 10_000.0
"""The widest view (metres around the self-driving car), far wider than any scene."""
MIN_RENDER_RADIUS_M = MIN_VIEW_RADIUS_M
"""The narrowest view, 1 m: the renderer's own limit (:data:`smart_marl.render.bev.MIN_VIEW_RADIUS_M`; line
widths scale with the zoom, and a radius of 1e-10 m makes one frame take forever)."""
MAX_AGENT_SLOTS = 1024
"""The most controlled agents (``max_agents``; the batched env's agent slots per scene): no scene the project reads or
makes holds more agents (a generated scene at most 1,024, :mod:`smart_marl.sources.sumo_config`; a real WOMD one a few
hundred tracks), so more slots would only stay padded, and each slot costs about 6 KB a scene in every step's
TensorDict (the prior's 1,024 float32 logits and the 473-value observation): ``max_agents=10**9`` asked terabytes."""
MAX_REWARD_WEIGHT = 1e3
"""The largest reward weight, either sign: a term weighted 1,000x the goal's (1) already drowns every other one, and a
weight such as 1e300 makes a step's float32 reward inf (the returns, the critic's loss and the gradients NaN)."""
TOP_K_WHY = "the largest vocabulary: a larger k is every token"
"""Why a top-k (``top_k``, ``reference_top_k``, fine-tuning's and training's) stops at :data:`~smart_marl.model.smart.MAX_VOCAB_SIZE`."""
CONTROLLED_NAMES = SELECTIONS  # "sdc", "predict", "vehicles", "all", "moving_vehicles"
OBSERVATION_RULES: dict[str, Rule] = {
    "kind": one_of("vector", "dict"), "num_agents": integer(0, 1024, "agents in one observation"),
    "num_road_points": integer(0, 4096, "road points in one observation"),
    "num_lights": integer(0, 256, "traffic lights in one observation"), "light_radius_m": number(0.0, MAX_DISTANCE_M, why="metres, farther than any scene reaches"),
}
"""What each ObservationConfig field takes."""
MAX_HEADWAY_S = 10.0
"""The longest time headway the ``headway`` term asks for (``headway_s``): 10 s is 280 m at 100 km/h, five times the
2 s of the driving-school rule and beyond what any observation or scene of the project reaches."""
MAX_TTC_S = 30.0
"""The longest time to collision the ``ttc`` term penalises (``ttc_s``): 30 s, ten times the 3 s of common
forward-collision warnings, longer than the 8 s episodes and the prior's horizon."""
REWARD_RULES: dict[str, Rule] = {
    **{f.name: number(-MAX_REWARD_WEIGHT, MAX_REWARD_WEIGHT, why="1,000x the goal's") for f in dataclasses.fields(RewardConfig)},
    "goal_radius_m": number(0.0, MAX_DISTANCE_M, why="metres, farther than any scene reaches"),
    "headway_s": number(0.0, MAX_HEADWAY_S, low_open=True, why="seconds, five times the 2 s rule"),
    "ttc_s": number(0.0, MAX_TTC_S, low_open=True, why="seconds, longer than an episode")}
"""What each RewardConfig field takes: weights within +-:data:`MAX_REWARD_WEIGHT`, a goal radius in [0, 10 km], the gap
terms' thresholds in (0, :data:`MAX_HEADWAY_S`] and (0, :data:`MAX_TTC_S`] seconds."""


def _check(name: str, value: Any, rule: Rule, kind: type | tuple = numbers.Real) -> Any:
    """``value`` when ``rule`` takes it; else EnvConfigError, an EnvConfigTypeError when it is not even
    of the ``kind`` the argument takes (a string for a number, a bool for an integer...)."""
    wrong_type = isinstance(value, bool) != (kind is bool) or not isinstance(value, kind)
    return check_value(name, value, rule, EnvConfigTypeError if wrong_type else EnvConfigError)


def _terminate_on(value: Any) -> frozenset:
    if isinstance(value, (str, bytes)) or not isinstance(value, Iterable):
        raise EnvConfigTypeError(f"terminate_on must be a list of event names out of {TERMINATION_EVENTS}, got {shown(value)}")
    events = list(value)
    bad = [e for e in events if not isinstance(e, str) or e not in TERMINATION_EVENTS]
    if bad:
        raise EnvConfigError(f"terminate_on: unknown event(s) {shown(bad)}; known: {TERMINATION_EVENTS}")
    return frozenset(events)


def _reward(value: Any) -> RewardConfig:
    config = RewardConfig.from_any(value)
    for name, rule in REWARD_RULES.items():
        _check(f"reward[{name!r}]", getattr(config, name), rule)
    return config


def _observation(value: Any) -> ObservationConfig:
    if isinstance(value, ObservationConfig):
        config = value
    elif isinstance(value, str):
        config = ObservationConfig(kind=value)  # its own check names the kinds
    else:
        raise EnvConfigTypeError(f"observation must be 'vector', 'dict' or an ObservationConfig, got {shown(value)}")
    for name, rule in OBSERVATION_RULES.items():
        _check(f"observation.{name}", getattr(config, name), rule, str if name == "kind" else numbers.Real)
    return config


def _controlled(value: Any) -> Any:
    if isinstance(value, str):
        return _check("controlled", value, one_of(*CONTROLLED_NAMES), str)
    if callable(value):
        return value
    if isinstance(value, Mapping) or not isinstance(value, Iterable):
        raise EnvConfigTypeError(f"controlled must be one of {CONTROLLED_NAMES}, a list of track ids or agent names, or a "
                                 f"callable(scene) -> mask; got {shown(value)}")
    items = list(value)
    bad = [x for x in items if not (isinstance(x, str) or is_integer(x))]
    if bad:
        raise EnvConfigTypeError(f"controlled: a list holds track ids (integers) and agent names (strings), got {shown(bad[:3])}")
    return items


def check_env_arguments(*, background: Any, horizon_steps: Any, scene_order: Any, terminate_on: Any, render_mode: Any,
                        render_modes: Iterable[str], max_agents: Any, top_k: Any, temperature: Any, reference_top_k: Any,
                        render_size_px: Any, render_radius_m: Any, avoid_collisions: Any, reward: Any, observation: Any,
                        controlled: Any, device: Any = "cpu", shield: Any = (), stop_lines: Any = True,
                        lights: Any = "log", precision: Any = "float32", persistence: Any = DEFAULT_PERSISTENCE) -> dict[str, Any]:
    """The constructor's arguments checked and normalised (see the module docstring), as a dict of
    the same names; :class:`~envs.errors.EnvConfigError` naming the first one that is refused."""
    return {
        "background": _check("background", background, one_of(*BACKGROUNDS), str),
        "horizon_steps": int(_check("horizon_steps", horizon_steps, integer(1, MAX_HORIZON_STEPS, "5,000 s of 0.5 s steps"))),
        "scene_order": _check("scene_order", scene_order, one_of("sequential", "random"), str),
        "terminate_on": _terminate_on(terminate_on),
        "render_mode": _check("render_mode", render_mode, optional(one_of(*render_modes)), str),
        "max_agents": None if max_agents is None else int(_check("max_agents", max_agents,
                                                                 integer(1, MAX_AGENT_SLOTS, "the most agents of a scene"))),
        "top_k": 0 if top_k is None else int(_check("top_k", top_k, integer(0, MAX_VOCAB_SIZE, TOP_K_WHY))),
        "temperature": float(_check("temperature", temperature, temperature_rule)),
        "reference_top_k": None if reference_top_k is None else int(_check("reference_top_k", reference_top_k,
                                                                            integer(1, MAX_VOCAB_SIZE, TOP_K_WHY))),
        "render_size_px": int(_check("render_size_px", render_size_px, integer(16, MAX_RENDER_SIZE_PX, "a 50 MB frame"))),
        "render_radius_m": float(_check("render_radius_m", render_radius_m,
                                        number(MIN_RENDER_RADIUS_M, MAX_RENDER_RADIUS_M, why="wider than any scene"))),
        "avoid_collisions": bool(_check("avoid_collisions", avoid_collisions, flag, bool)),
        "stop_lines": bool(_check("stop_lines", stop_lines, flag, bool)),
        "lights": _check("lights", lights, one_of(*LIGHTS), str),
        "precision": _check("precision", precision, one_of(*PRECISIONS), str),
        "persistence": float(_check("persistence", persistence, persistence_rule)),
        "reward": _reward(reward),
        "observation": _observation(observation),
        "controlled": _controlled(controlled),
        "device": _device(device),
        "shield": shield_checks(shield),
    }


def shield_checks(value: Any) -> tuple[str, ...]:
    """The shield's checks (module docstring); :class:`~envs.errors.EnvConfigError` naming a bad entry."""
    if value is None or value is False:
        return ()
    if value is True:
        return DEFAULT_SHIELD_CHECKS
    names = (value,) if isinstance(value, str) else value
    if not isinstance(names, (list, tuple)):
        raise EnvConfigTypeError(f"shield must be True, False or a list of {list(SHIELD_CHECKS)}, got {shown(value)}")
    bad = [v for v in names if v not in SHIELD_CHECKS]
    if bad:
        raise EnvConfigError(f"shield: unknown check(s) {bad}; known: {list(SHIELD_CHECKS)}")
    return tuple(c for c in SHIELD_CHECKS if c in names)


def shield_option(text: str) -> tuple[str, ...]:
    """A command line's shield, its checks joined with '+' (``"collision+offroad+gap"``; ``""``: none), as
    :func:`shield_checks` gives them: an argparse ``type`` (a bad check is refused by name as the argument's error)."""
    try:
        return shield_checks([c for c in str(text).split("+") if c])
    except EnvConfigError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("shield: ")) from None


def _device(value: Any):
    """``value`` as a torch.device this machine runs on (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a torch.device)."""
    import torch

    name = str(value) if isinstance(value, torch.device) else value
    problem = device_problem(name)
    if problem is not None:
        raise (EnvConfigTypeError if not isinstance(name, str) else EnvConfigError)(f"device: {problem}")
    return torch.device(name)


def check_reset_arguments(seed_value: Any, options: Any, num_scenes: int) -> tuple[int | None, int | None]:
    """(seed as an int or None, the scene index ``options`` asks for or None) of a ``reset(seed, options)``
    of an environment over ``num_scenes`` scenes; :class:`~envs.errors.EnvConfigError` naming what is refused."""
    if seed_value is not None:
        seed_value = int(_check("reset seed", seed_value, seed))
    if options is None:
        return seed_value, None
    if not isinstance(options, Mapping):
        raise EnvConfigTypeError(f"reset options must be None or a dict such as {{'scene_index': 0}}, got {shown(options)}")
    if "scene_index" not in options:
        return seed_value, None
    index = _check("options['scene_index']", options["scene_index"], integer(0, num_scenes - 1, "the last scene"))
    return seed_value, int(index)


__all__ = ["MAX_AGENT_SLOTS", "MAX_HEADWAY_S", "MAX_HORIZON_STEPS", "MAX_REWARD_WEIGHT", "MAX_TTC_S", "MAX_RENDER_SIZE_PX",
           "MAX_RENDER_RADIUS_M", "MIN_RENDER_RADIUS_M", "OBSERVATION_RULES", "REWARD_RULES", "TOP_K_WHY", "check_env_arguments", "check_reset_arguments", "shield_checks",
           "shield_option"]
