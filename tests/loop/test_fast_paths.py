"""HarvestController's per-tick and per-frame fast paths equal the numpy formulas they replace, bit for bit.

The controller computes its references on Python floats (``_camera_twist``, ``_hold_twist``,
``_roll_reference``, ``_camera_speeds``), splits a cloud the compiled split does not take
through a record view (``_rows``) and lists the active collision pairs column-wise
(``_active_pairs``). Oracles: the reference laws' checked public methods, the numpy
expressions of the previous implementation (written out here), numpy's boolean indexing, and
the collision limit's own ``active_pair_distances``. Exact equality is asserted: the closed
loop's results must not move by a bit (``/work/notes/compare_golden.py``).
"""

from __future__ import annotations

import copy

import numpy as np
import pinocchio as pin
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.interface import OBSTACLE, ROBOT, STEM, PointCloud
from harvest_qp.loop.controller import HarvestController, _wrap_half_turn
from harvest_qp.loop.settings import check_settings
from tests.helpers import assert_as_numpy, random_pose


def _bits(values) -> list[int]:
    """The IEEE bit patterns (so that -0.0 differs from 0.0, and NaN equals itself)."""
    return np.asarray(values, dtype=np.float64).reshape(-1).view(np.int64).tolist()


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def test_camera_twist_equals_the_checked_laws(controller):
    """V_cr + keep-out + V_cu on floats == ``reaching.update + _keep_out + unveiling.update`` (numpy).

    A third of the poses lie inside the keep-out distance (0.9 r from p_r) so that its
    branch runs. Catches: the keep-out distance not equal to |p_r - p_c| of V_cr, the
    filters' arithmetic reordered."""
    c = controller
    rng = np.random.default_rng(11)
    r = c.settings["reaching"]
    keep_out = r["min_distance_factor"] * r["radius"]
    inside = 0
    for i in range(600):
        centre = 0.3 * rng.normal(size=3)
        c.reaching.reset(centre)
        c.reaching.set_roi_centre(centre + 0.05 * rng.normal(size=3))
        c.unveiling.reset()
        c.unveiling.raw = 0.1 * rng.normal(size=6)
        pose = random_pose(rng)
        if i % 3 == 0:
            pose[:3, 3] = centre + rng.uniform(0.1, 0.95) * keep_out * pose[:3, 2]
        reaching, unveiling = copy.deepcopy(c.reaching), copy.deepcopy(c.unveiling)
        got = c._camera_twist(pose, 0.002)
        expected = reaching.update(pose, 0.002) + c._keep_out(pose) + unveiling.update(0.002)
        inside += bool(np.any(c._keep_out(pose)))
        assert _bits(got) == _bits(expected)
        assert c.reaching.distance == float(np.linalg.norm(c.reaching.roi_centre - pose[:3, 3]))
    assert inside > 100


def test_camera_twist_without_unveiling_keeps_the_sign_of_zero(controller):
    """With V_cu off, V_cr + zeros(6) + zeros(6) as before: inside the ROI (between the keep-out
    distance 0.9 r and V_cr's 0.95 r) V_cr's linear part is 0 * e_pc, -0.0 where e_pc < 0,
    which the old sum turned into 0.0. Catches: the ``+ 0.0`` left out (-0.0 handed on)."""
    c = controller
    rng = np.random.default_rng(19)
    c.settings["unveiling"]["enabled"] = False
    try:
        r = c.settings["reaching"]
        for _ in range(50):
            centre = 0.3 * rng.normal(size=3)
            c.reaching.reset(centre)
            pose = random_pose(rng)
            pose[:3, 3] = centre - 0.925 * r["radius"] * pose[:3, 2]  # p_r ahead, at 0.925 r
            reaching = copy.deepcopy(c.reaching)
            got = c._camera_twist(pose, 0.002)
            expected = reaching.update(pose, 0.002) + c._keep_out(pose) + np.zeros(6)
            assert not np.any(expected[:3])
            assert _bits(got) == _bits(expected)
    finally:
        c.settings["unveiling"]["enabled"] = True


def test_hold_twist_equals_the_numpy_formula(controller):
    """``_hold_twist`` (step's approach path) is -k_hold [p_g - p_hold; log3(R_g R_hold^T)], the
    same bits when called again, in a new array each call (its scratch rotation is not handed out).
    Catches: the hold gain's sign, the rotation error taken as R_hold R_g^T, the rotation part
    written into the wrong slots, one array reused between calls."""
    c = controller
    rng = np.random.default_rng(12)
    k = c.settings["grasping"]["k_hold"]
    previous = None
    for _ in range(300):
        hold = pin.SE3(random_pose(rng))
        c.state.hold_translation, c.state.hold_rotation_T = hold.translation, hold.rotation.T
        T_g = random_pose(rng)
        expected = np.zeros(6)
        expected[:3] = -k * (T_g[:3, 3] - hold.translation)
        expected[3:] = -k * pin.log3(T_g[:3, :3] @ hold.rotation.T)
        got = c._hold_twist(T_g)
        assert got.shape == (6,) and got.dtype == np.float64
        assert_as_numpy(got, expected)
        assert got.tobytes() == c._hold_twist(T_g).tobytes()
        assert got is not previous and got.base is None
        previous = got


