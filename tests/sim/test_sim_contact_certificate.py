"""The contact certificate: steps that skip MuJoCo's collision detection equal full steps.

``SimRobot`` runs ``mj_step1`` without collision detection when :class:`ContactCertificate`
proves no contact is possible (see its docstring). Oracles: the same robot stepped with
MuJoCo's full detection every step (bit for bit), MuJoCo's own ``mj_geomDistance`` for
the motion bound, and a hand-built pendulum model.
"""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from harvest_qp.sim import SimRobot
from harvest_qp.sim.contacts import _CERTIFICATE_CLEARANCE, _CERTIFICATE_HORIZON, _DSBL_CONTACT, ContactCertificate


def _full_detection(robot: SimRobot) -> SimRobot:
    """The oracle: the robot with its certificate switched off (plain mj_step2 + mj_step1)."""
    robot._certificate.supported = False
    robot._certificate.invalidate()
    return robot


def _assert_same_state(a: SimRobot, b: SimRobot, tick: int) -> None:
    da, db = a.data, b.data
    assert da.ncon == db.ncon, tick
    for name in ("qpos", "qvel", "qacc", "ctrl", "sensordata", "qacc_warmstart", "geom_xpos"):
        np.testing.assert_array_equal(getattr(da, name), getattr(db, name), err_msg=f"{name} at tick {tick}")
    if da.ncon:
        np.testing.assert_array_equal(da.contact.geom[: da.ncon], db.contact.geom[: db.ncon])
        np.testing.assert_array_equal(da.contact.dist[: da.ncon], db.contact.dist[: db.ncon])


def test_certified_steps_equal_full_detection_into_and_out_of_contact(default_scene):
    """Bug caught: a step certified while a contact was possible (wrong reach, clearance,
    margin or pair set), MuJoCo's flags left modified, a baseline taken while in contact.

    Oracle: the same robot stepped with MuJoCo's full collision detection every step. The
    commands sweep the grasping arm into the vine (contacts for ~100 ticks) and back, and
    the camera arm around; state, contacts and sensors are compared bit for bit every tick.
    Planted and caught: the flags restored as ``flags | _DSBL_CONTACT`` (no contact is ever
    found); the clearance set to -0.02 m (a contact missed on a certified step). Halved
    reaches pass here (the bound is loose on these sweeps): the next test catches them.
    """
    a = SimRobot(default_scene, camera=None)
    b = _full_detection(SimRobot(default_scene, camera=None))
    assert a._certificate.supported
    certified = contact_ticks = 0
    segments = [(6, 0.8, 90), (6, -0.8, 90), (0, 0.6, 60), (1, -0.5, 60), (7, 0.5, 60), (0, -0.6, 60)]
    tick = 0
    for joint, speed, ticks in segments:
        qdot = np.zeros(12)
        qdot[joint] = speed
        a.send_joint_velocities(qdot)
        b.send_joint_velocities(qdot)
        for _ in range(ticks):
            certified += a._certificate._valid
            a.step()
            b.step()
            tick += 1
            contact_ticks += a.data.ncon > 0
            _assert_same_state(a, b, tick)
    flags = a.model.opt.disableflags
    assert flags == b.model.opt.disableflags and not flags & _DSBL_CONTACT
    assert contact_ticks > 20  # the sweep did reach the vine
    assert certified > tick // 8  # and many steps skipped the detection (fast sweeps: ~1.5 mm per step)


