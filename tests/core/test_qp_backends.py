"""QP backends against quadprog called directly, infeasibility reports, and the retry chain."""

import numpy as np
import pytest
import quadprog

from harvest_qp import InfeasibleProblemError, Solver, SolverError
from harvest_qp.backends import FEASIBILITY_TOLERANCE, SolverAccuracyError, SolverCyclingError, make_backend
from harvest_qp.limits import CollisionAvoidance, JointPositionLimit, JointVelocityLimit
from harvest_qp.robot.description import HOME_Q
from harvest_qp.solver import INF, QPProblem
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

BACKENDS = ("daqp", "proxsuite", "quadprog", "qpsolvers:quadprog", "qpsolvers:daqp")


def _quadprog_direct(p: QPProblem) -> np.ndarray:
    """The oracle: quadprog.solve_qp on hand-stacked constraints (no harvest_qp code involved)."""
    n = p.n
    rows, bounds = [p.A], [p.b]
    finite = p.h < INF / 2
    rows += [-p.G[finite], -np.eye(n)[p.upper < INF / 2], np.eye(n)[p.lower > -INF / 2]]
    bounds += [-p.h[finite], -p.upper[p.upper < INF / 2], p.lower[p.lower > -INF / 2]]
    C, b = np.vstack(rows), np.concatenate(bounds)
    return quadprog.solve_qp(0.5 * (p.H + p.H.T), -p.f, C.T.copy(), b, p.A.shape[0])[0]


def _infeasible_problem(n=4) -> QPProblem:
    """x_0 <= -1 (box) and x_0 >= 0 (row): no solution."""
    upper = np.full(n, 1.0)
    upper[0] = -1.0
    G = np.zeros((1, n))
    G[0, 0] = -1.0
    return QPProblem(
        H=np.eye(n), f=np.zeros(n), lower=np.full(n, -2.0), upper=upper,
        A=np.zeros((0, n)), b=np.zeros(0), G=G, h=np.zeros(1),
    )


@pytest.mark.parametrize("name", ("daqp", "proxsuite", "quadprog", "qpsolvers:quadprog"))
def test_every_backend_reports_infeasibility_as_infeasible_problem_error(name):
    """Bug caught: quadprog (and DAQP at set-up) raising a plain SolverError, so the relaxation never ran.

    (Other qpsolvers backends return None without saying why: a plain SolverError.)
    """
    with pytest.raises(InfeasibleProblemError):
        make_backend(name).solve(_infeasible_problem())
    # DAQP's set-up path: a fresh model, then a second call with the same shape (update path).
    backend = make_backend("daqp")
    for _ in range(2):
        with pytest.raises(InfeasibleProblemError):
            backend.solve(_infeasible_problem())


@pytest.mark.parametrize("name", BACKENDS)
def test_qp_without_any_limit_solves_with_every_backend(name, rng):
    """Bug caught: quadprog failing on a QP with no constraint rows (empty constraint matrix)."""
    M = rng.normal(size=(12, 12))
    H = M @ M.T + np.eye(12)
    f = rng.normal(size=12)
    problem = QPProblem(
        H=H, f=f, lower=np.full(12, -INF), upper=np.full(12, INF),
        A=np.zeros((0, 12)), b=np.zeros(0), G=np.zeros((0, 12)), h=np.zeros(0),
    )
    np.testing.assert_allclose(make_backend(name).solve(problem), np.linalg.solve(H, -f), rtol=1e-7, atol=1e-9)


def _driven_together(configuration, rng):
    """A QP of a state where the arms are driven towards each other, with collision rows binding."""
    collision = CollisionAvoidance.dual_ur5e(configuration, influence_distance=0.2, gain=0.05)
    while True:
        configuration.update(np.clip(HOME_Q + rng.normal(0, 0.3, 12), configuration.lower_limits,
                                     configuration.upper_limits))
        if collision.distances(configuration).min() > 0.02:
            break
    cam, grasp = FrameTwistTask("camera"), FrameTwistTask("gripper")
    gap = configuration.frame_position("gripper") - configuration.frame_position("camera")
    cam.set_reference(np.concatenate([2.0 * gap, np.zeros(3)]))
    grasp.set_reference(np.concatenate([-2.0 * gap, np.zeros(3)]))
    tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12)]
    limits = [JointPositionLimit(configuration), JointVelocityLimit(configuration), collision]
    return tasks, limits


