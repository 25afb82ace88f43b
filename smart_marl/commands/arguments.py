"""Argument types the subcommands share: each refuses a bad value while the command line is parsed
(exit code 2 and one ``error:`` line naming the argument), before any work starts.

Each is :func:`checked`: the text parsed, then a rule of :mod:`smart_marl.config_files`, the one way
every value is checked. ``type=positive_int`` (``--workers``, ``--scenes-per-shard``...),
``type=non_negative_int``, ``type=top_k`` (``--top-k``: 0..8192, 0 means every token), ``type=seed``
(``--seed``: 0..2**63 - 1), ``bounded_int(low, high)`` / ``bounded_number(...)`` (a size with its limit named),
``type=workers`` (``--workers``: 1..4 per CPU), ``type=positive_number``, ``type=positive_numbers``
(``--speed-limits 30,50``: comma-separated numbers > 0), ``type=motion_types`` (``--types
pedestrian,cyclist``: agent types that have motion tokens), ``type=output_dir`` (``--out``:
anything but an existing file or a path below one), ``type=output_file`` (a file name to write),
``type=device`` (``--device``: a torch device this machine has;
``device_or_auto`` also takes ``auto``), :func:`reader_formats` (the ``choices`` of ``--format``)
and :func:`collision_avoidance_flag` (``--no-collision-avoidance`` on every command that rolls out
the prior).
"""

from __future__ import annotations

import argparse
import os
from typing import Any, Callable

from ..config_files import (Rule, device_problem, integer, number, output_dir_problem, output_file_problem,
                            seed as seed_rule)
from ..model.precision import PRECISIONS
from ..model.smart import MAX_VOCAB_SIZE
from ..readers import format_names
from ..rollout.engine import LIGHTS
from ..rollout.persistence import DEFAULT_PERSISTENCE, persistence_rule
from ..rollout.sampling import temperature_rule
from ..tokens.motion import MOTION_TYPES


