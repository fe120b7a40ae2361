"""Judging a sweep as a grower would: success on the lab's truth, each failure in a class, time to pre-cut.

Used by ``benchmarks/sweep_robustness.py`` (issue 20's evidence) on the rows of ``sweep.csv``.
Success is the episode's own ``success`` and, on the lab's ground truth, the true stem never torn,
the true stem tension never above 2 f_d and at most 50 ms (25 ticks) with a robot contact.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from harvest_qp.perception.grasp_target import CHOICE_NO_TARGET
from harvest_qp.sweep.stats import STATUS_OK, wilson_interval

__all__ = ["CLASSES", "MAX_CONTACT_TICKS", "failure_class", "grower_success", "summarise"]

#: Most ticks (2 ms each) with a robot contact that a grower would still accept.
MAX_CONTACT_TICKS = 25
#: A grasp target farther than this from the true hanging stem [deg] (the swing bound, 30, plus 10 of slack).
MAX_TARGET_ANGLE_DEG = 40.0
CLASSES = ("lab", "safety", "target", "priority", "perception", "camera", "other")


def grower_success(row: Mapping[str, Any]) -> bool:
    """The episode's ``success`` and, on the lab's truth: no tear, tension <= 2 f_d, <= 50 ms of contact."""
    if row.get("status") != STATUS_OK or not row.get("success"):
        return False
    f_d = float(row.get("f_d") or 3.0)
    tension = row.get("true_tension_max")
    return (not row.get("stem_torn") and (tension is None or float(tension) <= 2.0 * f_d)
            and int(row.get("contacts") or 0) <= MAX_CONTACT_TICKS)


#: The class of each abort cause (``metrics.json`` ``abort_cause``, :data:`harvest_qp.harvest.phases.ABORT_CAUSES`);
#: the others (the crop's side, QP failures, an external abort) are classed by the rest of the row.
_CLASS_OF_ABORT_CAUSE = {
    "force": "safety", "non_finite": "safety", "no_stem_base": "perception", "stem_lost": "perception",
    "no_grasp_target": "target", "no_precut": "priority", "not_executed": "priority", "no_switch": "camera",
}

#: The camera arm's success criteria (``metrics.json`` ``criteria``).
_CAMERA_CRITERIA = frozenset({"centred", "inside_roi"})


def failure_class(row: Mapping[str, Any]) -> str:
    """Why a row failed, in issue 20's classes.

    * ``lab``: the episode did not run to its end (an exception, a dead or timed-out process, a
      controller or robot error inside the episode: ``criteria.completed`` false);
    * ``safety``: a torn stem, a true tension above 2 f_d, more than 50 ms of contact, a force abort
      or a non-finite sensor reading;
    * ``target``: no grasp target (the crop level with or above the stem base; or the switch
      timeout after the switch test had passed), or one more than
      :data:`MAX_TARGET_ANGLE_DEG` off the true hanging stem or above the true stem base;
    * ``priority``: the bimanual phase ran but pre-cut was never reached (position or alignment
      never converged; the pre-cut timeout's abort names the tests that failed);
    * ``perception``: no stem base found (also at the switch timeout), or the stem lost;
    * ``camera``: pre-cut reached, only the camera arm's criteria failed (outside the ROI or not
      centred at the end), or the camera arm never met the switch test (the switch timeout);
    * ``other``: anything else (listed with its reason).

    Aborts are classed by the episode's ``abort_cause``, never by the words of its reason.
    """
    if row.get("status") != STATUS_OK or row.get("criteria.completed") is False:
        return "lab"
    f_d = float(row.get("f_d") or 3.0)
    tension = row.get("true_tension_max")
    by_cause = _CLASS_OF_ABORT_CAUSE.get(str(row.get("abort_cause") or ""))
    if (row.get("stem_torn") or (tension is not None and float(tension) > 2.0 * f_d)
            or int(row.get("contacts") or 0) > MAX_CONTACT_TICKS or by_cause == "safety"):
        return "safety"
    if by_cause in ("perception", "target"):
        return by_cause
    choice = str(row.get("p_gd_choice") or "")
    angle = row.get("target_angle_off_stem_deg")
    if (choice == CHOICE_NO_TARGET or row.get("target_above_stem_base")
            or (angle is not None and float(angle) > MAX_TARGET_ANGLE_DEG)):
        return "target"
    if row.get("phase_reached") == "bimanual" or by_cause == "priority":
        return "priority"
    failed = {key.removeprefix("criteria.") for key, value in row.items()
              if key.startswith("criteria.") and value is False}
    if (row.get("phase_reached") == "precut" and failed and failed <= _CAMERA_CRITERIA) or by_cause == "camera":
        return "camera"
    return "other"


def _percentile(values: Sequence[float], q: float) -> float:
    """numpy's (linear) percentile, NaN for no values."""
    return float(np.percentile(values, 100 * q)) if values else math.nan


def summarise(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Success (the episode's and the grower's) with 95 % Wilson intervals, failures by class, pre-cut times."""
    n = len(rows)
    own = sum(1 for r in rows if r.get("status") == STATUS_OK and r.get("success"))
    grower = sum(1 for r in rows if grower_success(r))
    failures: dict[str, list[int]] = {c: [] for c in CLASSES}
    for row in rows:
        if not grower_success(row):
            failures[failure_class(row)].append(int(row["seed"]))
    precut = [float(r["t_precut"]) for r in rows if grower_success(r) and r.get("t_precut") is not None]
    return {
        "episodes": n,
        "success": own, "success_interval": wilson_interval(own, n),
        "grower_success": grower, "grower_interval": wilson_interval(grower, n),
        "failures": {c: seeds for c, seeds in failures.items() if seeds},
        "abort_reasons": dict(Counter(str(r.get("abort_reason")) for r in rows if not grower_success(r))),
        "t_precut_median": _percentile(precut, 0.5), "t_precut_p90": _percentile(precut, 0.9),
        "torn": sum(1 for r in rows if r.get("stem_torn")),
        "contact_over_50ms": sum(1 for r in rows if int(r.get("contacts") or 0) > MAX_CONTACT_TICKS),
    }
