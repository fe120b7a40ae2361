"""The roll reference (references/roll.py) against hand-computed angles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import roll_reference, wrap_half_turn


def test_roll_reference_turns_the_blade_across_the_stem():
    """Roll twist about z_c by the angle from y_c to the stem seen in the image plane.

    Oracle: a camera with world axes (x_c = x, y_c = y, z_c = z) and a stem at 30 deg from y
    in the image plane must turn by -30 deg (rotating y by phi about z gives
    (-sin phi, cos phi, 0)); the stem's component along z_c does not matter; a stem
    reversed is the same line. Catches: a sign error, a missing projection, a directed angle."""
    k = 0.7
    T = np.eye(4)
    d = np.array([np.sin(np.radians(30)), np.cos(np.radians(30)), 0.0])
    twist, angle = roll_reference(T, d, k_roll=k)
    assert angle == pytest.approx(-np.radians(30))
    np.testing.assert_allclose(twist, [0, 0, 0, 0, 0, -k * np.radians(30)], atol=1e-12)
    _, angle_tilted = roll_reference(T, d + np.array([0, 0, 5.0]), k_roll=k)
    assert angle_tilted == pytest.approx(-np.radians(30))
    _, angle_reversed = roll_reference(T, -d, k_roll=k)
    assert angle_reversed == pytest.approx(-np.radians(30))
    twist, along_axis = roll_reference(T, np.array([0, 0, 1.0]), k_roll=k)
    assert np.isnan(along_axis) and not np.any(twist)


def test_roll_reference_on_a_turned_camera_rolls_about_its_optical_axis():
    """Camera turned 90 deg about x (z_c = -y world, y_c = z world); a stem along world x is at
    -90 deg from y_c about z_c, which wraps to -90 deg (a half turn is the same line): the twist is
    k phi z_c. Catches: the twist about the world z instead of z_c."""
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # x_c = x, y_c = z, z_c = -y
    twist, angle = roll_reference(T, [1.0, 0.0, 0.0], k_roll=2.0)
    # y_c x d = z x x = y; (y_c x d) . z_c = -1; y_c . d = 0: atan2(-1, 0) = -pi/2.
    assert angle == pytest.approx(-math.pi / 2)
    np.testing.assert_allclose(twist, [0, 0, 0, 0, 2.0 * math.pi / 2, 0], atol=1e-12)


def test_wrap_half_turn():
    assert wrap_half_turn(np.radians(100)) == pytest.approx(np.radians(-80))
    assert wrap_half_turn(np.radians(-100)) == pytest.approx(np.radians(80))
    assert wrap_half_turn(0.3) == pytest.approx(0.3)
    assert -math.pi / 2 <= wrap_half_turn(math.pi / 2) < math.pi / 2


def test_roll_reference_refuses_bad_input_naming_it():
    with pytest.raises(InvalidInputError, match="direction"):
        roll_reference(np.eye(4), [0.0, np.nan, 1.0], k_roll=1.0)
    with pytest.raises(InvalidInputError, match="camera_pose"):
        roll_reference(2 * np.eye(4), [0.0, 1.0, 0.0], k_roll=1.0)


def test_a_blade_turned_against_the_camera_is_what_the_roll_turns_across_the_stem():
    """Camera with world axes; the blade's y axis turned 10 deg about z_c and tilted 5 deg out of the
    image plane (a calibrated camera mounted off square): a stem along world y is then -10 deg from the
    blade's y seen in the image plane (hand value), not 0 as from y_c. Catches: the camera's y_c used
    for the blade."""
    a, tilt = np.radians(10.0), np.radians(5.0)
    blade_y = np.array([-np.sin(a) * np.cos(tilt), np.cos(a) * np.cos(tilt), np.sin(tilt)])
    twist, angle = roll_reference(np.eye(4), [0.0, 1.0, 0.0], k_roll=1.0, blade_y=blade_y)
    assert angle == pytest.approx(-a, abs=1e-12)
    np.testing.assert_allclose(twist, [0, 0, 0, 0, 0, -a], atol=1e-12)
    assert roll_reference(np.eye(4), [0.0, 1.0, 0.0], k_roll=1.0)[1] == pytest.approx(0.0)
    with pytest.raises(InvalidInputError, match="blade_y must not lie along the optical axis"):
        roll_reference(np.eye(4), [0.0, 1.0, 0.0], k_roll=1.0, blade_y=[0.0, 0.0, 1.0])
