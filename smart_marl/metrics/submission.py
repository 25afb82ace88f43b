"""Sim-agents submissions: rollouts <-> ``SimAgentsChallengeSubmission`` messages and files.

Stage: metrics / the end of the evaluation branch. :func:`build_submission` packs per-scenario
rollouts (object ids, [R, A, 80] x, y, z, heading in the *source* frame, optional box sizes) into
the message a WOSAC entry uploads; :func:`rollouts_from_submission` unpacks a message (or a file)
back into arrays. Values are float32 on the wire, so a float32 round trip is exact.
:func:`check_against_scene` validates a scenario's rollouts against the scene's simulated agents
with errors naming the file, the scenario and the object.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..proto.womd import JointScene, ScenarioRollouts, SimAgentsChallengeSubmission, SimulatedTrajectory
from ..readers.submission import read_submission, write_submission
from .config import NUM_SIMULATION_STEPS
from .inputs import LoggedScene, RolloutError, Rollouts

SIM_AGENTS_SUBMISSION = 1


@dataclass(frozen=True)
class ScenarioRolloutArrays:
    """One scenario's rollouts as arrays: ``object_ids`` [A], ``trajectories`` [R, A, T, 4] float32
    (x, y, z, heading; source frame), ``sizes`` [A, 3] (length, width, height) or None."""

    scenario_id: str
    object_ids: np.ndarray
    trajectories: np.ndarray
    sizes: np.ndarray | None = None

    def to_rollouts(self, frame=None) -> Rollouts:
        """As :class:`Rollouts` in a scene's local frame (``frame``: the scene's SceneFrame)."""
        if frame is None:
            return Rollouts.from_array(self.object_ids, self.trajectories)
        return Rollouts.from_source(self.object_ids, self.trajectories, frame)


def build_submission(scenarios: Iterable[ScenarioRolloutArrays], *, account_name: str = "",
                     unique_method_name: str = "smart-marl", authors: Iterable[str] = (), affiliation: str = "",
                     description: str = "", method_link: str = "", num_model_parameters: str = "",
                     uses_public_model_pretraining: bool = False,
                     acknowledge_complies_with_closed_loop_requirement: bool = True) -> SimAgentsChallengeSubmission:
    """A ``SimAgentsChallengeSubmission`` holding every scenario's rollouts."""
    msg = SimAgentsChallengeSubmission(
        submission_type=SIM_AGENTS_SUBMISSION, account_name=account_name, unique_method_name=unique_method_name,
        authors=list(authors), affiliation=affiliation, description=description, method_link=method_link,
        num_model_parameters=num_model_parameters, uses_public_model_pretraining=uses_public_model_pretraining,
        acknowledge_complies_with_closed_loop_requirement=acknowledge_complies_with_closed_loop_requirement,
    )
    for sc in scenarios:
        traj = np.asarray(sc.trajectories, dtype=np.float32)
        if traj.ndim != 4 or traj.shape[-1] != 4 or traj.shape[1] != len(sc.object_ids):
            raise RolloutError(f"scenario {sc.scenario_id}: trajectories must be [R, A={len(sc.object_ids)}, T, 4], "
                               f"got {traj.shape}")
        sr = ScenarioRollouts(scenario_id=sc.scenario_id)
        for r in range(traj.shape[0]):
            js = JointScene()
            for a, oid in enumerate(sc.object_ids):
                t = traj[r, a]
                st = SimulatedTrajectory(center_x=t[:, 0], center_y=t[:, 1], center_z=t[:, 2], heading=t[:, 3],
                                         object_id=int(oid))
                if sc.sizes is not None:
                    n = t.shape[0]
                    st.length.extend(np.full(n, sc.sizes[a, 0], np.float32))
                    st.width.extend(np.full(n, sc.sizes[a, 1], np.float32))
                    st.height.extend(np.full(n, sc.sizes[a, 2], np.float32))
                js.simulated_trajectories.append(st)
            sr.joint_scenes.append(js)
        msg.scenario_rollouts.append(sr)
    return msg


def write_rollouts(path: str | os.PathLike, scenarios: Iterable[ScenarioRolloutArrays], **metadata) -> int:
    """Write a submission file; returns its size in bytes."""
    return write_submission(build_submission(scenarios, **metadata), path)


