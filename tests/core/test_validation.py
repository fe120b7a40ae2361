"""Bad input gets the package's own error, naming the argument and the value, and touches no memory.

Oracles: the message is compared with the value that was passed (never with what the code
made of it), and sizes with the pinocchio model's ``nv``. The "no kernel runs" tests replace
every compiled kernel the solver calls with a spy.
"""

from __future__ import annotations

import re

import numpy as np
import pinocchio as pin
import pytest

import harvest_qp.solver as solver_module
from harvest_qp import Configuration, Solver
from harvest_qp.exceptions import DimensionError, HarvestQPError, InvalidInputError, UnknownFrameError
from harvest_qp.limits import JointPositionLimit, JointVelocityLimit, Limit, LimitRows
from harvest_qp.limits.limit import check_limits
from harvest_qp.tasks import DampingTask, FramePoseTask, FrameTwistTask, PostureTask, RelativeFrameTask, Task
from harvest_qp.tasks.task import check_tasks
from harvest_qp.validation import check_limit_rows, check_task_rows


@pytest.fixture(scope="module")
def dual() -> Configuration:
    return Configuration.dual_ur5e()


@pytest.fixture(scope="module")
def single(dual) -> Configuration:
    """The camera arm alone (nv = 6): the grasping arm's joints locked at home, same frame names."""
    model = dual.model
    lock = [model.getJointId(name) for name in dual.joint_names[6:]]
    return Configuration(pin.buildReducedModel(model, lock, dual.q), dual.q[:6])


# ----------------------------------------------------------------------------- bad input table
C = Configuration.dual_ur5e()  # for the table below; the tests never move it
R_REFLECTION = np.diag([1.0, 1.0, -1.0])
NAN6 = np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0])

