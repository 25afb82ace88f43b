"""Sim-agents submissions: rollouts <-> ``SimAgentsChallengeSubmission`` messages and files.

Stage: metrics / the end of the evaluation branch. :func:`build_submission` packs per-scenario
rollouts (object ids, [R, A, 80] x, y, z, heading in the *source* frame, optional box sizes) into
the message a WOSAC entry uploads; :func:`rollouts_from_submission` unpacks a message (or a file)
back into arrays. Values are float32 on the wire, so a float32 round trip is exact.
:func:`check_against_scene` validates a scenario's rollouts against the scene's simulated agents
with errors naming the file, the scenario and the object.

Large submissions are split in files ``PREFIX-00000-of-000NN``... (:func:`write_submission_shards`,
:func:`submission_files`); :class:`SubmissionReader` (:func:`open_submission`) reads one file or a
sharded set scenario by scenario, without holding the whole submission in memory.
"""

from __future__ import annotations

import mmap
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from ..errors import ScenarioReadError, check_regular_file
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
    """Every scenario's rollouts of a submission message or file, by scenario id (a sharded
    submission, named by its prefix or folder, is read whole: :func:`open_submission` reads on demand)."""
    if isinstance(submission, SimAgentsChallengeSubmission):
        msg, where = submission, "<submission>"
    else:
        where = os.fspath(submission)
        if not os.path.exists(where) or os.path.isdir(where):
            return dict(open_submission(where).items())
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


# ------------------------------------------------------------------------------- sharded submissions
# A large submission is a set of files PREFIX-00000-of-000NN ... PREFIX-000MM-of-000NN (the layout of
# the official tutorial and of the upload's tar.gz members, e.g. ``submission.binproto-00003-of-00150``):
# each file is a whole SimAgentsChallengeSubmission, with its own scenario_rollouts and the same header
# fields (method name, authors, description...). A protobuf message cannot exceed 2 GiB, so a
# submission of the ~45k validation scenes (about 2 MB of rollouts per scene) must be split.

SHARD_SUFFIX = re.compile(r"-(\d{5})-of-(\d{5})$")


def submission_shard_name(prefix: str | os.PathLike, index: int, count: int) -> str:
    """``PREFIX-iiiii-of-nnnnn``, the name of file ``index`` of a submission split in ``count`` files."""
    if not 0 <= index < count <= 99999:
        raise ValueError(f"shard {index} of {count}: needs 0 <= index < count <= 99999")
    return f"{os.fspath(prefix)}-{index:05d}-of-{count:05d}"


def write_submission_shards(prefix: str | os.PathLike, groups: Iterable[Iterable[ScenarioRolloutArrays]],
                            **metadata) -> list[str]:
    """Write a submission split in files, one per group of scenarios: ``PREFIX-00000-of-000NN``...,
    every file a whole ``SimAgentsChallengeSubmission`` with the same header (``metadata``, as
    :func:`build_submission` takes it). Returns the file names, in order."""
    groups = [list(g) for g in groups]
    names = [submission_shard_name(prefix, i, len(groups)) for i in range(len(groups))]
    for name, group in zip(names, groups):
        write_rollouts(name, group, **metadata)
    return names


def submission_files(spec: str | os.PathLike) -> list[str]:
    """The files of a submission given as one file, or as the prefix of a sharded one (``PREFIX``
    for ``PREFIX-00000-of-000NN``...), or as a folder holding one sharded submission. A sharded set
    must be complete: every index from 0 to N-1 once, all with the same N (the error names the
    missing or stray file)."""
    spec = os.fspath(spec)
    if os.path.isfile(spec) or (os.path.exists(spec) and not os.path.isdir(spec)):
        return [spec]  # a FIFO or device is refused when it is read, with the reader's message
    if os.path.isdir(spec):
        found = sorted(os.path.join(spec, n) for n in os.listdir(spec) if SHARD_SUFFIX.search(n))
        prefixes = sorted({SHARD_SUFFIX.sub("", f) for f in found})
        if not prefixes:
            raise ScenarioReadError(spec, "a folder without submission shards (files named PREFIX-00000-of-000NN)")
        if len(prefixes) > 1:
            raise ScenarioReadError(spec, f"holds shards of {len(prefixes)} submissions ({', '.join(os.path.basename(p) for p in prefixes[:3])}); "
                                          "name one by its prefix")
        spec = prefixes[0]
    folder = os.path.dirname(spec) or "."
    base = os.path.basename(spec)
    try:
        names = os.listdir(folder)
    except OSError as exc:
        raise ScenarioReadError(spec, f"cannot open: {exc.strerror or exc}") from exc
    shards: dict[int, set[int]] = {}
    for n in names:
        m = SHARD_SUFFIX.search(n)
        if m and n[: m.start()] == base:
            shards.setdefault(int(m.group(2)), set()).add(int(m.group(1)))
    if not shards:
        raise ScenarioReadError(spec, "no such file, and no submission shards named "
                                      f"{base}-00000-of-NNNNN beside it")
    if len(shards) > 1:
        counts = ", ".join(f"of-{c:05d}" for c in sorted(shards))
        raise ScenarioReadError(spec, f"shards of different splits share this prefix ({counts}): one set at a time")
    (count, indices), = shards.items()
    missing = sorted(set(range(count)) - indices)
    stray = sorted(i for i in indices if i >= count)
    if stray:
        raise ScenarioReadError(f"{spec}-{stray[0]:05d}-of-{count:05d}", f"shard index {stray[0]} is not below the shard count {count}")
    if missing:
        raise ScenarioReadError(submission_shard_name(spec, missing[0], count),
                                f"missing: the submission has {len(indices)} of its {count} shard files")
    return [submission_shard_name(spec, i, count) for i in range(count)]


