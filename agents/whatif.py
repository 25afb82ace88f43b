"""Agents stage, what-if scenarios: edits of a scene or of a running rollout, run against the
unperturbed rollouts with the same seeds, and a table of what changed.

What comes in: a :class:`~smart_marl.scenario.Scenario`, a SMART prior (model, Checkpoint or
checkpoint path) and a :class:`WhatIf` (a list of edits, built in Python or read from a small YAML
file with :func:`load_script`). What goes out: a :class:`WhatIfResult` holding the baseline and
the perturbed rollouts (10 Hz poses of every track, local frame), the comparison table
(:func:`compare`: collisions, minimum distances and speeds of the affected agents, speeds of the
vehicles behind a braking or stalled one and of those approaching an overridden light, sim-agents
realism) and, with :func:`render_comparison`, a side-by-side animation.

In Python::

    from agents.whatif import Brake, Jaywalker, WhatIf, run_whatif
    result = run_whatif("runs/smart/last.json", scene, WhatIf([Brake(agent=1609, at_s=1.0),
                        Jaywalker(relative_to=1630, start=(25, -8), end=(25, 8))]), num_rollouts=8, seed=0)
    print(format_table(result.table)); render_comparison(result, "out/whatif.gif")

Two kinds of edits:

* **scene edits**, applied to the Scenario before the rollout (the prior then sees them in the
  history it conditions on): ``remove`` at ``at_s = 0`` drops the tracks
  (``Scenario.select_tracks``); ``insert``, ``jaywalker`` and ``stalled_vehicle`` with a ``pose``
  add a track whose history is made up (constant velocity back from its first pose; standing
  still for a stalled vehicle or a waiting pedestrian) and whose logged future is the script;
  ``traffic_light`` writes the forced state into the scene's signal states from its onset frame.
* **forced tokens** during the rollout (:meth:`RolloutState.step`'s ``forced_tokens``): ``brake``,
  ``stop``, ``cut_in``, ``follow``, ``stalled_vehicle`` and the motion of inserted agents. Each
  0.5 s step the scripted agent takes the token of its type's vocabulary closest to the next 5
  frames of its target path, looking one token ahead (:func:`agents.scripted.nearest_tokens`), from
  the pose it actually reached; given ``tokens`` are forced as they are. ``remove`` with ``at_s > 0`` takes the agents
  out of the running rollout (:meth:`RolloutState.set_agent_valid`): gone from every later frame
  and from everyone's neighbourhoods.

Traffic lights: the SMART model sees a signal only through the light embedding of the road
pieces of the controlled lane (``smart_marl.model.batch.scene_road`` reads the state at the
scene's *current frame* into ``road_light``; RoadNet embeds it once per scene). An override at
``at_s = 0`` is a scene edit, so RoadNet sees it from the start. An override at a later time
sets the lane's pieces' light codes with ``RolloutState.set_road_light`` at that step (RoadNet
re-runs, the KV cache's map-attention keys and values are re-projected; :func:`override_road_lights`),
so every later step's map attention reads the new light; the steps already taken keep the old one.

Times: ``at_s`` counts seconds after the current frame; an edit takes effect at token step
``round(at_s / 0.5)`` (token steps are 0.5 s). Agents are named by their track id or ``"sdc"``.
Positions are in the scene's source coordinates (``frame: source``, the default), the local frame
(``frame: local``), or the frame of an agent at the current frame (``relative_to: AGENT``: x
forward, y left, heading relative to the agent's).

The YAML format (one file per scenario; see ``examples/whatif/``)::

    name: lead car brakes hard
    description: free text
    edits:
      - {kind: brake, agent: sdc, at_s: 1.0, decel_mps2: 8.0}
      - {kind: remove, agents: [1234, 5678], at_s: 0.0}
      - {kind: insert, type: vehicle, relative_to: sdc, path: [[20, 3.5], [80, 3.5]], speed_mps: 8}
      - {kind: traffic_light, lanes: all, state: stop, at_s: 0.0}

Kinds and their keys: :data:`KINDS` (the dataclasses below document each key).
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence, Union

import numpy as np
import torch

from smart_marl.config_files import integer, number, optional
from smart_marl.errors import SmartMarlError, check_regular_file
from smart_marl.scenario import AgentType, Scenario, SignalState, TrafficLights, Tracks, wrap_angle

from . import scripted

DT_S = 0.1
FRAMES_PER_TOKEN = 5
TOKEN_S = DT_S * FRAMES_PER_TOKEN
AgentRef = Union[int, str]

DEFAULT_SIZE_M = {"vehicle": (4.6, 2.0, 1.6), "pedestrian": (0.8, 0.8, 1.8), "cyclist": (1.8, 0.7, 1.7)}
FOLLOWER_REACH_M = 60.0
"""Vehicles up to this far behind a braking, stopping or stalled vehicle, in its lane (|lateral| <
2 m, heading within 30 degrees), count as its followers."""


class WhatIfError(SmartMarlError, ValueError):
    """A what-if script that cannot be applied: names the file (or ``<python>``), the edit and the problem."""

    def __init__(self, path: str | os.PathLike | None, problem: str, edit: int | None = None):
        self.path = os.fspath(path) if path is not None else "<python>"
        self.problem, self.edit = problem, edit
        where = f"{self.path}: edit {edit}" if edit is not None else self.path
        super().__init__(f"{where}: {problem}")


# ------------------------------------------------------------------------------------ edits
@dataclass
class Placement:
    """How an edit's coordinates are read: ``frame`` "source" (the scene file's coordinates) or
    "local" (the Scenario's local frame), or ``relative_to`` an agent (its pose at the current
    frame: x forward, y left, headings relative to its heading)."""

    frame: str = "source"
    relative_to: AgentRef | None = None


@dataclass
class Remove(Placement):
    """Take ``agents`` out of the scene (``at_s`` 0: before the rollout) or of the rollout from ``at_s`` on."""

    agents: Sequence[AgentRef] = ()
    at_s: float = 0.0


@dataclass
class Insert(Placement):
    """Add an agent of ``type`` (vehicle, pedestrian, cyclist) at the current frame, moving by one of:
    ``trajectory`` [[x, y(, heading)], ...] at 10 Hz from the current frame; ``path`` waypoints
    [[x, y], ...] at ``speed_mps`` after waiting ``wait_s``; or ``tokens`` (ids of its type's
    vocabulary, forced one per 0.5 s step) from ``pose`` [x, y, heading] with history speed
    ``speed_mps``. ``then``: "release" (the prior drives it once the script ends) or "hold"."""

    type: str = "vehicle"
    trajectory: Any = None
    path: Any = None
    speed_mps: float = 0.0
    wait_s: float = 0.0
    tokens: Sequence[int] | None = None
    pose: Sequence[float] | None = None
    id: int | None = None
    size_m: Sequence[float] | None = None
    then: str = "release"


@dataclass
class Brake(Placement):
    """``agent`` brakes at ``decel_mps2`` from ``at_s`` on, straight ahead, to a standstill, and stays."""

    agent: AgentRef = "sdc"
    at_s: float = 0.0
    decel_mps2: float = 8.0


@dataclass
class Stop(Brake):
    """``agent`` comes to a stop at a moderate ``decel_mps2`` from ``at_s`` on and stays stopped."""

    decel_mps2: float = 3.0


@dataclass
class CutIn(Placement):
    """``agent`` changes lane by ``lateral_m`` (left positive) over ``duration_s`` from ``at_s`` on,
    at ``speed_mps`` (default: its speed at the onset); then the prior drives it again."""

    agent: AgentRef = "sdc"
    at_s: float = 0.0
    lateral_m: float = 3.5
    duration_s: float = 2.0
    speed_mps: float | None = None


@dataclass
class Follow(Placement):
    """``agent`` follows ``path`` waypoints at ``speed_mps`` (default: its speed at the onset), or
    takes ``tokens`` one per step, from ``at_s`` on; ``then`` "release" or "hold"."""

    agent: AgentRef = "sdc"
    at_s: float = 0.0
    path: Any = None
    speed_mps: float | None = None
    tokens: Sequence[int] | None = None
    then: str = "release"


@dataclass
class StalledVehicle(Placement):
    """A vehicle that does not move: an existing ``agent`` held where it is for the whole rollout,
    or a new vehicle standing at ``pose`` [x, y, heading] (its history: standing there)."""

    agent: AgentRef | None = None
    pose: Sequence[float] | None = None
    id: int | None = None
    size_m: Sequence[float] | None = None


@dataclass
class Jaywalker(Placement):
    """A pedestrian who stands at ``start`` [x, y], then crosses to ``end`` at ``speed_mps`` after ``wait_s``."""

    start: Sequence[float] = (0.0, 0.0)
    end: Sequence[float] = (0.0, 0.0)
    speed_mps: float = 1.4
    wait_s: float = 0.0
    id: int | None = None


@dataclass
class TrafficLightOverride(Placement):
    """Force the signal of ``lanes`` (feature ids of lanes with a signal, or "all") to ``state``
    (a SignalState name: stop, caution, go, arrow_stop, ...) from ``at_s`` on."""

    lanes: Any = "all"
    state: str = "stop"
    at_s: float = 0.0


KINDS = {"remove": Remove, "insert": Insert, "brake": Brake, "stop": Stop, "cut_in": CutIn, "follow": Follow,
         "stalled_vehicle": StalledVehicle, "jaywalker": Jaywalker, "traffic_light": TrafficLightOverride}
_KIND_OF = {cls: kind for kind, cls in KINDS.items()}

MAX_STEPS = 64
"""Most token steps (0.5 s each: 32 s) a what-if rolls out; ``smart-marl whatif --steps`` refuses more."""


# ---------------------------------------------------------------------------- value checks
# Every key of every kind has a rule (smart_marl.config_files' rules, or the ones below) that a
# script's values must pass when it is loaded, before a scene is read or a rollout runs.
def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_)) and math.isfinite(v)


def _agent_ref(v):
    if isinstance(v, str) and v:
        return None
    return None if isinstance(v, (int, np.integer)) and not isinstance(v, bool) else f"must be a track id or 'sdc', got {v!r}"


def _agent_refs(v):
    return _agent_ref(v) if not isinstance(v, (list, tuple)) else next((f"[{k}] {p}" for k, p in ((k, _agent_ref(x))
                                                                        for k, x in enumerate(v)) if p), None)


def _points(widths: tuple[int, ...], count: int | None = None):
    """A list of points, each a list of ``widths`` finite numbers (all of one width); ``count``: exactly that many."""
    def rule(v):
        rows = v if isinstance(v, (list, tuple)) else None
        if not rows or not all(isinstance(r, (list, tuple)) for r in rows):
            return f"must be a list of [x, y{', heading' if 3 in widths else ''}] points, got {v!r}"
        if len({len(r) for r in rows}) != 1 or len(rows[0]) not in widths:
            return f"must be points of {' or '.join(map(str, widths))} numbers each (a rectangular list), got {v!r}"
        if not all(_is_number(x) for r in rows for x in r):
            return f"must hold finite numbers only, got {v!r}"
        if count is not None and len(rows) != count:
            return f"must be {count} point(s), got {len(rows)}"
        return None
    return rule


def _vector(n: int, positive: bool = False):
    """``n`` finite numbers (positive ones with ``positive``)."""
    def rule(v):
        if not (isinstance(v, (list, tuple)) and len(v) == n and all(_is_number(x) for x in v)) or (positive and min(v) <= 0):
            return f"must be {n} finite{' positive' if positive else ''} numbers, got {v!r}"
        return None
    return rule


def _tokens(v):
    if not isinstance(v, (list, tuple)) or not v or not all(isinstance(t, (int, np.integer)) and not isinstance(t, bool) and t >= 0
                                                             for t in v):
        return f"must be a non-empty list of token ids (integers >= 0), got {v!r}"
    return None


def _choice(*options):
    return lambda v: None if v in options else f"must be one of {', '.join(map(str, options))}, got {v!r}"


def _lanes(v):
    if v == "all" or (isinstance(v, (int, np.integer)) and not isinstance(v, bool)):
        return None
    if isinstance(v, (list, tuple)) and v and all(isinstance(x, (int, np.integer)) and not isinstance(x, bool) for x in v):
        return None
    return f"must be 'all' or lane ids (integers), got {v!r}"


_SIGNAL_NAMES = tuple(s.name.lower() for s in SignalState)
_PLACEMENT = {"frame": _choice("source", "local"), "relative_to": optional(_agent_ref)}
_AT = {"at_s": number(0.0)}
_EDIT_RULES = {
    Remove: {"agents": _agent_refs, **_AT},
    Insert: {"type": _choice("vehicle", "pedestrian", "cyclist"), "trajectory": optional(_points((2, 3))),
             "path": optional(_points((2,))), "speed_mps": number(0.0), "wait_s": number(0.0), "tokens": optional(_tokens),
             "pose": optional(_vector(3)), "id": optional(integer()), "size_m": optional(_vector(3, positive=True)),
             "then": _choice("release", "hold")},
    Brake: {"agent": _agent_ref, **_AT, "decel_mps2": number(0.0, low_open=True)},
    CutIn: {"agent": _agent_ref, **_AT, "lateral_m": number(), "duration_s": number(0.0, low_open=True),
            "speed_mps": optional(number(0.0))},
    Follow: {"agent": _agent_ref, **_AT, "path": optional(_points((2,))), "speed_mps": optional(number(0.0)),
             "tokens": optional(_tokens), "then": _choice("release", "hold")},
    StalledVehicle: {"agent": optional(_agent_ref), "pose": optional(_vector(3)), "id": optional(integer()),
                     "size_m": optional(_vector(3, positive=True))},
    Jaywalker: {"start": _vector(2), "end": _vector(2), "speed_mps": number(0.0, low_open=True), "wait_s": number(0.0),
                "id": optional(integer())},
    TrafficLightOverride: {"lanes": _lanes, "state": lambda v: _choice(*_SIGNAL_NAMES)(str(v).lower()), **_AT},
}
_EDIT_RULES[Stop] = _EDIT_RULES[Brake]


def check_edit(edit, path=None, index: int | None = None) -> None:
    """:class:`WhatIfError` naming the file, the edit and the key whose value is not what the kind
    takes (``at_s: soon``, a ragged path, ``decel_mps2: .inf``...)."""
    kind = _KIND_OF.get(type(edit))
    if kind is None:
        raise WhatIfError(path, f"not a what-if edit: {type(edit).__name__}", index)
    for key, rule in {**_PLACEMENT, **_EDIT_RULES[type(edit)]}.items():
        problem = rule(getattr(edit, key))
        if problem:
            raise WhatIfError(path, f"{kind}: {key} {problem}", index)


@dataclass
class WhatIf:
    """A what-if scenario: a name, a description and a list of edits (applied in order)."""

    edits: list
    name: str = "what-if"
    description: str = ""
    path: str | None = None  # the script file, for error messages

    @classmethod
    def from_dict(cls, data: dict, path: str | None = None) -> "WhatIf":
        if not isinstance(data, dict) or "edits" not in data:
            raise WhatIfError(path, "a what-if script is a mapping with an 'edits' list (and optional name, description)")
        unknown = set(data) - {"name", "description", "edits"}
        if unknown:
            raise WhatIfError(path, f"unknown top-level keys {sorted(unknown)} (expected name, description, edits)")
        edits = data["edits"]
        if not isinstance(edits, list) or not edits:
            raise WhatIfError(path, "'edits' must be a non-empty list")
        out = []
        for i, e in enumerate(edits):
            if not isinstance(e, dict) or "kind" not in e:
                raise WhatIfError(path, "each edit is a mapping with a 'kind'", i)
            kind = e["kind"]
            if kind not in KINDS:
                raise WhatIfError(path, f"unknown kind {kind!r} (one of {', '.join(KINDS)})", i)
            cls_ = KINDS[kind]
            names = {f.name for f in dataclasses.fields(cls_)}
            bad = set(e) - names - {"kind"}
            if bad:
                raise WhatIfError(path, f"{kind}: unknown keys {sorted(bad)} (allowed: {', '.join(sorted(names))})", i)
            edit = cls_(**{k: v for k, v in e.items() if k != "kind"})
            check_edit(edit, path, i)
            out.append(edit)
        return cls(edits=out, name=str(data.get("name", Path(path).stem if path else "what-if")),
                   description=str(data.get("description", "")), path=path)


def load_script(path: str | os.PathLike) -> WhatIf:
    """Read a what-if YAML (or JSON) script."""
    p = Path(path)
    if not p.exists():
        raise WhatIfError(p, "no such script file")
    check_regular_file(p, lambda name, problem: WhatIfError(name, problem))
    try:
        import yaml
    except ImportError as exc:  # pragma: no cover - pyyaml is in the whatif extra
        raise WhatIfError(p, "reading YAML scripts needs pyyaml (pip install 'smart-marl[whatif]')") from exc
    try:
        data = yaml.safe_load(p.read_text())
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as exc:
        raise WhatIfError(p, f"not valid YAML: {type(exc).__name__}: {exc}") from exc
    return WhatIf.from_dict(data, str(p))


# ------------------------------------------------------------------------------ preparation
@dataclass
class _Script:
    """One agent's forced tokens: from ``start_step`` on, toward ``path`` (computed at the onset by
    ``make_path(pose [G, 3], speed [G]) -> [G, T, 3]``, frames after the onset) or given ``tokens``."""

    track_id: int
    start_step: int
    make_path: Any = None
    tokens: list | None = None
    then: str = "hold"
    end_step: int | None = None  # steps after the onset it lasts; None: until the path (or the tokens) ends, then ``then``
    path: np.ndarray | None = None


@dataclass
class Prepared:
    """A what-if applied to a scene: the edited scene and what the rollout must do step by step."""

    scene: Scenario
    scripts: list[_Script]
    removals: list[tuple[int, list[int]]]  # (step, track ids) removed from the running rollout
    lights: list[tuple[int, np.ndarray, int]]  # (step, lane indices into traffic_lights, SignalState)
    affected: dict[int, str]  # track id -> what happened to it ("brake", "inserted", "removed", ...)
    followers: dict[int, list[int]]  # braking/stopping/stalled track id -> track ids of the vehicles behind it
    onset_step: dict[int, int]  # affected track id -> step its edit starts
    approaching: list[tuple[int, list[int]]] = dataclasses.field(default_factory=list)  # (step, vehicles heading for an overridden light)


def _step_of(at_s: float, path, i) -> int:
    """The token step an edit at ``at_s`` seconds (checked finite and >= 0 by :func:`check_edit`) starts at."""
    return int(round(float(at_s) / TOKEN_S))


def _track_index(scene: Scenario, ref: AgentRef, path, i) -> int:
    if isinstance(ref, str) and ref.lower() == "sdc":
        if scene.sdc_index < 0:
            raise WhatIfError(path, "agent 'sdc': this scene has no self-driving car (or it was removed)", i)
        return int(scene.sdc_index)
    if isinstance(ref, str) and "_" in ref:  # "vehicle_1234" names, as the env uses
        ref = ref.rsplit("_", 1)[1]
    try:
        tid = int(ref)
    except (TypeError, ValueError):
        raise WhatIfError(path, f"agent {ref!r} is neither a track id nor 'sdc'", i) from None
    hit = np.flatnonzero(scene.tracks.ids == tid)
    if not len(hit):
        raise WhatIfError(path, f"agent {tid} is not a track of scene {scene.scenario_id} (or it was removed)", i)
    return int(hit[0])


def _current_pose(scene: Scenario, index: int) -> np.ndarray:
    tr, cf = scene.tracks, scene.current_frame
    return np.array([tr.position[index, cf, 0], tr.position[index, cf, 1], tr.heading[index, cf]], np.float64)


def _to_local(scene: Scenario, edit: Placement, points, path, i) -> np.ndarray:
    """Points [K, 2] or poses [K, 3] of an edit -> poses [K, 3] in the scene's local frame (heading 0
    in the edit's frame when only points are given)."""
    a = np.asarray(points, np.float64)
    if a.ndim == 1:
        a = a[None]
    if a.ndim != 2 or a.shape[1] not in (2, 3) or not np.isfinite(a).all():
        raise WhatIfError(path, f"expected a list of [x, y] or [x, y, heading] points, got shape {a.shape}", i)
    out = np.zeros((len(a), 3))
    if edit.relative_to is not None:
        o = _current_pose(scene, _track_index(scene, edit.relative_to, path, i))
        c, s = math.cos(o[2]), math.sin(o[2])
        out[:, 0] = o[0] + c * a[:, 0] - s * a[:, 1]
        out[:, 1] = o[1] + s * a[:, 0] + c * a[:, 1]
        out[:, 2] = o[2] + (a[:, 2] if a.shape[1] == 3 else 0.0)
    elif edit.frame == "local":
        out[:, :2] = a[:, :2]
        out[:, 2] = a[:, 2] if a.shape[1] == 3 else 0.0
    elif edit.frame == "source":
        out[:, :2] = scene.frame.from_source(a[:, :2])
        out[:, 2] = (a[:, 2] - scene.frame.heading) if a.shape[1] == 3 else 0.0
    else:
        raise WhatIfError(path, f"frame must be 'source' or 'local', got {edit.frame!r}", i)
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def _agent_type(name: str, path, i) -> AgentType:
    key = str(name).lower()
    if key not in DEFAULT_SIZE_M:
        raise WhatIfError(path, f"type must be vehicle, pedestrian or cyclist, got {name!r}", i)
    return AgentType[key.upper()]


