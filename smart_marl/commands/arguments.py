"""Argument types the subcommands share: each refuses a bad value while the command line is parsed
(exit code 2 and one ``error:`` line naming the argument), before any work starts.

``type=positive_int`` (``--workers``, ``--scenes-per-shard``...), ``type=non_negative_int``
(``--top-k``: 0 means none), ``type=positive_number`` (``--temperature``), ``type=positive_numbers``
(``--speed-limits 30,50``: comma-separated numbers > 0), ``type=motion_types`` (``--types
pedestrian,cyclist``: agent types that have motion tokens), ``type=output_dir`` (``--out``:
anything but an existing file), ``type=device`` (``--device``: a torch device this machine has;
``device_or_auto`` also takes ``auto``), :func:`reader_formats` (the ``choices`` of ``--format``)
and :func:`collision_avoidance_flag` (``--no-collision-avoidance`` on every command that rolls out
the prior).
"""

from __future__ import annotations

import argparse

from ..config_files import device_problem, output_dir_problem
from ..readers import format_names
from ..tokens.motion import MOTION_TYPES


def _integer_at_least(text: str, low: int) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < low:
        raise argparse.ArgumentTypeError(f"must be at least {low}, got {value}")
    return value


def positive_int(text: str) -> int:
    """An integer >= 1."""
    return _integer_at_least(text, 1)


def non_negative_int(text: str) -> int:
    """An integer >= 0."""
    return _integer_at_least(text, 0)


def positive_number(text: str) -> float:
    """A finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (0 < value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return value


def positive_numbers(text: str) -> tuple[float, ...]:
    """Comma-separated numbers, each > 0."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"every value must be > 0, got {text!r}")
    return values


def motion_types(text: str) -> list[str]:
    """Comma-separated names of agent types with motion tokens (vehicle, pedestrian, cyclist)."""
    known = [t.name.lower() for t in MOTION_TYPES]
    names = [t.strip().lower() for t in text.split(",") if t.strip()]
    if not names or any(n not in known for n in names):
        raise argparse.ArgumentTypeError(f"expected a comma-separated list of {', '.join(known)}, got {text!r}")
    return names


def collision_avoidance_flag(parser: argparse.ArgumentParser, who: str = "the prior") -> None:
    """``--no-collision-avoidance`` (``args.avoid_collisions``, default True): the one way every
    command that rolls out the prior lets its draws be plain top-k (:mod:`smart_marl.rollout.avoidance`)."""
    parser.add_argument("--no-collision-avoidance", dest="avoid_collisions", action="store_false",
                        help=f"{who} samples plainly, without keeping its tokens out of other agents' boxes "
                             "(default: collision-aware sampling, smart_marl.rollout.avoidance)")


def output_dir(text: str) -> str:
    """A folder to write into: missing (it is created) or an existing folder, never an existing file."""
    problem = output_dir_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def _device(text: str, allow_auto: bool) -> str:
    if allow_auto and text == "auto":
        return text
    problem = device_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


def device(text: str) -> str:
    """A torch device this machine has: ``cpu``, ``cuda``, ``cuda:1``, ``mps``."""
    return _device(text, allow_auto=False)


def device_or_auto(text: str) -> str:
    """:func:`device`, or ``auto`` (cuda when available, else cpu)."""
    return _device(text, allow_auto=True)


def reader_formats() -> list[str]:
    """The names ``--format`` takes: one per scene reader."""
    return format_names()


__all__ = ["positive_int", "non_negative_int", "positive_number", "positive_numbers", "motion_types", "collision_avoidance_flag", "output_dir", "device", "device_or_auto", "reader_formats"]
