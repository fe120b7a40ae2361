"""The grasp target p_gd never leaves the swing bound and never lies above the stem base (issue 20, class "target").

Oracle: plain geometry, computed here: the angle between p_gd - p_sb and the stem now (p_sb ->
top of the crop), and p_gd's height against p_sb's. Scenes of our own: obstacle points cover
the sphere S(p_sb, l) around the hanging stem, so F has free samples only far outside the cone
(the held-out failures: no clear sample in the cone, and fallbacks then picked targets 55-167 deg
off the stem, once 7 cm above p_sb).
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.configuration import Configuration
from harvest_qp.perception import compute_free_space
from harvest_qp.perception.grasp_target import (
    CHOICE_ALONG_STEM,
    CHOICE_NO_TARGET,
    SwingCheck,
    arm_capsule_motion,
    choose_grasp_target,
)
from harvest_qp.perception.obstacle_map import ObstacleMap
from harvest_qp.runtime.interface import OBSTACLE, PointCloud

L = 0.08  # [m] stem length
P_SB = np.array([0.4, -0.1, 1.2])


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _cap_obstacles(axis: np.ndarray, half_angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Points of S(p_sb, l) within ``half_angle_deg`` of ``axis`` (dense: every sample there is occupied)."""
    d = rng.normal(size=(6000, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return P_SB + L * d[d @ axis > np.cos(np.radians(half_angle_deg))]


def _map_of(cells: np.ndarray, camera: np.ndarray, obstacle_map: ObstacleMap, *, updates: int = 1) -> ObstacleMap:
    """``obstacle_map`` after ``updates`` clouds of ``cells`` (obstacle points) seen from ``camera`` [m],
    the optical axis towards their mean."""
    cells = np.asarray(cells, float)
    z = _unit(cells.mean(axis=0) - camera)
    x = _unit(np.cross(z, [0.0, 0.0, 1.0]))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = np.column_stack([x, np.cross(z, x), z]), camera
    n = len(cells)
    side = int(np.ceil(np.sqrt(n)))
    rows, cols = np.divmod(np.arange(n), side)
    cloud = PointCloud(cells, np.full(n, OBSTACLE, np.int8), np.zeros((n, 3), np.uint8), pose, 0.0,
                       (cells - camera) @ z, np.column_stack([rows, cols]).astype(np.int32), (side, side))
    for _ in range(updates):
        obstacle_map.update(cloud)
    return obstacle_map


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(_unit(a) @ _unit(b), -1.0, 1.0))))


def test_nothing_free_in_the_cone_pulls_along_the_stem():
    """Catches: a fallback that takes the free sample nearest to the cone (here >= 50 deg off the
    stem: the crop is then swung up beside the branch). Planted back once (the earlier tier
    "nothing free in the cone: the free sample nearest to it"): the angle was 52 deg."""
    hanging = np.array([0.0, 0.0, -1.0])
    free = compute_free_space(_cap_obstacles(hanging, 50.0, np.random.default_rng(0)), P_SB, L,
                              P_SB + [0.35, 0.0, -0.05], n_samples=500)
    assert free.valid and not np.any(free.free & ((free.samples - P_SB) @ hanging > L * np.cos(np.radians(45))))
    target = choose_grasp_target(free, P_SB, P_SB + L * hanging, max_swing_deg=30.0)
    assert target.choice == CHOICE_ALONG_STEM
    assert _angle_deg(target.point - P_SB, hanging) < 1e-6
    assert np.linalg.norm(target.point - P_SB) == pytest.approx(L)