# (id, call, fragments that must all appear in the message: the argument and the value)
BAD_INPUT = [
    ("damping nv str", lambda: DampingTask("abc"), ["DampingTask nv", "'abc'"]),
    ("damping nv float", lambda: DampingTask(2.5), ["DampingTask nv", "2.5"]),
    ("damping nv None", lambda: DampingTask(None), ["DampingTask nv", "None"]),
    ("damping nv 0", lambda: DampingTask(0), ["DampingTask nv", "0"]),
    ("damping weight<0", lambda: DampingTask(12, weight=-1.0), ["weight", "-1"]),
    ("damping level None", lambda: DampingTask(12, level=None), ["level", "None"]),
    ("posture None", lambda: PostureTask(None), ["PostureTask target", "None"]),
    ("posture str", lambda: PostureTask("abc"), ["PostureTask target", "'abc'"]),
    ("posture empty", lambda: PostureTask([]), ["PostureTask target", "[]"]),
    ("posture 2-D", lambda: PostureTask(np.zeros((2, 6))), ["PostureTask target", "(2, 6)"]),
    ("posture ragged", lambda: PostureTask([[0.0], [0.0, 1.0]]), ["PostureTask target", "[[0.0]"]),
    ("posture Nones", lambda: PostureTask([None] * 12), ["PostureTask target", "None"]),
    ("posture NaN", lambda: PostureTask(np.full(12, np.nan)), ["PostureTask target", "nan"]),
    ("posture set 11", lambda: PostureTask(np.zeros(12)).set_target(np.zeros(11)), ["target", "(11,)"]),
    ("posture assign", lambda: setattr(PostureTask(np.zeros(12)), "target", "x"), ["target", "'x'"]),
    ("posture gain str", lambda: PostureTask(np.zeros(12), gain="abc"), ["gain", "'abc'"]),
    ("twist frame None", lambda: FrameTwistTask(None), ["FrameTwistTask frame", "None"]),
    ("twist frame int", lambda: FrameTwistTask(3), ["FrameTwistTask frame", "3"]),
    ("twist frame empty", lambda: FrameTwistTask(""), ["FrameTwistTask frame", "''"]),
    ("twist weight str", lambda: FrameTwistTask("camera", weight="abc"), ["weight", "'abc'"]),
    ("twist weight 3", lambda: FrameTwistTask("camera", weight=np.ones(3)), ["weight", "(3,)"]),
    ("twist weight NaN", lambda: FrameTwistTask("camera", weight=np.nan), ["weight", "nan"]),
    ("twist weight inf", lambda: FrameTwistTask("camera", weight=np.inf), ["weight", "inf"]),
    ("twist weight<0", lambda: FrameTwistTask("camera", weight=-1.0), ["weight", "-1"]),
    ("twist weight None", lambda: FrameTwistTask("camera", weight=None), ["weight", "None"]),
    ("weight_frame", lambda: FrameTwistTask("camera", weight_frame="body"), ["weight_frame", "'body'"]),
    ("level None", lambda: FrameTwistTask("camera", level=None), ["level", "None"]),
    ("level inf", lambda: FrameTwistTask("camera", level=np.inf), ["level", "inf"]),
    ("level nan", lambda: FrameTwistTask("camera", level=np.nan), ["level", "nan"]),
    ("level -1", lambda: FrameTwistTask("camera", level=-1), ["level", "-1"]),
    ("level 1.5", lambda: FrameTwistTask("camera", level=1.5), ["level", "1.5"]),
    ("level str", lambda: FrameTwistTask("camera", level="1"), ["level", "'1'"]),
    ("level bool", lambda: FrameTwistTask("camera", level=True), ["level", "True"]),
    ("gain None", lambda: FramePoseTask("camera", gain=None), ["gain", "None"]),
    ("gain str", lambda: FramePoseTask("camera", gain="abc"), ["gain", "'abc'"]),
    ("gain inf", lambda: FramePoseTask("camera", gain=np.inf), ["gain", "inf"]),
    ("gain nan", lambda: FramePoseTask("camera", gain=np.nan), ["gain", "nan"]),
    ("gain<0", lambda: FramePoseTask("camera", gain=-2.0), ["gain", "-2"]),
    ("gain array", lambda: FramePoseTask("camera", gain=np.ones(2)), ["gain", "[1., 1.]"]),
    ("reference None", lambda: FrameTwistTask("camera").set_reference(None), ["reference", "None"]),
    ("reference 5", lambda: FrameTwistTask("camera").set_reference(np.zeros(5)), ["reference", "(5,)"]),
    ("reference NaN", lambda: FrameTwistTask("camera").set_reference(NAN6), ["reference", "nan"]),
    ("reference str", lambda: FrameTwistTask("camera").set_reference(["a"] * 6), ["reference", "'a'"]),
    ("weight assign", lambda: setattr(FrameTwistTask("camera"), "weight", np.ones(5)), ["weight", "(5,)"]),
    ("gain assign", lambda: setattr(FrameTwistTask("camera"), "gain", None), ["gain", "None"]),
    ("frame assign", lambda: setattr(FrameTwistTask("camera"), "frame", None), ["frame", "None"]),
    ("pose frame None", lambda: FramePoseTask(None), ["FramePoseTask frame", "None"]),
    ("pose 2I", lambda: FramePoseTask("gripper").set_target(np.zeros(3), 2 * np.eye(3)), ["rotation", "det R = 8"]),
    (
        "pose reflection",
        lambda: FramePoseTask("gripper").set_target(np.zeros(3), R_REFLECTION),
        ["rotation", "det R = -1"],
    ),
    ("pose rot None", lambda: FramePoseTask("gripper").set_target(np.zeros(3), None), ["rotation", "None"]),
    ("pose rot 2x2", lambda: FramePoseTask("gripper").set_target(np.zeros(3), np.eye(2)), ["rotation", "(2, 2)"]),
    ("pose position None", lambda: FramePoseTask("gripper").set_target(None, np.eye(3)), ["position", "None"]),
    (
        "pose feedforward",
        lambda: FramePoseTask("gripper").set_target(np.zeros(3), np.eye(3), feedforward=np.zeros(3)),
        ["feedforward", "(3,)"],
    ),
    (
        "relative 2I",
        lambda: RelativeFrameTask("cutter_tip", "gripper").set_target(np.zeros(3), 2 * np.eye(3)),
        ["RelativeFrameTask", "rotation", "det R = 8"],
    ),
    (
        "pose assign rotation",
        lambda: setattr(FramePoseTask("gripper"), "target_rotation", 2 * np.eye(3)),
        ["rotation", "det R = 8"],
    ),
    (
        "pose assign feedforward",
        lambda: setattr(FramePoseTask("gripper"), "feedforward", None),
        ["feedforward", "None"],
    ),
    (
        "relative assign position",
        lambda: setattr(RelativeFrameTask("cutter_tip", "gripper"), "target_position", None),
        ["position", "None"],
    ),
    ("relative same", lambda: RelativeFrameTask("gripper", "gripper"), ["root", "'gripper'"]),
    ("relative root None", lambda: RelativeFrameTask("gripper", None), ["root", "None"]),
    ("jpl gain 2", lambda: JointPositionLimit(C, gain=2), ["JointPositionLimit gain", "2", "(0, 1]"]),
    ("jpl gain 0", lambda: JointPositionLimit(C, gain=0.0), ["JointPositionLimit gain", "0.0", "(0, 1]"]),
    ("jpl gain str", lambda: JointPositionLimit(C, gain="abc"), ["JointPositionLimit gain", "'abc'"]),
    ("jpl gain None", lambda: JointPositionLimit(C, gain=None), ["JointPositionLimit gain", "None"]),
    ("jpl gain nan", lambda: JointPositionLimit(C, gain=np.nan), ["JointPositionLimit gain", "nan"]),
    (
        "jpl lower>upper",
        lambda: JointPositionLimit(C, lower=np.full(12, 1.0), upper=np.zeros(12)),
        ["lower", "upper", "lower[0] = 1 > upper[0] = 0"],
    ),
    (
        "jpl one crossed",
        lambda: JointPositionLimit(C, lower=np.r_[np.zeros(11), 2.0], upper=np.ones(12)),
        ["lower[11] = 2 > upper[11] = 1"],
    ),
    ("jpl lower 11", lambda: JointPositionLimit(C, lower=np.zeros(11)), ["lower", "(11,)"]),
    ("jpl lower nan", lambda: JointPositionLimit(C, lower=np.full(12, np.nan)), ["lower", "nan"]),
    ("jpl upper -inf", lambda: JointPositionLimit(C, upper=-np.inf), ["upper", "-inf"]),
    ("jpl lower None-list", lambda: JointPositionLimit(C, lower=[None] * 12), ["lower", "None"]),
    ("jpl max_acc<0", lambda: JointPositionLimit(C, max_acceleration=-1.0), ["max_acceleration", "-1"]),
    ("jpl max_acc str", lambda: JointPositionLimit(C, max_acceleration="x"), ["max_acceleration", "'x'"]),
    ("jpl config None", lambda: JointPositionLimit(None), ["configuration", "None"]),
    ("jpl compute dt 0", lambda: JointPositionLimit(C).compute(C, 0.0), ["dt", "0.0"]),
    ("jvl max<0", lambda: JointVelocityLimit(C, max_velocity=-1.0), ["max_velocity", "-1"]),
    ("jvl max str", lambda: JointVelocityLimit(C, max_velocity="fast"), ["max_velocity", "'fast'"]),
    ("jvl max 11", lambda: JointVelocityLimit(C, max_velocity=np.ones(11)), ["max_velocity", "(11,)"]),
    ("jvl max nan", lambda: JointVelocityLimit(C, max_velocity=np.nan), ["max_velocity", "nan"]),
    ("jvl config str", lambda: JointVelocityLimit("robot"), ["configuration", "'robot'"]),
    ("config model", lambda: Configuration("x"), ["Configuration model", "str"]),
    ("config q str", lambda: Configuration.dual_ur5e(q="abc"), ["q", "'abc'"]),
    ("update None", lambda: C.update(None), ["q", "None"]),
    ("update Nones", lambda: C.update([None] * 12), ["q", "None"]),
    ("update 11", lambda: C.update(np.zeros(11)), ["q", "(11,)"]),
    ("update complex", lambda: C.update(np.zeros(12) + 1j), ["q", "+1.j"]),
    ("integrate 11", lambda: C.integrate(np.zeros(11), 0.1), ["qdot", "(11,)"]),
    ("integrate dt nan", lambda: C.integrate(np.zeros(12), np.nan), ["dt", "nan"]),
    ("integrate dt<0", lambda: C.integrate(np.zeros(12), -0.1), ["dt", "-0.1"]),
    ("frame_id 1e6", lambda: C.frame_jacobian_by_id(10**6), ["frame_id", "1000000"]),
    ("frame_id float", lambda: C.frame_jacobian_by_id(2.0), ["frame_id", "2.0"]),
    ("assign q", lambda: setattr(C, "q", None), ["q", "None"]),
    ("point None", lambda: C.point_jacobian("gripper", None), ["point", "None"]),
    ("urdf None", lambda: Configuration.from_urdf(None), ["URDF path", "None"]),
    ("residual qdot", lambda: DampingTask(12).residual(C, np.zeros(11), 0.002), ["qdot", "(11,)"]),
    ("tasks empty", lambda: check_tasks([]), ["tasks", "empty"]),
    ("tasks None", lambda: check_tasks(None), ["tasks", "None"]),
    ("tasks one Task", lambda: check_tasks(DampingTask(12)), ["tasks", "DampingTask"]),
    ("tasks non-Task", lambda: check_tasks([DampingTask(12), "posture"]), ["tasks[1]", "'posture'"]),
    ("limits non-Limit", lambda: check_limits([JointVelocityLimit(C), 3]), ["limits[1]", "3"]),
]