def test_backends_match_quadprog_called_directly_with_binding_collision_rows(configuration, rng):
    """Every backend's solution equals quadprog.solve_qp called on hand-stacked data.

    Bug caught: a backend that drops, flips or mis-pads collision rows (e.g. proxsuite's default
    settings returning wrong x flagged as solved) -- compared with an outside solver, not each other.
    """
    solvers = {name: Solver(name, fallback_backends=()) for name in ("daqp", "proxsuite", "quadprog")}
    binding, proxsuite_failed = 0, 0
    for _ in range(25):
        tasks, limits = _driven_together(configuration, rng)
        reference = None
        for name, solver in solvers.items():
            try:
                solution = solver.solve(configuration, tasks, limits, 0.002)
            except SolverError:
                # proxsuite (even with eps_primal_inf 1e-12 and a cold retry) sometimes stops at its
                # iteration limit on these QPs; it is a fallback backend, and it must never return a
                # wrong solution flagged as solved -- that is what is checked here.
                assert name == "proxsuite"
                proxsuite_failed += 1
                continue
            problem = solution.problems[-1]
            if reference is None:
                reference = _quadprog_direct(problem)
                binding += int(np.sum(np.abs(problem.G @ reference - problem.h) < 1e-9))
            np.testing.assert_allclose(solution.qdot, reference, atol=1e-6, err_msg=name)
    assert binding >= 10, f"only {binding} binding collision rows: the comparison must include active rows"
    assert proxsuite_failed <= 5


def _with(stand_ins: dict) -> Solver:
    """A daqp solver whose level-1 workspaces named in ``stand_ins`` are the given stand-ins (the
    relaxation QPs and any other level keep the real backends)."""

    def factory(name, level):
        return stand_ins[name] if level == 1 and name in stand_ins else make_backend(name)

    return Solver("daqp", backend_factory=factory)


class _Flaky:
    """A backend that always fails with the given error (a stand-in for DAQP cycling or lying)."""

    def __init__(self, error):
        self.error = error

    def solve(self, problem):
        raise self.error("planted failure", problem=problem, backend="flaky")


@pytest.mark.parametrize("error", [SolverCyclingError, InfeasibleProblemError, SolverError])
def test_a_failed_backend_is_retried_with_the_next_one(configuration, rng, error):
    """DAQP cycling (exitflag -2) and false infeasibility reports are retried before any fallback.

    Bug caught: no retry (the controller braked for 535 of 2,000 ticks of a crossing run).
    """
    tasks, limits = _driven_together(configuration, rng)
    solver = _with({"daqp": _Flaky(error)})
    solution = solver.solve(configuration, tasks, limits, 0.002)
    assert solution.retries and solution.retries[0] == f"daqp: {error.__name__}"
    np.testing.assert_allclose(solution.qdot, _quadprog_direct(solution.problems[-1]), atol=1e-6)


def test_feasibility_is_judged_relative_to_row_scale():
    """A row of size 1e4 off by 1e-6 (rounding) is accepted; a row of size 1 off by 1e-5 is not.

    Bug caught: the absolute 1e-7 tolerance rejected DAQP solutions off by 2e-7..1e-6.
    """
    n = 2
    base = dict(H=np.eye(n), f=np.zeros(n), lower=np.full(n, -INF), upper=np.full(n, INF),
                A=np.zeros((0, n)), b=np.zeros(0))
    big = QPProblem(G=np.array([[1e4, 0.0]]), h=np.array([1e4]), **base)
    assert big.scaled_violation(np.array([1.0 + 1e-10, 0.0])) < FEASIBILITY_TOLERANCE
    assert big.violation(np.array([1.0 + 1e-10, 0.0])) > FEASIBILITY_TOLERANCE  # absolute would reject
    small = QPProblem(G=np.array([[1.0, 0.0]]), h=np.array([1.0]), **base)
    assert small.scaled_violation(np.array([1.0 + 1e-5, 0.0])) > FEASIBILITY_TOLERANCE


