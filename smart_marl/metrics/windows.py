"""Scoring windows: any scene cut into the 91-frame, 10 Hz windows the realism metrics score.

Stage: metrics, between the readers' :class:`~smart_marl.scenario.Scenario` and
:func:`~.inputs.logged_scene`. The metrics score a window of 91 frames at 10 Hz: the current frame,
the 10 frames before it (1.1 s of history with it) and the 80 after it (8 s). A scene of any length
has such a window at every current frame ``c`` with ``c >= 10`` and ``c + 80 <= T - 1``
(:func:`window_frames`); :func:`cut_window` cuts one into a new Scenario whose current frame is 10
(tracks and traffic-light states sliced alike, the map, the roles and the frame kept).

Which windows (:func:`scene_windows`, ``smart-marl eval --window``):

* ``current`` (the default): the window at the scene's own current frame, the scene's id kept. When
  that frame has too little history or future (Argoverse 2: current frame 49 of 110, 60 frames of
  future; ScenarioNet's 20 s Waymo scenes: current frame 0), the window that fits nearest to it,
  named ``SCENEID@FRAME``.
* ``all``: every window that fits and has an agent to evaluate, each its own scenario ``SCENEID@FRAME``.
* an integer ``FRAME``: the window at that current frame, ``SCENEID@FRAME``.

``FRAME`` counts 10 Hz frames of the scene (after resampling, below).

The evaluated agents (:func:`evaluated_tracks`): WOSAC's, the self-driving car plus the tracks to
predict, at the scene's own current frame (exactly :func:`~.inputs.logged_scene`'s choice, so a
WOMD scene scores as it always did); at another window, those of them valid at its current frame.
A scene without tracks to predict gets :data:`EVALUATED_RULE`: an anchor plus up to 8 vehicles,
pedestrians or cyclists, nearest to the anchor at the current frame first, that are valid at the current
frame and on at least 40 of the 80 future frames and move at least 2 m within the window
(:func:`rule_tracks`). The anchor is the self-driving car where the window has one valid at its current
frame (nuScenes, ScenarioNet's 20 s Waymo scenes); otherwise (the Nocturne JSON scenes, some GPUDrive
ones: neither a self-driving car nor tracks to predict) the agent that meets the same three conditions
and travels farthest within the window, the lowest id among equals (:func:`anchor_track`): up to 9
agents either way. A window with no such agent has no agent to evaluate (:meth:`Window.logged` names
the three reasons) and is skipped. A scene with tracks to predict never uses the anchor: a window where
neither they nor the self-driving car are valid has no agent to evaluate, as before.

Resampling (:func:`to_10hz`): the frame step is read from ``Scenario.timestamps_s`` (every reader
fills it from the source's own timestamps where it has them, e.g. a ScenarioNet ``metadata/ts``).
A step within 10 % of 0.1 s is 10 Hz already (WOMD's timestamps jitter by 0.5 %). A step that is a
whole multiple k of 0.1 s (2 Hz: k = 5), up to 1 s, is upsampled: positions, velocities and sizes
interpolated linearly, headings along the shorter turn (the unwrapped difference), a frame valid
when both frames around it are, traffic-light states held from the frame before. The source frames
are kept bit for bit. Exactness: a straight path at constant speed and a constant yaw rate are
reproduced exactly; a path with acceleration ``a`` is off by at most ``a * dt**2 / 8`` between source
frames (3 cm per m/s^2 at 2 Hz; a turn at speed v and yaw rate w: ``v * w * dt**2 / 8``), and speed
is constant between source frames, so the acceleration features of such a log change only at the
source frames: compare resampled scenes with each other, not with native 10 Hz numbers. A step
that divides 0.1 s (20 Hz: every 2nd frame) keeps every k-th frame, the current frame among them
(exact). Anything else (irregular timestamps, a gap, a step above 1 s, 3 Hz) is a
:class:`ResampleError` naming the scene and the step.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass

import numpy as np

from ..scenario import AgentType, DT_S, Scenario, Tracks, wrap_angle
from ..values import _replace
from .config import CURRENT_STEP, NUM_SIMULATION_STEPS, NUM_STEPS
from .inputs import LoggedScene, SceneNotScorableError, logged_scene

WINDOW_CHOICES = ("current", "all")
"""The named ``--window`` values; an integer (a current frame >= 10) is the third kind."""
STEP_TOLERANCE = 0.1
"""A frame step within this fraction of 0.1 s (or of its multiple) counts as that step; a scene whose steps
differ from their median by more than this fraction is irregular (refused)."""
MAX_RESAMPLE_STEP_S = 1.0
"""The longest frame step upsampled to 10 Hz (a longer one is a gap linear motion does not bridge)."""
EVALUATED_MAX_TRACKS = 8
"""The rule's most tracks besides the self-driving car (WOMD gives at most 8 tracks to predict)."""
EVALUATED_MIN_FUTURE_FRAMES = 40
"""The rule's least valid frames among the 80 future ones (half of the 8 s)."""
EVALUATED_MIN_TRAVEL_M = 2.0
"""The rule's least travel: the farthest valid position in the window from the current one."""
_CONDITIONS = (f"valid at the current frame and on at least {EVALUATED_MIN_FUTURE_FRAMES} of the {NUM_SIMULATION_STEPS} "
               f"future frames and moving at least {EVALUATED_MIN_TRAVEL_M:g} m within the window (the farthest valid "
               f"position from the current one)")
