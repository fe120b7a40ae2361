"""The look-around sweep (references/look_around.py), integrated in closed loop against the cone's geometry.

Oracle: the camera's orientation is integrated here with the exact rotation exp([w] dt) (Rodrigues) of
the commanded angular velocity, and the optical axis compared with the cone computed in the test
(its angle from the ROI direction and its azimuth about it), not with the law's own direction.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import LookAround
from tests.references.flying_camera import look_at_pose, rotation_increment


def _look_at(position, direction) -> np.ndarray:
    return look_at_pose(position, np.asarray(position, float) + np.asarray(direction, float))


def _sweep(look: LookAround, T: np.ndarray, roi: np.ndarray, *, dt=0.002):
    """Integrate the camera's orientation under the law for one period; the optical axes, one per tick."""
    look.start(0.0, T, roi)
    axes, t = [], 0.0
    while t < look.period - 1e-12:
        w = look.angular_velocity(t, T)
        T = T.copy()
        T[:3, :3] = rotation_increment(w, dt) @ T[:3, :3]
        axes.append(T[:3, 2].copy())
        t += dt
    return np.array(axes)


def _cone_frame(p0, roi):
    a = (roi - p0) / np.linalg.norm(roi - p0)
    e1 = np.cross(a, [0.0, 0.0, 1.0])
    e1 /= np.linalg.norm(e1)
    return a, e1, np.cross(a, e1)


def test_the_optical_axis_sweeps_the_whole_cone_once():
    """Started on the cone, z_c stays within 0.5 deg of the 25 deg cone about the ROI direction and its
    azimuth about that direction turns one full turn, one way, in one period; then the law is zero.
    Catches: a feed-forward about the wrong axis or of the wrong sign (z_c leaves the cone or turns
    back), a period that is not one turn, a sweep that does not end."""
    cone, period = math.radians(25.0), 2.5
    p0, roi = np.array([0.3, 0.5, 1.1]), np.array([0.6, 0.1, 1.0])
    a, e1, e2 = _cone_frame(p0, roi)
    look = LookAround(cone=cone, period=period, gain=3.0)
    z = _sweep(look, _look_at(p0, math.cos(cone) * a + math.sin(cone) * e1), roi)
    off_axis = np.degrees(np.arccos(np.clip(z @ a, -1, 1)))
    assert np.max(np.abs(off_axis - 25.0)) < 0.5
    azimuth = np.unwrap(np.arctan2(z @ e2, z @ e1))
    assert azimuth[-1] - azimuth[0] == pytest.approx(2 * math.pi, abs=0.05)
    assert np.all(np.diff(azimuth) > 0)
    assert look.done(period) and not look.done(0.99 * period)
    np.testing.assert_array_equal(look.angular_velocity(period, np.eye(4)), 0.0)


def test_started_off_the_cone_the_axis_is_pulled_onto_it():
    """From z_c along the ROI direction (25 deg inside the cone), the axis is on the cone within 1 deg
    from 1.5 s on (gain 3/s). Catches: a pull of the wrong sign or about the wrong axis."""
    p0, roi = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 1.0])
    look = LookAround(cone=math.radians(25.0), period=2.5, gain=3.0)
    z = _sweep(look, _look_at(p0, roi - p0), roi)
    off_axis = np.degrees(np.arccos(np.clip(z[:, 0], -1, 1)))
    assert off_axis[0] < 1.0
    assert np.max(np.abs(off_axis[750:] - 25.0)) < 1.0


def test_the_angular_velocity_by_hand():
    """On the cone at the start the law is the feed-forward alone, (2 pi / T) (a - (a.z) z): a = y,
    e_1 = a x z = x, alpha = 30 deg, z_c = (sin 30, cos 30, 0), T = 2 s gives
    pi (-sin 30 cos 30, sin^2 30, 0); 10 deg inside the cone (z_c at 20 deg) the pull adds
    k 10 deg about z_c x d = -z."""
    p0, roi = np.array([0.0, 0.0, 1.0]), np.array([0.0, 2.0, 1.0])
    cone = math.radians(30.0)
    a, e1, _ = _cone_frame(p0, roi)  # e1 = a x z = (1, 0, 0)
    on_cone = _look_at(p0, math.cos(cone) * a + math.sin(cone) * e1)
    look = LookAround(cone=cone, period=2.0, gain=2.0)
    look.start(5.0, on_cone, roi)
    s30, c30 = math.sin(cone), math.cos(cone)
    np.testing.assert_allclose(look.angular_velocity(5.0, on_cone), [-math.pi * s30 * c30, math.pi * s30**2, 0],
                               atol=1e-12)
    s20, c20 = math.sin(math.radians(20)), math.cos(math.radians(20))
    inside = _look_at(p0, c20 * a + s20 * e1)
    expected = [-math.pi * s20 * c20, math.pi * s20**2, -2.0 * math.radians(10)]
    np.testing.assert_allclose(look.angular_velocity(5.0, inside), expected, atol=1e-12)
    np.testing.assert_allclose(look.direction(5.0), on_cone[:3, 2], atol=1e-12)


def test_the_sweep_never_rolls_the_camera_about_its_optical_axis():
    """w . z_c = 0 for any camera orientation and time: the sweep only turns z_c. Catches the
    review's finding on the first version: its feed-forward (2 pi / T) a rolled the camera about
    z_c; the QP's 5-D camera task ignored that, but the pseudo-inverse mapper followed it (293 deg
    of roll over one sweep, 4.5 rad/s of joint speed at the start)."""
    rng = np.random.default_rng(3)
    p0, roi = np.array([0.3, 0.5, 1.1]), np.array([0.6, 0.1, 1.0])
    look = LookAround()
    look.start(0.0, _look_at(p0, roi - p0), roi)
    for _ in range(200):
        T = _look_at(p0, rng.normal(size=3))
        w = look.angular_velocity(rng.uniform(0.0, look.period), T)
        assert abs(w @ T[:3, 2]) < 1e-12 * max(1.0, np.linalg.norm(w))


def test_bad_input_is_refused():
    with pytest.raises(InvalidInputError, match="cone"):
        LookAround(cone=math.pi / 2)
    with pytest.raises(InvalidInputError, match="period"):
        LookAround(period=0.0)
    look = LookAround()
    with pytest.raises(InvalidInputError, match="start"):
        look.angular_velocity(0.0, np.eye(4))
    with pytest.raises(InvalidInputError, match="ROI centre"):
        look.start(0.0, np.eye(4), [0.0, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match="finite"):
        look.start(float("nan"), np.eye(4), [1.0, 0.0, 0.0])
    look.start(0.0, np.eye(4), [1.0, 0.0, 0.0])
    with pytest.raises(InvalidInputError, match="finite"):
        look.angular_velocity(float("nan"), np.eye(4))
    with pytest.raises(InvalidInputError, match="finite"):
        look.done(float("nan"))
