"""CollisionAvoidance: input validation, active pairs reported by name, end-point rows."""

import numpy as np
import pytest

from harvest_qp import InvalidInputError
from harvest_qp.limits import CapsuleGeometry, CollisionAvoidance
from harvest_qp.robot.description import HOME_Q


@pytest.mark.parametrize("bad", ["x", 2.7, 0, -3, None, True, np.nan])
def test_max_pairs_must_be_a_positive_integer(configuration, bad):
    with pytest.raises(InvalidInputError, match=r"max_pairs must be an integer >= 1, got"):
        CollisionAvoidance.dual_ur5e(configuration, max_pairs=bad)


@pytest.mark.parametrize("end", [(np.nan, 0.0, 0.0), (0.0, np.inf, 0.0), (0.0, 0.0), "abc"])
def test_capsule_ends_must_be_three_finite_numbers(configuration, end):
    branch = CapsuleGeometry("branch", None, end, (0.5, 0.5, 1.3), 0.02)
    with pytest.raises(InvalidInputError, match=r"capsule 'branch' p0 must be 3 finite coordinates"):
        CollisionAvoidance.dual_ur5e(configuration, environment=[branch])


def test_obstacle_centres_and_radii_are_checked(configuration):
    limit = CollisionAvoidance.dual_ur5e(configuration)
    with pytest.raises(InvalidInputError, match=r"one per centre \(3\), got shape \(2,\)"):
        limit.set_obstacle_spheres(np.zeros((3, 3)), [0.1, 0.2])
    with pytest.raises(InvalidInputError, match="shape \\(n, 3\\)"):
        limit.set_obstacle_spheres(np.zeros((3, 2)), 0.1)
    with pytest.raises(InvalidInputError, match="radii must be finite and >= 0"):
        limit.set_obstacle_spheres(np.zeros((2, 3)), [0.1, -0.1])
    with pytest.raises(InvalidInputError, match="centers must be finite"):
        limit.set_obstacle_spheres(np.array([[0.0, np.nan, 1.0]]), 0.1)
    with pytest.raises(InvalidInputError, match="radii must be numbers"):
        limit.set_obstacle_spheres(np.zeros((1, 3)), "big")


def test_active_pairs_are_reported_by_name_with_coal_distances(configuration, rng):
    """The names and distances the episode log records match pinocchio + coal.

    Bug caught: a name or distance misreported for the rows (e.g. the pair order swapped).
    """
    from benchmarks.bench_fuzz import CoalGeometry

    limit = CollisionAvoidance.dual_ur5e(configuration, influence_distance=0.25, max_pairs=30)
    centres = rng.uniform([0.3, -0.3, 0.9], [0.7, 0.6, 1.3], (6, 3))
    limit.set_obstacle_spheres(centres, 0.03)
    geometry = CoalGeometry(configuration, limit)
    geometry.set_obstacles(centres, np.full(6, 0.03))
    seen = 0
    for _ in range(5):
        q = np.clip(HOME_Q + rng.normal(0, 0.3, 12), configuration.lower_limits, configuration.upper_limits)
        configuration.update(q)
        limit.compute(configuration, 0.002)
        reported = limit.active_pair_distances()
        truth = geometry.pair_distances(q)
        for a, b, d in reported:
            assert d == pytest.approx(truth[(a, b)], abs=1e-9), (a, b)
        # ... and they are the closest pairs within d_i.
        within = sorted(v for v in truth.values() if v < limit.influence_distance)[: limit.max_pairs]
        assert sorted(d for _, _, d in reported) == pytest.approx(within, abs=1e-9)
        seen += len(reported)
    assert seen > 20


def _parallel_branch(configuration, body="cam_forearm", joint=2, gap=0.03):
    """A world capsule parallel to ``body``'s capsule, ``gap`` [m] from its surface, on the side
    towards which ``joint`` turns the capsule's end p1 (the elbow joint barely moves end p0)."""
    limit = CollisionAvoidance.dual_ur5e(configuration)
    q = configuration.q.copy()
    i = limit.capsule_names.index(body)
    p0, p1 = limit.capsule_segments(configuration)
    w0, w1, r = p0[i], p1[i], limit.cap_radius[i]
    dq = np.zeros(12)
    dq[joint] = 1e-5
    configuration.update(q + dq)
    p0, p1 = limit.capsule_segments(configuration)
    v0, v1 = p0[i] - w0, p1[i] - w1
    configuration.update(q)
    assert np.linalg.norm(v0) < 0.1 * np.linalg.norm(v1), "p0 must be the end the joint barely moves"
    axis = (w1 - w0) / np.linalg.norm(w1 - w0)
    side = v1 - axis * (v1 @ axis)
    side /= np.linalg.norm(side)
    off = side * (r + 0.02 + gap)
    return CapsuleGeometry("branch", None, tuple(w0 + off), tuple(w1 + off), 0.02), axis, side


def test_parallel_links_get_a_row_at_each_end(configuration):
    """Two exactly parallel capsules: the closest-point row sits at one end, so a rotation about it
    that swings the other end in satisfies that row; the end-point row forbids it.

    Oracle: for a joint velocity that turns the far end towards the branch, the end-point distance
    (numpy, from the capsule's world end points) shrinks faster than the damper allows.
    Bug caught: one damper row per pair on a non-smooth (minimum-of-pieces) distance.
    """
    branch, axis, side = _parallel_branch(configuration)
    limit = CollisionAvoidance.dual_ur5e(configuration, environment=[branch], influence_distance=0.1)
    rows = limit.compute(configuration, 0.002)
    names = limit.pair_names()
    branch_rows = [r for r, k in enumerate(limit.row_pairs) if names[k] == ("cam_forearm", "branch")]
    assert len(branch_rows) == 2, "the parallel pair needs a row at each end"
    # A rotation of the forearm about the closest-point witness towards the branch: try joints.
    H = 1e-6
    i = limit.capsule_names.index("cam_forearm")
    q = configuration.q.copy()
    caught = 0
    for j in range(6):
        qdot = np.zeros(12)
        qdot[j] = 1.0
        G = rows.G[branch_rows]
        configuration.update(q + H * qdot)
        ends = np.array([end[i] for end in limit.capsule_segments(configuration)])
        configuration.update(q)
        ends0 = np.array([end[i] for end in limit.capsule_segments(configuration)])
        rate = -(ends - ends0) @ side / H  # d/dt of each end's distance to the branch
        main_only = G[0] @ qdot  # what the closest-point row alone sees (-d_dot)
        if rate.min() < -0.05 and abs(main_only) < 1e-3:
            caught += 1
            # The end-point row sees the approach of the other end.
            assert G[1] @ qdot == pytest.approx(-rate.min(), rel=1e-3)
    assert caught >= 1, "some joint must turn the far end in while the witness end stays"