def _add_track(scene: Scenario, track_id: int, agent_type: AgentType, future: np.ndarray, size_m, history_speed_mps: float) -> Scenario:
    """A new track: ``future`` [F, 3] poses for frames current, current + 1, ... (held after its end);
    history at ``history_speed_mps`` straight back along the first heading."""
    tr, cf, t = scene.tracks, scene.current_frame, scene.num_frames
    pose = np.zeros((t, 3))
    n_future = t - cf
    fut = future[:n_future]
    if len(fut) < n_future:
        fut = np.concatenate([fut, np.repeat(fut[-1:], n_future - len(fut), 0)], 0)
    pose[cf:] = fut
    back = DT_S * np.arange(cf, 0, -1)  # seconds before the current frame for frames 0..cf-1
    h0 = future[0, 2]
    pose[:cf, 0] = future[0, 0] - history_speed_mps * back * math.cos(h0)
    pose[:cf, 1] = future[0, 1] - history_speed_mps * back * math.sin(h0)
    pose[:cf, 2] = h0
    vel = np.gradient(pose[:, :2], DT_S, axis=0) if t > 1 else np.zeros((t, 2))
    cur_valid = tr.valid[:, cf]
    z = float(np.median(tr.position[cur_valid, cf, 2])) if cur_valid.any() else 0.0
    size = np.asarray(size_m, np.float32)
    new = Tracks(
        ids=np.concatenate([tr.ids, [track_id]]), types=np.concatenate([tr.types, [int(agent_type)]]),
        position=np.concatenate([tr.position, np.concatenate([pose[:, :2], np.full((t, 1), z)], 1)[None].astype(np.float32)]),
        heading=np.concatenate([tr.heading, pose[None, :, 2].astype(np.float32)]),
        velocity=np.concatenate([tr.velocity, vel[None].astype(np.float32)]),
        size=np.concatenate([tr.size, np.broadcast_to(size, (1, t, 3)).astype(np.float32)]),
        valid=np.concatenate([tr.valid, np.ones((1, t), bool)]),
    )
    return dataclasses.replace(scene, tracks=new)


