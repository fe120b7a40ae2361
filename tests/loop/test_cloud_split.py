"""One labelled camera frame split into S, W - S and the obstacle points, and the grasping arm's cloud filters.

Public API of :mod:`harvest_qp.perception.cloud_split`, as the controller uses it on every camera
frame. Oracles: the labels written by hand next to each point (a loop over the rows, not numpy's
boolean indexing on the same mask), and hand-placed points around a gripper pose.
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.cloud_split import LabelledFrame, obstacle_sphere_centres, outside_held_cluster
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM, PointCloud


def _cloud(points, labels, camera=(0.6, 0.0, 0.4), t=0.1) -> PointCloud:
    pose = np.eye(4)
    pose[:3, 3] = camera
    n = len(points)
    return PointCloud(points=np.asarray(points, float), labels=np.asarray(labels, np.int8),
                      colors=np.zeros((n, 3), np.uint8), camera_pose=pose, timestamp=t, depth=np.ones(n),
                      pixels=np.zeros((n, 2), np.int32), image_size=(8, 8))


@pytest.mark.parametrize("n", [0, 1, 7, 503])
def test_frame_splits_the_cloud_by_label_in_order(n):
    """Catches: a label test inverted, the robot's points in the obstacle set, rows reordered or
    partly copied, W - S missing the robot's points (the camera arm's obstacles are all of them)."""
    rng = np.random.default_rng(n)
    points = rng.normal(size=(n, 3))
    points[::97] = -0.0
    labels = rng.choice([STEM, OBSTACLE, ROBOT], size=n)
    stem = [p for p, label in zip(points, labels) if label == STEM]
    non_stem = [p for p, label in zip(points, labels) if label != STEM]
    obstacles = [p for p, label in zip(points, labels) if label == OBSTACLE]
    frame = LabelledFrame(_cloud(points, labels, t=0.25))
    assert frame.time == 0.25 and frame.n_stem == len(stem) and frame.fit is None
    np.testing.assert_array_equal(frame.camera_position, (0.6, 0.0, 0.4))
    for got, expected in ((frame.stem, stem), (frame.non_stem, non_stem), (frame.obstacles, obstacles)):
        assert got.shape == (len(expected), 3)
        np.testing.assert_array_equal(got, np.reshape(expected, (-1, 3)))
    assert frame.non_stem is frame.non_stem  # gathered once
    assert frame.n_non_stem == len(non_stem)


@pytest.mark.parametrize("stride", [1, 2, 5, 1000])
def test_every_kth_non_stem_row_is_the_thinned_split(stride):
    """``non_stem_every(k)`` (what the unveiling law's paper mode reads) is ``W - S`` thinned by k:
    the first matching row, then every k-th, before and after W - S itself was gathered.
    Catches: a stride over all rows instead of the non-stem ones, the first row skipped."""
    rng = np.random.default_rng(stride)
    points = rng.normal(size=(2003, 3))
    labels = rng.choice([STEM, OBSTACLE, ROBOT], size=2003)
    expected = np.reshape([p for p, label in zip(points, labels) if label != STEM], (-1, 3))[::stride]
    frame = LabelledFrame(_cloud(points, labels))
    np.testing.assert_array_equal(frame.non_stem_every(stride), expected)
    frame.non_stem  # noqa: B018 (gathered: the thinned rows are taken from it)
    np.testing.assert_array_equal(frame.non_stem_every(stride), expected)


def test_frame_keeps_its_own_camera_pose():
    """Catches: the frame holding the cloud's pose array (a caller that edits it moves the frame)."""
    cloud = _cloud(np.zeros((2, 3)), [STEM, OBSTACLE])
    frame = LabelledFrame(cloud)
    cloud.camera_pose[:3, 3] = 9.0
    np.testing.assert_array_equal(frame.camera_position, (0.6, 0.0, 0.4))
    np.testing.assert_array_equal(frame.camera_pose[:3, 3], (0.6, 0.0, 0.4))


def test_frame_refuses_what_is_not_a_labelled_cloud():
    with pytest.raises(InvalidInputError, match="PointCloud"):
        LabelledFrame(np.zeros((3, 3)))
    bad = _cloud(np.zeros((3, 3)), [STEM, STEM, STEM])
    object.__setattr__(bad, "labels", np.zeros(2, np.int8))
    with pytest.raises(InvalidInputError, match="labels"):
        LabelledFrame(bad)


def _gripper_pose() -> np.ndarray:
    """Gripper at (0, 0, 1) with y_g (the hanging direction) along -z."""
    T = np.eye(4)
    T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]
    T[:3, 3] = (0.0, 0.0, 1.0)
    return T


