"""Unveiling kernel (perception, eq:nearest) and the paper's literal law on it
(harvest_qp.references.unveiling: eq:art_potential, eq:u_ij, eq:omega_pivot, eq:omega_i, eq:v_c2)."""

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.unveiling import (
    NEAREST_AT_CAMERA,
    NEAREST_AT_STEM_POINT,
    NEAREST_INTERIOR,
    ray_obstacle_pairs,
)
from harvest_qp.references.unveiling import (
    barrier_potential,
    repulsive_velocity,
    stem_angular_velocities,
    unveiling_velocity,
)

D_A, D_O = 0.01, 0.001


# ---------------------------------------------------------------- literal reference


def _literal_pairs(stem, obstacles, camera, d_a, d_o):
    """eq:nearest and r_hat by the double loop over all (j, k), as written in the paper."""
    pairs = {}
    for j, stem_point in enumerate(stem):
        p_cs = stem_point - camera
        for k, obstacle in enumerate(obstacles):
            p_co = obstacle - camera
            projection = p_cs @ p_co / np.linalg.norm(p_cs)
            if projection <= 0.0:
                nearest, case = camera, NEAREST_AT_CAMERA
            elif projection < np.linalg.norm(p_cs):
                nearest, case = camera + np.outer(p_cs, p_cs) @ p_co / (p_cs @ p_cs), NEAREST_INTERIOR
            else:
                nearest, case = stem_point, NEAREST_AT_STEM_POINT
            r_hat = np.linalg.norm(nearest - obstacle) - d_o
            if r_hat < d_a:
                pairs[(j, k)] = (nearest, r_hat, case)
    return pairs


def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _literal_velocity(stem, obstacles, camera, d_a, d_o, k_c):
    """eq:u_ij, eq:omega_pivot, eq:omega_i and eq:v_c2 term by term."""
    total = np.zeros(6)
    for (j, k), (nearest, r_hat, case) in _literal_pairs(stem, obstacles, camera, d_a, d_o).items():
        if case != NEAREST_INTERIOR:
            continue
        barrier = d_a**2 - (d_a - r_hat) ** 2
        e = (d_a - r_hat) * (nearest - obstacles[k]) / np.linalg.norm(nearest - obstacles[k])
        u = 2.0 / barrier * np.log(d_a**2 / barrier) * e
        lever = nearest - stem[j]
        omega = _skew(lever) @ u / (lever @ lever)
        total += k_c * np.concatenate((_skew(stem[j] - camera) @ omega, omega))
    return total


def _random_scene(rng, n_stem, n_obstacles):
    camera = rng.normal(scale=0.1, size=3)
    centre = camera + [0.0, 0.0, 0.3] + rng.normal(scale=0.05, size=3)
    stem = centre + rng.normal(size=(n_stem, 3)) * rng.uniform(0.005, 0.05)
    obstacles = camera + rng.uniform(-0.12, 0.12, size=(n_obstacles, 3)) * [1.0, 1.0, 3.0]
    return stem, obstacles, camera


# ---------------------------------------------------------------- hand-computed cases


def test_eq_nearest_by_hand():
    # Camera at the origin, stem point at (0, 0, 1).
    camera, stem = np.zeros(3), np.array([[0.0, 0.0, 1.0]])
    obstacles = np.array(
        [
            [0.005, 0.0, 0.5],  # projection 0.5 in (0, 1): p_hat = (0, 0, 0.5), r_hat = 0.005 - 0.001
            [0.002, 0.0, -0.003],  # projection -0.003 <= 0: p_hat = p_c, r_hat = sqrt(13e-6) - 0.001
            [0.003, 0.004, 1.002],  # projection 1.002 >= 1: p_hat = p_s, r_hat = sqrt(29e-6) - 0.001
            [0.0, 0.012, 0.5],  # 0.012 from the ray: r_hat = 0.011 >= d_a, not a pair
        ]
    )
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=D_A, d_o=D_O)
    by_obstacle = {int(k): i for i, k in enumerate(pairs.obstacle_index)}
    assert sorted(by_obstacle) == [0, 1, 2]
    assert (pairs.stem_index == 0).all()

    interior, at_camera, at_stem = by_obstacle[0], by_obstacle[1], by_obstacle[2]
    np.testing.assert_allclose(pairs.nearest_points[interior], [0.0, 0.0, 0.5], atol=1e-15)
    assert pairs.surface_distance[interior] == pytest.approx(0.004, abs=1e-15)
    assert pairs.case[interior] == NEAREST_INTERIOR
    assert pairs.segment_parameter[interior] == pytest.approx(0.5)
    np.testing.assert_allclose(pairs.away_directions[interior], [-1.0, 0.0, 0.0], atol=1e-12)

    np.testing.assert_allclose(pairs.nearest_points[at_camera], [0.0, 0.0, 0.0], atol=1e-15)
    assert pairs.surface_distance[at_camera] == pytest.approx(np.sqrt(13e-6) - 0.001, abs=1e-15)
    assert pairs.case[at_camera] == NEAREST_AT_CAMERA

    np.testing.assert_allclose(pairs.nearest_points[at_stem], [0.0, 0.0, 1.0], atol=1e-15)
    assert pairs.surface_distance[at_stem] == pytest.approx(np.sqrt(29e-6) - 0.001, abs=1e-15)
    assert pairs.case[at_stem] == NEAREST_AT_STEM_POINT


