"""V_g of eq:gr_pos_contr, eq:gr_forc_contr, eq:contr_dir, eq:rot_contr, eq:superimp_g."""

import math

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references import StemStretching

# {G} with y_g = (0, 0, -1) (the crop hangs down): x = (1, 0, 0), z = x cross y = (0, 1, 0).
DOWN = np.column_stack(([1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]))


def _pose(position, rotation=DOWN):
    pose = np.eye(4)
    pose[:3, :3] = rotation
    pose[:3, 3] = position
    return pose


def test_v_g_by_hand():
    """p_sb = (0, 0, 1), p_gd = (0.3, 0, 0.6): n_c = (0.6, 0, -0.8).  p_g = (0.1, 0.2, 0.7):
    e_pg = (-0.2, 0.2, 0.1), n.e = -0.2, projected (-0.08, 0.2, -0.06), v_p = (0.012, -0.03,
    0.009).  f = 2 n_c + (0, 1, 0): e_fg = -1; after one 0.01 s step the integral is -0.01,
    k_fp e + k_fi I = -0.001002, v_f = 0.001002 n_c.  v_gw = -0.3 n_c x (0, 0, -1) =
    (0, -0.18, 0); alignment acos(0.8).
    Catches: v_p not projected, v_f with the wrong sign, v_gw = +k_og n_c x y_g."""
    law = StemStretching(k_pg=0.15, k_og=0.3, k_fp=0.001, k_fi=0.0002, f_d=3.0, integration_threshold=None)
    law.set_target([0.0, 0.0, 1.0], [0.3, 0.0, 0.6])
    np.testing.assert_allclose(law.n_c, [0.6, 0.0, -0.8], rtol=1e-15)
    twist = law.update(_pose([0.1, 0.2, 0.7]), np.array([1.2, 1.0, -1.6]), 0.01)
    v_p = np.array([0.012, -0.03, 0.009])
    v_f = 0.001002 * np.array([0.6, 0.0, -0.8])
    np.testing.assert_allclose(twist[:3], v_p + v_f, rtol=1e-12)
    np.testing.assert_allclose(twist[3:], [0.0, -0.18, 0.0], atol=1e-15)
    assert law.position_error == pytest.approx(math.sqrt(0.05), rel=1e-12)
    assert law.alignment == pytest.approx(math.acos(0.8), rel=1e-12)
    assert law.force_along_nc == pytest.approx(2.0)
    assert law.integral == pytest.approx(-0.01)
    np.testing.assert_allclose(law.v_gt, twist[:3])


def test_v_gw_rotates_y_g_onto_n_c():
    """Integrating R' = S(v_gw) R drives the alignment angle to 0.  Catches: the sign of eq:rot_contr."""
    law = StemStretching(k_og=1.0)
    law.set_target([0.0, 0.0, 1.0], [0.3, 0.0, 0.6])
    rotation = DOWN.copy()
    angles = []
    for _ in range(500):
        w = law.update(_pose([0.3, 0.0, 0.6], rotation), np.zeros(3), 0.01)[3:]
        angles.append(law.alignment)
        angle = np.linalg.norm(w) * 0.01
        if angle > 0:
            k = w / np.linalg.norm(w)
            skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
            rotation = (np.eye(3) + math.sin(angle) * skew + (1 - math.cos(angle)) * skew @ skew) @ rotation
    assert np.all(np.diff(angles) <= 0.0) and angles[-1] < 0.01 * angles[0]


def test_pulling_along_n_c_stretches_the_stem_to_f_d():
    """Sign convention: a stem of 400 N/m anchored at p_sb, slack until 5 cm; the gripper
    follows V_g kinematically and the sensor reads the force the gripper applies to the crop,
    +400 (stretch) n_c.  The force converges to f_d with the paper's gains (settling ~20 s,
    the lab measurements' linearised loop).  Catches: v_f's sign (the stem would go slack or tear), and an
    integral that never starts (steady error f_d k_fp / ... would remain)."""
    law = StemStretching()
    base = np.array([0.0, 0.0, 1.0])
    law.set_target(base, [0.0, 0.0, 0.9])  # n_c = (0, 0, -1), straight down
    position = np.array([0.0, 0.0, 0.96])  # 4 cm from the base: slack
    dt, forces = 0.01, []
    for _ in range(6000):
        stretch = max(0.0, np.linalg.norm(position - base) - 0.05)
        force = 400.0 * stretch * law.n_c
        position = position + dt * law.update(_pose(position), force, dt)[:3]
        forces.append(float(law.force_along_nc))
    forces = np.array(forces)
    assert abs(forces[-100:].mean() - 3.0) < 0.03
    assert forces.max() < 2 * 3.0