def test_motion_bound_holds_against_mujoco_distances(default_scene):
    """Bug caught: a joint's reach too short, a joint left out of a pair's terms, a common
    ancestor counted as moving one geom only.

    Oracle: ``mujoco.mj_geomDistance`` at two configurations. For every pair of the
    certificate, the distance at q1 must be at least the distance at q0 minus the
    certificate's motion bound sum R |q1 - q0| (single joints and all joints moved, large
    steps so the bound is nearly tight for the base joints). Planted and caught: reaches
    halved; the common-ancestor terms dropped from the other geom's side.
    """
    robot = SimRobot(default_scene, camera=None)
    m, d = robot.model, robot.data
    cert = robot._certificate
    rng = np.random.default_rng(3)
    home = robot.scene.home_q
    fromto = np.zeros(6)
    pairs = cert._pair_geoms
    worst = np.inf
    for trial in range(40):
        q0 = home + rng.normal(0.0, 0.4, 12)
        dq = np.zeros(12)
        if trial % 2:
            dq[rng.integers(12)] = rng.choice([-1.0, 1.0]) * rng.uniform(0.05, 0.3)
        else:
            dq = rng.normal(0.0, 0.05, 12)
        dist = []
        for q in (q0, q0 + dq):
            d.qpos[robot._qpos_ids] = q
            mujoco.mj_kinematics(m, d)
            dist.append(np.array([mujoco.mj_geomDistance(m, d, int(g), int(h), 10.0, fromto) for g, h in pairs]))
        moved = np.abs(dq)[np.searchsorted(robot._qpos_ids, cert._joint_qpos)]
        bound = (cert._term_reach * moved[cert._term_joint]).sum(axis=1)
        # ccd_tolerance: MuJoCo's convex distances (ellipsoids) are accurate to ~1e-6 m.
        slack = dist[1] - (dist[0] - bound) + 1e-6
        worst = min(worst, float((slack / np.maximum(bound, 1e-9)).min()))
        assert (slack >= 0.0).all(), [(m.geom(g).name, m.geom(h).name) for g, h in pairs[slack < 0]]
    robot.reset()
    assert worst < 0.5  # some sampled motion came within 2x of the bound (the test can fail)


_PENDULUM = """
<mujoco>
  <option timestep="0.002"/>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.1"/>
    <geom name="post" type="capsule" fromto="0.45 0 0 0.45 0 0.6" size="0.03"/>
    <body name="arm" pos="0 0 0.45">
      <joint name="hinge" type="hinge" axis="0 1 0" damping="0.01"/>
      <geom name="rod" type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="1"/>
      <body name="leaf_body" pos="0.3 0 0">
        <joint name="hinge2" type="hinge" axis="0 1 0"/>
        <geom name="leaf" type="ellipsoid" pos="0.1 0 0" size="0.1 0.05 0.01" mass="0.2"/>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def _step_pair(model: mujoco.MjModel, certificate: ContactCertificate, data: mujoco.MjData) -> bool:
    """SimRobot._physics_step's collision part on a bare model; True when the step was certified."""
    mujoco.mj_step2(model, data)
    if certificate._valid and certificate.certified(data.qpos):
        flags = model.opt.disableflags
        model.opt.disableflags = flags | _DSBL_CONTACT
        mujoco.mj_step1(model, data)
        model.opt.disableflags = flags
        return True
    mujoco.mj_step1(model, data)
    certificate.rebase(data)
    return False


@pytest.mark.parametrize("padding", ["", 'margin="0.01" gap="0.02"'])
def test_pendulum_falling_onto_a_post_and_floor_equals_full_detection(padding):
    """Bug caught: the certificate on a model other than the lab's (plane half-space bound,
    ellipsoid refinement, two-joint chain, geom margins and gaps) lets a contact through.

    Oracle: the same model stepped with full detection. A double pendulum swings down onto
    a post and the floor; contacts must appear at the same step in both, bit for bit.
    Planted and caught: the plane bound's sign flipped (``h = -h``); the gaps left out of
    the pairs' thresholds (MuJoCo reports contacts within margin + gap).
    """
    model = mujoco.MjModel.from_xml_string(_PENDULUM.replace('type="ellipsoid"', f'type="ellipsoid" {padding}'))
    a, b = mujoco.MjData(model), mujoco.MjData(model)
    a.qpos[:] = b.qpos[:] = [-1.2, 0.3]
    mujoco.mj_forward(model, a)
    mujoco.mj_forward(model, b)
    certificate = ContactCertificate(model)
    assert certificate.supported
    certified = contacts = 0
    for step in range(800):
        certified += _step_pair(model, certificate, a)
        mujoco.mj_step2(model, b)
        mujoco.mj_step1(model, b)
        assert a.ncon == b.ncon, step
        np.testing.assert_array_equal(a.qpos, b.qpos)
        np.testing.assert_array_equal(a.qvel, b.qvel)
        contacts += a.ncon > 0
    assert contacts > 10 and certified > 100


