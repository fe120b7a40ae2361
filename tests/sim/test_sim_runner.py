"""Episode runner: logging, bit-for-bit determinism, and surviving controller failures."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

import harvest_qp.runtime.runner as runner
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.interface import PointCloud
from harvest_qp.runtime.runner import Command, Observation, run_episode, write_npz
from harvest_qp.sim import CameraConfig, ForceSensorConfig, SimRobot, SimulationError, VineSceneParams
from tests.sim.helpers import JointPD


def _wave(t: float, q0: np.ndarray) -> np.ndarray:
    """Camera arm sweeps towards the vine; the grasping arm holds."""
    q = q0.copy()
    q[0] -= 0.4 * np.sin(np.pi * t / 2)
    q[3] += 0.2 * np.sin(np.pi * t)
    return q


def _noisy_robot(seed: int) -> SimRobot:
    return SimRobot(
        VineSceneParams.sample(seed),
        seed=seed,
        camera=CameraConfig(depth_noise=0.002, dropout=0.05),
        force=ForceSensorConfig(noise_std=0.02),
    )


def test_same_seed_gives_the_same_log_bit_for_bit(tmp_path):
    paths = []
    for name in ("a", "b"):
        robot = _noisy_robot(5)
        result = run_episode(robot, JointPD(_wave), duration=0.5, log_path=tmp_path / f"{name}.npz", log_clouds=True)
        assert result.ok
        paths.append(result.log_path)
    assert paths[0].read_bytes() == paths[1].read_bytes()
    # A different noise seed changes the log (so the comparison above can fail).
    other = run_episode(_noisy_robot(6), JointPD(_wave), duration=0.5, log_path=tmp_path / "c.npz")
    assert other.log_path.read_bytes() != paths[0].read_bytes()


def test_log_contents(tmp_path):
    robot = SimRobot(camera=CameraConfig())
    result = run_episode(robot, JointPD(_wave), duration=0.4, log_path=tmp_path / "ep", metadata={"name": "wave"})
    assert result.ok and result.n_ticks == 200 and result.sim_time == pytest.approx(0.4)
    assert result.log_path.suffix == ".npz"
    log = dict(np.load(result.log_path))
    assert log["t"].shape == (200,) and log["q"].shape == (200, 12) and log["qdot_cmd"].shape == (200, 12)
    np.testing.assert_allclose(np.diff(log["t"]), 0.002)
    assert log["force"].shape == (200, 3)
    assert set(log["status"]) == {"ok"}
    assert log["task_error/joint_error"].shape == (200,)
    assert log["truth/stem_tension"].shape == (200,) and log["truth/stem_force"].shape == (200, 3)
    # 30 Hz camera: frames at 0, 1/30, ..., 11/30 s seen by the ticks 0 .. 0.398 s.
    assert len(log["frame_time"]) == 12
    np.testing.assert_allclose(log["frame_time"], np.arange(12) / 30, atol=0.002)
    assert np.all(log["cloud_time"] <= log["t"] + 1e-12)
    assert np.all(log["stem_points"] >= 0) and log["frame_camera_pose"].shape == (12, 4, 4)
    assert str(log["episode_status"]) == "completed" and str(log["error"]) == ""
    assert str(log["meta/name"]) == "wave"
    # The command was executed: the camera arm moved as commanded.
    assert log["q"][-1, 0] < log["q"][0, 0] - 0.05


class _Failing:
    def __init__(self, at: float, kind: str) -> None:
        self.at, self.kind = at, kind

    def reset(self, robot) -> None:
        self.started = True

    def step(self, obs: Observation):
        if obs.time >= self.at - 1e-9:
            if self.kind == "raise":
                raise RuntimeError("solver exploded")
            if self.kind == "nan":
                return Command(qdot=np.full(12, np.nan))
            return np.zeros(7)
        return Command(qdot=np.r_[np.full(6, 0.5), np.zeros(6)], status="ok")


@pytest.mark.parametrize(
    ("kind", "status", "words"),
    [("raise", "controller_error", "solver exploded"), ("nan", "invalid_command", "finite"),
     ("shape", "invalid_command", "shape")],
)  # fmt: skip
def test_controller_failures_stop_the_arms_and_are_recorded(tmp_path, kind, status, words):
    robot = SimRobot(camera=None)
    result = run_episode(robot, _Failing(0.2, kind), duration=1.0, log_path=tmp_path / "fail.npz")
    assert result.status == status and not result.ok
    assert words in result.error
    assert result.n_ticks == 101  # ticks 0 .. 0.2 s, the last one failed
    log = np.load(result.log_path)
    assert str(log["episode_status"]) == status and words in str(log["error"])
    assert log["status"][-1] == "error" and log["status"][0] == "ok"
    # The arms were brought to rest.
    assert np.abs(robot.joint_velocities()).max() < 1e-3
    assert np.all(robot.velocity_reference() == 0.0)


def test_reset_failure_is_recorded():
    class BadReset:
        def reset(self, robot):
            raise ValueError("no robot model")

        def step(self, obs):
            return np.zeros(12)

    result = run_episode(SimRobot(camera=None), BadReset(), duration=0.1)
    assert result.status == "controller_error" and "no robot model" in result.error and result.n_ticks == 0


def test_observation_carries_the_latest_cloud():
    seen = []

    class Recorder:
        def reset(self, robot):
            pass

        def step(self, obs: Observation):
            seen.append((obs.time, obs.new_cloud, obs.cloud))
            return np.zeros(12)

    run_episode(SimRobot(), Recorder(), duration=0.1)
    assert seen[0][1] and isinstance(seen[0][2], PointCloud)
    new = [t for t, is_new, _ in seen if is_new]
    assert len(new) == 3  # 0, 1/30, 2/30 s
    assert all(cloud is not None for _, _, cloud in seen)


def test_a_diverging_simulation_ends_the_episode_as_a_robot_error():
    robot = SimRobot(camera=None)
    # Make the stem absurdly stiff after the reset: the next steps blow up.
    robot.model.jnt_stiffness[robot.scene.ids["stem_slide"]] = 1e9
    result = run_episode(robot, JointPD(), duration=1.0)
    assert result.status == "robot_error" and "unstable" in result.error
    assert 0 < result.n_ticks < 500
    # The robot refuses to go on until it is reset.
    with pytest.raises(SimulationError, match="reset"):
        robot.step()
    robot.model.jnt_stiffness[robot.scene.ids["stem_slide"]] = robot.scene.model.jnt_stiffness[
        robot.scene.ids["stem_slide"]
    ]
    robot.reset()
    robot.step()


def test_run_episode_validates_its_arguments():
    robot = SimRobot(camera=None)
    with pytest.raises(InvalidInputError, match="duration"):
        run_episode(robot, JointPD(), duration=0.0)
    with pytest.raises(InvalidInputError, match="controller"):
        run_episode(robot, object(), duration=0.1)
    with pytest.raises(InvalidInputError, match="RobotInterface"):
        run_episode(object(), JointPD(), duration=0.1)


def test_write_npz_is_deterministic_and_loadable(tmp_path):
    arrays = {"a": np.arange(5.0), "b": np.array("text"), "c/d": np.zeros((2, 3), np.int8)}
    p1 = write_npz(tmp_path / "x.npz", arrays)
    p2 = write_npz(tmp_path / "y.npz", arrays)
    assert p1.read_bytes() == p2.read_bytes()
    loaded = np.load(p1)
    np.testing.assert_array_equal(loaded["a"], arrays["a"])
    assert str(loaded["b"]) == "text" and loaded["c/d"].dtype == np.int8
    with pytest.raises(InvalidInputError, match="object"):
        write_npz(tmp_path / "z.npz", {"bad": np.array([None, 1], dtype=object)})


class _Tarer:
    """Pulls the held cluster away from the stem, then tares through the observation only."""

    def __init__(self, tare_at: float) -> None:
        self.tare_at = tare_at
        self.forces: list[tuple[float, np.ndarray]] = []

    def reset(self, robot) -> None:  # keeps no handle: everything below comes from obs
        self.q0 = robot.joint_positions()

    def step(self, obs: Observation) -> Command:
        if abs(obs.time - self.tare_at) < 1e-9:
            obs.tare_force()
        self.forces.append((obs.time, np.array(obs.force)))
        return Command(qdot=np.zeros(12), values={"scalar": obs.time, "vec": obs.q[:3]},
                       collision_pairs=[("a", "b", 0.05)] if obs.time < 0.01 else [("a", "c", 0.04), ("a", "b", 0.03)])


def test_observation_tares_the_wrist_sensor_without_a_robot_handle():
    """A controller tares the F/T sensor via ``obs.tare_force`` (issue 10 section 5).

    Catches: an Observation whose tare does nothing or tares another sensor. Oracle: the
    untared reading (the held cluster's weight is compensated but not the stem/weld
    offsets) differs from zero, and right after the tare it reads ~0."""
    robot = SimRobot(camera=None, force=ForceSensorConfig(noise_std=0.0))
    controller = _Tarer(tare_at=0.1)
    result = run_episode(robot, controller, duration=0.2)
    assert result.ok
    before = np.array([f for t, f in controller.forces if t < 0.1 - 1e-9])
    after = np.array([f for t, f in controller.forces if t > 0.1 + 1e-9])
    assert np.linalg.norm(before, axis=1).min() > 1.0  # the untared reading: the cluster's weight
    assert np.abs(after).max() < 0.05


def test_values_and_collision_pairs_are_logged_per_tick(tmp_path):
    """Named per-tick values and active collision pairs reach the log (issue 10 section 5)."""
    robot = SimRobot(camera=None)
    result = run_episode(robot, _Tarer(tare_at=-1.0), duration=0.02, log_path=tmp_path / "p.npz")
    log = np.load(result.log_path)
    assert log["value/scalar"].shape == (10,) and log["value/vec"].shape == (10, 3)
    np.testing.assert_allclose(log["value/scalar"], log["t"])
    names = list(log["collision/pair_names"])
    assert names == ["a|b", "a|c"]
    index, distance = log["collision/active_pair"], log["collision/active_distance"]
    assert index.shape == (10, 2)
    assert list(index[0]) == [0, -1] and distance[0, 0] == pytest.approx(0.05)
    assert list(index[-1]) == [1, 0]
    np.testing.assert_allclose(distance[-1], [0.04, 0.03], rtol=1e-6)


def test_command_done_ends_the_episode():
    class Quitter:
        def reset(self, robot):
            pass

        def step(self, obs):
            return Command(qdot=np.zeros(12), done=obs.time >= 0.01 - 1e-9)

    result = run_episode(SimRobot(camera=None), Quitter(), duration=1.0)
    assert result.ok and result.n_ticks == 6


# ---------------------------------------------------------------- the library's own log protocol

from harvest_qp.runtime import runner as _runner  # noqa: E402
from harvest_qp.runtime.log import EpisodeLog, PairColumns, ValueLayout, ValueRow  # noqa: E402

_LAYOUT_A = ValueLayout((("late", ()), ("never", (2,)), ("s", ()), ("v", (3,)), ("m", (2, 2))))
_LAYOUT_B = ValueLayout((("s", ()), ("w", (2,))))


class _Rows:
    """Values as rows of a layout and pairs as columns, with entries missing on some ticks;
    ``as_dicts``: the same values and pairs as a dict and a list of tuples (the oracle).
    ``switch_at``: from that tick on, ``other`` gives the values (another layout, or a dict)."""

    def __init__(self, as_dicts: bool, switch_at: int | None = None, other: str = "layout") -> None:
        self.as_dicts, self.switch_at, self.other = as_dicts, switch_at, other

    def reset(self, robot) -> None:
        self.k = 0

    def step(self, obs) -> Command:
        k, self.k = self.k, self.k + 1
        t = float(obs.time)
        if self.switch_at is not None and k >= self.switch_at:
            if self.other == "dict":
                values = {"s": -t, "v": np.array([t, 2 * t, -0.0])}
            else:
                values = ValueRow(_LAYOUT_B, np.array([t, np.nan, -t]), ("w",) if k % 2 else ())
        else:
            row = np.array([k, 9.0, 9.0, t, 1.0 + t, -0.0, np.inf, 1.0, 2.0, 3.0, 4.0 * t])
            missing = ("never",) + (("late",) if k < 3 else ()) + (("v",) if k % 4 == 1 else ())
            values = ValueRow(_LAYOUT_A, row, missing)
        # The same first names with other second names (c|d, c|5), and 5 / "5" (one name in the log).
        first, second = ["a", "b", "c"], ["b", "c", ("d", 5, "5")[k % 3]]
        n = 3 if k % 4 else 2
        pairs = PairColumns(first[:n], second[:n], np.array([0.01 * k + i for i in range(n)]))
        if self.as_dicts:
            values = dict(values) if isinstance(values, ValueRow) else values
            pairs = [(str(a), str(b), d) for a, b, d in pairs]
        return Command(qdot=np.zeros(12), values=values, collision_pairs=pairs)


@pytest.mark.parametrize(("switch_at", "other"), [(None, ""), (6, "layout"), (6, "dict"), (0, "dict")])
def test_value_rows_and_pair_columns_log_what_dicts_and_tuples_log(switch_at, other):
    """The runner's row log (one copy per tick, split into columns at the end) and its pair
    columns give the log of the same values as a dict and the pairs as tuples: same keys in
    the same order (a column is created when its name is first given), NaN where a value is
    missing, no column for a name never given, the same pair indices; also when another
    layout or a dict takes over mid-episode (the rows become columns then).
    Catches: columns ordered by the layout instead of first use, a missing value logged
    from its slot, the row log not handed over at the switch, pair indices reused for other
    names, a non-str name logged differently from its str."""
    fast = run_episode(SimRobot(camera=None), _Rows(False, switch_at, other), duration=0.03)
    oracle = run_episode(SimRobot(camera=None), _Rows(True, switch_at, other), duration=0.03)
    assert fast.ok and oracle.ok
    assert list(fast.log) == list(oracle.log)
    for key, value in oracle.log.items():
        assert fast.log[key].dtype == value.dtype and fast.log[key].shape == value.shape, key
        assert fast.log[key].tobytes() == value.tobytes(), key
    assert "value/never" not in fast.log
    if switch_at is None:
        assert [k for k in fast.log if k.startswith("value/")] == ["value/s", "value/v", "value/m", "value/late"]
    assert list(fast.log["collision/pair_names"]) == ["a|b", "b|c", "c|5", "c|d"]


def test_fast_finiteness_check_refuses_every_non_finite_entry():
    """The fast command check (math.isfinite on each float) refuses NaN, inf and -inf in every
    position and passes every finite command, 1e308 and -0.0 included, as the full check does.
    Catches: a check by a sum (1e308 overflows), or one that misses a position."""
    for i in range(12):
        for bad in (np.nan, np.inf, -np.inf):
            qdot = np.zeros(12)
            qdot[i] = bad
            with pytest.raises(InvalidInputError, match="finite"):
                _runner.as_command(Command(qdot=qdot))
    for qdot in (np.full(12, 1e308), np.full(12, -1e308), np.full(12, -0.0), np.full(12, 5e-324)):
        cmd = _runner.as_command(Command(qdot=qdot))
        assert cmd.qdot is qdot


def test_value_rows_and_pair_columns_read_as_mappings_and_sequences():
    """What a viewer or a wrapper reads from a command: the row as a mapping (floats for
    scalars, shaped views, missing names absent) and the columns as (a, b, distance) tuples.
    Catches: a missing name still readable, a slot read at the wrong offset, a bad row or
    bad columns accepted."""
    row = ValueRow(_LAYOUT_A, np.arange(11.0), ("never",))
    assert list(row) == ["late", "s", "v", "m"] and len(row) == 4 and "never" not in row
    assert row["late"] == 0.0 and type(row["s"]) is float and row["s"] == 3.0
    np.testing.assert_array_equal(row["v"], [4.0, 5.0, 6.0])
    np.testing.assert_array_equal(row["m"], [[7.0, 8.0], [9.0, 10.0]])
    assert np.isnan(row.row[1:3]).all()  # a missing entry's slots are NaN, as the log holds it
    with pytest.raises(KeyError):
        row["never"]
    with pytest.raises(InvalidInputError):
        ValueRow(_LAYOUT_A, np.arange(10.0))
    with pytest.raises(InvalidInputError):
        ValueRow(_LAYOUT_A, np.arange(11, dtype=np.float32))
    pairs = PairColumns(["a", "b"], ["c", "d"], np.array([0.5, 0.25]))
    assert list(pairs) == [("a", "c", 0.5), ("b", "d", 0.25)] and pairs[1] == ("b", "d", 0.25)
    assert pairs == [("a", "c", 0.5), ("b", "d", 0.25)] and min(pairs, key=lambda p: p[2])[0] == "b"
    with pytest.raises(InvalidInputError):
        PairColumns(["a"], ["c", "d"], np.array([0.5, 0.25]))
    with pytest.raises(InvalidInputError):
        PairColumns(["a", "b"], ["c", "d"], [0.5, 0.25])


def test_pair_arrays_cut_at_k_match_a_per_event_loop():
    """The log's pair arrays for the first k ticks when later ticks have events too (the
    event table is built by a row-major boolean mask). Oracle: one event at a time into its
    tick's row; the width is the most events of any logged tick (as before).
    Catches: events of ticks >= k shifted into the table, events placed in the wrong row."""
    rng = np.random.default_rng(9)
    log = EpisodeLog(60, None, False, False)
    names = ["p", "q", "r", "s", "t"]
    events = []
    for k in range(60):
        if k % 7 == 3:
            continue  # a tick without pairs
        n = int(rng.integers(1, 6))
        pairs = PairColumns([names[i] for i in rng.integers(0, 5, n)], [names[i] for i in rng.integers(0, 5, n)],
                             rng.random(n))
        log.pairs(k, pairs)
        events.extend((k, f"{a}|{b}", d) for a, b, d in pairs)
    order = list(dict.fromkeys(name for _, name, _ in events))
    width = max(sum(1 for e in events if e[0] == k) for k in range(60))
    for cut in (60, 41, 1, 0):
        got = log.pair_arrays(cut)
        index = np.full((cut, width), -1, np.int32)
        distance = np.full((cut, width), np.nan, np.float32)
        fill = [0] * 60
        for k, name, d in events:
            if k < cut:
                index[k, fill[k]] = order.index(name)
                distance[k, fill[k]] = d
                fill[k] += 1
        assert list(got["collision/pair_names"]) == order
        np.testing.assert_array_equal(got["collision/active_pair"], index)
        np.testing.assert_array_equal(got["collision/active_distance"], distance)
    assert log.pair_events == [(k, order.index(name), d) for k, name, d in events]


class _Mixed:
    """Commands with every kind of value the runner accepts: floats, np.float64, ints, arrays, pairs."""

    def reset(self, robot) -> None:
        self.k = 0

    def step(self, obs) -> Command:
        self.k += 1
        t = float(obs.time)
        qdot = np.zeros(12)
        qdot[0] = 0.2 * math.sin(10 * t)
        values = {
            "scalar": t,
            "np_scalar": np.float64(2 * t),
            "vec": np.array([t, -t, 1.0]),
        }
        if self.k % 5 == 0:
            values["int_value"] = self.k  # not a float: this command takes the full check
        pairs = [("a", "b", 0.05 + t)] + ([("a", "c", 0.04)] if self.k % 3 == 0 else [])
        if self.k % 4 == 0:
            pairs.append(["c", "d", 0.01])  # a list, not a tuple: takes the full check
        if self.k % 7 == 0:
            pairs = (pair for pair in pairs)  # a generator: read once, by the full check
        return Command(qdot=qdot, values=values, collision_pairs=pairs, task_errors={"e": t})


@pytest.mark.parametrize(
    ("qdot", "words"),
    [(np.r_[np.zeros(11), np.inf], "finite"), (np.r_[np.zeros(11), np.nan], "finite"),
     (np.full(12, 1e308), None), (np.zeros(12, np.float32), None)],
)  # fmt: skip
def test_command_check_rejects_non_finite_and_passes_huge_finite_speeds(qdot, words):
    """Bug caught: a finiteness test that lets inf/nan through, or rejects huge finite values.

    1e308 * 12 overflows a sum of the speeds: that command must still pass (clipped by the
    servo); float32 speeds come back as the same float64 values (oracle: the input itself).
    """
    out = Command(qdot=qdot)
    if words is None:
        cmd = runner.as_command(out)
        assert cmd.qdot.dtype == np.float64
        np.testing.assert_array_equal(cmd.qdot, qdot.astype(np.float64))
    else:
        with pytest.raises(runner.InvalidInputError, match=words):
            runner.as_command(out)


def test_pair_arrays_match_a_per_event_loop():
    """Bug caught: events placed in the wrong column, ticks mixed up, or float32 rounding changed.

    Oracle: the plain loop the runner used before (one event at a time into its tick's row).
    """
    rng = np.random.default_rng(4)
    log = EpisodeLog(50, None, False, False)
    names = ["p", "q", "r", "s"]
    events = []
    for k in range(50):
        pairs = [(names[i], names[j], float(rng.random())) for i, j in rng.integers(0, 4, (rng.integers(0, 5), 2))]
        log.pairs(k, pairs)
        events.extend((k, f"{a}|{b}", d) for a, b, d in pairs)
    got = log.pair_arrays(50)
    order = list(dict.fromkeys(name for _, name, _ in events))
    assert list(got["collision/pair_names"]) == order
    width = max(sum(1 for e in events if e[0] == k) for k in range(50))
    index = np.full((50, width), -1, np.int32)
    distance = np.full((50, width), np.nan, np.float32)
    fill = [0] * 50
    for k, name, d in events:
        index[k, fill[k]] = order.index(name)
        distance[k, fill[k]] = d
        fill[k] += 1
    np.testing.assert_array_equal(got["collision/active_pair"], index)
    np.testing.assert_array_equal(got["collision/active_distance"], distance)


def test_runner_uses_an_overridden_send_joint_velocities():
    """Bug caught: the runner bypassing a subclass's own send_joint_velocities."""

    class Counting(SimRobot):
        sent = 0

        def send_joint_velocities(self, qdot) -> None:
            Counting.sent += 1
            super().send_joint_velocities(qdot)

    robot = Counting(camera=None)
    run_episode(robot, _Mixed(), duration=0.01, stop_at_end=False)
    assert Counting.sent == 5


def test_runner_calls_an_instance_override_and_a_proxys_own_sender():
    """Bug caught: the runner bypassing ``robot.send_joint_velocities = wrapper`` set on the
    instance, or a proxy's own sender (a user's safety or fault-injection wrapper silently
    skipped; found by an audit)."""
    from harvest_qp.runtime.interface import RobotInterface

    robot = SimRobot(camera=None)
    calls = []
    robot.send_joint_velocities = lambda qdot: calls.append(np.array(qdot))
    run_episode(robot, _Mixed(), duration=0.01, stop_at_end=False)
    assert len(calls) == 5

    class Proxy(RobotInterface):
        def __init__(self, inner):
            self.__dict__["inner"], self.__dict__["sent"] = inner, 0

        def __getattr__(self, name):
            return getattr(self.inner, name)

        def send_joint_velocities(self, qdot):
            self.__dict__["sent"] += 1
            self.inner.send_joint_velocities(qdot)

    for name in RobotInterface.__abstractmethods__ - {"send_joint_velocities"}:
        attr = getattr(SimRobot, name)
        if isinstance(attr, property):
            setattr(Proxy, name, property(lambda self, n=name: getattr(self.inner, n)))
        else:
            setattr(Proxy, name, lambda self, *a, n=name, **k: getattr(self.inner, n)(*a, **k))
    Proxy.__abstractmethods__ = frozenset()
    proxy = Proxy(SimRobot(camera=None))
    run_episode(proxy, _Mixed(), duration=0.01, stop_at_end=False)
    assert proxy.sent == 5


@pytest.mark.parametrize(
    ("first", "later", "words"),
    [(np.zeros(3), np.zeros(2), "(3,) to (2,)"), (0.5, np.zeros(2), "() to (2,)"), (np.zeros(3), 0.5, "(3,) to ()")],
)
def test_a_value_that_changes_shape_is_refused(first, later, words):
    """Bug caught: the per-key log writing a differently shaped value (a broadcast scalar into a
    vector row, or a vector into a scalar column) instead of refusing it, in either fast path."""

    class Changing:
        def reset(self, robot) -> None:
            self.k = 0

        def step(self, obs) -> Command:
            self.k += 1
            return Command(qdot=np.zeros(12), values={"v": first if self.k < 3 else later})

    # An invalid command ends the episode with its status and the arms stopped; run_episode
    # itself does not raise (it did before an audit of the fast paths).
    result = run_episode(SimRobot(camera=None), Changing(), duration=0.02)
    assert result.status == "invalid_command" and result.n_ticks == 3
    assert re.search(r"value 'v' changed shape from " + re.escape(words), result.error)


def test_a_task_error_that_is_not_a_number_is_an_invalid_command():
    """Bug caught: numpy's ValueError from float("abc") escaping run_episode (an audit)."""

    class Wordy:
        def reset(self, robot) -> None:
            pass

        def step(self, obs) -> Command:
            return Command(qdot=np.zeros(12), task_errors={"e": "abc"})

    result = run_episode(SimRobot(camera=None), Wordy(), duration=0.02)
    assert result.status == "invalid_command" and "task error 'e' must be a number" in result.error
