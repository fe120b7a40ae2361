"""Point-cloud classification (Table table:PCs)."""

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception.classify import obstacles_near_stem_base, red_stem_mask, split_scene


def test_split_scene_separates_stem_and_the_rest():
    points = np.arange(15, dtype=float).reshape(5, 3)
    split = split_scene(points, [True, False, True, False, False])
    np.testing.assert_array_equal(split.stem, points[[0, 2]])
    np.testing.assert_array_equal(split.non_stem, points[[1, 3, 4]])
    assert split.n_dropped == 0


def test_split_scene_drops_non_finite_rows_and_counts_them():
    points = np.array([[0, 0, 1], [np.nan, 0, 1], [0, 1, 1], [0, np.inf, 1], [1, 1, 1.0]])
    split = split_scene(points, np.array([1, 1, 0, 0, 0]))  # 0/1 labels are accepted
    np.testing.assert_array_equal(split.stem, [[0, 0, 1]])
    np.testing.assert_array_equal(split.non_stem, [[0, 1, 1], [1, 1, 1]])
    assert split.n_dropped == 2


def test_split_scene_of_an_empty_cloud():
    split = split_scene(np.zeros((0, 3)), np.zeros(0, dtype=bool))
    assert split.stem.shape == (0, 3) and split.non_stem.shape == (0, 3) and split.n_dropped == 0


@pytest.mark.parametrize(
    ("points", "mask", "message"),
    [
        (np.zeros((4, 2)), np.zeros(4, bool), r"points must have shape \(n, 3\), got shape \(4, 2\)"),
        (np.zeros((4, 3)), np.zeros(3, bool), r"stem_mask must have shape \(4,\)"),
        (np.zeros((2, 3)), np.array([0.5, 1.0]), "stem_mask must be boolean"),
        (np.zeros((2, 3)), np.array([2, 0]), "stem_mask must be boolean"),
        ([["a", "b", "c"]], np.zeros(1, bool), "points must be numeric"),
    ],
)
def test_split_scene_rejects_bad_input(points, mask, message):
    with pytest.raises(InvalidInputError, match=message):
        split_scene(points, mask)


def test_obstacles_are_the_non_stem_points_strictly_inside_the_sphere():
    base = np.array([1.0, 2.0, 3.0])
    non_stem = base + np.array(
        [
            [0.0, 0.0, 0.0],
            [0.05, 0.0, 0.0],  # inside r_o = 0.06
            [0.0, -0.0599, 0.0],  # inside
            [0.0, 0.0, 0.06],  # on the sphere: outside
            [0.04, 0.04, 0.04],  # 0.069 away: outside
        ]
    )
    inside = obstacles_near_stem_base(non_stem, base, 0.06)
    np.testing.assert_allclose(inside, non_stem[:3])


def test_obstacles_near_stem_base_rejects_bad_input():
    with pytest.raises(InvalidInputError, match="radius must be finite and > 0"):
        obstacles_near_stem_base(np.zeros((3, 3)), np.zeros(3), 0.0)
    with pytest.raises(InvalidInputError, match="NaN or inf"):
        obstacles_near_stem_base(np.array([[np.nan, 0, 0]]), np.zeros(3), 0.1)
    with pytest.raises(InvalidInputError, match=r"stem_base must have shape \(3,\)"):
        obstacles_near_stem_base(np.zeros((3, 3)), np.zeros(2), 0.1)


def test_red_stem_mask_on_8_bit_and_float_colours():
    colours = np.array(
        [
            [200, 30, 40],  # red stem
            [120, 10, 10],  # dark red stem
            [60, 10, 10],  # too dark (red < 0.35)
            [40, 160, 50],  # green leaf
            [230, 220, 210],  # white
            [150, 90, 40],  # brown branch: red share 0.54
            [140, 100, 100],  # pinkish grey: red share 0.41
        ],
        dtype=np.uint8,
    )
    expected = [True, True, False, False, False, False, False]
    np.testing.assert_array_equal(red_stem_mask(colours), expected)
    np.testing.assert_array_equal(red_stem_mask(colours / 255.0), expected)
    # A looser share threshold lets the brown branch through.
    assert red_stem_mask(colours, min_red_share=0.5)[5]


def test_red_stem_mask_rejects_out_of_range_colours():
    with pytest.raises(InvalidInputError, match=r"colors must be integers in \[0, 255\] or floats in \[0, 1\]"):
        red_stem_mask(np.array([[1.5, 0.0, 0.0]]))
    with pytest.raises(InvalidInputError, match=r"colors must have shape \(n, 3\)"):
        red_stem_mask(np.zeros((3, 4)))
