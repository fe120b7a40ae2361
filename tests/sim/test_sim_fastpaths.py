"""The lab's and the runner's fast paths give exactly what their checked or plain versions give.

Speed work replaced per-tick Python by unchecked private calls and numba kernels; these tests
hold each of them to an independent oracle: the runner's full command check, a plain
per-event loop for the collision-pair log, numpy's ``site_force_world`` for the stem
tension, every arm-vine pair's segment distance for the pruned ground-truth search, every
ray against every geom for the culled ray caster, and the two-pass cloud for the one-pass one.
"""

from __future__ import annotations

import math
import re

import mujoco
import numpy as np
import pytest
from numba import njit

import harvest_qp.runner as runner
from harvest_qp.runner import Command, run_episode
from harvest_qp.sim import CameraConfig, SimRobot, VineSceneParams, _raycast
from harvest_qp.sim import contacts as contacts_module
from harvest_qp.sim.force import site_force_world
from tests.sim.helpers import look_at


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


def test_fast_command_check_logs_exactly_what_the_full_check_logs(monkeypatch):
    """Bug caught: a fast path that drops, reshapes or re-rounds a value, a pair or qdot.

    Oracle: the same episode with every command through :func:`runner._as_command`.
    """
    calls = []
    monkeypatch.setattr(runner, "_as_command", lambda out, full=runner._as_command: calls.append(1) or full(out))
    fast = run_episode(SimRobot(camera=None), _Mixed(), duration=0.05)
    assert 0 < len(calls) < 15  # most of the 25 commands took the fast path, some the full check
    monkeypatch.setattr(runner, "_as_command_fast", runner._as_command)  # the full check for every command
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


def test_runner_calls_an_instance_override_and_a_proxys_own_sender():
    """Bug caught: the unchecked sender bypassing ``robot.send_joint_velocities = wrapper`` set on
    the instance, or a proxy whose ``__getattr__`` hands out the inner SimRobot's sender (a
    user's safety or fault-injection wrapper silently skipped; found by an audit)."""
    from harvest_qp.interface import RobotInterface

    robot = SimRobot(camera=None)
    calls = []
    robot.send_joint_velocities = lambda qdot: calls.append(np.array(qdot))
    assert robot._unchecked_sender() is None
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
        np.testing.assert_array_equal(robot.stem_force(), f)  # the bound views read the live state
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
            best, k, n, *_ = contacts_module._vine_near_search(
                d.geom_xpos, d.geom_xmat, cm._near_ints, cm._near_floats, *cm._sizes, cm.max_distance, h,
            )  # fmt: skip
            assert best == pytest.approx(want_best, abs=1e-15) and k == want_k
            assert sorted(cm._candidates[:n].tolist()) == want_candidates
            lower = cm._lower[cm._candidates[:n]]
            assert np.all(np.diff(lower) >= 0)
        hint = k
        assert k // nv < cm.arm_geoms.size


@njit(cache=True)
def _cast_every_geom(rays_c, origin, rotation, geom_type, geom_size, geom_xpos, geom_xmat, mask, cutoff, geomid, dist):
    """Brute force: every pixel ray against every geom, in id order (nearest wins, ties to the lowest id)."""
    for i in range(rays_c.shape[0]):
        geomid[i] = -1
        dist[i] = -1.0
        for g in range(geom_type.shape[0]):
            if not mask[g]:
                continue
            ex, ey, ez = rays_c[i, 0], rays_c[i, 1], rays_c[i, 2]
            # Ray in the world, then in the geom frame (the caster's own order of operations).
            px = geom_xpos[g, 0] - origin[0]
            py = geom_xpos[g, 1] - origin[1]
            pz = geom_xpos[g, 2] - origin[2]
            c0 = rotation[0, 0] * px + rotation[1, 0] * py + rotation[2, 0] * pz
            c1 = rotation[0, 1] * px + rotation[1, 1] * py + rotation[2, 1] * pz
            c2 = rotation[0, 2] * px + rotation[1, 2] * py + rotation[2, 2] * pz
            rg = np.empty((3, 3))
            for a in range(3):
                for b in range(3):
                    rg[a, b] = (
                        rotation[0, a] * geom_xmat[g, b]
                        + rotation[1, a] * geom_xmat[g, 3 + b]
                        + rotation[2, a] * geom_xmat[g, 6 + b]
                    )
            ox = -(rg[0, 0] * c0 + rg[1, 0] * c1 + rg[2, 0] * c2)
            oy = -(rg[0, 1] * c0 + rg[1, 1] * c1 + rg[2, 1] * c2)
            oz = -(rg[0, 2] * c0 + rg[1, 2] * c1 + rg[2, 2] * c2)
            dx = rg[0, 0] * ex + rg[1, 0] * ey + rg[2, 0] * ez
            dy = rg[0, 1] * ex + rg[1, 1] * ey + rg[2, 1] * ez
            dz = rg[0, 2] * ex + rg[1, 2] * ey + rg[2, 2] * ez
            t = _raycast._geom_local(geom_type[g], geom_size[g], ox, oy, oz, dx, dy, dz)
            if t >= 0.0 and t <= cutoff and (dist[i] < 0.0 or t < dist[i]):
                dist[i] = t
                geomid[i] = g


