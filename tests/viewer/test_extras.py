"""The paper episode's viewer extras: the controller's per-tick values as ViewerFrame fields."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from harvest_qp.loop.controller import Phase
from harvest_qp.viewer import ViewerFrame, paper_episode_extras


def _command(**values):
    base = {"phase": float(Phase.BIMANUAL), "theta": 0.01, "p_r": [0.1, 0.2, 0.3], "p_sb": [0.1, 0.2, 0.31],
            "p_gd": [np.nan] * 3, "V_c": np.arange(6.0), "V_g": -np.arange(6.0)}
    base.update(values)
    return SimpleNamespace(values={k: np.asarray(v, dtype=float) for k, v in base.items()})


def test_extras_name_the_phase_draw_the_roi_and_leave_out_unknown_points():
    """Catches: the ROI sphere missing from `harvest-qp run --viewer meshcat` (the CLI drew no
    markers before), NaN points (p_gd before the switch) sent to the viewer, a field name the
    viewer does not know."""
    extras = paper_episode_extras(0.35)(None, _command())
    assert extras["phase"] == "bimanual" and extras["theta"] == 0.01
    np.testing.assert_array_equal(extras["roi_center"], [0.1, 0.2, 0.3])
    assert extras["roi_radius"] == 0.35
    assert "p_gd" not in extras
    np.testing.assert_array_equal(extras["v_g"], -np.arange(6.0))
    assert set(extras) <= set(ViewerFrame.__dataclass_fields__)


def test_extras_copy_the_values_the_viewer_draws_later():
    """The viewer draws on its own thread: a controller that reuses its arrays must not change
    what was observed."""
    command = _command(p_gd=[0.0, 0.1, 0.2])
    extras = paper_episode_extras(0.35)(None, command)
    command.values["p_gd"][:] = 9.0
    np.testing.assert_array_equal(extras["p_gd"], [0.0, 0.1, 0.2])
