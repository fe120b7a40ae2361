"""The phase machine (harvest_qp/harvest/phases.py) on hand-made sequences, without a robot.

Oracles: the thresholds of ``subsec:biman_coord`` / ``sec:exper`` applied by hand to the inputs
(times, camera poses, forces) each test builds.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from harvest_qp.config.settings import check_settings
from harvest_qp.harvest.phases import Phase, PhaseMachine, PhaseRules

DT = 0.002


@pytest.fixture
def rules() -> PhaseRules:
    """The paper's defaults with round numbers where the tests need them."""
    return dataclasses.replace(
        PhaseRules.from_settings(check_settings({})), radius=0.35, f_d=3.0, switch_window=0.5,
        switch_distance_factor=1.05, switch_max_linear=0.01, switch_max_angular=0.025, no_stem_timeout=20.0,
        stem_lost_timeout=2.0, force_limit=6.0, max_qp_failures=3, force_tolerance=0.1, position_tolerance=0.01,
        alignment_tolerance_deg=10.0, hold_time=0.5, force_time_constant=0.0, end_after_precut=1.0,
        stop_after_abort=0.5,
    )


def _pose(position=(0.0, 0.0, 0.0), yaw: float = 0.0, tilt: float = 0.0) -> np.ndarray:
    """A camera pose at ``position`` whose optical axis z_c is turned by ``tilt`` about x and
    which is rolled by ``yaw`` about z_c."""
    cz, sz, cx, sx = math.cos(yaw), math.sin(yaw), math.cos(tilt), math.sin(tilt)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]) @ np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    pose[:3, 3] = position
    return pose


def _approach(machine: PhaseMachine, ticks: int, pose_at, *, stem: bool = True, distance: float = 0.3,
              start: float = 0.0) -> list[bool]:
    return [machine.approach(start + DT * (k + 1), pose_at(k), stem_base_found=stem, roi_distance=distance)
            for k in range(ticks)]


def test_switch_waits_for_a_full_window_then_tests_distance_and_mean_speeds(rules):
    """A still camera within 1.05 r: not ready until the window spans 0.5 s (tick 251), ready after.
    Catches: a switch on the first ticks (no window yet), the window never filling."""
    machine = PhaseMachine(rules)
    ready = _approach(machine, 300, lambda k: _pose())
    assert not any(ready[:250]) and all(ready[250:])  # t - t0 = 0.502 - 0.002 on the 251st tick
    assert machine.phase == Phase.APPROACH  # the test alone never switches
    machine.switch(0.6)
    assert machine.phase == Phase.BIMANUAL and machine.t_switch == 0.6 and machine.bimanual


def test_switch_refused_outside_the_roi_or_without_a_stem_base(rules):
    machine = PhaseMachine(rules)
    assert not any(_approach(machine, 300, lambda k: _pose(), distance=1.06 * 0.35))
    assert any(_approach(PhaseMachine(rules), 300, lambda k: _pose(), distance=1.04 * 0.35))
    assert not any(_approach(PhaseMachine(rules), 300, lambda k: _pose(), stem=False))


def test_switch_uses_the_mean_linear_speed_over_the_window(rules):
    """Moving at 0.012 m/s along x (above 0.01): never ready; at 0.008 m/s: ready once the window
    is full. A camera dithering +-1 mm every tick (instantaneous 0.5 m/s, mean ~0) is ready.
    Catches: the instantaneous speed (never ready while dithering), the distance not divided by the window."""
    assert not any(_approach(PhaseMachine(rules), 400, lambda k: _pose((0.012 * DT * k, 0, 0))))
    assert any(_approach(PhaseMachine(rules), 400, lambda k: _pose((0.008 * DT * k, 0, 0))))
    assert any(_approach(PhaseMachine(rules), 400, lambda k: _pose((1e-3 * (-1) ** k, 0, 0))))