def test_eq_art_potential_and_eq_u_ij_by_hand():
    # r_hat = 0.004, d_a = 0.01: d_a^2 - (d_a - r_hat)^2 = 1e-4 - 3.6e-5 = 6.4e-5,
    # ln(1e-4 / 6.4e-5) = ln(1.5625) = 0.44628710262841953.
    log_ratio = 0.44628710262841953
    assert barrier_potential(0.004, D_A) == pytest.approx(0.5 * log_ratio**2, rel=1e-14)
    assert barrier_potential(D_A, D_A) == 0.0
    assert barrier_potential(0.02, D_A) == 0.0
    assert barrier_potential(0.0, D_A) == np.inf
    # |u| = 2 / 6.4e-5 * 0.446287... * (0.01 - 0.004) = 31250 * 0.446287... * 0.006 = 83.6788...,
    # along (p_hat - p_o) / |p_hat - p_o| = (-1, 0, 0) for p_hat = (0, 0, 0.5), p_o = (0.005, 0, 0.5).
    u = repulsive_velocity([[0.0, 0.0, 0.5]], [[0.005, 0.0, 0.5]], d_a=D_A, d_o=D_O)
    np.testing.assert_allclose(u, [[-83.67883174282866, 0.0, 0.0]], rtol=1e-13)
    # Outside the influence distance the velocity is zero.
    np.testing.assert_array_equal(repulsive_velocity([[0.0, 0.0, 0.5]], [[0.0115, 0.0, 0.5]], d_a=D_A, d_o=D_O), 0.0)


def test_eq_omega_pivot_and_eq_v_c2_by_hand():
    # Same pair: lever p_hat - p_s = (0, 0, -0.5), |lever|^2 = 0.25,
    # omega = S(lever) u / 0.25 = (0, 0, -0.5) x (-83.6788, 0, 0) / 0.25 = (0, 167.3577, 0).
    # eq:v_c2 with k_c = 0.00025 and p_cs = (0, 0, 1):
    # linear = k_c (0, 0, 1) x omega = (-0.0418394, 0, 0), angular = k_c omega = (0, 0.0418394, 0).
    pairs = ray_obstacle_pairs([[0.0, 0.0, 1.0]], [[0.005, 0.0, 0.5]], np.zeros(3), d_a=D_A, d_o=D_O)
    np.testing.assert_allclose(stem_angular_velocities(pairs), [[0.0, 167.35766348565732, 0.0]], rtol=1e-12)
    twist = unveiling_velocity(pairs, k_c=0.00025)
    np.testing.assert_allclose(twist, [-0.04183941587141433, 0, 0, 0, 0.04183941587141433, 0], rtol=1e-12, atol=1e-18)


def test_end_branches_of_eq_nearest_give_no_angular_velocity():
    # Obstacles near the camera end and beyond the stem point only: eq:omega_pivot is zero.
    pairs = ray_obstacle_pairs(
        [[0.0, 0.0, 1.0]], [[0.002, 0.0, -0.003], [0.003, 0.004, 1.002]], np.zeros(3), d_a=D_A, d_o=D_O
    )
    assert len(pairs) == 2 and NEAREST_INTERIOR not in pairs.case
    np.testing.assert_array_equal(unveiling_velocity(pairs, k_c=1.0), np.zeros(6))


