"""Exceptions raised by physgs stages.

Every error names *what* is wrong and *where* (a file path or a config key), so the
message alone tells a user what to fix.  Stage entry points turn these into a non-zero
exit without a traceback wall (see :mod:`physgs_steps.runtime`).
"""
from __future__ import annotations


class PhysGSError(Exception):
    """Base class of all errors that physgs reports to users."""


class InputError(PhysGSError):
    """A bad input file: truncated, malformed, non-finite values, empty..."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ConfigError(PhysGSError):
    """A config value of the wrong type, out of range, or unknown."""

    def __init__(self, key: str, problem: str, source: str | None = None):
        self.key = key
        self.problem = problem
        self.source = source
        where = f" (in {source})" if source else ""
        super().__init__(f"config key '{key}'{where}: {problem}")


class SimulationError(PhysGSError):
    """The simulation became unstable or cannot run with the given parameters."""


class RenderError(PhysGSError):
    """Rendering cannot produce a meaningful image (camera inside object, NaN positions...)."""