def test_switch_uses_the_turn_of_the_optical_axis_not_the_roll(rules):
    """Rolling about z_c at 0.1 rad/s leaves z_c fixed: ready. Tilting z_c at 0.03 rad/s (above
    0.025): never; at 0.02 rad/s: ready. Catches: the roll counted (the camera's free roll alone
    moves at ~0.045 rad/s), the angle not divided by the window's span."""
    assert any(_approach(PhaseMachine(rules), 400, lambda k: _pose(yaw=0.1 * DT * k)))
    assert not any(_approach(PhaseMachine(rules), 400, lambda k: _pose(tilt=0.03 * DT * k)))
    assert any(_approach(PhaseMachine(rules), 400, lambda k: _pose(tilt=0.02 * DT * k)))


def test_no_stem_base_within_the_timeout_aborts(rules):
    machine = PhaseMachine(rules)
    assert not machine.approach(20.0, _pose(), stem_base_found=False, roi_distance=0.3)
    assert machine.phase == Phase.APPROACH
    machine.approach(20.002, _pose(), stem_base_found=False, roi_distance=0.3)
    assert machine.phase == Phase.ABORT and machine.t_abort == 20.002
    assert machine.abort_reason == "no stem base found within 20.0 s" and machine.abort_cause == "no_stem_base"
    machine.approach(20.004, _pose(), stem_base_found=True, roi_distance=0.3)
    assert machine.phase == Phase.ABORT and machine.t_abort == 20.002  # the first reason stays


def test_no_switch_within_the_switch_timeout_aborts_and_says_where_the_camera_is(rules):
    """A stem base found but the camera held 0.66 m from the ROI centre (the camera arm folded onto its
    own wrist, held-out 18066): the switch test never passes, so at ``switch_timeout`` the episode
    aborts and names the distance against 1.05 r = 0.3675 m.  A camera inside the ROI that is still
    moving past the timeout aborts too.  Catches: an approach that holds to the episode's end
    without a reason (18066 ran 50 s in APPROACH)."""
    machine = PhaseMachine(dataclasses.replace(rules, switch_timeout=2.0))
    ticks = int(round(2.0 / DT))
    ready = _approach(machine, ticks - 1, lambda k: _pose(), distance=0.66)
    assert not any(ready) and machine.phase == Phase.APPROACH
    machine.approach(2.0, _pose(), stem_base_found=True, roi_distance=0.66)
    assert machine.phase == Phase.ABORT and machine.t_abort == 2.0
    assert machine.abort_reason == ("no switch within 2.0 s: the camera is 0.660 m from the ROI centre "
                                    "(switch within 0.367 m), stem base found")
    assert machine.abort_cause == "no_switch"


def test_a_switch_timeout_after_the_switch_test_passed_blames_the_grasp_target(rules):
    """The camera is ready (still, 0.3 m from the ROI centre) but the controller never switches (no
    p_gd found): the reason says the test passed and when, not where the camera is.  A first pass on
    the timeout's own tick is let through (p_gd not yet looked for).  Catches: "the camera is 0.300 m
    ... (switch within 0.367 m)", which contradicts itself and was classed as a camera failure."""
    machine = PhaseMachine(dataclasses.replace(rules, switch_timeout=2.0))
    ready = _approach(machine, int(round(2.0 / DT)) - 1, lambda k: _pose())
    assert any(ready) and machine.phase == Phase.APPROACH
    machine.approach(2.0, _pose(), stem_base_found=True, roi_distance=0.3)
    assert machine.phase == Phase.ABORT
    assert machine.abort_reason == ("no switch within 2.0 s: the switch test passed (last at 2.0 s) but no grasp "
                                    "target was found")
    assert machine.abort_cause == "no_grasp_target"
    late = PhaseMachine(dataclasses.replace(rules, switch_timeout=0.502))
    assert _approach(late, 251, lambda k: _pose())[-1]  # the first pass, on the timeout's tick: no abort
    assert late.phase == Phase.APPROACH
    late.approach(0.504, _pose(), stem_base_found=True, roi_distance=0.3)
    assert late.phase == Phase.ABORT