def _place_tokens(vocab_type, pose: np.ndarray, tokens: Sequence[int]) -> np.ndarray:
    """Poses [1 + 5 * len(tokens), 3] of ``tokens`` placed one after another from ``pose``."""
    from smart_marl.tokens import compose_poses

    out, cur = [pose], pose
    for tok in tokens:
        placed = compose_poses(cur, vocab_type.poses[int(tok), 1:].astype(np.float64))
        out.extend(placed)
        cur = placed[-1]
    return np.asarray(out)


def prepare(scene: Scenario, whatif: WhatIf, motion_vocab=None) -> Prepared:
    """Apply a what-if's scene edits and list its per-step actions (see the module docstring).
    ``motion_vocab`` is needed only for inserted agents driven by ``tokens``."""
    path = whatif.path
    scripts, removals, lights = [], [], []
    affected, followers, onset, approaching = {}, {}, {}, []
    next_id = int(scene.tracks.ids.max()) + 1 if scene.num_tracks else 1
    horizon = scene.num_frames - scene.current_frame  # frames of script a new track stores
    for i, e in enumerate(whatif.edits):
        check_edit(e, path, i)
        kind = _KIND_OF[type(e)]
        if kind == "remove":
            idx = [_track_index(scene, a, path, i) for a in (e.agents if isinstance(e.agents, (list, tuple)) else [e.agents])]
            ids = [int(scene.tracks.ids[k]) for k in idx]
            step = _step_of(e.at_s, path, i)
            for tid in ids:
                affected[tid], onset[tid] = "removed", step
            if step == 0:
                scene = scene.select_tracks(np.setdiff1d(np.arange(scene.num_tracks), idx))
            else:
                removals.append((step, ids))
        elif kind in ("brake", "stop"):
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            a = float(e.decel_mps2)
            scripts.append(_Script(tid, step, make_path=lambda pose, v, a=a, n=horizon: scripted.brake_path(pose, v, a, n), then="hold"))
            affected[tid], onset[tid] = kind, step
            followers[tid] = _followers(scene, k)
        elif kind == "cut_in":
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            lat, dur, spd = float(e.lateral_m), float(e.duration_s), e.speed_mps
            n = int(math.ceil(dur / DT_S))
            n = FRAMES_PER_TOKEN * int(math.ceil(n / FRAMES_PER_TOKEN))
            scripts.append(_Script(tid, step, then="release", make_path=lambda pose, v, lat=lat, dur=dur, spd=spd, n=n:
                                   scripted.cut_in_path(pose, v if spd is None else np.full_like(v, spd), lat, dur, n)))
            affected[tid], onset[tid] = "cut_in", step
        elif kind == "follow":
            k = _track_index(scene, e.agent, path, i)
            tid = int(scene.tracks.ids[k])
            step = _step_of(e.at_s, path, i)
            if (e.path is None) == (e.tokens is None):
                raise WhatIfError(path, "follow needs exactly one of 'path' or 'tokens'", i)
            if e.tokens is not None:
                _check_tokens(scene, k, e.tokens, motion_vocab, path, i)
                scripts.append(_Script(tid, step, tokens=[int(t) for t in e.tokens], then=_then(e.then, path, i)))
            else:
                wp = _to_local(scene, e, e.path, path, i)[:, :2]
                spd = e.speed_mps

                def make(pose, v, wp=wp, spd=spd, n=horizon):
                    speed = float(np.mean(v)) if spd is None else float(spd)
                    p = scripted.polyline_path(wp, speed, n, first_frame=1)
                    return np.repeat(p[None], len(pose), 0)
                scripts.append(_Script(tid, step, make_path=make, then=_then(e.then, path, i)))
            affected[tid], onset[tid] = "follow", step
        elif kind in ("insert", "jaywalker", "stalled_vehicle"):
            if kind == "stalled_vehicle" and e.agent is not None:
                if e.pose is not None:
                    raise WhatIfError(path, "stalled_vehicle takes either 'agent' or 'pose', not both", i)
                k = _track_index(scene, e.agent, path, i)
                tid = int(scene.tracks.ids[k])
                scripts.append(_Script(tid, 0, make_path=lambda pose, v, n=horizon: scripted.hold_path(pose, n), then="hold"))
                affected[tid], onset[tid] = "stalled", 0
                followers[tid] = _followers(scene, k)
                continue
            tid = int(e.id) if e.id is not None else next_id
            if np.isin(tid, scene.tracks.ids):
                raise WhatIfError(path, f"id {tid} is already a track of the scene", i)
            next_id = max(next_id, tid) + 1
            if kind == "jaywalker":
                atype, then = AgentType.PEDESTRIAN, "release"
                wp = _to_local(scene, e, [e.start, e.end], path, i)[:, :2]
                future = scripted.polyline_path(wp, float(e.speed_mps), horizon, wait_s=float(e.wait_s))
                hist_speed, size, tokens = 0.0, DEFAULT_SIZE_M["pedestrian"], None
            elif kind == "stalled_vehicle":
                if e.pose is None:
                    raise WhatIfError(path, "stalled_vehicle needs 'agent' (an existing vehicle) or 'pose' [x, y, heading]", i)
                atype, then = AgentType.VEHICLE, "hold"
                future = _to_local(scene, e, [list(e.pose)], path, i)[:1]
                hist_speed, size, tokens = 0.0, e.size_m or DEFAULT_SIZE_M["vehicle"], None
            else:
                atype = _agent_type(e.type, path, i)
                then = _then(e.then, path, i)
                size = e.size_m or DEFAULT_SIZE_M[atype.name.lower()]
                given = [x is not None for x in (e.trajectory, e.path, e.tokens)]
                if sum(given) != 1:
                    raise WhatIfError(path, "insert needs exactly one of 'trajectory', 'path' or 'tokens'", i)
                tokens = None
                if e.trajectory is not None:
                    future = _to_local(scene, e, e.trajectory, path, i)
                    if np.asarray(e.trajectory).shape[-1] == 2:  # headings from the motion
                        d = np.diff(future[:, :2], axis=0)
                        h = np.arctan2(d[:, 1], d[:, 0]) if len(d) else np.zeros(0)
                        future[:, 2] = np.concatenate([h[:1], h]) if len(h) else 0.0
                    hist_speed = float(np.linalg.norm(future[1, :2] - future[0, :2]) / DT_S) if len(future) > 1 else 0.0
                elif e.path is not None:
                    wp = _to_local(scene, e, e.path, path, i)[:, :2]
                    future = scripted.polyline_path(wp, float(e.speed_mps), horizon, wait_s=float(e.wait_s))
                    hist_speed = 0.0 if e.wait_s > 0 else float(e.speed_mps)
                else:
                    if motion_vocab is None:
                        raise WhatIfError(path, "insert with 'tokens' needs the prior's motion vocabulary", i)
                    if e.pose is None:
                        raise WhatIfError(path, "insert with 'tokens' needs 'pose' [x, y, heading]", i)
                    tokens = [int(t) for t in e.tokens]
                    vt = motion_vocab[atype]
                    if any(t < 0 or t >= vt.size for t in tokens):
                        raise WhatIfError(path, f"tokens outside the {atype.name.lower()} vocabulary [0, {vt.size})", i)
                    start = _to_local(scene, e, [list(e.pose)], path, i)[0]
                    future = _place_tokens(vt, start, tokens)
                    hist_speed = float(e.speed_mps)
            if len(np.asarray(size).reshape(-1)) != 3:
                raise WhatIfError(path, f"size_m must be [length, width, height], got {size}", i)
            scene = _add_track(scene, tid, atype, future, size, hist_speed)
            if tokens is not None:
                scripts.append(_Script(tid, 0, tokens=tokens, then=then))
            else:
                fut = future[1:] if len(future) > 1 else future
                end_step = None
                if then == "release":  # released when its motion ends; the target runs on past the end (no sudden stop)
                    moving = _moving_frames(future)
                    end_step = int(math.ceil(moving / FRAMES_PER_TOKEN))
                    fut = _extrapolate(future[: moving + 1], horizon + 2 * FRAMES_PER_TOKEN)[1:]
                scripts.append(_Script(tid, 0, then=then, end_step=end_step, make_path=lambda pose, v, fut=fut, n=horizon - 1:
                                       np.repeat(_pad_hold(fut, n + 2 * FRAMES_PER_TOKEN)[None], len(pose), 0)))
            affected[tid], onset[tid] = {"insert": "inserted", "jaywalker": "jaywalker", "stalled_vehicle": "stalled"}[kind], 0
            if kind == "stalled_vehicle":
                followers[tid] = _followers(scene, scene.num_tracks - 1)
        elif kind == "traffic_light":
            step = _step_of(e.at_s, path, i)
            tl = scene.traffic_lights
            if not len(tl.lane_ids):
                raise WhatIfError(path, f"scene {scene.scenario_id} has no traffic lights to override", i)
            try:
                code = int(SignalState[str(e.state).upper()])
            except KeyError:
                raise WhatIfError(path, f"state must be one of {', '.join(s.name.lower() for s in SignalState)}, got {e.state!r}", i) from None
            if isinstance(e.lanes, str) and e.lanes == "all":
                lanes = np.arange(len(tl.lane_ids))
            else:
                want = np.asarray(e.lanes if isinstance(e.lanes, (list, tuple)) else [e.lanes], np.int64)
                missing = want[~np.isin(want, tl.lane_ids)]
                if len(missing):
                    raise WhatIfError(path, f"lanes {missing.tolist()} have no traffic light in this scene (lanes with one: "
                                            f"{tl.lane_ids[:20].tolist()}{'...' if len(tl.lane_ids) > 20 else ''})", i)
                lanes = np.flatnonzero(np.isin(tl.lane_ids, want))
            first = scene.current_frame + FRAMES_PER_TOKEN * step
            states, present = tl.states.copy(), tl.present.copy()
            states[first:, lanes] = code
            present[first:, lanes] = True
            scene = dataclasses.replace(scene, traffic_lights=TrafficLights(tl.lane_ids, states, present, tl.stop_points))
            if step > 0:
                lights.append((step, lanes, code))
            approaching.append((step, _approaching(scene, tl.stop_points[lanes, :2].astype(np.float64))))
        else:  # pragma: no cover
            raise WhatIfError(path, f"kind {kind} not handled", i)
    return Prepared(scene=scene, scripts=scripts, removals=removals, lights=lights, affected=affected, followers=followers,
                    onset_step=onset, approaching=approaching)


