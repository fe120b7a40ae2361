"""process_cloud: the per-frame pipeline on a rendered vine scene."""

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import process_cloud, ray_obstacle_pairs
from harvest_qp.perception.synthetic import VineScene, render_scene

SCENE = VineScene.default()
CAMERA = SCENE.stem_base + np.array([0.25, 0.02, -0.04])
GRIPPER = SCENE.stem_end + np.array([0.0, 0.0, -0.05])


@pytest.fixture(scope="module")
def frame():
    return render_scene(SCENE, CAMERA, width=283, height=160)


@pytest.fixture(scope="module")
def result(frame):
    return process_cloud(frame.points, frame.stem_mask, camera_position=CAMERA, gripper_position=GRIPPER)


def test_rendered_scene_is_a_realistic_frame(frame):
    assert frame.points.shape == (283 * 160, 3)  # the background wall fills every pixel
    assert 150 <= np.count_nonzero(frame.stem_mask) <= 400


def test_stem_model_and_base_on_a_partly_occluded_stem(result):
    assert result.stem.valid, result.stem.reason
    assert np.linalg.norm(result.stem_base - SCENE.stem_base) < 0.004
    assert result.stem.length == pytest.approx(0.06, abs=0.01)
    # The top cluster is the one attached to the branch.
    top_mean = result.stem_points[result.stem.top_mask].mean(axis=0)
    assert np.linalg.norm(top_mean - SCENE.stem_base) < np.linalg.norm(top_mean - SCENE.stem_end)


def test_grasp_obstacles_and_target(result):
    base, length = result.stem_base, result.stem.length
    # r_o defaults to the stem length (Section sec:exper).
    assert len(result.grasp_obstacles) > 100
    assert (np.linalg.norm(result.grasp_obstacles - base, axis=1) < length).all()
    free_space = result.free_space
    assert free_space.valid and result.target is not None
    assert np.linalg.norm(result.target - base) == pytest.approx(length)
    # The target is a kept sample, on the camera side of the obstacle plane, clear of obstacles.
    assert any(np.array_equal(result.target, sample) for sample in free_space.kept_samples)
    assert (result.target - free_space.plane.point) @ free_space.plane.normal >= 0.0
    assert free_space.target_clearance > 0.01


def test_unveiling_uses_all_non_stem_points(frame, result):
    non_stem = frame.points[~frame.stem_mask]
    np.testing.assert_array_equal(result.unveiling.obstacle_points, non_stem)
    direct = ray_obstacle_pairs(frame.points[frame.stem_mask], non_stem, CAMERA)
    assert len(result.unveiling) == len(direct) > 0


def test_non_finite_rows_are_dropped(frame, result):
    points = frame.points.copy()
    points[::97] = np.nan
    points[5::101, 1] = np.inf
    dropped = process_cloud(points, frame.stem_mask, camera_position=CAMERA, gripper_position=GRIPPER)
    n_bad = np.count_nonzero(~np.isfinite(points).all(axis=1))
    assert dropped.n_dropped == n_bad > 0
    assert len(dropped.stem_points) + len(dropped.unveiling.obstacle_points) == len(points) - n_bad
    assert dropped.stem.valid
    assert np.linalg.norm(dropped.stem_base - result.stem_base) < 0.002


def test_r_o_bounds_the_grasp_obstacles(frame, result):
    """O is exactly the non-stem points within r_o of p_sb (Table table:PCs), computed here by
    brute force: catches r_o being ignored (the default l used instead), used as a diameter,
    or the set coming back empty (the former test passed on an empty result)."""
    small = process_cloud(frame.points, frame.stem_mask, camera_position=CAMERA, gripper_position=GRIPPER, r_o=0.02)
    non_stem = frame.points[~frame.stem_mask]
    expected = non_stem[np.linalg.norm(non_stem - small.stem_base, axis=1) < 0.02]
    assert len(expected) > 20
    np.testing.assert_array_equal(small.grasp_obstacles, expected)
    # The default r_o = l (about 0.06 m here) keeps more of them.
    assert len(result.grasp_obstacles) > len(expected)


def test_empty_cloud():
    empty = process_cloud(np.zeros((0, 3)), np.zeros(0, bool), camera_position=CAMERA, gripper_position=GRIPPER)
    assert not empty.stem.valid and "too few stem points: 0" in empty.stem.reason
    assert empty.free_space is None and empty.target is None and empty.stem_base is None
    assert len(empty.unveiling) == 0


def test_one_stem_point_still_unveils(frame):
    mask = np.zeros(len(frame.points), bool)
    mask[np.flatnonzero(frame.stem_mask)[0]] = True
    single = process_cloud(frame.points, mask, camera_position=CAMERA, gripper_position=GRIPPER)
    assert not single.stem.valid and single.free_space is None
    assert single.unveiling.stem_points.shape == (1, 3)
    assert len(single.unveiling) > 0


def test_no_stem_points_give_no_unveiling_pairs(frame):
    none = process_cloud(
        frame.points, np.zeros(len(frame.points), bool), camera_position=CAMERA, gripper_position=GRIPPER
    )
    assert len(none.unveiling) == 0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"camera_position": [0.0, 0.0]}, r"camera_position must have shape \(3,\)"),
        ({"camera_position": 0.3}, r"camera_position must have shape \(3,\), got the scalar 0.3"),
        ({"gripper_position": [0.0, np.nan, 0.0]}, "gripper_position must be finite"),
        ({"stem_mask": np.zeros(3, bool)}, r"stem_mask must have shape \(4,\)"),
        ({"points": np.zeros((4, 4))}, r"points must have shape \(n, 3\)"),
        ({"r_o": 0.0}, "r_o must be finite and > 0"),
        ({"d_a": -0.01}, "d_a must be finite and > 0"),
        ({"n_samples": 0}, "n_samples must be an integer >= 1"),
    ],
)
def test_invalid_arguments_raise(kwargs, message):
    rng = np.random.default_rng(0)
    arguments = {
        "points": np.vstack([np.column_stack((np.zeros(2), np.zeros(2), [1.0, 1.05])), rng.normal(size=(2, 3))]),
        "stem_mask": np.array([True, True, False, False]),
        "camera_position": [0.0, 0.0, 0.0],
        "gripper_position": [0.0, 0.0, 2.0],
        **kwargs,
    }
    with pytest.raises(InvalidInputError, match=message):
        process_cloud(arguments.pop("points"), arguments.pop("stem_mask"), **arguments, min_stem_points=2)
