"""One exception hierarchy for the whole package.

Every error the library raises on purpose derives from :class:`HarvestQPError`,
so user code can catch the package's failures with one ``except`` clause.
Input errors also derive from :class:`ValueError` (or :class:`KeyError` for
unknown names) so generic handlers keep working.
"""

from __future__ import annotations

from typing import Any


class HarvestQPError(Exception):
    """Base class of every error raised by :mod:`harvest_qp`."""


class InvalidInputError(HarvestQPError, ValueError):
    """An argument has the wrong shape, sign, type or a non-finite value."""


class DimensionError(InvalidInputError):
    """A size does not match the robot model (e.g. a joint-space task with ``dim != nv``).

    Raised before any compiled kernel sees the mismatched arrays: the kernels index
    by the sizes they are handed and do not check bounds.
    """


class UnknownFrameError(HarvestQPError, KeyError):
    """A frame name is not part of the robot model; the message lists valid names."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


class ModelError(HarvestQPError):
    """A robot or scene description cannot be loaded or is inconsistent."""


class SolverError(HarvestQPError):
    """A QP backend failed or returned no usable solution.

    Attributes:
        problem: the QP that failed (a :class:`harvest_qp.solver.QPProblem`), kept
            so the failure can be reproduced and inspected offline.
        backend: name of the backend that failed.
        status: the backend's own status string or code.
    """

    def __init__(self, message: str, *, problem: Any = None, backend: str = "", status: Any = None) -> None:
        super().__init__(message)
        self.problem = problem
        self.backend = backend
        self.status = status


class InfeasibleProblemError(SolverError):
    """The constraints of the QP admit no solution."""


class SolverNotAvailableError(SolverError):
    """The requested QP backend is unknown or not installed."""


class EpisodeError(HarvestQPError):
    """An episode ended before its controller logged a single tick, so it has nothing to score.

    The message gives the runner's ``episode_status`` and the first line of its error (the
    full traceback is in the log's ``error`` entry).
    """


class ConfigError(HarvestQPError, ValueError):
    """A YAML task configuration is malformed; the message names the key."""