def _check_tokens(scene: Scenario, index: int, tokens, motion_vocab, path, i) -> None:
    """Tokens an existing agent is to take must be in its type's vocabulary (checked before any rollout)."""
    atype = AgentType(int(scene.tracks.types[index]))
    if atype == AgentType.OTHER:
        raise WhatIfError(path, f"agent {int(scene.tracks.ids[index])} is of type other, which has no motion tokens", i)
    if motion_vocab is not None:
        size = motion_vocab[atype].size
        bad = [int(t) for t in tokens if not 0 <= int(t) < size]
        if bad:
            raise WhatIfError(path, f"tokens {bad[:5]} are outside the {atype.name.lower()} vocabulary [0, {size})", i)


def _then(value: str, path, i) -> str:
    if value not in ("hold", "release"):
        raise WhatIfError(path, f"then must be 'hold' or 'release', got {value!r}", i)
    return value


def _pad_hold(poses: np.ndarray, n: int) -> np.ndarray:
    return poses[:n] if len(poses) >= n else np.concatenate([poses, np.repeat(poses[-1:], n - len(poses), 0)], 0)


def _extrapolate(poses: np.ndarray, n: int) -> np.ndarray:
    """``poses`` [K, 3] continued at their last velocity to ``n`` poses."""
    if len(poses) >= n:
        return poses[:n]
    step = poses[-1] - poses[-2] if len(poses) > 1 else np.zeros(3)
    step[2] = 0.0
    extra = poses[-1] + step * np.arange(1, n - len(poses) + 1)[:, None]
    return np.concatenate([poses, extra], 0)