@pytest.mark.parametrize("downsample", [4, 8])
def test_culled_caster_equals_every_ray_against_every_geom_bit_for_bit(downsample):
    """Bug caught: a per-row span (bounding-sphere cone, the ellipsoid or infinite-cylinder
    quadric) that cuts off a pixel the geom covers, or an occlusion skip that drops the
    nearest hit. Oracle: a brute-force kernel that casts every pixel ray against every
    geom with the shared per-geom intersection routine, in id order; the two must agree
    exactly (distances and ids) on views from the episode and random views near the vine.
    """
    robot = SimRobot(VineSceneParams.sample(2), camera=CameraConfig(downsample=downsample))
    cam, m, d = robot._camera, robot.model, robot.data
    rng = np.random.default_rng(downsample)
    centre = np.asarray(robot.scene.stem_base)
    bounded = m.geom_rbound > 0
    leaves = [g for g in range(m.ngeom) if m.geom(g).name.startswith("leaf")]
    views = [robot.site_pose("camera")]
    while len(views) < 25:
        eye = centre + rng.normal(0.0, 0.3, 3)
        eye[2] = max(eye[2], 0.05)
        if np.any(np.linalg.norm(d.geom_xpos[bounded] - eye, axis=1) < m.geom_rbound[bounded] + 0.01):
            continue  # inside a geom's bounding sphere the casters may differ by design
        # Every other view looks at a leaf (the ellipsoid quadric), the rest at the stem region.
        target = d.geom_xpos[leaves[rng.integers(len(leaves))]] if len(views) % 2 else centre + rng.normal(0, 0.15, 3)
        views.append(look_at(eye, target, rng.normal(0.0, 0.3, 3) + (0.0, 0.0, -1.0)))
    n = cam.n_pixels
    ids, lengths = np.empty(n, np.int32), np.empty(n)
    hits = {int(t): 0 for t in np.unique(m.geom_type)}
    for pose in views:
        dist, geomid = cam.cast(d, pose)
        _cast_every_geom(
            cam._rays_c, np.ascontiguousarray(pose[:3, 3]), np.ascontiguousarray(pose[:3, :3]), cam._geom_type,
            m.geom_size, d.geom_xpos, d.geom_xmat, cam._mask, cam._cutoff, ids, lengths,
        )  # fmt: skip
        np.testing.assert_array_equal(geomid, ids)
        np.testing.assert_array_equal(dist, lengths)
        for t in hits:
            hits[t] += int(np.sum(m.geom_type[ids[ids >= 0]] == t))
    # The views did hit ellipsoids (leaves), capsules (arms, canes) and the floor.
    assert hits[int(mujoco.mjtGeom.mjGEOM_ELLIPSOID)] > 1000 and hits[int(mujoco.mjtGeom.mjGEOM_CAPSULE)] > 1000
    assert hits[int(mujoco.mjtGeom.mjGEOM_PLANE)] > 100


def test_one_pass_cloud_equals_the_two_pass_cloud_with_noise_and_dropout():
    """Bug caught: the one-pass compaction of the ray lengths (depth per pixel, row and column
    from the loop) changing a point, its order, a label or the noise and dropout draws.
    Oracle: the shared ``_finish(pose, dist * ray_z, ...)`` path (also used by the OpenGL
    camera), over several views.
    """
    cfg = CameraConfig(downsample=4, depth_noise=0.003, dropout=0.1, stem_range=0.9)
    robot = SimRobot(camera=cfg, seed=3)
    cam, d = robot._camera, robot.data
    rng = np.random.default_rng(1)
    centre = np.asarray(robot.scene.stem_base)
    poses = [robot.site_pose("camera")] + [
        look_at(centre + rng.normal(0, 0.25, 3) + (-0.3, 0.0, 0.1), centre + rng.normal(0, 0.1, 3)) for _ in range(4)
    ]
    total = 0
    for k, pose in enumerate(poses):
        cam.reset(seed=k)
        one = cam.capture(d, pose, 0.5)
        dist, geomid = (x.copy() for x in cam.cast(d, pose))
        cam.reset(seed=k)
        two = cam._finish(pose, dist * cam._ray_z, geomid, 0.5)
        cam.reset(seed=k)
        rays = cam._finish_rays(pose, dist, geomid, 0.5)
        total += len(one)
        for name in ("points", "labels", "colors", "depth", "pixels", "camera_pose"):
            np.testing.assert_array_equal(getattr(one, name), getattr(two, name), err_msg=name)
            np.testing.assert_array_equal(getattr(rays, name), getattr(two, name), err_msg=name)
    assert total > 5000


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
