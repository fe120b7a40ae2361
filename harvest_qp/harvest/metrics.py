"""Episode metrics (``metrics.json``) and the ``success`` criteria of the paper episode.

Computed after the episode from the runner's log in two parts: :func:`controller_metrics`, from the
controller's own per-tick values (``value/*``) and what any robot measures (joints, frames), the
same on the lab and on the real cell; and :func:`compute_metrics`, the lab's, which adds the
simulator's ground truth (``truth/*``, the scene) for what a robot cannot measure (true stem base,
contacts, tear, tension, capsule distances to the vine).

``success`` is all of (issue 7, section 5):

* camera inside the ROI at the end: distance to the *true* stem base <= 1.02 r, and the
  true theta < 2 deg;
* visible stem points at the end >= 3x those at the start (start counted as at least 1);
  "at the end" is the median over the frames of the last 0.5 s, "at the start" the first frame;
* mean force along n_c over the last second within 10 % of f_d, never above 2 f_d
  after the tare; the same for the lab's true stem tension (what the stem really feels: a wrist
  force held by a branch contact is not a stretched stem);
* alignment < 5 deg and projected position error < 5 mm at the end;
* no contact (the arms with anything, the held crop with the wood; the held crop brushing a
  leaf is counted in ``contacts_by_kind`` but fails nothing), no tear, no abort;
* pre-cut reached (``precut_reached``): the end state alone is not a harvest (an episode that ends
  before the pre-cut test passed, e.g. one cut short by ``episode.duration``, scored every end
  criterion true);
* the episode ran to its end (``completed``: the runner's ``episode_status``; a controller that
  raised mid-episode left no abort reason).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from harvest_qp.config import EpisodeConfig
from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import EpisodeError
from harvest_qp.harvest.environment import environment_capsules_for
from harvest_qp.harvest.phases import Phase
from harvest_qp.limits import CollisionAvoidance

__all__ = ["compute_metrics", "controller_metrics", "finite_or_none", "min_capsule_distance", "SUCCESS_KEYS"]

SUCCESS_KEYS = (
    "precut_reached", "inside_roi", "centred", "unveiled", "force_settled", "force_below_2fd", "true_tension_settled",
    "true_tension_below_2fd", "aligned", "position_error_small", "no_contact", "no_tear", "no_abort", "completed",
)


def _stem_base_raised(controller: Any) -> float | None:
    """How far [m] the frozen p_sb lies from the switch frame's own fit (``perception.stem_memory``); None
    without a switch."""
    switch = getattr(controller, "switch_snapshot", None)
    if switch is None or getattr(switch.stem, "base", None) is None:
        return None
    return float(np.linalg.norm(np.asarray(switch.stem_base) - np.asarray(switch.stem.base)))


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na < 1e-12 or nb < 1e-12:
        return float("nan")
    return float(np.degrees(np.arccos(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def finite_or_none(x: float | None) -> float | None:
    """``x`` as a float, or None when it is None or not finite (JSON has no NaN)."""
    return float(x) if x is not None and math.isfinite(float(x)) else None


def min_capsule_distance(q_log: np.ndarray, environment, every: int = 10) -> float:
    """Smallest surface distance [m] over every capsule pair (arm-arm, arm-stand, arm-vine)."""
    configuration = Configuration.dual_ur5e()
    collision = CollisionAvoidance.dual_ur5e(configuration, environment=environment)
    best = math.inf
    for q in q_log[::every]:
        configuration.update(q)
        best = min(best, float(collision.distances(configuration).min()))
    if len(q_log):
        configuration.update(q_log[-1])
        best = min(best, float(collision.distances(configuration).min()))
    return best


def _last_finite(log: dict, key: str) -> float:
    """The last finite value of a per-tick series (the failing tick of an episode logs NaN)."""
    values = np.asarray(log[key], dtype=float)
    finite_values = values[np.isfinite(values)]
    return float(finite_values[-1]) if len(finite_values) else math.nan


def _end_reason(phases, reached: Phase, duration: float) -> str | None:
    """Why an episode that ended in the bimanual phase without an abort had not reached pre-cut (the
    pre-cut timeout cannot fire when the switch came late), else None."""
    if reached != Phase.BIMANUAL or phases.abort_reason is not None or phases.t_switch is None:
        return None
    misses = phases.precut_misses() or "no bimanual tick"
    return f"no pre-cut when the episode ended {duration - phases.t_switch:.1f} s after the switch: {misses}"


def controller_metrics(log: dict, controller, settings: EpisodeConfig, *, mapper: str,
                       realtime_factor: float) -> tuple[dict[str, Any], dict[str, bool]]:
    """The metrics that need no ground truth, and their success checks (pre-cut reached, ``unveiled``, the
    force, the alignment, the position error, no abort, the episode completed): what the lab and the real
    cell both report.

    Raises:
        EpisodeError: the log holds no controller values (the episode failed before the first tick).
    """
    t = log["t"]
    n = len(t)
    if n == 0 or "value/phase" not in log:
        # Nothing to score: say what the runner saw instead of a KeyError.
        status = str(log.get("episode_status", "unknown"))
        lines = str(log.get("error", "")).strip().splitlines()
        if lines:
            # The controller (or a wrapper around it) or the robot failed before any value was logged.
            raise EpisodeError(f"the episode ended with status {status!r} before the controller logged its "
                               f"values: {lines[0]}")
        raise EpisodeError(
            f"the episode ({n} ticks, status {status!r}) logged no value/phase: the paper episode's metrics need "
            "HarvestController's per-tick values; a wrapper must pass the controller's Command values through"
        )
    st, phases = controller.state, controller.phases
    f_d = float(settings.grasping.f_d)
    # --- stem points seen: the first frame, at the switch, the median of the last 0.5 s
    frame_time, frame_stem = log["frame_time"], log["frame_stem_points"]
    start = int(frame_stem[0]) if len(frame_stem) else 0
    end = int(np.median(frame_stem[frame_time >= frame_time[-1] - 0.5])) if len(frame_stem) else 0
    at_switch = None
    if phases.t_switch is not None and len(frame_time):
        before = np.flatnonzero(frame_time <= phases.t_switch + 1e-9)
        at_switch = int(frame_stem[before[-1]]) if len(before) else None
    # --- grasping arm: the wrist force along n_c over the last second, its peak
    force_nc = log["value/force_nc"]
    last = t >= t[-1] - 1.0 + 1e-9
    force_mean = float(np.nanmean(force_nc[last])) if np.any(np.isfinite(force_nc[last])) else math.nan
    force_max = float(np.nanmax(force_nc)) if np.any(np.isfinite(force_nc)) else math.nan
    position_error = _last_finite(log, "value/position_error")
    alignment = math.degrees(_last_finite(log, "value/alignment"))
    reached = Phase(int(_last_finite(log, "value/phase")))
    configuration = Configuration.dual_ur5e()
    q = log["q"]
    violation = max(float(np.maximum(configuration.lower_limits - q, 0.0).max(initial=0.0)),
                    float(np.maximum(q - configuration.upper_limits, 0.0).max(initial=0.0)))
    metrics: dict[str, Any] = {
        "mapper": mapper,
        "episode_status": str(log["episode_status"]),
        "duration": float(n * float(log["control_period"])),
        "phase_reached": "abort" if reached == Phase.ABORT else reached.name.lower(),
        "t_bimanual_start": finite_or_none(phases.t_switch),
        "t_precut": finite_or_none(phases.t_precut),
        "final_distance_to_estimated_roi_center": finite_or_none(_last_finite(log, "value/roi_distance")),
        "roi_radius": float(settings.reaching.radius),
        "final_theta_estimated_roi_deg": finite_or_none(math.degrees(_last_finite(log, "value/theta"))),
        "visible_stem_points_start": start,
        "visible_stem_points_switch": at_switch,
        "visible_stem_points_end": end,
        "final_position_error": finite_or_none(position_error),
        "final_alignment_deg": finite_or_none(alignment),
        "force_mean_last_1s": finite_or_none(force_mean),
        "force_max": finite_or_none(force_max),
        "f_d": f_d,
        "max_joint_limit_violation": violation,
        "peak_joint_speed": float(np.abs(log["qdot"]).max()),
        "qp_failures": int(phases.qp_failures),
        "qp_backup_solves": int(phases.backup_solves),
        "abort_reason": phases.abort_reason,
        "abort_cause": phases.abort_cause,
        # why the runner stopped before the end (a controller or robot error), its first line; None when completed
        "episode_error": (str(log.get("error", "")).strip().splitlines() or [None])[0],
        "end_reason": _end_reason(phases, reached, float(n * float(log["control_period"]))),
        "p_gd_choice": getattr(controller, "target_choice", None),
        "stem_base_raised_at_switch": _stem_base_raised(controller),
        "estimated_stem_length": finite_or_none(st.stem_length),
        "realtime_factor": float(realtime_factor),
    }
    checks = {
        "precut_reached": phases.t_precut is not None,
        "unveiled": end >= 3 * max(start, 1),
        "force_settled": math.isfinite(force_mean) and abs(force_mean - f_d) <= 0.1 * f_d,
        "force_below_2fd": math.isfinite(force_max) and force_max <= 2.0 * f_d,
        "aligned": math.isfinite(alignment) and alignment < 5.0,
        "position_error_small": math.isfinite(position_error) and position_error < 0.005,
        "no_abort": phases.abort_reason is None,
        "completed": metrics["episode_status"] == "completed",
    }
    return metrics, checks


def compute_metrics(log: dict, robot, controller, settings: EpisodeConfig, *, mapper: str, seed: int,
                    realtime_factor: float) -> dict[str, Any]:
    """The lab episode's metrics (see the module docstring): :func:`controller_metrics` and the ground truth."""
    own, own_checks = controller_metrics(log, controller, settings, mapper=mapper, realtime_factor=realtime_factor)
    radius = float(settings.reaching.radius)
    t = log["t"]
    n = len(t)
    # --- camera, from the true stem base
    p_sb_true = np.asarray(robot.scene.stem_base, float)
    p_c, z_c, x_c = log["value/p_c"][-1], log["value/z_c"][-1], log["value/x_c"][-1]
    distance_true = float(np.linalg.norm(p_sb_true - p_c))
    theta_true = _angle_deg(z_c, p_sb_true - p_c)
    # --- the true stem tension over the last second, its peak
    last = t >= t[-1] - 1.0 + 1e-9
    tension = log.get("truth/stem_tension")
    tension_mean = float(np.mean(tension[last])) if tension is not None else float("nan")
    tension_max = float(np.max(tension)) if tension is not None else float("nan")
    # cutter: the blade closes along x_c; angle between x_c and the true stem seen in the image plane
    stem_end_true = log["truth/stem_end"][-1] if "truth/stem_end" in log else robot.scene.stem_end
    stem_dir = p_sb_true - stem_end_true
    stem_in_image = stem_dir - (stem_dir @ z_c) * z_c
    cutter_angle = _angle_deg(x_c, stem_in_image)
    if math.isfinite(cutter_angle):
        cutter_angle = min(cutter_angle, 180.0 - cutter_angle)
    # --- safety from the ground truth
    contact_keys = [k for k in log if k.startswith("truth/contacts_")] or ["truth/robot_contacts"]
    in_contact = np.zeros(n, dtype=bool)
    for key in contact_keys:
        # The held crop brushing a leaf (soft, it yields) is counted by kind but fails nothing: a
        # grower minds the arms touching the vine and the crop pressed on the wood, not a leaf.
        if key in log and key != "truth/contacts_crop_leaf":
            in_contact |= np.nan_to_num(log[key]) > 0
    contacts = int(np.count_nonzero(in_contact))  # ticks with a robot contact or the crop on the wood
    torn = bool(np.any(log["truth/stem_torn"] > 0)) if "truth/stem_torn" in log else False
    min_distance = min_capsule_distance(log["q"], environment_capsules_for(robot, ["branch", "cane"]))
    # --- the grasp target chosen at the switch, against the true stem: its angle off the hanging stem
    # (p_sb -> stem end) and whether it lies above the stem base (the crop turned upside down)
    target_angle, target_above = None, None
    bimanual = np.flatnonzero(log["value/phase"] >= Phase.BIMANUAL)
    if len(bimanual) and "truth/stem_end" in log:
        k = int(bimanual[0])
        p_gd = np.asarray(log["value/p_gd"][k], float)
        if np.all(np.isfinite(p_gd)):
            hanging = np.asarray(log["truth/stem_end"][k]) - p_sb_true
            target_angle = finite_or_none(_angle_deg(p_gd - p_sb_true, hanging))
            target_above = bool(p_gd[2] > p_sb_true[2])
    st = controller.state
    metrics: dict[str, Any] = {
        "seed": int(seed),
        **own,
        "final_distance_to_roi_center": distance_true,
        "final_theta_deg": theta_true,
        "final_cutter_stem_angle_deg": finite_or_none(cutter_angle),
        "true_tension_mean_last_1s": finite_or_none(tension_mean),
        "true_tension_max": finite_or_none(tension_max),
        "min_collision_distance": finite_or_none(min_distance),
        "contacts": contacts,
        "contacts_by_kind": {k.removeprefix("truth/contacts_"): int(np.count_nonzero(np.nan_to_num(log[k]) > 0))
                             for k in contact_keys if k in log},
        "min_vine_distance": (finite_or_none(float(np.nanmin(log["truth/min_vine_distance"])))
                              if "truth/min_vine_distance" in log else None),
        "stem_torn": torn,
        "target_angle_off_stem_deg": target_angle,
        "target_above_stem_base": target_above,
        "stem_base_error_at_switch": (
            float(np.linalg.norm(st.p_sb - p_sb_true)) if st.p_sb is not None else None
        ),
    }
    checks = {
        "inside_roi": distance_true <= 1.02 * radius,
        "centred": theta_true < 2.0,
        **own_checks,
        "true_tension_settled": tension is None or (math.isfinite(tension_mean)
                                                    and abs(tension_mean - float(settings.grasping.f_d))
                                                    <= 0.1 * float(settings.grasping.f_d)),
        "true_tension_below_2fd": tension is None or tension_max <= 2.0 * float(settings.grasping.f_d),
        "no_contact": contacts == 0,
        "no_tear": not torn,
    }
    metrics["criteria"] = {k: bool(checks[k]) for k in SUCCESS_KEYS}
    metrics["success"] = bool(all(checks.values()))
    return metrics
