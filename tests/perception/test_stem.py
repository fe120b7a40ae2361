"""Two-segment stem model and stem base p_sb (subsec:scePC_proc, stem_basend)."""

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.stem import fit_stem
from harvest_qp.perception.synthetic import bent_stem


def _unit(vector):
    vector = np.asarray(vector, dtype=float)
    return vector / np.linalg.norm(vector)


def _random_bent_stem(rng, *, bend_degrees, bend_fraction, n_points):
    """A 5-7 cm stem with a random base and orientation, 1 mm noise; returns points, true
    base and a gripper 5 cm past the crop end."""
    length = rng.uniform(0.05, 0.07)
    top_direction = _unit(rng.normal(size=3))
    perpendicular = _unit(np.cross(top_direction, rng.normal(size=3)))
    bend = np.deg2rad(bend_degrees)
    bottom_direction = np.cos(bend) * top_direction + np.sin(bend) * perpendicular
    base = rng.uniform(-1.0, 1.0, 3)
    top_length, bottom_length = bend_fraction * length, (1.0 - bend_fraction) * length
    points = bent_stem(
        base,
        top_direction,
        bottom_direction,
        top_length,
        bottom_length,
        n_points=n_points,
        noise=0.001,
        rng=rng,
    )
    crop_end = base + top_length * top_direction + bottom_length * bottom_direction
    return points, base, crop_end + 0.05 * bottom_direction, length


@pytest.mark.parametrize("seed", range(40))
def test_stem_base_within_3_mm_on_bent_noisy_stems(seed):
    rng = np.random.default_rng(seed)
    # Bends up to 45 degrees anywhere in the middle fifth, or up to 30 degrees from 30 % to
    # 70 % of the length; 300-2000 points as in a 283x160 to 848x480 frame.
    if seed % 2:
        bend_degrees, bend_fraction = rng.uniform(0.0, 45.0), rng.uniform(0.4, 0.6)
    else:
        bend_degrees, bend_fraction = rng.uniform(0.0, 30.0), rng.uniform(0.3, 0.7)
    points, true_base, gripper, true_length = _random_bent_stem(
        rng, bend_degrees=bend_degrees, bend_fraction=bend_fraction, n_points=int(rng.integers(300, 2000))
    )
    model = fit_stem(points, gripper)
    assert model.valid, model.reason
    assert np.linalg.norm(model.base - true_base) < 0.003
    assert model.length == pytest.approx(true_length, abs=0.004)


def test_stem_base_formula_and_naming_on_an_exact_two_segment_stem():
    # Noise-free: top segment from (0,0,0) to (0,0,-0.03), bottom to (0.03,0,-0.03);
    # the gripper below the bottom end makes the first segment "top".
    rng = np.random.default_rng(0)
    points = bent_stem([0, 0, 0], [0, 0, -1], [1, 0, 0], 0.03, 0.03, n_points=4000, radius=0.0, noise=0.0, rng=rng)
    model = fit_stem(points, gripper_position=[0.08, 0.0, -0.03])
    assert model.valid
    top, bottom = model.top, model.bottom
    # k-means splits at the bend; the segments are the two halves of the L.
    np.testing.assert_allclose(top.centroid, [0.0, 0.0, -0.015], atol=5e-4)
    np.testing.assert_allclose(bottom.centroid, [0.015, 0.0, -0.03], atol=5e-4)
    # n_st points from the branch towards the bottom cluster, n_sb away from the top one.
    np.testing.assert_allclose(top.direction, [0.0, 0.0, -1.0], atol=1e-3)
    np.testing.assert_allclose(bottom.direction, [1.0, 0.0, 0.0], atol=1e-3)
    assert top.length == pytest.approx(0.03, abs=1e-3)
    assert bottom.length == pytest.approx(0.03, abs=1e-3)
    # stem_basend: p_sb = mean(T) - (l_t / 2) n_st.
    np.testing.assert_allclose(model.base, top.centroid - 0.5 * top.length * top.direction, atol=1e-15)
    np.testing.assert_allclose(model.base, [0.0, 0.0, 0.0], atol=1e-3)
    assert model.length == pytest.approx(0.06, abs=2e-3)
    assert np.count_nonzero(model.top_mask) == pytest.approx(2000, abs=150)
    assert (points[model.top_mask][:, 0] < 0.005).all()


