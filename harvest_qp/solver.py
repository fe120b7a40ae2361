"""Build and solve the task-priority velocity QP.

For each priority level ``k = 1, 2, ...`` (in increasing order) the solver computes

    min_qdot  sum_{tasks at k} || W^1/2 (J qdot - v) ||^2 + eps ||qdot||^2
    s.t.      lower <= qdot <= upper                    (joint limits)
              G qdot <= h                               (collision dampers)
              J_0 qdot = v_0                            (hard tasks, level 0)
              W_j^1/2 J_j qdot = W_j^1/2 J_j qdot_j*    (every level j < k)

so that a lower level only optimises within the optimal set of the levels above
it: a cascade of QPs (strict priorities). With a single soft level it is one QP.
The equality rows of earlier levels are compressed to an orthonormal basis (an SVD),
so redundant rows never make the solver see dependent equalities.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from harvest_qp.backends import Backend, make_backend
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InfeasibleProblemError, InvalidInputError, SolverError
from harvest_qp.limits.limit import Limit
from harvest_qp.qp_kernels import (
    accumulate_diagonal,
    accumulate_task,
    add_to_diagonal,
    clip_inplace,
    intersect_boxes,
    max_violation,
)
from harvest_qp.tasks.task import HARD, Task
from harvest_qp.validation import as_positive_scalar, as_vector

#: Bound magnitude that stands for "no bound" in the QP data.
INF = 1e30
#: Box limits from this priority on (acceleration limits) yield to infeasibility.
RELAXABLE_PRIORITY = 2


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
        """A deep copy (the solver reuses some buffers between steps)."""
        return QPProblem(**{k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in vars(self).items()})

    def violation(self, x: np.ndarray) -> float:
        """Largest constraint violation of ``x`` (0 when feasible)."""
        return max_violation(np.asarray(x, dtype=float), self.lower, self.upper, self.A, self.b, self.G, self.h)


@dataclass
class BoxConflict:
    """A joint whose limit boxes did not overlap; the earlier (higher-priority) limit won."""

    joint: int
    limit: str


@dataclass
class Solution:
    """Result of :func:`solve_ik`: joint velocities [rad/s] and what the solver saw."""

    qdot: np.ndarray | None
    problems: list[QPProblem] = field(default_factory=list)
    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    conflicts: list[BoxConflict] = field(default_factory=list)
    relaxed: list[str] = field(default_factory=list)
    """Limits dropped because the QP was infeasible with them (acceleration limits)."""


def _priority(item) -> int:
    return item[0].priority


def combine_boxes(limits_rows: list[tuple[Limit, np.ndarray, np.ndarray]], n: int):
    """Intersect velocity boxes in priority order; later boxes yield where they conflict.

    Returns ``(lower, upper, conflicts)``; a conflict names the joint and the limit that yielded.
    """
    ordered = sorted(limits_rows, key=_priority)
    if not ordered:
        return _intersect([], np.zeros((0, n)), np.zeros((0, n)), n)
    lowers = np.array([lo for _, lo, _ in ordered])
    uppers = np.array([hi for _, _, hi in ordered])
    return _intersect([limit for limit, _, _ in ordered], lowers, uppers, n)


def _intersect(box_limits: list[Limit], lowers: np.ndarray, uppers: np.ndarray, n: int):
    """:func:`combine_boxes` on rows already in priority order (row i belongs to ``box_limits[i]``)."""
    if not box_limits:
        return np.full(n, -INF), np.full(n, INF), []
    lower, upper = np.empty(n), np.empty(n)  # the kernel writes every entry
    conflicts = []
    conflict = np.empty(n, dtype=np.int64)
    if intersect_boxes(lowers, uppers, lower, upper, conflict):
        conflicts = [BoxConflict(int(j), type(box_limits[conflict[j]]).__name__) for j in np.flatnonzero(conflict >= 0)]
    return lower, upper, conflicts


def _orthonormal_rows(A: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Equivalent equality rows with orthonormal, independent rows (for consistent ``A x = b``)."""
    if A.shape[0] == 0:
        return A, b
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    rank = int(np.sum(s > tol * max(1.0, s[0])))
    return Vt[:rank], (U[:, :rank].T @ b) / s[:rank]


