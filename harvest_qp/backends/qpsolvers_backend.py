"""Any :mod:`qpsolvers` backend (``"qpsolvers:<name>"``); infinite bounds and inactive rows dropped first."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from harvest_qp.backends.base import INF, checked
from harvest_qp.exceptions import SolverError, SolverNotAvailableError

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem


def available_solvers() -> list[str]:
    """The :mod:`qpsolvers` backends installed here (empty when qpsolvers itself is not)."""
    try:
        import qpsolvers
    except ImportError:
        return []
    return sorted(qpsolvers.available_solvers)


class QpsolversBackend:
    """A :mod:`qpsolvers` backend by its qpsolvers name."""

    def __init__(self, solver: str) -> None:
        available = available_solvers()
        if solver not in available:
            raise SolverNotAvailableError(
                f"qpsolvers backend {solver!r} is not installed; available: {', '.join(available) or 'none'}. "
                f"Install it, e.g. pip install qpsolvers {solver}",
                backend=solver,
            )
        import qpsolvers

        self._qpsolvers = qpsolvers
        self.solver = solver
        self.name = f"qpsolvers:{solver}"

    def solve(self, problem: QPProblem) -> np.ndarray:
        eye = np.eye(problem.n)
        G = np.vstack([problem.G, eye, -eye])
        h = np.concatenate([problem.h, problem.upper, -problem.lower])
        keep = h < INF / 2
        G, h = (G[keep], h[keep]) if keep.any() else (None, None)  # some backends reject 0-row G
        P = 0.5 * (problem.H + problem.H.T)
        A, b = (problem.A, problem.b) if problem.A.shape[0] else (None, None)
        try:
            x = self._qpsolvers.solve_qp(P, problem.f, G, h, A, b, solver=self.solver)
        except Exception as err:  # every backend raises its own types
            raise SolverError(
                f"{self.name} raised {type(err).__name__}: {err}", problem=problem, backend=self.name
            ) from err
        if x is None:
            raise SolverError(f"{self.name} found no solution", problem=problem, backend=self.name)
        return checked(x, problem, self.name)
