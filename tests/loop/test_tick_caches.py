"""What HarvestController.step keeps between ticks (glue7) stays true to the state it stands for.

* The camera and gripper placements are read through proxies of pinocchio's ``data.oMf`` kept
  from tick to tick: the logged camera pose must be the configuration's frame pose at the
  tick's q, also in a deep copy of the controller and after the configuration's data object is
  replaced (oracle: a separate :class:`Configuration` at the same q, pinocchio's own placement).
* ``_active_pair_columns`` reuses the last tick's name lists while the limit's pair tables are
  the same objects and the active indices the same: a replaced table must not be read as the
  old one (oracle: the limit's own ``active_pair_distances``).
* ``Configuration.update``'s inline fast path keeps ``as_vector``'s checks and copy.
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.configuration import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.loop.controller import HarvestController
from harvest_qp.loop.settings import check_settings
from harvest_qp.robot.description import HOME_Q
from harvest_qp.runner import Observation


class _Robot:
    """What HarvestController.reset reads of a robot."""

    control_period = 0.002

    def __init__(self, q: np.ndarray) -> None:
        self.q = np.asarray(q, float)

    def joint_positions(self) -> np.ndarray:
        return self.q.copy()


def _observation(t: float, q: np.ndarray) -> Observation:
    return Observation(time=t, q=q, qdot=np.zeros(12), force=np.zeros(3), cloud=None, new_cloud=False)


def _assert_logged_pose_is_pinocchios(command, q: np.ndarray) -> None:
    oracle = Configuration.dual_ur5e(q)
    pose = oracle.frame_pose("camera").homogeneous
    values = command.values
    assert values["p_c"].tobytes() == pose[:3, 3].tobytes()
    assert values["z_c"].tobytes() == pose[:3, 2].tobytes()
    assert values["x_c"].tobytes() == pose[:3, 0].tobytes()


@pytest.fixture(scope="module")
def controller():
    c = HarvestController(check_settings({}))
    c.reset(_Robot(HOME_Q))
    return c


def test_logged_camera_pose_is_the_configurations(controller):
    """The camera pose step logs (p_c, z_c, x_c: read through the kept oMf proxies) is pinocchio's
    placement at the tick's q, tick after tick, also after the configuration's data object is
    replaced; a copy of the controller's state leaves the proxies out (a copied proxy would be
    a frozen copy of the old placement; a stepped controller cannot be deep-copied today, its
    QP solver holds a module, but its state must not carry them when it can). Catches: the
    proxies not made again for a new data object, the proxies in the copied state (no
    __getstate__)."""
    c = controller
    rng = np.random.default_rng(71)
    home = np.asarray(HOME_Q, float)
    for k in range(3):
        q = home + 0.05 * rng.normal(size=12)
        _assert_logged_pose_is_pinocchios(c.step(_observation(0.002 * (k + 1), q)), q)
    assert c._pose_refs is not None  # kept between ticks
    state = c.__getstate__()
    assert state["_pose_refs"] is None and c._pose_refs is not None
    assert state.keys() == c.__dict__.keys()
    config = c.configuration
    config.data = config.model.createData()
    for k in range(2):
        q = home + 0.05 * rng.normal(size=12)
        _assert_logged_pose_is_pinocchios(c.step(_observation(0.01 + 0.002 * k, q)), q)
    # A controller restored from a state without proxies makes them again.
    twin = HarvestController.__new__(HarvestController)
    twin.__dict__.update(c.__getstate__())
    q = home + 0.05 * rng.normal(size=12)
    _assert_logged_pose_is_pinocchios(twin.step(_observation(0.03, q)), q)


def test_pair_columns_follow_a_replaced_pair_table(controller):
    """Same active indices, but the limit's pair table replaced by another (new object): the
    columns list the new pairs (the limit's own listing), not the last tick's names.
    Catches: the name lists reused on equal active indices alone."""
    c = controller
    lim = c.collision
    q = c.configuration.q.copy()
    c.qp.reset(q)
    c.qp.step(q)
    first = c._active_pair_columns()
    assert len(first) > 0 and list(first) == lim.active_pair_distances()
    saved = lim.pair_a, lim.pair_b
    try:
        lim.pair_a, lim.pair_b = saved[1].copy(), saved[0].copy()  # every pair's names swapped
        again = c._active_pair_columns()
        assert list(again) == lim.active_pair_distances() == c._active_pairs()
        assert [(a, b) for a, b, _ in again] == [(b, a) for a, b, _ in first]
    finally:
        lim.pair_a, lim.pair_b = saved
    assert list(c._active_pair_columns()) == lim.active_pair_distances()


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
    from harvest_qp.runner import Command, _as_command_fast

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
                    _as_command_fast(Command(qdot=qdot))
    for qdot in (np.array([1e308, 1e308, -1e308] * 4), np.array([1.7e308] * 6 + [-1.7e308] * 6),
                 np.full(12, 1e308), rng.normal(size=12)):
        assert np.isfinite(qdot).all()
        assert _as_command_fast(Command(qdot=qdot)).qdot is qdot
