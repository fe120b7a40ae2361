"""Free space on S(p_sb, l), obstacle plane and the target p_gd (subsec:scePC_proc, eq:attr_point)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.fibonacci import fibonacci_sphere
from harvest_qp.perception.free_space import compute_free_space, fit_obstacle_plane

BASE = np.array([0.2, -0.1, 1.2])
LENGTH = 0.06


def _leaf(rng, centre, normal, radius, n_points):
    """Points on a flat disc (a leaf) with 1 mm noise."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.cross(normal, [0.3, 0.5, 0.7])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    r = radius * np.sqrt(rng.uniform(0, 1, n_points))
    a = rng.uniform(0, 2 * np.pi, n_points)
    return (
        centre + np.outer(r * np.cos(a), u) + np.outer(r * np.sin(a), v) + rng.normal(scale=0.001, size=(n_points, 3))
    )


def _brute_force(obstacles, centre, radius, camera, n_samples):
    """Exhaustive versions of every step: nearest sample per obstacle by full search, plane by
    SVD, argmax over all free samples of the min over all projected obstacles."""
    samples = centre + radius * fibonacci_sphere(n_samples)
    offsets = obstacles - centre
    projected = centre + radius * offsets / np.linalg.norm(offsets, axis=1)[:, None]
    occupied = np.zeros(n_samples, bool)
    for point in projected:
        occupied[np.argmin(np.linalg.norm(samples - point, axis=1))] = True
    centroid = obstacles.mean(axis=0)
    normal = np.linalg.svd(obstacles - centroid)[2][2]
    normal = normal if normal @ (camera - centroid) > 0 else -normal
    free = ~occupied & ((samples - centroid) @ normal >= 0)
    clearance = [min(np.linalg.norm(projected - sample, axis=1)) for sample in samples[free]]
    return samples, occupied, free, samples[free][int(np.argmax(clearance))], max(clearance)