def _moving_frames(future: np.ndarray) -> int:
    """Frames after the current one until the scripted motion has reached its end."""
    d = np.linalg.norm(np.diff(future[:, :2], axis=0), axis=1)
    moving = np.flatnonzero(d > 1e-6)
    return int(moving[-1] + 1) if len(moving) else 0


APPROACH_REACH_M = 40.0
"""Vehicles with an overridden light's stop point up to this far ahead (|lateral| < 3 m) approach it."""


def _approaching(scene: Scenario, stop_points: np.ndarray) -> list[int]:
    """Vehicles at the current frame with one of ``stop_points`` [L, 2] ahead of them, in their lane."""
    tr, cf = scene.tracks, scene.current_frame
    xy = tr.position[:, cf, :2].astype(np.float64)
    h = tr.heading[:, cf].astype(np.float64)
    d = stop_points[None] - xy[:, None]  # (N, L, 2)
    c, s = np.cos(h)[:, None], np.sin(h)[:, None]
    lon, lat = c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]
    ahead = ((lon > 0) & (lon < APPROACH_REACH_M) & (np.abs(lat) < 3.0)).any(1)
    sel = ahead & tr.valid[:, cf] & (tr.types == AgentType.VEHICLE)
    return [int(t) for t in tr.ids[sel]]


def _followers(scene: Scenario, index: int) -> list[int]:
    """Vehicles behind track ``index`` at the current frame, in its lane (see :data:`FOLLOWER_REACH_M`)."""
    tr, cf = scene.tracks, scene.current_frame
    o = _current_pose(scene, index)
    c, s = math.cos(o[2]), math.sin(o[2])
    d = tr.position[:, cf, :2].astype(np.float64) - o[:2]
    lon, lat = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    dh = np.abs(wrap_angle(tr.heading[:, cf].astype(np.float64) - o[2]))
    sel = tr.valid[:, cf] & (tr.types == AgentType.VEHICLE) & (lon < -1.0) & (lon > -FOLLOWER_REACH_M) & (np.abs(lat) < 2.0) & (dh < math.radians(30))
    sel[index] = False
    order = np.argsort(-lon[sel])  # nearest first
    return [int(x) for x in tr.ids[sel][order]]


