"""The keep-out term (references/keep_out.py) against hand values."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import keep_out_velocity


def test_keep_out_pushes_out_only_below_the_minimum_distance():
    """Outward speed k (d_min - d) along p_c - p_r below d_min, zero above and at p_c = p_r.
    Catches: an inward push (sign), a speed not scaled by the depth inside, the term active outside."""
    d_min, k = 0.3, 2.0
    p_r = np.array([0.1, -0.2, 0.5])
    v = keep_out_velocity(p_r + [0.0, 0.2, 0.0], p_r, min_distance=d_min, gain=k)
    np.testing.assert_allclose(v, [0, k * (d_min - 0.2), 0, 0, 0, 0], atol=1e-15)
    v = keep_out_velocity(p_r + [-0.06, 0.0, 0.08], p_r, min_distance=d_min, gain=k)  # d = 0.1
    np.testing.assert_allclose(v, [k * 0.2 * -0.6, 0, k * 0.2 * 0.8, 0, 0, 0], atol=1e-15)
    assert not np.any(keep_out_velocity(p_r + [0.0, 0.0, d_min + 1e-3], p_r, min_distance=d_min, gain=k))
    assert not np.any(keep_out_velocity(p_r, p_r, min_distance=d_min, gain=k))
    assert not np.any(keep_out_velocity(p_r + [0.0, 0.1, 0.0], p_r, min_distance=0.0, gain=k))


def test_keep_out_refuses_bad_input_naming_it():
    with pytest.raises(InvalidInputError, match="roi_centre"):
        keep_out_velocity(np.zeros(3), [0.0, np.inf, 0.0], min_distance=0.3, gain=1.0)
    with pytest.raises(InvalidInputError, match="min_distance"):
        keep_out_velocity(np.zeros(3), np.ones(3), min_distance=-0.3, gain=1.0)