_ELIGIBLE = f"vehicles, pedestrians or cyclists {_CONDITIONS}"
EVALUATED_RULE = (
    f"an anchor plus up to {EVALUATED_MAX_TRACKS} more vehicles, pedestrians or cyclists, nearest to the anchor at the "
    f"current frame first (ties: the lower id), each {_CONDITIONS}; the anchor is the self-driving car when it is valid "
    f"at the current frame, otherwise the agent that meets those conditions and moves farthest within the window "
    f"(ties: the lowest id), and a window where no agent meets them has no agent to evaluate and is skipped")
"""The evaluated agents of a window of a scene without tracks to predict, in words (``eval --help``, docs/metrics.md)."""


class WindowError(SceneNotScorableError):
    """A scene with no scoring window (too short, or the asked current frame does not fit); ``eval`` skips it
    with the reason."""


class ResampleError(WindowError):
    """A scene whose frame times cannot be brought to 10 Hz exactly enough (irregular, a gap, an odd rate)."""


@dataclass(frozen=True)
class Window:
    """One scoring window: ``scenario`` (91 frames at 10 Hz, current frame 10, its id the scene's or
    ``SCENEID@FRAME``), ``frame`` (its current frame in the 10 Hz scene), ``evaluated`` (track indices to
    evaluate; None: :func:`~.inputs.logged_scene`'s own, the SDC and the tracks to predict) and ``shifted``
    (``current`` could not use the scene's own current frame: why, in words; None otherwise)."""

    scenario: Scenario
    frame: int
    evaluated: np.ndarray | None = None
    shifted: str | None = None

    def logged(self) -> LoggedScene:
        """The metrics' logged inputs of the window (:class:`SceneNotScorableError` when it has no agent to evaluate)."""
        if self.evaluated is None and _anchored(self.scenario):  # the rule found no one: say why
            raise SceneNotScorableError(_nobody(self.scenario))
        return logged_scene(self.scenario, self.evaluated)


# ------------------------------------------------------------------------------------ the option
def parse_window(text: str) -> str | int:
    """``--window`` (an argparse type): ``current``, ``all`` or a current frame >= 10 (an int)."""
    value = text.strip().lower()
    if value in WINDOW_CHOICES:
        return value
    try:
        frame = int(value, 10)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not current, all or a frame number") from None
    if not CURRENT_STEP <= frame <= 10**6:
        raise argparse.ArgumentTypeError(f"{text!r}: a window's current frame must be in {CURRENT_STEP}..1000000 "
                                         f"(it needs {CURRENT_STEP} frames of history before it)")
    return frame


# ------------------------------------------------------------------------------------ resampling
def frame_step_s(scenario: Scenario) -> float | None:
    """The scene's frame step in seconds (the median step of its timestamps), None with fewer than 2 frames."""
    ts = scenario.timestamps_s
    return float(np.median(np.diff(ts))) if len(ts) > 1 else None


def _whole_ratio(a: float, b: float) -> int | None:
    """k when ``a`` is k >= 2 times ``b`` within :data:`STEP_TOLERANCE`, else None."""
    k = round(a / b)
    return k if k >= 2 and abs(a - k * b) <= STEP_TOLERANCE * b else None