def _varint(buf, pos: int, end: int, where: str) -> tuple[int, int]:
    result = shift = 0
    while True:
        if pos >= end:
            raise ScenarioReadError(where, "not a SimAgentsChallengeSubmission protobuf (truncated varint)")
        byte = buf[pos]
        pos += 1
        result |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return result, pos
        shift += 7
        if shift >= 70:
            raise ScenarioReadError(where, "not a SimAgentsChallengeSubmission protobuf (a varint longer than 10 bytes)")


def _wire_fields(buf, start: int, end: int, where: str):
    """(field number, wire type, start of the field's tag, start of its value, end) of every field
    of one protobuf message in ``buf[start:end]``, without decoding the values."""
    pos = start
    while pos < end:
        tag_at = pos
        key, pos = _varint(buf, pos, end, where)
        field, wire = key >> 3, key & 7
        if field == 0:
            raise ScenarioReadError(where, "not a SimAgentsChallengeSubmission protobuf (field number 0)")
        value_at = pos
        if wire == 0:
            _, pos = _varint(buf, pos, end, where)
        elif wire == 1:
            pos += 8
        elif wire == 2:
            size, value_at = _varint(buf, pos, end, where)
            pos = value_at + size
        elif wire == 5:
            pos += 4
        else:
            raise ScenarioReadError(where, f"not a SimAgentsChallengeSubmission protobuf (wire type {wire} of field {field})")
        if pos > end:
            raise ScenarioReadError(where, f"not a SimAgentsChallengeSubmission protobuf (field {field} runs past the end)")
        yield field, wire, tag_at, value_at, pos


class SubmissionReader(Mapping):
    """A submission of one or more files (:func:`submission_files`), as a mapping scenario id ->
    :class:`ScenarioRolloutArrays` that reads a scenario's rollouts only when asked for them.

    Opening scans each file's top-level protobuf fields (lengths only: the joint scenes are not
    decoded), so memory stays small whatever the submission's size. A scenario found twice (in one
    file or in two), or files whose header fields differ, is an error naming the files.
    ``header``: the submission's header, a ``SimAgentsChallengeSubmission`` without scenario_rollouts."""

    def __init__(self, paths: Iterable[str | os.PathLike]):
        self.paths = [os.fspath(p) for p in paths]
        self._where: dict[str, tuple[int, int, int]] = {}  # scenario id -> (file, offset, size)
        self.header: SimAgentsChallengeSubmission | None = None
        header_file = None
        for k, path in enumerate(self.paths):
            header = self._scan(k, path)
            if self.header is None:
                self.header, header_file = header, path
            elif header != self.header:
                differ = sorted({f.name for f, _ in header.ListFields()} ^ {f.name for f, _ in self.header.ListFields()}
                                | {f.name for f, v in header.ListFields() if getattr(self.header, f.name) != v})
                raise ScenarioReadError(path, f"its header differs from {header_file}'s ({', '.join(differ)}): "
                                              "the files of one submission share their header fields")

    def _scan(self, k: int, path: str) -> SimAgentsChallengeSubmission:
        check_regular_file(path)
        size = os.path.getsize(path)
        header_parts: list[bytes] = []
        with open(path, "rb") as f:
            buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
            try:
                for field, wire, tag_at, value_at, end in _wire_fields(buf, 0, size, path):
                    if field != 1:
                        header_parts.append(bytes(buf[tag_at:end]))
                        continue
                    if wire != 2:
                        raise ScenarioReadError(path, "not a SimAgentsChallengeSubmission protobuf (scenario_rollouts is not a message)")
                    sid = None
                    for f1, w1, _, v1, e1 in _wire_fields(buf, value_at, end, path):
                        if f1 == 1 and w1 == 2:
                            sid = bytes(buf[v1:e1]).decode("utf-8", errors="replace")
                    if sid is None:
                        sid = ""
                    if sid in self._where:
                        other = self.paths[self._where[sid][0]]
                        raise ScenarioReadError(path, f"scenario {sid} appears twice" + ("" if other == path else f" (also in {other})"))
                    self._where[sid] = (k, value_at, end - value_at)
            finally:
                if size:
                    buf.close()
        try:
            header = SimAgentsChallengeSubmission.FromString(b"".join(header_parts))
        except Exception as exc:  # noqa: BLE001 - a malformed header field: named, not a traceback
            raise ScenarioReadError(path, f"not a SimAgentsChallengeSubmission protobuf (header: {exc})") from exc
        if size and not self._where and not header.ListFields():
            raise ScenarioReadError(path, "not a SimAgentsChallengeSubmission protobuf (no known field in it)")
        return header

    def __getitem__(self, scenario_id: str) -> ScenarioRolloutArrays:
        k, offset, size = self._where[scenario_id]
        path = self.paths[k]
        with open(path, "rb") as f:
            f.seek(offset)
            payload = f.read(size)
        try:
            message = ScenarioRollouts.FromString(payload)
        except Exception as exc:  # noqa: BLE001
            raise ScenarioReadError(path, f"scenario {scenario_id}: cannot parse its rollouts: {exc}") from exc
        return _scenario_arrays(message, path)

    def __iter__(self):
        return iter(self._where)

    def __len__(self) -> int:
        return len(self._where)

    def file_of(self, scenario_id: str) -> str:
        """The file that holds a scenario's rollouts."""
        return self.paths[self._where[scenario_id][0]]


def open_submission(spec: str | os.PathLike) -> SubmissionReader:
    """A submission file, or a sharded one (its prefix or folder, see :func:`submission_files`), read on demand."""
    return SubmissionReader(submission_files(spec))