@pytest.mark.parametrize("call, fragments", [case[1:] for case in BAD_INPUT], ids=[c[0] for c in BAD_INPUT])
def test_bad_input_raises_own_error_naming_argument_and_value(call, fragments):
    """Catches foreign exceptions (TypeError, OverflowError, numpy's ValueError) and messages
    that misreport the value (``update(None)`` reported as ``got [nan nan ...]``)."""
    with pytest.raises(HarvestQPError) as info:
        call()
    assert isinstance(info.value, InvalidInputError), f"{type(info.value).__name__}: {info.value}"
    message = str(info.value)
    for fragment in fragments:
        assert fragment in message, f"{fragment!r} not in {message!r}"
    if "None" in fragments:
        assert "nan" not in message.lower(), message  # None must not be reported as the NaN numpy makes of it


def test_a_rejected_set_target_keeps_the_old_target():
    """Catches a setter that assigns the position before rejecting the rotation (half-updated target)."""
    task = FramePoseTask("gripper")
    task.set_target([0.1, 0.2, 0.3], np.eye(3))
    with pytest.raises(InvalidInputError):
        task.set_target([9.0, 9.0, 9.0], 2 * np.eye(3))
    np.testing.assert_array_equal(task.target_position, [0.1, 0.2, 0.3])