def _roll_reference_numpy(k_roll: float, T_c: np.ndarray, direction: np.ndarray):
    """The previous implementation (numpy), the oracle."""
    twist = np.zeros(6)
    z, y = T_c[:3, 2], T_c[:3, 1]
    d = direction - (direction @ z) * z
    if np.linalg.norm(d) < 1e-6:
        return twist, float("nan")
    angle = _wrap_half_turn(float(np.arctan2(np.cross(y, d) @ z, y @ d)))
    twist[3:] = k_roll * angle * z
    return twist, angle


def test_roll_reference_equals_the_numpy_formula(controller):
    """Including a direction given as a strided view (the gripper's y axis, as in the loop)
    and one along the optical axis (no roll). Catches: math.atan2 for np.arctan2 (they differ
    in the last bit on ~7 % of arguments), y x d swapped."""
    c = controller
    rng = np.random.default_rng(13)
    k_roll = c.settings["roll"]["k_roll"]
    for i in range(1000):
        T_c = random_pose(rng)
        direction = random_pose(rng)[:3, 1] if i % 2 else rng.normal(size=3)
        twist, angle = c._roll_reference(T_c, direction)
        twist_np, angle_np = _roll_reference_numpy(k_roll, T_c, direction)
        assert _bits(twist) == _bits(twist_np)
        assert _bits(angle) == _bits(angle_np)
    T_c = random_pose(rng)
    twist, angle = c._roll_reference(T_c, T_c[:3, 2].copy())
    assert np.isnan(angle) and not np.any(twist)


def test_camera_speeds_equal_the_numpy_formula(controller):
    """Mean speeds over the window from a deque of poses == the numpy norm/arccos formula, also
    after ticks that only record (``measure=False``). Catches: math.acos for np.arccos, a
    history kept one sample too long or too short, a pose not recorded when not measured."""
    c = controller
    rng = np.random.default_rng(14)
    c.state.camera_history.clear()
    window = c.settings["switch"]["window"]
    poses, times = [], []
    for k in range(600):
        t = 0.002 * (k + 1)
        pose = random_pose(rng, scale=0.01)
        poses.append(pose)
        times.append(t)
        if k % 3 == 0:  # no stem base yet: recorded, not measured
            assert c._camera_speeds(t, pose, measure=False) == (float("inf"), float("inf"))
            continue
        linear, angular = c._camera_speeds(t, pose)
        first = next(j for j, s in enumerate(times) if s > t - window + 1e-12) - 1
        first = max(first, 0)
        if t - times[first] < window - 1e-9:
            assert linear == angular == float("inf")
            continue
        span = t - times[first]
        assert _bits(linear) == _bits(float(np.linalg.norm(pose[:3, 3] - poses[first][:3, 3])) / span)
        z0 = poses[first][:3, 2].copy()
        assert _bits(angular) == _bits(float(np.arccos(np.clip(z0 @ pose[:3, 2], -1.0, 1.0))) / span)


def test_active_pairs_equal_the_limits_own_listing(controller):
    """Catches: distances or names taken from the wrong index column."""
    c = controller
    q = c.configuration.q.copy()
    c.qp.reset(q)
    c.qp.step(q)
    pairs = c._active_pairs()
    assert len(pairs) > 0
    assert pairs == c.collision.active_pair_distances()
    assert all(isinstance(d, float) for _, _, d in pairs)


def test_a_non_finite_cloud_point_still_raises(controller):
    """The cloud is checked once per frame instead of per split: a NaN obstacle point still
    raises the package's error naming the obstacle points (as Unveiling.observe's check did)."""
    c = controller
    c.state = type(c.state)()
    n = 40
    points = np.random.default_rng(16).normal(size=(n, 3))
    # 3 stem points: the predicted (next-best-view) mode, where nothing downstream checks the points.
    labels = np.array([STEM] * 3 + [OBSTACLE] * 27 + [ROBOT] * 10, dtype=np.int8)
    points[15] = np.nan
    cloud = PointCloud(points=points, labels=labels, colors=np.zeros((n, 3), np.uint8), camera_pose=np.eye(4),
                       timestamp=0.1, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(8, 8))
    with pytest.raises(InvalidInputError, match="obstacle_points"):
        c._perceive(cloud, np.eye(4))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_non_finite_observation_time_raises_naming_it(bad):
    """Catches: a NaN robot clock accepted by the fast path (it stayed in the camera-speed
    window for good, so the switch rule averaged over seconds instead of 0.5 s; an audit)."""
    from harvest_qp.robot.description import HOME_Q
    from harvest_qp.runner import Observation

    c = HarvestController(check_settings({}))
    obs = Observation(time=bad, q=np.array(HOME_Q, float), qdot=np.zeros(12), force=np.zeros(3),
                      cloud=None, new_cloud=False)
    with pytest.raises(InvalidInputError, match="observation time"):
        c.step(obs)
