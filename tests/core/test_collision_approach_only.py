"""CollisionAvoidance.set_approach_only: obstacle rows that stop a capsule but never push it."""

import numpy as np
import pytest

from harvest_qp import InvalidInputError, TaskController
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot import description as desc
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

DT = 0.002
GAP = 0.004  # [m] the capsule's starting distance to the wall, inside d_s = 0.01
CELL_RADIUS = 0.5 * np.sqrt(3) * 0.01  # an obstacle-map cell sphere (1 cm cells)


def _wall_in_front_of_gripper(configuration):
    """Nine cell spheres in a plane 4 mm (hand-computed) from the gripper capsule's surface.

    The capsule's world segment comes from pinocchio's frame placement and the description's
    end points (not from the limit's kernels); the wall's normal ``n`` is perpendicular to it.
    """
    import pinocchio as pin

    body = next(b for b in desc.collision_bodies() if b.name == "grasp_gripper")
    data = configuration.model.createData()
    pin.framesForwardKinematics(configuration.model, data, configuration.q)
    placement = data.oMf[configuration.frame_id(body.link)]
    a, b = placement.act(np.asarray(body.capsule.p0, float)), placement.act(np.asarray(body.capsule.p1, float))
    axis = (b - a) / np.linalg.norm(b - a)
    n = np.cross(axis, [0.0, 0.0, 1.0])
    n /= np.linalg.norm(n)
    u = np.cross(axis, n)
    middle = 0.5 * (a + b)
    centre = middle + n * (body.capsule.radius + GAP + CELL_RADIUS)
    # Neighbours sit further out along n so that the centre sphere is the closest (distance GAP).
    offsets = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    centres = np.array([centre + 0.012 * (i * axis + j * u) + n * 0.002 * (abs(i) + abs(j)) for i, j in offsets])
    return centres, n


def _run(configuration, *, approach_only: bool, push: float, ticks: int = 40):
    """Coal distances [m] of the gripper capsule to the wall over ``ticks`` steps; ``push`` [m/s]
    is the gripper's commanded speed towards the wall (0: hold still)."""
    from benchmarks.bench_fuzz import CoalGeometry

    configuration.update(HOME_Q)
    centres, n = _wall_in_front_of_gripper(configuration)
    collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.01, influence_distance=0.1)
    collision.set_obstacle_spheres(centres, CELL_RADIUS)
    if approach_only:
        collision.set_approach_only(["grasp_gripper", "grasp_wrist_3"])
    geometry = CoalGeometry(configuration, collision)
    geometry.set_obstacles(centres, np.full(len(centres), CELL_RADIUS))
    wall = [("grasp_gripper", f"obstacle_{k}") for k in range(len(centres))]

    def distance(q):
        return min(geometry.pair_distances(q, wall).values())

    grasp, cam = FrameTwistTask("gripper"), FrameTwistTask("camera")
    grasp.set_reference(np.concatenate([push * n, np.zeros(3)]))
    cam.set_reference(np.zeros(6))
    controller = TaskController(
        configuration, [grasp, cam, PostureTask(HOME_Q, weight=1e-4), DampingTask(12, weight=1e-4)], [collision], dt=DT
    )
    q = HOME_Q.copy()
    controller.reset(q)
    distances = [distance(q)]
    for _ in range(ticks):
        step = controller.step(q)
        assert step.ok, step.status
        q = q + step.qdot * DT
        distances.append(distance(q))
    return np.array(distances)


def test_wall_starts_where_it_was_placed(configuration):
    """The hand-computed set-up: coal measures the 4 mm gap (inside d_s) at the start."""
    d = _run(configuration, approach_only=True, push=0.0, ticks=0)
    assert d[0] == pytest.approx(GAP, abs=1e-6)


def test_approach_only_capsule_is_stopped_not_pushed(configuration):
    """A gripper capsule 4 mm from a wall of map cells (inside d_s = 10 mm), through TaskController.

    Oracle: coal distances from pinocchio placements, the start hand-computed. With the option,
    a task driving the gripper into the wall at 5 cm/s leaves the distance where it was (never
    decreasing), and with no task motion the rows alone do not move it away (unchanged). Without
    the option, the same rows push it away (the separation demand the option removes).
    Bugs caught: the clamp left out (the gripper pushed off: the false-success mechanism of
    seed 1); the approach-only rows dropped instead of clamped (the gripper enters the wall).
    """
    into = _run(configuration, approach_only=True, push=0.05)
    assert np.all(np.diff(into) >= -2e-6), f"moved closer: {into.min():.6f} m from {GAP} m"
    still = _run(configuration, approach_only=True, push=0.0)
    assert np.max(np.abs(still - GAP)) < 1e-5, f"the rows alone moved it: {still.min():.6f}-{still.max():.6f} m"
    pushed = _run(configuration, approach_only=False, push=0.0)
    assert pushed[-1] > GAP + 5e-4, "without the option the separation rows push the capsule away"


def test_approach_only_keeps_separation_for_other_pairs(configuration):
    """Only (approach-only capsule, obstacle sphere) rows are clamped.

    The same sphere 4 mm from the gripper capsule, once as an obstacle sphere and once as a
    fixed environment primitive: the obstacle row's bound is 0, the environment row's is the
    hand-computed separation speed ``(d - d_s) / recovery_time`` = -0.3 m/s. Arm-arm pairs
    (the approach-only capsules on both arms) are never flagged. Bug caught: every row of an
    approach-only capsule clamped (environment or arm-arm pairs lose their separation).
    """
    from harvest_qp.limits import CapsuleGeometry

    configuration.update(HOME_Q)
    centres, _ = _wall_in_front_of_gripper(configuration)
    c = tuple(centres[4])  # the closest sphere, GAP from the capsule
    branch = CapsuleGeometry("branch", None, c, c, CELL_RADIUS)
    limit = CollisionAvoidance.dual_ur5e(
        configuration, environment=[branch], safety_distance=0.01, influence_distance=0.1, recovery_time=0.02
    )
    limit.set_obstacle_spheres(centres[4:5], CELL_RADIUS)
    limit.set_approach_only(["grasp_gripper", "cam_cutter"])
    rows = limit.compute(configuration, DT)
    names = limit.pair_names()
    bounds = {}  # the closest-point row of each pair (end-point rows follow it)
    for r, k in enumerate(limit.row_pairs):
        bounds.setdefault(names[k], rows.h[r])
    assert bounds[("grasp_gripper", "obstacle_0")] == 0.0
    assert bounds[("grasp_gripper", "branch")] == pytest.approx((GAP - 0.01) / 0.02, rel=1e-6)
    flagged = sorted(limit.approach_only_pairs)
    assert flagged == [("cam_cutter", "obstacle_0"), ("grasp_gripper", "obstacle_0")]
    assert limit.approach_only_capsules == ["cam_cutter", "grasp_gripper"]
    limit.set_approach_only(())
    rows = limit.compute(configuration, DT)
    first = list(limit.row_pairs).index(names.index(("grasp_gripper", "obstacle_0")))
    assert rows.h[first] == pytest.approx((GAP - 0.01) / 0.02, rel=1e-6)


def test_approach_only_names_are_checked(configuration):
    limit = CollisionAvoidance.dual_ur5e(configuration)
    with pytest.raises(InvalidInputError, match=r"approach-only capsule 'gripperx' is not a moving capsule"):
        limit.set_approach_only(["gripperx"])
