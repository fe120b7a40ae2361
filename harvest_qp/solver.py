"""Build and solve the task-priority velocity QP.

For each priority level ``k = 1, 2, ...`` (in increasing order) the solver computes

    min_qdot  sum_{tasks at k} || W^1/2 (J qdot - v) ||^2 + qdot^T E qdot
    s.t.      lower <= qdot <= upper                    (joint limits)
              G qdot <= h                               (collision dampers)
              J_0 qdot = v_0                            (hard tasks, level 0)
              W_j^1/2 J_j qdot = W_j^1/2 J_j qdot_j*    (every level j < k)

so that a lower level only optimises within the optimal set of the levels above
it: a cascade of QPs (strict priorities). With a single soft level it is one QP.
The equality rows of earlier levels are compressed to an orthonormal basis (a Householder
QR with column pivoting), so redundant rows never make the solver see dependent equalities.

``E`` is a diagonal regularization that only tops the Hessian's diagonal up to
``regularization`` where joint-space tasks (damping, posture) do not already put
that much weight: with a ``DampingTask`` of weight ``lambda^2 >= regularization``
the QP is exactly the damped least-squares problem (a constant ``eps I`` made
"QP == damped pseudo-inverse" wrong by 3.4e-5 at lambda = 1e-3, FINDINGS "QP core").

Robustness (nothing here runs when the first backend succeeds):

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
   hard task beyond the speed limit) is the failure reported.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from harvest_qp._daqp_native import (
    CASCADE2,
    LAYOUT_REFUSED,
    NativeModel,
    update_solve,
    update_solve_check_clip_rate,
)
from harvest_qp.backends import (
    ACCEPTABLE_VIOLATION,
    FEASIBILITY_TOLERANCE,
    Backend,
    DaqpBackend,
    _checked,
    backend_name_problem,
    make_backend,
)
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InfeasibleProblemError, InvalidInputError, SolverError, SolverNotAvailableError
from harvest_qp.limits.joint_acceleration_limit import JointAccelerationLimit
from harvest_qp.limits.joint_position_limit import JointPositionLimit
from harvest_qp.limits.joint_velocity_limit import JointVelocityLimit
from harvest_qp.limits.limit import Limit
from harvest_qp.qp_kernels import (
    IDENTITY_ROWS,
    accumulate_diagonal,
    accumulate_task,
    assemble_level_1,
    assemble_level_2,
    assemble_level_3,
    assemble_level_4,
    assemble_load_1,
    assemble_load_2,
    assemble_load_3,
    assemble_load_4,
    builtin_boxes,
    check_clip,
    check_clip_equalities_1,
    check_clip_equalities_2,
    check_clip_equalities_3,
    check_clip_rate,
    clip_inplace,
    episode_task_rows,
    handover_1_1,
    handover_1_2,
    handover_1_3,
    handover_1_4,
    handover_2_1,
    handover_2_2,
    handover_2_3,
    handover_2_4,
    handover_3_1,
    handover_3_2,
    handover_3_3,
    handover_3_4,
    intersect_boxes,
    level_equalities_1,
    level_equalities_2,
    level_equalities_3,
    max_scaled_violation,
    max_violation,
    orthonormal_rows_qr,
    top_up_diagonal,
    weighted_identity_rows,
    weighted_rows,
)
from harvest_qp.tasks.damping_task import DampingTask
from harvest_qp.tasks.frame_twist_task import FrameTwistTask
from harvest_qp.tasks.posture_task import PostureTask
from harvest_qp.tasks.task import _STRUCTURE as _TASK_STRUCTURE
from harvest_qp.tasks.task import HARD, Task
from harvest_qp.validation import as_positive_scalar, as_vector

_new = object.__new__
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_frame_jacobian = pin.getFrameJacobian
_FLOAT64 = np.dtype(np.float64)
# The fused DAQP level kernels by the level's task count (see Solver._daqp_level).
_ASSEMBLE_LOAD = {1: assemble_load_1, 2: assemble_load_2, 3: assemble_load_3, 4: assemble_load_4}
_CHECK_CLIP_EQUALITIES = {1: check_clip_equalities_1, 2: check_clip_equalities_2, 3: check_clip_equalities_3}
# Two consecutive DAQP levels' hand-over by (upper, lower) task count (see Solver._solve_step).
_HANDOVER = {
    (1, 1): handover_1_1, (1, 2): handover_1_2, (1, 3): handover_1_3, (1, 4): handover_1_4,
    (2, 1): handover_2_1, (2, 2): handover_2_2, (2, 3): handover_2_3, (2, 4): handover_2_4,
    (3, 1): handover_3_1, (3, 2): handover_3_2, (3, 3): handover_3_3, (3, 4): handover_3_4,
}

#: Bound magnitude that stands for "no bound" in the QP data.
INF = 1e30
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
    """Result of :func:`solve_ik`: joint velocities [rad/s] and what the solver saw."""

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
    """Equivalent equality rows with orthonormal, independent rows (for consistent ``A x = b``).

    A Householder QR of ``A^T`` with column pivoting (:func:`orthonormal_rows_qr`), rank from
    its pivots ``|R_kk| > tol max(1, |R_00|)``. Deviation from the earlier SVD basis (same
    span, another orthonormal basis of it): the SVD of the paper episode's 11 x 12 level-1 rows
    cost ~20 us hot and 35-60 us of the replayed episode step, the compiled QR ~2 us; the
    episode's log then differs from the SVD run by round-off only (joint positions <= 2e-11 rad
    over 20 s; with :func:`level_equalities_2` <= 2e-12 rad). The solver's hot path calls it
    through the ``level_equalities_*`` kernels.
    """
    if A.shape[0] == 0:
        return A, b
    k = min(A.shape)
    rows, rhs = np.empty((k, A.shape[1])), np.empty(k)
    rank = orthonormal_rows_qr(np.asarray(A, dtype=float), np.asarray(b, dtype=float), tol, rows, rhs)
    return rows[:rank], rhs[:rank]


def _least_squares_rows(A: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal equality rows for hard tasks ``A x = b`` that need not be consistent.

    The SVD basis of ``A``'s row space with ``b`` projected on its range: two hard tasks that
    ask for different things get the least-squares compromise (independent of their order),
    and a non-finite entry raises (numpy's SVD does not converge), so the step falls back to
    a safe stop. :func:`_orthonormal_rows`'s pivoted QR is only for the consistent rows a
    priority level hands on (``rows @ x``): it satisfies the first pivot rows exactly and
    skips a NaN row. Hard tasks are rare (none in the paper episode), so the SVD costs nothing
    there.
    """
    if A.shape[0] == 0:
        return A, b
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    rank = int(np.sum(s > tol * max(1.0, s[0])))
    return Vt[:rank], (U[:, :rank].T @ b) / s[:rank]


