"""Errors raised when a scene or a file is not what it should be.

Every reader raises :class:`ScenarioReadError` naming the file, the record inside it (when the
format has records) and what is wrong, so that a user can find the bad input and nothing is dropped
silently. :class:`ScenarioValidationError` is raised by :class:`smart_marl.Scenario` itself when the
arrays it is given do not agree; readers wrap it into a :class:`ScenarioReadError`.
"""

from __future__ import annotations

import os


class SmartMarlError(Exception):
    """Base class of the errors this package raises on bad input."""


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
