"""The paper episode's per-tick ground truth handed to the runner as one float64 row.

:func:`harvest_qp.loop.episode.episode_ground_truth` returns, for a plain ``SimRobot``, a
``runner._ValueRow`` (read as the same mapping) built from ``SimRobot._truth_floats``; the
runner logs it in one copy into views of one ``(n, width)`` array. Oracles: the robot's
generic ``ground_truth`` branch (each truth method called one by one, forced with
``_plain_truth = False``) and whole episodes logged through dicts: the logs must be equal bit
for bit, with the same keys in the same order and the same (C-contiguous) arrays.
"""

from __future__ import annotations

import numpy as np

from harvest_qp.loop.controller import HarvestController
from harvest_qp.loop.episode import build_robot, environment_capsules_for, episode_ground_truth
from harvest_qp.loop.settings import load_settings
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.runner import _ValueRow, run_episode


def _same(a, b) -> bool:
    """Equal dtype, shape and bytes (NaN and -0.0 included)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _setup(plain: bool = True):
    settings = load_settings(tasks_dir() / "paper.yaml", ["camera.downsample=6"])
    robot = build_robot(settings, 0)
    if not plain:
        robot._plain_truth = False  # the generic branch: each truth method called one by one
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings["qp"]["environment"]))
    return robot, controller


def test_truth_row_reads_as_the_generic_ground_truth():
    """The row, read as a mapping, equals ``SimRobot.ground_truth()``'s generic branch plus
    ``stem_end``: same keys in the same order, floats for scalars, the same bits. Catches: a
    value in the wrong slot (stem_force and qdot_ref swapped, a contact kind shifted), a
    copy of the live servo reference missing (the row would change afterwards)."""
    robot, _ = _setup()
    truth = episode_ground_truth(robot)
    rng = np.random.default_rng(3)
    for _ in range(3):
        robot.send_joint_velocities(rng.normal(scale=0.2, size=12))
        for _ in range(5):
            robot.step()
        row = truth()
        assert type(row) is _ValueRow
        robot._plain_truth = False
        try:
            oracle = robot.ground_truth()
        finally:
            robot._plain_truth = True
        oracle["stem_end"] = robot.data.site_xpos[robot.model.site("stem_end").id].copy()
        assert list(row) == list(oracle)
        for name, value in oracle.items():
            got = row[name]
            if np.ndim(value) == 0:
                assert type(got) is float and _same(np.float64(got), np.float64(value)), name
            else:
                assert _same(got, np.asarray(value, dtype=np.float64)), name
        kept = row["qdot_ref"].copy()
        robot.send_joint_velocities(np.full(12, 0.3))
        robot.step()
        assert _same(row["qdot_ref"], kept)  # the row holds its own copy
    # Most scalars are 0 in a short run (no contact, no tear): with every value distinct, each
    # slot of the row must hold the value ground_truth()'s dict gives under the same key.
    values = (1.5, np.array([2.0, 3.0, 4.0]), np.arange(5.0, 17.0), 17.0, 18.0, 19.0, 20.0, 21.0, 22.0,
              np.float64(23.0), 24.0, 25.0)  # fmt: skip
    robot._plain_truth_values = lambda: values
    row, oracle = dict(truth()), robot.ground_truth()
    assert list(row)[:-1] == list(oracle)
    for name, value in oracle.items():
        assert _same(np.asarray(row[name], dtype=np.float64), np.asarray(value, dtype=np.float64)), name
    assert sorted(np.concatenate([np.ravel(v) for v in oracle.values()]).tolist()) == [1.5, *range(2, 26)]


def test_overridden_truth_part_falls_back_to_the_dict():
    """A truth method overridden on the instance is asked (the row would bypass it): the
    truth is then the generic dict with the override's value. Catches: the row built from
    the inlined parts whatever the instance overrides."""
    robot, _ = _setup()
    truth = episode_ground_truth(robot)
    assert type(truth()) is _ValueRow
    robot.stem_tension = lambda: 12.5
    out = truth()
    assert type(out) is dict and out["stem_tension"] == 12.5 and "stem_end" in out


def _episode(truth_of, duration: float = 0.3):
    robot, controller = _setup()
    return run_episode(robot, controller, duration=duration, ground_truth=truth_of(robot)).log


def test_episode_truth_log_equals_the_dict_log():
    """The same episode with the truth as rows and as the generic robot's dicts: every array
    equal by bytes (dtype, shape, NaN), keys in the same order, truth arrays C-contiguous.
    Also rows mixed with dicts that leave a name out on some ticks (the runner's generic
    path writes into the rows' storage): equal to all-dict ticks with the same names left
    out (NaN there). Catches: a row logged at the wrong tick, the truth columns left as
    strided views, a dict tick after rows lost or a left-out name not NaN."""

    def generic(robot):
        robot._plain_truth = False
        return episode_ground_truth(robot)

    rows = _episode(episode_ground_truth)
    dicts = _episode(generic)
    assert list(rows) == list(dicts)
    truth_keys = [k for k in rows if k.startswith("truth/")]
    assert len(truth_keys) == 13 and "truth/stem_end" in truth_keys
    for key in dicts:
        if key != "controller_time":
            assert _same(rows[key], dicts[key]), key
    for key in truth_keys:
        assert rows[key].flags.c_contiguous
    assert np.isfinite(rows["truth/stem_tension"]).all() and np.ptp(rows["truth/qdot_ref"][:, 0]) > 0

    def mixed(as_dict_every: int):
        def make(robot):
            truth = episode_ground_truth(robot)
            tick = [0]

            def each():
                tick[0] += 1
                out = truth()
                if tick[0] % as_dict_every == 0:
                    out = dict(out)
                    del out["stem_force"]
                return out

            return each

        return make

    mixed_log = _episode(mixed(3), duration=0.1)
    def all_dicts(robot):
        each = mixed(3)(robot)
        return lambda: dict(each())

    dict_log = _episode(all_dicts, duration=0.1)
    assert list(mixed_log) == list(dict_log)
    for key in dict_log:
        if key != "controller_time":
            assert _same(mixed_log[key], dict_log[key]), key
    force = mixed_log["truth/stem_force"]
    # The runner's first call (the log's shapes) is call 1: calls 3, 6, ... are ticks 1, 4, ...
    assert np.isnan(force[1::3]).all() and not np.isnan(force[0::3]).any() and not np.isnan(force[2::3]).any()
