"""The map-aware p_gd: the gripper's swing to p_gd keeps clear of what the obstacle map holds.

No episode: the arms at their initial pose, a free space computed by the perception
pipeline, and a leaf inserted in an obstacle map from a synthetic cloud; p_gd from
:func:`harvest_qp.perception.grasp_target.choose_grasp_target` with the settings' bounds. The
oracle is the control law's own end state, computed here independently of the swing model:
with e_p = 0 and alignment = 0 (``eq:gr_pos_contr``, ``eq:rot_contr``) the
gripper point lies on the line p_sb + s n_c (s from the stem's length to 3 cm beyond) and
y_g = n_c, reached by the shortest turn of the gripper; its capsule (from the robot
description, placed with pinocchio) is measured against the leaf's points by brute force.
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.config.settings import check_settings
from harvest_qp.configuration import Configuration
from harvest_qp.perception import compute_free_space
from harvest_qp.perception.grasp_target import SWING_CAPSULES, SwingCheck, choose_grasp_target
from harvest_qp.perception.obstacle_map import ObstacleMap
from harvest_qp.robot import description
from harvest_qp.runtime.interface import OBSTACLE, PointCloud

STEM_LENGTH = 0.08  # [m]


def _segment_point_distance(a: np.ndarray, b: np.ndarray, points: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def _shortest_turn(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    axis = np.cross(u, v)
    s, c = np.linalg.norm(axis), float(u @ v)
    if s < 1e-12:
        return np.eye(3)
    k = axis / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * K @ K


class _Scene:
    """The arms at their initial pose, the stem hanging along y_g, the camera to one side."""

    def __init__(self, swing_clearance):
        self.settings = settings = check_settings({"grasping": {"swing_clearance": swing_clearance}})
        self.configuration = Configuration.dual_ur5e()
        m = settings.obstacle_map
        self.obstacle_map = ObstacleMap(resolution=m.resolution, clear_rays=m.clear_rays)
        self.T_g = T_g = _pose(self, "gripper")
        self.p_g, self.R_g = T_g[:3, 3], T_g[:3, :3]
        self.top = self.p_g - settings.perception.grasp_offset * self.R_g[:, 1]
        self.p_sb = self.top - STEM_LENGTH * self.R_g[:, 1]
        # camera 0.35 m away across the stem (along the gripper's approach axis, backwards);
        # a wall of obstacle points behind the stem keeps F on the camera's side.
        side = -self.R_g[:, 2]
        self.camera = self.p_sb + 0.35 * side
        u, w = self.R_g[:, 0], self.R_g[:, 1]
        grid = np.linspace(-0.05, 0.05, 11)
        wall = self.p_sb - 0.04 * side + grid[:, None, None] * u + grid[None, :, None] * w
        self.free = compute_free_space(wall.reshape(-1, 3), self.p_sb, STEM_LENGTH, self.camera, n_samples=500)

    def choice(self):
        g = self.settings.grasping
        swing = None
        if g.swing_clearance is not None:
            capsules = []
            for body in description.collision_bodies():
                if body.arm and body.name in SWING_CAPSULES:
                    pose = self.configuration.frame_pose(body.link)
                    ends = [pose.act(np.asarray(p, float)) for p in (body.capsule.p0, body.capsule.p1)]
                    capsules.append((*ends, float(body.capsule.radius)))
            swing = SwingCheck(self.obstacle_map, self.p_g, capsules, clearance=g.swing_clearance,
                               stretch=g.swing_stretch)
        return choose_grasp_target(self.free, self.p_sb, self.top, max_swing_deg=g.max_swing_deg, swing=swing)

    def target(self) -> np.ndarray:
        return self.choice().point

    def capsules_at_end(self, target: np.ndarray, stretch: float) -> list[tuple[np.ndarray, np.ndarray, float]]:
        """The gripper-side capsules when the law has converged on ``target`` (see the module docstring)."""
        n_c = (target - self.p_sb) / np.linalg.norm(target - self.p_sb)
        turn = _shortest_turn(self.R_g[:, 1], n_c)
        reach = np.linalg.norm(self.p_g - self.p_sb) + stretch
        p_end = self.p_sb + reach * n_c
        out = []
        for body in description.collision_bodies():
            if body.name not in ("grasp_gripper", "grasp_wrist_3"):
                continue
            pose = self.configuration.frame_pose(body.link)
            ends = [pose.act(np.asarray(p, float)) for p in (body.capsule.p0, body.capsule.p1)]
            out.append(tuple(p_end + turn @ (e - self.p_g) for e in ends) + (body.capsule.radius,))
        return out


def _pose(scene, frame: str) -> np.ndarray:
    pose = scene.configuration.frame_pose(frame)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = pose.rotation, pose.translation
    return T


def _leaf_cloud(points: np.ndarray, camera: np.ndarray) -> PointCloud:
    z = points.mean(axis=0) - camera
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    pose[:3, 3] = camera
    n = len(points)
    side = int(np.ceil(np.sqrt(n)))
    rows, cols = np.divmod(np.arange(n), side)
    return PointCloud(points, np.full(n, OBSTACLE, np.int8), np.zeros((n, 3), np.uint8), pose, 0.0,
                      (points - camera) @ z, np.column_stack([rows, cols]).astype(np.int32), (side, side))


def _min_distance(capsules, points) -> float:
    return min(float(np.min(_segment_point_distance(a, b, points))) - r for a, b, r in capsules)


@pytest.fixture(scope="module")
def leaf_scene():
    """The paper's choice (no swing check) and a leaf placed 4 mm off the gripper at its end state."""
    plain = _Scene(None)
    target = plain.target()
    a, b, r = plain.capsules_at_end(target, 0.015)[0]  # grasp_gripper
    axis = (b - a) / np.linalg.norm(b - a)
    # the leaf faces the gripper's displacement, just beyond where the swing ends
    shift = target - plain.p_g
    away = shift - (shift @ axis) * axis
    away /= np.linalg.norm(away)
    centre = 0.5 * (a + b) + (r + 0.004) * away
    e1 = axis
    e2 = np.cross(away, e1)
    grid = np.arange(-0.02, 0.0201, 0.003)
    leaf = centre + grid[:, None, None] * e1 + grid[None, :, None] * e2
    return plain, target, leaf.reshape(-1, 3)


