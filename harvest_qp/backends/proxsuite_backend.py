"""proxsuite's dense QP kept between steps, with the settings that stay exact on collision rows.

Its defaults declare feasible QPs with near-duplicate collision rows infeasible and, with a
warm start and ``eps_abs >= 1e-7``, return wrong solutions flagged as solved (STACK_NOTES):
hence the tight absolute tolerances, the duality-gap check and ``eps_primal_inf = 1e-12``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from harvest_qp.backends.base import INF, checked
from harvest_qp.exceptions import InfeasibleProblemError, SolverError, SolverNotAvailableError

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem


class ProxsuiteBackend:
    """proxsuite dense QP kept between steps, with settings that stay exact on collision rows."""

    name = "proxsuite"

    def __init__(self, *, eps_abs: float = 1e-9) -> None:
        try:
            import proxsuite
        except ImportError as err:
            raise SolverNotAvailableError("proxsuite is not installed: pip install proxsuite",
                                          backend=self.name) from err
        self._proxsuite = proxsuite
        self._qp = None
        self._shape: tuple[int, int, int] | None = None
        self.eps_abs = eps_abs

    def _new_qp(self, n: int, n_eq: int, n_in: int):
        px = self._proxsuite.proxqp
        qp = px.dense.QP(n, n_eq, n_in, True)
        s = qp.settings
        s.eps_abs = self.eps_abs
        s.eps_rel = 0.0
        s.eps_primal_inf = 1e-12
        s.eps_dual_inf = 1e-12
        s.check_duality_gap = True
        s.eps_duality_gap_abs = self.eps_abs
        s.eps_duality_gap_rel = 0.0
        s.max_iter = 1_000  # a failing solve must not stall the 2 ms loop (quadprog is tried first)
        s.verbose = False
        s.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        return qp

    def solve(self, problem: QPProblem) -> np.ndarray:
        px = self._proxsuite.proxqp
        # Presolve: proxsuite mistakes trivially satisfied rows (padding, zero rows of
        # pairs a joint axis cannot move) for infeasibility, so drop them.
        keep = (problem.h < INF / 2) & ~((np.abs(problem.G).max(axis=1, initial=0.0) < 1e-12) & (problem.h >= 0))
        G, h = problem.G[keep], problem.h[keep]
        n, n_eq, n_in = problem.n, problem.A.shape[0], G.shape[0]
        inf = 1e20
        l_box, u_box = np.maximum(problem.lower, -inf), np.minimum(problem.upper, inf)
        C, u, l = (G, h, np.full(n_in, -inf)) if n_in else (None, None, None)
        A, b = (problem.A, problem.b) if n_eq else (None, None)
        if self._qp is None or self._shape != (n, n_eq, n_in):
            self._qp, self._shape = self._new_qp(n, n_eq, n_in), (n, n_eq, n_in)
            self._qp.init(problem.H, problem.f, A, b, C, l, u, l_box, u_box)
        else:
            self._qp.update(problem.H, problem.f, A, b, C, l, u, l_box, u_box)
        self._qp.solve()
        status = self._qp.results.info.status
        if status != px.QPSolverOutput.PROXQP_SOLVED:
            # A warm start from another step's solution can end in a false infeasibility
            # report: solve once more from a cold start before believing it.
            self._qp.settings.initial_guess = px.InitialGuess.NO_INITIAL_GUESS
            self._qp.solve()
            self._qp.settings.initial_guess = px.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            status = self._qp.results.info.status
        if status != px.QPSolverOutput.PROXQP_SOLVED:
            info = self._qp.results.info
            self._qp = None
            kind = InfeasibleProblemError if "INFEASIBLE" in str(status) else SolverError
            # With eps_primal_inf = 1e-12 (needed against false reports on near-duplicate
            # rows) an infeasible QP ends at the iteration limit with the dual residual
            # converged and the primal residual stuck: report that as infeasible.
            if status == px.QPSolverOutput.PROXQP_MAX_ITER_REACHED and info.pri_res > 1e-6 and info.dua_res < 1e-6:
                kind = InfeasibleProblemError
            raise kind(
                f"proxsuite failed: {status} (primal residual {info.pri_res:.3g}, dual {info.dua_res:.3g})",
                problem=problem, backend=self.name, status=status,
            )
        return checked(self._qp.results.x.copy(), problem, self.name)