# ---------------------------------------------------------------- against the literal equations


@pytest.mark.parametrize("seed", range(12))
def test_kernel_equals_the_double_loop(seed):
    rng = np.random.default_rng(seed)
    stem, obstacles, camera = _random_scene(rng, int(rng.integers(1, 60)), int(rng.integers(1, 300)))
    if seed % 3 == 0:  # obstacles at and right next to the camera: near every ray
        obstacles = np.vstack([obstacles, camera, camera + rng.normal(scale=0.004, size=(4, 3))])
    if seed % 4 == 1:  # rays in every direction: no useful cone around them
        stem = camera + rng.normal(size=stem.shape)
    if seed % 4 == 2:  # duplicated obstacles give duplicated pairs
        obstacles = np.vstack([obstacles, obstacles[:50]])
    d_a, d_o = (0.02, 0.002) if seed % 2 else (D_A, D_O)
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=d_a, d_o=d_o)
    _assert_pairs_equal(pairs, _literal_pairs(stem, obstacles, camera, d_a, d_o))
    assert (pairs.surface_distance < d_a).all()


def _dense_pairs(stem, obstacles, camera, d_a, d_o):
    """eq:nearest for all n_S x n_O pairs at once (the double loop, vectorised)."""
    p_cs = (stem - camera)[:, None, :]
    p_co = (obstacles - camera)[None, :, :]
    projection = (p_cs * p_co).sum(-1) / np.linalg.norm(p_cs, axis=-1)
    length = np.linalg.norm(p_cs, axis=-1)
    nearest = np.where(
        (projection <= 0)[..., None],
        camera,
        np.where(
            (projection >= length)[..., None],
            stem[:, None, :],
            camera + (projection / length)[..., None] * p_cs,
        ),
    )
    r_hat = np.linalg.norm(nearest - obstacles[None], axis=-1) - d_o
    case = np.where(projection <= 0, NEAREST_AT_CAMERA, np.where(projection >= length, NEAREST_AT_STEM_POINT, 1))
    j, k = np.nonzero(r_hat < d_a)  # row-major: sorted by (j, k)
    return j, k, nearest[j, k], r_hat[j, k], case[j, k]


def _as_sorted_arrays(pairs):
    order = np.lexsort((pairs.obstacle_index, pairs.stem_index))
    return (
        pairs.stem_index[order],
        pairs.obstacle_index[order],
        pairs.nearest_points[order],
        pairs.surface_distance[order],
        pairs.case[order],
    )


def _assert_pairs_equal(pairs, expected):
    """``expected``: a dict (j, k) -> (p_hat, r_hat, case) or arrays sorted by (j, k)."""
    if isinstance(expected, dict):
        keys = sorted(expected)
        values = [expected[key] for key in keys]
        expected = (
            np.array([j for j, _ in keys], dtype=int),
            np.array([k for _, k in keys], dtype=int),
            np.array([value[0] for value in values]).reshape(-1, 3),
            np.array([value[1] for value in values]),
            np.array([value[2] for value in values]),
        )
    stem_index, obstacle_index, nearest, r_hat, case = _as_sorted_arrays(pairs)
    np.testing.assert_array_equal(stem_index, expected[0])
    np.testing.assert_array_equal(obstacle_index, expected[1])
    np.testing.assert_allclose(nearest, expected[2], rtol=0, atol=1e-13)
    np.testing.assert_allclose(r_hat, expected[3], rtol=0, atol=1e-13)
    np.testing.assert_array_equal(case, expected[4])


def test_kernel_equals_dense_evaluation_on_a_stem_with_many_ray_bundles():
    # 700 stem points (several ray bundles) along a bent line 0.3 m away, 4000 obstacles
    # scattered around the rays, part of them near the camera.
    rng = np.random.default_rng(42)
    camera = np.array([0.1, -0.2, 0.3])
    along = rng.uniform(0.0, 1.0, 700)[:, None]
    stem = (
        camera
        + [0.0, 0.0, 0.3]
        + np.where(along < 0.5, along * [0.0, 0.06, 0.0], [0, 0.03, 0] + (along - 0.5) * [0.04, 0.04, 0])
    )
    stem += rng.normal(scale=0.001, size=stem.shape)
    fractions = rng.uniform(-0.05, 1.1, 4000)[:, None]
    obstacles = (
        camera + fractions * (stem[rng.integers(0, 700, 4000)] - camera) + rng.normal(scale=0.01, size=(4000, 3))
    )
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=D_A, d_o=D_O)
    expected = _dense_pairs(stem, obstacles, camera, D_A, D_O)
    assert len(expected[0]) > 10_000
    _assert_pairs_equal(pairs, expected)


