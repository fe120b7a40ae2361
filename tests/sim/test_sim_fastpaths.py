"""The lab's and the runner's fast paths give exactly what their checked or plain versions give.

Speed work replaced per-tick Python by unchecked private calls and numba kernels; these tests
hold each of them to an independent oracle: the runner's full command check, a plain
per-event loop for the collision-pair log, numpy's ``site_force_world`` for the stem
tension, and every arm-vine pair's segment distance for the pruned ground-truth search.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

import harvest_qp.runner as runner
from harvest_qp.runner import Command, run_episode
from harvest_qp.sim import SimRobot, VineSceneParams
from harvest_qp.sim import contacts as contacts_module
from harvest_qp.sim.force import site_force_world


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
            "int_value": self.k,  # not a float: takes the full check
        }
        pairs = [("a", "b", 0.05 + t)] + ([("a", "c", 0.04)] if self.k % 3 == 0 else [])
        if self.k % 4 == 0:
            pairs.append(["c", "d", 0.01])  # a list, not a tuple: takes the full check
        return Command(qdot=qdot, values=values, collision_pairs=pairs, task_errors={"e": t})


def test_fast_command_check_logs_exactly_what_the_full_check_logs(monkeypatch):
    """Bug caught: a fast path that drops, reshapes or re-rounds a value, a pair or qdot.

    Oracle: the same episode with every command through :func:`runner._as_command`.
    """
    fast = run_episode(SimRobot(camera=None), _Mixed(), duration=0.05)
    monkeypatch.setattr(runner, "_as_command_fast", runner._as_command)
    full = run_episode(SimRobot(camera=None), _Mixed(), duration=0.05)
    assert fast.ok and full.ok
    assert sorted(fast.log) == sorted(full.log)
    for key in full.log:
        assert fast.log[key].dtype == full.log[key].dtype, key
        np.testing.assert_array_equal(fast.log[key], full.log[key], err_msg=key)
    assert fast.log["value/vec"].shape == (25, 3) and list(fast.log["collision/pair_names"]) == ["a|b", "a|c", "c|d"]


@pytest.mark.parametrize(
    ("qdot", "words"),
    [(np.r_[np.zeros(11), np.inf], "finite"), (np.r_[np.zeros(11), np.nan], "finite"),
     (np.full(12, 1e308), None), (np.zeros(12, np.float32), None)],
)  # fmt: skip
def test_fast_command_check_rejects_what_the_full_check_rejects(qdot, words):
    """Bug caught: a finiteness test that lets inf/nan through, or rejects huge finite values.

    1e308 * 12 overflows the sum the fast check uses: that command must still pass (clipped
    by the servo); float32 takes the full check.
    """
    out = Command(qdot=qdot)
    if words is None:
        cmd = runner._as_command_fast(out)
        np.testing.assert_array_equal(cmd.qdot, runner._as_command(out).qdot)
    else:
        with pytest.raises(runner.InvalidInputError, match=words):
            runner._as_command_fast(out)


def test_pair_arrays_match_a_per_event_loop():
    """Bug caught: events placed in the wrong column, ticks mixed up, or float32 rounding changed.

    Oracle: the plain loop the runner used before (one event at a time into its tick's row).
    """
    rng = np.random.default_rng(4)
    log = runner._Log(50, None, False, False)
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
    """Bug caught: the runner's unchecked sender bypassing a subclass's own send_joint_velocities."""

    class Counting(SimRobot):
        sent = 0

        def send_joint_velocities(self, qdot) -> None:
            Counting.sent += 1
            super().send_joint_velocities(qdot)

    robot = Counting(camera=None)
    assert robot._unchecked_sender() is None and SimRobot(camera=None)._unchecked_sender() is not None
    run_episode(robot, _Mixed(), duration=0.01, stop_at_end=False)
    assert Counting.sent == 5


def test_stem_tension_kernel_equals_the_force_sensor_reading():
    """Bug caught: a wrong row/column of the site rotation or a wrong sign in the numba tension.

    Oracle: numpy's ``site_force_world`` (R f) and the stem direction, over states of a
    pulled stem; and bit-equality with the plain-Python ``_fast_tension``.
    """
    robot = SimRobot(camera=None)
    m, d = robot.model, robot.data
    rng = np.random.default_rng(2)
    signs = set()
    for _ in range(40):
        robot.send_joint_velocities(np.r_[np.zeros(6), rng.normal(0, 0.3, 6)])
        for _ in range(5):
            robot.step()
        f = site_force_world(m, d, robot._ids["stem_force"], robot._ids["stem_end_site"])
        towards_base = np.asarray(robot.scene.stem_base) - d.site_xpos[robot._ids["stem_end_site"]]
        expected = math.copysign(np.linalg.norm(f), 1.0 if f @ towards_base >= 0 else -1.0)
        assert robot.stem_tension() == pytest.approx(expected, rel=1e-12, abs=1e-12)
        assert robot.stem_tension() == robot._fast_tension()
        signs.add(expected > 0)
    assert True in signs


def test_pruned_vine_distance_search_equals_every_pair():
    """Bug caught: a broad phase that skips the nearest pair, or changes which pair wins a tie.

    Oracle: the segment distance of every exact (capsule/sphere) arm-vine pair, first
    minimum in pair order, and every bounded pair's lower bound, over random states with
    the hint of the previous call (as in an episode) and without it.
    """
    robot = SimRobot(VineSceneParams.sample(5), camera=None)
    m, d = robot.model, robot.data
    cm = robot._contacts
    arm_axis, arm_half, _, _ = cm._arm_caps
    vine_axis, vine_half, _, _ = cm._vine_caps
    nv = cm.vine_geoms.size
    rng = np.random.default_rng(8)
    hint = -1
    for _ in range(120):
        d.qpos[robot._qpos_ids] = robot.scene.home_q + rng.normal(0, 0.3, 12)
        mujoco.mj_forward(m, d)

        def ends(geoms, axis, half):
            off = np.array([half[i] * d.geom_xmat[g].reshape(3, 3)[:, axis[i]] for i, g in enumerate(geoms)])
            return d.geom_xpos[geoms] - off, d.geom_xpos[geoms] + off

        pa, qa = ends(cm.arm_geoms, arm_axis, arm_half)
        pv, qv = ends(cm.vine_geoms, vine_axis, vine_half)
        all_pairs = contacts_module._segment_distances(pa, qa, pv, qv) - cm._radius_sum
        flat = all_pairs.ravel()
        exact = flat[cm._exact_pairs]
        want_best = min(cm.max_distance, float(exact.min()))
        want_k = int(cm._exact_pairs[np.argmax(exact == exact.min())]) if exact.min() < cm.max_distance else -1
        want_candidates = [j for j in range(cm._bounded_pairs.size) if flat[cm._bounded_pairs[j]] < want_best]
        for h in (hint, -1):
            best, k, n = contacts_module._capsule_bounds(
                d.geom_xpos, d.geom_xmat, cm._static, cm._radius_sum, cm._exact_pairs, cm._bounded_pairs,
                cm.max_distance, cm._lower, cm._candidates, h,
            )  # fmt: skip
            assert best == pytest.approx(want_best, abs=1e-15) and k == want_k
            assert sorted(cm._candidates[:n].tolist()) == want_candidates
            lower = cm._lower[cm._candidates[:n]]
            assert np.all(np.diff(lower) >= 0)
        hint = k
        assert k // nv < cm.arm_geoms.size