def test_eq_attr_point_by_hand():
    # Unit sphere at the origin, 4 samples at z = 0.75, 0.25, -0.25, -0.75.  One obstacle at
    # (0, 0, 2) projects to (0, 0, 1) and occupies sample 0 (no plane from one point).  The
    # free sample furthest from (0, 0, 1) is the lowest: |p - (0,0,1)| = sqrt(2 - 2 z) =
    # sqrt(3.5) for z = -0.75.
    result = compute_free_space([[0.0, 0.0, 2.0]], np.zeros(3), 1.0, [5.0, 0.0, 0.0], n_samples=4)
    np.testing.assert_array_equal(result.occupied, [True, False, False, False])
    np.testing.assert_allclose(result.projected_obstacles, [[0.0, 0.0, 1.0]])
    assert result.plane is None
    np.testing.assert_allclose(result.target, fibonacci_sphere(4)[3])
    assert result.target[2] == pytest.approx(-0.75)
    assert result.target_clearance == pytest.approx(np.sqrt(3.5), rel=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_target_points_into_the_free_side(seed):
    # A leaf 2 cm to the +y side of the stem base and a second one above it; the camera looks
    # from +x.  The free space is the -y side, seen from the camera.
    rng = np.random.default_rng(seed)
    obstacles = np.vstack(
        [
            _leaf(rng, BASE + [0.0, 0.02, -0.02], [0, 1, 0.1], 0.05, 1500),
            _leaf(rng, BASE + [0.0, 0.025, 0.03], [0, 1, 0.3], 0.04, 800),
        ]
    )
    camera = BASE + [0.35, 0.0, 0.0]
    result = compute_free_space(obstacles, BASE, LENGTH, camera, n_samples=500)
    assert result.valid, result.reason
    direction = (result.target - BASE) / LENGTH
    assert direction[1] < -0.8  # away from the leaves
    assert result.target_clearance > 0.04
    # The camera side of the obstacle plane is kept, the occupied samples removed.
    assert result.plane is not None and result.plane.normal[1] < -0.9
    assert result.occupied.any() and result.behind_plane.any()
    assert not (result.free & (result.occupied | result.behind_plane)).any()
    np.testing.assert_allclose(np.linalg.norm(result.kept_samples - BASE, axis=1), LENGTH, atol=1e-12)
    assert len(result.kept_samples) + len(result.removed_samples) == 500


def test_every_step_equals_the_exhaustive_version():
    rng = np.random.default_rng(11)
    obstacles = np.vstack(
        [
            _leaf(rng, BASE + [0.01, 0.03, 0.0], [0.2, 1, 0.1], 0.04, 600),
            BASE + rng.normal(scale=0.03, size=(300, 3)) + [0.0, 0.02, 0.02],
        ]
    )
    camera = BASE + [0.3, -0.1, 0.05]
    result = compute_free_space(obstacles, BASE, LENGTH, camera, n_samples=300)
    samples, occupied, free, target, clearance = _brute_force(obstacles, BASE, LENGTH, camera, 300)
    np.testing.assert_allclose(result.samples, samples)
    np.testing.assert_array_equal(result.occupied, occupied)
    np.testing.assert_array_equal(result.free, free)
    np.testing.assert_allclose(result.target, target)
    assert result.target_clearance == pytest.approx(clearance, rel=1e-12)


def test_removed_samples_are_the_nearest_samples_of_projected_obstacles():
    rng = np.random.default_rng(5)
    obstacles = BASE + rng.normal(scale=0.05, size=(2000, 3))
    result = compute_free_space(obstacles, BASE, LENGTH, BASE + [0.0, 0.0, 0.4], n_samples=500)
    _, nearest = cKDTree(result.samples).query(result.projected_obstacles)
    np.testing.assert_array_equal(np.flatnonzero(result.occupied), np.unique(nearest))
    np.testing.assert_allclose(np.linalg.norm(result.projected_obstacles - BASE, axis=1), LENGTH)


def test_every_sample_occupied_gives_no_target():
    # 20 000 obstacles all around the base occupy all 100 samples.
    rng = np.random.default_rng(6)
    obstacles = BASE + rng.normal(size=(20_000, 3)) * 0.03
    result = compute_free_space(obstacles, BASE, LENGTH, BASE + [0.3, 0.0, 0.0], n_samples=100)
    assert result.occupied.all()
    assert not result.valid
    assert result.target is None and np.isnan(result.target_clearance)
    assert "no free sample" in result.reason
    assert result.kept_samples.shape == (0, 3)


def test_no_obstacles_targets_the_sample_facing_the_camera():
    camera = BASE + [0.0, 0.0, 0.5]
    result = compute_free_space(np.zeros((0, 3)), BASE, LENGTH, camera, n_samples=500)
    assert result.valid and result.plane is None
    assert result.free.all()
    np.testing.assert_allclose(result.target, BASE + LENGTH * fibonacci_sphere(500)[0])  # the +z pole sample
    assert result.target_clearance == np.inf
    assert "no obstacles" in result.reason


def test_obstacles_at_the_stem_base_are_ignored():
    obstacles = np.vstack([BASE, BASE, BASE + [0.0, 0.05, 0.0]])
    result = compute_free_space(obstacles, BASE, LENGTH, BASE + [0.3, 0.0, 0.0], n_samples=200)
    assert result.projected_obstacles.shape == (1, 3)
    assert np.count_nonzero(result.occupied) == 1


def test_plane_normal_faces_the_camera_and_degenerate_planes_are_none():
    rng = np.random.default_rng(8)
    wall = np.column_stack((rng.uniform(-1, 1, 100), rng.uniform(-1, 1, 100), np.full(100, 0.5)))
    plane = fit_obstacle_plane(wall, [0.0, 0.0, -2.0])
    np.testing.assert_allclose(plane.normal, [0.0, 0.0, -1.0], atol=1e-12)
    np.testing.assert_allclose(plane.point, wall.mean(axis=0))
    assert fit_obstacle_plane(wall, [0.0, 0.0, 3.0]).normal[2] == pytest.approx(1.0)
    # Collinear obstacles, fewer than 3 points, or the camera on the plane: no plane.
    line = np.outer(np.linspace(0, 1, 20), [1.0, 2.0, 3.0])
    assert fit_obstacle_plane(line, [5.0, 0.0, 0.0]) is None
    assert fit_obstacle_plane(wall[:2], [0.0, 0.0, -2.0]) is None
    assert fit_obstacle_plane(wall, [0.3, 0.3, 0.5]) is None


def test_collinear_obstacles_remove_no_half_space():
    obstacles = BASE + np.outer(np.linspace(-0.03, 0.03, 30), [0.0, 1.0, 0.0])
    result = compute_free_space(obstacles, BASE, LENGTH, BASE + [0.3, 0.0, 0.0], n_samples=200)
    assert result.plane is None and not result.behind_plane.any()
    assert result.valid


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"obstacles": np.zeros((3, 2))}, r"obstacles must have shape \(n, 3\)"),
        ({"obstacles": np.array([[np.inf, 0.0, 0.0]])}, "NaN or inf"),
        ({"stem_length": 0.0}, "stem_length must be finite and > 0"),
        ({"stem_length": np.nan}, "stem_length must be finite and > 0"),
        ({"camera_position": [1.0, np.nan, 0.0]}, "camera_position must be finite"),
        ({"camera_position": [0.0, 0.0, 0.0], "scene_points": np.ones((4, 3))},
         "camera_position must differ from stem_base"),  # was a ZeroDivisionError in the scoring
        ({"n_samples": 0}, "n_samples must be an integer >= 1"),
        ({"scene_points": np.zeros((4, 2))}, r"scene_points must have shape \(n, 3\)"),
        ({"scene_points": np.ones((4, 3)), "up": [0.0, 0.0, 0.0]}, "up must be a non-zero direction"),
        ({"scene_points": np.ones((4, 3)), "max_elevation": 2.0}, r"max_elevation must be in \[-pi/2, pi/2\]"),
        ({"scene_points": np.ones((4, 3)), "tie_break": "random"}, "tie_break must be 'paper' or 'camera'"),
        ({"scene_points": np.ones((4, 3)), "clearance_cap": -1.0}, "clearance_cap must be finite and > 0"),
        (
            {"scene_points": np.ones((4, 3)), "stem_visibility_skip": -1.0},
            "stem_visibility_skip must be finite and >= 0",
        ),
    ],
)
def test_invalid_arguments_raise(kwargs, message):
    arguments = {
        "obstacles": np.ones((3, 3)),
        "stem_base": np.zeros(3),
        "stem_length": 0.06,
        "camera_position": [1.0, 0.0, 0.0],
        **kwargs,
    }
    n_samples = arguments.pop("n_samples", 100)
    with pytest.raises(InvalidInputError, match=message):
        compute_free_space(**arguments, n_samples=n_samples)


