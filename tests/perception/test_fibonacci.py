"""Spherical Fibonacci lattice and its O(1) inverse mapping (subsec:scePC_proc)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.fibonacci import GOLDEN_RATIO, fibonacci_sphere, nearest_fibonacci_index


def _unit_rows(vectors):
    return vectors / np.linalg.norm(vectors, axis=1)[:, None]


def _hard_directions(rng, n):
    """Random unit vectors plus the cases that break naive inverse mappings: both poles
    exactly, points within 1e-16..1e-1 of each pole in 1 - |z|, the equator, and the
    lattice points themselves (mirrored too)."""
    random = _unit_rows(rng.normal(size=(20_000, 3)))
    near_pole = []
    for sign in (1.0, -1.0):
        gap = 10.0 ** rng.uniform(-16.0, -1.0, 2_000)  # 1 - |z|
        azimuth = rng.uniform(0.0, 2.0 * np.pi, gap.size)
        radius = np.sqrt(gap * (2.0 - gap))
        near_pole.append(np.column_stack((radius * np.cos(azimuth), radius * np.sin(azimuth), sign * (1.0 - gap))))
        near_pole.append([[0.0, 0.0, sign]])
    azimuth = rng.uniform(0.0, 2.0 * np.pi, 2_000)
    equator = np.column_stack((np.cos(azimuth), np.sin(azimuth), np.zeros_like(azimuth)))
    lattice = fibonacci_sphere(n)[rng.choice(n, size=min(n, 2_000), replace=False)]
    return np.vstack([random, *near_pole, equator, lattice, -lattice])


def test_lattice_matches_the_formula_written_out():
    # n = 4: z_i = 1 - (2i + 1)/4 = 0.75, 0.25, -0.25, -0.75; phi_i = 2 pi frac(i (Phi - 1)).
    points = fibonacci_sphere(4)
    z = np.array([0.75, 0.25, -0.25, -0.75])
    phi = 2.0 * np.pi * np.array([0.0, 0.6180339887498949, 0.2360679774997898, 0.8541019662496847])
    radius = np.sqrt(1.0 - z**2)
    expected = np.column_stack((radius * np.cos(phi), radius * np.sin(phi), z))
    np.testing.assert_allclose(points, expected, atol=1e-12)
    assert GOLDEN_RATIO - 1.0 == pytest.approx(0.6180339887498949)


def test_lattice_points_are_unit_vectors_and_cover_the_sphere_evenly():
    points = fibonacci_sphere(500)
    np.testing.assert_allclose(np.linalg.norm(points, axis=1), 1.0, atol=1e-12)
    # Equal-area lattice: each hemisphere and each octant holds its share of points.
    assert np.count_nonzero(points[:, 2] > 0) == 250
    octant_counts = np.bincount(((points > 0) * [1, 2, 4]).sum(axis=1), minlength=8)
    assert octant_counts.min() >= 55 and octant_counts.max() <= 70


@pytest.mark.parametrize("n", [10, 100, 500, 10_000, 1_000_000])
def test_inverse_mapping_equals_kdtree_oracle(n):
    rng = np.random.default_rng(n)
    directions = _hard_directions(rng, n)
    lattice = fibonacci_sphere(n)
    oracle_distance, oracle_index = cKDTree(lattice).query(directions)
    index = nearest_fibonacci_index(directions, n)
    assert index.shape == (directions.shape[0],)
    assert index.min() >= 0 and index.max() <= n - 1
    # The same point, or (on an exact tie) one at the same distance.
    distance = np.linalg.norm(lattice[index] - directions, axis=1)
    mismatched = index != oracle_index
    np.testing.assert_allclose(distance[mismatched], oracle_distance[mismatched], rtol=0, atol=1e-12)
    assert np.count_nonzero(mismatched) <= 2


@pytest.mark.parametrize("n", [1, 2, 3, 5])
def test_inverse_mapping_on_tiny_lattices(n):
    rng = np.random.default_rng(7)
    directions = _unit_rows(rng.normal(size=(5_000, 3)))
    lattice = fibonacci_sphere(n)
    _, oracle_index = cKDTree(lattice).query(directions)
    np.testing.assert_array_equal(nearest_fibonacci_index(directions, n), oracle_index)


def test_lattice_points_map_to_themselves():
    n = 777
    np.testing.assert_array_equal(nearest_fibonacci_index(fibonacci_sphere(n), n), np.arange(n))


def test_non_unit_directions_are_normalised():
    directions = _unit_rows(np.random.default_rng(1).normal(size=(100, 3)))
    scaled = directions * np.random.default_rng(2).uniform(0.01, 100.0, (100, 1))
    np.testing.assert_array_equal(nearest_fibonacci_index(scaled, 500), nearest_fibonacci_index(directions, 500))


def test_empty_input_gives_empty_indices():
    assert nearest_fibonacci_index(np.zeros((0, 3)), 500).shape == (0,)


@pytest.mark.parametrize(
    ("points", "n", "message"),
    [
        (np.zeros((4, 2)), 10, r"points must have shape \(n, 3\)"),
        (np.array([[0.0, 0.0, np.nan]]), 10, "NaN or inf"),
        (np.array([[0.0, np.inf, 1.0]]), 10, "NaN or inf"),
        (np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), 10, "row 1 is the zero vector"),
        (np.array([[1.0, 0.0, 0.0]]), 0, "n must be an integer >= 1"),
        (np.array([[1.0, 0.0, 0.0]]), 2.5, "n must be an integer >= 1"),
    ],
)
def test_invalid_input_is_rejected_with_a_clear_message(points, n, message):
    with pytest.raises(InvalidInputError, match=message):
        nearest_fibonacci_index(points, n)


def test_fibonacci_sphere_rejects_bad_sizes():
    with pytest.raises(InvalidInputError, match="n must be an integer >= 1"):
        fibonacci_sphere(0)
    with pytest.raises(InvalidInputError, match="n must be an integer >= 1"):
        fibonacci_sphere(True)