def test_a_non_finite_position_error_or_alignment_aborts(rules):
    """Catches: NaN passing every comparison, so the pre-cut timeout would say "the tests never held
    together" instead of naming the broken input."""
    for error, alignment in ((math.nan, 0.0), (0.0, math.nan)):
        machine = PhaseMachine(rules)
        machine.switch(0.0)
        machine.stretch(0.1, DT, 3.0, error, alignment, force_norm=3.0)
        assert machine.phase == Phase.ABORT and machine.abort_reason.startswith("non-finite grasp state")
        assert machine.abort_cause == "non_finite"


def test_no_precut_within_the_precut_timeout_aborts_and_names_the_failing_tests(rules):
    """After the switch the force sits at f_d but a steady push across n_c holds the gripper 7 mm
    off the line by 12 mm (the tolerance here is 10 mm; the yield's equilibrium k_pg e = k_yield
    (|f_perp| - d)): nothing else aborts, and at ``precut_timeout`` after the switch the machine aborts
    naming the position error only.  Just before it, a run whose tests hold reaches pre-cut and the timeout never
    applies.  Catches: an episode that neither reaches pre-cut nor aborts (found by review)."""
    machine = PhaseMachine(dataclasses.replace(rules, precut_timeout=3.0))
    machine.switch(1.0)
    t = 1.0
    while t < 4.0 - 2 * DT:
        t += DT
        machine.stretch(t, DT, 3.0, 0.012, 0.0, force_norm=math.hypot(3.0, 1.0))
        assert machine.phase == Phase.BIMANUAL
    machine.stretch(4.0, DT, 3.0, 0.012, 0.0, force_norm=math.hypot(3.0, 1.0))
    assert machine.phase == Phase.ABORT and machine.t_abort == 4.0
    assert machine.abort_reason == "no pre-cut within 3.0 s of the switch: position error 12.0 mm (> 10.0 mm)"
    assert machine.abort_cause == "no_precut"
    slack = PhaseMachine(dataclasses.replace(rules, precut_timeout=1.0))
    slack.switch(0.0)
    for k in range(501):
        slack.stretch(k * DT, DT, -0.4, 0.0, 0.0, force_norm=0.4)
    assert slack.abort_reason == ("no pre-cut within 1.0 s of the switch: force along n_c -0.40 N (f_d 3.00 N +- "
                                  "10 %), no pull along n_c (-0.40 N)")
    ok = PhaseMachine(dataclasses.replace(rules, precut_timeout=3.0))
    ok.switch(1.0)
    t = 1.0
    while t < 6.0:
        t += DT
        ok.stretch(t, DT, 3.0, 0.0, 0.0, force_norm=3.0)
    assert ok.phase == Phase.PRECUT and ok.abort_reason is None


def test_a_stem_lost_for_the_timeout_aborts_only_after_the_switch(rules):
    machine = PhaseMachine(rules)
    machine.watch_stem(5.0, last_stem_time=1.0)
    assert machine.phase == Phase.APPROACH
    machine.switch(3.0)
    machine.watch_stem(5.0, last_stem_time=3.0)
    assert machine.phase == Phase.BIMANUAL  # 2.0 s is not more than the timeout
    machine.watch_stem(5.002, last_stem_time=3.0)
    assert machine.phase == Phase.ABORT and "stem not seen for 2.0 s" in machine.abort_reason


def test_force_above_the_limit_aborts(rules):
    machine = PhaseMachine(rules)
    machine.switch(0.0)
    machine.stretch(0.1, DT, 6.0, 0.0, 0.0, force_norm=6.0)
    assert machine.phase == Phase.BIMANUAL
    machine.stretch(0.102, DT, 6.01, 0.0, 0.0, force_norm=6.01)
    assert machine.phase == Phase.ABORT and machine.abort_reason == "stem force 6.01 N above the limit 6.00 N"
    assert machine.abort_cause == "force"


