"""QP backends behind :class:`harvest_qp.solver.Solver`, one per file.

* ``daqp`` (default, :mod:`.daqp_backend`): a persistent ``daqp.Model`` set up once and
  updated each step.
* ``proxsuite`` (:mod:`.proxsuite_backend`): a kept ``proxqp.dense.QP`` with tight settings.
* ``quadprog`` (also ``qpsolvers:quadprog``, :mod:`.quadprog_backend`): called directly.
* ``qpsolvers:<name>`` (:mod:`.qpsolvers_backend`): any other backend of :mod:`qpsolvers`.

Every backend failure becomes a :class:`~harvest_qp.exceptions.SolverError` that carries the
QP; infeasibility is :class:`~harvest_qp.exceptions.InfeasibleProblemError` in every backend;
every returned solution is checked (:func:`.base.checked`).
"""

from __future__ import annotations

from harvest_qp.backends.base import (
    ACCEPTABLE_VIOLATION,
    FEASIBILITY_TOLERANCE,
    INF,
    Backend,
    SolverAccuracyError,
    SolverCyclingError,
    checked,
)
from harvest_qp.backends.daqp_backend import DaqpBackend
from harvest_qp.backends.proxsuite_backend import ProxsuiteBackend
from harvest_qp.backends.qpsolvers_backend import QpsolversBackend, available_solvers
from harvest_qp.backends.quadprog_backend import QuadprogBackend
from harvest_qp.exceptions import SolverNotAvailableError

#: The backends this package wraps itself; any other name must be ``"qpsolvers:<name>"``.
BUILT_IN = ("daqp", "proxsuite", "quadprog")
_USAGE = "use 'daqp', 'proxsuite', 'quadprog' or 'qpsolvers:<name>' (e.g. 'qpsolvers:quadprog')"


def backend_name_problem(name: object) -> str | None:
    """Why ``name`` cannot name a QP backend (None when it can): checked when a solver is configured,
    so a typo is reported at once rather than as a fallback on every control step."""
    if not isinstance(name, str):
        return f"a QP backend name must be a string, got {name!r} ({type(name).__name__})"
    if name in BUILT_IN:
        return None
    if name.startswith("qpsolvers:"):
        solver = name.split(":", 1)[1]
        available = available_solvers()
        if solver in available:
            return None
        return f"qpsolvers backend {solver!r} is not installed; available: {', '.join(available) or 'none'}"
    return f"unknown QP backend {name!r}; {_USAGE}"


def make_backend(name: str) -> Backend:
    """Backend by name: ``daqp``, ``proxsuite``, ``quadprog`` or ``qpsolvers:<solver>``."""
    if name == "daqp":
        return DaqpBackend()
    if name == "proxsuite":
        return ProxsuiteBackend()
    if name in ("quadprog", "qpsolvers:quadprog"):
        return QuadprogBackend()
    if isinstance(name, str) and name.startswith("qpsolvers:"):
        return QpsolversBackend(name.split(":", 1)[1])
    raise SolverNotAvailableError(f"unknown QP backend {name!r}; {_USAGE}", backend=str(name))


__all__ = [
    "ACCEPTABLE_VIOLATION",
    "BUILT_IN",
    "FEASIBILITY_TOLERANCE",
    "INF",
    "Backend",
    "DaqpBackend",
    "ProxsuiteBackend",
    "QpsolversBackend",
    "QuadprogBackend",
    "SolverAccuracyError",
    "SolverCyclingError",
    "backend_name_problem",
    "checked",
    "make_backend",
]
