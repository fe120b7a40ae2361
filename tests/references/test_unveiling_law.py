"""The unveiling law (eq:art_potential .. eq:v_c2), its bounded form and the Unveiling object:
hand-computed values on small cases."""

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.unveiling import ray_obstacle_pairs
from harvest_qp.references import Unveiling, predicted_stem_points
from harvest_qp.references.unveiling import (
    barrier_potential,
    bounded_unveiling_velocity,
    repulsive_velocity,
    saturate_twist,
    unveiling_velocity,
)

D_A, D_O = 0.01, 0.001


def test_u_ij_matches_the_potentials_gradient_by_finite_differences():
    """u = -dV/dp_hat (eq:u_ij vs eq:art_potential) by central differences of V(|p - p_o| - d_o)
    at several r_hat across (0, d_a).  Catches: a dropped factor 2 or (d_a - r) in eq:u_ij."""
    obstacle = np.array([0.01, -0.02, 0.3])
    rng = np.random.default_rng(3)
    for r_hat in (0.0005, 0.002, 0.005, 0.009):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        point = obstacle + (r_hat + D_O) * direction
        u = repulsive_velocity(point[None], obstacle[None], d_a=D_A, d_o=D_O)[0]
        gradient = np.zeros(3)
        for axis in range(3):
            step = np.zeros(3)
            step[axis] = 1e-7
            plus = barrier_potential(np.linalg.norm(point + step - obstacle) - D_O, D_A)
            minus = barrier_potential(np.linalg.norm(point - step - obstacle) - D_O, D_A)
            gradient[axis] = (plus - minus) / 2e-7
        np.testing.assert_allclose(u, -gradient, rtol=1e-5)


def test_v_is_non_increasing_along_u_and_under_the_camera_twist():
    """(1) Moving p_hat along u lowers V.  (2) The paper's claim under eq:v_c2: for one stem
    point and one obstacle near the middle of the ray, moving the camera by V_cu (the exact
    rigid motion of the twist) increases r_hat and lowers V at every step until the ray leaves
    the influence distance.  Catches: a sign error anywhere in eq:omega_pivot/eq:v_c2 (the
    camera would turn the ray into the obstacle)."""
    obstacle = np.array([[0.004, 0.0, 0.25]])
    stem = np.array([[0.0, 0.0, 0.5]])
    u = repulsive_velocity([[0.0, 0.0, 0.25]], obstacle, d_a=D_A, d_o=D_O)[0]
    v0 = barrier_potential(0.003, D_A)
    assert barrier_potential(np.linalg.norm([0.0, 0.0, 0.25] + 1e-5 * u - obstacle[0]) - D_O, D_A) < v0

    camera = np.zeros(3)
    r_hats = []
    for _ in range(200):
        pairs = ray_obstacle_pairs(stem, obstacle, camera, d_a=D_A, d_o=D_O)
        if len(pairs) == 0:
            break
        r_hats.append(float(pairs.surface_distance[0]))
        twist = unveiling_velocity(pairs, k_c=1e-6)
        # Rigid motion of the camera point under the twist (v at the camera origin, w):
        camera = camera + 0.01 * twist[:3]
        # The twist is a pure rotation about the stem point: |p_c - p_s| is preserved to first order.
    assert len(r_hats) > 5 and np.all(np.diff(r_hats) > 0.0)
    assert np.linalg.norm(camera - stem[0]) == pytest.approx(0.5, rel=2e-3)


def test_eq_v_c2_single_pair_by_hand():
    """Camera 0, stem point (0, 0, 0.5), obstacle (0.004, 0, 0.25): p_hat = (0, 0, 0.25),
    r_hat = 0.003, |u| = 2/(1e-4 - 4.9e-5) ln(1e-4/5.1e-5) 0.007 = 184.9538..., u along -x.
    w = S(p_hat - p_s) u / |p_hat - p_s|^2 = (0,0,-0.25) x (-|u|,0,0) / 0.0625 = (0, 4|u|, 0);
    V_cu = k_c [p_cs x w; w] = k_c [(-2|u|, 0, 0); (0, 4|u|, 0)].
    Catches: the lever S(p_s - p_hat) or S(p_cs) applied with the wrong sign."""
    pairs = ray_obstacle_pairs([[0.0, 0.0, 0.5]], [[0.004, 0.0, 0.25]], np.zeros(3), d_a=D_A, d_o=D_O)
    magnitude = 2.0 / (1e-4 - 4.9e-5) * math.log(1e-4 / 5.1e-5) * 0.007
    expected = 0.001 * np.array([-2.0 * magnitude, 0.0, 0.0, 0.0, 4.0 * magnitude, 0.0])
    np.testing.assert_allclose(unveiling_velocity(pairs, k_c=0.001), expected, rtol=1e-12, atol=1e-12)


