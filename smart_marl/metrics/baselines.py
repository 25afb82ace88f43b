"""Baseline rollouts for the realism metrics: constant velocity, log replay, random, noisy log replay.

Stage: metrics (a stand-in for the rollout engine when there is no model). Each policy takes a
:class:`~smart_marl.scenario.Scenario` and returns :class:`~.inputs.Rollouts` ``[R, A, 80]`` of the
simulated agents (tracks valid at the current step, scenario order) in the scene's local frame.
All are deterministic given ``seed``; they compute in float64 from the scene's float32 arrays, so
the same function run elsewhere on the same arrays gives the same bits (the parity goldens rely on
this: see tests/golden/README.md).
"""

from __future__ import annotations

import numpy as np

from ..scenario import Scenario
from .config import CURRENT_STEP, NUM_ROLLOUTS, NUM_SIMULATION_STEPS, STEP_S
from .inputs import Rollouts, simulated_agent_indices

POLICIES = ("constant_velocity", "log_replay", "random")


def _agents(scenario: Scenario):
    sim = simulated_agent_indices(scenario)
    tr = scenario.tracks
    return sim, tr.ids[sim].astype(np.int64), tr.position[sim], tr.velocity[sim], tr.heading[sim], tr.valid[sim]


def _future_times_s() -> np.ndarray:
    return np.arange(1, NUM_SIMULATION_STEPS + 1, dtype=np.float64) * STEP_S


def constant_velocity(scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0) -> Rollouts:
    """Every agent keeps its logged velocity vector of the current step (heading and z held)."""
    _, ids, pos, vel, heading, _ = _agents(scenario)
    t = _future_times_s()
    p = pos[:, CURRENT_STEP].astype(np.float64)
    v = vel[:, CURRENT_STEP].astype(np.float64)
    h = heading[:, CURRENT_STEP].astype(np.float64)
    x = p[:, None, 0] + v[:, None, 0] * t
    y = p[:, None, 1] + v[:, None, 1] * t
    z = np.repeat(p[:, None, 2], NUM_SIMULATION_STEPS, axis=1)
    hh = np.repeat(h[:, None], NUM_SIMULATION_STEPS, axis=1)
    traj = np.stack([x, y, z, hh], -1)[None].repeat(num_rollouts, 0)
    return Rollouts.from_array(ids, traj)


def constant_speed_along_heading(scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0,
                                 min_speed_mps: float = 10.0) -> Rollouts:
    """Every agent drives straight along its current heading at max(logged speed, ``min_speed_mps``)
    (stopped cars start: a stress test that runs red lights and leaves the road)."""
    _, ids, pos, vel, heading, _ = _agents(scenario)
    t = _future_times_s()
    p = pos[:, CURRENT_STEP].astype(np.float64)
    v = vel[:, CURRENT_STEP].astype(np.float64)
    h = heading[:, CURRENT_STEP].astype(np.float64)
    speed = np.maximum(np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1]), min_speed_mps)
    x = p[:, None, 0] + (speed * np.cos(h))[:, None] * t
    y = p[:, None, 1] + (speed * np.sin(h))[:, None] * t
    z = np.repeat(p[:, None, 2], NUM_SIMULATION_STEPS, axis=1)
    hh = np.repeat(h[:, None], NUM_SIMULATION_STEPS, axis=1)
    return Rollouts.from_array(ids, np.stack([x, y, z, hh], -1)[None].repeat(num_rollouts, 0))


def _held_log_future(pos, heading, valid) -> np.ndarray:
    """[A, 80, 4] logged future, the last valid pose held where the log is invalid."""
    a, t = valid.shape
    idx = np.where(valid, np.arange(t)[None], 0)
    idx = np.maximum.accumulate(idx, axis=1)  # index of the last valid step so far (step 10 is valid)
    ai = np.arange(a)[:, None]
    p = pos.astype(np.float64)
    h = heading.astype(np.float64)
    return np.concatenate([p[ai, idx], h[ai, idx][..., None]], -1)[:, CURRENT_STEP + 1:]


def log_replay(scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0) -> Rollouts:
    """The logged future where valid, the last valid pose held after (identical rollouts)."""
    _, ids, pos, _, heading, valid = _agents(scenario)
    base = _held_log_future(pos, heading, valid)
    return Rollouts.from_array(ids, np.repeat(base[None], num_rollouts, 0))


NOISE_SCALE = np.array([0.6, 0.6, 0.1, 0.1])
"""Noisy log replay: uniform noise of this full width on x, y (m), z (m) and heading (rad)."""


def noisy_log_replay(scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0) -> Rollouts:
    """:func:`log_replay` plus independent uniform noise per rollout, agent, step and coordinate
    (``(U[0, 1) - 0.5) * NOISE_SCALE``, from ``numpy.random.default_rng(seed).random``)."""
    _, ids, pos, _, heading, valid = _agents(scenario)
    base = _held_log_future(pos, heading, valid)
    u = np.random.default_rng(seed).random((num_rollouts, len(ids), NUM_SIMULATION_STEPS, 4))
    return Rollouts.from_array(ids, base[None] + (u - 0.5) * NOISE_SCALE)


RANDOM_ACCEL_MPS2 = 2.0
RANDOM_YAW_RATE_RADPS = 0.2


def random_rollouts(scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0) -> Rollouts:
    """Constant-velocity-like rollouts with a random constant acceleration in
    [-2, 2] m/s^2 and a random constant yaw rate in [-0.2, 0.2] rad/s per rollout and agent
    (unicycle integration from the logged speed and heading of the current step; the speed never
    goes below 0)."""
    _, ids, pos, vel, heading, _ = _agents(scenario)
    rng = np.random.default_rng(seed)
    a = len(ids)
    accel = rng.uniform(-RANDOM_ACCEL_MPS2, RANDOM_ACCEL_MPS2, (num_rollouts, a, 1))
    yaw_rate = rng.uniform(-RANDOM_YAW_RATE_RADPS, RANDOM_YAW_RATE_RADPS, (num_rollouts, a, 1))
    t = _future_times_s()[None, None]
    v0 = np.linalg.norm(vel[:, CURRENT_STEP].astype(np.float64), axis=-1)[None, :, None]
    h0 = heading[:, CURRENT_STEP].astype(np.float64)[None, :, None]
    speed = np.maximum(v0 + accel * t, 0.0)
    h = h0 + yaw_rate * t
    x = pos[:, CURRENT_STEP, 0].astype(np.float64)[None, :, None] + np.cumsum(speed * np.cos(h) * STEP_S, axis=-1)
    y = pos[:, CURRENT_STEP, 1].astype(np.float64)[None, :, None] + np.cumsum(speed * np.sin(h) * STEP_S, axis=-1)
    z = np.broadcast_to(pos[:, CURRENT_STEP, 2].astype(np.float64)[None, :, None], x.shape)
    return Rollouts.from_array(ids, np.stack([x, y, z, h], axis=-1))


def policy_rollouts(name: str, scenario: Scenario, num_rollouts: int = NUM_ROLLOUTS, seed: int = 0) -> Rollouts:
    """Rollouts of a named baseline policy (:data:`POLICIES`)."""
    fn = {"constant_velocity": constant_velocity, "log_replay": log_replay, "random": random_rollouts,
          "noisy_log_replay": noisy_log_replay}.get(name)
    if fn is None:
        raise ValueError(f"unknown baseline policy {name!r}: expected one of {POLICIES}")
    return fn(scenario, num_rollouts, seed)