# ---------------------------------------------------------------------------------- rollout
@dataclass
class SimRollouts:
    """R rollouts of one scene: every track of ``scene`` over ``T`` future frames (local frame)."""

    scene: Scenario
    poses: np.ndarray  # [R, A, T, 3] x, y, heading (NaN where absent)
    present: np.ndarray  # [R, A, T] bool: simulated (driven by the prior or a script) on that frame
    scripted: np.ndarray  # [R, A, T] bool: moved by a forced token on that frame
    light_states: np.ndarray  # [T, L] SignalState per future frame (the scene's, after overrides)
    light_present: np.ndarray  # [T, L] bool

    @property
    def track_ids(self) -> np.ndarray:
        return self.scene.tracks.ids

    def speed_mps(self) -> np.ndarray:
        """[R, A, T] speed over each 0.1 s frame (the first from the current pose), NaN where absent."""
        cf = self.scene.current_frame
        tr = self.scene.tracks
        start = np.concatenate([tr.position[:, cf, :2], tr.heading[:, cf, None]], -1).astype(np.float64)
        p = np.concatenate([np.broadcast_to(start[None, :, None], (self.poses.shape[0], len(start), 1, 3)), self.poses], 2)
        return np.linalg.norm(np.diff(p[..., :2], axis=2), axis=-1) / DT_S


def override_road_lights(state, piece_light_index: np.ndarray, lane_indices: np.ndarray, code: int) -> None:
    """Force the light state of the road pieces of ``lane_indices`` (indices into the scene's
    ``traffic_lights``) to ``code`` in a running :class:`~smart_marl.rollout.RolloutState` of one
    scene (:meth:`~smart_marl.rollout.RolloutState.set_road_light`: RoadNet re-runs and the KV
    cache's road keys and values are re-projected), so every later step's map attention sees it.
    ``piece_light_index`` [R]: each road piece's traffic-light lane index (``road_pieces(...).traffic_light_index``,
    the same pieces in the same order as the state's road tokens)."""
    sel = torch.from_numpy(np.isin(piece_light_index, lane_indices) & (piece_light_index >= 0)).to(state.device)
    light = state.road_light.clone()
    light[:, : len(sel)][:, sel] = int(code)
    state.set_road_light(light)


def simulate(model, vocab, prepared: Prepared, num_rollouts: int, seed: int, num_steps: int = 16, top_k: int = 5,
             temperature: float = 1.0, device="cpu", scripted_on: bool = True) -> SimRollouts:
    """Roll out ``prepared.scene`` with its per-step actions (``scripted_on=False``: the scene as
    it is, no forced tokens, removals or light changes)."""
    from smart_marl.rollout import RolloutState
    from smart_marl.tokens import road_pieces

    scene = prepared.scene
    state = RolloutState.start(model, scene, num_rollouts=num_rollouts, seed=seed, top_k=top_k, temperature=temperature,
                               device=device, motion_vocab=vocab)
    g, n = state.num_groups, state.num_slots
    ids = state.agent_ids[0].cpu().numpy()
    slot_of = {int(t): k for k, t in enumerate(ids) if t >= 0 and bool(state.simulated[0, k])}
    tr, cf = scene.tracks, scene.current_frame
    ti = state.track_index[0].cpu().numpy()
    speed = np.zeros((g, n))
    ok = ti >= 0
    speed[:, ok] = np.linalg.norm(tr.velocity[ti[ok], cf].astype(np.float64), axis=-1)[None]
    scripts = [dataclasses.replace(s, path=None) for s in prepared.scripts] if scripted_on else []
    for s in scripts:
        if s.track_id not in slot_of:
            raise WhatIfError(None, f"agent {s.track_id} is not simulated in scene {scene.scenario_id} (not valid at the current frame, or not a vehicle, pedestrian or cyclist)")
    piece_tl = road_pieces(scene.road_map, scene.traffic_lights).traffic_light_index if (scripted_on and prepared.lights) else None
    a_count, t_frames = scene.num_tracks, FRAMES_PER_TOKEN * num_steps
    poses = np.full((g, a_count, t_frames, 3), np.nan)
    present = np.zeros((g, a_count, t_frames), bool)
    forced_mask = np.zeros((g, a_count, t_frames), bool)
    for k in range(num_steps):
        if scripted_on:
            for step, gone in prepared.removals:
                if step == k:
                    state.set_agent_valid(~torch.from_numpy(np.isin(state.agent_ids.cpu().numpy(), gone)))
            for step, lanes, code in prepared.lights:
                if step == k:
                    override_road_lights(state, piece_tl, lanes, code)
        forced = torch.full((g, n), -1, dtype=torch.long)
        for s in scripts:
            slot = slot_of[s.track_id]
            j = k - s.start_step
            if j < 0 or (s.end_step is not None and j >= s.end_step):
                continue
            if not bool(state.simulated[0, slot]):
                continue
            atype = int(state.agent_type[0, slot])
            if s.tokens is not None:
                if j < len(s.tokens):
                    forced[:, slot] = s.tokens[j]
                elif s.then == "hold":
                    forced[:, slot] = _nearest(state, atype, slot, scripted.hold_path(state.current_pose[:, slot].cpu().numpy(), 2 * FRAMES_PER_TOKEN))
                continue
            if s.path is None:
                onset_pose = state.current_pose[:, slot].cpu().numpy().astype(np.float64)
                s.path = s.make_path(onset_pose, speed[:, slot])
                if s.then == "release" and s.end_step is None:  # released once the scripted motion has ended
                    moving = max(_moving_frames(np.concatenate([onset_pose[r, None], s.path[r]])) for r in range(len(onset_pose)))
                    s.end_step = int(math.ceil(moving / FRAMES_PER_TOKEN))
            lo = FRAMES_PER_TOKEN * j
            if lo >= s.path.shape[1]:
                if s.then != "hold":
                    continue
                s.path = np.concatenate([s.path, np.repeat(s.path[:, -1:], lo + FRAMES_PER_TOKEN - s.path.shape[1], 1)], 1)
            seg = s.path[:, lo: lo + 2 * FRAMES_PER_TOKEN]  # this token's 5 frames and the next one's (look-ahead)
            if seg.shape[1] < 2 * FRAMES_PER_TOKEN:
                seg = np.concatenate([seg, np.repeat(seg[:, -1:], 2 * FRAMES_PER_TOKEN - seg.shape[1], 1)], 1)
            forced[:, slot] = _nearest(state, atype, slot, seg)
        out = state.step(forced)
        p = out.poses.cpu().numpy().astype(np.float64)  # (G, N, 5, 3)
        sim = out.simulated.cpu().numpy()
        fr = slice(FRAMES_PER_TOKEN * k, FRAMES_PER_TOKEN * (k + 1))
        for slot in np.flatnonzero(ti >= 0):
            a = ti[slot]
            on = sim[:, slot]
            poses[on, a, fr] = p[on, slot]
            present[on, a, fr] = True
            forced_mask[on, a, fr] = (forced[:, slot].numpy() >= 0)[on, None]
        speed = np.linalg.norm(p[:, :, -1, :2] - p[:, :, -2, :2], axis=-1) / DT_S
    tl = scene.traffic_lights
    fut = slice(cf + 1, cf + 1 + t_frames)
    ls, lp = tl.states[fut], tl.present[fut]
    if len(ls) < t_frames:  # a rollout past the scene's end: lights held
        pad = t_frames - len(ls)
        ls = np.concatenate([ls, np.repeat(tl.states[-1:], pad, 0)]) if len(tl.lane_ids) else np.zeros((t_frames, 0), np.int8)
        lp = np.concatenate([lp, np.repeat(tl.present[-1:], pad, 0)]) if len(tl.lane_ids) else np.zeros((t_frames, 0), bool)
    return SimRollouts(scene=scene, poses=poses, present=present, scripted=forced_mask, light_states=ls, light_present=lp)


