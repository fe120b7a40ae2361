"""HarvestController pieces against hand-computed values (no episode); its laws are tested in tests/references."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.loop.controller import HarvestController, Phase
from harvest_qp.loop.settings import DEFAULTS, check_settings


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def test_safe_stop_decelerates_within_the_acceleration_limit(controller):
    """Each tick of an abort lowers every joint speed by at most a_max dt, to exactly zero."""
    controller.state.previous_qdot = np.linspace(-0.5, 0.5, 12)
    a_max = DEFAULTS["qp"]["limits"][2]["max_acceleration"]
    previous = controller.state.previous_qdot.copy()
    for _ in range(200):
        qdot = controller._safe_stop()
        assert np.all(np.abs(qdot - previous) <= a_max * controller.dt + 1e-12)
        assert np.all(np.abs(qdot) <= np.abs(previous) + 1e-12)
        controller.state.previous_qdot = previous = qdot
    assert not np.any(qdot)
    assert controller.phase == Phase.APPROACH
