"""QP backends behind :class:`harvest_qp.solver.Solver`.

* ``daqp`` (default): a persistent ``daqp.Model`` set up once and updated each step;
  dimensions are fixed after ``setup``, so equality rows are padded to ``n`` and
  the model is set up again only when the number of inequality rows changes. With daqp 0.11.0
  the model is a :class:`harvest_qp._daqp_native.NativeModel` (DAQP's C API called directly:
  the same calls on the same data, self-tested bit for bit against ``daqp.Model``).
* ``proxsuite``: a kept ``proxqp.dense.QP`` with tight absolute tolerances, the
  duality-gap check and ``eps_primal_inf = 1e-12``; its defaults declare feasible
  QPs with near-duplicate collision rows infeasible and return wrong solutions.
* ``quadprog`` (also ``qpsolvers:quadprog``): Goldfarb-Idnani dual active set called
  directly, because :mod:`qpsolvers` turns quadprog's "constraints are inconsistent"
  into ``None`` and infeasibility could not be told from a crash.
* ``qpsolvers:<name>``: any other backend of :mod:`qpsolvers`.

Every backend failure becomes a :class:`~harvest_qp.exceptions.SolverError` that
carries the QP; infeasibility is :class:`~harvest_qp.exceptions.InfeasibleProblemError`
in every backend. Every returned solution is checked: finite, and feasible to
:data:`FEASIBILITY_TOLERANCE` *relative to the scale of each row* (a row ``g x <= h``
is judged by ``(g x - h) / (1 + |h| + |g| |x|)``): an absolute tolerance rejected
DAQP solutions off by 2e-7..1e-6 on rows whose terms are ~1 (FINDINGS, "QP core").
A rejected solution raises :class:`SolverAccuracyError`; the solver then re-solves
the QP with a second backend.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

import numpy as np

from harvest_qp._daqp_native import NativeLayoutError, NativeModel, new_model
from harvest_qp._daqp_native import disable as disable_native
from harvest_qp.exceptions import InfeasibleProblemError, SolverError, SolverNotAvailableError
from harvest_qp.qp_kernels import load_daqp_rows, max_scaled_violation

if TYPE_CHECKING:
    from harvest_qp.solver import QPProblem

_INF = 1e30
#: Largest scale-relative constraint violation accepted in a returned solution
#: (see :func:`harvest_qp.qp_kernels.max_scaled_violation`).
FEASIBILITY_TOLERANCE = 1e-7
#: When every backend returns a solution outside :data:`FEASIBILITY_TOLERANCE`, the least
#: violating one is still used if it is within this (scale-relative: 1e-5 of a 1 m/s row is
#: 10 um/s) instead of braking the robot; the step's ``retries`` say so. Measured in closed
#: loop (audit, seed 8, tick 871): daqp 6.3e-7, and the tick braked.
ACCEPTABLE_VIOLATION = 1e-5


class SolverAccuracyError(SolverError):
    """A backend returned a solution outside the constraints by more than the tolerance."""


class SolverCyclingError(SolverError):
    """An active-set backend cycled or hit its iteration limit (DAQP exitflag -2 / -4)."""


class Backend(Protocol):
    """Solves one :class:`~harvest_qp.solver.QPProblem`, raising :class:`SolverError` on failure."""

    def solve(self, problem: QPProblem) -> np.ndarray: ...


def _checked(x, problem: QPProblem, backend: str) -> np.ndarray:
    if x is None:
        raise SolverError(f"{backend} returned no solution", problem=problem, backend=backend)
    violation = problem.scaled_violation(x)
    if violation == np.inf:
        raise SolverError(f"{backend} returned a non-finite solution", problem=problem, backend=backend)
    if violation > FEASIBILITY_TOLERANCE:
        error = SolverAccuracyError(
            f"{backend} returned a solution violating the constraints by {violation:.3g} (relative to row scale)",
            problem=problem,
            backend=backend,
        )
        error.x, error.violation = np.array(x, dtype=float), float(violation)  # for the last resort
        raise error
    return np.asarray(x, dtype=float)


class DaqpBackend:
    """DAQP with a persistent workspace (fastest exact backend measured here)."""

    name = "daqp"
    _FLAGS = {-1: "infeasible", -2: "cycling", -3: "unbounded", -4: "iteration limit", -5: "nonconvex",
              -6: "overdetermined initial active set"}

    def __init__(self) -> None:
        import daqp

        self._daqp = daqp
        self._model = None
        self._shape: tuple[int, int] | None = None

    def _allocate(self, n: int, n_in: int) -> None:
        # Fixed layout: n bounds, then n equality slots (padded), then the inequality rows.
        self._A = np.zeros((n + n_in, n))
        self._upper = np.full(2 * n + n_in, _INF)
        self._lower = np.full(2 * n + n_in, -_INF)
        self._sense = np.zeros(2 * n + n_in, dtype=np.int32)
        self._n_eq = 0
        #: The four layout buffers in the order the solver's fused kernels take them.
        self._layout = (self._A, self._upper, self._lower, self._sense)

    @staticmethod
    def _error(flag: int) -> type[SolverError]:
        if flag == -1:
            return InfeasibleProblemError
        if flag in (-2, -4):
            return SolverCyclingError
        return SolverError

    def _update_solve(self, problem: QPProblem, H: np.ndarray, f: np.ndarray, rows_changed: bool) -> np.ndarray:
        """The set-up model updated with ``H``, ``f`` and the rows already in this backend's buffers
        (``load_daqp_rows``), then solved; raises on a failure flag (no feasibility check here).
        The solver's fused levels call it when the model is set up for the problem's size
        (``_model`` not None, ``_shape == (n, n_in)``)."""
        if rows_changed:
            if type(self._model) is NativeModel:  # update and solve in one compiled call
                x, flag = self._model.update_solve(H, f, *self._layout)
                if flag < 0:
                    self._raise_failure(problem, flag)
                return x
            self._model.update(H=H, f=f, A=self._A, bupper=self._upper, blower=self._lower, sense=self._sense)
        else:  # only bounds and cost moved: skip copying the constraint matrix
            self._model.update(H=H, f=f, bupper=self._upper, blower=self._lower)
        return self._solve_model(problem)

    def _solve_model(self, problem: QPProblem) -> np.ndarray:
        x, _, flag, _ = self._model.solve()
        if flag < 0:
            self._raise_failure(problem, flag)
        return x

    def _raise_failure(self, problem: QPProblem, flag: int) -> None:
        """Drop the model (start from scratch next time: a bad active set is not reused) and raise."""
        self._model = None
        raise self._error(flag)(
            f"daqp failed: {self._FLAGS.get(flag, 'error')} (exitflag {flag})",
            problem=problem,
            backend=self.name,
            status=flag,
        )

    def solve(self, problem: QPProblem) -> np.ndarray:
        H, f, A_eq, G, h = problem.H, problem.f, problem.A, problem.G, problem.h
        box_lower, box_upper = problem.lower, problem.upper
        n, n_eq, n_in = H.shape[0], A_eq.shape[0], G.shape[0]
        shape = self._shape
        fresh = self._model is None or shape is None or shape[0] != n or shape[1] != n_in
        if fresh:
            self._allocate(n, n_in)
        A, upper, lower, sense = self._A, self._upper, self._lower, self._sense
        n_eq_before = self._n_eq
        rows_changed = fresh or n_in > 0 or n_eq > 0 or n_eq_before > 0
        # One compiled call writes the bounds, equality slots and inequality rows (ten numpy
        # slice assignments before: ~13 us per level inside the episode).
        self._n_eq = load_daqp_rows(
            A, upper, lower, sense, A_eq, problem.b, G, h, box_lower, box_upper, n_eq_before, _INF
        )
        if fresh:
            # DAQP's C API called directly when validated for this daqp (bit for bit daqp.Model)
            self._model = new_model(self._daqp)
            try:
                flag, _ = self._model.setup(problem.H, problem.f, A, upper, lower, sense)
            except NativeLayoutError as err:  # never seen: the self-test checks the same; use daqp.Model
                disable_native(f"setup: {err}")
                self._model = self._daqp.Model()
                flag, _ = self._model.setup(problem.H, problem.f, A, upper, lower, sense)
            self._shape = (n, n_in)
            if flag < 0:
                self._model = None
                raise self._error(flag)(
                    f"daqp setup failed: {self._FLAGS.get(flag, 'error')} (exitflag {flag})",
                    problem=problem,
                    backend=self.name,
                    status=flag,
                )
            x = self._solve_model(problem)
        else:
            x = self._update_solve(problem, H, f, rows_changed)
        # The check of _checked, without its conversions (x is DAQP's own float64 copy).
        violation = max_scaled_violation(x, box_lower, box_upper, A_eq, problem.b, G, h)
        if violation <= FEASIBILITY_TOLERANCE:
            return x
        return _checked(x, problem, self.name)  # raises with the message and the last-resort data


class ProxsuiteBackend:
    """proxsuite dense QP kept between steps, with settings that stay exact on collision rows."""

    name = "proxsuite"

    def __init__(self, *, eps_abs: float = 1e-9) -> None:
        import proxsuite

        self._proxsuite = proxsuite
        self._qp = None
        self._shape: tuple[int, int, int] | None = None
        self.eps_abs = eps_abs

    def solve(self, problem: QPProblem) -> np.ndarray:
        px = self._proxsuite.proxqp
        # Presolve: proxsuite mistakes trivially satisfied rows (padding, zero rows of
        # pairs a joint axis cannot move) for infeasibility, so drop them.
        keep = (problem.h < _INF / 2) & ~((np.abs(problem.G).max(axis=1, initial=0.0) < 1e-12) & (problem.h >= 0))
        G, h = problem.G[keep], problem.h[keep]
        n, n_eq, n_in = problem.n, problem.A.shape[0], G.shape[0]
        inf = 1e20
        l_box, u_box = np.maximum(problem.lower, -inf), np.minimum(problem.upper, inf)
        C = G if n_in else None
        u = h if n_in else None
        l = np.full(n_in, -inf) if n_in else None
        A = problem.A if n_eq else None
        b = problem.b if n_eq else None
        if self._qp is None or self._shape != (n, n_eq, n_in):
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
            qp.init(problem.H, problem.f, A, b, C, l, u, l_box, u_box)
            self._qp, self._shape = qp, (n, n_eq, n_in)
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
                problem=problem,
                backend=self.name,
                status=status,
            )
        return _checked(self._qp.results.x.copy(), problem, self.name)


class QuadprogBackend:
    """quadprog called directly (dense Goldfarb-Idnani); needs a positive definite Hessian."""

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
        keep = np.abs(bound) < _INF / 2
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
        return _checked(x, problem, self.name)


class QpsolversBackend:
    """Any :mod:`qpsolvers` backend; infinite bounds and inactive rows are dropped first."""

    def __init__(self, solver: str) -> None:
        import qpsolvers

        if solver not in qpsolvers.available_solvers:
            raise SolverNotAvailableError(
                f"qpsolvers backend {solver!r} is not installed; available: "
                f"{', '.join(sorted(qpsolvers.available_solvers))}. Install it, e.g. pip install {solver}",
                backend=solver,
            )
        self._qpsolvers = qpsolvers
        self.solver = solver
        self.name = f"qpsolvers:{solver}"

    def solve(self, problem: QPProblem) -> np.ndarray:
        n = problem.n
        eye = np.eye(n)
        G = np.vstack([problem.G, eye, -eye])
        h = np.concatenate([problem.h, problem.upper, -problem.lower])
        keep = h < _INF / 2
        G, h = (G[keep], h[keep]) if keep.any() else (None, None)  # some backends reject 0-row G
        P = 0.5 * (problem.H + problem.H.T)
        A = problem.A if problem.A.shape[0] else None
        b = problem.b if problem.A.shape[0] else None
        try:
            x = self._qpsolvers.solve_qp(
                P, problem.f, G, h, A, b, solver=self.solver
            )
        except Exception as err:  # every backend raises its own types
            raise SolverError(
                f"{self.name} raised {type(err).__name__}: {err}", problem=problem, backend=self.name
            ) from err
        if x is None:
            raise SolverError(f"{self.name} found no solution", problem=problem, backend=self.name)
        return _checked(x, problem, self.name)


def backend_name_problem(name: object) -> str | None:
    """Why ``name`` cannot name a QP backend (None when it can): checked when a solver is configured,
    so a typo is reported at once rather than as a fallback on every control step."""
    if not isinstance(name, str):
        return f"a QP backend name must be a string, got {name!r} ({type(name).__name__})"
    if name in ("daqp", "proxsuite", "quadprog"):
        return None
    if name.startswith("qpsolvers:"):
        import qpsolvers

        solver = name.split(":", 1)[1]
        if solver in qpsolvers.available_solvers:
            return None
        return (f"qpsolvers backend {solver!r} is not installed; available: "
                f"{', '.join(sorted(qpsolvers.available_solvers))}")
    return f"unknown QP backend {name!r}; use 'daqp', 'proxsuite', 'quadprog' or 'qpsolvers:<name>'"


def make_backend(name: str) -> Backend:
    """Backend by name: ``daqp``, ``proxsuite``, ``quadprog`` or ``qpsolvers:<solver>``."""
    if name == "daqp":
        return DaqpBackend()
    if name == "proxsuite":
        return ProxsuiteBackend()
    if name in ("quadprog", "qpsolvers:quadprog"):
        return QuadprogBackend()
    if name.startswith("qpsolvers:"):
        return QpsolversBackend(name.split(":", 1)[1])
    raise SolverNotAvailableError(
        f"unknown QP backend {name!r}; use 'daqp', 'proxsuite', 'quadprog' or 'qpsolvers:<name>' "
        "(e.g. 'qpsolvers:quadprog')",
        backend=name,
    )