def test_selection_keeps_the_stem_clear_of_a_wall_by_hand():
    """A wall of observed points at x = -0.02 m behind the stem base (the camera at +x): the
    paper's plane keeps the camera side of the wall, and the clearance selection must pick the
    free sample whose straight stem from p_sb is farthest from the wall, i.e. straight towards
    the camera (x = l), clear by l + 0.02 = 0.08 m (hand value).  Catches a clearance
    measured to projected points only (it would see every free sample as equally far)."""
    y, z = np.meshgrid(np.linspace(-0.1, 0.1, 81), np.linspace(-0.1, 0.1, 81))
    wall = np.column_stack((np.full(y.size, -0.02), y.ravel(), z.ravel()))
    camera = np.array([0.5, 0.0, 0.0])
    result = compute_free_space(
        wall[np.linalg.norm(wall, axis=1) < LENGTH], np.zeros(3), LENGTH, camera, n_samples=2000,
        scene_points=wall, max_elevation=np.pi / 2,
    )  # fmt: skip
    assert result.valid
    direction = result.target / LENGTH
    assert direction[0] > 0.99
    assert result.target_point_clearance == pytest.approx(0.03, abs=1e-9)  # capped at clearance_cap
    # Uncapped, the clearance is the hand value.
    uncapped = compute_free_space(
        wall[np.linalg.norm(wall, axis=1) < LENGTH], np.zeros(3), LENGTH, camera, n_samples=2000,
        scene_points=wall, max_elevation=np.pi / 2, clearance_cap=1.0,
    )  # fmt: skip
    assert uncapped.target_point_clearance == pytest.approx(LENGTH + 0.02, abs=2e-3)
    assert uncapped.target[0] / LENGTH > 0.99


