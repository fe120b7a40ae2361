"""What every QP backend shares: the acceptance check of a returned solution and its errors.

Every returned solution is checked: finite, and feasible to :data:`FEASIBILITY_TOLERANCE`
*relative to the scale of each row* (a row ``g x <= h`` is judged by
``(g x - h) / (1 + |h| + |g| |x|)``): an absolute tolerance rejected DAQP solutions off by
2e-7..1e-6 on rows whose terms are ~1 (FINDINGS, "QP core"). A rejected solution raises
:class:`SolverAccuracyError`; the solver then re-solves the QP with a second backend.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from harvest_qp.exceptions import SolverError

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem

#: Bound magnitude that stands for "no bound" in the QP data.
INF = 1e30
#: Largest scale-relative constraint violation accepted in a returned solution
#: (see :func:`harvest_qp.qp_kernels.max_scaled_violation`).
FEASIBILITY_TOLERANCE = 1e-7
#: When every backend returns a solution outside :data:`FEASIBILITY_TOLERANCE`, the least
#: violating one is still used if it is within this (scale-relative: 1e-5 of a 1 m/s row is
#: 10 um/s) instead of braking the robot; the step's ``retries`` say so. Measured in closed
#: loop (audit, seed 8, tick 871): daqp 6.3e-7, and the tick braked.
ACCEPTABLE_VIOLATION = 1e-5


class SolverAccuracyError(SolverError):
    """A backend returned a solution outside the constraints by more than the tolerance.

    Carries ``x`` (the solution) and ``violation`` (its scale-relative violation) so the
    solver can still take the least violating answer within :data:`ACCEPTABLE_VIOLATION`.
    """


class SolverCyclingError(SolverError):
    """An active-set backend cycled or hit its iteration limit (DAQP exitflag -2 / -4)."""


class Backend(Protocol):
    """Solves one :class:`~harvest_qp.solver.QPProblem`, raising :class:`SolverError` on failure."""

    name: str

    def solve(self, problem: QPProblem) -> np.ndarray: ...


def checked(x, problem: QPProblem, backend: str) -> np.ndarray:
    """``x`` as a float array if it satisfies ``problem`` to :data:`FEASIBILITY_TOLERANCE`, else raise."""
    if x is None:
        raise SolverError(f"{backend} returned no solution", problem=problem, backend=backend)
    x = np.asarray(x, dtype=float)
    violation = problem.scaled_violation(x)
    if violation == np.inf:
        raise SolverError(f"{backend} returned a non-finite solution", problem=problem, backend=backend)
    if violation > FEASIBILITY_TOLERANCE:
        error = SolverAccuracyError(
            f"{backend} returned a solution violating the constraints by {violation:.3g} (relative to row scale)",
            problem=problem,
            backend=backend,
        )
        error.x, error.violation = x.copy(), float(violation)  # for the last resort
        raise error
    return x
