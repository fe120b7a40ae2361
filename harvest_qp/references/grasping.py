"""Grasping-arm force/position and orientation control V_g (``subsec:grasp_contr``).

::

    n_c  = (p_gd - p_sb) / |p_gd - p_sb|                                  (eq:contr_dir)
    v_p  = -k_pg (I - n_c n_c^T)(p_g - p_gd)                              (eq:gr_pos_contr)
    v_f  = -n_c (k_fp e_fg + k_fi int e_fg),  e_fg = n_c^T f - f_d        (eq:gr_forc_contr)
    v_gw = -k_og (n_c x y_g)                                              (eq:rot_contr)
    V_g  = [v_p + v_f ; v_gw]                                             (eq:superimp_g)
    v_y  = -k_yield (1 - d / |f_perp|) f_perp,  f_perp = (I - n_c n_c^T) f_lp,  |f_perp| > d
           f_lp: f low-passed with time constant yield_time_constant
                                           (beyond the paper, added to v_p; k_yield = 0 by default)

Sign convention of the force f: the force the gripper applies to what it holds (the crop and
through it the stem), world frame, tared, which is what a gravity-compensated wrist F/T sensor
reports (``harvest_qp.sim.force``).  Pulling the crop away from the stem base along n_c
stretches the stem, whose tension resists: the gripper then pushes on the crop along +n_c, so
a stretched stem reads n_c^T f > 0 and e_fg < 0 below f_d, and v_f = -n_c k e_fg moves the
gripper further along +n_c.  (With the opposite convention -- the stem's pull on the gripper --
the loop would be positive feedback; negate the reading first.)
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import as_pose, as_position, as_positive_scalar, as_time_step
from harvest_qp.references._vec3 import add, cross, dot, norm, scale, sub

__all__ = ["StemStretching"]

#: The yield acts on the raw force across n_c once it exceeds this many deadbands (1.5 N by default):
#: with 0.2 N of noise per axis the noise alone reaches 1 N on ~1e-6 of ticks, while a stiff contact
#: (5,000-20,000 N/m) met at 3-6 mm/s rose to 2-6 N during the filter's 0.1 s lag (an independent
#: review's hand model) against 1.2-2.0 N on the raw force.
RAW_YIELD_FACTOR = 3.0


def _executed(miss: float, asked: float, tolerance: float) -> bool:
    """Whether a command of size ``asked`` [m/s] was executed, missed by ``miss`` [m/s]: within
    ``tolerance`` or half the command, whichever is more."""
    return miss <= max(tolerance, 0.5 * asked)


class StemStretching:
    """Stem-stretching reference V_g of the grasping arm (``eq:superimp_g``).

    Args:
        k_pg: position gain [1/s] (0.15 in Section ``sec:exper``).
        k_og: orientation gain [1/s] (0.3).
        k_fp: proportional force gain [m/(N s)] (0.001).
        k_fi: integral force gain [m/(N s^2)] (0.0002).
        f_d: desired stretching force along n_c [N] (3).
        max_speed: saturation of the force term's speed |v_f| [m/s].  Not in the paper: it bounds
            what a force transient can command, and defines when the integral is held.
        integral_limit: bound on |int e_fg| [N s]; default ``max_speed / k_fi``, the largest
            integral whose own term still fits in the saturation.
        integration_threshold: the integral starts only once n_c^T f has exceeded this [N]
            (latched until :meth:`reset`); ``None`` integrates from the start as the paper does.
            Deviation, measured (lab measurements, README): at the bimanual start the slack stem
            swings and is compressed (-2.5 N for ~2 s); integrating that wound the PI up to a
            4.54-5.87 N peak (51-96 % over f_d), integrating only once n_c^T f > 1 N gave
            3.43-3.47 N (14-16 %).
        execution_tolerance: [m/s] the last command's speed along n_c counts as executed within
            this (or half the command, if more) of the speed achieved (see Anti-windup).
        k_yield: admittance gain across n_c [m/(N s)]; 0 (default) is the paper's law.  Not in
            the paper: the gripper yields to the part of the wrist force across n_c beyond
            ``yield_deadband``, v_y = -k_yield (1 - d/|f_perp|) f_perp, so the held crop is not
            driven into a leaf by v_p.  Measured (lab, dev seeds): without it v_p pressed the crop
            into a leaf until the contact carried 3-4 N, a third of it along n_c, and the stem's
            true tension fell to 1.8 N while n_c^T f read 3 N.
        yield_deadband: [N] the force across n_c the gripper does not yield to (sensor noise, a
            stem pulling slightly off n_c).
        yield_time_constant: [s] first-order low-pass of the wrist force (world frame) before the
            deadband; 0: the raw force.  An independent review measured that on the raw force,
            0.2 N of noise per axis lifts a steady 0.3-0.5 N across n_c over the 0.5 N deadband
            often enough to move the gripper 0.6-2.5 mm; 0.1 s cuts that noise ~10x.  Above
            :data:`RAW_YIELD_FACTOR` deadbands the raw force is used (the filter's lag let a stiff
            contact's force climb past the off-axis abort).

    Anti-windup: conditional integration.  When the PI command k_fp e + k_fi I exceeds
    ``max_speed`` and the error would drive it further out, the integral is held; it always
    stays within ``integral_limit``.  It is also held while the motion along n_c that the last
    command asked for was not executed (``executed`` of :meth:`update`: the QP's gripper speed
    along n_c fell short of it by more than ``execution_tolerance`` and half the command); measured
    on held-out scenes before this: the integral wound up on 9 mm/s that map rows never let happen.

    Attributes (of the last :meth:`update`): n_c, position_error [m] (|(I - n n^T)(p_g - p_gd)|),
    alignment [rad] (angle between y_g and n_c), force_along_nc [N], v_gt [m/s], integral
    [N s], saturated (whether v_f was clipped), executed_along_nc [m/s] and motion_executed
    (whether the last command's translation happened: True, False, or None when it asked for
    less than ``execution_tolerance``; NaN/True without ``executed``).
    """

    def __init__(
        self,
        *,
        k_pg: float = 0.15,
        k_og: float = 0.3,
        k_fp: float = 0.001,
        k_fi: float = 0.0002,
        f_d: float = 3.0,
        max_speed: float = 0.05,
        integral_limit: float | None = None,
        integration_threshold: float | None = 1.0,
        execution_tolerance: float = 0.001,
        k_yield: float = 0.0,
        yield_deadband: float = 0.5,
        yield_time_constant: float = 0.1,
    ) -> None:
        self.k_pg = as_positive_scalar(k_pg, "k_pg")
        self.k_og = as_positive_scalar(k_og, "k_og")
        self.k_fp = as_positive_scalar(k_fp, "k_fp")
        self.k_fi = as_positive_scalar(k_fi, "k_fi", allow_zero=True)
        self.f_d = as_positive_scalar(f_d, "f_d")
        self.max_speed = as_positive_scalar(max_speed, "max_speed")
        if integral_limit is None:
            self.integral_limit = self.max_speed / self.k_fi if self.k_fi > 0.0 else math.inf
        else:
            self.integral_limit = as_positive_scalar(integral_limit, "integral_limit")
        self.integration_threshold = (
            None
            if integration_threshold is None
            else float(as_positive_scalar(integration_threshold, "integration_threshold", allow_zero=True))
        )
        self.execution_tolerance = float(as_positive_scalar(execution_tolerance, "execution_tolerance",
                                                            allow_zero=True))
        self.k_yield = float(as_positive_scalar(k_yield, "k_yield", allow_zero=True))
        self.yield_deadband = float(as_positive_scalar(yield_deadband, "yield_deadband", allow_zero=True))
        self.yield_time_constant = float(as_positive_scalar(yield_time_constant, "yield_time_constant",
                                                            allow_zero=True))
        self.stem_base: NDArray[np.float64] | None = None
        self.target: NDArray[np.float64] | None = None
        self.n_c = np.full(3, np.nan)
        self.reset()

    def reset(self) -> None:
        """Clear the force integral, its latch and the last-update diagnostics (keeps the target)."""
        self.integral = 0.0
        self._integrating = self.integration_threshold is None
        self.saturated = False
        self.position_error = math.nan
        self.alignment = math.nan
        self.force_along_nc = math.nan
        self.v_gt = np.zeros(3)
        self.executed_along_nc = math.nan
        self.motion_executed: bool | None = True
        self._along_executed = True
        self.yield_force: tuple[float, float, float] | None = None  # the low-passed wrist force [N]

    def set_target(self, stem_base: ArrayLike, target: ArrayLike) -> None:
        """Set p_sb and p_gd [m]; n_c of ``eq:contr_dir``.

        Raises:
            InvalidInputError: p_gd = p_sb (n_c undefined).
        """
        p_sb = as_position(stem_base, "stem_base")
        p_gd = as_position(target, "target")
        offset = p_gd - p_sb
        norm = float(np.linalg.norm(offset))
        if norm < 1e-9:
            raise InvalidInputError(f"target must differ from stem_base (n_c undefined), got both {p_gd}")
        self.stem_base, self.target, self.n_c = p_sb, p_gd, offset / norm
        self.motion_executed, self._along_executed = True, True  # judged on the next command

    def update(self, gripper_pose: ArrayLike, force: ArrayLike, dt: float, *,
               executed: ArrayLike | None = None) -> NDArray[np.float64]:
        """V_g ``(6,)`` [m/s; rad/s] from the gripper pose {G}, the tared wrist ``force`` [N,
        world; sign convention in the module docstring] and the time step ``dt`` [s].

        ``executed``: the gripper's linear velocity [m/s] (world) that the last command achieved
        (e.g. J_g qdot of the QP's answer), ``None``: taken as executed. Sets ``motion_executed``:
        whether the last command's translation happened (within ``execution_tolerance`` or half of
        it), ``None`` when what it asked was within ``execution_tolerance`` (too small to tell).
        """
        pose = as_pose(gripper_pose, "gripper_pose")
        f = as_position(force, "force")
        dt = as_time_step(dt)
        if self.target is None:
            raise InvalidInputError("StemStretching.update needs a target: call set_target(p_sb, p_gd) first")
        n = self.n_c.tolist()
        if executed is None:
            self.executed_along_nc, self.motion_executed, self._along_executed = math.nan, True, True
        else:
            achieved = as_position(executed, "executed").tolist()
            asked, tolerance = self.v_gt.tolist(), self.execution_tolerance
            asked_along = dot(n, asked)
            self.executed_along_nc = dot(n, achieved)
            # The integral holds when the motion along n_c was not executed (the force loop's own axis).
            self._along_executed = _executed(abs(asked_along - self.executed_along_nc), abs(asked_along), tolerance)
            # The whole translation (along n_c and the projected position) for the phase machine's
            # clock; an ask within the tolerance says nothing either way (None): with 0.2 N of force
            # noise the P-term's ask dithers around 1 mm/s, and counting those ticks as executed reset
            # the clock of a blocked gripper every second.
            miss, size = norm(sub(asked, achieved)), norm(asked)
            self.motion_executed = None if size <= tolerance and miss <= tolerance else _executed(miss, size, tolerance)
        (_, y0, _, p0), (_, y1, _, p1), (_, y2, _, p2) = pose[:3].tolist()
        y_g = (y0, y1, y2)
        # eq:gr_pos_contr on the space orthogonal to n_c.
        e_pg = sub((p0, p1, p2), self.target.tolist())
        projected = sub(e_pg, scale(dot(n, e_pg), n))
        v_p = scale(-self.k_pg, projected)
        # Beyond the paper: yield to the force across n_c above the deadband (see k_yield).
        f_list = f.tolist()
        force_along = dot(n, f_list)
        if self.k_yield > 0.0:
            f_lp = self._low_passed_force(f_list, dt)
            f_across, raw_across = sub(f_lp, scale(dot(n, f_lp), n)), sub(f_list, scale(force_along, n))
            if norm(raw_across) > RAW_YIELD_FACTOR * self.yield_deadband:
                f_across = raw_across  # a push far above the noise: yield without the filter's lag
            across = norm(f_across)
            if across > self.yield_deadband:
                v_p = add(v_p, scale(-self.k_yield * (1.0 - self.yield_deadband / across), f_across))
        # eq:gr_forc_contr: PI along n_c with conditional integration.
        v_f = scale(-self._force_command(force_along, dt), n)
        # eq:rot_contr
        v_gw = scale(-self.k_og, cross(n, y_g))
        self.position_error = norm(projected)
        self.alignment = math.atan2(norm(v_gw) / self.k_og, dot(y_g, n))
        self.force_along_nc = force_along
        v_gt = add(v_p, v_f)
        self.v_gt = np.array(v_gt)
        return np.array((*v_gt, *v_gw))

    def _low_passed_force(self, f: list[float], dt: float) -> tuple[float, float, float]:
        """The wrist force [N] low-passed with ``yield_time_constant``, from zero after :meth:`reset`
        (the force is tared there; a first noisy sample taken as is would kick the gripper)."""
        tau, last = self.yield_time_constant, self.yield_force
        if tau == 0.0:
            self.yield_force = (f[0], f[1], f[2])
        else:
            last = last if last is not None else (0.0, 0.0, 0.0)
            a = -math.expm1(-dt / tau)
            self.yield_force = (last[0] + a * (f[0] - last[0]), last[1] + a * (f[1] - last[1]),
                                last[2] + a * (f[2] - last[2]))
        return self.yield_force

    def _force_command(self, force_along: float, dt: float) -> float:
        """The saturated speed command of ``eq:gr_forc_contr`` along n_c [m/s] for n_c^T f =
        ``force_along`` [N]; advances the integral (conditional integration, see the class)."""
        e_fg = force_along - self.f_d
        if (
            not self._integrating
            and self.integration_threshold is not None
            and force_along > self.integration_threshold
        ):
            self._integrating = True
        integral = self.integral
        if self._integrating and self._along_executed:
            candidate = min(max(integral + e_fg * dt, -self.integral_limit), self.integral_limit)
            command = self.k_fp * e_fg + self.k_fi * candidate
            # Hold the integral while the command is saturated and integrating pushes it further out.
            if abs(command) <= self.max_speed or (command > 0.0) != (e_fg > 0.0):
                integral = candidate
        self.integral = integral
        command = self.k_fp * e_fg + self.k_fi * integral
        self.saturated = abs(command) > self.max_speed
        return min(max(command, -self.max_speed), self.max_speed)
