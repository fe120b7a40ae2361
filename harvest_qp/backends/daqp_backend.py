"""DAQP (dual active set) through its public ``daqp.Model``: set up once, updated every step."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from harvest_qp.backends.base import INF, SolverCyclingError, checked
from harvest_qp.exceptions import InfeasibleProblemError, SolverError, SolverNotAvailableError
from harvest_qp.qp_kernels import load_daqp_rows

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem

_FLAGS = {-1: "infeasible", -2: "cycling", -3: "unbounded", -4: "iteration limit", -5: "nonconvex",
          -6: "overdetermined initial active set"}


def _error(flag: int) -> type[SolverError]:
    if flag == -1:
        return InfeasibleProblemError
    if flag in (-2, -4):
        return SolverCyclingError
    return SolverError


class DaqpBackend:
    """DAQP with a persistent ``daqp.Model`` (the fastest exact backend measured here).

    DAQP's dimensions are fixed at ``setup``, so the constraint layout is fixed too: ``n``
    simple bounds, then ``n`` equality slots (unused ones free), then the inequality rows.
    The model is set up again only when ``n`` or the number of inequality rows changes, or
    after a failure (a bad active set is not reused). Between set-ups each solve starts from
    the previous solve's active set (DAQP's warm start) unless the number of equalities changed.
    """

    name = "daqp"

    def __init__(self) -> None:
        try:
            import daqp
        except ImportError as err:
            raise SolverNotAvailableError("daqp is not installed: pip install 'daqp>=0.11,<0.12'",
                                          backend=self.name) from err
        self._daqp = daqp
        self._model = None
        self._shape: tuple[int, int] | None = None
        self._n_eq = 0

    def _allocate(self, n: int, n_in: int) -> None:
        self._A = np.zeros((n + n_in, n))
        self._upper = np.full(2 * n + n_in, INF)
        self._lower = np.full(2 * n + n_in, -INF)
        self._sense = np.zeros(2 * n + n_in, dtype=np.int32)
        self._n_eq = 0
        self._shape = (n, n_in)

    def _raise(self, problem: QPProblem, flag: int, what: str = "") -> None:
        self._model = None  # start from scratch next time
        raise _error(flag)(
            f"daqp{what} failed: {_FLAGS.get(flag, 'error')} (exitflag {flag})",
            problem=problem, backend=self.name, status=flag,
        )

    def solve(self, problem: QPProblem) -> np.ndarray:
        n, n_in = problem.n, problem.G.shape[0]
        fresh = self._model is None or self._shape != (n, n_in)
        if fresh:
            self._allocate(n, n_in)
        # One compiled call writes the bounds, the equality slots and the inequality rows.
        n_eq_before = self._n_eq
        self._n_eq = load_daqp_rows(
            self._A, self._upper, self._lower, self._sense, problem.A, problem.b, problem.G, problem.h,
            problem.lower, problem.upper, n_eq_before, INF,
        )
        if fresh:
            model = self._daqp.Model()
            flag, _ = model.setup(problem.H, problem.f, self._A, self._upper, self._lower, self._sense)
            if flag < 0:
                self._raise(problem, flag, " setup")
            self._model = model
        elif self._n_eq == n_eq_before:
            # Same equality slots: DAQP starts from the previous step's active set (its warm start;
            # passing ``sense`` would reset it to the equalities alone and cost ~3 us per level).
            self._model.update(H=problem.H, f=problem.f, A=self._A, bupper=self._upper, blower=self._lower)
        else:
            self._model.update(H=problem.H, f=problem.f, A=self._A, bupper=self._upper, blower=self._lower,
                               sense=self._sense)
        x, _, flag, _ = self._model.solve()
        if flag < 0:
            self._raise(problem, flag)
        return checked(x, problem, self.name)