def test_saturate_twist_scales_both_parts_by_one_factor():
    """(0.3, 0, 0, 0, 0.5, 0) with bounds 0.1 m/s, 0.2 rad/s: linear needs 1/3, angular 0.4 ->
    1/3.  Clipping each part separately would change the screw axis."""
    np.testing.assert_allclose(saturate_twist(np.array([0.3, 0, 0, 0, 0.5, 0]), 0.1, 0.2), [0.1, 0, 0, 0, 0.5 / 3, 0])
    np.testing.assert_allclose(
        saturate_twist(np.array([0.01, 0, 0, 0, 0.9, 0]), 0.1, 0.2), [0.01 * 0.2 / 0.9, 0, 0, 0, 0.2, 0]
    )
    small = np.array([0.01, 0.0, 0.0, 0.0, 0.02, 0.0])
    np.testing.assert_array_equal(saturate_twist(small, 0.1, 0.2), small)


def test_bounded_law_drops_short_pivots_and_keeps_the_direction():
    """An obstacle 1 cm from the stem point along the ray (pivot arm 1 cm < 3 cm) is dropped;
    one at mid-ray is kept, and the bounded twist is the literal one scaled down.
    Catches: the pivot test on the wrong end of the ray (|p_hat - p_c|)."""
    stem, camera = np.array([[0.0, 0.0, 0.5]]), np.zeros(3)
    touching = ray_obstacle_pairs(stem, [[0.004, 0.0, 0.49]], camera, d_a=D_A, d_o=D_O)
    assert np.abs(unveiling_velocity(touching, k_c=0.00025)).max() > 1e-3  # the paper's law acts
    np.testing.assert_array_equal(bounded_unveiling_velocity(touching), np.zeros(6))
    both = ray_obstacle_pairs(stem, [[0.004, 0.0, 0.49], [0.004, 0.0, 0.25]], camera, d_a=D_A, d_o=D_O)
    middle = ray_obstacle_pairs(stem, [[0.004, 0.0, 0.25]], camera, d_a=D_A, d_o=D_O)
    literal = unveiling_velocity(middle, k_c=1.0)
    bounded = bounded_unveiling_velocity(both, k_c=1.0, max_linear=0.1, max_angular=0.2)
    assert np.linalg.norm(bounded[3:]) == pytest.approx(0.2)
    np.testing.assert_allclose(bounded / np.linalg.norm(bounded), literal / np.linalg.norm(literal), rtol=1e-12)


def test_predicted_stem_points_by_hand():
    """{G} at (1, 2, 3) with y_g = (0, 1, 0): the stem is expected along -y_g from 1.5 cm to
    7.5 cm.  Catches: +y_g (the points would lie inside the cluster)."""
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 2.0, 3.0]
    points = predicted_stem_points(pose)
    assert points.shape == (12, 3)
    np.testing.assert_allclose(points[0], [1.0, 1.985, 3.0])
    np.testing.assert_allclose(points[-1], [1.0, 1.925, 3.0])
    np.testing.assert_allclose(np.diff(points[:, 1]), -0.06 / 11)
    with pytest.raises(InvalidInputError, match="n must"):
        predicted_stem_points(pose, n=0)


def test_unveiling_object_modes_and_filter():
    """Idle without stem and prediction; paper mode with seen stem points; the low-pass
    moves (1 - exp(-dt/tau)) of the way per update.  Catches: V_cu acting when n_S = 0
    (the paper's 'zero by design') and an unfiltered output."""
    law = Unveiling(time_constant=0.2)
    law.observe(np.zeros(3), np.zeros((0, 3)), [[0.004, 0.0, 0.25]])
    assert law.mode == "idle" and not law.raw.any() and not law.update(0.01).any()
    law.observe(np.zeros(3), [[0.0, 0.0, 0.5]], [[0.004, 0.0, 0.25]])
    assert law.mode == "paper" and law.n_pairs == 1
    # The single pair of test_eq_v_c2_single_pair_by_hand with k_c = 0.00025: |w| = 0.18495 rad/s,
    # |v| = 0.0925 m/s, both under the bounds (0.2, 0.1), so the raw twist is the literal one.
    magnitude = 2.0 / (1e-4 - 4.9e-5) * math.log(1e-4 / 5.1e-5) * 0.007
    np.testing.assert_allclose(law.raw, 0.00025 * magnitude * np.array([-2.0, 0, 0, 0, 4.0, 0]), rtol=1e-12, atol=1e-15)
    first = law.update(0.01)
    np.testing.assert_allclose(first, -math.expm1(-0.05) * law.raw, rtol=1e-12)
    second = law.update(0.01)
    np.testing.assert_allclose(second, first + -math.expm1(-0.05) * (law.raw - first), rtol=1e-12)
    law.reset()
    assert law.mode == "idle" and not law.update(0.01).any()


