"""The paper episode's task rows in one compiled call (``Solver._episode_rows``) against each task's
own ``compute_rows`` (the general path), and the cached plan against every change of the task set.

Oracle throughout: the same tasks' ``compute_rows`` (pinocchio's Jacobians, the tasks' own kernels
and numpy), through ``Solver._rows_and_levels``, and the general ``Solver._solve`` on a twin solver.
"""

import numpy as np
import pytest

from harvest_qp import Configuration, TaskController
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.qp_kernels import IDENTITY_ROWS
from harvest_qp.robot.description import HOME_Q
from harvest_qp.solver import Solver
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask


def _episode_tasks(rng, *, gains=(1.0, 1.0, 1.0, 1.0)):
    """The paper episode's five tasks (tasks/paper.yaml: levels 1, 1, 2, 2, 2), random references."""
    camera = FrameTwistTask("camera", weight=[1, 1, 1, 1, 1, 0], weight_frame="local", level=1, gain=gains[0])
    gripper = FrameTwistTask("gripper", weight=1.0, level=1, gain=gains[1])
    roll = FrameTwistTask("camera", weight=[0, 0, 0, 0, 0, 1.0], weight_frame="local", level=2, gain=gains[2])
    posture = PostureTask(HOME_Q + rng.normal(0, 0.2, 12), weight=1e-4, level=2, gain=gains[3])
    damping = DampingTask(12, weight=1e-3, level=2)
    for task in (camera, gripper, roll):
        task.set_reference(rng.normal(0, 0.05, 6))
    return [camera, gripper, roll, posture, damping]


def _general_rows(config, tasks):
    """Each task's own ``compute_rows`` (the solver's general path), on fresh kinematics."""
    config.update(config.q.copy())  # a fresh _frame_rows: the camera task computes its rows itself
    general = Solver()
    general._box_limits([], config.nv)  # (no limits: the rows of the tasks only)
    by_level = general._rows_and_levels(config, tasks, 0.002, None, config.nv)[3]
    return {level: [(task, None if J is None else J.copy(), v.copy()) for task, J, v in entries]
            for level, entries in by_level.items()}


def _same_rows(a, b):
    assert sorted(a) == sorted(b)
    for level in a:
        assert len(a[level]) == len(b[level])
        for (ta, Ja, va), (tb, Jb, vb) in zip(a[level], b[level]):
            assert ta is tb
            assert (Ja is None) == (Jb is None)
            assert Ja is None or (Ja.shape == Jb.shape and np.array_equal(Ja, Jb))
            assert va.shape == vb.shape and np.array_equal(va, vb)