def test_anti_windup_holds_the_integral_while_saturated():
    """A large force error saturates |v_f| at max_speed; the integral is then held (not
    integrated), and resumes as soon as the error reverses.  Catches: plain integration
    (the integral would grow by e dt every step)."""
    law = StemStretching(k_fp=0.01, k_fi=0.01, max_speed=0.02, integration_threshold=None)
    law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    pose = _pose([0.0, 0.0, 0.9])
    # n_c . f = 0: e_fg = -3, k_fp e = -0.03 already past -0.02: held from the first step.
    for _ in range(100):
        twist = law.update(pose, np.zeros(3), 0.01)
        assert law.saturated
        assert law.integral == 0.0
        np.testing.assert_allclose(twist[:3], [0.0, 0.0, -0.02])  # -n_c * (-0.02)
    # Slightly below the saturation: integrates until the command reaches it, then holds.
    law.reset()
    force = np.array([0.0, 0.0, -1.5])  # n_c . f = 1.5: e = -1.5, k_fp e = -0.015
    integrals = []
    for _ in range(200):
        law.update(pose, force, 0.01)
        integrals.append(law.integral)
    assert integrals[0] == pytest.approx(-0.015)
    # Held where k_fp e + k_fi I first reaches -max_speed (I ~ -0.5), within one step's
    # increment k_fi e dt = 1.5e-4; plain integration would end at -3.0.
    command = 0.01 * -1.5 + 0.01 * integrals[-1]
    assert -0.02 <= command <= -0.02 + 1.5e-4
    assert integrals[-1] == integrals[-50]
    # Error reversed (force above f_d): the integral unwinds at once.
    law.update(pose, np.array([0.0, 0.0, -4.0]), 0.01)
    assert law.integral == pytest.approx(integrals[-1] + 0.01)


def test_integration_starts_once_the_force_exceeds_the_threshold():
    """With integration_threshold = 1 N (the lab measurements' remedy for wind-up during the slack swing)
    the integral stays 0 while n_c.f <= 1 N, starts above it, and stays on afterwards."""
    law = StemStretching(integration_threshold=1.0)
    law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    pose = _pose([0.0, 0.0, 0.9])
    for _ in range(10):
        law.update(pose, np.array([0.0, 0.0, 2.5]), 0.01)  # compressed: n_c.f = -2.5
    assert law.integral == 0.0
    law.update(pose, np.array([0.0, 0.0, -1.5]), 0.01)
    assert law.integral == pytest.approx(-0.015)
    law.update(pose, np.array([0.0, 0.0, -0.5]), 0.01)  # latched: still integrating
    assert law.integral == pytest.approx(-0.015 - 0.025)
    law.reset()
    assert law.integral == 0.0


def test_bad_input_raises():
    with pytest.raises(InvalidInputError, match="k_pg"):
        StemStretching(k_pg=-1.0)
    law = StemStretching()
    with pytest.raises(InvalidInputError, match="set_target"):
        law.update(_pose([0.0, 0.0, 0.0]), np.zeros(3), 0.01)
    with pytest.raises(InvalidInputError, match="target must differ"):
        law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 1.0])
    law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    with pytest.raises(InvalidInputError, match="force"):
        law.update(_pose([0.0, 0.0, 0.0]), [0.0, np.nan, 0.0], 0.01)