def test_unveiling_bad_input_raises():
    with pytest.raises(InvalidInputError, match="max_angular"):
        Unveiling(max_angular=0.0)
    with pytest.raises(InvalidInputError, match="goal_fraction"):
        Unveiling(goal_fraction=1.5)
    with pytest.raises(InvalidInputError, match="stem_points"):
        Unveiling().observe(np.zeros(3), [[0.0, 0.0]], [])
    with pytest.raises(InvalidInputError, match="dt"):
        Unveiling().update(-0.1)


def _law_scene(seed: int, n_stem: int = 60, n_obstacles: int = 4000):
    """A stem of ``n_stem`` points 0.3 m from the camera behind a leaf-like slab of obstacles."""
    rng = np.random.default_rng(seed)
    camera = rng.normal(scale=0.05, size=3)
    stem = camera + np.column_stack(
        (rng.uniform(-0.01, 0.01, n_stem), np.linspace(-0.04, 0.04, n_stem), rng.uniform(0.28, 0.32, n_stem))
    )
    obstacles = camera + np.column_stack(
        (rng.uniform(-0.05, 0.05, n_obstacles), rng.uniform(-0.06, 0.06, n_obstacles),
         rng.uniform(0.01, 0.31, n_obstacles))
    )  # fmt: skip
    return stem, obstacles, camera


def test_unchecked_pairs_are_the_checked_pairs_and_observe_still_checks():
    """_ray_obstacle_pairs_unchecked (the law's per-frame path) returns the public function's
    arrays bit for bit (a strided stem view included, as the law thins its stem), and the
    public entry points still reject NaN.  Catches: the unchecked variant diverging from the
    public one (e.g. the stem-at-camera test dropped), a public check removed."""
    from harvest_qp.perception.unveiling import _ray_obstacle_pairs_unchecked

    stem, obstacles, camera = _law_scene(4, n_stem=90)
    stem = stem[::2]
    checked = ray_obstacle_pairs(stem, obstacles, camera, d_a=D_A, d_o=D_O)
    unchecked = _ray_obstacle_pairs_unchecked(stem, obstacles, camera, D_A, D_O)
    for name in ("stem_index", "obstacle_index", "surface_distance", "case", "segment_parameter", "away_directions"):
        a, b = getattr(checked, name), getattr(unchecked, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name
    with pytest.raises(InvalidInputError, match="stem_points must differ from camera_position"):
        _ray_obstacle_pairs_unchecked(np.vstack((stem, camera)), obstacles, camera, D_A, D_O)
    bad = obstacles.copy()
    bad[7, 1] = np.nan
    with pytest.raises(InvalidInputError, match="obstacle_points"):
        ray_obstacle_pairs(stem, bad, camera, d_a=D_A, d_o=D_O)
    with pytest.raises(InvalidInputError, match="obstacle_points"):
        Unveiling().observe(camera, stem, bad)


def test_observe_gives_the_numpy_laws_twist():
    """Unveiling.observe against the literal composition ray_obstacle_pairs ->
    bounded_unveiling_velocity, and its pair count.  Catches: the law fed the wrong
    d_a / k_c / min_pivot."""
    stem, obstacles, camera = _law_scene(5)
    law = Unveiling()
    law.observe(camera, stem, obstacles)
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=law.d_a, d_o=law.d_o)
    expected = bounded_unveiling_velocity(pairs, k_c=law.k_c, min_pivot=law.min_pivot, max_linear=law.max_linear,
                                          max_angular=law.max_angular)  # fmt: skip
    assert law.mode == "paper" and law.n_pairs > 0
    np.testing.assert_array_equal(law.raw, expected)