def to_10hz(scenario: Scenario) -> Scenario:
    """The scene at 10 Hz (this very object when it is at 10 Hz already); see the module docstring for how
    and how exactly. :class:`ResampleError` naming the scene when its frame times cannot be resampled."""
    step = frame_step_s(scenario)
    if step is None:
        return scenario
    sid, diffs = scenario.scenario_id, np.diff(scenario.timestamps_s)
    worst = int(np.argmax(np.abs(diffs - step)))
    if not step > 0 or abs(diffs[worst] - step) > STEP_TOLERANCE * step:
        gap = f"a gap of {diffs[worst]:.3g} s" if diffs[worst] > step else f"a step of {diffs[worst]:.3g} s"
        raise ResampleError(f"scenario {sid}: irregular frame times ({gap} between frames {worst} and {worst + 1}, "
                            f"the usual step is {step:.3g} s): it cannot be resampled to 10 Hz")
    if abs(step - DT_S) <= STEP_TOLERANCE * DT_S:
        return scenario
    if step > MAX_RESAMPLE_STEP_S * (1 + STEP_TOLERANCE):
        raise ResampleError(f"scenario {sid}: frames {step:.3g} s apart, a gap larger than {MAX_RESAMPLE_STEP_S:g} s "
                            "that linear interpolation does not bridge: it cannot be resampled to 10 Hz")
    up, down = _whole_ratio(step, DT_S), _whole_ratio(DT_S, step)
    if up is not None:
        return _upsample(scenario, up, step)
    if down is not None:
        return _downsample(scenario, down, step)
    raise ResampleError(f"scenario {sid}: frame step {step:.4g} s ({1 / step:.3g} Hz) is neither a whole multiple nor a "
                        f"whole fraction of 0.1 s: it cannot be resampled to 10 Hz exactly enough")