def _nearest(state, atype: int, slot: int, targets: np.ndarray) -> torch.Tensor:
    size = int(state.vocab_sizes[atype])
    weight = scripted.HEADING_WEIGHT_M_PER_RAD if atype != int(AgentType.PEDESTRIAN) else scripted.PEDESTRIAN_HEADING_WEIGHT_M_PER_RAD
    return scripted.nearest_tokens(state.token_poses[atype].cpu(), size, state.current_pose[:, slot].cpu(),
                                   torch.from_numpy(np.asarray(targets, np.float64)), weight).to(torch.long)


# ------------------------------------------------------------------------------- comparison
@dataclass
class WhatIfResult:
    whatif: WhatIf
    prepared: Prepared
    baseline: SimRollouts
    perturbed: SimRollouts
    table: list[dict]


def resolve_prior(checkpoint=None, device="cpu"):
    """(model, motion vocabulary) from a checkpoint path, a model or Checkpoint, or — when None —
    the package's embedded prior (:func:`smart_marl.model.checkpoint.embedded_checkpoint_path`)."""
    from smart_marl.model.checkpoint import embedded_checkpoint_path
    from smart_marl.rollout import resolve_model

    return resolve_model(embedded_checkpoint_path() if checkpoint is None else checkpoint, device)


def run_whatif(prior, scene: Scenario, whatif: WhatIf, num_rollouts: int = 8, seed: int = 0, num_steps: int = 16,
               top_k: int = 5, temperature: float = 1.0, device="cpu", realism: bool = True) -> WhatIfResult:
    """The what-if and its unperturbed baseline (same seed, same number of rollouts) on one scene,
    and the comparison table (:func:`compare`). ``prior``: a SMART model, Checkpoint, checkpoint
    path, or None for the embedded prior."""
    if isinstance(num_steps, bool) or not isinstance(num_steps, int) or not 1 <= num_steps <= MAX_STEPS:
        raise WhatIfError(whatif.path, f"num_steps must be 1..{MAX_STEPS} token steps of 0.5 s, got {num_steps!r}")
    model, vocab = resolve_prior(prior, device)
    prepared = prepare(scene, whatif, vocab)  # every edit checked against the scene and the vocabulary before any rollout
    base_prep = Prepared(scene=scene, scripts=[], removals=[], lights=[], affected={}, followers={}, onset_step={})
    baseline = simulate(model, vocab, base_prep, num_rollouts, seed, num_steps, top_k, temperature, device, scripted_on=False)
    perturbed = simulate(model, vocab, prepared, num_rollouts, seed, num_steps, top_k, temperature, device)
    return WhatIfResult(whatif, prepared, baseline, perturbed, compare(baseline, perturbed, prepared, realism=realism))


def _box_size(scene: Scenario) -> np.ndarray:
    return scene.tracks.box_size()[:, :2].astype(np.float64)


def agent_min_distance_m(sim: SimRollouts, index: int) -> np.ndarray:
    """[R] minimum rounded-box distance (m, negative = overlap) between track ``index`` and any
    other present track over the rollout's frames (NaN when it is never present with another)."""
    from smart_marl.geometry import rounded_box_signed_distance

    size = _box_size(sim.scene)
    r, a, t, _ = sim.poses.shape
    me, others = sim.poses[:, index], sim.poses  # (R, T, 3), (R, A, T, 3)
    both = sim.present[:, index, None] & sim.present
    both[:, index] = False
    centre = np.linalg.norm(others[..., :2] - me[:, None, :, :2], axis=-1)
    centre = np.where(both, centre, np.inf)
    near = centre < 30.0  # box distance only for the near pairs
    d = np.where(both, centre, np.nan)  # far pairs: the centre distance is a good enough upper bound
    rr, aa, tt = np.nonzero(near)
    if len(rr):
        d[rr, aa, tt] = rounded_box_signed_distance(me[rr, tt, 0], me[rr, tt, 1], size[index, 0], size[index, 1], me[rr, tt, 2],
                                                    others[rr, aa, tt, 0], others[rr, aa, tt, 1], size[aa, 0], size[aa, 1], others[rr, aa, tt, 2])
    with np.errstate(all="ignore"):
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmin(d.reshape(r, -1), axis=1)


def colliding_agents(sim: SimRollouts) -> np.ndarray:
    """[R, A] bool: the track overlaps another present track (rounded boxes) on some frame."""
    from smart_marl.geometry import box_distance_bounds, rounded_box_signed_distance

    size = _box_size(sim.scene)
    r, a, t, _ = sim.poses.shape
    out = np.zeros((r, a), bool)
    xy = np.where(sim.present[..., None], sim.poses[..., :2], 1e9 + np.arange(a)[None, :, None, None] * 1e3)
    d = np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1)  # (R, A, A, T)
    lo, _ = box_distance_bounds(d, size[:, 0, None, None], size[:, 1, None, None], size[None, :, 0, None], size[None, :, 1, None])
    cand = (lo < 0) & sim.present[:, :, None] & sim.present[:, None] & ~np.eye(a, dtype=bool)[None, :, :, None]
    rr, i, j, tt = np.nonzero(cand)
    keep = i < j
    rr, i, j, tt = rr[keep], i[keep], j[keep], tt[keep]
    if len(rr):
        p, q = sim.poses[rr, i, tt], sim.poses[rr, j, tt]
        hit = rounded_box_signed_distance(p[:, 0], p[:, 1], size[i, 0], size[i, 1], p[:, 2], q[:, 0], q[:, 1], size[j, 0], size[j, 1], q[:, 2]) < 0
        out[rr[hit], i[hit]] = True
        out[rr[hit], j[hit]] = True
    return out


def _realism(sim: SimRollouts, common_ids: np.ndarray, original: Scenario) -> float:
    """Sim-agents meta-metric (2025 rules) of the rollouts restricted to ``common_ids``, against the
    original scene's log of those agents; NaN when the scene or rollout is not a WOSAC-shaped one."""
    from smart_marl.metrics import Rollouts, score_scenario
    from smart_marl.metrics.config import CURRENT_STEP, NUM_SIMULATION_STEPS, NUM_STEPS

    if original.num_frames != NUM_STEPS or original.current_frame != CURRENT_STEP or sim.poses.shape[2] < NUM_SIMULATION_STEPS:
        return float("nan")
    keep_orig = np.flatnonzero(np.isin(original.tracks.ids, common_ids))
    scene = original.select_tracks(keep_orig)
    cf = scene.current_frame
    sim_agents = np.flatnonzero(scene.tracks.valid[:, cf])
    ids = scene.tracks.ids[sim_agents]
    col = np.searchsorted(sim.track_ids, ids) if np.all(np.diff(sim.track_ids) > 0) else np.array([np.flatnonzero(sim.track_ids == t)[0] for t in ids])
    p = sim.poses[:, col, :NUM_SIMULATION_STEPS]
    if not np.isfinite(p).all():
        return float("nan")
    z = np.broadcast_to(scene.tracks.position[sim_agents, cf, 2].astype(np.float64)[None, :, None], p.shape[:3])
    traj = np.concatenate([p[..., :2], z[..., None], p[..., 2:3]], -1)
    return float(score_scenario(scene, Rollouts.from_array(ids, traj)).meta_metric)