def test_assigning_q_recomputes_the_kinematics(rng):
    """Oracle: pinocchio's forward kinematics. Catches ``configuration.q = ...`` storing the
    joints without recomputing frame placements and Jacobians (a stale pose)."""
    configuration = Configuration.dual_ur5e()
    q = configuration.q + rng.uniform(-0.5, 0.5, 12)
    configuration.q = q
    model = configuration.model
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    np.testing.assert_allclose(
        configuration.frame_position("gripper"), data.oMf[model.getFrameId("gripper")].translation
    )


def test_valid_inputs_still_pass(dual):
    """The checks accept what the public API documents (no over-strict rejection)."""
    FrameTwistTask("camera", weight=[1, 1, 1, 1, 1, 0], weight_frame="local", level=np.int64(2), gain=0)
    FramePoseTask("gripper", level=2.0).set_target([0, 0, 1], pin.exp3(np.array([0.3, -0.2, 1.0])).tolist())
    PostureTask(list(dual.q), weight=np.arange(12.0), gain=np.float32(2.0))
    DampingTask(np.int64(12), weight=0.0)
    limit = JointPositionLimit(dual, gain=1, lower=-np.inf, upper=np.inf, max_acceleration=0.0)
    assert np.all(np.isinf(limit.compute(dual, 0.002).upper))
    JointVelocityLimit(dual, max_velocity=[1.0] * 12)
    assert len(check_tasks((DampingTask(12),), dual)) == 1
    assert check_limits([], dual) == []