@pytest.mark.parametrize("seed", range(12))
def test_target_within_the_swing_bound_and_below_the_stem_base(seed):
    """Random stems (tilted up to 80 deg from the vertical), obstacles and bounds, with and without a
    map whose cells block part of the sphere: p_gd is within ``max_swing_deg`` of the stem now and
    below p_sb, or there is none and the choice says why. Catches the earlier fallbacks "least swing
    outside the cone" and "most clearance" (anywhere on the sphere, once above p_sb)."""
    rng = np.random.default_rng(seed)
    tilt = np.radians(rng.uniform(0.0, 80.0))
    heading = rng.uniform(0.0, 2 * np.pi)
    hanging = np.array([np.sin(tilt) * np.cos(heading), np.sin(tilt) * np.sin(heading), -np.cos(tilt)])
    max_swing = float(rng.uniform(10.0, 45.0))
    free = None
    while free is None or not free.valid:  # a draw whose F has a free sample (most do)
        blocked = _unit(hanging + rng.normal(scale=0.5, size=3))
        obstacles = _cap_obstacles(blocked, float(rng.uniform(20.0, 70.0)), rng)
        camera = P_SB + 0.35 * _unit(rng.normal(size=3))
        free = compute_free_space(obstacles, P_SB, L, camera, n_samples=500)
    top = P_SB + L * hanging
    swing = None
    if seed % 2:
        grid = _map_of(obstacles[rng.random(len(obstacles)) < 0.3], camera, ObstacleMap(resolution=0.01), updates=3)
        gripper = top + 0.015 * _unit(top - P_SB)
        capsules = [(gripper, gripper + 0.1 * _unit(rng.normal(size=3)), 0.04)]
        swing = SwingCheck(grid, gripper, capsules, clearance=0.02, stretch=0.03, map_bias=0.01)
    target = choose_grasp_target(free, P_SB, top, max_swing_deg=max_swing, swing=swing)
    assert target.point is not None, target.choice
    assert _angle_deg(target.point - P_SB, hanging) <= max_swing + 1e-6, target.choice
    assert target.point[2] < P_SB[2], target.choice