def test_held_cluster_is_the_capsule_below_the_gripper():
    """Hand-placed points: on the hanging axis within the cluster's length, just inside and just
    outside its radius, beyond its end, above the gripper (the rounded top), and to the side.
    Catches: the capsule along another axis, its length or radius swapped, a cylinder without
    the rounded ends."""
    T = _gripper_pose()
    points = np.array([
        (0.0, 0.0, 0.95),    # on the axis, 5 cm below: held
        (0.029, 0.0, 0.9),   # 2.9 cm off the axis: held
        (0.031, 0.0, 0.9),   # 3.1 cm off the axis: outside
        (0.0, 0.0, 0.875),   # 12.5 cm below the gripper, 2.5 cm past the end: on the rounded end, held
        (0.0, 0.0, 0.86),    # 14 cm below: outside
        (0.0, 0.0, 1.02),    # 2 cm above the gripper point: the rounded top, held
        (0.0, 0.0, 1.04),    # 4 cm above: outside
        (0.2, 0.0, 0.95),    # to the side: outside
    ])
    outside = outside_held_cluster(points, T, cluster_length=0.1, cluster_radius=0.03)
    assert outside.tolist() == [False, False, True, False, True, False, True, True]


def test_obstacle_spheres_are_the_first_point_of_each_voxel_near_the_gripper():
    """Catches: the held cluster or far points turned into spheres, the last point of a voxel
    kept instead of the first, centres out of the cloud's order."""
    T = _gripper_pose()
    points = np.array([
        (0.105, 0.005, 0.955),   # voxel (10, 0, 95): first
        (0.205, 0.005, 0.955),   # voxel (20, 0, 95): first
        (0.106, 0.006, 0.956),   # voxel (10, 0, 95) again: not a sphere
        (0.0, 0.0, 0.955),       # in the held cluster
        (0.9, 0.0, 1.0),         # farther than max_distance
        (-0.105, 0.005, 0.955),  # voxel (-11, 0, 95)
    ])
    centres = obstacle_sphere_centres(points, T, max_distance=0.5, cluster_length=0.1, cluster_radius=0.03,
                                      voxel=0.01)
    np.testing.assert_array_equal(centres, points[[0, 1, 5]])
    none = obstacle_sphere_centres(points[[3, 4]], T, max_distance=0.5, cluster_length=0.1, cluster_radius=0.03,
                                   voxel=0.01)
    assert none.shape == (0, 3)


@pytest.mark.parametrize("n_obstacles", [300, 4000])
def test_the_laws_every_kth_rows_give_the_laws_own_thinning(n_obstacles):
    """The controller hands the unveiling law's paper mode ``non_stem_every(law.obstacle_stride(n))``
    instead of all of W - S; the law must reach the same V_cu target as when it thins W - S itself
    (``max_obstacle_points`` 1000 here: strides 1 and 4). Oracle: the law's public ``observe`` on
    the whole W - S. Catches: a stride other than the law's, rows counted over the whole cloud."""
    from harvest_qp.config.settings import check_settings
    from harvest_qp.references import Unveiling

    u = check_settings({}).unveiling
    rng = np.random.default_rng(n_obstacles)
    camera = np.array([0.6, 0.0, 0.4])
    stem = np.column_stack((0.02 * rng.normal(size=40), 0.02 * rng.normal(size=40), 0.5 + 0.1 * rng.random(40)))
    leaves = np.column_stack((0.3 + 0.05 * rng.normal(size=n_obstacles), 0.05 * rng.normal(size=n_obstacles),
                              0.55 + 0.05 * rng.normal(size=n_obstacles)))
    points = np.vstack((leaves, stem, rng.normal(size=(50, 3))))
    labels = np.array([OBSTACLE] * n_obstacles + [STEM] * 40 + [ROBOT] * 50)
    order = rng.permutation(len(points))
    frame = LabelledFrame(_cloud(points[order], labels[order], camera))
    laws = []
    for _ in range(2):
        law = Unveiling(k_c=u.k_c, d_a=u.d_a, d_o=u.d_o, time_constant=u.time_constant,
                        max_linear=u.max_linear, max_angular=u.max_angular, min_pivot=u.min_pivot)
        law.max_obstacle_points = 1000
        laws.append(law)
    thinned, whole = laws
    thinned.observe(camera, frame.stem, frame.non_stem_every(thinned.obstacle_stride(frame.n_non_stem)), timestamp=0.1)
    whole.observe(camera, frame.stem, frame.non_stem, timestamp=0.1)
    assert thinned.mode == whole.mode == "paper" and thinned.n_pairs == whole.n_pairs > 0
    np.testing.assert_array_equal(thinned.raw, whole.raw)
