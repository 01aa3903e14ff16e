"""Exception hierarchy: every expected failure is a `ScanGuardError` with a one-line message."""

from __future__ import annotations

from pathlib import Path
from typing import Any


class ScanGuardError(Exception):
    """Base class of all errors scanguard raises on purpose (bad input, bad config, ...)."""


class InputError(ScanGuardError):
    """A file or recording could not be read.

    The message always names the file and, where it is known, the line or topic.
    """

    def __init__(
        self, path: str | Path | None, problem: str, *, location: str | None = None
    ) -> None:
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.location = location
        where = "" if self.path is None else str(self.path)
        if location:
            where = f"{where}, {location}" if where else location
        super().__init__(f"{where}: {problem}" if where else problem)

    def __reduce__(self) -> tuple[Any, ...]:
        # an error raised in a worker process crosses back by pickling: keep its fields
        return (_rebuild_input_error, (type(self), self.path, self.problem, self.location))


def _rebuild_input_error(
    cls: type[InputError], path: Path | None, problem: str, location: str | None
) -> InputError:
    return cls(path, problem, location=location)


class FormatError(InputError):
    """The file exists but its contents are not in the expected format (garbled, truncated)."""


class UnknownFormatError(InputError):
    """No reader is registered for the file's extension."""


class ScanError(ScanGuardError):
    """A scan is malformed (zero beams, inconsistent lengths, non-positive increment)."""


class ConfigError(ScanGuardError):
    """A configuration file or value is invalid."""


class ModelError(ScanGuardError):
    """A model file is missing, corrupt or does not match the expected architecture."""


class MatchingError(ScanGuardError):
    """A scan matcher was called with arguments it cannot work with."""


class OutputError(ScanGuardError):
    """An output destination cannot or must not be written (special file, not writable, ...).

    The message always names the destination.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple[Any, ...]:
        # an error raised in a worker process crosses back by pickling: keep its fields
        return (type(self), (self.path, self.problem))


class BackendError(ScanGuardError):
    """A SLAM back end cannot go on (its solver refuses the graph, for instance)."""