# ----------------------------------------------------------------------------- sizes against the model
def _spy_on_solver_kernels(monkeypatch) -> list[tuple[str, object, bool]]:
    """Replace every compiled (numba) kernel the solver module calls with a recording spy:
    ``(name, returned, whether it changed its first argument)`` per call."""
    calls: list[tuple[str, object, bool]] = []
    for name, obj in vars(solver_module).items():
        if type(obj).__name__ == "CPUDispatcher":

            def spy(*args, _name=name, _kernel=obj):
                before = args[0].copy() if isinstance(args[0], np.ndarray) else None
                returned = _kernel(*args)
                changed = before is not None and not np.array_equal(before, args[0])
                calls.append((_name, returned, changed))
                return returned

            monkeypatch.setattr(solver_module, name, spy)
    assert any(type(obj).__name__ == "function" and obj.__name__ == "spy" for obj in vars(solver_module).values())
    return calls


def _assembly(calls) -> list[tuple[str, object, bool]]:
    """The Hessian-assembly kernel calls among ``calls`` (one per task)."""
    return [call for call in calls if call[0].startswith("accumulate_")]


def _refused_untouched(call) -> bool:
    """An assembly call that refused its rows (returned False) and wrote nothing into the Hessian."""
    _name, returned, changed = call
    return returned is False and not changed


@pytest.mark.parametrize(
    "task, fragments",
    [
        (DampingTask(13), ["DampingTask nv", "nv = 12", "13"]),
        (DampingTask(11), ["DampingTask nv", "nv = 12", "11"]),
        (PostureTask(np.zeros(11)), ["PostureTask target", "nv = 12", "11 entries"]),
        (PostureTask(np.zeros(13)), ["PostureTask target", "nv = 12", "13 entries"]),
    ],
    ids=["damping13", "damping11", "posture11", "posture13"],
)
def test_joint_space_task_of_wrong_size_raises_without_writing(dual, monkeypatch, task, fragments):
    """Catches DampingTask(13) writing past the 12x12 Hessian in a numba kernel and
    DampingTask(11)/PostureTask(11) silently acting on 11 of 12 joints: the assembly kernel
    refuses the rows (writes nothing) and the solver raises DimensionError naming them."""
    calls = _spy_on_solver_kernels(monkeypatch)
    with pytest.raises(DimensionError) as info:
        Solver().solve(dual, [FrameTwistTask("camera"), task])
    for fragment in fragments:
        assert fragment in str(info.value)
    # The task may be stopped by its own model check before any kernel; if a kernel saw its rows,
    # it refused them. Only the camera task's rows (which fit) were ever written.
    assembly = _assembly(calls)
    assert [call[1] for call in assembly if not _refused_untouched(call)] in ([], [True]), calls
    assert len(assembly) <= 2, calls
    # The same mistake is caught up front when the task list is checked against the model.
    with pytest.raises(DimensionError):
        check_tasks([task], dual)


def test_right_size_reaches_the_kernels(dual, monkeypatch):
    """The spy does see the kernels accept and write when the sizes are right (so the tests around can fail)."""
    calls = _spy_on_solver_kernels(monkeypatch)
    Solver().solve(dual, [FrameTwistTask("camera"), DampingTask(12), PostureTask(dual.q)])
    assembly = _assembly(calls)
    assert len(assembly) == 3 and all(returned is True and changed for _, returned, changed in assembly), calls


def test_user_task_returning_wrong_shape_raises_dimension_error(dual, monkeypatch):
    """Catches a user ``compute`` with the wrong column count written past the Hessian by ``accumulate_task``."""

    class Wide(Task):
        def compute(self, configuration, dt):
            return np.ones((2, 13)), np.zeros(2)

    calls = _spy_on_solver_kernels(monkeypatch)
    with pytest.raises(DimensionError, match=r"\(2, 12\).*\(2, 13\)"):
        Solver().solve(dual, [Wide(2)])
    assert [_refused_untouched(call) for call in _assembly(calls)] == [True], calls


def test_user_task_overriding_compute_rows_is_checked_too(dual, monkeypatch):
    """Catches the fast path (``compute_rows`` with ``J = None`` meaning identity) handing
    ``accumulate_diagonal`` a 13-entry weight for a 12x12 Hessian from user code."""

    class Joints(Task):
        def compute(self, configuration, dt):
            return np.eye(self.dim), np.zeros(self.dim)

        def compute_rows(self, configuration, dt):
            return None, np.zeros(self.dim)

    calls = _spy_on_solver_kernels(monkeypatch)
    with pytest.raises(DimensionError, match=r"J = None \(identity\) needs weight and v of shape \(12,\)"):
        Solver().solve(dual, [Joints(13)])
    assert [_refused_untouched(call) for call in _assembly(calls)] == [True], calls
    assert Solver().solve(dual, [Joints(12)]).qdot.shape == (12,)