@pytest.mark.parametrize(("along", "norm", "reason"), [
    (-8.9, 15.0, "wrist force magnitude 15.00 N above the limit 6.00 N (-8.90 N along n_c)"),  # a stem pulled
    (1.0, 6.5, "wrist force magnitude 6.50 N above the limit 6.00 N (1.00 N along n_c)"),  # off n_c: FINDINGS
    (2.0, 4.0, "wrist force 3.46 N across n_c above the limit 3.00 N"),
])
def test_the_wrist_force_aborts_off_n_c_too(rules, along, norm, reason):
    """What the robot sees off n_c stops the arms (issue 20, safety): a 15 N wrist force reading -8.9 N
    along n_c (a stem torn at 15 N while n_c^T f never reached 2 f_d), or a force across n_c above
    f_d. Hand values: across = sqrt(4^2 - 2^2) = 3.46 N. Catches: the abort comparing n_c^T f alone."""
    machine = PhaseMachine(dataclasses.replace(rules, off_axis_force_limit=3.0))
    machine.switch(0.0)
    machine.stretch(0.1, DT, along, 0.0, 0.0, force_norm=norm)
    assert machine.phase == Phase.ABORT and machine.abort_reason == reason
    assert machine.abort_cause == "force"


def test_motion_not_executed_for_the_timeout_aborts_with_a_reason(rules):
    """V_g asks for motion along n_c that the QP never gives (map rows or limits): after
    ``unexecuted_timeout`` of it the machine aborts and says why; executed motion in between
    restarts the clock. Hand sequence: 1.0 s unexecuted, one executed tick, then 1.5 s.
    Catches: an episode that never converges and never says why (7 of 100 held-out scenes)."""
    machine = PhaseMachine(dataclasses.replace(rules, unexecuted_timeout=1.5))
    machine.switch(0.0)
    for k in range(500):
        machine.stretch(0.1 + k * DT, DT, 1.0, 0.02, 0.0, force_norm=1.0, motion_executed=False)
    machine.stretch(1.2, DT, 1.0, 0.02, 0.0, force_norm=1.0, motion_executed=True)
    t = 1.2
    while t < 2.7 - 1e-9:
        t += DT
        machine.stretch(t, DT, 1.0, 0.02, 0.0, force_norm=1.0, motion_executed=False)
        assert machine.phase == Phase.BIMANUAL
    machine.stretch(2.71, DT, 1.0, 0.02, 0.0, force_norm=1.0, motion_executed=False)
    assert machine.phase == Phase.ABORT and "not executed for 1.5 s" in machine.abort_reason


def test_a_crop_on_the_wrong_side_of_the_stem_base_aborts(rules):
    """The top of the crop 4 mm beyond p_sb against n_c: compression reads as stretch there (held-out
    scenes: true tension -1.8 N while n_c^T f read +1.8 N), so the stretch stops. Catches: a stretch
    that only looks at n_c^T f."""
    machine = PhaseMachine(rules)
    machine.switch(0.0)
    machine.stretch(0.1, DT, 1.8, 0.0, 0.0, force_norm=1.8, crop_side=0.07)
    assert machine.phase == Phase.BIMANUAL
    machine.stretch(0.102, DT, 1.8, 0.0, 0.0, force_norm=1.8, crop_side=-0.004)
    assert machine.phase == Phase.ABORT and machine.abort_reason == (
        "the crop is 4 mm on the wrong side of the stem base along n_c")


def test_precut_only_with_the_force_along_n_c(rules):
    """3 N along n_c but 1.5 N across it (27 deg off, a pull held by a branch contact): every other
    pre-cut test holds, yet pre-cut is never declared; 1.0 N across (18 deg) is. Catches: pre-cut
    judged on n_c^T f alone."""
    machine = PhaseMachine(dataclasses.replace(rules, max_force_angle_deg=20.0))
    machine.switch(0.0)
    t = 0.1
    while t < 2.0:
        machine.stretch(t, DT, 3.0, 0.0, 0.0, force_norm=math.hypot(3.0, 1.5))
        t += DT
    assert machine.phase == Phase.BIMANUAL
    while t < 3.2:
        machine.stretch(t, DT, 3.0, 0.0, 0.0, force_norm=math.hypot(3.0, 1.0))
        t += DT
    assert machine.phase == Phase.PRECUT


