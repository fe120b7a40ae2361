"""Judging sweep rows as a grower would (harvest_qp.sweep.robustness), on hand-made rows.

Oracle: the rules written out by hand per row (issue 20's classes). Catches: a torn stem or a
50 ms contact counted as a success because the episode's own flag said so; a failure put in the
wrong class; an interval computed on the episode's flag instead of the grower's.
"""

from __future__ import annotations

import math

import pytest

from harvest_qp.perception.grasp_target import CHOICE_ALONG_STEM, CHOICE_NO_TARGET
from harvest_qp.sweep.robustness import failure_class, grower_success, summarise

GOOD_CHOICE = "free, in the cone, swing clear (eq:attr_point among them)"


def row(seed, **kw):
    base = {"seed": seed, "status": "ok", "success": True, "f_d": 3.0, "true_tension_max": 3.2, "contacts": 0,
            "stem_torn": False, "abort_reason": None, "p_gd_choice": GOOD_CHOICE, "phase_reached": "precut",
            "t_precut": 15.0}
    base.update(kw)
    return base


@pytest.mark.parametrize(("kw", "grower", "cls"), [
    ({}, True, None),
    ({"stem_torn": True}, False, "safety"),  # the episode's own flag may still be True
    ({"true_tension_max": 6.5}, False, "safety"),
    ({"contacts": 26}, False, "safety"),
    ({"contacts": 25}, True, None),
    ({"success": False, "abort_reason": "stem force 6.10 N above the limit 6.00 N", "abort_cause": "force",
      "phase_reached": "abort"},
     False, "safety"),
    ({"success": False, "abort_reason": "no stem base found within 30 s", "abort_cause": "no_stem_base",
      "phase_reached": "abort"},
     False, "perception"),
    ({"success": False, "p_gd_choice": CHOICE_NO_TARGET, "phase_reached": "approach"}, False, "target"),
    ({"success": False, "p_gd_choice": CHOICE_ALONG_STEM, "phase_reached": "bimanual"}, False, "priority"),
    ({"success": False, "phase_reached": "bimanual", "t_precut": None}, False, "priority"),
    ({"success": False, "phase_reached": "bimanual", "target_angle_off_stem_deg": 164.0}, False, "target"),
    ({"success": False, "phase_reached": "bimanual", "target_above_stem_base": True}, False, "target"),
    ({"status": "error", "success": None}, False, "lab"),
    # a controller that raised inside the episode: metrics were written, but it did not run to its end
    ({"success": False, "phase_reached": "bimanual", "t_precut": None, "criteria.completed": False,
      "episode_error": "controller.step failed: RuntimeError: planted"}, False, "lab"),
    # the phase timeouts: a pre-cut timeout names the force too, yet it is no force abort
    ({"success": False, "phase_reached": "abort", "abort_reason": "no pre-cut within 30.0 s of the switch: force "
      "along n_c 2.51 N (f_d 3.00 N +- 10 %), position error 7.2 mm (> 5.0 mm)",
      "abort_cause": "no_precut"}, False, "priority"),
    ({"success": False, "phase_reached": "abort", "abort_reason": "no switch within 40.0 s: the camera is 0.663 m "
      "from the ROI centre (switch within 0.368 m), stem base found", "abort_cause": "no_switch"}, False, "camera"),
    ({"success": False, "phase_reached": "abort", "abort_reason": "no switch within 40.0 s: the switch test passed "
      "(last at 39.9 s) but no grasp target was found",
      "abort_cause": "no_grasp_target"}, False, "target"),
    ({"success": False, "phase_reached": "abort", "abort_reason": "no switch within 20.0 s: the camera is 0.300 m "
      "from the ROI centre (switch within 0.368 m), stem base not found",
      "abort_cause": "no_stem_base"}, False, "perception"),
    ({"success": False, "phase_reached": "abort", "abort_reason": "non-finite grasp state (force along n_c nan, "
      "magnitude nan, crop side 0.07, position error 0.0, alignment 0.0)",
      "abort_cause": "non_finite"}, False, "safety"),
    ({"success": False, "criteria.centred": False, "criteria.inside_roi": False, "criteria.aligned": True},
     False, "camera"),
    ({"success": False, "criteria.centred": False, "criteria.aligned": False}, False, "other"),
])
def test_each_row_is_judged_and_classed(kw, grower, cls):
    r = row(1, **kw)
    assert grower_success(r) is grower
    if cls is not None:
        assert failure_class(r) == cls


def test_aborts_are_classed_by_their_cause_not_by_the_words_of_their_reason():
    """A pre-cut timeout's reason names the force and "above" a tolerance; classed by text it read as a
    force abort (safety). Catches: classing on substrings of the reason."""
    r = row(1, success=False, phase_reached="abort", abort_cause="no_precut",
            abort_reason="no pre-cut within 30.0 s of the switch: force along n_c above the limit")
    assert failure_class(r) == "priority"
    assert failure_class(row(2, success=False, phase_reached="abort", abort_cause="force",
                             abort_reason="anything")) == "safety"


def test_summary_counts_the_growers_success_and_its_interval():
    rows = [row(s) for s in range(8)] + [row(8, stem_torn=True), row(9, success=False, phase_reached="bimanual",
                                                                      t_precut=None, p_gd_choice=GOOD_CHOICE)]
    rows[1]["t_precut"] = 25.0
    s = summarise(rows)
    assert (s["episodes"], s["success"], s["grower_success"]) == (10, 9, 8)
    assert s["failures"] == {"safety": [8], "priority": [9]}
    assert s["torn"] == 1
    # Wilson 95 % for 8/10, by hand: centre (0.8 + z^2/20) / (1 + z^2/10), half-width as in the formula
    z = 1.959963984540054
    centre = (0.8 + z * z / 20) / (1 + z * z / 10)
    half = z / (1 + z * z / 10) * math.sqrt(0.8 * 0.2 / 10 + z * z / 400)
    assert s["grower_interval"] == pytest.approx((centre - half, centre + half))
    assert s["t_precut_median"] == 15.0 and s["t_precut_p90"] == pytest.approx(15.0 + 0.3 * 10.0)


def test_the_reason_of_an_episode_stopped_by_an_error_is_its_error():
    """A review found "no abort_reason (success false)" for an episode whose controller raised."""
    from harvest_qp.sweep.stats import failure_reason

    failed = row(1, success=False, phase_reached="bimanual", t_precut=None, **{"criteria.completed": False},
                 episode_error="controller.step failed: RuntimeError: planted")
    assert failure_reason(failed) == "controller.step failed: RuntimeError: planted"
