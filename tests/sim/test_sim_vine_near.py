"""The vine-distance near list (``_vine_near_search``) against every pair measured, along trajectories."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

import harvest_qp.sim.contacts as contacts_module
from harvest_qp.sim import SimRobot, VineSceneParams


def _every_pair(robot: SimRobot):
    """Brute force at the current state: (best, pair index, bounded candidates nearest first, their bounds).

    Every arm-vine pair's enclosing-capsule distance (``_segment_distances`` minus the radii,
    numpy for the segment ends), the first minimum over the exact pairs in pair order, and
    the bounded pairs below it ordered by (bound, index).
    """
    cm, d = robot._contacts, robot.data
    arm_axis, arm_half, _, _ = cm._arm_caps
    vine_axis, vine_half, _, _ = cm._vine_caps

    def ends(geoms, axis, half):
        off = np.array([half[i] * d.geom_xmat[g].reshape(3, 3)[:, axis[i]] for i, g in enumerate(geoms)])
        return d.geom_xpos[geoms] - off, d.geom_xpos[geoms] + off

    pa, qa = ends(cm.arm_geoms, arm_axis, arm_half)
    pv, qv = ends(cm.vine_geoms, vine_axis, vine_half)
    flat = (contacts_module._segment_distances(pa, qa, pv, qv) - cm._radius_sum).ravel()
    exact = flat[cm._exact_pairs]
    if exact.min() < cm.max_distance:
        best, k = float(exact.min()), int(cm._exact_pairs[np.argmax(exact == exact.min())])
    else:
        best, k = cm.max_distance, -1
    bounds = flat[cm._bounded_pairs]
    order = sorted((float(bounds[j]), j) for j in range(bounds.size) if bounds[j] < best)
    return best, k, [j for _, j in order], [b for b, _ in order]


@pytest.mark.parametrize("seed", [0, 5])
def test_near_list_equals_every_pair_along_random_walks(seed):
    """Bug caught: a near list that misses the nearest pair or a candidate after the geoms moved.

    Oracle: every pair measured at every state (:func:`_every_pair`), compared exactly: the
    distance, the winning pair (first in pair order on a tie), the candidates, their order
    and bounds. The arms walk at random (slow and fast legs, so baselines are both kept for
    many calls and retaken), with the previous answer as the hint as in an episode; then a
    leaf is moved through the model (the vine is not assumed static). Most calls must reuse
    a baseline, else the near list itself would go untested.
    """
    robot = SimRobot(None if seed == 0 else VineSceneParams.sample(seed), camera=None)
    m, d, cm = robot.model, robot.data, robot._contacts
    na, nv = cm._sizes
    rng = np.random.default_rng(seed + 3)
    q = robot.scene.home_q.copy()
    hint, reused, calls = -1, 0, 0

    def check():
        nonlocal hint, reused, calls
        mujoco.mj_kinematics(m, d)
        reused += int(cm._near_ints[0])
        calls += 1
        best, k, n, arm, vine, candidate_arm, candidate_vine = contacts_module._vine_near_search(
            d.geom_xpos, d.geom_xmat, cm._near_ints, cm._near_floats, na, nv, cm.max_distance, hint,
        )  # fmt: skip
        want = _every_pair(robot)
        got_candidates = cm._candidates[:n].tolist()
        assert (best, k, got_candidates, cm._lower[got_candidates].tolist()) == want
        # The geoms of the best pair and of the nearest candidate, by pair index.
        assert (arm, vine) == ((cm.arm_geoms[k // nv], cm.vine_geoms[k % nv]) if k >= 0 else (-1, -1))
        first = cm._bounded_pairs[got_candidates[0]] if n else -1
        assert (candidate_arm, candidate_vine) == (
            (cm.arm_geoms[first // nv], cm.vine_geoms[first % nv]) if n else (-1, -1)
        )
        hint = k

    for leg in range(6):
        velocity = rng.normal(0.0, 0.4, 12)
        for _ in range(60):
            q = q + velocity * 0.002 * (1.0 if leg % 2 else 8.0)
            d.qpos[robot._qpos_ids] = q
            check()
    # A leaf (a vine geom) moves towards the grasp gripper while the arms hold still.
    leaf = next(g for g in cm.vine_geoms if m.geom(g).name.startswith("leaf"))
    gripper = next(g for g in cm.arm_geoms if m.geom(g).name == "grasp_gripper")
    toward = d.geom_xpos[gripper] - d.geom_xpos[leaf]
    body_rotation = d.xmat[m.geom_bodyid[leaf]].reshape(3, 3)
    for _ in range(40):
        m.geom_pos[leaf] += body_rotation.T @ (0.02 * toward)
        check()
    assert reused > 0.8 * calls



def test_near_list_follows_a_capsule_turning_about_one_end():
    """Bug caught: a geom's move measured at one end of its segment only (a turn about that end
    then looks like no move, and the pair keeps its stale bound).

    Oracle: every pair measured (:func:`_every_pair`). The arm capsule of the nearest exact
    pair turns about its first segment end towards its vine capsule, written straight into
    the data's geom poses (the search reads nothing else).
    """
    robot = SimRobot(None, camera=None)
    d, cm = robot.data, robot._contacts
    na, nv = cm._sizes
    best, k, _, _ = _every_pair(robot)
    assert k >= 0
    i, m = k // nv, k % nv
    g, vine = int(cm.arm_geoms[i]), int(cm.vine_geoms[m])
    axis, half = int(cm._arm_caps[0][i]), float(cm._arm_caps[1][i])
    rotation = d.geom_xmat[g].reshape(3, 3).copy()
    end0 = d.geom_xpos[g] - half * rotation[:, axis]
    hint = -1
    for step in range(30):
        if step:
            # Turn the segment about end0 by 0.02 rad towards the vine capsule's centre.
            direction = rotation[:, axis]
            target = d.geom_xpos[vine] - end0
            normal = np.cross(direction, target)
            normal /= np.linalg.norm(normal)
            turn = np.zeros(9)
            mujoco.mju_axisAngle2Quat(quat := np.zeros(4), normal, 0.02)
            mujoco.mju_quat2Mat(turn, quat)
            rotation = turn.reshape(3, 3) @ rotation
            d.geom_xmat[g] = rotation.ravel()
            d.geom_xpos[g] = end0 + half * rotation[:, axis]
        got = contacts_module._vine_near_search(
            d.geom_xpos, d.geom_xmat, cm._near_ints, cm._near_floats, na, nv, cm.max_distance, hint,
        )  # fmt: skip
        want = _every_pair(robot)
        assert (got[0], got[1], cm._candidates[: got[2]].tolist()) == want[:3], step
        hint = got[1]
    assert _every_pair(robot)[0] < best  # it did come nearer


def test_ncon_view_reads_the_contact_count():
    """Bug caught: a view of the wrong int of MuJoCo's data struct (ne, nefc, nisland: they
    follow ncon in some states and not in others), or one that does not follow the data.

    Oracle: ``data.ncon`` through the bindings, over a robot pushed into the vine and its
    stand and released (contacts come and go), and the robot's contact counts.
    """
    robot = SimRobot(None, camera=None)
    m, d = robot.model, robot.data
    view = robot._ncon_view
    assert view is not None
    rng = np.random.default_rng(2)
    seen = set()
    for _ in range(200):
        d.qpos[robot._qpos_ids] = robot.scene.home_q + rng.normal(0, 0.6, 12)
        mujoco.mj_forward(m, d)
        assert view[0] == d.ncon
        seen.add(int(d.ncon))
        truth = robot.ground_truth()
        want = robot._contacts.contact_counts(d)
        assert [truth[f"contacts_{k}"] for k in want] == [float(v) for v in want.values()]
    assert len(seen) > 3  # contacts came and went