@pytest.mark.parametrize("gains", [(1.0, 1.0, 1.0, 1.0), (0.7, 1.3, 2.0, 0.4)])
def test_episode_rows_equal_each_tasks_compute_rows_bit_for_bit(rng, gains):
    """Oracle: the tasks' own ``compute_rows`` (pinocchio's frame Jacobians rotated by the tasks'
    kernels, the posture's ``gain * (target - q)``). The plan is taken for the episode's set and
    gives the same ``(task, J, v)`` per level, bit for bit, with and without gains.

    Bugs caught (planted and seen failing): the roll twist rotated from the camera's reference;
    the camera's gain not applied; the posture velocity written into the damping task's zeros."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks = _episode_tasks(rng, gains=gains)
    solver = Solver()
    for _ in range(6):
        config.update(HOME_Q + rng.normal(0, 0.3, 12))
        expected = _general_rows(config, tasks)  # also binds the tasks to the model
        plan = solver._episode_plan(config, tasks)
        assert plan is not None
        by_level, (rows1, rows2) = solver._episode_rows(config, plan)
        _same_rows(by_level, expected)
        # The fused cascade's arguments: (J or the identity marker, weight, v) per task, in order.
        for flat, entries in ((rows1, by_level[1]), (rows2, by_level[2])):
            built = [x for task, J, v in entries for x in (IDENTITY_ROWS if J is None else J, task.weight, v)]
            assert len(flat) == len(built) and all(x is y for x, y in zip(flat, built))
        for task in tasks[:3]:
            task.set_reference(rng.normal(0, 0.05, 6))


def test_episode_plan_follows_every_change_of_the_task_set(rng):
    """The cached plan is dropped whenever the task set stops being the episode's: a level, the
    weight axes, the frame, the task list, a subclass, another model. Oracle: the general path's
    rows (the plan, when taken, must give them; when not, ``_solve_step`` takes the general path).

    Bugs caught (planted and seen failing): the level setter not marking the structure changed (the
    stale plan put the roll task on its old level); the list identity checks skipped (a swapped
    list kept the plan)."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks = _episode_tasks(rng)
    solver = Solver()
    _general_rows(config, tasks)
    assert solver._episode_plan(config, tasks) is not None

    def check(expect_plan):
        expected = _general_rows(config, tasks)
        plan = solver._episode_plan(config, tasks)
        assert (plan is not None) == expect_plan
        if plan is not None:
            _same_rows(solver._episode_rows(config, plan)[0], expected)

    camera, gripper, roll, posture, damping = tasks
    roll.level = 1  # three tasks above: not the episode's structure
    check(False)
    roll.level = 2
    check(True)
    roll.level, posture.level, damping.level = 3, 3, 3  # another lower level: still the structure
    check(True)
    gripper.weight_frame = "local"
    check(False)
    gripper.weight_frame = "world"
    check(True)
    roll.frame = "gripper"  # roll rows on another frame
    check(False)
    roll.frame = "camera"
    check(True)
    camera.weight = [1, 1, 1, 0, 0, 0]  # a new weight array: taken from the task
    check(True)
    tasks[0], tasks[1] = tasks[1], tasks[0]  # the list changed in place
    check(False)
    tasks[0], tasks[1] = tasks[1], tasks[0]
    check(True)

    class MyDamping(DampingTask):
        pass

    tasks[4] = MyDamping(12, weight=1e-3, level=3)
    check(False)
    tasks[4] = damping
    check(True)
    # Another model (another Configuration of the same robot is another pinocchio model object).
    other = Configuration.dual_ur5e(HOME_Q)
    assert solver._episode_plan(other, tasks) is None  # not bound to it: compute_rows binds first


