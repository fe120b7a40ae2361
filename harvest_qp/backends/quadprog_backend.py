"""quadprog (dense Goldfarb-Idnani dual active set) called directly.

Not through :mod:`qpsolvers`, which turns quadprog's "constraints are inconsistent" into
``None``: infeasibility could not be told from a crash.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from harvest_qp.backends.base import INF, checked
from harvest_qp.exceptions import InfeasibleProblemError, SolverError, SolverNotAvailableError

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem


class QuadprogBackend:
    """quadprog called directly; needs a positive definite Hessian."""

    name = "quadprog"

    def __init__(self) -> None:
        try:
            import quadprog
        except ImportError as err:
            raise SolverNotAvailableError(
                "quadprog is not installed: pip install quadprog", backend=self.name
            ) from err
        self._quadprog = quadprog

    def solve(self, problem: QPProblem) -> np.ndarray:
        n = problem.n
        eye = np.eye(n)
        # quadprog: min 1/2 x^T G x - a^T x  s.t.  C^T x >= b, the first meq rows equalities.
        C = np.vstack([problem.A, -problem.G, -eye, eye])
        bound = np.concatenate([problem.b, -problem.h, -problem.upper, problem.lower])
        keep = np.abs(bound) < INF / 2
        keep[: problem.A.shape[0]] = True
        C, bound = C[keep], bound[keep]
        H = 0.5 * (problem.H + problem.H.T)
        try:
            if C.shape[0]:
                x = self._quadprog.solve_qp(H, -problem.f, C.T.copy(), bound, problem.A.shape[0])[0]
            else:  # quadprog rejects an empty constraint matrix
                x = self._quadprog.solve_qp(H, -problem.f)[0]
        except ValueError as err:
            kind = InfeasibleProblemError if "inconsistent" in str(err) else SolverError
            raise kind(f"quadprog: {err}", problem=problem, backend=self.name, status=str(err)) from err
        return checked(x, problem, self.name)
