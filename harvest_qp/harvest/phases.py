"""The harvest's phase machine (``subsec:biman_coord``), without a robot.

::

    APPROACH --switch test + p_sb, p_gd found--> BIMANUAL --pre-cut test held--> PRECUT
        |                                           |                               |
        +--------------- ABORT <--------------------+-------------------------------+

* APPROACH -> BIMANUAL: the camera is within ``distance_factor`` x r of the ROI centre and its
  mean speeds over ``window`` are below the thresholds (:func:`~harvest_qp.references.switch_ready`),
  and the perception then finds p_sb and p_gd (the controller calls :meth:`PhaseMachine.switch`).
* BIMANUAL -> PRECUT: the low-passed force along n_c within ``force_tolerance`` x f_d of f_d,
  the projected position error and the alignment within their tolerances, for ``hold_time``.
  Control goes on in PRECUT (the same tests keep running; an abort can still follow).
* -> ABORT: no stem base within ``no_stem_timeout`` of the start, no switch within
  ``switch_timeout`` of the start, no pre-cut within ``precut_timeout`` of the switch, the stem
  not seen for ``stem_lost_timeout`` after the switch, the force along n_c above ``force_limit``,
  or ``max_qp_failures`` failed QP steps in a row. The arms then brake to rest (the controller).
  The two phase timeouts turn an episode that would hold forever (a camera arm that cannot
  reach the ROI, a gripper held off the line by a steady push across n_c) into an abort whose
  reason names the test that never passed.

Deviation (lab measurements): the switch uses the camera's mean speeds
over the window, the angular one from the turn of the optical axis z_c (the free roll left
out): with V_cu acting the camera dithers about a fixed view (+-0.06 rad/s on seed 1) and its
instantaneous speeds never met 0.025 rad/s in 35 s, while its mean motion was nil.

The machine only reads numbers (times [s], the camera pose, forces [N], errors); every input
is handed in, so it is tested on hand-made sequences (tests/loop/test_phases.py).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from harvest_qp.references import switch_ready

__all__ = ["ABORT_CAUSES", "Phase", "PhaseMachine", "PhaseRules"]

#: Why the machine aborted, as a name that tools can match (the reason text is for people):
#: ``force`` (along n_c, its magnitude or its part across n_c above a limit), ``non_finite``
#: (a NaN grasp input), ``crop_side`` (the crop on the wrong side of p_sb), ``not_executed``
#: (the gripper's motion), ``no_precut`` (the pre-cut timeout), ``no_stem_base``, ``stem_lost``,
#: ``no_switch`` (the camera never met the switch test), ``no_grasp_target`` (it did, but no p_gd
#: was found), ``qp_failures``, and ``external`` (:meth:`PhaseMachine.abort` called from outside).
ABORT_CAUSES = ("force", "non_finite", "crop_side", "not_executed", "no_precut", "no_stem_base", "stem_lost",
                "no_switch", "no_grasp_target", "qp_failures", "external")


class Phase(IntEnum):
    """Episode phase, logged per tick as ``value/phase``."""

    APPROACH = 0
    BIMANUAL = 1
    PRECUT = 2
    ABORT = 3


@dataclass(frozen=True)
class PhaseRules:
    """The thresholds of the phase machine (units in brackets; the settings' keys in parentheses, whose
    schema, :class:`harvest_qp.config.EpisodeConfig`, holds the defaults)."""

    radius: float  # r [m] (reaching.radius)
    f_d: float  # desired force along n_c [N] (grasping.f_d)
    switch_window: float  # [s] (switch.window)
    switch_distance_factor: float  # (switch.distance_factor)
    switch_max_linear: float  # [m/s] (switch.max_linear_speed)
    switch_max_angular: float  # [rad/s] (switch.max_angular_speed)
    no_stem_timeout: float  # [s] (safety.no_stem_timeout)
    stem_lost_timeout: float  # [s] (safety.stem_lost_timeout)
    force_limit: float  # [N] (safety.force_limit; default 2 f_d)
    max_qp_failures: int  # (safety.max_qp_failures)
    force_tolerance: float  # fraction of f_d (precut.force_tolerance)
    position_tolerance: float  # [m] (precut.position_tolerance)
    alignment_tolerance_deg: float  # [deg] (precut.alignment_tolerance_deg)
    hold_time: float  # [s] (precut.hold_time)
    force_time_constant: float  # [s] low-pass of the force for the pre-cut test (precut.force_time_constant)
    end_after_precut: float | None  # [s] (episode.end_after_precut; None: never)
    stop_after_abort: float  # [s] at rest after an abort (episode.stop_after_abort)
    off_axis_force_limit: float = math.inf  # [N] the wrist force across n_c (safety.off_axis_force_limit; f_d)
    max_force_angle_deg: float = 180.0  # [deg] the force's angle from n_c at pre-cut (precut.max_force_angle_deg)
    unexecuted_timeout: float = math.inf  # [s] commanded translation not executed (safety.unexecuted_timeout)
    switch_timeout: float = math.inf  # [s] from the start, no switch (safety.switch_timeout)
    precut_timeout: float = math.inf  # [s] from the switch, no pre-cut (safety.precut_timeout)

    @classmethod
    def from_settings(cls, s: dict[str, Any]) -> PhaseRules:
        """From the checked settings tree (:func:`harvest_qp.config.settings.check_settings`)."""
        sw, safety, p = s.switch, s.safety, s.precut
        f_d = float(s.grasping.f_d)
        return cls(
            radius=s.reaching.radius, f_d=f_d, switch_window=sw.window,
            switch_distance_factor=sw.distance_factor, switch_max_linear=sw.max_linear_speed,
            switch_max_angular=sw.max_angular_speed, no_stem_timeout=safety.no_stem_timeout,
            stem_lost_timeout=safety.stem_lost_timeout,
            force_limit=2.0 * f_d if safety.force_limit is None else float(safety.force_limit),
            max_qp_failures=safety.max_qp_failures, force_tolerance=p.force_tolerance,
            position_tolerance=p.position_tolerance, alignment_tolerance_deg=p.alignment_tolerance_deg,
            hold_time=p.hold_time, force_time_constant=p.force_time_constant,
            end_after_precut=s.episode.end_after_precut, stop_after_abort=s.episode.stop_after_abort,
            off_axis_force_limit=f_d if safety.off_axis_force_limit is None else float(safety.off_axis_force_limit),
            max_force_angle_deg=p.max_force_angle_deg, unexecuted_timeout=safety.unexecuted_timeout,
            switch_timeout=safety.switch_timeout, precut_timeout=safety.precut_timeout,
        )


class PhaseMachine:
    """The phase and its timers; the controller reports each tick's facts, the machine decides.

    Attributes:
        phase: the current :class:`Phase`.
        abort_reason: why it aborted, in words (``None`` before).
        abort_cause: the same as one of :data:`ABORT_CAUSES` (``None`` before).
        t_switch, t_precut, t_abort, t_at_rest: when it switched, reached pre-cut, aborted,
            came to rest after the abort [s] (``None`` before).
        qp_failures: failed QP steps so far; backup_solves: steps the backup solver saved.
        force_filtered: the low-passed force along n_c of the pre-cut test [N].
    """

    def __init__(self, rules: PhaseRules) -> None:
        self.rules = rules
        self.reset()

    def reset(self) -> None:
        self.phase = Phase.APPROACH
        self.abort_reason: str | None = None
        self.abort_cause: str | None = None
        self.t_switch: float | None = None
        self.t_precut: float | None = None
        self.t_abort: float | None = None
        self.t_at_rest: float | None = None
        self.qp_failures = 0
        self.qp_failures_in_row = 0
        self.backup_solves = 0
        self.force_filtered: float | None = None
        self.precut_since: float | None = None
        self.unexecuted_time: float | None = None
        self.switch_test_passed_at: float | None = None  # the last approach tick whose switch test passed
        self._grasp_state: tuple[float, bool, float, float] | None = None  # the last pre-cut test's inputs
        self._camera_window: deque[tuple[float, tuple, tuple]] = deque()  # (t, p_c, z_c)

    @property
    def bimanual(self) -> bool:
        """In BIMANUAL or PRECUT (the grasping arm stretches the stem)."""
        return self.phase == Phase.BIMANUAL or self.phase == Phase.PRECUT

    def abort(self, t: float, reason: str, cause: str = "external") -> None:
        """Go to ABORT at ``t`` [s] for ``reason`` (words) and ``cause`` (one of :data:`ABORT_CAUSES`);
        the first abort's are kept."""
        if self.phase != Phase.ABORT:
            self.phase, self.abort_reason, self.abort_cause, self.t_abort = Phase.ABORT, reason, cause, t

    # ------------------------------------------------------------------ approach

    def approach(self, t: float, camera_pose: np.ndarray, *, stem_base_found: bool, roi_distance: float) -> bool:
        """One approach tick: whether the switch test passes (the caller then looks for p_gd and
        calls :meth:`switch`). Aborts when no stem base is found within ``no_stem_timeout``, and
        when the switch has not come within ``switch_timeout``: the reason says whether the switch
        test ever passed (then the perception found no grasp target there) or gives the ROI distance.

        ``camera_pose``: {C} ``(4, 4)``; ``roi_distance``: |p_r - p_c| [m].
        """
        r = self.rules
        if not stem_base_found and t > r.no_stem_timeout:
            self.abort(t, f"no stem base found within {r.no_stem_timeout} s", "no_stem_base")
            return False
        speeds = self._camera_speeds(t, camera_pose)
        ready = stem_base_found and speeds is not None and switch_ready(
            roi_distance, r.radius, *speeds, distance_factor=r.switch_distance_factor,
            max_linear=r.switch_max_linear, max_angular=r.switch_max_angular)
        first_pass = ready and self.switch_test_passed_at is None  # p_gd not yet looked for: let it try
        if ready:
            self.switch_test_passed_at = t
        if t >= r.switch_timeout - 1e-9 and not first_pass:
            if self.switch_test_passed_at is not None:
                # The camera was ready: the perception found no grasp target (p_sb or p_gd) there.
                self.abort(t, f"no switch within {r.switch_timeout} s: the switch test passed (last at "
                              f"{self.switch_test_passed_at:.1f} s) but no grasp target was found", "no_grasp_target")
            else:
                self.abort(t, f"no switch within {r.switch_timeout} s: the camera is {roi_distance:.3f} m from the "
                              f"ROI centre (switch within {r.switch_distance_factor * r.radius:.3f} m), stem base "
                              f"{'found' if stem_base_found else 'not found'}",
                           "no_switch" if stem_base_found else "no_stem_base")
            return False
        return ready

    def _camera_speeds(self, t: float, camera_pose: np.ndarray) -> tuple[float, float] | None:
        """The camera's mean speeds over the window: |p_c(t) - p_c(t0)| / (t - t0) [m/s] and the
        angle z_c turned / (t - t0) [rad/s]; None until the window spans ``switch_window``."""
        window = self._camera_window
        (_, _, z0, c0), (_, _, z1, c1), (_, _, z2, c2) = camera_pose[:3].tolist()
        p_c, z_c = (c0, c1, c2), (z0, z1, z2)
        window.append((t, p_c, z_c))
        span = self.rules.switch_window
        while len(window) > 1 and window[1][0] <= t - span + 1e-12:
            window.popleft()
        t0, p0, z0 = window[0]
        if t - t0 < span - 1e-9:
            return None
        linear = math.dist(p_c, p0) / (t - t0)
        angular = math.acos(min(max(z0[0] * z_c[0] + z0[1] * z_c[1] + z0[2] * z_c[2], -1.0), 1.0)) / (t - t0)
        return linear, angular

    def switch(self, t: float) -> None:
        """The perception found p_sb and p_gd at the switch: BIMANUAL from ``t``."""
        if self.phase == Phase.APPROACH:
            self.phase, self.t_switch = Phase.BIMANUAL, t

    # ------------------------------------------------------------------ bimanual

    def watch_stem(self, t: float, last_stem_time: float) -> None:
        """Abort when the stem was last seen more than ``stem_lost_timeout`` before ``t`` (after the switch)."""
        timeout = self.rules.stem_lost_timeout
        if self.bimanual and t - last_stem_time > timeout:
            self.abort(t, f"stem not seen for {timeout} s in the bimanual phase", "stem_lost")

    def stretch(self, t: float, dt: float, force_nc: float, position_error: float, alignment: float, *,
                force_norm: float, motion_executed: bool | None = True, crop_side: float = math.inf) -> None:
        """One bimanual tick's grasp state: the wrist force along n_c and its magnitude [N], the
        projected position error [m] and the alignment angle [rad] of V_g (``eq:superimp_g``),
        whether the last command's translation was executed, and how far the top of the
        crop lies beyond p_sb along n_c [m].

        Aborts when the crop is not on the target side of p_sb (``crop_side`` < 0: compression
        would read as stretch along n_c), on a non-finite force or crop side, and, before pre-cut,
        when the gripper's commanded translation has not been executed for ``unexecuted_timeout``
        (the QP could not move the gripper where V_g asks: obstacles or limits; the reason says so
        instead of an episode that never converges). ``motion_executed`` None (the command asked
        too little to tell) pauses that clock; True restarts it.

        Aborts on what the robot can see (beyond the paper, which compares n_c^T f alone): the force
        along n_c or the force's magnitude above ``force_limit`` (a stem pulled off-axis, or the
        gripper pressed on a petiole, reads little along n_c), or its part across n_c above
        ``off_axis_force_limit``. Else low-passes the force along n_c (with 0.2 N sensor noise the raw
        samples leave the +-10 % band on ~13 % of ticks) and runs the pre-cut test, which also asks
        that the force lie within ``max_force_angle_deg`` of n_c (a pull held by a branch contact
        across n_c is not a stretched stem)."""
        r = self.rules
        if crop_side < 0.0:
            self.abort(t, f"the crop is {-1000 * crop_side:.0f} mm on the wrong side of the stem base along n_c",
                       "crop_side")
            return
        if any(math.isnan(value) for value in (force_nc, force_norm, crop_side, position_error, alignment)):
            self.abort(t, f"non-finite grasp state (force along n_c {force_nc}, magnitude {force_norm}, "
                          f"crop side {crop_side}, position error {position_error}, alignment {alignment})",
                       "non_finite")
            return
        if motion_executed:
            self.unexecuted_time = None
        elif motion_executed is not None and self.phase == Phase.BIMANUAL:
            # Time of not-executed ticks since the last executed one; ticks too small to tell pause it.
            self.unexecuted_time = 0.0 if self.unexecuted_time is None else self.unexecuted_time + dt
            if self.unexecuted_time >= r.unexecuted_timeout - 1e-9:
                self.abort(t, f"the gripper's motion not executed for {r.unexecuted_timeout} s "
                              "(obstacle rows or limits)", "not_executed")
                return
        if force_nc > r.force_limit:
            self.abort(t, f"stem force {force_nc:.2f} N above the limit {r.force_limit:.2f} N", "force")
            return
        if force_norm > r.force_limit:
            self.abort(t, f"wrist force magnitude {force_norm:.2f} N above the limit {r.force_limit:.2f} N "
                          f"({force_nc:.2f} N along n_c)", "force")
            return
        across = math.sqrt(max(force_norm * force_norm - force_nc * force_nc, 0.0))
        if across > r.off_axis_force_limit:
            self.abort(t, f"wrist force {across:.2f} N across n_c above the limit {r.off_axis_force_limit:.2f} N",
                       "force")
            return
        tau = r.force_time_constant
        if self.force_filtered is None or tau == 0:
            self.force_filtered = force_nc
        else:
            self.force_filtered += -math.expm1(-dt / tau) * (force_nc - self.force_filtered)
        along = force_nc > 0.0 and math.degrees(math.atan2(across, force_nc)) <= r.max_force_angle_deg
        self._grasp_state = (force_nc, along, position_error, alignment)
        within = (
            along
            and abs(self.force_filtered - r.f_d) <= r.force_tolerance * r.f_d
            and position_error <= r.position_tolerance
            and math.degrees(alignment) <= r.alignment_tolerance_deg
        )
        if not within:
            self.precut_since = None
            if (self.phase == Phase.BIMANUAL and self.t_switch is not None
                    and t - self.t_switch >= r.precut_timeout - 1e-9):
                self.abort(t, f"no pre-cut within {r.precut_timeout} s of the switch: "
                              + self._precut_misses(force_nc, along, position_error, alignment), "no_precut")
            return
        if self.precut_since is None:
            self.precut_since = t
        if self.phase == Phase.BIMANUAL and t - self.precut_since >= r.hold_time:
            self.phase, self.t_precut = Phase.PRECUT, t

    def precut_misses(self) -> str | None:
        """The pre-cut tests that failed on the last bimanual tick, with their values (None before the
        first one): why an episode that ended in the bimanual phase had not reached pre-cut."""
        return None if self._grasp_state is None else self._precut_misses(*self._grasp_state)

    def _precut_misses(self, force_nc: float, along: bool, position_error: float, alignment: float) -> str:
        """Which of the pre-cut tests fail, with their values (for the abort's reason)."""
        r, misses = self.rules, []
        if abs(self.force_filtered - r.f_d) > r.force_tolerance * r.f_d:
            misses.append(f"force along n_c {self.force_filtered:.2f} N (f_d {r.f_d:.2f} N +- "
                          f"{100 * r.force_tolerance:.0f} %)")
        if force_nc <= 0.0:
            misses.append(f"no pull along n_c ({force_nc:.2f} N)")
        elif not along:
            misses.append(f"force more than {r.max_force_angle_deg:.0f} deg off n_c")
        if position_error > r.position_tolerance:
            misses.append(f"position error {1000 * position_error:.1f} mm (> {1000 * r.position_tolerance:.1f} mm)")
        if math.degrees(alignment) > r.alignment_tolerance_deg:
            misses.append(f"alignment {math.degrees(alignment):.1f} deg (> {r.alignment_tolerance_deg:.1f} deg)")
        return ", ".join(misses) or "the tests never held together"

    # ------------------------------------------------------------------ every tick

    def solved(self, t: float, ok: bool, status: str) -> None:
        """The QP step's outcome; aborts after ``max_qp_failures`` failures in a row."""
        if ok:
            self.qp_failures_in_row = 0
            return
        self.qp_failures += 1
        self.qp_failures_in_row += 1
        if self.qp_failures_in_row >= self.rules.max_qp_failures:
            self.abort(t, f"{self.qp_failures_in_row} QP failures in a row ({status})", "qp_failures")

    def braking(self, t: float, at_rest: bool) -> None:
        """An abort tick's safe stop; ``at_rest``: the commanded speeds are all zero."""
        if at_rest and self.t_at_rest is None:
            self.t_at_rest = t

    def done(self, t: float) -> bool:
        """Whether the episode may end at ``t``: ``end_after_precut`` after pre-cut, or
        ``stop_after_abort`` after the arms came to rest from an abort."""
        r = self.rules
        if self.phase == Phase.PRECUT:
            return r.end_after_precut is not None and t - self.t_precut >= r.end_after_precut
        if self.phase == Phase.ABORT:
            return self.t_at_rest is not None and t - self.t_at_rest >= r.stop_after_abort
        return False