def _scenario_arrays(sr, where: str) -> ScenarioRolloutArrays:
    sid = sr.scenario_id
    if not len(sr.joint_scenes):
        raise RolloutError(f"{where}: scenario {sid}: no joint scenes")
    ids = np.array([t.object_id for t in sr.joint_scenes[0].simulated_trajectories], dtype=np.int64)
    r, a = len(sr.joint_scenes), len(ids)
    steps = len(sr.joint_scenes[0].simulated_trajectories[0].center_x) if a else 0
    traj = np.empty((r, a, steps, 4), np.float32)
    sizes = None
    for ri, js in enumerate(sr.joint_scenes):
        these = [t.object_id for t in js.simulated_trajectories]
        if len(these) != a or any(int(x) != int(y) for x, y in zip(these, ids)):
            extra = sorted(set(these) - set(ids.tolist()))
            missing = sorted(set(ids.tolist()) - set(these))
            what = f"object {extra[0]} is extra" if extra else (f"object {missing[0]} is missing" if missing else "objects are in another order")
            raise RolloutError(f"{where}: scenario {sid}: joint scene {ri} does not hold the objects of joint scene 0 ({what})")
        for ai, t in enumerate(js.simulated_trajectories):
            cols = (t.center_x, t.center_y, t.center_z, t.heading)
            lens = [len(c) for c in cols]
            if any(n != steps for n in lens):
                raise RolloutError(f"{where}: scenario {sid}: object {t.object_id} in joint scene {ri} has "
                                   f"{lens} steps (x, y, z, heading); expected {steps} each")
            for k, c in enumerate(cols):
                traj[ri, ai, :, k] = c
            if ri == 0 and len(t.length):
                if sizes is None:
                    sizes = np.full((a, 3), np.nan, np.float32)
                sizes[ai] = (t.length[0], t.width[0] if len(t.width) else np.nan, t.height[0] if len(t.height) else np.nan)
    return ScenarioRolloutArrays(sid, ids, traj, sizes)


def rollouts_from_submission(submission: SimAgentsChallengeSubmission | str | os.PathLike) -> dict[str, ScenarioRolloutArrays]:
    """Every scenario's rollouts of a submission message or file, by scenario id."""
    if isinstance(submission, SimAgentsChallengeSubmission):
        msg, where = submission, "<submission>"
    else:
        where = os.fspath(submission)
        msg = read_submission(where)
    out: dict[str, ScenarioRolloutArrays] = {}
    for sr in msg.scenario_rollouts:
        if sr.scenario_id in out:
            raise RolloutError(f"{where}: scenario {sr.scenario_id} appears twice")
        out[sr.scenario_id] = _scenario_arrays(sr, where)
    return out


def check_against_scene(arrays: ScenarioRolloutArrays, scene: LoggedScene, where: str = "<submission>",
                        num_rollouts: int | None = None) -> None:
    """RolloutError (naming the file, scenario and object) unless the rollouts have 80 steps and
    exactly the scene's simulated agents (and ``num_rollouts`` joint scenes when given)."""
    sid = arrays.scenario_id
    steps = arrays.trajectories.shape[2]
    if steps != NUM_SIMULATION_STEPS:
        raise RolloutError(f"{where}: scenario {sid}: trajectories have {steps} steps, expected {NUM_SIMULATION_STEPS}")
    if num_rollouts is not None and arrays.trajectories.shape[0] != num_rollouts:
        raise RolloutError(f"{where}: scenario {sid}: {arrays.trajectories.shape[0]} joint scenes, expected {num_rollouts}")
    ids = set(arrays.object_ids.tolist())
    want = set(scene.object_ids.tolist())
    extra, missing = sorted(ids - want), sorted(want - ids)
    if missing:
        raise RolloutError(f"{where}: scenario {sid}: simulated agent {missing[0]} is missing "
                           f"({len(missing)} of the scene's {len(want)} simulated agents missing)")
    if extra:
        raise RolloutError(f"{where}: scenario {sid}: object {extra[0]} is not a simulated agent of the scene "
                           f"({len(extra)} extra; simulated agents are the tracks valid at step 10)")
