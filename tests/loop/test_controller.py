"""HarvestController pieces against hand-computed values (no episode)."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.loop.controller import HarvestController, Phase, _wrap_half_turn
from harvest_qp.loop.settings import DEFAULTS, check_settings


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def test_roll_reference_turns_the_blade_across_the_stem(controller):
    """Roll twist about z_c by the angle from y_c to the stem seen in the image plane.

    Oracle: a camera with world axes (x_c = x, y_c = y, z_c = z) and a stem at 30 deg from y
    in the image plane must turn by -30 deg (rotating y by phi about z gives
    (-sin phi, cos phi, 0)); the stem's component along z_c does not matter; a stem
    reversed is the same line. Catches: a sign error, a missing projection, a directed angle."""
    k = controller.settings["roll"]["k_roll"]
    T = np.eye(4)
    d = np.array([np.sin(np.radians(30)), np.cos(np.radians(30)), 0.0])
    twist, angle = controller._roll_reference(T, d)
    assert angle == pytest.approx(-np.radians(30))
    np.testing.assert_allclose(twist, [0, 0, 0, 0, 0, -k * np.radians(30)], atol=1e-12)
    _, angle_tilted = controller._roll_reference(T, d + np.array([0, 0, 5.0]))
    assert angle_tilted == pytest.approx(-np.radians(30))
    _, angle_reversed = controller._roll_reference(T, -d)
    assert angle_reversed == pytest.approx(-np.radians(30))
    _, along_axis = controller._roll_reference(T, np.array([0, 0, 1.0]))
    assert np.isnan(along_axis)


def test_wrap_half_turn():
    assert _wrap_half_turn(np.radians(100)) == pytest.approx(np.radians(-80))
    assert _wrap_half_turn(np.radians(-100)) == pytest.approx(np.radians(80))
    assert _wrap_half_turn(0.3) == pytest.approx(0.3)


def test_keep_out_pushes_out_only_below_the_minimum_distance(controller):
    """Outward speed k (d_min - d) along p_c - p_r below d_min = 0.85 r, zero above (hand values)."""
    controller.reaching.reset(np.zeros(3))
    r = controller.settings["reaching"]
    d_min = r["min_distance_factor"] * r["radius"]
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.2, 0.0]
    np.testing.assert_allclose(controller._keep_out(T), [0, r["k_keep_out"] * (d_min - 0.2), 0, 0, 0, 0])
    T[:3, 3] = [0.0, 0.0, d_min + 1e-3]
    assert not np.any(controller._keep_out(T))


def test_safe_stop_decelerates_within_the_acceleration_limit(controller):
    """Each tick of an abort lowers every joint speed by at most a_max dt, to exactly zero."""
    controller.state.previous_qdot = np.linspace(-0.5, 0.5, 12)
    a_max = DEFAULTS["qp"]["limits"][2]["max_acceleration"]
    previous = controller.state.previous_qdot.copy()
    for _ in range(200):
        qdot = controller._safe_stop()
        assert np.all(np.abs(qdot - previous) <= a_max * controller.dt + 1e-12)
        assert np.all(np.abs(qdot) <= np.abs(previous) + 1e-12)
        controller.state.previous_qdot = previous = qdot
    assert not np.any(qdot)
    assert controller.phase == Phase.APPROACH