@pytest.mark.parametrize("bundle_size", [1, 3, 7])
def test_kernel_does_not_depend_on_the_bundle_size(monkeypatch, bundle_size):
    import harvest_qp.perception.unveiling as unveiling

    rng = np.random.default_rng(bundle_size)
    stem, obstacles, camera = _random_scene(rng, 40, 300)
    obstacles = np.vstack([obstacles, camera, camera + rng.normal(scale=0.004, size=(4, 3))])
    monkeypatch.setattr(unveiling, "_BUNDLE_SIZE", bundle_size)
    _assert_pairs_equal(ray_obstacle_pairs(stem, obstacles, camera), _dense_pairs(stem, obstacles, camera, D_A, D_O))


@pytest.mark.parametrize("seed", range(4))
def test_velocity_equals_the_literal_sums(seed):
    rng = np.random.default_rng(100 + seed)
    stem, obstacles, camera = _random_scene(rng, 40, 400)
    # Move some obstacles close to the rays so that many interior pairs exist.
    picks = rng.integers(0, 40, 150)
    fractions = rng.uniform(0.05, 0.95, 150)[:, None]
    obstacles[:150] = camera + fractions * (stem[picks] - camera) + rng.normal(scale=0.006, size=(150, 3))
    # The paper's potential is only defined for r_hat > 0: drop obstacles a ray goes through.
    touching = {k for (_, k), (_, r_hat, _) in _literal_pairs(stem, obstacles, camera, D_A, D_O).items() if r_hat <= 0}
    obstacles = np.delete(obstacles, sorted(touching), axis=0)
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=D_A, d_o=D_O)
    assert np.count_nonzero(pairs.case == NEAREST_INTERIOR) > 50
    expected = _literal_velocity(stem, obstacles, camera, D_A, D_O, k_c=0.00025)
    np.testing.assert_allclose(unveiling_velocity(pairs, k_c=0.00025), expected, rtol=1e-9)


def test_u_ij_is_minus_the_gradient_of_the_potential():
    rng = np.random.default_rng(21)
    obstacle = np.array([0.1, -0.2, 0.5])
    step = 1e-8
    for _ in range(20):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        nearest = obstacle + rng.uniform(D_O + 0.0003, D_O + D_A - 0.0003) * direction

        def potential(p):
            return barrier_potential(np.linalg.norm(p - obstacle) - D_O, D_A)

        gradient = np.array(
            [(potential(nearest + step * e) - potential(nearest - step * e)) / (2 * step) for e in np.eye(3)]
        )
        u = repulsive_velocity(nearest[None], obstacle[None], d_a=D_A, d_o=D_O)[0]
        np.testing.assert_allclose(u, -gradient, rtol=1e-5, atol=1e-6)


def test_linear_part_is_orthogonal_to_the_ray_of_a_single_stem_point():
    # S(p_cs) omega is orthogonal to p_cs: the camera keeps its distance to the stem point.
    rng = np.random.default_rng(4)
    camera, stem = np.zeros(3), np.array([[0.05, -0.02, 0.4]])
    obstacles = 0.5 * stem + rng.normal(scale=0.006, size=(30, 3))
    twist = unveiling_velocity(ray_obstacle_pairs(stem, obstacles, camera), k_c=0.00025)
    assert np.linalg.norm(twist[:3]) > 0
    assert twist[:3] @ stem[0] == pytest.approx(0.0, abs=1e-12 * np.linalg.norm(twist[:3]))


# ---------------------------------------------------------------- degenerate inputs


