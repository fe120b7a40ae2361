"""HarvestController's per-tick log protocol: its values as one row, its active pairs as columns.

The controller hands the runner its ~18 logged values as one float64 row
(``runner._ValueRow``) and its active collision pairs as three columns
(``runner._PairColumns``) instead of a dict of arrays and a list of tuples. Oracles: the
controller's own dict and tuple listing (``_log_values``, ``_active_pairs``, themselves
tested against item-by-item values and the limit's ``active_pair_distances``), and whole
episodes run with the generic protocol (``_row_log = False``): the logs must be equal bit
for bit, with the same keys in the same order.
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.loop.controller import HarvestController, Phase
from harvest_qp.loop.episode import build_robot, environment_capsules_for, episode_ground_truth
from harvest_qp.loop.settings import check_settings, load_settings
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runner import _PairColumns, _ValueRow, run_episode


def _same(a, b) -> bool:
    """Equal dtype, shape and bytes (NaN and -0.0 included)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def _states(c: HarvestController, rng):
    """Approach (no p_sb, then a p_sb), bimanual (stretching after the switch), abort."""
    c.reaching.reset(rng.normal(size=3))
    st = c.state
    yield
    st.p_sb = rng.normal(size=3)
    yield
    st.p_gd = st.p_sb + rng.normal(size=3)
    c.stretching.set_target(st.p_sb, st.p_gd)
    T_g = np.eye(4)
    T_g[:3, 3] = rng.normal(size=3)
    c.stretching.update(T_g, rng.normal(size=3), 0.002)
    st.phase, st.t_switch = Phase.BIMANUAL, 1.0
    yield
    st.phase = Phase.ABORT
    yield


@pytest.mark.parametrize("roll_error", [None, 0.25, -0.0])
@pytest.mark.parametrize("map_cells", [None, 7.0])
def test_log_row_reads_as_the_log_values_dict(controller, roll_error, map_cells):
    """The row, read as a mapping, is ``_log_values``'s dict after the tick's ``roll_error`` and
    ``map_cells`` (each when given): same keys in the same order, floats for scalars, the same
    bits for every value. Catches: an entry's slot shifted (p_c and z_c swapped, x_c read from
    the wrong column), a missing entry still listed, -0.0 or a NaN payload changed."""
    c = controller
    rng = np.random.default_rng(5)
    saved = c.map_feed
    c.map_feed = object() if map_cells is not None else saved  # the layout with map_cells
    try:
        for _ in _states(c, rng):
            T_c = np.eye(4)
            T_c[:3, :3] = np.linalg.qr(rng.normal(size=(3, 3)))[0]
            T_c[:3, 3] = rng.normal(size=3)
            V_c, V_g = rng.normal(size=6), rng.normal(size=6)
            force = float(rng.normal())
            for distance in (None, 0.7):
                expected = {}
                if roll_error is not None:
                    expected["roll_error"] = roll_error
                if map_cells is not None:
                    expected["map_cells"] = map_cells
                c._log_values(T_c, V_c, V_g, force, into=expected, roi_distance=distance)
                row = c._log_row(T_c, V_c, V_g, force, distance, roll_error, map_cells)
                assert type(row) is _ValueRow
                assert list(row) == list(expected) and len(row) == len(expected)
                for name, value in expected.items():
                    assert type(row[name]) is type(value) or (type(value) is float and type(row[name]) is float)
                    assert _same(np.float64(row[name]) if np.ndim(value) == 0 else row[name],
                                 np.float64(value) if np.ndim(value) == 0 else value), name
                assert dict(row).keys() == expected.keys()
    finally:
        c.map_feed = saved
        c.state = type(c.state)()


def test_pair_columns_read_as_the_pair_tuples(controller):
    """``_active_pair_columns`` lists the tuples of ``_active_pairs`` (itself the limit's own
    listing), also when a capsule name changes in place between two calls with the same
    pairs (the map's feed renames its obstacle slots). Catches: the reused name lists kept
    after a rename (a stale cell name in the log)."""
    c = controller
    q = c.configuration.q.copy()
    c.qp.reset(q)
    c.qp.step(q)
    pairs = c._active_pair_columns()
    assert type(pairs) is _PairColumns and len(pairs) > 0
    assert pairs == c._active_pairs() == c.collision.active_pair_distances()
    assert list(pairs) == c._active_pairs() and pairs[0] == c._active_pairs()[0]
    assert all(type(d) is float for _, _, d in pairs)
    names = c.collision.capsule_names
    index = int(c.collision.pair_a[c.collision.active_pairs[0]])
    old = names[index]
    names[index] = "renamed"
    try:
        again = c._active_pair_columns()
        assert list(again) == c._active_pairs() and again[0][0] == "renamed"
    finally:
        names[index] = old
    assert list(c._active_pair_columns()) == c._active_pairs()


def _episode(row_log: bool, overrides: list[str], duration: float):
    settings = load_settings(tasks_dir() / "paper.yaml", ["camera.downsample=6", *overrides])
    robot = build_robot(settings, 0)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings["qp"]["environment"]))
    controller._row_log = row_log
    return run_episode(robot, controller, duration=duration, ground_truth=episode_ground_truth(robot)), controller


@pytest.mark.parametrize(
    ("overrides", "duration"),
    [([], 0.4), (["safety.no_stem_timeout=0.1", "episode.stop_after_abort=0.05"], 0.5)],
    ids=["approach", "abort"],
)
def test_episode_log_equals_the_generic_protocols(overrides, duration):
    """A paper episode logged through the row and the pair columns equals the same episode
    through the generic dict and tuples, key by key (same order), bit for bit; in the abort
    case roll_error and map_cells are missing on the ticks after the abort (NaN in the log).
    Catches: a column created in the wrong order, a missing value logged as a number, the
    pair indices reused for different pairs."""
    fast, controller = _episode(True, overrides, duration)
    generic, _ = _episode(False, overrides, duration)
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