def checked(rule: Rule, parse: Callable[[str], Any] = int, what: str = "an integer", name: str = "") -> Callable[[str], Any]:
    """An argparse ``type``: the text parsed with ``parse`` (``what`` it must be), then checked with a
    rule of :mod:`smart_marl.config_files` (the one way every value is checked); argparse prints the
    problem on one ``error:`` line naming the argument and exits with 2."""
    def convert(text: str):
        try:
            value = parse(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        problem = rule(value)
        if problem:
            raise argparse.ArgumentTypeError(problem)
        return value
    convert.__name__ = name or getattr(rule, "__name__", "value")
    return convert


positive_int = checked(integer(1), name="positive_int")
"""An integer >= 1."""
non_negative_int = checked(integer(0), name="non_negative_int")
"""An integer >= 0."""
seed = checked(seed_rule, name="seed")
"""A random seed: an integer in 0..2**63 - 1."""
positive_number = checked(number(0.0, low_open=True), float, "a number", "positive_number")
"""A finite number > 0."""


def bounded_int(low: int, high: int, why: str = "") -> Callable[[str], int]:
    """An integer in low..high (``why``: where the upper limit comes from)."""
    return checked(integer(low, high, why), name="bounded_int")


def bounded_number(low: float | None = None, high: float | None = None, low_open: bool = False,
                   why: str = "") -> Callable[[str], float]:
    """A finite number in [low, high] (> low with ``low_open``)."""
    return checked(number(low, high, low_open=low_open, why=why), float, "a number", "bounded_number")


def numbers_list(rule: Rule, name: str = "numbers") -> Callable[[str], tuple[float, ...]]:
    """Comma-separated numbers, each passing ``rule``."""
    def convert(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
        bad = next((p for p in map(rule, values) if p), None)
        if bad:
            raise argparse.ArgumentTypeError(f"every value {bad}")
        return values
    convert.__name__ = name
    return convert


positive_numbers = numbers_list(number(0.0, low_open=True), "positive_numbers")
"""Comma-separated finite numbers, each > 0."""


MAX_ROLLOUTS = 1024
"""The most rollouts per scene a command generates (32x WOSAC's 32)."""
rollouts = bounded_int(1, MAX_ROLLOUTS, "32x WOSAC's 32")
"""``--rollouts``: an integer in 1..:data:`MAX_ROLLOUTS`."""
temperature = checked(temperature_rule, float, "a number", "temperature")
"""``--temperature``: a finite number in :data:`smart_marl.rollout.TEMPERATURE_RANGE`."""
top_k = bounded_int(0, MAX_VOCAB_SIZE, "the largest vocabulary: a larger k is every token")
"""``--top-k``: an integer in 0..:data:`~smart_marl.model.smart.MAX_VOCAB_SIZE` (0: every token)."""

MAX_WORKERS = 4 * (os.cpu_count() or 1)
"""The most worker processes a command starts: 4 per CPU of this machine (more only wait for a CPU)."""
workers = bounded_int(1, MAX_WORKERS, "4 per CPU of this machine")
"""``--workers``: an integer in 1..:data:`MAX_WORKERS`."""


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


def stop_lines_flag(parser: argparse.ArgumentParser, who: str = "the prior") -> None:
    """``--no-stop-lines`` (``args.stop_lines``, default True): the one way every command that rolls out the prior
    turns traffic control off (:mod:`smart_marl.rollout.stop_lines`: its vehicles stop at red lights and stop signs and
    move off again when nothing holds them). ``--stop-lines`` is kept for older command lines (the default)."""
    parser.add_argument("--no-stop-lines", dest="stop_lines", action="store_false",
                        help=f"{who}'s vehicles ignore stop lines: no stopping at red lights and stop signs, no release "
                             "when a light turns green (default: traffic control on, smart_marl.rollout.stop_lines)")
    parser.add_argument("--stop-lines", dest="stop_lines", action="store_true",
                        help="traffic control on (the default; kept for older command lines)")
    parser.set_defaults(stop_lines=True)


def lights_option(parser: argparse.ArgumentParser, default: str) -> None:
    """``--lights current|log`` (``args.lights``): what the prior and the stop lines see of the traffic lights
    (:data:`smart_marl.rollout.LIGHTS`)."""
    parser.add_argument("--lights", default=default, choices=LIGHTS,
                        help="current: the current frame's light states, held (the sim-agents challenge's rule); "
                             f"log: the log's states at every step, held after its last frame (default: {default})")


def precision_option(parser: argparse.ArgumentParser, who: str = "the prior") -> None:
    """``--precision float32|bfloat16`` (``args.precision``, default float32): the arithmetic ``who`` runs in
    (:mod:`smart_marl.model.precision`)."""
    parser.add_argument("--precision", default="float32", choices=PRECISIONS,
                        help=f"{who}'s arithmetic: float32, or bfloat16 (weights and activations; logits, sampling and "
                             "geometry stay float32; default: float32)")


def persistence_option(parser: argparse.ArgumentParser, who: str = "the prior") -> None:
    """``--persistence B`` (``args.persistence``, default :data:`~smart_marl.rollout.persistence.DEFAULT_PERSISTENCE`):
    how strongly ``who``'s vehicles go on with the change of speed they are in (:mod:`smart_marl.rollout.persistence`;
    0: off, the model's distribution as it is)."""
    parser.add_argument("--persistence", type=checked(persistence_rule, float, "a number", "persistence"), default=DEFAULT_PERSISTENCE, metavar="B",
                        help=f"{who}'s vehicles lean toward going on with the change of speed they are in, this strongly "
                             f"(0: off; default: {DEFAULT_PERSISTENCE:g}, smart_marl.rollout.persistence)")


def output_file(text: str) -> str:
    """A file (or checkpoint name) to write: not a folder, in a folder that exists or can be created."""
    problem = output_file_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return text


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


__all__ = ["checked", "numbers_list", "workers", "MAX_WORKERS", "rollouts", "MAX_ROLLOUTS", "temperature", "top_k", "positive_int", "non_negative_int", "seed", "positive_number", "bounded_int", "bounded_number",
           "positive_numbers", "output_file", "motion_types", "collision_avoidance_flag", "stop_lines_flag", "lights_option", "persistence_option", "precision_option", "output_dir", "device", "device_or_auto", "reader_formats"]
