"""Errors raised when a scene, a file or an argument is not what it should be.

Every error this package raises on bad input is a :class:`SmartMarlError` (keeping a builtin base,
``ValueError``, ``KeyError``..., where callers may catch one). Every reader raises
:class:`ScenarioReadError` naming the file, the record inside it (when the format has records) and
what is wrong, so that a user can find the bad input and nothing is dropped silently.
:class:`ScenarioValidationError` is raised by :class:`smart_marl.Scenario` itself when the arrays it
is given do not agree; readers wrap it into a :class:`ScenarioReadError`. :class:`UsageError` is a
bad argument or config value: the command line exits with 2 on it (1 on every other
:class:`SmartMarlError`).

:func:`check_regular_file` is the one check every reader of user files runs before opening one: a
FIFO, a device, a socket or a file of /proc or /sys given as input would block or stream forever.
"""

from __future__ import annotations

import os
import stat


class SmartMarlError(Exception):
    """Base class of the errors this package raises on bad input."""


class UsageError(SmartMarlError, ValueError):
    """A bad command-line argument or config value (the command line exits with 2 and prints it on one line)."""


class ScenarioValidationError(SmartMarlError, ValueError):
    """The arrays of a Scenario are inconsistent (shapes, dtypes, NaN on valid frames...)."""


class ScenarioReadError(SmartMarlError, ValueError):
    """A file could not be read as scenes.

    Attributes:
        path: the file.
        record: the record index inside the file (a TFRecord record, a JSON key path...), or None
            when the problem concerns the whole file.
        problem: what is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike, problem: str, record: int | str | None = None):
        self.path = os.fspath(path)
        self.record = record
        self.problem = problem
        where = self.path if record is None else f"{self.path}, record {record}"
        super().__init__(f"{where}: {problem}")

    def __reduce__(self):  # keep the fields when the error crosses a process boundary
        return (type(self), (self.path, self.problem, self.record))


class UnknownFormatError(ScenarioReadError):
    """No reader recognises the file."""


KERNEL_FILE_SYSTEMS = ("/proc", "/sys")
"""Folders whose files are the kernel's, not data: they read forever, block, or change as they are read."""


def on_kernel_file_system(path: str | os.PathLike) -> bool:
    """Whether ``path`` (links followed) lies under /proc or /sys."""
    real = os.path.realpath(os.fspath(path))
    return any(real == root or real.startswith(root + os.sep) for root in KERNEL_FILE_SYSTEMS)


def regular_file_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be read as an input file (missing, a folder, a FIFO, a device, a file of
    /proc or /sys...), or None."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        return f"cannot open: {getattr(exc, 'strerror', None) or exc}"
    if stat.S_ISREG(mode):
        if on_kernel_file_system(path):
            return "is a file of /proc or /sys, not a regular data file (it would block or never end)"
        return None
    if stat.S_ISDIR(mode):
        return "is a folder, not a file"
    kind = ("a FIFO" if stat.S_ISFIFO(mode) else "a socket" if stat.S_ISSOCK(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) else "not a regular file")
    return f"is {kind}, not a regular file (it would block or never end)"


def check_regular_file(path: str | os.PathLike, error=None) -> None:
    """Raise ``error(path, problem)`` (default :class:`ScenarioReadError`) unless ``path`` is a regular file."""
    problem = regular_file_problem(path)
    if problem is not None:
        raise (error or ScenarioReadError)(path, problem)