def test_the_force_integral_holds_while_the_motion_is_not_executed():
    """The last command asked for v_f along n_c; the QP's answer moved the gripper 0 m/s along n_c
    (an obstacle row): the integral holds. Executed motion (within 1 mm/s): it integrates. Hand
    values: e_fg = 1 - 3 = -2 N, dt = 0.01 s, so each integrating step adds -0.02 N s.
    Catches: the integral winding up on motion that never happened (9 mm/s on held-out scenes)."""
    law = StemStretching(k_fp=0.001, k_fi=0.0002, f_d=3.0, integration_threshold=None)
    law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])  # n_c = (0, 0, -1)
    pose = _pose([0.0, 0.0, 0.9])
    force = np.array([0.0, 0.0, -1.0])  # 1 N along n_c
    law.update(pose, force, 0.01)
    assert law.integral == pytest.approx(-0.02)
    asked = law.v_gt.copy()
    assert asked @ law.n_c > 0.002  # the command moves along n_c
    law.update(pose, force, 0.01, executed=np.zeros(3))
    assert not law.motion_executed and law.integral == pytest.approx(-0.02)
    law.update(pose, force, 0.01, executed=law.v_gt + [0.0005, 0.0, 0.0005])
    assert law.motion_executed and law.integral == pytest.approx(-0.04)


def test_the_gripper_yields_to_the_force_across_n_c_beyond_the_deadband():
    """n_c = (0, 0, -1), the gripper at p_gd, f = (2, 0, -3): 2 N across n_c, 1.5 N beyond the
    0.5 N deadband, so v_y = -0.004 (1 - 0.5/2) (2, 0, 0) = (-0.006, 0, 0) on top of the paper's
    V_g (k_yield = 0); 0.4 N across (inside the deadband) adds nothing.
    Catches: yielding towards the push (sign), yielding to the force along n_c, no deadband.
    (The raw force, yield_time_constant = 0: the low-pass has its own tests below.)"""
    paper = StemStretching(integration_threshold=None)
    yielding = StemStretching(integration_threshold=None, k_yield=0.004, yield_deadband=0.5, yield_time_constant=0)
    for law in (paper, yielding):
        law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    pose = _pose([0.0, 0.0, 0.9])
    difference = yielding.update(pose, [2.0, 0.0, -3.0], 0.01) - paper.update(pose, [2.0, 0.0, -3.0], 0.01)
    np.testing.assert_allclose(difference, [-0.006, 0.0, 0.0, 0.0, 0.0, 0.0], atol=1e-15)
    difference = yielding.update(pose, [0.4, 0.0, -3.0], 0.01) - paper.update(pose, [0.4, 0.0, -3.0], 0.01)
    np.testing.assert_allclose(difference, np.zeros(6), atol=1e-15)


def _displacement_across(law, steady_across, *, seconds=10.0, dt=0.002, noise=0.2, seed=3):
    """The kinematic gripper's largest offset [m] across n_c = (0, 0, -1) from p_gd while the wrist reads
    ``steady_across`` [N] along +x, f_d along n_c and ``noise`` [N] Gaussian per axis (seeded)."""
    rng = np.random.default_rng(seed)
    law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    position, worst = np.array([0.0, 0.0, 0.9]), 0.0
    for _ in range(int(round(seconds / dt))):
        force = np.array([steady_across, 0.0, -3.0]) + noise * rng.standard_normal(3)
        position = position + dt * law.update(_pose(position), force, dt)[:3]
        position[2] = 0.9  # hold the axis: only the offset across n_c is judged
        worst = max(worst, float(np.hypot(position[0], position[1])))
    return worst


def test_sensor_noise_does_not_lift_a_force_inside_the_deadband_into_a_yield():
    """0.4 N across n_c (inside the 0.5 N deadband) with 0.2 N of noise per axis: on the raw force
    the noisy magnitude passes 0.5 N on about a third of the ticks and the gripper creeps (an
    independent review measured 0.6-2.5 mm).  Low-passed with 0.1 s the noise is ~0.02 N per axis
    (0.2 sqrt(a / (2 - a)), a = dt / tau = 0.02), five of its deviations below the deadband: the
    gripper stays put.  Catches: the deadband acting on the raw force (yield_time_constant
    ignored), which moves it by over 0.5 mm here."""
    raw = _displacement_across(StemStretching(k_yield=0.004, yield_time_constant=0.0), 0.4)
    filtered = _displacement_across(StemStretching(k_yield=0.004, yield_time_constant=0.1), 0.4)
    assert raw > 5e-4  # the hazard is real on the raw force
    assert filtered < 5e-5