def test_a_false_infeasibility_from_two_backends_is_caught_by_the_relaxation_check(configuration, rng):
    """DAQP and quadprog both (falsely) report infeasibility on a feasible QP: proxsuite still solves it.

    Two agreeing reports skip proxsuite on the first pass (speed); the relaxation check then
    finds that no widening is needed, and the QP is solved again with every backend.
    Oracle: quadprog called directly. Bug caught: believing two agreeing reports without
    the relaxation check (the controller would brake for a solvable problem).
    """
    tasks, limits = _driven_together(configuration, rng)
    solver = _with({"daqp": _Flaky(InfeasibleProblemError), "quadprog": _Flaky(InfeasibleProblemError)})
    solution = solver.solve(configuration, tasks, limits, 0.002)
    assert not solution.relaxed and not np.any(solution.box_relaxation)
    assert solution.retries[-2:] == ["daqp: InfeasibleProblemError", "quadprog: InfeasibleProblemError"]
    np.testing.assert_allclose(solution.qdot, _quadprog_direct(solution.problems[-1]), atol=1e-6)


class _Counting:
    """A backend stand-in that counts its calls and fails."""

    def __init__(self):
        self.calls = 0

    def solve(self, problem):
        self.calls += 1
        raise SolverError("counted", problem=problem, backend="counting")


def test_agreeing_infeasibility_reports_go_to_the_relaxation_without_proxsuite():
    """States whose acceleration box conflicts with a collision row are relaxed without a proxsuite call.

    On an infeasible QP proxsuite only stops at its 1,000-iteration cap, twice (0.33 s per tick
    measured, in 61 of 400 fuzz states, none solved). Bug caught: asking proxsuite after DAQP and
    quadprog agree on infeasibility, i.e. a control tick of hundreds of milliseconds.
    """
    from benchmarks.bench_fuzz import fuzz_states

    relaxed = 0
    for _, _, controller, q, _ in fuzz_states(16, seed=5, categories=("combination",)):
        spy = _Counting()
        controller.solver = _with({"proxsuite": spy})
        step = controller.step(q)
        assert step.ok, step.status
        relaxed += "relaxed" in step.status
        assert spy.calls == 0
    assert relaxed >= 8, "the states must need the relaxation"


class _Inaccurate:
    """A backend stand-in that returns ``x`` as a solution just outside the 1e-7 tolerance."""

    def __init__(self, x, violation):
        self.x, self.violation = x, violation

    def solve(self, problem):
        error = SolverAccuracyError("planted inaccuracy", problem=problem, backend="inaccurate")
        error.x, error.violation = np.array(self.x), self.violation
        raise error


def test_solutions_just_outside_the_tolerance_from_every_backend_do_not_brake(configuration, rng):
    """Every backend returns a solution 2e-7..6e-7 (scale-relative) outside the constraints: the
    least violating one is used, not the relaxation or the safe stop (audit: seed 8 braked one
    tick on daqp's 6.3e-7). Beyond 1e-5 it is still a failure.
    Oracle: quadprog called directly. Bug caught: no last resort (the tick falls back)."""
    tasks, limits = _driven_together(configuration, rng)
    reference_solver = Solver("daqp")
    reference = reference_solver.solve(configuration, tasks, limits, 0.002)
    x_ref = _quadprog_direct(reference.problems[-1])
    solver = _with({
        name: _Inaccurate(x_ref + (0.0 if name == "proxsuite" else 1.0), violation)
        for name, violation in (("daqp", 6e-7), ("proxsuite", 2e-7), ("quadprog", 4e-7))
    })
    solution = solver.solve(configuration, tasks, limits, 0.002)
    np.testing.assert_allclose(solution.qdot, x_ref, atol=1e-6)
    assert solution.retries[-1] == "accepted proxsuite at 2.0e-07 relative violation"
    far = _with({name: _Inaccurate(x_ref, 1e-3) for name in ("daqp", "proxsuite", "quadprog")})
    with pytest.raises(SolverError):
        far.solve(configuration, tasks, limits, 0.002)
