"""``MapCollisionFeed._checked_q``'s fast path for the loop's own q (a float64 ``(12,)`` array).

The loop hands ``obs.q`` (the robot's float64 array) every tick; the check passes it through
without ``np.asarray``. Oracle: the same feed fed the same q as a list (the generic path),
and the error messages the generic check gives for bad shapes.
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from tests.perception.test_obstacle_map import _controller


def test_feed_q_fast_path_equals_the_generic_check():
    """A float64 (12,) array gives the cells and distances a list of the same numbers gives;
    a float64 array of another shape (13,), (12, 1) or (1, 12) is refused with the generic
    message (the fast path must test the exact shape), a float32 or int array converted as before.
    Catches: a fast path that only checks the dtype or the length (a (12, 1) or (13,) q read
    by the compiled kinematics), or that hands on another array than the one given."""
    config, _, _, _, feed = _controller(True, ahead=0.09)
    q = config.q + 0.05 * np.sin(np.arange(config.nv))
    assert feed._checked_q(q) is q
    n_fast = feed.update(q)
    fast = (feed._count.copy(), feed._dist.copy(), feed.cells.copy())
    n_generic = feed.update(q.tolist())
    assert n_fast == n_generic > 0
    assert np.array_equal(fast[0], feed._count) and fast[1].tobytes() == feed._dist.tobytes()
    assert np.array_equal(fast[2], feed.cells)
    for bad in (np.zeros(config.nv + 1), np.zeros((config.nv, 1)), np.zeros((1, config.nv))):
        with pytest.raises(InvalidInputError, match=r"q must have shape \(12,\)"):
            feed.update(bad)
    for other in (q.astype(np.float32), np.zeros(config.nv, dtype=np.int64)):
        checked = feed._checked_q(other)
        assert checked.dtype == np.float64 and np.array_equal(checked, other.astype(np.float64))