def test_user_task_rows_that_are_not_arrays_raise_the_package_error(dual):
    """Rows the compiled kernels cannot take at all (a list, complex numbers) end in the package's own
    error naming the task, not in numba's typing error."""

    class Listed(Task):
        def compute(self, configuration, dt):
            return [[1.0] * 12], np.zeros(1)

    class Complex(Task):
        def compute(self, configuration, dt):
            return np.ones((1, 12), dtype=complex), np.zeros(1, dtype=complex)

    with pytest.raises(DimensionError, match=r"Listed.*J list"):
        Solver().solve(dual, [Listed(1)])
    with pytest.raises(InvalidInputError, match=r"Complex.*complex128"):
        Solver().solve(dual, [Complex(1)])


@pytest.mark.parametrize("width", [11, 13])
def test_hard_task_rows_of_wrong_width_raise(dual, width):
    """Catches hard (level 0) rows skipping the size check: they bypass the assembly kernels and went
    straight to the backend's row loader (11 columns: read past the array's end; 13: the last column
    silently dropped). Found by an independent review of the kernels' own size check."""

    class Hard(Task):
        def __init__(self):
            super().__init__(1, level=0)

        def compute(self, configuration, dt):
            return np.arange(1.0, width + 1.0)[None], np.ones(1)

    with pytest.raises(DimensionError, match=rf"\(1, 12\).*\(1, {width}\)"):
        Solver().solve(dual, [Hard(), DampingTask(12)])
    with pytest.raises(InvalidInputError, match="not real numbers"):

        class ComplexHard(Hard):
            def compute(self, configuration, dt):
                return np.ones((1, 12), dtype=complex), np.ones(1)

        Solver().solve(dual, [ComplexHard(), DampingTask(12)])


def test_assembly_kernels_refuse_sizes_that_do_not_fit():
    """The kernels index without bounds checks: each size mismatch is refused before any write; fitting rows
    give ``J^T W J`` and ``-J^T W v`` (numpy as the oracle)."""
    from harvest_qp.qp_kernels import accumulate_diagonal, accumulate_task

    rng = np.random.default_rng(3)
    J, w, v = rng.normal(size=(4, 6)), rng.uniform(0.5, 2.0, 4), rng.normal(size=4)
    H, f = np.zeros((6, 6)), np.zeros(6)
    assert accumulate_task(H, f, J, w, v) is True
    np.testing.assert_allclose(H, J.T @ np.diag(w) @ J, atol=1e-12)
    np.testing.assert_allclose(f, -J.T @ (w * v), atol=1e-12)
    for args in ((np.ones((4, 7)), w, v), (J, w[:3], v), (J, w, v[:3]), (J, np.ones(5), np.ones(5))):
        H0, f0 = H.copy(), f.copy()
        assert accumulate_task(H, f, *args) is False
        assert np.array_equal(H, H0) and np.array_equal(f, f0)
    floor = np.zeros(6)
    assert accumulate_diagonal(H, f, np.ones(6), np.ones(6), floor) is True
    for w_, v_ in ((np.ones(7), np.ones(7)), (np.ones(5), np.ones(5)), (np.ones(6), np.ones(5))):
        H0, f0, floor0 = H.copy(), f.copy(), floor.copy()
        assert accumulate_diagonal(H, f, w_, v_, floor) is False
        assert np.array_equal(H, H0) and np.array_equal(f, f0) and np.array_equal(floor, floor0)


def test_user_limit_rows_with_nan_are_refused_not_dropped(dual):
    """Catches a NaN row G qdot <= h reaching the backends, where it is never active: the constraint was
    dropped without a word (found by an independent review). The controller stops the arms instead."""
    from harvest_qp import TaskController

    class Broken(Limit):
        def compute(self, configuration, dt, previous_qdot=None):
            G = np.zeros((1, 12))
            G[0, 0] = 1.0
            return LimitRows(G=G, h=np.array([np.nan]))

    with pytest.raises(InvalidInputError, match="Broken.*NaN"):
        Solver().solve(dual, [DampingTask(12)], [Broken()])
    step = TaskController(dual, [DampingTask(12)], [Broken()]).step(dual.q)
    assert step.status.startswith("fallback") and np.all(np.isfinite(step.qdot))