def test_without_the_map_check_the_gripper_ends_in_the_leaf(leaf_scene):
    """Precondition of the next test: the leaf is where the paper's p_gd takes the gripper,
    and far from the gripper now (so the check has room)."""
    plain, target, leaf = leaf_scene
    assert _min_distance(plain.capsules_at_end(target, 0.015), leaf) < 0.005
    now = [(plain.configuration.frame_pose(b.link).act(np.asarray(b.capsule.p0, float)),
            plain.configuration.frame_pose(b.link).act(np.asarray(b.capsule.p1, float)), b.capsule.radius)
           for b in description.collision_bodies() if b.name in ("grasp_gripper", "grasp_wrist_3")]
    assert _min_distance(now, leaf) > 0.03


def test_map_aware_target_keeps_the_gripper_clear_of_the_mapped_leaf(leaf_scene):
    """With the leaf in the obstacle map, p_gd moves so that the converged gripper keeps clear.

    Oracle: the law's end state (module docstring) for every stretch 0..3 cm, measured
    against the leaf's true points (the map's cells are up to one cell-sphere short of them,
    so >= swing_clearance on the map means >= swing_clearance here). Catches (each planted
    once, each failed this test): a swing model that leaves out the gripper's turn about its
    own point, a check that is computed but not used. (Leaving out the stretch along n_c is
    not caught here: this leaf is hit by the turn's end state already.)"""
    _, plain_target, leaf = leaf_scene
    scene = _Scene(0.02)
    cloud = _leaf_cloud(leaf, scene.camera)
    for _ in range(3):
        scene.obstacle_map.update(cloud)
    assert scene.obstacle_map.num_occupied > 10  # the leaf (4 x 4 cm) is in the map
    choice = scene.choice()
    target = choice.point
    assert np.linalg.norm(target - plain_target) > 0.005
    assert abs(np.linalg.norm(target - scene.p_sb) - STEM_LENGTH) < 1e-9  # on the sphere S(p_sb, l)
    for stretch in (0.0, 0.015, 0.03):
        assert _min_distance(scene.capsules_at_end(target, stretch), leaf) >= 0.02 - 1e-9, stretch
    clearance, needed = choice.swing_clearance
    assert needed == pytest.approx(0.02)
    assert choice.choice.startswith("free, in the cone, swing clear")