def test_no_stem_points_or_no_obstacles_give_zero_velocity():
    obstacles = np.random.default_rng(0).normal(size=(50, 3))
    for stem, obs in ((np.zeros((0, 3)), obstacles), ([[0.0, 0.0, 1.0]], np.zeros((0, 3)))):
        pairs = ray_obstacle_pairs(stem, obs, np.zeros(3))
        assert len(pairs) == 0
        np.testing.assert_array_equal(unveiling_velocity(pairs, k_c=0.00025), np.zeros(6))
        assert stem_angular_velocities(pairs).shape == (np.asarray(stem).reshape(-1, 3).shape[0], 3)


def test_duplicated_obstacles_double_the_velocity():
    rng = np.random.default_rng(9)
    stem, obstacles, camera = _random_scene(rng, 20, 200)
    obstacles[:80] = camera + 0.5 * (stem[rng.integers(0, 20, 80)] - camera) + rng.normal(scale=0.005, size=(80, 3))
    once = unveiling_velocity(ray_obstacle_pairs(stem, obstacles, camera), k_c=1.0)
    twice = unveiling_velocity(ray_obstacle_pairs(stem, np.vstack([obstacles, obstacles]), camera), k_c=1.0)
    assert np.abs(once).max() > 0
    np.testing.assert_allclose(twice, 2.0 * once, rtol=1e-12)


def test_ray_through_an_obstacle_gives_a_finite_velocity():
    # Obstacle centre on the ray (r_hat = -d_o) and one inside the obstacle sphere.
    stem, camera = np.array([[0.0, 0.0, 1.0]]), np.zeros(3)
    obstacles = np.array([[0.0, 0.0, 0.5], [0.0005, 0.0, 0.4]])
    pairs = ray_obstacle_pairs(stem, obstacles, camera)
    assert sorted(pairs.surface_distance.round(6).tolist()) == [-0.001, -0.0005]
    np.testing.assert_array_equal(pairs.away_directions[pairs.surface_distance == -0.001], 0.0)
    twist = unveiling_velocity(pairs, k_c=0.00025)
    assert np.isfinite(twist).all() and np.abs(twist).max() > 0


@pytest.mark.parametrize(
    ("stem", "obstacles", "camera", "kwargs", "message"),
    [
        (
            [[0.0, 0.0, 1.0]],
            [[0.0, np.nan, 0.0]],
            [0.0, 0.0, 0.0],
            {},
            "obstacle_points must contain only finite",
        ),
        (
            [[0.0, 0.0, np.inf]],
            [[0.0, 0.0, 0.0]],
            [0.0, 0.0, 0.0],
            {},
            "stem_points must contain only finite",
        ),
        ([[0.0, 0.0, 1.0]], [[0.0, 0.0]], [0.0, 0.0, 0.0], {}, r"obstacle_points must have shape \(n, 3\)"),
        ([[0.0, 0.0, 1.0]], [[0.0, 0.0, 0.0]], [0.0, 0.0], {}, r"camera_position must have shape \(3,\)"),
        ([[0.0, 0.0, 1.0], [1.0, 2.0, 3.0]], [[0.0, 0.0, 0.0]], [1.0, 2.0, 3.0], {}, "row 1 coincides"),
        (
            [[0.0, 0.0, 1.0]],
            [[0.0, 0.0, 0.0]],
            [0.0, 0.0, 0.0],
            {"d_a": 0.0},
            "d_a must be finite and > 0",
        ),
        (
            [[0.0, 0.0, 1.0]],
            [[0.0, 0.0, 0.0]],
            [0.0, 0.0, 0.0],
            {"d_o": -1e-3},
            "d_o must be finite and >= 0",
        ),
    ],
)
def test_invalid_kernel_input_raises(stem, obstacles, camera, kwargs, message):
    with pytest.raises(InvalidInputError, match=message):
        ray_obstacle_pairs(stem, obstacles, camera, **kwargs)


def test_invalid_velocity_arguments_raise():
    pairs = ray_obstacle_pairs([[0.0, 0.0, 1.0]], [[0.005, 0.0, 0.5]], np.zeros(3))
    with pytest.raises(InvalidInputError, match="k_c must be finite and > 0"):
        unveiling_velocity(pairs, k_c=-1.0)
    with pytest.raises(InvalidInputError, match=r"same shape \(P, 3\)"):
        repulsive_velocity(np.zeros((2, 3)), np.zeros((3, 3)), d_a=D_A, d_o=D_O)