def test_certificate_refuses_what_it_cannot_prove():
    """Bug caught: a certificate valid for a free body, with a contact filter callback, with
    sleeping enabled, or a baseline taken in contact.

    Oracle: hand-built models and MuJoCo's own flags. Planted and caught: the free-joint
    check removed (the free body's certificate says supported).
    """
    free = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom type="plane" size="1 1 .1"/><body pos="0 0 1"><freejoint/>'
        '<geom type="sphere" size=".1"/></body></worldbody></mujoco>'
    )
    assert not ContactCertificate(free).supported
    model = mujoco.MjModel.from_xml_string(_PENDULUM)
    data = mujoco.MjData(model)
    data.qpos[:] = [-1.2, 0.3]
    mujoco.mj_forward(model, data)
    certificate = ContactCertificate(model)
    certificate.rebase(data)
    assert certificate._valid and certificate.certified(data.qpos)
    model.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
    certificate.invalidate()
    certificate.rebase(data)
    assert not certificate._valid
    model.opt.enableflags = 0
    # In contact (the leaf pressed into the floor): no baseline.
    data.qpos[:] = [1.4, 0.0]
    mujoco.mj_forward(model, data)
    assert data.ncon > 0
    certificate.invalidate()
    certificate.rebase(data)
    assert not certificate._valid
    # A clearance below the certificate's: no baseline either (no contact yet, but too close).
    data.qpos[:] = [-1.2, 0.3]
    mujoco.mj_forward(model, data)
    certificate.invalidate()
    certificate.rebase(data)
    assert certificate._valid
    moved = data.qpos.copy()
    moved[0] += 10.0  # far beyond any slack
    assert not certificate.certified(moved)
    assert _CERTIFICATE_CLEARANCE > 1e-4


def test_contact_filter_callback_disables_the_certificate():
    """Bug caught: steps certified while a user's contact filter (which replaces MuJoCo's
    bitmask filter, so any pair may collide) is installed. Oracle: the callback itself.
    Planted and caught: the callback check removed from ``rebase``.
    """
    import ctypes

    model = mujoco.MjModel.from_xml_string(_PENDULUM)
    data = mujoco.MjData(model)
    data.qpos[:] = [-1.2, 0.3]
    mujoco.mj_forward(model, data)
    certificate = ContactCertificate(model)
    prototype = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int)
    keep = prototype(lambda m, d, g1, g2: 0)
    mujoco.set_mjcb_contactfilter(keep)
    try:
        certificate.rebase(data)
        assert not certificate._valid
    finally:
        mujoco.set_mjcb_contactfilter(None)
    certificate.rebase(data)
    assert certificate._valid


