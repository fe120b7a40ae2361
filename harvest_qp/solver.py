"""Build and solve the task-priority velocity QP: one strict-priority cascade.

For each priority level ``k = 1, 2, ...`` (in increasing order) the solver computes

    min_qdot  sum_{tasks at k} || W^1/2 (J qdot - v) ||^2 + qdot^T E qdot
    s.t.      lower <= qdot <= upper                    (joint limits)
              G qdot <= h                               (collision dampers)
              J_0 qdot = v_0                            (hard tasks, level 0)
              W_j^1/2 J_j qdot = W_j^1/2 J_j qdot_j*    (every level j < k)

so that a lower level only optimises within the optimal set of the levels above
it: a cascade of QPs (strict priorities). With a single soft level it is one QP.
Each task enters only through its public ``compute_rows(configuration, dt)`` (``J``, ``v``;
``J`` None for joint-space tasks) and ``weight``; each limit through ``fill_box`` (box
limits) or ``compute`` (rows ``G``, ``h``). The sizes of those rows are checked before the
compiled kernels index them without bounds checks: the task rows by the assembly kernels
themselves (a mismatch raises :class:`~harvest_qp.exceptions.DimensionError`), the limit rows
here. The equality rows of earlier levels are compressed to an orthonormal basis (a Householder
QR with column pivoting), so redundant rows never make the solver see dependent equalities.

``E`` is a diagonal regularization that only tops the Hessian's diagonal up to
``regularization`` where joint-space tasks (damping, posture) do not already put
that much weight: with a ``DampingTask`` of weight ``lambda^2 >= regularization``
the QP is exactly the damped least-squares problem (a constant ``eps I`` made
"QP == damped pseudo-inverse" wrong by 3.4e-5 at lambda = 1e-3, FINDINGS "QP core").

Robustness (nothing here runs when the first backend succeeds), all in :meth:`Solver._solve_level`
and :meth:`Solver._relaxed`:

1. A backend failure of any kind (accuracy, cycling, infeasibility report) is
   retried with the next backend of ``fallback_backends`` (quadprog called directly,
   then proxsuite with tight settings and a 1,000-iteration cap: at 10,000 iterations one
   failing proxsuite solve took seconds). When two exact active-set backends (DAQP and
   quadprog) both report infeasibility, the report goes straight to the relaxation check
   below instead of to proxsuite: on an infeasible QP proxsuite only stops at its
   iteration cap (measured 0.33 s per tick on the 2-core machine, in 61 of 400 fuzz
   states, none of which it solved). If the relaxation check then finds that no widening
   is needed (a false report), the QP is solved again with every backend, proxsuite included.
2. When every backend fails, the problem is checked for a relaxation: the
   acceleration box (priority >= :data:`RELAXABLE_PRIORITY`) is widened by the least
   amount (a slack QP, ``min ||s||^2``) that makes the safety constraints
   feasible, and the separation speed that collision rows ask of pairs already
   inside the safety distance is lowered, at most to "no further approach", by the
   least amount that fits in that box. Only when even that is infeasible (e.g. a
   hard task beyond the speed limit) is the failure reported (a
   :class:`~harvest_qp.exceptions.SolverError` carrying the QP).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from harvest_qp.backends import (
    ACCEPTABLE_VIOLATION,
    INF,
    Backend,
    SolverAccuracyError,
    backend_name_problem,
    make_backend,
)
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import (
    DimensionError,
    InfeasibleProblemError,
    InvalidInputError,
    SolverError,
    SolverNotAvailableError,
)
from harvest_qp.limits.limit import Limit, check_limit_output, check_limits
from harvest_qp.qp_kernels import (
    accumulate_diagonal,
    accumulate_task,
    clip_inplace,
    intersect_boxes,
    max_scaled_violation,
    max_violation,
    orthonormal_rows_qr,
    top_up_diagonal,
    weighted_rows,
)
from harvest_qp.tasks.task import HARD, Task, check_tasks
from harvest_qp.validation import as_positive_scalar, as_vector, check_task_rows

#: Box limits from this priority on (acceleration limits) yield to infeasibility.
RELAXABLE_PRIORITY = 2
#: Widening [rad/s] added on top of the least relaxation so the re-solved QP is not degenerate.
RELAXATION_MARGIN = 1e-9
#: Widening [rad/s] below which the least relaxation is taken as none (stage 1's noise is ~1e-11).
RELAXATION_TOLERANCE = 1e-9
#: Backends tried, in order, after the chosen one fails (those not installed are skipped).
DEFAULT_FALLBACK_BACKENDS = ("quadprog", "proxsuite")
#: Infeasibility reports from this many backends are believed without asking the rest
#: (the relaxation check that follows still catches a false report; see the module docstring).
CONFIRMING_REPORTS = 2
#: Relative rank tolerance of the orthonormal equality rows a level hands on.
RANK_TOLERANCE = 1e-9


@dataclass
class QPProblem:
    """One QP ``min 1/2 x^T H x + f^T x`` s.t. ``lower <= x <= upper``, ``A x = b``, ``G x <= h``.

    Kept whole in :class:`~harvest_qp.exceptions.SolverError` so a failure can be replayed.
    """

    H: np.ndarray
    f: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    A: np.ndarray
    b: np.ndarray
    G: np.ndarray
    h: np.ndarray
    level: int = 1

    @property
    def n(self) -> int:
        return self.H.shape[0]

    def copy(self) -> QPProblem:
        """A deep copy."""
        return QPProblem(**{k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in vars(self).items()})

    def violation(self, x: np.ndarray) -> float:
        """Largest absolute constraint violation of ``x`` (0 when feasible)."""
        return max_violation(np.asarray(x, dtype=float), self.lower, self.upper, self.A, self.b, self.G, self.h)

    def scaled_violation(self, x: np.ndarray) -> float:
        """Largest violation of ``x``, each row relative to its scale (see ``max_scaled_violation``)."""
        return max_scaled_violation(
            np.asarray(x, dtype=float), self.lower, self.upper, self.A, self.b, self.G, self.h
        )


@dataclass
class BoxConflict:
    """A joint whose limit boxes did not overlap; the earlier (higher-priority) limit won."""

    joint: int
    limit: str


@dataclass
class Solution:
    """Result of :meth:`Solver.solve`: joint velocities [rad/s] and what the solver saw."""

    qdot: np.ndarray | None
    problems: list[QPProblem] = field(default_factory=list)
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    conflicts: list[BoxConflict] = field(default_factory=list)
    relaxed: list[str] = field(default_factory=list)
    """Limits relaxed because the QP was infeasible with them (acceleration limits)."""
    box_relaxation: np.ndarray | None = None
    """Per joint, how far [rad/s] the relaxable box was widened (None: not relaxed)."""
    row_relaxation: np.ndarray | None = None
    """Per inequality row, how much [m/s] of the separation speed asked was given up."""
    retries: list[str] = field(default_factory=list)
    """Backend failures that a later backend recovered, e.g. ``"daqp: SolverCyclingError"``."""


# ---------------------------------------------------------------------- the QP's parts
def combine_boxes(box_limits: Sequence[Limit], lowers: np.ndarray, uppers: np.ndarray, n: int):
    """Intersect velocity boxes [rad/s] in priority order; later boxes yield where they conflict.

    ``box_limits`` in priority order, row ``i`` of ``lowers`` / ``uppers`` the box of ``box_limits[i]``.
    Returns ``(lower, upper, conflicts)``; a conflict names the joint and the limit that yielded.
    """
    if not box_limits:
        return np.full(n, -INF), np.full(n, INF), []
    lower, upper = np.empty(n), np.empty(n)
    conflict = np.empty(n, dtype=np.int64)
    conflicts = []
    if intersect_boxes(lowers, uppers, lower, upper, conflict):
        conflicts = [BoxConflict(int(j), type(box_limits[conflict[j]]).__name__) for j in np.flatnonzero(conflict >= 0)]
    return lower, upper, conflicts


def orthonormal_rows(A: np.ndarray, x: np.ndarray, tol: float = RANK_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal, independent rows ``Q`` spanning the rows of ``A``, and ``Q x``: ``{y : Q y = Q x}``
    is ``{y : A y = A x}`` without dependent rows.

    A Householder QR of ``A^T`` with column pivoting (:func:`orthonormal_rows_qr`), rank from
    its pivots ``|R_kk| > tol max(1, |R_00|)`` (the SVD of the paper's 11 x 12 level-1 rows cost
    ~20 us, the compiled QR ~2 us; same span, another orthonormal basis of it).
    """
    if A.shape[0] == 0:
        return A, np.zeros(0)
    k = min(A.shape)
    rows, rhs = np.empty((k, A.shape[1])), np.empty(k)
    rank = orthonormal_rows_qr(np.ascontiguousarray(A, dtype=float), x, tol, rows, rhs)
    return rows[:rank], rhs[:rank]


