"""What-if scenarios, the edits: what a what-if script says, as dataclasses, and the YAML reader.

Stage: agents (what-if). What comes in: edit objects built in Python or a YAML (or JSON) script
file. What goes out: a :class:`WhatIf` (a name, a description and a list of edits), which
:func:`agents.whatif.prepare.prepare` applies to a scene. The format is in :mod:`agents.whatif`.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence, Union

from smart_marl.config_files import integer, is_integer, is_number, number, optional, shown
from smart_marl.model.smart import MAX_VOCAB_SIZE
from smart_marl.errors import SmartMarlError, check_regular_file
from smart_marl.scenario import SignalState

AgentRef = Union[int, str]


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
    ``speed_mps``. ``then``: "release" (the prior drives it once the script ends) or "hold". ``size_m``
    [length, width, height]; without it, its type's :data:`~smart_marl.scenario.TYPICAL_BOX_M`."""

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
    or a new vehicle standing at ``pose`` [x, y, heading] (its history: standing there), of ``size_m``
    [length, width, height] (default a vehicle's :data:`~smart_marl.scenario.TYPICAL_BOX_M`)."""

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
KIND_OF = {cls: kind for kind, cls in KINDS.items()}

MAX_STEPS = 64
"""Most token steps (0.5 s each: 32 s) a what-if rolls out; ``smart-marl whatif --steps`` refuses more."""
MAX_ROLLOUTS = 1024
"""Most rollouts a what-if and its baseline each take (32x WOSAC's 32); ``smart-marl whatif --rollouts`` refuses more."""
MAX_SCRIPT_BYTES = 1_000_000
"""The largest what-if script file."""
MAX_SCRIPT_NODES = 100_000
"""The most values a what-if script may hold once its YAML aliases are expanded (an alias bomb is refused)."""


# ---------------------------------------------------------------------------- value checks
# Every key of every kind has a rule (smart_marl.config_files' rules, or the ones below) that a
# script's values must pass when it is loaded, before a scene is read or a rollout runs.
MAX_COORDINATE_M = 1e6
"""The largest coordinate (metres) or heading a what-if script may give: farther than any map."""
MAX_SPEED_MPS = 100.0
"""The fastest scripted agent (360 km/h): faster would leave the map within a token step."""
MAX_SIZE_M = 30.0
"""The largest box side of an inserted agent (a long truck is 25 m)."""
MAX_DURATION_S = MAX_STEPS * 0.5
"""The latest onset, wait or manoeuvre duration: the longest rollout."""
MAX_POINTS = 10_000
"""The most points of a trajectory or path."""
MAX_TRACK_ID = 2**62
"""The largest track id (ids are int64)."""


def _is_number(v) -> bool:
    """A finite number within :data:`MAX_COORDINATE_M` (coordinates, headings)."""
    return is_number(v) and abs(v) <= MAX_COORDINATE_M


def _agent_ref(v):
    if isinstance(v, str) and v:
        return None
    return None if is_integer(v) and abs(v) <= MAX_TRACK_ID else f"must be a track id or 'sdc', got {v!r}"


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
            return f"must hold finite numbers within +-{MAX_COORDINATE_M:g} only, got {v!r}"
        if len(rows) > MAX_POINTS:
            return f"must be at most {MAX_POINTS} points, got {len(rows)}"
        if count is not None and len(rows) != count:
            return f"must be {count} point(s), got {len(rows)}"
        return None
    return rule


def _vector(n: int, positive: bool = False, high: float = MAX_COORDINATE_M):
    """``n`` finite numbers within +-``high`` (positive ones with ``positive``)."""
    def rule(v):
        if not (isinstance(v, (list, tuple)) and len(v) == n and all(is_number(x) and abs(x) <= high for x in v)) or \
                (positive and min(v) <= 0):
            return f"must be {n} finite{' positive' if positive else ''} numbers within +-{high:g}, got {v!r}"
        return None
    return rule


def _tokens(v):
    if not isinstance(v, (list, tuple)) or not v or not all(is_integer(t) and 0 <= t < MAX_VOCAB_SIZE for t in v):
        return f"must be a non-empty list of token ids (integers in 0..{MAX_VOCAB_SIZE - 1}), got {v!r}"
    if len(v) > MAX_POINTS:
        return f"must be at most {MAX_POINTS} token ids, got {len(v)}"
    return None


def _choice(*options):
    return lambda v: None if v in options else f"must be one of {', '.join(map(str, options))}, got {v!r}"


def _lanes(v):
    lane = lambda x: is_integer(x) and abs(x) <= MAX_TRACK_ID  # noqa: E731 - ids are int64
    if v == "all" or lane(v) or (isinstance(v, (list, tuple)) and v and len(v) <= MAX_POINTS and all(map(lane, v))):
        return None
    return f"must be 'all' or lane ids (integers within +-{MAX_TRACK_ID}, at most {MAX_POINTS}), got {shown(v)}"


_SIGNAL_NAMES = tuple(s.name.lower() for s in SignalState)
_PLACEMENT = {"frame": _choice("source", "local"), "relative_to": optional(_agent_ref)}
_SECONDS = number(0.0, MAX_DURATION_S, why="the longest rollout")
_SPEED = number(0.0, MAX_SPEED_MPS, why="360 km/h")
_SIZE = _vector(3, positive=True, high=MAX_SIZE_M)
_ID = integer(0, MAX_TRACK_ID)
_AT = {"at_s": _SECONDS}
_EDIT_RULES = {
    Remove: {"agents": _agent_refs, **_AT},
    Insert: {"type": _choice("vehicle", "pedestrian", "cyclist"), "trajectory": optional(_points((2, 3))),
             "path": optional(_points((2,))), "speed_mps": _SPEED, "wait_s": _SECONDS, "tokens": optional(_tokens),
             "pose": optional(_vector(3)), "id": optional(_ID), "size_m": optional(_SIZE),
             "then": _choice("release", "hold")},
    Brake: {"agent": _agent_ref, **_AT, "decel_mps2": number(0.0, 20.0, low_open=True, why="2 g")},
    CutIn: {"agent": _agent_ref, **_AT, "lateral_m": number(-20.0, 20.0, why="five lanes"),
            "duration_s": number(0.0, MAX_DURATION_S, low_open=True, why="the longest rollout"), "speed_mps": optional(_SPEED)},
    Follow: {"agent": _agent_ref, **_AT, "path": optional(_points((2,))), "speed_mps": optional(_SPEED),
             "tokens": optional(_tokens), "then": _choice("release", "hold")},
    StalledVehicle: {"agent": optional(_agent_ref), "pose": optional(_vector(3)), "id": optional(_ID), "size_m": optional(_SIZE)},
    Jaywalker: {"start": _vector(2), "end": _vector(2), "speed_mps": number(0.0, MAX_SPEED_MPS, low_open=True),
                "wait_s": _SECONDS, "id": optional(_ID)},
    TrafficLightOverride: {"lanes": _lanes, "state": lambda v: _choice(*_SIGNAL_NAMES)(str(v).lower()), **_AT},
}
_EDIT_RULES[Stop] = _EDIT_RULES[Brake]


def check_edit(edit, path=None, index: int | None = None) -> None:
    """:class:`WhatIfError` naming the file, the edit and the key whose value is not what the kind
    takes (``at_s: soon``, a ragged path, ``decel_mps2: .inf``...)."""
    kind = KIND_OF.get(type(edit))
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


EXAMPLES_DIR = Path(__file__).resolve().parent / "examples"
"""The example scripts that ship with the package, one per kind, written for the embedded sample scene
``sumo-7-000000-03`` (:func:`smart_marl.embedded.sample_scenarios`)."""


def example_scripts() -> list[str]:
    """The names of the shipped example scripts (``brake_hard``, ``cut_in``, ...)."""
    return sorted(p.stem for p in EXAMPLES_DIR.glob("*.yaml"))


def script_path(script: str | os.PathLike) -> Path:
    """``script`` as a file path: an existing file as it is, else the shipped example of that name
    (``"brake_hard"`` -> ``EXAMPLES_DIR / "brake_hard.yaml"``), else the path unchanged (so that
    :func:`load_script` names it as missing)."""
    p = Path(script)
    example = EXAMPLES_DIR / f"{p.name}.yaml"
    if not p.exists() and p.name == os.fspath(script) and example.is_file():
        return example
    return p


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
    if p.stat().st_size > MAX_SCRIPT_BYTES:
        raise WhatIfError(p, f"{p.stat().st_size} bytes: a what-if script is at most {MAX_SCRIPT_BYTES} bytes")
    try:
        loader = yaml.SafeLoader(p.read_text())
        try:
            node = loader.get_single_node()
            nodes = _expanded_nodes(node, {}, set())
            data = loader.construct_document(node) if node is not None and nodes <= MAX_SCRIPT_NODES else None
        finally:
            loader.dispose()
    except (yaml.YAMLError, ValueError, RecursionError) as exc:  # ValueError: UnicodeDecodeError, a recursive alias
        raise WhatIfError(p, f"not valid YAML: {type(exc).__name__}: {exc}") from exc
    if nodes > MAX_SCRIPT_NODES:
        raise WhatIfError(p, f"the YAML expands to more than {MAX_SCRIPT_NODES} values through its aliases (&anchor / "
                             f"*alias): {nodes} counted before stopping; a what-if script holds at most {MAX_SCRIPT_NODES}")
    return WhatIf.from_dict(data, str(p))


def _expanded_nodes(node, sizes: dict, visiting: set) -> int:
    """How many values the YAML node stands for once its aliases are expanded (an alias counts as
    many times as it is used); a node that contains itself is refused."""
    if node is None:
        return 0
    key = id(node)
    if key in sizes:
        return sizes[key]
    if key in visiting:
        raise ValueError("a recursive alias (a value that contains itself)")
    visiting.add(key)
    children = node.value if isinstance(node.value, list) else []
    total = 1
    for child in children:
        total += sum(_expanded_nodes(c, sizes, visiting) for c in child) if isinstance(child, tuple) else \
            _expanded_nodes(child, sizes, visiting)
        if total > MAX_SCRIPT_NODES:  # stop early: the count of a bomb grows geometrically
            break
    visiting.discard(key)
    sizes[key] = total
    return total


