"""SUMO traffic, its motion made lifelike: headings smoothed over a few frames
(:func:`smooth_heading`), pedestrians' paths smoothed (:func:`smooth_walkers`) and then swaying
sideways as people walk (:func:`sway_walkers`). Re-exported by :mod:`.sumo_sim`.
"""

from __future__ import annotations

import math

import numpy as np

from ..geometry import frame_steps
from ..scenario import DT_S, wrap_angle


def _window_mean(values: np.ndarray, valid: np.ndarray, window: int) -> np.ndarray:
    """Mean of ``values`` [A, T, C] over a centred window of frames, valid frames only."""
    k = window // 2
    w = valid.astype(np.float64)
    cs = np.cumsum(np.pad(values * w[..., None], ((0, 0), (k + 1, k), (0, 0))), axis=1)
    cw = np.cumsum(np.pad(w, ((0, 0), (k + 1, k))), axis=1)
    total = cw[:, window:] - cw[:, :-window]
    return (cs[:, window:] - cs[:, :-window]) / np.maximum(total, 1.0)[..., None]


def smooth_heading(heading: np.ndarray, valid: np.ndarray, window: int = 5) -> np.ndarray:
    """Headings [A, T] averaged (as unit vectors) over ``window`` frames: SUMO's angle jumps by a few
    degrees where a lane's polyline kinks or meets the next lane; a real car turns smoothly."""
    unit = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    mean = _window_mean(unit, valid, window)
    return np.where(valid, np.arctan2(mean[..., 1], mean[..., 0]), heading)


def smooth_walkers(xy: np.ndarray, valid: np.ndarray, heading: np.ndarray, window: int = 9,
                   max_yaw_rate: float = 2 * math.pi, min_speed_mps: float = 0.2):
    """Pedestrian tracks made physical: SUMO's walkers start and stop instantly, turn on the spot and
    shift sideways between sidewalk stripes. Positions ``xy`` [P, T, 2] are averaged over ``window``
    frames (valid ones only), velocities are their central differences, headings follow the velocity
    (held while standing) and turn at most ``max_yaw_rate`` (rad/s). Returns (xy, velocity, heading)."""
    smooth = np.where(valid[..., None], _window_mean(xy, valid, window), 0.0)
    velocity = frame_steps(smooth, valid)[0] / DT_S
    speed = np.linalg.norm(velocity, axis=-1)
    target = np.where(speed > min_speed_mps, np.arctan2(velocity[..., 1], velocity[..., 0]), np.nan)
    out = heading.copy()
    step = max_yaw_rate * DT_S
    for t in range(xy.shape[1]):  # over frames, vectorised over walkers
        goal = np.where(np.isnan(target[:, t]), out[:, t - 1] if t else heading[:, 0], target[:, t])
        if t == 0:
            out[:, 0] = goal
            continue
        turn = wrap_angle(goal - out[:, t - 1])
        limited = out[:, t - 1] + np.clip(turn, -step, step)
        out[:, t] = np.where(valid[:, t] & valid[:, t - 1], limited, goal)
    out = wrap_angle(out)
    return smooth, velocity, out


WALKER_JITTER_DOF = 1.3
"""Degrees of freedom of the Student-t innovations of the walkers' heading jitter: heavy tails, as the
headings of logged pedestrians have (mostly a few hundredths of a radian per frame, now and then a
turn of the body or a tracker's flip of a few tenths)."""
WALKER_JITTER_MAX_RAD = 0.5


def _smoothed_noise(rng: np.random.Generator, shape: tuple[int, int], time_scale_s: float, draw) -> np.ndarray:
    """Noise [P, T] from ``draw(size)`` innovations smoothed by a Gaussian of ``time_scale_s`` whose
    weights have unit L2 norm (unit-variance innovations stay unit variance)."""
    p, t = shape
    half = max(1, int(math.ceil(3 * time_scale_s / DT_S)))
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) * DT_S / time_scale_s) ** 2)
    kernel /= np.sqrt((kernel**2).sum())
    noise = draw((p, t + 2 * half))
    return np.stack([np.convolve(row, kernel, mode="valid") for row in noise]) if p else np.zeros((p, t))


def sway_walkers(xy: np.ndarray, valid: np.ndarray, heading: np.ndarray, rng: np.random.Generator,
                 amplitude_m: float, time_scale_s: float, jitter_rad: float = 0.0, jitter_s: float = 0.15,
                 walking_mps: float = 1.0):
    """Walking pedestrians made to move as logged ones do. SUMO walks them along perfectly straight
    lines, so their heading never changes between corners; a logged pedestrian's heading changes by
    about 0.1 rad/s at the median and by more than 0.4 rad/s in one frame of eight (the GPUDrive and
    Nocturne scenes of ../shared/data). Two things are added to the smoothed tracks ``xy`` [P, T, 2]
    (:func:`smooth_walkers`), both faded in with the walker's speed (full from ``walking_mps``;
    standing walkers neither move nor turn):

    * a sideways sway (to the left of ``heading``): white noise smoothed by a Gaussian of
      ``time_scale_s``, standard deviation ``amplitude_m``; velocities and headings are derived again
      from the swayed positions, so the heading follows the path;
    * a heading jitter around the direction of travel: Student-t innovations
      (:data:`WALKER_JITTER_DOF`) smoothed over ``jitter_s`` and scaled by ``jitter_rad``, clipped to
      :data:`WALKER_JITTER_MAX_RAD`. The body turns, the path does not.

    Returns (xy, velocity, heading)."""
    shape = valid.shape
    step = frame_steps(xy, valid)[0] / DT_S
    walking = _window_mean(np.clip(np.linalg.norm(step, axis=-1) / walking_mps, 0.0, 1.0)[..., None], valid, 9)[..., 0]
    offset = amplitude_m * _smoothed_noise(rng, shape, time_scale_s, rng.standard_normal)
    left = np.stack([-np.sin(heading), np.cos(heading)], axis=-1)
    swayed = np.where(valid[..., None], xy + (offset * walking)[..., None] * left, 0.0)
    xy, velocity, heading = smooth_walkers(swayed, valid, heading, window=1)
    if jitter_rad > 0:
        jitter = jitter_rad * _smoothed_noise(rng, shape, jitter_s, lambda size: rng.standard_t(WALKER_JITTER_DOF, size))
        heading = np.where(valid, wrap_angle(heading + np.clip(jitter, -WALKER_JITTER_MAX_RAD, WALKER_JITTER_MAX_RAD) * walking),
                           heading)
    return xy, velocity, heading