class Solver:
    """Reusable QP solver: keeps the backend's workspace between control steps.

    Args:
        backend: ``"daqp"`` (default, persistent model), ``"proxsuite"`` (dense, with
            settings that stay exact on collision rows) or any :mod:`qpsolvers`
            backend name prefixed by ``"qpsolvers:"`` (e.g. ``"qpsolvers:quadprog"``).
        regularization: ``eps`` added to the Hessian diagonal (keeps it definite).
    """

    def __init__(self, backend: str = "daqp", *, regularization: float = 1e-10) -> None:
        self.backend_name = backend
        self._backends: dict[int, Backend] = {}
        self._box_key: tuple = ()
        self._box_list: list[Limit] = []
        self.regularization = as_positive_scalar(regularization, "regularization", allow_zero=True)

    def _backend(self, level: int) -> Backend:
        if level not in self._backends:
            self._backends[level] = make_backend(self.backend_name)
        return self._backends[level]

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

        Acceleration limits (box priority >= 2) yield to the safety limits: when the
        QP is infeasible with them (an arm too fast to brake before an obstacle) it is
        solved again without them and ``Solution.relaxed`` names what was dropped.

        Raises:
            SolverError: the backend failed (the exception carries the QP).
            InfeasibleProblemError: the safety constraints admit no solution.
        """
        dt = as_positive_scalar(dt, "dt")
        if previous_qdot is not None:
            previous_qdot = as_vector(previous_qdot, configuration.nv, "previous_qdot")
        return self._solve(configuration, tasks, limits, dt, previous_qdot)

    def _solve(self, configuration, tasks, limits, dt: float, previous_qdot: np.ndarray | None) -> Solution:
        """:meth:`solve` with ``dt`` and ``previous_qdot`` already validated (the controller's path)."""
        n = configuration.nv
        box_limits = self._box_limits(limits, n)
        for i, limit in enumerate(box_limits):
            limit.fill_box(configuration, dt, previous_qdot, self._lowers[i], self._uppers[i])
        G_rows, h_rows = [], []
        for limit in limits:
            if limit.has_box:
                continue
            rows = limit.compute(configuration, dt, previous_qdot)
            if rows.lower is not None:
                raise InvalidInputError(
                    f"{type(limit).__name__}.compute returned a box: set has_box = True on the class "
                    "(and override fill_box for speed)"
                )
            if rows.G is not None:
                G_rows.append(rows.G)
                h_rows.append(rows.h)
        if len(G_rows) == 1:
            G, h = G_rows[0], h_rows[0]
        elif G_rows:
            G, h = np.vstack(G_rows), np.concatenate(h_rows)
        else:
            G, h = np.zeros((0, n)), np.zeros(0)

        by_level: dict[int, list[tuple[Task, np.ndarray | None, np.ndarray]]] = {}
        for task in tasks:
            J, v = task.compute_rows(configuration, dt)
            by_level.setdefault(task.level, []).append((task, J, v))
        hard = by_level.pop(HARD, None)
        if hard:
            hard = [(t, np.eye(n) if J is None else J, v) for t, J, v in hard]
            A, b = _orthonormal_rows(
                np.vstack([J[t.weight > 0] for t, J, _ in hard]), np.concatenate([v[t.weight > 0] for t, _, v in hard])
            )
        else:
            A, b = np.zeros((0, n)), np.zeros(0)
        try:
            return self._cascade(n, by_level, box_limits, A, b, G, h)
        except InfeasibleProblemError:
            # Box limits are sorted by priority: the relaxable ones are the tail.
            safe = [limit for limit in box_limits if limit.priority < RELAXABLE_PRIORITY]
            if len(safe) == len(box_limits):
                raise
            solution = self._cascade(n, by_level, safe, A, b, G, h)
            solution.relaxed = [type(limit).__name__ for limit in box_limits[len(safe) :]]
            return solution

    def _box_limits(self, limits: Sequence[Limit], n: int) -> list[Limit]:
        """The box limits in priority order, with row buffers for their boxes (cached)."""
        key = (n, *map(id, limits))
        if key != self._box_key:
            self._box_key = key
            self._box_list = sorted((limit for limit in limits if limit.has_box), key=lambda lim: lim.priority)
            self._lowers = np.empty((max(len(self._box_list), 1), n))
            self._uppers = np.empty((max(len(self._box_list), 1), n))
        return self._box_list

    def _cascade(self, n, by_level, box_limits, A, b, G, h) -> Solution:
        """Solve the levels in order, each within the optimal set of those before."""
        k = len(box_limits)
        lower, upper, conflicts = _intersect(box_limits, self._lowers[:k], self._uppers[:k], n)
        solution = Solution(qdot=None, lower=lower, upper=upper, conflicts=conflicts)
        levels = sorted(by_level) or [1]
        for level in levels:
            entries = by_level.get(level, [])
            H = np.zeros((n, n))
            add_to_diagonal(H, self.regularization if entries else max(self.regularization, 1e-12))
            f = np.zeros(n)
            for task, J, v in entries:
                if J is None:  # joint-space task: J = I
                    accumulate_diagonal(H, f, task.weight, v)
                else:
                    accumulate_task(H, f, J, task.weight, v)
            problem = QPProblem(H=H, f=f, lower=lower, upper=upper, A=A, b=b, G=G, h=h, level=level)
            solution.problems.append(problem)
            try:
                x = self._backend(level).solve(problem)
            except SolverError as err:
                err.problem = problem.copy()  # a snapshot: G and h are reused buffers
                raise
            # Backends meet bounds to their tolerance; clip so joint limits hold exactly.
            x = clip_inplace(x, lower, upper)
            if level != levels[-1] and entries:
                # The optimal set of this level: its weighted task velocities stay as found.
                rows = [
                    (np.sqrt(task.weight)[:, None] * (np.eye(n) if J is None else J))[task.weight > 0]
                    for task, J, _ in entries
                ]
                A_lvl = np.vstack([A, *rows])
                A, b = _orthonormal_rows(A_lvl, A_lvl @ x)
        solution.qdot = x
        return solution


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
    if not tasks:
        raise InvalidInputError("solve_ik needs at least one task")
    return Solver(solver).solve(configuration, tasks, limits, dt, previous_qdot=previous_qdot).qdot


__all__ = ["INF", "QPProblem", "Solution", "Solver", "solve_ik", "SolverError", "InfeasibleProblemError"]