def test_sorted_early_exit_equals_testing_every_pair(default_scene):
    """Bug caught: the per-step kernel's early exit (near pairs sorted by slack over largest
    reach, stop once the total joint travel is below it; far pairs never tested) certifying
    a configuration that the full per-pair test refuses, or refusing one it accepts.

    Oracle: numpy over every pair: total travel below the horizon and
    ``(reach * |q - q0|[joint]).sum(1) < slack`` for all pairs (slacks from the baseline,
    exact or the bounding-sphere gap beyond the horizon). 600 random configurations around
    the baseline, both outcomes present. Planted and caught: the exit test as
    ``travel < 2 * tau[i]``; the travel summed over half the joints; the near list cut at
    half the horizon in ``_certificate_order``.
    """
    robot = SimRobot(default_scene, camera=None)
    cert = robot._certificate
    cert.invalidate()
    cert.rebase(robot.data)
    assert cert._valid
    # The near list: exactly the moving pairs whose slack over largest reach is below the
    # horizon, in increasing order of it (numpy's stable argsort).
    reach_max = cert._term_reach.max(axis=1)
    tau = np.where(reach_max > 0, cert._pair_slack / np.where(reach_max > 0, reach_max, 1.0), np.inf)
    expected_near = np.flatnonzero(tau < _CERTIFICATE_HORIZON)
    expected_near = expected_near[np.argsort(tau[expected_near], kind="stable")]
    nj, n_near = cert._joint_qpos.size, cert._ints[3]
    np.testing.assert_array_equal(cert._ints[4 + nj : 4 + nj + n_near], expected_near)
    rng = np.random.default_rng(11)
    q0 = robot.data.qpos.copy()
    outcomes = set()
    for i in range(600):
        q = q0.copy()
        scale = 10.0 ** rng.uniform(-4.5, -1.0)
        q[robot._qpos_ids] += rng.normal(0.0, scale, 12) * (rng.random(12) < 0.5)
        dq = np.abs(q[cert._joint_qpos] - cert._q0)
        within = dq.sum() < _CERTIFICATE_HORIZON  # beyond the horizon: always a new baseline
        expected = within and bool(((cert._term_reach * dq[cert._term_joint]).sum(axis=1) < cert._pair_slack).all())
        assert cert.certified(q) == expected, i
        outcomes.add(expected)
    # Adversarial: each pair that can come within its margin before the horizon, moved on
    # its longest-reach joint alone just past (and just short of) its slack.
    at_risk = np.flatnonzero((reach_max > 0) & (cert._pair_slack < 0.9 * _CERTIFICATE_HORIZON * reach_max))
    assert at_risk.size > 0
    for p in at_risk.tolist():
        c = int(np.argmax(cert._term_reach[p]))
        joint = cert._joint_qpos[cert._term_joint[p, c]]
        for factor in (1.01, 0.99):
            q = q0.copy()
            q[joint] += factor * cert._pair_slack[p] / cert._term_reach[p, c]
            dq = np.abs(q[cert._joint_qpos] - cert._q0)
            within = dq.sum() < _CERTIFICATE_HORIZON
            expected = within and bool(((cert._term_reach * dq[cert._term_joint]).sum(axis=1) < cert._pair_slack).all())
            assert cert.certified(q) == expected, (p, factor)
            if factor > 1.0:
                assert not expected
    assert outcomes == {True, False}


def test_carried_slacks_stay_below_mujoco_distances(default_scene):
    """Bug caught: a baseline that carries a pair's slack over from the last one without
    subtracting the motion since (or subtracting too little), or keeps a stale slack.

    Oracle: ``mujoco.mj_geomDistance`` of every pair at each new baseline: the slack held
    must not exceed the true distance minus margin and clearance (1e-6 m for MuJoCo's
    convex distances). The arms sweep fast through large motions, so carried slacks are
    used (checked) and shrink a lot between baselines. Planted and caught:
    ``carried = slack[p]`` (nothing subtracted); ``0.05 * max_reach[p] * travel`` subtracted
    (0.3 times passes: the bound is loose by more than 3x on these sweeps).
    """
    robot = SimRobot(default_scene, camera=None)
    m, d = robot.model, robot.data
    cert = robot._certificate
    fromto = np.zeros(6)
    inner = cert.rebase
    checked = carried = 0

    def rebase(data):
        nonlocal checked, carried
        full = cert._full
        inner(data)
        if not cert._valid or full:
            return
        carried += 1
        if carried % 3:
            return  # every third incremental baseline is held to MuJoCo (each costs ~650 distances)
        true = np.array([mujoco.mj_geomDistance(m, d, int(a), int(b), 10.0, fromto) for a, b in cert._pair_geoms])
        limit = true - cert._margin_view - _CERTIFICATE_CLEARANCE + 1e-6
        assert (cert._pair_slack <= limit).all(), [(m.geom(a).name, m.geom(b).name) for a, b in
                                                   cert._pair_geoms[cert._pair_slack > limit]]  # fmt: skip
        checked += 1

    cert.rebase = rebase
    for joint, speed, ticks in [(0, 1.0, 120), (7, -0.8, 120), (1, -0.6, 120), (6, 0.7, 60), (2, 0.8, 120)]:
        qdot = np.zeros(12)
        qdot[joint] = speed
        robot.send_joint_velocities(qdot)
        for _ in range(ticks):
            robot.step()
    assert checked >= 5
