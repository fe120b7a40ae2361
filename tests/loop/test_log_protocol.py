"""HarvestController's per-tick log protocol: its values as one row, its active pairs as columns.

The controller hands the runner its ~18 logged values as one float64 row
(``harvest_qp.runtime.log.ValueRow``) and its active collision pairs as three columns
(``harvest_qp.runtime.log.PairColumns``). Oracles: the collision limit's own ``active_pair_distances``,
pinocchio's frame placements, and the same episode handed to the runner through its generic
protocol (a wrapper that passes every value as a plain array in a dict and the pairs as a list
of tuples): the logs must be equal, with the same keys in the same order.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from harvest_qp.config.settings import check_settings, load_settings
from harvest_qp.configuration import Configuration
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.harvest.phases import Phase
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runtime.log import PairColumns
from harvest_qp.runtime.runner import run_episode
from harvest_qp.sim.paper_episode import build_robot, environment_capsules_for, episode_ground_truth


def _same(a, b) -> bool:
    """Equal dtype, shape and bytes (NaN and -0.0 included)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def test_pair_columns_read_as_the_pair_tuples(controller):
    """``_active_pair_columns`` lists the limit's own ``active_pair_distances``, also when a
    capsule name changes in place between two calls with the same pairs (the map's feed renames
    its obstacle slots) and when the pair table is replaced (same active indices, other pairs).
    Catches: the reused name lists kept after a rename (a stale cell name in the log) or on
    equal active indices alone."""
    c = controller
    q = c.configuration.q.copy()
    c.qp.reset(q)
    c.qp.step(q)
    pairs = c._active_pair_columns()
    assert type(pairs) is PairColumns and len(pairs) > 0
    listing = c.collision.active_pair_distances()
    assert pairs == listing and list(pairs) == listing and pairs[0] == listing[0]
    assert all(type(d) is float for _, _, d in pairs)
    names = c.collision.capsule_names
    index = int(c.collision.pair_a[c.collision.active_pairs[0]])
    old = names[index]
    names[index] = "renamed"
    try:
        again = c._active_pair_columns()
        assert list(again) == c.collision.active_pair_distances() and again[0][0] == "renamed"
    finally:
        names[index] = old
    assert list(c._active_pair_columns()) == c.collision.active_pair_distances()
    lim = c.collision
    saved = lim.pair_a, lim.pair_b
    try:
        lim.pair_a, lim.pair_b = saved[1].copy(), saved[0].copy()  # every pair's names swapped
        swapped = c._active_pair_columns()
        assert list(swapped) == lim.active_pair_distances()
        assert [(a, b) for a, b, _ in swapped] == [(b, a) for a, b, _ in pairs]
    finally:
        lim.pair_a, lim.pair_b = saved


class _Generic:
    """The controller behind the runner's generic protocol: values as a dict of new arrays,
    pairs as a list of tuples."""

    def __init__(self, inner: HarvestController) -> None:
        self.inner = inner

    def reset(self, robot) -> None:
        self.inner.reset(robot)

    def step(self, obs):
        command = self.inner.step(obs)
        values = {name: np.array(value) for name, value in command.values.items()}
        pairs = [tuple(pair) for pair in command.collision_pairs]
        return dataclasses.replace(command, values=values, collision_pairs=pairs)


def _episode(generic: bool, overrides: list[str], duration: float):
    settings = load_settings(tasks_dir() / "paper.yaml", ["camera.downsample=6", *overrides])
    robot = build_robot(settings, 0)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings.qp.environment))
    driven = _Generic(controller) if generic else controller
    return run_episode(robot, driven, duration=duration, ground_truth=episode_ground_truth(robot)), controller


@pytest.mark.parametrize(
    ("overrides", "duration"),
    [([], 0.4), (["safety.no_stem_timeout=0.1", "episode.stop_after_abort=0.05"], 0.5)],
    ids=["approach", "abort"],
)
def test_episode_log_equals_the_generic_protocols(overrides, duration):
    """A paper episode logged through the row and the pair columns equals the same episode
    through the generic dict and tuples, key by key (same order); in the abort case roll_error
    and map_cells are missing on the ticks after the abort (NaN in the log); the logged camera
    pose is pinocchio's placement at the logged q. Catches: a column created in the wrong
    order, a missing value logged as a number, the pair indices reused for different pairs."""
    fast, controller = _episode(False, overrides, duration)
    generic, _ = _episode(True, overrides, duration)
    assert fast.status == generic.status
    assert list(fast.log) == list(generic.log)
    for key in generic.log:
        if key != "controller_time":
            assert _same(fast.log[key], generic.log[key]), key
    assert fast.log["collision/active_pair"].shape[1] >= 5 and len(fast.log["collision/pair_names"]) >= 5
    if overrides:
        assert controller.phase == Phase.ABORT
        aborted = fast.log["value/phase"] == float(Phase.ABORT)
        assert aborted.any() and np.isnan(fast.log["value/roll_error"][aborted]).all()
        assert np.isnan(fast.log["value/map_cells"][aborted]).all() and not np.isnan(fast.log["value/map_cells"][0])
    oracle = Configuration.dual_ur5e(fast.log["q"][-1])
    pose = oracle.frame_pose("camera").homogeneous
    np.testing.assert_allclose(fast.log["value/p_c"][-1], pose[:3, 3], atol=1e-12)
    np.testing.assert_allclose(fast.log["value/z_c"][-1], pose[:3, 2], atol=1e-12)
    np.testing.assert_allclose(fast.log["value/x_c"][-1], pose[:3, 0], atol=1e-12)
