"""The controller's compiled cloud split equals numpy's boolean indexing, bit for bit.

``_perceive`` splits each camera frame with numba kernels (``_scan_cloud``: stem count and
finiteness in one pass; ``_gather_labelled``: the rows of one label, or of every other label,
thinned by a stride) and hands the unveiling law only the non-stem rows it uses. Oracles:
numpy's boolean indexing and ``np.isfinite`` on the same arrays, and the unveiling law's
checked public ``observe`` on the numpy split of the whole cloud.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from harvest_qp.interface import OBSTACLE, ROBOT, STEM, PointCloud
from harvest_qp.loop.controller import (
    HarvestController,
    Phase,
    _count_label,
    _gather_labelled,
    _labelled_rows,
    _LabelRows,
    _scan_cloud,
    _split_labelled,
)
from harvest_qp.loop.settings import check_settings


def _bits(values) -> list[int]:
    return np.asarray(values, dtype=np.float64).reshape(-1).view(np.int64).tolist()


def _cloud_arrays(rng: np.random.Generator, n: int, stem_fraction: float = 0.1):
    points = rng.normal(size=(n, 3))
    points[::97] = -0.0  # signed zeros must survive the copy
    u = rng.random(n)
    labels = np.where(u < stem_fraction, STEM, np.where(u < 0.7, OBSTACLE, ROBOT)).astype(np.int8)
    return points, labels


@pytest.mark.parametrize("n", [0, 1, 7, 5003])
def test_scan_and_gather_equal_boolean_indexing(n):
    """Catches: a stride that skips the first matching row or counts all rows instead of the
    matching ones (``[::k]`` of the matches), a label test inverted, rows copied partly
    (two of three coordinates), a stem count off by the robot rows."""
    rng = np.random.default_rng(n + 3)
    points, labels = _cloud_arrays(rng, n)
    n_stem, finite = _scan_cloud(points, labels, STEM)
    assert n_stem == int(np.count_nonzero(labels == STEM)) and finite
    for label in (STEM, OBSTACLE, ROBOT):
        for equal in (True, False):
            mask = labels == label if equal else labels != label
            for stride in (1, 2, 5, 1000):
                expected = points[mask][::stride]
                got = _labelled_rows(points, labels, label, equal=equal, stride=stride)
                assert got.shape == expected.shape and _bits(got) == _bits(expected)
                count = len(range(0, int(mask.sum()), stride))
                assert _bits(_gather_labelled(points, labels, label, equal, stride, count)) == _bits(expected)


@pytest.mark.parametrize("n", [0, 1, 5003])
def test_split_equals_boolean_indexing(n):
    """``_split_labelled`` gives the stem rows and every k-th other row in one pass. Catches:
    the stride counted over all rows instead of the non-stem ones, the first non-stem row
    skipped, stem rows counted into the stride."""
    rng = np.random.default_rng(n + 30)
    points, labels = _cloud_arrays(rng, n, stem_fraction=0.3)
    is_stem = labels == STEM
    for stride in (1, 2, 7):
        n_other = len(range(0, int((~is_stem).sum()), stride))
        stem, other, finite = _split_labelled(points, labels, STEM, int(is_stem.sum()), stride, n_other)
        assert finite and _count_label(labels, STEM) == int(is_stem.sum())
        assert _bits(stem) == _bits(points[is_stem]) and stem.shape == (int(is_stem.sum()), 3)
        assert _bits(other) == _bits(points[~is_stem][::stride]) and other.shape == (n_other, 3)
    if n:
        with pytest.raises(ValueError, match="row counts"):
            _split_labelled(points, labels, STEM, int(is_stem.sum()) + 1, 1, int((~is_stem).sum()))


def test_labelled_rows_fall_back_on_other_layouts():
    """float32 points, Fortran order, strided rows and int64 labels go through numpy's own
    indexing; the values are the same. Catches: the kernel called on a layout it cannot read."""
    rng = np.random.default_rng(5)
    points, labels = _cloud_arrays(rng, 801)
    for p, lab in ((points.astype(np.float32), labels), (np.asfortranarray(points), labels),
                   (points[::2], labels[::2]), (points, labels.astype(np.int64))):
        expected = p[lab != STEM][::3]
        np.testing.assert_array_equal(_labelled_rows(p, lab, STEM, equal=False, stride=3), expected)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("where", [(0, 0), (400, 1), (800, 2)])
def test_scan_finds_every_non_finite_coordinate(bad, where):
    """Catches: only the first coordinate (or only stem rows) checked, the check stopping the
    stem count once a bad point is found."""
    rng = np.random.default_rng(9)
    points, labels = _cloud_arrays(rng, 801)
    points[where] = bad
    n_stem, finite = _scan_cloud(points, labels, STEM)
    assert finite == bool(np.isfinite(points).all()) is False
    assert n_stem == int(np.count_nonzero(labels == STEM))
    n_other = int(np.count_nonzero(labels != STEM))
    for stride in (1, 3):  # the split checks every row, also those it does not gather
        *_, finite = _split_labelled(points, labels, STEM, n_stem, stride, len(range(0, n_other, stride)))
        assert finite is False


def test_label_rows_gather_once_on_first_use():
    """Catches: the lazy rows re-gathered from a later frame, or the given rows ignored."""
    rng = np.random.default_rng(12)
    points, labels = _cloud_arrays(rng, 2003)
    rows = _LabelRows(points, labels, OBSTACLE)
    assert rows._all is None
    assert rows.shape == (int(np.count_nonzero(labels == OBSTACLE)), 3)
    first = rows[::1]
    assert rows[::1] is not first and np.shares_memory(rows[::1], first)
    np.testing.assert_array_equal(rows[::4], points[labels == OBSTACLE][::4])
    given = np.zeros((3, 3))
    assert _LabelRows(points, labels, STEM, equal=False, rows=given)[::1].base is given


def _cloud(points, labels, camera_position, t):
    pose = np.eye(4)
    pose[:3, 3] = camera_position
    n = len(points)
    return PointCloud(points=points, labels=labels, colors=np.zeros((n, 3), np.uint8), camera_pose=pose,
                      timestamp=t, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(8, 8))


@pytest.mark.parametrize("n_obstacles", [300, 4000])
def test_perceive_gives_the_unveiling_law_the_checked_result(n_obstacles):
    """The loop's unveiling target (thinned non-stem rows gathered by the kernel) equals the
    checked ``Unveiling.observe`` on numpy's split of the same cloud, bit for bit, in the
    paper mode with and without thinning (``max_obstacle_points`` 1000 here) and in the
    predicted mode. Catches: a thinning stride other than the law's, the thinned rows used
    in the predicted mode, the frame keeping thinned rows as its non-stem cloud."""
    settings = check_settings({})
    c = HarvestController(settings)
    rng = np.random.default_rng(n_obstacles)
    camera = np.array([0.6, 0.0, 0.4])
    for n_stem in (40, 3):  # the paper mode, then (fewer than min_stem_points) the predicted mode
        stem = np.column_stack((0.02 * rng.normal(size=n_stem), 0.02 * rng.normal(size=n_stem),
                                0.5 + 0.1 * rng.random(n_stem)))
        leaves = np.column_stack((0.3 + 0.05 * rng.normal(size=n_obstacles), 0.05 * rng.normal(size=n_obstacles),
                                  0.55 + 0.05 * rng.normal(size=n_obstacles)))
        robot = rng.normal(size=(50, 3))
        points = np.vstack((leaves[: n_obstacles // 2], stem, robot, leaves[n_obstacles // 2:]))
        labels = np.array([OBSTACLE] * (n_obstacles // 2) + [STEM] * n_stem + [ROBOT] * 50
                          + [OBSTACLE] * (n_obstacles - n_obstacles // 2), dtype=np.int8)
        order = rng.permutation(len(points))
        points, labels = np.ascontiguousarray(points[order]), labels[order]
        T_g = np.eye(4)
        T_g[:3, 3] = (0.0, 0.0, 0.3)
        loop_law = c.unveiling
        loop_law.max_obstacle_points = 1000
        c.state = type(c.state)()
        c.reaching.reset(np.array([0.0, 0.0, 0.55]))
        loop_law.reset()
        oracle = copy.deepcopy(loop_law)
        c._perceive(_cloud(points, labels, camera, 0.1), T_g)
        oracle.observe(camera, points[labels == STEM], points[labels != STEM],
                       predicted_stem_points=c._predicted_stem(T_g), roi_centre=c.reaching.roi_centre, timestamp=0.1)
        assert loop_law.mode == oracle.mode == ("paper" if n_stem == 40 else "predicted")
        assert loop_law.n_pairs == oracle.n_pairs
        assert (loop_law.n_pairs > 0) == (n_stem == 40)  # the law acts: pairs found in the paper mode
        assert _bits(loop_law.raw) == _bits(oracle.raw)
        assert c.state.phase == Phase.APPROACH
        np.testing.assert_array_equal(c.state.frame.non_stem, points[labels != STEM])
        np.testing.assert_array_equal(c.state.frame.obstacles, points[labels == OBSTACLE])
        np.testing.assert_array_equal(c.state.frame.stem, points[labels == STEM])


def test_gather_with_a_wrong_count_raises_instead_of_writing_past_the_end():
    """Catches: the kernel trusting its caller's count (a count too small wrote past the array)."""
    points = np.zeros((10, 3))
    labels = np.full(10, STEM, np.int8)
    for count in (3, 11):
        with pytest.raises(ValueError, match="row count"):
            _gather_labelled(points, labels, STEM, True, 1, count)


def test_a_nan_in_a_row_the_thinned_law_skips_still_raises():
    """Paper mode with thinning (stride 5): a NaN in a non-stem row the law does not use
    still raises the package's error naming the obstacle points, as the checked observe of
    the whole cloud did. Catches: the finiteness checked on the gathered rows only."""
    from harvest_qp.exceptions import InvalidInputError

    c = HarvestController(check_settings({}))
    c.unveiling.max_obstacle_points = 100
    rng = np.random.default_rng(31)
    n_stem, n_other = 40, 500
    points = np.vstack((rng.normal(size=(n_stem, 3)), rng.normal(size=(n_other, 3))))
    labels = np.array([STEM] * n_stem + [OBSTACLE] * n_other, dtype=np.int8)
    points[n_stem + 1, 2] = np.nan  # the second non-stem row: not in [::5]
    c.reaching.reset(np.zeros(3))
    with pytest.raises(InvalidInputError, match="obstacle_points"):
        c._perceive(_cloud(points, labels, np.array([0.6, 0.0, 0.4]), 0.1), np.eye(4))