def test_user_fill_box_and_compute_rows_mistakes_raise_the_package_errors(dual):
    """A fill_box override writing 11 entries and a compute_rows returning three values ended in numpy's and
    Python's own ValueError (independent review): now DimensionError / InvalidInputError naming the culprit."""

    class ShortBox(Limit):
        has_box = True
        priority = 3

        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(lower=-np.ones(12), upper=np.ones(12))

        def fill_box(self, configuration, dt, previous_qdot, lower, upper):
            lower[:] = -np.ones(11)
            upper[:] = np.ones(11)

    class Triple(Task):
        def compute(self, configuration, dt):
            return np.eye(12), np.zeros(12)

        def compute_rows(self, configuration, dt):
            return None, np.zeros(12), "extra"

    with pytest.raises(DimensionError, match=r"ShortBox.fill_box.*12 entries"):
        Solver().solve(dual, [DampingTask(12)], [ShortBox()])
    with pytest.raises(InvalidInputError, match=r"Triple.*compute_rows must return the pair"):
        Solver().solve(dual, [Triple(12)])


def test_user_limit_rows_of_wrong_width_raise(dual):
    """Catches user inequality rows with 11 columns reaching the feasibility kernel,
    which reads ``G[r, i]`` for every ``i < nv`` without bounds checks."""

    class Narrow(Limit):
        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(G=np.ones((1, 11)), h=np.ones(1))

    class Wrong(Limit):
        has_box = True

        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(lower=-np.ones(11), upper=np.ones(11))

    with pytest.raises(DimensionError, match=r"Narrow.*\(1, 11\).*\(m, 12\)"):
        Solver().solve(dual, [DampingTask(12)], [Narrow()])
    with pytest.raises(DimensionError, match=r"Wrong.*lower of shape \(11,\), expected \(12,\)"):
        Solver().solve(dual, [DampingTask(12)], [Wrong()])


def test_limits_sized_for_another_model_raise(dual, single):
    """Catches a limit built for the 6-joint model read past its end on the 12-joint model
    (``position_limit_bounds`` indexes its limits by ``len(q)`` without bounds checks)."""
    small_pos, small_vel = JointPositionLimit(single), JointVelocityLimit(single)
    for limit in (small_pos, small_vel):
        with pytest.raises(DimensionError, match=r"6 entries but the model has nv = 12"):
            Solver().solve(dual, [DampingTask(12)], [limit])
    with pytest.raises(DimensionError, match=r"12 entries but the model has nv = 6"):
        JointPositionLimit(dual).compute(single, 0.002)
    with pytest.raises(DimensionError):
        check_limits([JointVelocityLimit(dual)], single)


def test_frame_twist_task_moved_to_another_model_uses_that_model(dual, single, rng):
    """Catches the frame index and local-row buffers cached for the first model only:
    on a 6-joint model the rows must be 6 wide and equal pinocchio's Jacobian there."""
    task = FrameTwistTask("camera", weight_frame="local")
    task.compute_rows(dual, 0.002)
    single.update(rng.uniform(-1, 1, 6))
    J, _ = task.compute_rows(single, 0.002)
    data = single.model.createData()
    J_local = pin.computeFrameJacobian(single.model, data, single.q, single.model.getFrameId("camera"), pin.LOCAL)
    assert J.shape == (6, 6)
    np.testing.assert_allclose(J, J_local, atol=1e-12)
    qdot = Solver().solve(single, [task, DampingTask(6)]).qdot
    assert qdot.shape == (6,)


def test_reassigned_frame_is_the_one_computed(dual):
    """Catches a stale cached frame index after ``task.frame = ...``."""
    task = FrameTwistTask("camera")
    task.compute_rows(dual, 0.002)
    task.frame = "gripper"
    J, _ = task.compute_rows(dual, 0.002)
    data = dual.model.createData()
    frame = dual.model.getFrameId("gripper")
    J_oracle = pin.computeFrameJacobian(dual.model, data, dual.q, frame, pin.LOCAL_WORLD_ALIGNED)
    np.testing.assert_allclose(J, J_oracle, atol=1e-12)
    task.frame = "nope"
    with pytest.raises(UnknownFrameError, match="valid frames"):
        task.compute_rows(dual, 0.002)