def compare(baseline: SimRollouts, perturbed: SimRollouts, prepared: Prepared, realism: bool = True) -> list[dict]:
    """Rows ``{quantity, agent, baseline, whatif, change}`` (means over rollouts; NaN where the agent
    does not exist in that run): collisions; per affected agent its minimum distance to any other
    agent, mean and final speed and whether it collided; the mean speed of the vehicles behind a
    braking, stopping or stalled one after the onset; and the realism meta-metric of the agents
    present in both runs."""
    rows = []

    def add(quantity, agent, b, w):
        b, w = float(b), float(w)
        rows.append({"quantity": quantity, "agent": agent, "baseline": b, "whatif": w,
                     "change": w - b if np.isfinite(b) and np.isfinite(w) else float("nan")})

    cb, cp = colliding_agents(baseline), colliding_agents(perturbed)
    add("colliding_agents_per_rollout", "all", cb.sum(1).mean(), cp.sum(1).mean())
    veh_b = baseline.scene.tracks.types == AgentType.VEHICLE
    veh_p = perturbed.scene.tracks.types == AgentType.VEHICLE
    add("vehicles_mean_speed_mps", "all vehicles", np.nanmean(baseline.speed_mps()[:, veh_b]), np.nanmean(perturbed.speed_mps()[:, veh_p]))
    col_b = {int(t): k for k, t in enumerate(baseline.track_ids)}
    col_p = {int(t): k for k, t in enumerate(perturbed.track_ids)}
    sb, sp = baseline.speed_mps(), perturbed.speed_mps()
    nan = float("nan")
    for tid, what in prepared.affected.items():
        name = f"{tid} ({what})"
        kb, kp = col_b.get(tid), col_p.get(tid)
        onset = FRAMES_PER_TOKEN * prepared.onset_step.get(tid, 0)

        def mean_speed(s, sim, k):
            if k is None or not sim.present[:, k, onset:].any():
                return nan
            return float(np.nanmean(np.where(sim.present[:, k, onset:], s[:, k, onset:], np.nan)))

        def final_speed(s, sim, k):
            if k is None or not sim.present[:, k, -1].any():
                return nan
            return float(np.nanmean(np.where(sim.present[:, k, -1], s[:, k, -1], np.nan)))

        add("min_distance_m", name, np.nanmean(agent_min_distance_m(baseline, kb)) if kb is not None else nan,
            np.nanmean(agent_min_distance_m(perturbed, kp)) if kp is not None and perturbed.present[:, kp].any() else nan)
        add("mean_speed_after_onset_mps", name, mean_speed(sb, baseline, kb), mean_speed(sp, perturbed, kp))
        add("final_speed_mps", name, final_speed(sb, baseline, kb), final_speed(sp, perturbed, kp))
        add("collided_rate", name, cb[:, kb].mean() if kb is not None else nan,
            cp[:, kp].mean() if kp is not None and perturbed.present[:, kp].any() else nan)
    for tid, behind in prepared.followers.items():
        onset = FRAMES_PER_TOKEN * prepared.onset_step.get(tid, 0)
        fb = [col_b[t] for t in behind if t in col_b]
        fp = [col_p[t] for t in behind if t in col_p]
        if not fb or not fp:
            continue
        add("followers_mean_speed_after_onset_mps", f"{len(fp)} behind {tid}", np.nanmean(sb[:, fb, onset:]), np.nanmean(sp[:, fp, onset:]))
        add("followers_min_speed_mps", f"{len(fp)} behind {tid}", np.nanmean(np.nanmin(sb[:, fb, onset:], axis=-1)),
            np.nanmean(np.nanmin(sp[:, fp, onset:], axis=-1)))
    for step, ids in prepared.approaching:
        onset = FRAMES_PER_TOKEN * step
        fb = [col_b[t] for t in ids if t in col_b]
        fp = [col_p[t] for t in ids if t in col_p]
        if fb and fp:
            add("approaching_mean_speed_after_onset_mps", f"{len(fp)} vehicles at the lights", np.nanmean(sb[:, fb, onset:]),
                np.nanmean(sp[:, fp, onset:]))
    if realism:
        gone = {t for t, w in prepared.affected.items() if w == "removed"}
        common = np.array([t for t in baseline.track_ids if int(t) not in gone and int(t) in col_p], np.int64)
        add("realism_meta_metric", "unedited agents", _realism(baseline, common, baseline.scene),
            _realism(perturbed, common, baseline.scene))
    return rows


def format_table(rows: list[dict]) -> str:
    lines = [f"{'quantity':<38} {'agent':<28} {'baseline':>10} {'what-if':>10} {'change':>10}"]
    for r in rows:
        lines.append(f"{r['quantity']:<38} {r['agent']:<28} {r['baseline']:>10.3f} {r['whatif']:>10.3f} {r['change']:>+10.3f}")
    return "\n".join(lines)


def write_table_csv(rows: list[dict], path: str | os.PathLike) -> Path:
    import csv

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    with p.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["quantity", "agent", "baseline", "whatif", "change"])
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return p


# -------------------------------------------------------------------------------- rendering
def render_comparison(result: WhatIfResult, path: str | os.PathLike, rollout_index: int = 0, size_px: int = 400,
                      view_radius_m: float = 50.0, fps: float = 10.0) -> Path:
    """A side-by-side animation (GIF or MP4 by extension): the baseline rollout on the left, the
    what-if on the right (same rollout index, same seed); affected agents drawn in strong colours,
    the view fixed on the first affected agent (else the self-driving car)."""
    from smart_marl.render import BevRenderer, EpisodeRecorder

    base, pert = result.baseline, result.perturbed
    scene = pert.scene
    cf = scene.current_frame
    aff = [t for t in result.prepared.affected if np.isin(t, scene.tracks.ids)]
    if aff:
        k = int(np.flatnonzero(scene.tracks.ids == aff[0])[0])
    else:
        k = scene.sdc_index if scene.sdc_index >= 0 else int(np.flatnonzero(scene.tracks.valid[:, cf])[0])
    center = tuple(float(v) for v in scene.tracks.position[k, cf, :2])
    rec = EpisodeRecorder(path, fps=fps)
    sides = []
    for sim, label in ((base, "baseline"), (pert, result.whatif.name)):
        renderer = BevRenderer(sim.scene, size_px=size_px, view_radius_m=view_radius_m, center=center)
        ctrl = np.isin(sim.scene.tracks.ids, list(result.prepared.affected))
        sides.append((renderer, sim, ctrl, label))
    size = None
    for f in range(base.poses.shape[2]):
        images = []
        for renderer, sim, ctrl, label in sides:
            sc = sim.scene
            p, on = sim.poses[rollout_index, :, f], sim.present[rollout_index, :, f]
            trail_lo = max(0, f - 10)
            trail = sim.poses[rollout_index, :, trail_lo: f + 1, :2]
            tv = sim.present[rollout_index, :, trail_lo: f + 1]
            img = renderer.render(np.nan_to_num(p[:, :2]), np.nan_to_num(p[:, 2]), _box_size(sc), on, sc.tracks.types, ctrl,
                                  ego_index=-1, trajectories=np.nan_to_num(trail), trajectories_valid=tv,
                                  light_states=sim.light_states[f] if sim.light_states.shape[1] else None,
                                  light_present=sim.light_present[f] if sim.light_states.shape[1] else None,
                                  text=f"{label}  t={0.1 * (f + 1):4.1f} s")
            images.append(img)
        frame = np.concatenate([images[0], np.full((images[0].shape[0], 4, 3), 255, np.uint8), images[1]], 1)
        size = size or frame.shape
        rec.add(frame)
    for renderer, *_ in sides:
        renderer.close()
    return rec.write()