_FRAME_TWIST_COMPUTE_ROWS = FrameTwistTask.compute_rows
_POSTURE_COMPUTE_ROWS = PostureTask.compute_rows
_DAMPING_COMPUTE_ROWS = DampingTask.compute_rows


def _builtin_compute_rows_intact(tasks) -> bool:
    """True when the episode plan's five tasks would run the library's own ``compute_rows``:
    neither their classes' method replaced (e.g. ``mock.patch.object``) nor one set on a task
    object (``task.compute_rows = f``), so building their rows in one compiled call is exact."""
    if (FrameTwistTask.compute_rows is not _FRAME_TWIST_COMPUTE_ROWS
            or PostureTask.compute_rows is not _POSTURE_COMPUTE_ROWS
            or DampingTask.compute_rows is not _DAMPING_COMPUTE_ROWS):
        return False
    for task in tasks:
        if "compute_rows" in task.__dict__:
            return False
    return True


class Solver:
    """Reusable QP solver: keeps the backend's workspace between control steps.

    Args:
        backend: ``"daqp"`` (default, persistent model), ``"proxsuite"`` (dense, with
            settings that stay exact on collision rows), ``"quadprog"`` or any
            :mod:`qpsolvers` backend name prefixed by ``"qpsolvers:"``.
        regularization: smallest diagonal entry of every level's Hessian: where
            joint-space tasks put less weight on a joint, the difference is added
            (keeps the Hessian definite without perturbing damped problems).
        fallback_backends: backends tried in order when ``backend`` fails
            (default: quadprog, then proxsuite; those not installed are skipped).
    """

    def __init__(
        self,
        backend: str = "daqp",
        *,
        regularization: float = 1e-10,
        fallback_backends: Sequence[str] | None = None,
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
        self._backends: dict[tuple[str, int], Backend] = {}
        self._box_key: tuple = ()
        self._box_list: list[Limit] = []
        self.regularization = as_positive_scalar(regularization, "regularization", allow_zero=True)
        names = DEFAULT_FALLBACK_BACKENDS if fallback_backends is None else tuple(fallback_backends)
        self.fallback_backends = tuple(name for name in names if name != backend)
        self._unavailable: set[str] = set()
        self._rows_buffer = np.empty((0, 0))
        self._episode = None  # the cached plan of _episode_plan

    def _backend(self, level: int, name: str | None = None) -> Backend:
        key = (name or self.backend_name, level)
        if key not in self._backends:
            self._backends[key] = make_backend(key[0])
        return self._backends[key]

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
            InvalidInputError: no task.
            SolverError: every backend failed (the exception carries the QP).
            InfeasibleProblemError: the safety constraints admit no solution even
                with the acceleration limits relaxed.
        """
        if not tasks:
            raise InvalidInputError("tasks must contain at least one Task, got an empty sequence")
        dt = as_positive_scalar(dt, "dt")
        if previous_qdot is not None:
            previous_qdot = as_vector(previous_qdot, configuration.nv, "previous_qdot")
        return self._solve(configuration, tasks, limits, dt, previous_qdot)

    def _solve(self, configuration, tasks, limits, dt: float, previous_qdot: np.ndarray | None) -> Solution:
        """:meth:`solve` with ``dt`` and ``previous_qdot`` already validated (the controller's path)."""
        n = configuration.nv
        box_limits = self._box_limits(limits, n)
        boxes = self._builtin_boxes(configuration, dt, previous_qdot) if self._builtin_trio else None
        if boxes is None:
            for limit, lower_row, upper_row in self._box_rows:
                limit.fill_box(configuration, dt, previous_qdot, lower_row, upper_row)
        G, h, row_limits, by_level = self._rows_and_levels(configuration, tasks, dt, previous_qdot, n)
        hard = by_level.pop(HARD, None)
        A, b = self._hard_equalities(hard, n) if hard else self._no_equalities  # empty: shared between steps
        if boxes is None:
            lower, upper, conflicts = _intersect(box_limits, self._lower_rows, self._upper_rows, n)
        else:
            lower, upper, conflicts = boxes
        retries: list[str] = []
        try:
            return self._cascade(n, by_level, lower, upper, conflicts, A, b, G, h, retries, confirm=CONFIRMING_REPORTS)
        except SolverNotAvailableError:
            raise
        except SolverError as err:
            return self._relaxed(err, n, by_level, box_limits, lower, upper, conflicts, A, b, G, h, row_limits, retries)

    def _rows_and_levels(self, configuration, tasks, dt, previous_qdot, n):
        """The row limits' stacked ``G``, ``h`` with ``(limit, its h)`` per limit that gave rows
        (which rows may be relaxed), and the tasks' ``(task, J, v)`` grouped by level."""
        G, h, row_limits = self._limit_rows(configuration, dt, previous_qdot, n)
        by_level: dict[int, list[tuple[Task, np.ndarray | None, np.ndarray]]] = {}
        for task in tasks:
            J, v = task.compute_rows(configuration, dt)
            # (get, then a fresh list only for a new level: setdefault built one per task)
            level = task.level
            entries = by_level.get(level)
            if entries is None:
                by_level[level] = [(task, J, v)]
            else:
                entries.append((task, J, v))
        return G, h, row_limits, by_level

    def _limit_rows(self, configuration, dt, previous_qdot, n):
        """The row limits' stacked ``G``, ``h`` and ``(limit, its h)`` per limit that gave rows."""
        row_limits: list[tuple[Limit, np.ndarray]] = []  # (limit, its h): which rows may be relaxed
        G_rows, h_rows = [], []
        for limit in self._row_limits:
            rows = limit.compute(configuration, dt, previous_qdot)
            if rows.lower is not None:
                raise InvalidInputError(
                    f"{type(limit).__name__}.compute returned a box: set has_box = True on the class "
                    "(and override fill_box for speed)"
                )
            if rows.G is not None:
                G_rows.append(rows.G)
                h_rows.append(rows.h)
                row_limits.append((limit, rows.h))
        if len(G_rows) == 1:
            G, h = G_rows[0], h_rows[0]
        elif G_rows:
            G, h = np.vstack(G_rows), np.concatenate(h_rows)
        else:
            G, h = np.zeros((0, n)), np.zeros(0)
        return G, h, row_limits

    def _episode_plan(self, configuration, tasks):
        """The cached plan for the paper episode's task set, or None (then each task's own
        ``compute_rows`` runs). The set: exactly ``[camera, gripper, roll, posture, damping]`` of
        the built-in classes (not subclasses: an override of ``compute_rows`` must run), the
        camera and roll tasks :class:`FrameTwistTask` in local axes on one frame, the gripper's in
        world axes, camera and gripper on one soft level and the other three on one level below
        it, all bound to ``configuration``'s model. Rebuilt whenever a task's structure changes
        (``tasks.task._STRUCTURE``: weight array, level, frame, axes or model binding).
        """
        plan = self._episode
        model = configuration.model
        # An override of compute_rows on the classes (a patch) or on a task object must run, as
        # in the generic path (an audit patched it and the plan skipped it): checked every tick.
        if (plan is not None and plan[7] == _TASK_STRUCTURE[0] and plan[6] is model and len(tasks) == 5
                and tasks[0] is plan[0] and tasks[1] is plan[1] and tasks[2] is plan[2] and tasks[3] is plan[3]
                and tasks[4] is plan[4] and _builtin_compute_rows_intact(tasks)):
            return plan
        self._episode = None
        if len(tasks) != 5:
            return None
        camera, gripper, roll, posture, damping = tasks
        if not (type(camera) is FrameTwistTask and type(gripper) is FrameTwistTask and type(roll) is FrameTwistTask
                and type(posture) is PostureTask and type(damping) is DampingTask
                and _builtin_compute_rows_intact(tasks)):
            return None
        if any(task._model is not model for task in tasks):  # not yet bound: compute_rows binds them
            return None
        upper, lower = camera._level, roll._level
        if not (camera._local and not gripper._local and roll._local and camera._frame_id == roll._frame_id
                and HARD < upper < lower and gripper._level == upper and posture._level == lower
                and damping._level == lower and configuration.nv == posture.dim == damping.dim):
            return None
        self._episode_posture_v = np.empty(configuration.nv)
        self._episode = plan = (camera, gripper, roll, posture, damping, camera._frame_id, model,
                                _TASK_STRUCTURE[0], gripper._frame_id, upper, lower)
        return plan

    def _episode_rows(self, configuration, plan):
        """The tasks' ``(task, J, v)`` by level for the episode's task set (:meth:`_episode_plan`):
        what each task's ``compute_rows`` returns, bit for bit (the same pinocchio calls and
        arithmetic), with the three compiled calls in one (:func:`episode_task_rows`).

        Differences that change no number: the roll task is given the camera task's local rows
        (``compute_rows`` gives it a copy of them through ``configuration._frame_rows``, which this
        path does not fill: a later ``compute_rows`` on that frame computes them again), and the
        posture velocity is written into a buffer of this solver (rewritten at the next step;
        only this step's cascade reads it).
        """
        camera, gripper, roll, posture, damping, frame_id, model, _, gripper_id, upper, lower = plan
        data = configuration.data
        R = data.oMf[frame_id].rotation
        J = _frame_jacobian(model, data, frame_id, _LWA)
        gain = camera._gain
        v = camera._reference if gain == 1.0 else gain * camera._reference
        J_local, v_local = camera._J_local, camera._v_local
        gain = roll._gain
        roll_v = roll._reference if gain == 1.0 else gain * roll._reference
        roll_local = roll._v_local
        posture_v = self._episode_posture_v
        episode_task_rows(R, J, v, J_local, v_local, roll_v, roll_local, posture._gain, posture._target,
                          configuration.q, posture_v)
        gain = gripper._gain
        gripper_v = gripper._reference if gain == 1.0 else gain * gripper._reference
        J_gripper = _frame_jacobian(model, data, gripper_id, _LWA)
        w_camera, w_gripper, w_roll, w_posture, w_damping = (
            camera._weight, gripper._weight, roll._weight, posture._weight, damping._weight
        )
        zeros = damping._zeros
        by_level = {
            upper: [(camera, J_local, v_local), (gripper, J_gripper, gripper_v)],
            lower: [(roll, J_local, roll_local), (posture, None, posture_v), (damping, None, zeros)],
        }
        # The fused cascade's task arguments as _fused_two_levels builds them from by_level, and
        # the rows the upper level's equalities stack (6 + 6 above no hard rows).
        flat = (
            (J_local, w_camera, v_local, J_gripper, w_gripper, gripper_v),
            (J_local, w_roll, roll_local, IDENTITY_ROWS, w_posture, posture_v, IDENTITY_ROWS, w_damping, zeros),
        )
        return by_level, flat

    def _solve_step(self, configuration, tasks, limits, dt: float, previous_qdot: np.ndarray):
        """:meth:`_solve` for the controller's step, with the step's acceleration: ``(solution,
        (solution.qdot - previous_qdot) / dt)`` [rad/s, rad/s^2], the acceleration None when it
        was not computed here (the caller then computes it with numpy).

        The same operations in the same order as :meth:`_solve` (bit for bit; tested against it),
        in fewer Python frames and compiled calls: with the cached built-in trio of box limits and
        every level a DAQP model already set up for the problem's size, the cascade runs here,
        two consecutive levels hand over in one compiled call (``handover_*``: the upper level's
        check, clip and equalities, then the lower level's assembly and DAQP layout) and the last
        level's check and clip also compute the acceleration (:func:`check_clip_rate`). With two
        levels whose models are :class:`~harvest_qp._daqp_native.NativeModel` (DAQP's C API) and
        inequality rows (the paper episode), the whole cascade is one compiled call
        (:meth:`_fused_two_levels`); the loop resumes where that call stopped. A rejected answer,
        a failure or any other case takes :meth:`_solve`'s own code.
        """
        n = configuration.nv
        if (n, *map(id, limits)) != self._box_key or not self._builtin_trio:
            return self._solve(configuration, tasks, limits, dt, previous_qdot), None
        box_list = self._box_list
        velocity, position, acceleration = box_list
        model = configuration.model
        if velocity._model is not model or position._model is not model or acceleration._model is not model:
            return self._solve(configuration, tasks, limits, dt, previous_qdot), None
        # _builtin_boxes inlined (lower and upper fresh: the solution and its problems keep them)
        lower, upper = np.empty(n), np.empty(n)
        conflict = self._conflict
        count = builtin_boxes(
            configuration.q, position.lower, position.upper, position.gain, dt, position._braking,
            velocity.max_velocity, acceleration._zeros if previous_qdot is None else previous_qdot,
            acceleration.max_acceleration, self._lowers, self._uppers, lower, upper, conflict,
        )
        if count < 0:  # the limits' own fill_box (with its checks), in _solve
            return self._solve(configuration, tasks, limits, dt, previous_qdot), None
        conflicts = []
        if count:
            conflicts = [
                BoxConflict(int(j), type(box_list[conflict[j]]).__name__) for j in np.flatnonzero(conflict >= 0)
            ]
        episode = self._episode_plan(configuration, tasks)
        if episode is None:
            G, h, row_limits, by_level = self._rows_and_levels(configuration, tasks, dt, previous_qdot, n)
            flat = None
        else:  # the paper episode's task set: its rows in fewer frames and one compiled call
            G, h, row_limits = self._limit_rows(configuration, dt, previous_qdot, n)
            by_level, flat = self._episode_rows(configuration, episode)
        hard = by_level.pop(HARD, None)
        A0, b0 = self._hard_equalities(hard, n) if hard else self._no_equalities  # empty: shared between steps
        retries: list[str] = []
        try:
            # The levels, each a DAQP model set up for this size (else _cascade's own code).
            levels = sorted(by_level) or [1]
            plan = []
            # (previous_qdot None: the acceleration kernel needs a vector; the controller always has one)
            if self.backend_name == "daqp" and A0.dtype is _FLOAT64 and previous_qdot is not None:
                backends = self._backends
                shape = (n, G.shape[0])
                last = levels[-1]
                for level in levels:
                    entries = by_level.get(level, ())
                    backend = backends.get(("daqp", level))
                    if not (type(backend) is DaqpBackend and backend._model is not None and backend._shape == shape
                            and 0 < len(entries) <= (4 if level == last else 3)):
                        break
                    plan.append((level, entries, backend))
            if len(plan) != len(levels):
                solution = self._cascade(
                    n, by_level, lower, upper, conflicts, A0, b0, G, h, retries, confirm=CONFIRMING_REPORTS
                )
                return solution, None
            solution = _new(Solution)
            solution.__dict__.update(
                qdot=None, problems=[], lower=lower, upper=upper, conflicts=conflicts, relaxed=[],
                box_relaxation=None, row_relaxation=None, retries=retries,
            )
            problems = solution.problems
            regularization = self.regularization
            A, b = A0, b0
            block = None  # the level's H, f and floor when the level above assembled them
            n_in = G.shape[0]
            final = len(plan) - 1
            # Two native DAQP levels (the episode's cascade): every level's assembly, DAQP update and
            # solve, check, clip and hand-over in one compiled call (cascade2_*); where it stops early
            # (a DAQP failure or a rejected answer), the loop below resumes with its results.
            pre = (None,) * len(plan)
            if final == 1 and n_in > 0:
                pre, fused = self._fused_two_levels(plan, n, A0, b0, G, h, lower, upper, previous_qdot, dt, flat)
                if pre is None:  # both levels accepted: fused is (qdot, acceleration, the two problems)
                    problems += fused[2]
                    solution.qdot = fused[0]
                    return solution, fused[1]
                block = fused  # the upper level's block when assembled by the fused call, else None
                n_eq_before = 0  # (rows_changed holds through n_in > 0 here)
            for i, (level, entries, backend) in enumerate(plan):
                if block is None:  # as in _daqp_level
                    block = np.zeros((n + 2, n))  # fresh: the problem keeps H and f
                    args = [block, regularization]
                    for task, J, v in entries:
                        args += (IDENTITY_ROWS if J is None else J, task.weight, v)
                    n_eq_before = backend._n_eq
                    backend._n_eq = _ASSEMBLE_LOAD[len(entries)](
                        *args, *backend._layout, A, b, G, h, lower, upper, n_eq_before, INF
                    )
                rows_changed = n_in > 0 or A.shape[0] > 0 or n_eq_before > 0
                H, f = block[:n], block[n]
                block = None
                problem = _new(QPProblem)
                problem.__dict__.update(H=H, f=f, lower=lower, upper=upper, A=A, b=b, G=G, h=h, level=level)
                problems.append(problem)
                try:
                    model = backend._model
                    rate = None
                    done = pre[i]
                    if done is not None:  # solved by the fused call: (x, flag, rate or hand-over)
                        x, flag = done[0], done[1]
                        if i == final:
                            rate = done[2]
                    elif rows_changed and type(model) is NativeModel:
                        # DAQP's update and solve (the same C calls as daqp.Model's) in one compiled
                        # call, on the last level with its check, clip and acceleration too.
                        keep = model._keep
                        keep["H"], keep["f"] = H, f  # DAQP's problem points at them (as daqp.Model's)
                        layout = backend._layout
                        if i == final:
                            x, flag, rate = update_solve_check_clip_rate(
                                model._work, model._problem, model._result, model._x, model._lam, H, f, *layout,
                                lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE, previous_qdot, dt,
                            )
                        else:
                            x, flag = update_solve(
                                model._work, model._problem, model._result, model._x, model._lam, H, f, *layout
                            )
                        if flag == LAYOUT_REFUSED:  # not the set-up arrays: daqp.Model's own handling
                            x, flag = model.update_solve(H, f, *layout)
                            rate = None
                        else:
                            model._has_solved = True
                    else:
                        if rows_changed:
                            model.update(H, f, *backend._layout)
                        else:  # only bounds and cost moved: skip copying the constraint matrix
                            model.update(H, f, None, backend._upper, backend._lower)
                        x, _, flag, _ = model.solve()
                    if flag < 0:
                        backend._raise_failure(problem, flag)
                    if i == final:
                        if rate is None:
                            rate = check_clip_rate(
                                x, lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE, previous_qdot, dt
                            )
                        if rate.shape[0]:
                            solution.qdot = x
                            return solution, rate
                    elif A.dtype is _FLOAT64:
                        # This level's check, clip and equalities, then the next level's assembly.
                        below_entries, below_backend = plan[i + 1][1], plan[i + 1][2]
                        m = A.shape[0]
                        eq_tail = []
                        for task, J, _v in entries:
                            weight = task.weight
                            if J is None:
                                m += weight.shape[0]
                                J = IDENTITY_ROWS
                            else:
                                m += J.shape[0]
                            eq_tail += (J, weight)
                        stack = self._rows_buffer
                        if stack.shape[0] < m or stack.shape[1] != n:
                            stack = self._rows_buffer = np.empty((max(m, stack.shape[0]), n))
                        block = np.zeros((n + 2, n))
                        args = [block, regularization]
                        for task, J, v in below_entries:
                            args += (IDENTITY_ROWS if J is None else J, task.weight, v)
                        n_eq_before = below_backend._n_eq
                        if done is not None:  # the fused call's hand-over (block: its lower level's)
                            accepted, rows, rhs, n_eq = done[2]
                            block = done[3]
                        else:
                            accepted, rows, rhs, n_eq = _HANDOVER[len(entries), len(below_entries)](
                                x, lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE, 1e-9, stack, *eq_tail,
                                *args, *below_backend._layout, n_eq_before, INF,
                            )
                        if accepted:
                            below_backend._n_eq = n_eq
                            A, b = rows, rhs
                            continue
                        block = None  # rejected: the level below was left untouched
                    elif check_clip(x, lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE):
                        A, b = self._level_equalities(A, entries, n, x)
                        continue
                    # Rejected by the check (x as DAQP returned it): raises as DaqpBackend.solve does.
                    x = _checked(x, problem, backend.name)
                except SolverNotAvailableError:
                    raise
                except SolverError as first:
                    x = self._recover(level, problem, retries, CONFIRMING_REPORTS, first)
                x = clip_inplace(x, lower, upper)
                if i != final:
                    A, b = self._level_equalities(A, entries, n, x)
            solution.qdot = x
            return solution, None
        except SolverNotAvailableError:
            raise
        except SolverError as err:
            solution = self._relaxed(
                err, n, by_level, box_list, lower, upper, conflicts, A0, b0, G, h, row_limits, retries
            )
            return solution, None


    def _fused_two_levels(self, plan, n, A0, b0, G, h, lower, upper, previous_qdot, dt, flat=None):
        """The two levels of ``plan`` (each a :class:`NativeModel` set up for the size, rows present)
        in one compiled call (``cascade2_*``: the same calls in the same order as the loop of
        :meth:`_solve_step`). Returns ``(None, (qdot, rate, problems))`` when both levels were
        accepted, else ``(pre, block)`` for the loop to resume from: per level None (the loop does
        it) or the fused call's results, and the upper level's assembled block (None: not native).
        ``flat``: the two levels' task arguments as built below from ``plan``, given by
        :meth:`_episode_rows` (the episode's task set, no hard rows)."""
        (level1, entries1, backend1), (level2, entries2, backend2) = plan
        model1, model2 = backend1._model, backend2._model
        if type(model1) is not NativeModel or type(model2) is not NativeModel:
            return (None, None), None
        native1, native2 = model1._call_args, model2._call_args  # (work, problem, result, x, lam)
        if native1 is None or native2 is None:  # never set up: the loop's own code
            return (None, None), None
        block1 = np.zeros((n + 2, n))  # fresh: the problems keep H and f
        block2 = np.zeros((n + 2, n))
        # The kernel's arguments in one call expression (no list grown argument by argument):
        # ~1 us less per tick than building a 50-item list (the same arrays in the same order).
        if flat is None:
            rows1 = []
            m = A0.shape[0]  # rows the upper level's equalities stack
            for task, J, v in entries1:
                weight = task.weight
                if J is None:
                    m += weight.shape[0]
                    J = IDENTITY_ROWS
                else:
                    m += J.shape[0]
                rows1 += (J, weight, v)
            rows2 = []
            for task, J, v in entries2:
                rows2 += (IDENTITY_ROWS if J is None else J, task.weight, v)
        else:
            rows1, rows2 = flat
            m = rows1[0].shape[0] + rows1[3].shape[0]  # the camera's and the gripper's rows, no hard rows above
        stack = self._rows_buffer
        if stack.shape[0] < m or stack.shape[1] != n:
            stack = self._rows_buffer = np.empty((max(m, stack.shape[0]), n))
        stage, n_eq1, x1, flag1, rows, rhs, n_eq2, x2, flag2, rate = CASCADE2[len(entries1), len(entries2)](
            block1, self.regularization, *rows1, *native1, *backend1._layout, backend1._n_eq, block2, *rows2,
            *native2, *backend2._layout, backend2._n_eq, A0, b0, G, h, lower, upper, FEASIBILITY_TOLERANCE, 1e-9,
            stack, previous_qdot, dt, INF,
        )
        backend1._n_eq = n_eq1
        H1, f1 = block1[:n], block1[n]
        if flag1 == LAYOUT_REFUSED:  # nothing passed to DAQP: the loop solves the assembled level
            return (None, None), block1
        keep = model1._keep
        keep["H"], keep["f"] = H1, f1  # DAQP's problem points at them (as daqp.Model's)
        model1._has_solved = True
        if stage == 0:
            return ((x1, flag1), None), block1
        if stage == 1:
            return ((x1, flag1, (False, rows, rhs, -1), None), None), block1
        H2, f2 = block2[:n], block2[n]
        upper_done = (x1, flag1, (True, rows, rhs, n_eq2), block2)
        if flag2 == LAYOUT_REFUSED:
            return (upper_done, None), block1
        keep = model2._keep
        keep["H"], keep["f"] = H2, f2
        model2._has_solved = True
        if stage == 2:
            return (upper_done, (x2, flag2, rate)), block1
        backend2._n_eq = n_eq2
        problem1 = _new(QPProblem)
        problem1.__dict__.update(H=H1, f=f1, lower=lower, upper=upper, A=A0, b=b0, G=G, h=h, level=level1)
        problem2 = _new(QPProblem)
        problem2.__dict__.update(H=H2, f=f2, lower=lower, upper=upper, A=rows, b=rhs, G=G, h=h, level=level2)
        return None, (x2, rate, [problem1, problem2])

    def _hard_equalities(self, hard, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Orthonormal equality rows of the hard tasks' ``(task, J, v)`` (``J`` None: ``I``)."""
        hard = [(t, np.eye(n) if J is None else J, v) for t, J, v in hard]
        for t, J, v in hard:
            # A hard task must be met exactly: a non-finite target is an error, not a
            # problem daqp refuses and a retry quietly drops (an audit found the latter).
            if not (np.all(np.isfinite(v)) and np.all(np.isfinite(J))):
                raise InvalidInputError(
                    f"hard task {type(t).__name__} (level 0) computed non-finite rows: target {v.tolist()}"
                )
        return _least_squares_rows(
            np.vstack([J[t.weight > 0] for t, J, _ in hard]), np.concatenate([v[t.weight > 0] for t, _, v in hard])
        )

    def _relaxed(self, err, n, by_level, box_limits, lower, upper, conflicts, A, b, G, h, row_limits, retries):
        """:meth:`_solve` after the cascade failed with ``err``: the least relaxation, or ``err``."""
        # Rows that ask for separation (may be lowered to "no further approach"), per limit.
        sep = (
            np.concatenate([
                np.full(len(rows_h), bool(getattr(limit, "separation_rows", False))) for limit, rows_h in row_limits
            ])
            if row_limits else np.zeros(0, dtype=bool)
        )
        # First ignore a widening below the solvers' noise; if that leaves the QP
        # infeasible after all, take the widening exactly as computed.
        for tolerance in (RELAXATION_TOLERANCE, 0.0):
            relaxed = self._least_relaxation(n, box_limits, lower, upper, A, b, G, h, sep, retries, tolerance)
            if relaxed is None:
                continue
            lower2, upper2, h2, box_slack, row_slack = relaxed
            try:
                solution = self._cascade(n, by_level, lower2, upper2, conflicts, A, b, G, h2, retries)
                break
            except SolverError:
                continue
        else:
            raise err from None
        if np.any(box_slack > 0):
            solution.relaxed = [
                type(limit).__name__ for limit in box_limits if limit.priority >= RELAXABLE_PRIORITY
            ]
        solution.box_relaxation = box_slack
        solution.row_relaxation = row_slack
        return solution

    def _box_limits(self, limits: Sequence[Limit], n: int) -> list[Limit]:
        """The box limits in priority order, with row buffers for their boxes (cached).

        Also caches, for the same ``limits``: ``_box_rows`` (each box limit with its rows of
        the buffers), ``_lower_rows`` / ``_upper_rows`` (the buffers' rows in use) and
        ``_row_limits`` (the limits with inequality rows, in the given order).
        """
        key = (n, *map(id, limits))
        if key != self._box_key:
            self._box_key = key
            self._box_list = sorted((limit for limit in limits if limit.has_box), key=lambda lim: lim.priority)
            self._lowers = np.empty((max(len(self._box_list), 1), n))
            self._uppers = np.empty((max(len(self._box_list), 1), n))
            k = len(self._box_list)
            self._box_rows = [(limit, self._lowers[i], self._uppers[i]) for i, limit in enumerate(self._box_list)]
            self._lower_rows, self._upper_rows = self._lowers[:k], self._uppers[:k]
            self._row_limits = [limit for limit in limits if not limit.has_box]
            self._conflict = np.empty(n, dtype=np.int64)
            self._no_equalities = (np.zeros((0, n)), np.zeros(0))
            self._builtin_trio = tuple(map(type, self._box_list)) == (
                JointVelocityLimit, JointPositionLimit, JointAccelerationLimit
            )
        return self._box_list

    def _builtin_boxes(self, configuration, dt: float, previous_qdot: np.ndarray | None):
        """``(lower, upper, conflicts)`` of the built-in velocity, position and acceleration limits
        in one compiled call (:func:`builtin_boxes`: their own arithmetic), the buffers' rows filled
        as their ``fill_box`` fills them; None when a limit was not yet checked against this
        model or a size does not fit (then each limit's ``fill_box`` runs, with its checks).
        """
        velocity, position, acceleration = self._box_list
        model = configuration.model
        if velocity._model is not model or position._model is not model or acceleration._model is not model:
            return None
        n = configuration.nv
        lower, upper = np.empty(n), np.empty(n)  # fresh: the solution and its problems keep them
        conflict = self._conflict  # scratch, read only below
        count = builtin_boxes(
            configuration.q, position.lower, position.upper, position.gain, dt, position._braking,
            velocity.max_velocity, acceleration._zeros if previous_qdot is None else previous_qdot,
            acceleration.max_acceleration, self._lowers, self._uppers, lower, upper, conflict,
        )
        if count < 0:
            return None
        conflicts = []
        if count:
            conflicts = [
                BoxConflict(int(j), type(self._box_list[conflict[j]]).__name__) for j in np.flatnonzero(conflict >= 0)
            ]
        return lower, upper, conflicts

    # ------------------------------------------------------------------ backends
    def _solve_qp(self, level: int, problem: QPProblem, retries: list[str], confirm: int | None = None) -> np.ndarray:
        """Solve with the chosen backend, then with each fallback backend, until one succeeds.

        With ``confirm``, stop after that many backends reported infeasibility (believed).
        """
        try:
            return self._backend(level).solve(problem)
        except SolverNotAvailableError:
            raise  # a misconfigured backend is reported, not papered over
        except SolverError as first:
            return self._recover(level, problem, retries, confirm, first)

    def _recover(self, level: int, problem: QPProblem, retries: list[str], confirm: int | None,
                 first: SolverError) -> np.ndarray:
        """:meth:`_solve_qp` after the chosen backend failed with ``first``: the fallback backends."""
        first.problem = problem.copy()  # a snapshot: G and h are reused buffers
        failures = [f"{self.backend_name}: {type(first).__name__}"]
        reports = int(isinstance(first, InfeasibleProblemError))
        inaccurate = [(first.violation, first.x, self.backend_name)] if hasattr(first, "violation") else []
        for name in self.fallback_backends:
            if name in self._unavailable:
                continue
            if confirm is not None and reports >= confirm:
                break
            try:
                x = self._backend(level, name).solve(problem)
            except SolverNotAvailableError:
                self._unavailable.add(name)
                continue
            except SolverError as err:
                failures.append(f"{name}: {type(err).__name__}")
                reports += isinstance(err, InfeasibleProblemError)
                if hasattr(err, "violation"):
                    inaccurate.append((err.violation, err.x, name))
                continue
            retries.extend(failures)
            return x
        if inaccurate:
            # Last resort before the relaxation and the safe stop: every backend returned a
            # solution just outside the tolerance; the least violating one is good enough.
            violation, x, name = min(inaccurate, key=lambda item: item[0])
            if violation <= ACCEPTABLE_VIOLATION:
                retries.extend([*failures, f"accepted {name} at {violation:.1e} relative violation"])
                return x
        raise first

    def _solve_any(self, problem: QPProblem) -> np.ndarray | None:
        """Auxiliary QP (relaxation) with each backend in turn; None when all report failure.

        Infeasibility reported by :data:`CONFIRMING_REPORTS` backends is believed.
        """
        reports = 0
        for name in (self.backend_name, *self.fallback_backends):
            if name in self._unavailable:
                continue
            if reports >= CONFIRMING_REPORTS:
                break
            try:
                return make_backend(name).solve(problem)
            except SolverNotAvailableError:
                self._unavailable.add(name)
            except InfeasibleProblemError:
                reports += 1
            except SolverError:
                continue
        return None

    # ------------------------------------------------------------------ cascade
    def _cascade(self, n, by_level, lower, upper, conflicts, A, b, G, h, retries, confirm=None) -> Solution:
        """Solve the levels in order, each within the optimal set of those before."""
        # The dataclasses' constructors without their call overhead (the same instance state).
        solution = _new(Solution)
        solution.__dict__.update(
            qdot=None, problems=[], lower=lower, upper=upper, conflicts=conflicts, relaxed=[],
            box_relaxation=None, row_relaxation=None, retries=retries,
        )
        problems = solution.problems
        levels = sorted(by_level) or [1]
        last = levels[-1]
        regularization = self.regularization
        # DAQP levels whose model is set up for this size take the fused path (_daqp_level).
        daqp = self._backends if self.backend_name == "daqp" else None
        n_in = G.shape[0]
        shape = (n, n_in)
        for level in levels:
            entries = by_level.get(level, ())
            count = len(entries)
            if daqp is not None and 0 < count <= 4:
                backend = daqp.get(("daqp", level))
                # Only DAQP's own backend (a replaced or subclassed one keeps its own solve).
                if type(backend) is DaqpBackend and backend._model is not None and backend._shape == shape:
                    x, A, b = self._daqp_level(
                        backend, level, level != last, n, entries, lower, upper, A, b, G, h, retries, confirm, problems
                    )
                    continue
            # H, f and the floor (weight joint-space tasks already put on each joint) as rows of
            # one fresh block: one allocation instead of three (H and f stay contiguous).
            block = np.zeros((n + 2, n))
            H, f, floor = block[:n], block[n], block[n + 1]
            # Top the diagonal up to the regularization only where it is missing, so a
            # damped problem stays exactly the damped least-squares problem.
            if 0 < count <= 4:
                # One compiled call for the level: each task's kernel in order, then the top-up.
                args = [H, f, floor, regularization]
                for task, J, v in entries:
                    args += (IDENTITY_ROWS if J is None else J, task.weight, v)
                if count == 2:
                    assemble_level_2(*args)
                elif count == 3:
                    assemble_level_3(*args)
                elif count == 1:
                    assemble_level_1(*args)
                else:
                    assemble_level_4(*args)
            else:
                reg = regularization if entries else max(regularization, 1e-12)
                for task, J, v in entries:
                    if J is None:  # joint-space task: J = I
                        accumulate_diagonal(H, f, task.weight, v, floor)
                    else:
                        accumulate_task(H, f, J, task.weight, v)
                top_up_diagonal(H, floor, reg)
            problem = _new(QPProblem)
            problem.__dict__.update(H=H, f=f, lower=lower, upper=upper, A=A, b=b, G=G, h=h, level=level)
            problems.append(problem)
            x = self._solve_qp(level, problem, retries, confirm)
            # Backends meet bounds to their tolerance; clip so joint limits hold exactly.
            x = clip_inplace(x, lower, upper)
            if level != last and entries:
                # The optimal set of this level: its weighted task velocities stay as found.
                A, b = self._level_equalities(A, entries, n, x)
        solution.qdot = x
        return solution

    def _daqp_level(self, backend, level, below, n, entries, lower, upper, A, b, G, h, retries, confirm, problems):
        """One level of :meth:`_cascade` on a DAQP model already set up for its size: the same
        operations as the general path (assembly, DAQP's layout, update and solve, the
        feasibility check, the clip, and with ``below`` the level's equalities) in two compiled
        calls around DAQP's. Returns ``(x, A, b)``: the level's solution and the equalities
        for the levels below (``A``, ``b`` unchanged when ``below`` is False).
        """
        count = len(entries)
        block = np.zeros((n + 2, n))  # H, f, floor: fresh, the problem keeps H and f
        H, f = block[:n], block[n]
        # One pass over the tasks: the assembly's (J, w, v) and the equalities' (J, w) arguments
        # and the rows the equalities stack (A's and every task's).
        args = [block, self.regularization]
        eq_tail = []
        m = A.shape[0]
        for task, J, v in entries:
            weight = task.weight
            if J is None:
                m += weight.shape[0]
                J = IDENTITY_ROWS
            else:
                m += J.shape[0]
            args += (J, weight, v)
            eq_tail += (J, weight)
        n_eq_before = backend._n_eq
        rows_changed = G.shape[0] > 0 or A.shape[0] > 0 or n_eq_before > 0
        backend._n_eq = _ASSEMBLE_LOAD[count](*args, *backend._layout, A, b, G, h, lower, upper, n_eq_before, INF)
        problem = _new(QPProblem)
        problem.__dict__.update(H=H, f=f, lower=lower, upper=upper, A=A, b=b, G=G, h=h, level=level)
        problems.append(problem)
        try:
            # The episode's levels take _solve_step's fused cascade; this general path calls
            # the backend's own update and solve (raises on DAQP's failure flag).
            x = backend._update_solve(problem, H, f, rows_changed)
            if below and count <= 3 and A.dtype is _FLOAT64:
                stack = self._rows_buffer
                if stack.shape[0] < m or stack.shape[1] != n:
                    stack = self._rows_buffer = np.empty((max(m, stack.shape[0]), n))
                accepted, rows, rhs = _CHECK_CLIP_EQUALITIES[count](
                    x, lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE, 1e-9, stack, *eq_tail
                )
                if accepted:
                    return x, rows, rhs
            elif check_clip(x, lower, upper, A, b, G, h, FEASIBILITY_TOLERANCE):
                if below:
                    A, b = self._level_equalities(A, entries, n, x)
                return x, A, b
            # Rejected by the check (x as DAQP returned it): raises as DaqpBackend.solve does.
            x = _checked(x, problem, backend.name)
        except SolverNotAvailableError:
            raise
        except SolverError as first:
            x = self._recover(level, problem, retries, confirm, first)
        x = clip_inplace(x, lower, upper)
        if below:
            A, b = self._level_equalities(A, entries, n, x)
        return x, A, b

    def _level_rows(self, A: np.ndarray, entries, n: int) -> np.ndarray:
        """``A`` stacked over each task's rows ``sqrt(w_r) J_r`` with ``w_r > 0`` (``J = I`` for
        joint-space tasks): the rows that hold a level's optimum for the levels below it.

        Bit for bit ``np.vstack([A, *[(np.sqrt(w)[:, None] * J)[w > 0] ...]])``, written into a
        buffer kept between steps (the caller only reads it before the next step).
        """
        m = A.shape[0] + sum(task.weight.shape[0] if J is None else J.shape[0] for task, J, _ in entries)
        buffer = self._rows_buffer
        if buffer.shape[0] < m or buffer.shape[1] != n:
            buffer = self._rows_buffer = np.empty((max(m, buffer.shape[0]), n))
        row = A.shape[0]
        if row:
            buffer[:row] = A
        for task, J, _ in entries:
            if J is None:
                row = weighted_identity_rows(task.weight, buffer, row)
            else:
                row = weighted_rows(J, task.weight, buffer, row)
        return buffer[:row]

    def _level_equalities(self, A: np.ndarray, entries, n: int, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Orthonormal equality rows (and right-hand side) that hold this level's optimum ``x``:
        ``A`` and the level's weighted task rows, as ``_orthonormal_rows(rows, rows @ x)``, in one
        compiled call for 1-3 tasks (:func:`level_equalities_2` etc.)."""
        count = len(entries)
        if count > 3 or A.dtype != np.float64:
            A_lvl = self._level_rows(A, entries, n)
            return _orthonormal_rows(A_lvl, A_lvl @ x)
        m = A.shape[0]
        args = [A, x, 1e-9, None]
        for task, J, _ in entries:
            weight = task.weight
            if J is None:
                m += weight.shape[0]
                args += (IDENTITY_ROWS, weight)
            else:
                m += J.shape[0]
                args += (J, weight)
        stack = self._rows_buffer
        if stack.shape[0] < m or stack.shape[1] != n:
            stack = self._rows_buffer = np.empty((max(m, stack.shape[0]), n))
        args[3] = stack
        if count == 2:
            return level_equalities_2(*args)
        if count == 1:
            return level_equalities_1(*args)
        return level_equalities_3(*args)

    # ------------------------------------------------------------------ relaxation
    def _least_relaxation(self, n, box_limits, lower, upper, A, b, G, h, separating, retries, tolerance=0.0):
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
        safe = [limit for limit in box_limits if limit.priority < RELAXABLE_PRIORITY]
        k = len(safe)
        safe_lower, safe_upper, _ = _intersect(safe, self._lowers[:k], self._uppers[:k], n)
        m = G.shape[0]
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
        H1 = np.diag(np.concatenate([np.full(n, 1e-9), np.ones(n)]))
        stage1 = QPProblem(
            H=H1, f=np.zeros(2 * n),
            lower=np.concatenate([safe_lower, np.zeros(n)]), upper=np.concatenate([safe_upper, np.full(n, INF)]),
            A=np.hstack([A, np.zeros((A.shape[0], n))]), b=b, G=G1, h=h1,
        )
        z = self._solve_any(stage1)
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
            z2 = self._solve_any(stage2)
            if z2 is None:
                return None
            t = np.clip(z2[n:], 0.0, -h[asking])
            row_slack[asking] = np.minimum(t + RELAXATION_MARGIN, -h[asking])
        return lower2, upper2, h + row_slack, box_slack, row_slack


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


__all__ = ["INF", "QPProblem", "Solution", "Solver", "solve_ik", "SolverError", "InfeasibleProblemError"]