def test_precut_after_the_tests_hold_for_the_hold_time(rules):
    """Force 3.2 N (within 10 % of 3 N), 5 mm, 5 deg from t = 1.0: pre-cut at t = 1.5, not before;
    a tick out of tolerance restarts the hold. Catches: the hold not restarted, radians compared
    with the degree tolerance, an absolute force tolerance."""
    machine = PhaseMachine(rules)
    machine.switch(0.5)
    t = 1.0
    while t < 1.3:
        machine.stretch(t, DT, 3.2, 0.005, math.radians(5), force_norm=3.2)
        t += DT
    machine.stretch(t, DT, 3.31, 0.005, math.radians(5), force_norm=3.31)  # 10.3 % off: out
    assert machine.precut_since is None
    start = t + DT
    for k in range(1000):
        t = start + DT * k
        machine.stretch(t, DT, 2.75, 0.009, math.radians(9.9), force_norm=2.75)
        if machine.phase == Phase.PRECUT:
            break
    assert machine.t_precut == pytest.approx(start + 0.5, abs=1.5 * DT)
    assert not machine.done(machine.t_precut + 0.99) and machine.done(machine.t_precut + 1.0)
    for error, alignment in ((0.011, 0.0), (0.0, math.radians(10.1))):
        other = PhaseMachine(rules)
        other.switch(0.0)
        for k in range(400):
            other.stretch(DT * k, DT, 3.0, error, alignment, force_norm=3.0)
        assert other.phase == Phase.BIMANUAL


def test_the_precut_force_is_low_passed(rules):
    """With a 0.1 s time constant, a force that alternates 2.4 / 3.6 N (each outside +-10 %) filters
    to within the band and reaches pre-cut; without the filter it never does."""
    filtered = PhaseMachine(dataclasses.replace(rules, force_time_constant=0.1))
    raw = PhaseMachine(rules)
    for machine in (filtered, raw):
        machine.switch(0.0)
        for k in range(1000):
            force = 3.0 + 0.6 * (-1) ** k
            machine.stretch(DT * (k + 1), DT, force, 0.0, 0.0, force_norm=force)
    assert filtered.phase == Phase.PRECUT and raw.phase == Phase.BIMANUAL
    assert abs(filtered.force_filtered - 3.0) < 0.1


def test_qp_failures_in_a_row_abort(rules):
    machine = PhaseMachine(rules)
    machine.solved(0.1, False, "infeasible")
    machine.solved(0.2, False, "infeasible")
    machine.solved(0.3, True, "ok")
    machine.solved(0.4, False, "infeasible")
    machine.solved(0.5, False, "infeasible")
    assert machine.phase == Phase.APPROACH and machine.qp_failures == 4
    machine.solved(0.6, False, "max iterations")
    assert machine.phase == Phase.ABORT and machine.abort_reason == "3 QP failures in a row (max iterations)"


def test_after_an_abort_the_episode_ends_once_at_rest_for_the_stop_time(rules):
    machine = PhaseMachine(rules)
    machine.abort(1.0, "test")
    machine.braking(1.1, at_rest=False)
    assert not machine.done(1.1)
    machine.braking(1.2, at_rest=True)
    machine.braking(1.3, at_rest=True)
    assert machine.t_at_rest == 1.2
    assert not machine.done(1.69) and machine.done(1.7)


def test_reset_starts_a_new_episode(rules):
    machine = PhaseMachine(rules)
    _approach(machine, 300, lambda k: _pose())
    machine.switch(0.6)
    machine.abort(0.7, "test")
    machine.reset()
    assert machine.phase == Phase.APPROACH and machine.t_switch is None and machine.abort_reason is None
    assert not any(_approach(machine, 250, lambda k: _pose()))  # the window starts empty again


def test_rules_from_the_settings():
    """The force limit defaults to 2 f_d; an explicit one is kept."""
    rules = PhaseRules.from_settings(check_settings({"grasping": {"f_d": 2.5}}))
    assert rules.force_limit == 5.0 and rules.f_d == 2.5
    assert PhaseRules.from_settings(check_settings({"safety": {"force_limit": 4.0}})).force_limit == 4.0