def _upsample(scenario: Scenario, k: int, step: float) -> Scenario:
    """k frames per source frame: linear in everything, headings along the shorter turn, states held."""
    t = scenario.num_frames
    j = np.arange((t - 1) * k + 1)
    i0 = np.minimum(j // k, t - 1)
    i1 = np.minimum(i0 + 1, t - 1)
    frac = (j - i0 * k) / k
    on_source = frac == 0.0
    tr = scenario.tracks

    def lerp(a: np.ndarray) -> np.ndarray:
        a64 = a.astype(np.float64)
        f = frac.reshape((1, -1) + (1,) * (a.ndim - 2))
        out = a64[:, i0] + f * (a64[:, i1] - a64[:, i0])
        out[:, on_source] = a64[:, i0[on_source]]  # the source frames bit for bit
        return out.astype(a.dtype)

    h64 = tr.heading.astype(np.float64)
    heading = wrap_angle(h64[:, i0] + frac * wrap_angle(h64[:, i1] - h64[:, i0])).astype(np.float32)
    heading[:, on_source] = tr.heading[:, i0[on_source]]
    valid = tr.valid[:, i0] & (on_source | tr.valid[:, i1])
    tracks = Tracks(ids=tr.ids, types=tr.types, position=lerp(tr.position), heading=heading, velocity=lerp(tr.velocity),
                    size=lerp(tr.size), valid=valid)
    ts = scenario.timestamps_s
    timestamps = ts[i0] + frac * (ts[i1] - ts[i0])
    tl = scenario.traffic_lights
    lights = _replace(tl, states=tl.states[i0], present=tl.present[i0])
    method = f"linear, {k} frames per source frame"
    metadata = {**scenario.metadata, "resampled_to_10hz": {"from_step_s": step, "method": method}}
    return dataclasses.replace(scenario, timestamps_s=timestamps, current_frame=scenario.current_frame * k, tracks=tracks,
                               traffic_lights=lights, metadata=metadata)


def _downsample(scenario: Scenario, k: int, step: float) -> Scenario:
    """Every k-th frame, the current frame among them."""
    keep = np.arange(scenario.current_frame % k, scenario.num_frames, k)
    tr, tl = scenario.tracks, scenario.traffic_lights
    tracks = _replace(tr, position=tr.position[:, keep], heading=tr.heading[:, keep], velocity=tr.velocity[:, keep],
                      size=tr.size[:, keep], valid=tr.valid[:, keep])
    metadata = {**scenario.metadata, "resampled_to_10hz": {"from_step_s": step, "method": f"every {k}th frame"}}
    return _replace(scenario, timestamps_s=scenario.timestamps_s[keep], current_frame=scenario.current_frame // k,
                    tracks=tracks, traffic_lights=_replace(tl, states=tl.states[keep], present=tl.present[keep]),
                    metadata=metadata)


# ---------------------------------------------------------------------------------- the windows
def window_frames(scenario: Scenario) -> list[int]:
    """The current frames of every window that fits a 10 Hz scene: ``c >= 10`` and 80 frames after ``c``."""
    return list(range(CURRENT_STEP, scenario.num_frames - NUM_SIMULATION_STEPS))


def cut_window(scenario: Scenario, current: int, scenario_id: str | None = None) -> Scenario:
    """The 91 frames around ``current`` of a 10 Hz scene, as a Scenario whose current frame is 10 (arrays
    shared with the scene; ``scenario_id`` replaces the id when given). :class:`WindowError` when it does not fit."""
    if current not in range(CURRENT_STEP, scenario.num_frames - NUM_SIMULATION_STEPS):
        raise WindowError(_no_window(scenario, f"a window at current frame {current} does not fit"))
    window = scenario.window(current - CURRENT_STEP, current - CURRENT_STEP + NUM_STEPS, current_frame=CURRENT_STEP)
    return window if scenario_id is None else _replace(window, scenario_id=scenario_id)


def _no_window(scenario: Scenario, what: str) -> str:
    resampled = " (at 10 Hz)" if "resampled_to_10hz" in scenario.metadata else ""
    return (f"scenario {scenario.scenario_id}: {what}: the sim-agents metrics need {NUM_STEPS} frames at 10 Hz (a current "
            f"frame with {CURRENT_STEP} frames before it and {NUM_SIMULATION_STEPS} after it); the scene has "
            f"{scenario.num_frames} frames{resampled}, its current frame is {scenario.current_frame}")


def scene_windows(scenario: Scenario, which: str | int = "current") -> list[Window]:
    """The windows ``which`` (``current``, ``all`` or a current frame) of a scene at any rate, resampled to
    10 Hz first, each with its evaluated agents. :class:`WindowError` (or :class:`ResampleError`) naming the
    scene when it has none."""
    scene = to_10hz(scenario)
    fits = window_frames(scene)
    own = scene.current_frame
    sid = scene.scenario_id
    if which == "all":
        if not fits:
            raise WindowError(_no_window(scene, "no window fits"))
        frames, shifted = fits, None
    elif which == "current":
        if not fits:
            raise WindowError(_no_window(scene, "no window fits"))
        frame = min(fits, key=lambda c: (abs(c - own), c))
        frames = [frame]
        shifted = None if frame == own else (
            f"its current frame {own} has {min(own, CURRENT_STEP)} of {CURRENT_STEP} history frames and "
            f"{min(scene.num_frames - 1 - own, NUM_SIMULATION_STEPS)} of {NUM_SIMULATION_STEPS} future frames; "
            f"scored at the nearest window that fits, current frame {frame} ({sid}@{frame})")
    else:
        frames, shifted = [int(which)], None
    out = []
    for frame in frames:
        named = which == "current" and frame == own
        window = cut_window(scene, frame, None if named else f"{sid}@{frame}")
        out.append(Window(window, frame, evaluated_tracks(window, own=frame == own), shifted))
    if which == "all":  # every window that fits *and* has someone to evaluate; a scene without any is one skip
        out = [w for w in out if _evaluable(w)]
        if not out:
            raise WindowError(f"scenario {sid}: no agent to evaluate in any of its {len(frames)} windows (no self-driving "
                              "car or track to predict valid at their current frames"
                              + (f", nor an agent for the rule to anchor on: none of its {_ELIGIBLE})"
                                 if not len(scene.predict_indices) else ")"))
    return out


def _evaluable(window: Window) -> bool:
    """Whether :meth:`Window.logged` finds agents to evaluate, all valid at the current frame (its two checks)."""
    sc = window.scenario
    idx = window.evaluated
    if idx is None:
        idx = np.array([*sc.predict_indices, *([sc.sdc_index] if sc.sdc_index >= 0 else [])], np.int64)
    return len(idx) > 0 and bool(sc.tracks.valid[idx, CURRENT_STEP].all())


def evaluated_tracks(window: Scenario, own: bool) -> np.ndarray | None:
    """Track indices to evaluate in a window (see the module docstring), None for
    :func:`~.inputs.logged_scene`'s own choice (the SDC and the tracks to predict): always at the scene's own
    current frame (``own``) when it has tracks to predict, and where neither they nor the rule give anyone
    (``logged_scene``, or :meth:`Window.logged` for the anchored rule, then names what is missing)."""
    valid = window.tracks.valid[:, CURRENT_STEP]
    sdc = window.sdc_index
    if len(window.predict_indices):
        if own:
            return None
        keep = [int(i) for i in window.predict_indices if valid[i]]
        if keep:
            return np.unique(np.array(keep + ([sdc] if sdc >= 0 and valid[sdc] else []), np.int64))
    if sdc >= 0 and valid[sdc]:
        return np.unique(np.array([sdc, *rule_tracks(window)], np.int64))
    if not _anchored(window):
        return None
    anchor = anchor_track(window)
    if anchor is None:
        return None
    return np.unique(np.array([anchor, *rule_tracks(window, anchor)], np.int64))


EVALUATED_BY = ("tracks to predict", "rule, self-driving car anchor", "rule, farthest-moving anchor")
"""How a window's evaluated agents are chosen (:func:`evaluated_by`): WOSAC's (the SDC and the tracks to predict),
:data:`EVALUATED_RULE` around the self-driving car, or around the agent that moves farthest."""


def evaluated_by(window: Window) -> str | None:
    """Which of :data:`EVALUATED_BY` chose a window's evaluated agents; None when it has none to evaluate."""
    sc = window.scenario
    if not _evaluable(window):
        return None
    if len(sc.predict_indices) and sc.tracks.valid[sc.predict_indices, CURRENT_STEP].any():
        return EVALUATED_BY[0]
    return EVALUATED_BY[2] if _anchored(sc) else EVALUATED_BY[1]


def _anchored(window: Scenario) -> bool:
    """Whether a window's evaluated agents come from the rule around an anchor other than the SDC: no tracks to
    predict and no self-driving car valid at its current frame."""
    sdc = window.sdc_index
    return not len(window.predict_indices) and not (sdc >= 0 and window.tracks.valid[sdc, CURRENT_STEP])


def _eligible(window: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rule's conditions: (eligible [N] bool, travel [N] in m, current positions [N, 2]) of a window's tracks."""
    tr = window.tracks
    current = tr.position[:, CURRENT_STEP, :2].astype(np.float64)
    future_valid = tr.valid[:, CURRENT_STEP + 1:].sum(axis=1)
    travel = np.linalg.norm(tr.position[..., :2].astype(np.float64) - current[:, None], axis=-1)
    travel = np.where(tr.valid, travel, 0.0).max(axis=1)
    movable = np.isin(tr.types, [AgentType.VEHICLE, AgentType.PEDESTRIAN, AgentType.CYCLIST])
    ok = movable & tr.valid[:, CURRENT_STEP]
    ok &= (future_valid >= EVALUATED_MIN_FUTURE_FRAMES) & (travel >= EVALUATED_MIN_TRAVEL_M)
    return ok, travel, current


def anchor_track(window: Scenario) -> int | None:
    """The agent :data:`EVALUATED_RULE` anchors on in a window without a valid self-driving car or tracks to
    predict: of the agents the rule may pick, the one that travels farthest within the window (its farthest valid
    position from its current one), the lowest id among equals; None when no agent qualifies."""
    ok, travel, _ = _eligible(window)
    candidates = np.flatnonzero(ok)
    if not len(candidates):
        return None
    order = np.lexsort((window.tracks.ids[candidates], -travel[candidates]))  # farthest first, ties by id
    return int(candidates[order[0]])


def rule_tracks(window: Scenario, anchor: int | None = None) -> list[int]:
    """The tracks :data:`EVALUATED_RULE` adds to its anchor (the self-driving car unless ``anchor`` names
    another track) in a window, nearest to the anchor first."""
    tr = window.tracks
    anchor = window.sdc_index if anchor is None else int(anchor)
    ok, _, current = _eligible(window)
    ok[anchor] = False
    candidates = np.flatnonzero(ok)
    distance = np.linalg.norm(current[candidates] - current[anchor], axis=-1)
    order = np.lexsort((tr.ids[candidates], distance))  # nearest first, ties by id
    return [int(i) for i in candidates[order][:EVALUATED_MAX_TRACKS]]


def _nobody(window: Scenario) -> str:
    """Why a window the anchored rule applies to has no agent to evaluate."""
    sdc = window.sdc_index
    car = ("no self-driving car" if sdc < 0 else
           f"its self-driving car (object {int(window.tracks.ids[sdc])}) is not valid at the current frame")
    return (f"scenario {window.scenario_id}: no agent to evaluate: {car}, no track to predict, and no agent for the rule "
            f"to anchor on (none of its {_ELIGIBLE}; docs/metrics.md)")


__all__ = ["EVALUATED_BY", "EVALUATED_RULE", "ResampleError", "Window", "WindowError", "anchor_track", "cut_window",
           "evaluated_by", "evaluated_tracks", "frame_step_s", "parse_window", "rule_tracks", "scene_windows", "to_10hz",
           "window_frames"]
