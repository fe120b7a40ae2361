"""What the control loop hands on unchecked stays checked: the configuration's joint vector and the
runner's command (oracles: ``np.isfinite`` per entry, pinocchio's placements)."""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.robot.description import HOME_Q


def test_configuration_update_keeps_as_vectors_checks_and_copy():
    """The control loop's inline path of ``Configuration.update`` refuses what ``as_vector`` refuses
    (NaN/inf at any index, another size) with the message naming ``Configuration q``, converts
    other dtypes, and keeps a copy (changing the caller's array later changes nothing).
    Catches: the finiteness test dropped from the inline path, the caller's array kept."""
    config = Configuration.dual_ur5e()
    q = np.asarray(HOME_Q, float) + 0.1
    config.update(q)
    expected = config.frame_pose("camera").homogeneous.copy()
    q[0] += 1.0
    assert config.q[0] == q[0] - 1.0
    assert config.frame_pose("camera").homogeneous.tobytes() == expected.tobytes()
    for index in (0, 5, 11):
        for bad in (np.nan, np.inf, -np.inf):
            wrong = np.asarray(HOME_Q, float).copy()
            wrong[index] = bad
            with pytest.raises(InvalidInputError, match=r"Configuration q must be finite"):
                config.update(wrong)
    with pytest.raises(InvalidInputError, match=r"Configuration q must have shape \(12,\)"):
        config.update(np.zeros(13))
    config.update(np.asarray(HOME_Q, np.float32))
    assert config.q.dtype == np.float64
    assert config.q.tobytes() == np.asarray(np.asarray(HOME_Q, np.float32), np.float64).tobytes()


def test_command_check_by_sum_then_by_entry():
    """The runner's fast command check passes a command whose speeds have a finite sum and hands
    any other to the full check: opposite infinities (a NaN sum) and a NaN among huge values are
    refused at every pair of positions, finite values whose sum overflows or cancels are
    accepted (oracle: np.isfinite on each entry). Catches: a fast check that passes a non-finite
    command (e.g. one testing only the first and last speeds, or none)."""
    from harvest_qp.runtime.runner import Command, as_command

    rng = np.random.default_rng(3)
    for i in range(12):
        for j in range(12):
            if i == j:
                continue
            for a, b in ((np.inf, -np.inf), (np.nan, 1e308), (-np.inf, np.nan)):
                qdot = rng.normal(size=12)
                qdot[i], qdot[j] = a, b
                assert not np.isfinite(qdot).all()
                with pytest.raises(InvalidInputError, match="finite"):
                    as_command(Command(qdot=qdot))
    for qdot in (np.array([1e308, 1e308, -1e308] * 4), np.array([1.7e308] * 6 + [-1.7e308] * 6),
                 np.full(12, 1e308), rng.normal(size=12)):
        assert np.isfinite(qdot).all()
        assert as_command(Command(qdot=qdot)).qdot is qdot
