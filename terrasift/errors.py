"""One exception root for terrasift; domain errors also subclass builtins.

The service maps these to RFC 9457 problem responses in one table
(``terrasift.service.problems``); the CLI prints their message.
"""

from __future__ import annotations


class TerrasiftError(Exception):
    """Root of every error terrasift raises on purpose."""

    #: short machine-readable problem type, used in problem+json bodies
    problem: str = "terrasift-error"


class InputError(TerrasiftError, ValueError):
    """An input file is not usable: not LAS, truncated, empty, absurd header."""

    problem = "invalid-input"


class NothingChanged(TerrasiftError):
    """An incremental survey run was asked for and no tile or parameter changed."""

    problem = "survey-unchanged"


class ParameterError(TerrasiftError, ValueError):
    """A job parameter is unknown or out of range."""

    problem = "invalid-parameter"


class FilterSyntaxError(ParameterError):
    """A feature filter text does not parse; carries the offending line."""

    problem = "invalid-filter"

    def __init__(self, message: str, line: int | None = None, name: str | None = None):
        where = f"{name or 'filter'}, line {line}: " if line is not None else ""
        super().__init__(where + message)
        self.line = line
        self.name = name


class JobCancelled(TerrasiftError):
    """Raised inside a task when its job was dismissed."""

    problem = "job-dismissed"


class ProcessingError(TerrasiftError, RuntimeError):
    """A task failed on data it could only judge while processing."""

    problem = "processing-failed"


class Unavailable(TerrasiftError):
    """The machine, not the request, stopped the work (too busy, short of memory,
    shutting down); the same request may succeed later."""

    problem = "service-unavailable"
