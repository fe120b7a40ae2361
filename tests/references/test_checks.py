"""The laws' argument checks and row-wise cross product (references/_checks.py).

Oracles: numpy's ``np.cross``, and poses built by hand to be (or not be) homogeneous."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import as_pose, cross_rows
from tests.helpers import random_pose


def test_cross_rows_is_np_cross():
    """Row-wise cross products of the unveiling law (eq:omega_pivot, eq:v_c2). Catches: a component's
    operands swapped, an empty (0, 3) input mishandled."""
    rng = np.random.default_rng(6)
    a, b = rng.normal(size=(500, 3)) * rng.uniform(1e-3, 1e3, size=(500, 1)), rng.normal(size=(500, 3))
    np.testing.assert_allclose(cross_rows(a, b), np.cross(a, b), rtol=1e-15, atol=0)
    assert cross_rows(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)


@pytest.mark.parametrize("as_list", [False, True])
def test_as_pose_accepts_poses_and_refuses_the_rest(as_list):
    """A float64 array (the loop's fast path) and a nested list (the numpy path) give the same
    verdicts: random rigid poses pass; a scaled rotation, a sheared one, a NaN or inf anywhere,
    a wrong last row fail, naming the argument. Catches: a test that skips the translation's
    finiteness, or the off-diagonal terms of R^T R."""
    rng = np.random.default_rng(7)
    for _ in range(50):
        pose = random_pose(rng)
        checked = as_pose(pose.tolist() if as_list else pose, "pose")
        np.testing.assert_array_equal(checked, pose)
    bad = []
    pose = random_pose(rng)
    scaled = pose.copy()
    scaled[:3, :3] *= 1.001
    sheared = pose.copy()
    sheared[0, 1] += 1e-3
    last = pose.copy()
    last[3, 0] = 1e-6
    bad += [scaled, sheared, last]
    for i in range(4):
        for j in range(4):
            for value in (np.nan, np.inf):
                broken = pose.copy()
                broken[i, j] = value
                bad.append(broken)
    for broken in bad:
        with pytest.raises(InvalidInputError, match="camera_pose"):
            as_pose(broken.tolist() if as_list else broken, "camera_pose")
