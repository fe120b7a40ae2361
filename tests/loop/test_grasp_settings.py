"""The grasping settings reach the episode: the yield's three settings and eq:final_vc's feed-forward.

Oracles: the settings given here, and for the feed-forward eq:final_vc's term computed from the
episode's own log (v_gt, p_c, p_sb at the switch) by :class:`GraspFeedForward`, whose formula is
checked by hand in tests/references/test_coordination.py.
"""

from __future__ import annotations

import numpy as np

from harvest_qp.config.settings import check_settings
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.references import GraspFeedForward


def test_the_yield_settings_reach_the_stretching_law():
    """Catches: a setting read from the schema but not handed to StemStretching (the review found
    none of the three tested; the yield then silently keeps its library defaults)."""
    settings = check_settings({"grasping": {"k_yield": 0.007, "yield_deadband": 0.3, "yield_time_constant": 0.25}})
    law = HarvestController(settings).stretching
    assert (law.k_yield, law.yield_deadband, law.yield_time_constant) == (0.007, 0.3, 0.25)
    default = HarvestController(check_settings({})).stretching
    assert (default.k_yield, default.yield_deadband, default.yield_time_constant) == (0.004, 0.5, 0.1)


def test_feed_forward_off_by_default_and_on_adds_exactly_its_term(cli_episode):
    """Seed 0 with the default settings (feed-forward off) and with ``grasping.feed_forward=true``:
    the two episodes are equal up to the switch; on the switch tick (same state in both) the camera
    reference differs by exactly eq:final_vc's term of that tick's v_gt, p_c and p_sb, and that term
    is not zero. Catches: the setting ignored (no difference), or the term added while off (the
    default episode would then differ from the paper's law by it)."""
    args = cli_episode.scene_args
    _, off_metrics, off, _ = cli_episode(0, *args)
    _, on_metrics, on, _ = cli_episode(0, *args, "--set", "grasping.feed_forward=true")
    t_switch = off_metrics["t_bimanual_start"]
    assert t_switch is not None and on_metrics["t_bimanual_start"] == t_switch
    k = int(np.flatnonzero(off["value/phase"] >= 1)[0])
    assert off["t"][k] == on["t"][k]
    np.testing.assert_array_equal(on["value/V_c"][:k], off["value/V_c"][:k])
    np.testing.assert_array_equal(on["q"][: k + 1], off["q"][: k + 1])
    term = GraspFeedForward()(on["value/V_g"][k, :3], on["value/p_c"][k], on["value/p_sb"][k])
    assert np.linalg.norm(term) > 1e-4
    np.testing.assert_allclose(on["value/V_c"][k] - off["value/V_c"][k], term, atol=1e-12)