def test_the_low_passed_yield_still_gives_way_to_a_steady_push():
    """A steady 1.2 N across n_c (below the raw bypass at 1.5 N), no noise: after 1 s (10 time
    constants) v_y is the raw law's -0.004 (1 - 0.5/1.2) 1.2 = -2.8 mm/s to 1e-4 relative (e^-10).
    The filter starts from the tared zero: the first tick's 1.2 (1 - e^-0.02) = 0.024 N is inside
    the deadband.
    Catches: a filter that never converges, or a deadband applied after the yield's scaling."""
    law = StemStretching(integration_threshold=None, k_yield=0.004, yield_time_constant=0.1)
    paper = StemStretching(integration_threshold=None)
    for each in (law, paper):
        each.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
    pose, force = _pose([0.0, 0.0, 0.9]), [1.2, 0.0, -3.0]
    first = law.update(pose, force, 0.002) - paper.update(pose, force, 0.002)
    assert first[0] == 0.0
    for _ in range(500):
        last = law.update(pose, force, 0.002) - paper.update(pose, force, 0.002)
    assert last[0] == pytest.approx(-0.0028, rel=1e-4)


def _contact_peak(law, stiffness, depth=0.02, dt=0.002):
    """Peak force [N] of a one-sided spring across n_c (surface at x = 0) that v_p drives the
    kinematic gripper into: p_gd ``depth`` [m] inside it, the gripper 5 mm outside at the start."""
    law.set_target([depth, 0.0, 0.3], [depth, 0.0, 0.0])
    position, peak = np.array([-0.005, 0.0, 0.0]), 0.0
    for _ in range(int(round(8.0 / dt))):
        push = stiffness * max(position[0], 0.0)
        position = position + dt * law.update(_pose(position), [push, 0.0, -3.0], dt)[:3]
        position[2] = 0.0
        peak = max(peak, push)
    return peak


def test_a_stiff_contact_is_yielded_to_without_the_filters_lag():
    """A 20,000 N/m contact (a cane near its support) met at k_pg x 20 mm = 3 mm/s: on the raw force
    the yield holds the peak at 1.25 N; through the 0.1 s low-pass alone it reached 3.56 N, over the
    3 N off-axis abort (an independent review's hand model).  Above 3 deadbands the law takes the raw
    force, so the peak stays within 0.5 N of the raw law's.  Catches: the filter applied to every push."""
    raw = _contact_peak(StemStretching(k_yield=0.004, yield_time_constant=0.0), 20000.0)
    filtered = _contact_peak(StemStretching(k_yield=0.004, yield_time_constant=0.1), 20000.0)
    assert 1.2 < raw < 1.3
    assert filtered < raw + 0.5 and filtered < 3.0


def test_a_leaf_beside_the_target_is_not_pressed_beyond_the_deadband():
    """A stiff leaf (2000 N/m) across n_c whose surface lies 3 mm short of p_gd: the paper's
    law drives the kinematic gripper onto p_gd and presses the leaf with 6 N; yielding settles
    where v_p and v_y balance, the leaf carrying under 1 N (hand model: k_pg e = k_yield
    (2000 (3 mm - e) - 0.5) gives e = 2.70 mm, 0.60 N).  The stem (400 N/m along n_c) is
    stretched to f_d either way.  Catches: a yield of the wrong sign (presses deeper) or none."""

    def settle(law):
        law.set_target([0.0, 0.0, 1.0], [0.0, 0.0, 0.9])
        position, dt = np.array([0.0, 0.0, 0.9]), 0.01
        for _ in range(8000):
            stretch = max(0.0, 1.0 - position[2] - 0.05)
            leaf = 2000.0 * max(0.0, position[0] + 0.003)  # the leaf pushes the crop towards -x
            force = np.array([leaf, 0.0, -400.0 * stretch])  # what the gripper applies: it holds the push
            position = position + dt * law.update(_pose(position), force, dt)[:3]
        return leaf, law.force_along_nc

    leaf_paper, along_paper = settle(StemStretching())
    leaf_yield, along_yield = settle(StemStretching(k_yield=0.004, yield_deadband=0.5))
    assert leaf_paper > 5.5
    assert leaf_yield < 1.0
    assert abs(along_paper - 3.0) < 0.05 and abs(along_yield - 3.0) < 0.05