def test_top_is_the_cluster_further_from_the_gripper():
    rng = np.random.default_rng(1)
    points = bent_stem([0, 0, 0], [0, 0, -1], [1, 0, 0], 0.03, 0.03, n_points=800, rng=rng)
    near_bottom_end = fit_stem(points, gripper_position=[0.08, 0.0, -0.03])
    near_top_end = fit_stem(points, gripper_position=[0.0, 0.0, 0.05])
    np.testing.assert_array_equal(near_bottom_end.top_mask, ~near_top_end.top_mask)
    # With the gripper at the other end, the base is the other end of the stem.
    np.testing.assert_allclose(near_bottom_end.base, [0.0, 0.0, 0.0], atol=0.003)
    np.testing.assert_allclose(near_top_end.base, [0.03, 0.0, -0.03], atol=0.003)


def test_straight_collinear_stem_is_valid():
    points = np.column_stack((np.zeros(50), np.zeros(50), np.linspace(0.0, -0.06, 50)))
    model = fit_stem(points, gripper_position=[0.0, 0.0, -0.1])
    assert model.valid, model.reason
    np.testing.assert_allclose(model.base, [0.0, 0.0, 0.0], atol=0.002)
    assert model.length == pytest.approx(0.06, abs=0.003)


def test_duplicated_points_give_the_same_model():
    rng = np.random.default_rng(2)
    points = bent_stem([0, 0, 0], [0, 0.3, -1], [0, -0.2, -1], 0.03, 0.03, n_points=500, rng=rng)
    once = fit_stem(points, [0.0, 0.0, -0.1])
    twice = fit_stem(np.vstack([points, points]), [0.0, 0.0, -0.1])
    np.testing.assert_allclose(twice.base, once.base, atol=1e-12)
    assert twice.length == pytest.approx(once.length, abs=1e-12)


@pytest.mark.parametrize(
    ("points", "reason"),
    [
        (np.zeros((0, 3)), "too few stem points: 0 < min_points=10"),
        (np.array([[0.1, 0.2, 0.3]]), "too few stem points: 1 < min_points=10"),
        (np.tile([[0.1, 0.2, 0.3]], (50, 1)), "span less than min_length"),
        (np.random.default_rng(3).normal(scale=0.02, size=(300, 3)), "not line-like"),
    ],
    ids=["empty", "one point", "coincident duplicates", "noise blob"],
)
def test_degenerate_stems_give_an_invalid_model_with_a_reason(points, reason):
    model = fit_stem(points, gripper_position=[0.0, 0.0, -0.2])
    assert not model.valid
    assert reason in model.reason
    assert model.base is None and model.top is None and model.bottom is None
    assert np.isnan(model.length)
    assert model.top_mask.shape == (points.shape[0],)


def test_two_tight_clumps_are_not_a_stem():
    rng = np.random.default_rng(4)
    clumps = np.vstack([rng.normal(scale=1e-4, size=(30, 3)), [0.05, 0, 0] + rng.normal(scale=1e-4, size=(30, 3))])
    model = fit_stem(clumps, gripper_position=[0.2, 0.0, 0.0])
    assert not model.valid
    assert "clump" in model.reason


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"stem_points": np.array([[0.0, 0.0, np.nan]] * 20)}, "NaN or inf"),
        ({"stem_points": np.zeros((20, 2))}, r"stem_points must have shape \(n, 3\)"),
        ({"gripper_position": [0.0, 0.0]}, r"gripper_position must have shape \(3,\)"),
        ({"min_points": 1}, "min_points must be an integer >= 2"),
        ({"max_spread_ratio": -1.0}, "max_spread_ratio must be finite and > 0"),
        ({"max_residual": 0.0}, "max_residual must be finite and > 0"),
        ({"base_estimator": "mean"}, "base_estimator must be 'extent' or 'paper'"),
        ({"end_quantile": 0.3}, r"end_quantile must be in \[0, 0.25\)"),
        ({"camera_position": [0.0, np.inf, 0.0]}, "camera_position must be finite"),
        ({"non_stem_points": np.zeros((3, 4))}, r"non_stem_points must have shape \(n, 3\)"),
        ({"stem_radius": -0.001}, "stem_radius must be finite and >= 0"),
    ],
)
def test_invalid_arguments_raise(kwargs, message):
    arguments = {"stem_points": np.zeros((20, 3)), "gripper_position": [0.0, 0.0, 1.0], **kwargs}
    with pytest.raises(InvalidInputError, match=message):
        fit_stem(**arguments)