def test_check_helpers_for_the_solver(dual):
    """The helpers the solver can call on rows from user code reject what a kernel would mis-index."""
    twist = FrameTwistTask("camera")
    check_task_rows(twist, np.zeros((6, 12)), np.zeros(6), 12)
    check_task_rows(DampingTask(12), None, np.zeros(12), 12)
    for J, v in [(np.zeros((6, 11)), np.zeros(6)), (np.zeros((5, 12)), np.zeros(5)), (np.zeros((6, 12)), np.zeros(7))]:
        with pytest.raises(DimensionError):
            check_task_rows(twist, J, v, 12)
    with pytest.raises(DimensionError):
        check_task_rows(DampingTask(11), None, np.zeros(11), 12)

    class Rows(Limit):
        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(G=np.zeros((1, 11)), h=np.zeros(1))

    check_limit_rows(Rows(), np.zeros((2, 12)), np.zeros(2), 12)
    check_limit_rows(Rows(), None, None, 12)
    with pytest.raises(DimensionError, match=r"\(1, 11\)"):
        check_limit_rows(Rows(), np.zeros((1, 11)), np.zeros(1), 12)
    with pytest.raises(DimensionError):
        check_limit_rows(Rows(), np.zeros((2, 12)), np.zeros(3), 12)
    with pytest.raises(UnknownFrameError):
        check_tasks([FrameTwistTask("elbow")], dual)


@pytest.mark.parametrize(
    ("tasks", "limits", "error", "text"),
    [
        ([], [], "InvalidInputError", "at least one Task"),
        (["x"], [], "InvalidInputError", "tasks[0] must be a Task"),
        ("damping13", [], "DimensionError", "nv = 12, got 13"),
        ("twist", ["notalimit"], "InvalidInputError", "limits[0] must be a Limit"),
    ],
)
def test_task_controller_refuses_bad_tasks_and_limits_when_built(tasks, limits, error, text):
    """Catches a controller that accepts a wrong task list and then safe-stops on every tick
    (or, for DampingTask(13), hands a 13-wide task to the 12x12 kernels)."""
    import harvest_qp
    from harvest_qp import Configuration, TaskController
    from harvest_qp.tasks import DampingTask, FrameTwistTask

    config = Configuration.dual_ur5e()
    if tasks == "damping13":
        tasks = [DampingTask(13)]
    elif tasks == "twist":
        tasks = [FrameTwistTask("camera")]
    with pytest.raises(getattr(harvest_qp, error), match=re.escape(text)):
        TaskController(config, tasks, limits)


def test_acceleration_limit_built_for_a_smaller_model_is_refused():
    """Catches JointAccelerationLimit reading max_acceleration past its end on a bigger model."""
    import pinocchio as pin

    from harvest_qp import Configuration, DimensionError
    from harvest_qp.limits import JointAccelerationLimit

    big = Configuration.dual_ur5e()
    small_model = pin.buildReducedModel(big.model, list(range(8, 14)), big.q.copy())
    small = Configuration(small_model)
    limit = JointAccelerationLimit(small)
    with pytest.raises(DimensionError, match=f"max_acceleration has {small.nv} entries"):
        limit.fill_box(big, 0.002, np.zeros(12), np.empty(12), np.empty(12))


def test_a_limit_inside_the_package_is_size_checked_too(dual):
    """A new limit written inside ``harvest_qp.limits`` (the documented way to add one) gets its rows
    checked like a user's: found by a newcomer, whose 11-column rows were solved silently because
    built-in limits were exempt from the check."""

    class InPackage(Limit):
        __module__ = "harvest_qp.limits.in_package"  # as if written in the package (seen at class creation)

        def compute(self, configuration, dt, previous_qdot=None):
            return LimitRows(G=np.ones((1, 11)), h=np.ones(1))

    with pytest.raises(DimensionError, match=r"InPackage.*\(1, 11\).*\(m, 12\)"):
        Solver().solve(dual, [DampingTask(12)], [InPackage()])