def _segment_to_point_2d(start, end, point):
    """Distance from each 2-D segment start[i] -> end[i] to ``point``."""
    d = end - start
    t = np.clip(np.einsum("ij,ij->i", point - start, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    return np.linalg.norm(start + t[:, None] * d - point, axis=1)


@pytest.mark.parametrize("camera", [(0.35, 0.0, -0.03), (0.2, 0.0, 0.3)], ids=["front-below", "above"])
def test_stems_behind_the_observed_front_of_a_branch_are_hidden_by_hand(camera):
    """A branch: a solid horizontal cylinder (radius 20 mm, along y, axis at z = 20 mm) of which
    only the half facing the camera is observed; p_sb at its underside.  Oracle, the analytic
    cylinder: every scored sample whose straight stem runs more than 5 mm inside the cylinder
    past its first 12 mm is flagged ``stem_hidden``; every scored sample whose stem keeps 8 mm
    (the depth buffer's widening) out of the cylinder's shadow seen from the camera is not;
    the target's stem stays out of the cylinder.  Seen from above, every stem is in the
    branch's shadow: all are hidden and ``reason`` says so.  Catches a visibility test that
    looks at the end point only (planted once: the assertion on the through-wood stems
    fails) or at no stem point."""
    camera = np.array(camera)
    radius_b = 0.02
    axis = np.array([0.0, radius_b])  # (x, z) of the cylinder axis
    angle = np.linspace(0.0, 2.0 * np.pi, 720, endpoint=False)
    y = np.arange(-0.15, 0.15, 0.0015)
    a, yy = np.meshgrid(angle, y)
    surface = np.column_stack((radius_b * np.cos(a.ravel()), yy.ravel(), radius_b + radius_b * np.sin(a.ravel())))
    normals = surface - np.column_stack((np.zeros(len(surface)), surface[:, 1], np.full(len(surface), radius_b)))
    seen = np.einsum("ij,ij->i", normals, camera - surface) > 0.0
    observed = surface[seen]
    centre = np.zeros(3)
    obstacles = observed[np.linalg.norm(observed - centre, axis=1) < LENGTH]
    skip = 0.012  # past the depth buffer's widening (two 4 mm cells) around p_sb
    result = compute_free_space(
        obstacles, centre, LENGTH, camera, n_samples=1000, scene_points=observed, stem_visibility_skip=skip
    )
    assert result.valid
    scored = np.isfinite(result.stem_clearance)  # the samples the selection looked at (inf: not scored)

    along = np.arange(skip, LENGTH + 1e-9, 0.001)
    stem_points = centre + (along / LENGTH)[None, :, None] * result.samples[:, None, :]  # (n, k, 3)
    xz = stem_points[..., [0, 2]]
    depth_inside = radius_b - np.linalg.norm(xz - axis, axis=2)  # > 0 inside the cylinder
    through_wood = (depth_inside > 0.005).any(axis=1)
    # Out of the shadow: the 2-D segment camera -> stem point keeps 8 mm (two cells) from the cylinder.
    flat = xz.reshape(-1, 2)
    ray_gap = _segment_to_point_2d(np.broadcast_to(camera[[0, 2]], flat.shape), flat, axis).reshape(xz.shape[:2])
    in_plain_view = (ray_gap > radius_b + 0.008).all(axis=1)
    assert result.stem_hidden[scored & through_wood].all()
    assert not result.stem_hidden[scored & in_plain_view].any()
    index = int(np.argmin(np.linalg.norm(result.samples - result.target, axis=1)))
    assert not through_wood[index]
    if camera[2] > 0.2:
        # Every stem is in the branch's shadow: all scored, all hidden, and the result says so.
        assert (scored & through_wood).sum() >= 50 and result.stem_hidden[scored].all()
        assert "passes behind an observed surface" in result.reason
    else:
        assert (scored & in_plain_view).sum() >= 50
        assert result.free[index] and not result.stem_hidden[index] and result.reason == ""
