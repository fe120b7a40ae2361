"""V_cr of eq:control_signal_rr_world / eq:ktheta_world and the p_r filter, against hand values."""

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import ReachingCentering, minimum_rotation


def _pose(rotation=None, position=(0.0, 0.0, 0.0)):
    pose = np.eye(4)
    pose[:3, :3] = np.eye(3) if rotation is None else rotation
    pose[:3, 3] = position
    return pose


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


def test_v_cr_by_hand():
    """Camera at the origin looking along +z, p_r = (0, 0.6, 0.8): |e| = 1, f = 1 - 0.35^2 =
    0.8775, theta = acos(0.8) = 0.643501 rad, k = z x e / |z x e| = (-1, 0, 0).
    Catches: a wrong sign of k (S(z_c) e vs S(e) z_c), max(0, f) replaced by |e| or f^2,
    theta in degrees."""
    law = ReachingCentering(radius=0.35, k_cp=2.0, k_co=3.0)
    law.reset(roi_centre=[0.0, 0.6, 0.8])
    twist = law.update(_pose(), 0.01)
    np.testing.assert_allclose(twist[:3], 2.0 * 0.8775 * np.array([0.0, 0.6, 0.8]), rtol=1e-12)
    np.testing.assert_allclose(twist[3:], 3.0 * 0.6435011087932844 * np.array([-1.0, 0.0, 0.0]), rtol=1e-12)
    assert law.theta == pytest.approx(0.6435011087932844, rel=1e-12)
    assert law.distance == pytest.approx(1.0)


def test_angular_part_turns_the_optical_axis_onto_the_roi():
    """Integrating R' = S(w) R under V_cr's angular part drives theta to 0 exponentially
    (rate k_co).  Catches: the axis sign (theta would grow to pi)."""
    law = ReachingCentering(k_co=1.0)
    rotation = _rotation([1.0, 2.0, 0.5], 1.2)
    centre = np.array([0.3, -0.2, 0.5])
    law.reset(roi_centre=centre)
    thetas = []
    for _ in range(300):
        w = law.update(_pose(rotation), 0.01)[3:]
        thetas.append(law.theta)
        rotation = _rotation(w, np.linalg.norm(w) * 0.01) @ rotation if np.linalg.norm(w) > 0 else rotation
    assert np.all(np.diff(thetas) < 0)
    assert thetas[-1] == pytest.approx(thetas[0] * math.exp(-2.99), rel=0.02)


def test_v_cr_is_zero_inside_the_region_when_centred():
    """Inside the ball (f <= 0) and theta = 0: V_cr = 0 exactly (the paper's 'zero iff').
    Catches: a law without the max(0, .) (it would pull the camera onto p_r)."""
    law = ReachingCentering(radius=0.35)
    law.reset(roi_centre=[0.0, 0.0, 0.2])
    np.testing.assert_array_equal(law.update(_pose(), 0.01), np.zeros(6))
    # On the sphere itself too.
    law.reset(roi_centre=[0.0, 0.0, 0.35])
    np.testing.assert_array_equal(law.update(_pose(), 0.01), np.zeros(6))
    # Outside, centred: only the linear part, along e_pc.
    law.reset(roi_centre=[0.0, 0.0, 0.5])
    twist = law.update(_pose(), 0.01)
    np.testing.assert_array_equal(twist[3:], 0.0)
    assert twist[2] == pytest.approx(1.0 * (0.25 - 0.1225) * 0.5)


def test_v_cr_is_finite_where_k_is_undefined():
    """theta = 0 (k = 0/0) and e_pc = 0 give zeros, never NaN; an ROI straight behind
    (theta = pi) still turns the camera at k_co pi.  Catches: k = S(z)e / |S(z)e| unguarded."""
    law = ReachingCentering()
    law.reset(roi_centre=[0.0, 0.0, 0.0])
    np.testing.assert_array_equal(law.update(_pose(), 0.01), np.zeros(6))
    law.reset(roi_centre=[0.0, 0.0, 2.0])
    assert np.isfinite(law.update(_pose(), 0.01)).all() and law.theta == 0.0
    law.reset(roi_centre=[0.0, 0.0, -0.1])
    twist = law.update(_pose(), 0.01)
    assert np.linalg.norm(twist[3:]) == pytest.approx(math.pi)
    assert twist[5] == 0.0  # turning about an axis normal to z_c
    theta, axis = minimum_rotation([0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
    assert theta == 0.0 and not axis.any()


def test_roi_filter_never_jumps():
    """A 0.4 m step of the ROI target moves the filtered p_r by exactly (1 - exp(-dt/tau)) of
    the remaining gap per update (first-order filter), so V_cr changes by a bounded amount per
    tick, and p_r converges to the target.  Catches: the target used directly (a jump)."""
    law = ReachingCentering(roi_time_constant=0.5)
    law.reset(roi_centre=[0.0, 0.0, 0.6])
    pose = _pose()
    previous_twist = law.update(pose, 0.002)
    law.set_roi_centre([0.4, 0.0, 0.6])
    previous = law.roi_centre.copy()
    fraction = 1.0 - math.exp(-0.002 / 0.5)
    worst = 0.0
    for _ in range(2000):
        twist = law.update(pose, 0.002)
        step = np.linalg.norm(law.roi_centre - previous)
        gap = np.linalg.norm(np.array([0.4, 0.0, 0.6]) - previous)
        assert step == pytest.approx(fraction * gap, rel=1e-9, abs=1e-15)
        worst = max(worst, np.abs(twist - previous_twist).max())
        previous, previous_twist = law.roi_centre.copy(), twist
    assert worst < 0.01  # per 2 ms tick, against 0.4+ rad/s of total change
    np.testing.assert_allclose(law.roi_centre, [0.4, 0.0, 0.6], atol=1e-3)


def test_first_target_is_taken_at_once_and_update_needs_one():
    law = ReachingCentering()
    with pytest.raises(InvalidInputError, match="set_roi_centre"):
        law.update(_pose(), 0.01)
    law.set_roi_centre([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(law.roi_centre, [1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    "kwargs, message",
    [({"radius": -0.1}, "radius"), ({"k_cp": 0.0}, "k_cp"), ({"k_co": float("nan")}, "k_co")],
)
def test_bad_parameters_raise(kwargs, message):
    with pytest.raises(InvalidInputError, match=message):
        ReachingCentering(**kwargs)


def test_bad_pose_and_dt_raise():
    law = ReachingCentering()
    law.reset(roi_centre=[0.0, 0.0, 1.0])
    with pytest.raises(InvalidInputError, match="camera_pose"):
        law.update(np.eye(3), 0.01)
    with pytest.raises(InvalidInputError, match="camera_pose"):
        law.update(2.0 * np.eye(4), 0.01)
    with pytest.raises(InvalidInputError, match="dt"):
        law.update(np.eye(4), 0.0)
