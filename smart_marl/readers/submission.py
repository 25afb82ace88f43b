"""Sim-agents challenge submissions (``SimAgentsChallengeSubmission`` protobuf files) <-> messages.

Stage: the end of the data flow's evaluation branch: rollouts are packed into a submission message
(elsewhere, on top of these helpers) and written here; a submission file is parsed here for the
realism metrics. Thin helpers only: parse and serialize the message of
:mod:`smart_marl.proto.womd`, with errors that name the file. A submission file is one serialized
message, not TFRecord-framed (the challenge's ``.binproto`` shards).
"""

from __future__ import annotations

import os

from google.protobuf.message import DecodeError

from ..errors import ScenarioReadError, check_regular_file
from ..proto.womd import SimAgentsChallengeSubmission

__all__ = ["SimAgentsChallengeSubmission", "read_submission", "write_submission", "parse_submission"]


def parse_submission(payload: bytes, path: str = "<bytes>") -> SimAgentsChallengeSubmission:
    """Parse serialized bytes; ScenarioReadError(path, ...) when they are not a submission."""
    try:
        message = SimAgentsChallengeSubmission.FromString(bytes(payload))
    except (DecodeError, RuntimeError, ValueError) as exc:
        raise ScenarioReadError(path, f"not a SimAgentsChallengeSubmission protobuf (cannot parse it: {exc})") from exc
    if len(payload) and not len(message.scenario_rollouts) and not message.ListFields():
        raise ScenarioReadError(path, "not a SimAgentsChallengeSubmission protobuf (no known field in it)")
    return message


def read_submission(path: str | os.PathLike) -> SimAgentsChallengeSubmission:
    """The ``SimAgentsChallengeSubmission`` stored in ``path``."""
    path = os.fspath(path)
    check_regular_file(path)  # a FIFO, a device, a link to /dev/urandom, /proc: refused before it is opened
    try:
        with open(path, "rb") as f:
            payload = f.read()
    except OSError as exc:
        raise ScenarioReadError(path, f"cannot open: {exc.strerror or exc}") from exc
    return parse_submission(payload, path)


def write_submission(message: SimAgentsChallengeSubmission, path: str | os.PathLike) -> int:
    """Serialize ``message`` to ``path``; returns the number of bytes written."""
    path = os.fspath(path)
    if not isinstance(message, SimAgentsChallengeSubmission):
        raise TypeError(f"expected a SimAgentsChallengeSubmission, got {type(message).__name__}")
    payload = message.SerializeToString()
    try:
        with open(path, "wb") as f:
            f.write(payload)
    except OSError as exc:
        raise ScenarioReadError(path, f"cannot write: {exc.strerror or exc}") from exc
    return len(payload)
