"""eq:final_vc's feed-forward and the switch thresholds of subsec:biman_coord."""

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import GraspFeedForward, switch_ready


def test_feed_forward_by_hand():
    """p_c = (0.35, 0, 0), p_sb = 0, v_gt = (0, 0.01, 0): S(p_c - p_sb) v_gt = (0, 0, 0.0035)
    (the printed term, m^2/s) and / 0.35^2 = (0, 0, 0.028571) rad/s (normalised).
    Catches: S(p_sb - p_c) (wrong sign), a missing normalisation."""
    v = np.array([0.0, 0.01, 0.0])
    np.testing.assert_allclose(
        GraspFeedForward(normalise=False)(v, [0.35, 0.0, 0.0], np.zeros(3)), [0, 0.01, 0, 0, 0, 0.0035], atol=1e-15
    )
    np.testing.assert_allclose(
        GraspFeedForward()(v, [0.35, 0.0, 0.0], np.zeros(3)), [0, 0.01, 0, 0, 0, 0.0035 / 0.1225], rtol=1e-12
    )
    np.testing.assert_array_equal(GraspFeedForward()(v, np.zeros(3), np.zeros(3)), [0, 0.01, 0, 0, 0, 0])


def test_normalised_feed_forward_keeps_the_stem_base_centred():
    """Moving the camera by v_gt and turning it by the normalised term keeps z_c on p_sb to
    second order: after 1 s in 1 ms steps the bearing error is < 1e-4 rad, against 0.1 rad
    without the angular term.  The printed (unnormalised) term leaves 0.09 rad."""

    def drift(feed):
        position, z = np.array([0.35, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])
        v = np.array([0.0, 0.035, 0.0])
        for _ in range(1000):
            twist = feed(v, position, np.zeros(3)) if feed else np.concatenate((v, np.zeros(3)))
            position = position + 0.001 * twist[:3]
            z = z + 0.001 * np.cross(twist[3:], z)
            z /= np.linalg.norm(z)
        return math.acos(min(1.0, z @ (-position / np.linalg.norm(position))))

    assert drift(GraspFeedForward()) < 1e-4
    assert drift(None) > 0.09
    assert drift(GraspFeedForward(normalise=False)) > 0.08


@pytest.mark.parametrize(
    "distance, linear, angular, expected",
    [
        (0.36, 0.005, 0.01, True),
        (0.3675, 0.005, 0.01, True),  # exactly 1.05 r
        (0.37, 0.005, 0.01, False),
        (0.36, 0.01, 0.01, False),  # not strictly slower
        (0.36, 0.005, 0.03, False),
        (0.0, 0.0, 0.0, True),
    ],
)
def test_switch_thresholds(distance, linear, angular, expected):
    """1.05 r, 0.01 m/s, 0.025 rad/s (sec:exper).  Catches: a swapped threshold or a missing factor."""
    assert switch_ready(distance, 0.35, linear, angular) is expected


def test_switch_bad_input_raises():
    with pytest.raises(InvalidInputError, match="linear_speed"):
        switch_ready(0.3, 0.35, -0.1, 0.0)