@pytest.mark.parametrize("gains", [(1.0, 1.0, 1.0, 1.0), (0.7, 1.3, 2.0, 0.4)])
def test_episode_step_equals_the_general_solve_bit_for_bit(rng, gains):
    """Oracle: the general ``Solver._solve`` (each task's ``compute_rows``, the general cascade) on a
    twin controller. The loop's ``_step`` with the episode's task set (the plan taken, checked by a
    spy) gives the same command, acceleration, status and problems every tick, including ticks
    after the tasks' references, gains and levels changed.

    Bugs caught (planted and seen failing): the level setter not marking the structure changed
    (after the levels change at tick 7 the stale plan keeps the old levels); the roll twist
    rotated from the camera's reference."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks = _episode_tasks(rng, gains=gains)
    limits = [CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)]
    fast = TaskController(config, tasks, limits)
    general = TaskController(config, tasks, limits)
    for controller in (fast, general):
        controller.solver.fallback_backends = ("quadprog",)  # proxsuite is not bit-for-bit repeatable
    taken = []
    inner = fast.solver._episode_rows
    fast.solver._episode_rows = lambda *args: taken.append(1) or inner(*args)
    for step in range(12):
        q = HOME_Q + rng.normal(0, 0.15, 12)
        previous = rng.normal(0, 0.005, 12)
        fast.previous_qdot = previous.copy()
        general.previous_qdot = previous.copy()
        config.update(q)
        a = fast._step(q, reuse_kinematics=True)
        sa = fast.solver_solution
        b = general.step(q)
        sb = general.solver_solution
        assert a.status == b.status and a.ok
        assert np.array_equal(a.qdot, b.qdot) and np.array_equal(a.acceleration, b.acceleration)
        assert len(sa.problems) == len(sb.problems)
        for pa, pb in zip(sa.problems, sb.problems):
            assert pa.level == pb.level
            for name in ("H", "f", "A", "b", "lower", "upper", "G", "h"):
                assert np.array_equal(getattr(pa, name), getattr(pb, name)), name
        for task in tasks[:3]:
            task.set_reference(rng.normal(0, 0.05, 6))
        if step == 6:
            tasks[3].gain = 2.5
            for task in tasks[2:]:
                task.level = 3
    assert len(taken) >= 10  # every tick but the first (the tasks bind there)


def test_episode_step_resumes_and_relaxes_like_the_general_solve(rng, monkeypatch):
    """Oracle: the general ``Solver._solve`` on a twin solver. Fuzz-like states of the episode's task
    set (large joint offsets and previous commands: DAQP reporting infeasibility, relaxations) and,
    every fourth state, every fused check rejecting (its tolerance set below zero: the loop resumes
    from the fused call's results with the episode rows' ``(task, J, v)``, then ``_checked`` accepts):
    the same outcome bit for bit, retries and relaxations included, or the same error.

    Bug caught (planted and seen failing): ``by_level`` with the posture and damping tasks swapped
    (the fused call, given ``flat``, is unaffected; the levels the loop resumes sum in another
    order; the plain step test above does not see it)."""
    import harvest_qp.solver as solver_module
    from harvest_qp._daqp_native import CASCADE2

    from tests.core.test_qp_speed_paths import _outcome, _same_outcome

    stages = []
    wrapped = {}
    for key, kernel in CASCADE2.items():
        def spy(*args, _kernel=kernel):
            out = _kernel(*args)
            stages.append(int(out[0]))
            return out
        wrapped[key] = spy
    monkeypatch.setattr(solver_module, "CASCADE2", wrapped)
    config = Configuration.dual_ur5e(HOME_Q)
    tasks = _episode_tasks(rng)
    limits = TaskController(config, tasks, [CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)]).limits
    fast, general = Solver(fallback_backends=("quadprog",)), Solver(fallback_backends=("quadprog",))
    taken = []
    inner = fast._episode_rows
    fast._episode_rows = lambda *args: taken.append(1) or inner(*args)
    relaxed = 0
    for k in range(40):
        q = np.clip(HOME_Q + rng.normal(0, 0.6, 12), config.lower_limits, config.upper_limits)
        previous = rng.uniform(-0.5, 0.5, 12) * config.velocity_limits
        config.update(q)
        for task in tasks[:3]:
            task.set_reference(rng.normal(0, 0.3, 6))
        with monkeypatch.context() as m:
            if k % 4 == 3:
                m.setattr(solver_module, "FEASIBILITY_TOLERANCE", -1.0)
            a = _outcome(lambda p=previous: fast._solve_step(config, tasks, limits, 0.002, p)[0])
        b = _outcome(lambda p=previous: general._solve(config, tasks, limits, 0.002, p))
        _same_outcome(a, b)
        relaxed += not isinstance(a, tuple) and a.box_relaxation is not None
    assert len(taken) >= 35
    assert relaxed >= 2
    assert {1, 3} <= set(stages), sorted(set(stages))


@pytest.mark.parametrize("where", ["instance", "class"])
def test_a_compute_rows_override_runs_every_step_as_in_the_general_path(rng, where, monkeypatch):
    """Oracle: the override itself (it counts its calls and zeroes the gripper's reference
    velocity, so the grasping arm must not move). ``compute_rows`` set on a task object or patched
    on its class must run every step, as the general path runs it.

    Bug caught (an audit's reproducer; planted by dropping ``_builtin_compute_rows_intact`` from the
    plan's per-tick check, seen failing): the cached plan built the rows itself after the first
    step, calling the override once in 3 steps, and the gripper arm moved at up to 0.04 rad/s."""
    config = Configuration.dual_ur5e(HOME_Q)
    tasks = _episode_tasks(rng)
    gripper = tasks[1]
    controller = TaskController(config, tasks)
    q = HOME_Q.copy()
    config.update(q)
    for _ in range(2):  # the first step binds the tasks, the second caches the plan
        config.update(q)
        controller._step(q, reuse_kinematics=True)
    assert controller.solver._episode is not None
    calls = []
    original = FrameTwistTask.compute_rows

    def frozen(self, configuration, dt):
        calls.append(self)
        J, v = original(self, configuration, dt)
        return J, (np.zeros_like(v) if self is gripper else v)

    if where == "instance":
        gripper.compute_rows = frozen.__get__(gripper)
    else:
        monkeypatch.setattr(FrameTwistTask, "compute_rows", frozen)
    for _ in range(3):
        config.update(q)
        out = controller._step(q, reuse_kinematics=True)
    assert sum(task is gripper for task in calls) == 3
    assert np.abs(out.qdot[6:]).max() < 1e-9