@pytest.mark.parametrize("seed", range(6))
def test_the_target_equals_the_rule_applied_to_every_samples_swing(seed):
    """The swing is checked for the candidates only (free, in the cone, below p_sb): the chosen p_gd
    and the candidates' clearances equal a brute-force reference that checks every sample's swing
    (SwingCheck.clearances on all 500) and applies the documented rule 1 in the test (the most
    projected clearance among the clear candidates; the stem's direction when none is clear)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(100 + seed)
    hanging = _unit([rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), -1.0])
    max_swing = float(rng.uniform(25.0, 45.0))
    free, cone = None, np.cos(np.radians(max_swing))
    while free is None or not np.any(free.free & ((free.samples - P_SB) @ hanging >= L * cone)):
        blocked = _unit(hanging + rng.normal(scale=0.5, size=3))  # a draw with free samples in the cone
        obstacles = _cap_obstacles(blocked, float(rng.uniform(10.0, 25.0)), rng)
        camera = P_SB + 0.35 * _unit([1.0, rng.uniform(-0.3, 0.3), -0.2])
        free = compute_free_space(obstacles, P_SB, L, camera, n_samples=500)
    top = P_SB + L * hanging
    grid = _map_of(obstacles[rng.random(len(obstacles)) < 0.3], camera, ObstacleMap(resolution=0.01), updates=3)
    gripper = top + 0.015 * hanging
    swing = SwingCheck(grid, gripper, [(gripper, gripper + 0.1 * _unit(rng.normal(size=3)), 0.02)],
                       clearance=0.01, stretch=0.03, map_bias=0.005)
    target = choose_grasp_target(free, P_SB, top, max_swing_deg=max_swing, swing=swing)

    directions = (free.samples - P_SB) / np.linalg.norm(free.samples - P_SB, axis=1)[:, None]
    candidates = free.free & (directions @ hanging >= np.cos(np.radians(max_swing))) & (directions[:, 2] < 0)
    every = swing.clearances(free.samples, P_SB, hanging)
    now = swing.clearances(top[None], P_SB, hanging, fractions=(0.0,), stretches=(0.0,))[0]
    clear = candidates & np.all(every >= np.minimum(swing.needed, now) - 1e-9, axis=1)
    assert 0 < candidates.sum() < len(free.samples) / 2  # the candidates are a small part of the sphere
    np.testing.assert_allclose(target.swing_clearance[0][candidates], every[candidates], atol=1e-12)
    assert np.all(np.isnan(target.swing_clearance[0][~candidates]))
    if not clear.any():
        np.testing.assert_allclose(target.point, P_SB + L * hanging, atol=1e-12)
    else:
        projected, _ = cKDTree(free.projected_obstacles).query(free.samples[clear])
        np.testing.assert_allclose(target.point, free.samples[clear][np.argmax(projected)], atol=1e-12)


def test_a_crop_level_with_the_stem_base_gets_no_target():
    """A crop beside or above p_sb (a wrong p_sb, or a crop flipped up): no target, so the episode
    does not switch, instead of a stretch where compression reads as stretch along n_c."""
    hanging = _unit([1.0, 0.0, 0.05])
    free = compute_free_space(np.empty((0, 3)), P_SB, L, P_SB + [0.0, 0.35, 0.0], n_samples=200)
    target = choose_grasp_target(free, P_SB, P_SB + L * hanging, max_swing_deg=30.0)
    assert target.point is None and target.choice == CHOICE_NO_TARGET


def test_arm_capsule_motion_matches_the_arm_moved_by_its_joints():
    """The first-order motion of the forearm and wrist 1 per gripper twist (the swing check's model
    of the arm, ``J_end J_g^+``) against the arm moved by pinocchio: a small gripper displacement
    solved for the joints by Newton steps on the gripper pose, the points then placed by forward
    kinematics. Catches a motion built from the wrong arm's joints or the gripper's Jacobian in the
    local frame (both planted once: errors of several mm per cm)."""
    config = Configuration.dual_ur5e()
    joints = config.support_mask("gripper")
    J_g = config.frame_jacobian("gripper")[:, joints]
    frames = ("grasp_forearm_link", "grasp_wrist_1_link")
    offsets = {f: np.array([0.05, 0.02, 0.1]) for f in frames}
    points = {f: config.frame_pose(f).act(offsets[f]) for f in frames}
    motions = {f: arm_capsule_motion(config.point_jacobian(f, points[f])[:, joints], J_g) for f in frames}
    twist = np.array([0.004, -0.003, 0.005, 0.02, -0.015, 0.01])  # [m; rad]
    start = config.frame_pose("gripper")
    goal_p = start.translation + twist[:3]
    angle = np.linalg.norm(twist[3:])
    k = twist[3:] / angle
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    goal_R = (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K) @ start.rotation
    q = config.q.copy()
    for _ in range(20):  # Newton on the gripper pose (world-aligned error)
        config.update(q)
        pose = config.frame_pose("gripper")
        R_err = goal_R @ pose.rotation.T
        w = 0.5 * np.array([R_err[2, 1] - R_err[1, 2], R_err[0, 2] - R_err[2, 0], R_err[1, 0] - R_err[0, 1]])
        error = np.concatenate([goal_p - pose.translation, w])
        dq = np.zeros(config.nv)
        dq[joints] = np.linalg.solve(config.frame_jacobian("gripper")[:, joints], error)
        q = q + dq
    config.update(q)
    for f in frames:
        moved = config.frame_pose(f).act(offsets[f]) - points[f]
        predicted = motions[f] @ twist
        # second-order terms of a 7 mm / 1.5 deg motion: well under a millimetre
        assert np.linalg.norm(moved - predicted) < 5e-4, (f, moved, predicted)
        assert np.linalg.norm(moved) > 2e-3  # the point does move (the check is not vacuous)


def test_an_arm_capsule_already_near_a_cell_does_not_switch_the_swing_check_off_for_the_gripper():
    """One candidate 25 deg off the hanging stem; a map cell 12 mm beside where the gripper ends its
    swing (hand value: 2 mm of surface clearance for the 10 mm gripper capsule, below the 30 mm
    asked), and a second cell that a distant, motionless arm capsule already overlaps by ~21 mm.

    Bug caught (found by an independent review): the clearance "now" relaxed the requirement for
    the whole arm at once (``min(needed, least clearance now over all capsules)``), so the far
    cell lowered what the gripper had to keep to -21 mm and the swing into the leaf was accepted.
    Planted back once: the choice was "free, in the cone, swing clear" instead of along the stem.
    """
    from harvest_qp.perception.free_space import FreeSpace
    from harvest_qp.perception.grasp_target import CHOICE_CONE_CLEAR, ArmCapsule

    centre, length = np.array([0.0, 0.0, 1.0]), 0.05
    hanging = np.array([0.0, 0.0, -1.0])
    p_g = centre + length * hanging
    a = np.radians(25.0)
    candidate = centre + length * np.array([np.sin(a), 0.0, -np.cos(a)])
    free = FreeSpace(valid=True, reason="", centre=centre, radius=length, samples=candidate[None],
                     occupied=np.zeros(1, bool), behind_plane=np.zeros(1, bool),
                     projected_obstacles=np.zeros((0, 3)), plane=None, target=candidate, target_clearance=np.inf)
    leaf = candidate + [0.012, 0.0, 0.0]
    far = np.array([0.5, 0.0, 1.0])
    gripper = [(p_g, p_g + np.array([0.0, 0.0, -0.02]), 0.01)]
    still_arm = [ArmCapsule(p0=far - [0, 0, 0.05], p1=far + [0, 0, 0.05], radius=0.02,
                            motion0=np.zeros((3, 6)), motion1=np.zeros((3, 6)))]
    chosen = {}
    for name, cells in (("clear", []), ("leaf", [leaf]), ("leaf and far cell", [leaf, far])):
        cell_map = _map_of(cells or [[0.9, 0.9, 1.9]], np.array([0.0, -1.0, 1.0]),
                           ObstacleMap(resolution=0.005, bounds=((-1, -1.5, 0), (1, 1, 2))))
        swing = SwingCheck(obstacle_map=cell_map, gripper_position=p_g,
                           capsules=gripper, clearance=0.02, arm=still_arm, map_bias=0.01)
        chosen[name] = choose_grasp_target(free, centre, centre + 0.03 * hanging, max_swing_deg=30.0,
                                           swing=swing).choice
    assert chosen == {"clear": CHOICE_CONE_CLEAR, "leaf": CHOICE_ALONG_STEM, "leaf and far cell": CHOICE_ALONG_STEM}


@pytest.mark.parametrize("bad, match", [
    (dict(top_of_crop=P_SB), "top_of_crop must differ"),
    (dict(top_of_crop=[np.nan, 0.0, 1.0]), "top_of_crop"),
    (dict(stem_base=[0.4, np.inf, 1.2]), "stem_base"),
    (dict(max_swing_deg=-60.0), "max_swing_deg"),
    (dict(max_swing_deg=300.0), "max_swing_deg"),
    (dict(max_swing_deg=float("nan")), "max_swing_deg"),
])
def test_bad_input_gets_the_package_error_naming_it(bad, match):
    """A stem of no length, a non-finite point or a swing bound outside (0, 180] deg: the package's
    InvalidInputError naming the value (before: a NaN target, or -60/300 deg read as a 60 deg cone)."""
    from harvest_qp.exceptions import InvalidInputError

    free = compute_free_space(np.zeros((0, 3)), P_SB, L, P_SB + [0.35, 0.0, -0.05], n_samples=100)
    args = dict(stem_base=P_SB, top_of_crop=P_SB + [0.0, 0.0, -L], max_swing_deg=30.0) | bad
    with pytest.raises(InvalidInputError, match=match):
        choose_grasp_target(free, args.pop("stem_base"), args.pop("top_of_crop"), **args)


def _tilted_stem_free_on_the_far_side_only():
    """A stem 60 deg off the vertical (towards +x); obstacle points fill the +x side of S(p_sb, l), so
    the free samples lie on the far side, most of them 90 deg or more off the stem now (an independent
    review's scene)."""
    hanging = np.array([np.sin(np.radians(60.0)), 0.0, -np.cos(np.radians(60.0))])
    obstacles = P_SB + np.array([[0.05, y, z] for y in np.linspace(-0.05, 0.05, 15)
                                 for z in np.linspace(-0.08, 0.02, 15)])
    free = compute_free_space(obstacles, P_SB, L, P_SB + [-0.3, 0.0, 0.1], n_samples=500)
    top = P_SB + L * hanging
    swing = SwingCheck(ObstacleMap(resolution=0.01), top.copy(), [(top + [0, 0, 0.01], top + [0, 0, 0.05], 0.01)],
                       clearance=0.02)
    return hanging, free, top, swing


def test_without_a_bound_the_map_aware_target_keeps_the_crop_on_its_side_of_the_stem_base():
    """``max_swing_deg=None`` with the map's swing check: p_gd less than 90 deg off the stem now, so the
    crop where it hangs now lies ahead of p_sb along n_c = (p_gd - p_sb)/|...| (oracle: that
    projection, computed here). Catches the unbounded cone (planted: ``cos_swing >= -1``): p_gd was
    149.7 deg off the stem, the crop 69 mm behind p_sb along n_c, where compression reads as stretch."""
    hanging, free, top, swing = _tilted_stem_free_on_the_far_side_only()
    assert np.any(free.free & ((free.samples - P_SB) @ hanging < 0.0))  # free samples behind exist
    target = choose_grasp_target(free, P_SB, top, max_swing_deg=None, swing=swing)
    assert target.point is not None, target.choice
    n_c = _unit(target.point - P_SB)
    assert (top - P_SB) @ n_c > 0.0, (target.choice, _angle_deg(n_c, hanging))
    assert _angle_deg(n_c, hanging) < 90.0 and target.point[2] < P_SB[2]


@pytest.mark.parametrize("bound", [90.0, 150.0, 200.0])
def test_a_swing_bound_of_90_deg_or_more_is_refused(bound):
    """A bound that admits the crop's wrong side is an input error naming the value (the settings
    refuse it too, before a run: a 200 deg bound once passed check-config and stopped the episode at
    its switch with a controller error)."""
    from harvest_qp import ConfigError, InvalidInputError
    from harvest_qp.config.settings import check_settings

    _, free, top, _ = _tilted_stem_free_on_the_far_side_only()
    with pytest.raises(InvalidInputError, match=rf"max_swing_deg must be in \(0, 90\).*got {bound}"):
        choose_grasp_target(free, P_SB, top, max_swing_deg=bound)
    with pytest.raises(ConfigError, match=r"grasping.max_swing_deg.*an angle in \(0, 90\)"):
        check_settings({"grasping": {"max_swing_deg": bound}})


def test_the_papers_choice_with_no_free_sample_is_no_target():
    """The paper's rule (no bound, no map check) on an F with no free sample: no target and the
    choice says why (it raised AttributeError on ``None.copy()``)."""
    from harvest_qp.perception.grasp_target import CHOICE_NO_FREE

    free = compute_free_space(P_SB + [[0.0, 0.0, -L]], P_SB, L, P_SB + [0.3, 0.0, 0.0], n_samples=1)
    assert not free.valid and free.target is None
    target = choose_grasp_target(free, P_SB, P_SB + [0.0, 0.0, -L], max_swing_deg=None)
    assert target.point is None and target.choice == CHOICE_NO_FREE


@pytest.mark.parametrize("change, match", [
    ({"capsules": []}, r"SwingCheck.capsules must be a non-empty list"),
    ({"clearance": -1.0}, r"SwingCheck.clearance \[m\] must be finite and >= 0, got -1.0"),
    ({"gripper_position": [np.nan, 0.0, 1.0]}, r"SwingCheck.gripper_position must be finite"),
    ({"capsules": [(P_SB, P_SB, -0.01)]}, r"SwingCheck.capsules\[0\] radius must be finite and >= 0, got -0.01"),
    ({"obstacle_map": None}, r"SwingCheck.obstacle_map must be an ObstacleMap, got NoneType"),
    ({"arm": None}, r"SwingCheck.arm must be a list of ArmCapsule, got NoneType"),
    ({"arm": (c for c in ())}, r"SwingCheck.arm must be a list of ArmCapsule, got generator"),
])
def test_a_swing_check_built_from_bad_input_says_which(change, match):
    from harvest_qp import InvalidInputError

    kwargs = {"obstacle_map": ObstacleMap(resolution=0.01), "gripper_position": P_SB - [0.0, 0.0, L],
              "capsules": [(P_SB, P_SB + [0.0, 0.0, 0.05], 0.01)], "clearance": 0.02, **change}
    with pytest.raises(InvalidInputError, match=match):
        SwingCheck(**kwargs)