def test_quality_without_a_camera_leaves_the_hidden_base_unknown():
    """Without camera_position there is no near-surface correction (radius 0) and no
    visibility test: base_hidden is None and the model is not trusted."""
    rng = np.random.default_rng(7)
    points = bent_stem([0, 0, 0], [0, 0, -1], [0.2, 0, -1], 0.03, 0.03, n_points=400, noise=0.0, rng=rng)
    model = fit_stem(points, [0.0, 0.0, -0.1])
    assert model.valid
    assert model.quality.base_hidden is None and model.quality.radius == 0.0
    assert not model.trusted()
    assert model.quality.n_points == 400
    assert 0.0 < model.quality.base_uncertainty < 0.003


def test_near_surface_correction_on_a_half_cylinder_by_hand():
    """Only the near half of a cylinder of radius r is seen; its points lie pi r / 4 in front
    of the axis on average (hand value for points spread uniformly across the image).  With
    the camera given, p_sb must land on the axis, not pi r / 4 (2.4 mm for r = 3 mm) in front."""
    radius, camera = 0.003, np.array([0.4, 0.0, -0.03])
    lateral = np.linspace(-radius, radius, 9)[1:-1]
    heights = np.linspace(0.0, -0.06, 60)
    y, z = np.meshgrid(lateral, heights)
    x = np.sqrt(radius**2 - y**2)  # the near (camera, +x) side of a vertical cylinder on the z axis
    points = np.column_stack((x.ravel(), y.ravel(), z.ravel()))
    corrected = fit_stem(points, [0.0, 0.0, -0.1], camera_position=camera, stem_radius=radius)
    plain = fit_stem(points, [0.0, 0.0, -0.1])
    assert plain.base[0] == pytest.approx(np.mean(x), abs=2e-4)  # in front of the axis
    assert abs(corrected.base[0]) < 0.0006
    assert abs(corrected.base[2]) < 0.0015


def test_distinct_rows_are_numpys_unique_rows():
    """``_distinct_rows`` (a column lexsort) keeps the same rows as ``np.unique(axis=0)`` (the oracle).

    Clouds with duplicated points (a point cloud repeats a pixel's point) and rows that
    differ in one coordinate only, by one ulp, or by the sign of a zero (numbers: equal).
    Catches a lexsort over the wrong column order (adjacent duplicates missed) or a
    byte-wise comparison (0.0 and -0.0 kept apart).
    """
    from harvest_qp.perception.stem import _distinct_rows

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 300):
        base = rng.normal(size=(n, 3))
        rows = base[rng.integers(0, n, 3 * n)].copy()
        rows[::5, 1] = np.nextafter(rows[::5, 1], np.inf)
        rows[::7, 2] = base[0, 2]
        rows[::11, 0] = 0.0
        rows[::13, 0] = -0.0
        expected = np.unique(rows, axis=0)
        got = _distinct_rows(rows)
        assert got.shape == expected.shape
        key = lambda a: np.lexsort((a[:, 2], a[:, 1], a[:, 0]))  # noqa: E731
        np.testing.assert_array_equal(got[key(got)], expected[key(expected)])