def least_squares_rows(A: np.ndarray, b: np.ndarray, tol: float = RANK_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal equality rows for hard tasks ``A x = b`` that need not be consistent.

    The SVD basis of ``A``'s row space with ``b`` projected on its range: two hard tasks that
    ask for different things get the least-squares compromise (independent of their order).
    :func:`orthonormal_rows` (pivoted QR) is only for the rows a level hands on (held at its optimum).
    """
    if A.shape[0] == 0:
        return A, b
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    rank = int(np.sum(s > tol * max(1.0, s[0])))
    return Vt[:rank], (U[:, :rank].T @ b) / s[:rank]


def level_equalities(A: np.ndarray, entries, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal equality rows that hold a level's optimum ``x`` for the levels below it.

    ``A`` (the rows of the levels above) stacked over each task's weighted rows ``sqrt(w_r) J_r``
    (``w_r > 0``; ``J`` None is the identity), with ``rows @ x`` as right-hand side.
    """
    n = x.shape[0]
    m = A.shape[0] + sum([task.weight.shape[0] for task, _, _ in entries])
    rows = np.empty((m, n))
    end = A.shape[0]
    rows[:end] = A
    for task, J, _ in entries:
        end = weighted_rows(_identity(n) if J is None else J, task.weight, rows, end)
    return orthonormal_rows(rows[:end], x)


_IDENTITIES: dict[int, np.ndarray] = {}


def _identity(n: int) -> np.ndarray:
    """A read-only ``I`` (n x n), made once per size."""
    eye = _IDENTITIES.get(n)
    if eye is None:
        eye = _IDENTITIES[n] = np.eye(n)
        eye.flags.writeable = False
    return eye


def assemble_level(entries, n: int, regularization: float) -> tuple[np.ndarray, np.ndarray]:
    """``H``, ``f`` of one level: ``sum_tasks J^T W J``, ``-J^T W v``, the diagonal topped up to ``regularization``.

    The top-up only adds where the level's joint-space tasks put less weight on a joint, so a
    damped problem stays exactly the damped least-squares problem.
    """
    H, f, floor = np.zeros((n, n)), np.zeros(n), np.zeros(n)
    for task, J, v in entries:
        try:  # the kernels check the sizes themselves (they index without bounds checks)
            fits = (accumulate_diagonal(H, f, task.weight, v, floor) if J is None  # joint-space task: J = I
                    else accumulate_task(H, f, J, task.weight, v))
        except Exception as err:  # noqa: BLE001 - numba refuses rows that are not arrays of numbers
            check_task_rows(task, J, v, n)
            raise InvalidInputError(f"{task!r} computed rows the solver cannot use (J {_describe_rows(J)}, "
                                    f"v {_describe_rows(v)}): {type(err).__name__}") from None
        if not fits:
            check_task_rows(task, J, v, n)  # raises DimensionError naming the task and the shapes
            raise DimensionError(f"{task!r} rows do not fit the model (nv = {n}): J {_describe_rows(J)}, "
                                 f"v {_describe_rows(v)}")  # the kernel refused what the check let through
    top_up_diagonal(H, floor, regularization if entries else max(regularization, 1e-12))
    return H, f


def _describe_rows(rows) -> str:
    return f"{rows.dtype} {rows.shape}" if isinstance(rows, np.ndarray) else type(rows).__name__


def _is_separating(limit: Limit) -> bool:
    return bool(getattr(limit, "separation_rows", False))


class Solver:
    """Reusable QP solver: keeps each backend's workspace (per level) between control steps.

    Args:
        backend: ``"daqp"`` (default, persistent model), ``"proxsuite"`` (dense, with
            settings that stay exact on collision rows), ``"quadprog"`` or any
            :mod:`qpsolvers` backend name prefixed by ``"qpsolvers:"``.
        regularization: smallest diagonal entry of every level's Hessian: where
            joint-space tasks put less weight on a joint, the difference is added
            (keeps the Hessian definite without perturbing damped problems).
        fallback_backends: backends tried in order when ``backend`` fails
            (default: quadprog, then proxsuite; those not installed are skipped).
        backend_factory: ``factory(name, level)`` makes the backend ``name`` for priority ``level``
            (one workspace per level, kept between steps; ``level`` None: a fresh one for a
            relaxation QP). Default: :func:`~harvest_qp.backends.make_backend` ``(name)``. A hook to
            configure or wrap backends (e.g. a stand-in that fails, to test the fallbacks).
    """

    def __init__(
        self,
        backend: str = "daqp",
        *,
        regularization: float = 1e-10,
        fallback_backends: Sequence[str] | None = None,
        backend_factory: Callable[[str, int | None], Backend] | None = None,
    ) -> None:
        problem = backend_name_problem(backend)
        if problem is not None:
            raise SolverNotAvailableError(f"backend: {problem}", backend=str(backend))
        for name in () if fallback_backends is None else fallback_backends:
            if not isinstance(name, str) or (not name.startswith("qpsolvers:")
                                             and backend_name_problem(name) is not None):
                # an uninstalled qpsolvers fallback is skipped at run time; a typo is an error
                raise SolverNotAvailableError(f"fallback_backends: {backend_name_problem(name)}", backend=str(name))
        self.backend_name = backend
        self.regularization = as_positive_scalar(regularization, "regularization", allow_zero=True)
        names = DEFAULT_FALLBACK_BACKENDS if fallback_backends is None else tuple(fallback_backends)
        self.fallback_backends = tuple(name for name in names if name != backend)
        self._make = backend_factory if backend_factory is not None else (lambda name, level: make_backend(name))
        self._backends: dict[tuple[str, int], Backend] = {}
        self._unavailable: set[str] = set()
        self._key: tuple | None = None  # the task and limit lists last checked (see _checked)
        self._lists: tuple[list[Task], list[Limit], list[tuple[Limit, bool]]] = ([], [], [])

    def _backend(self, name: str, level: int) -> Backend:
        """The backend ``name`` for priority ``level`` (one workspace per level, kept between steps)."""
        backend = self._backends.get((name, level))
        if backend is None:
            backend = self._backends[name, level] = self._make(name, level)
        return backend

    # ------------------------------------------------------------------ public
    def solve(
        self,
        configuration: Configuration,
        tasks: Sequence[Task],
        limits: Sequence[Limit] = (),
        dt: float = 0.002,
        *,
        previous_qdot: np.ndarray | None = None,
    ) -> Solution:
        """Joint velocities [rad/s] for the tasks under the limits at the current state.

        Acceleration limits (box priority >= 2) yield to the safety limits by the least
        amount needed (``Solution.relaxed`` names them, ``Solution.box_relaxation``
        says by how much); see the module docstring.

        Raises:
            InvalidInputError: no task, a non-Task among the tasks or a non-Limit among the
                limits (the message names its position and type), a bad ``dt`` or ``previous_qdot``.
            SolverError: every backend failed (the exception carries the QP).
            InfeasibleProblemError: the safety constraints admit no solution even
                with the acceleration limits relaxed.
        """
        tasks, box_limits, row_limits = self._checked(tasks, limits)
        dt = as_positive_scalar(dt, "dt")
        n = configuration.nv
        if previous_qdot is not None:  # a private copy: the limits (user code too) get it
            previous_qdot = as_vector(previous_qdot, n, "previous_qdot")

        # Boxes, in priority order (velocity, position, acceleration, ...).
        lowers, uppers = np.empty((len(box_limits), n)), np.empty((len(box_limits), n))
        for limit, lower_row, upper_row in zip(box_limits, lowers, uppers):
            try:
                limit.fill_box(configuration, dt, previous_qdot, lower_row, upper_row)
            except (ValueError, IndexError) as err:  # numpy's words for a box of the wrong size
                raise DimensionError(f"{type(limit).__name__}.fill_box failed ({err}): it must write {n} entries "
                                     "[rad/s] into lower and upper") from err
        lower, upper, conflicts = combine_boxes(box_limits, lowers, uppers, n)

        # Inequality rows G x <= h, and which of them ask for separation (relaxable).
        G_rows, h_rows, separating = [], [], []  # separating: (row count, asks for separation) per limit
        for limit, separates in row_limits:
            rows = limit.compute(configuration, dt, previous_qdot)
            check_limit_output(limit, rows, n)  # user code; the kernels below do not check bounds
            if rows.lower is not None:
                raise InvalidInputError(
                    f"{type(limit).__name__}.compute returned a box: set has_box = True on the class "
                    "(and override fill_box for speed)"
                )
            if rows.G is not None:
                G_rows.append(rows.G)
                h_rows.append(rows.h)
                separating.append((rows.h.shape[0], separates))
        if len(G_rows) == 1:  # (the usual case: one collision limit; no copy)
            G, h = G_rows[0], h_rows[0]
        elif G_rows:
            G, h = np.vstack(G_rows), np.concatenate(h_rows)
        else:
            G, h = np.zeros((0, n)), np.zeros(0)

        # The tasks' rows, grouped by level.
        by_level: dict[int, list] = {}
        for task in tasks:
            rows = task.compute_rows(configuration, dt)
            try:
                J, v = rows
            except (TypeError, ValueError) as err:
                raise InvalidInputError(f"{task!r}.compute_rows must return the pair (J, v): {err}") from None
            by_level.setdefault(task.level, []).append((task, J, v))
        hard = by_level.pop(HARD, None)
        A, b = self._hard_equalities(hard, n) if hard else (np.zeros((0, n)), np.zeros(0))
        levels = [(level, by_level[level]) for level in sorted(by_level)] or [(1, [])]

        retries: list[str] = []
        try:
            solution = self._cascade(levels, lower, upper, A, b, G, h, retries, CONFIRMING_REPORTS)
        except SolverNotAvailableError:
            raise
        except SolverError as err:
            solution = self._relaxed(err, levels, box_limits, lowers, uppers, lower, upper, A, b, G, h,
                                     separating, retries)
        solution.conflicts = conflicts
        return solution

    def _checked(self, tasks, limits) -> tuple[list[Task], list[Limit], list[tuple[Limit, bool]]]:
        """The tasks, the box limits in priority order and the row limits (with whether their rows ask
        for separation), checked when a list changes.

        A list is checked (each item a Task / a Limit) and its limits sorted only when its items
        differ from the last call's (compared by identity), not at every control step.
        """
        key = (tuple(tasks), tuple(limits)) if isinstance(tasks, list | tuple) and isinstance(limits, list | tuple) \
            else None
        if key is None or key != self._key:
            tasks, limits = check_tasks(tasks), check_limits(limits)
            box_limits = sorted((limit for limit in limits if limit.has_box), key=lambda limit: limit.priority)
            row_limits = [(limit, _is_separating(limit)) for limit in limits if not limit.has_box]
            self._key = (tuple(tasks), tuple(limits))
            self._lists = (tasks, box_limits, row_limits)
        return self._lists

    # ------------------------------------------------------------------ the cascade
    def _cascade(self, levels, lower, upper, A, b, G, h, retries, confirm=None) -> Solution:
        """Solve the levels in order, each within the optimal set of those before."""
        n = lower.shape[0]
        problems = []
        x = None
        for i, (level, entries) in enumerate(levels):
            H, f = assemble_level(entries, n, self.regularization)
            problem = QPProblem(H=H, f=f, lower=lower, upper=upper, A=A, b=b, G=G, h=h, level=level)
            problems.append(problem)
            # Backends meet bounds to their tolerance; clip so joint limits hold exactly.
            x = clip_inplace(self._solve_level(level, problem, retries, confirm), lower, upper)
            if i + 1 < len(levels) and entries:
                # The optimal set of this level: its weighted task velocities stay as found.
                A, b = level_equalities(A, entries, x)
        return Solution(qdot=x, problems=problems, lower=lower, upper=upper, retries=retries)

    def _solve_level(self, level: int, problem: QPProblem, retries: list[str], confirm: int | None) -> np.ndarray:
        """Solve with the chosen backend, then with each fallback backend, until one succeeds.

        With ``confirm``, stop after that many backends reported infeasibility (believed). When
        every backend only missed the tolerance, the least violating answer within
        :data:`ACCEPTABLE_VIOLATION` is taken (``retries`` says so); else the first failure is raised.
        """
        failures, reports, inaccurate, first = [], 0, [], None
        for name in (self.backend_name, *self.fallback_backends):
            if name in self._unavailable:
                continue
            if confirm is not None and reports >= confirm:
                break
            try:
                x = self._backend(name, level).solve(problem)
            except SolverNotAvailableError:
                if name == self.backend_name:
                    raise  # a misconfigured backend is reported, not papered over
                self._unavailable.add(name)
                continue
            except SolverError as err:
                if first is None:
                    first = err
                    first.problem = problem.copy()
                failures.append(f"{name}: {type(err).__name__}")
                reports += isinstance(err, InfeasibleProblemError)
                if isinstance(err, SolverAccuracyError):
                    inaccurate.append((err.violation, err.x, name))
                continue
            if failures:
                retries.extend(failures)
            return x
        if inaccurate:
            violation, x, name = min(inaccurate, key=lambda item: item[0])
            if violation <= ACCEPTABLE_VIOLATION:
                retries.extend([*failures, f"accepted {name} at {violation:.1e} relative violation"])
                return x
        raise first

    def _hard_equalities(self, hard, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Orthonormal equality rows of the hard tasks' ``(task, J, v)`` (``J`` None: ``I``)."""
        for task, J, v in hard:
            # These rows reach the backends' kernels without the assembly kernels' size check.
            check_task_rows(task, J, v, n)
            if not (np.isrealobj(v) and (J is None or np.isrealobj(J))):
                raise InvalidInputError(f"hard task {task!r} (level 0) computed rows that are not real numbers "
                                        f"(J {_describe_rows(J)}, v {_describe_rows(v)})")
            # A hard task must be met exactly: a non-finite target is an error, not a
            # problem daqp refuses and a retry quietly drops (an audit found the latter).
            if not (np.all(np.isfinite(v)) and (J is None or np.all(np.isfinite(J)))):
                raise InvalidInputError(
                    f"hard task {type(task).__name__} (level 0) computed non-finite rows: target {v.tolist()}"
                )
        A = np.vstack([(np.eye(n) if J is None else J)[t.weight > 0] for t, J, _ in hard])
        b = np.concatenate([v[t.weight > 0] for t, _, v in hard])
        return least_squares_rows(A, b)

    # ------------------------------------------------------------------ relaxation
    def _relaxed(self, err, levels, box_limits, lowers, uppers, lower, upper, A, b, G, h, separating,
                 retries) -> Solution:
        """The cascade after it failed with ``err``: under the least relaxation, or ``err`` raised.

        ``separating``: ``(row count, whether the rows ask for separation)`` of each row limit, in row order.
        """
        separating = np.array([flag for count, flag in separating for _ in range(count)], dtype=bool)
        # The safety boxes (speed, position) come first in priority order.
        k = sum(limit.priority < RELAXABLE_PRIORITY for limit in box_limits)
        safe_lower, safe_upper, _ = combine_boxes(box_limits[:k], lowers[:k], uppers[:k], lower.shape[0])
        # First ignore a widening below the solvers' noise; if that leaves the QP
        # infeasible after all, take the widening exactly as computed.
        for tolerance in (RELAXATION_TOLERANCE, 0.0):
            relaxed = self._least_relaxation(safe_lower, safe_upper, lower, upper, A, b, G, h, separating, tolerance)
            if relaxed is None:
                continue
            lower2, upper2, h2, box_slack, row_slack = relaxed
            try:
                solution = self._cascade(levels, lower2, upper2, A, b, G, h2, retries)
                break
            except SolverError:
                continue
        else:
            raise err from None
        if np.any(box_slack > 0):
            solution.relaxed = [type(limit).__name__ for limit in box_limits if limit.priority >= RELAXABLE_PRIORITY]
        solution.box_relaxation = box_slack
        solution.row_relaxation = row_slack
        return solution

    def _least_relaxation(self, safe_lower, safe_upper, lower, upper, A, b, G, h, separating, tolerance=0.0):
        """Least widening of the relaxable box, then least separation given up, that make the QP feasible.

        Stage 1: ``min ||s||^2`` over ``(x, s)`` with ``x`` in the safety box (speed and
        position limits), ``lower - s <= x <= upper + s``, ``A x = b`` and ``G x <= h``
        where separating rows ask at most "no further approach" (``h >= 0``). At a
        collision-free state inside the limits ``x = 0`` is feasible, so this never fails there.
        Stage 2 (rows with ``h < 0`` only): within the widened box, ``min ||t||^2`` with
        ``G x <= h + t``, ``0 <= t <= -h``: as much separation as the box allows.

        A widening of at most ``tolerance`` [rad/s] is taken as zero (solver noise: stage 1
        returns ~1e-11 where no widening is needed).

        Returns ``(lower, upper, h, box_slack, row_slack)`` or None when even this is infeasible.
        """
        n, m = lower.shape[0], G.shape[0]
        h_floor = np.where(separating & (h < 0), 0.0, h)
        eye = np.eye(n)
        # Stage 1 over z = [x, s].
        finite_lo, finite_hi = lower > -INF / 2, upper < INF / 2
        G1 = np.vstack([
            np.hstack([G, np.zeros((m, n))]),
            np.hstack([eye, -eye])[finite_hi],
            np.hstack([-eye, -eye])[finite_lo],
        ])
        h1 = np.concatenate([h_floor, upper[finite_hi], -lower[finite_lo]])
        stage1 = QPProblem(
            H=np.diag(np.concatenate([np.full(n, 1e-9), np.ones(n)])), f=np.zeros(2 * n),
            lower=np.concatenate([safe_lower, np.zeros(n)]), upper=np.concatenate([safe_upper, np.full(n, INF)]),
            A=np.hstack([A, np.zeros((A.shape[0], n))]), b=b, G=G1, h=h1,
        )
        z = self._solve_auxiliary(stage1)
        if z is None:
            return None
        box_slack = np.maximum(z[n:], 0.0)
        box_slack = np.where(box_slack > tolerance, box_slack + RELAXATION_MARGIN, 0.0)
        lower2 = np.maximum(lower - box_slack, safe_lower)
        upper2 = np.minimum(upper + box_slack, safe_upper)
        row_slack = np.zeros(m)
        asking = np.flatnonzero(separating & (h < 0))
        if asking.size:
            p = asking.size
            E = np.zeros((m, p))
            E[asking, np.arange(p)] = 1.0
            stage2 = QPProblem(
                H=np.diag(np.concatenate([np.full(n, 1e-9), np.ones(p)])), f=np.zeros(n + p),
                lower=np.concatenate([lower2, np.zeros(p)]), upper=np.concatenate([upper2, -h[asking]]),
                A=np.hstack([A, np.zeros((A.shape[0], p))]), b=b, G=np.hstack([G, -E]), h=h.copy(),
            )
            z2 = self._solve_auxiliary(stage2)
            if z2 is None:
                return None
            t = np.clip(z2[n:], 0.0, -h[asking])
            row_slack[asking] = np.minimum(t + RELAXATION_MARGIN, -h[asking])
        return lower2, upper2, h + row_slack, box_slack, row_slack

    def _solve_auxiliary(self, problem: QPProblem) -> np.ndarray | None:
        """A relaxation QP with each backend in turn (fresh workspaces); None when all report failure.

        Infeasibility reported by :data:`CONFIRMING_REPORTS` backends is believed.
        """
        reports = 0
        for name in (self.backend_name, *self.fallback_backends):
            if name in self._unavailable:
                continue
            if reports >= CONFIRMING_REPORTS:
                break
            try:
                return self._make(name, None).solve(problem)
            except SolverNotAvailableError:
                self._unavailable.add(name)
            except InfeasibleProblemError:
                reports += 1
            except SolverError:
                continue
        return None


def solve_ik(
    configuration: Configuration,
    tasks: Sequence[Task],
    limits: Sequence[Limit] = (),
    dt: float = 0.002,
    *,
    solver: str = "daqp",
    previous_qdot: np.ndarray | None = None,
) -> np.ndarray:
    """One-shot convenience: joint velocities [rad/s] solving the task QP (see :class:`Solver`)."""
    return Solver(solver).solve(configuration, tasks, limits, dt, previous_qdot=previous_qdot).qdot


__all__ = [
    "INF", "BoxConflict", "QPProblem", "Solution", "Solver", "solve_ik", "SolverError", "InfeasibleProblemError",
]
