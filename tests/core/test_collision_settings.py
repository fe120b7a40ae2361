"""``CollisionAvoidance.compute`` follows every change of the limit's settings and arrays made after
its first compute. Oracle: a fresh limit built with the new settings (or given the new arrays before
its first compute), computing at the same ``q``."""

import numpy as np

from harvest_qp import Configuration
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot.description import HOME_Q


def _rows(limit, config):
    rows = limit.compute(config, 0.002)
    k = limit.num_rows
    return rows.G[:k].copy(), rows.h[:k].copy(), limit.active_pairs.copy()


def _same(a, b):
    for x, y in zip(a, b):
        assert x.shape == y.shape and np.array_equal(x, y)


def test_compute_follows_every_assignment_after_a_first_compute(rng):
    """Each change below is made after a compute cached the arguments; the next compute must equal a
    fresh limit's with that change. Bugs caught (planted and seen failing): the limit's __setattr__
    not dropping the cache (a new gain and new obstacle spheres ignored); the tree's version not
    compared (a replaced tree array ignored)."""
    config = Configuration.dual_ur5e(HOME_Q)
    centres = np.array([[0.3, 0.1, 0.9], [0.5, -0.2, 1.1], [0.4, 0.0, 1.0]])
    cached = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)
    cached.set_obstacle_spheres(centres, 0.02)
    for _ in range(3):
        config.update(HOME_Q + rng.normal(0, 0.3, 12))
        fresh = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3)
        fresh.set_obstacle_spheres(centres, 0.02)
        _same(_rows(cached, config), _rows(fresh, config))
    # A setting assigned after the cache was made.
    cached.gain = 0.2
    fresh = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3, gain=0.2)
    fresh.set_obstacle_spheres(centres, 0.02)
    _same(_rows(cached, config), _rows(fresh, config))
    # New obstacle spheres (new buffers) and approach-only capsules.
    centres2 = centres + 0.05
    cached.set_obstacle_spheres(centres2, 0.03)
    cached.set_approach_only(["grasp_left"] if "grasp_left" in cached.capsule_names else [cached.capsule_names[-4]])
    fresh.set_obstacle_spheres(centres2, 0.03)
    fresh.set_approach_only(cached.approach_only_capsules)
    _same(_rows(cached, config), _rows(fresh, config))
    # Obstacle spheres moved in place (the obstacle map's feed): the same buffers, seen at once.
    cached.cap_p0[-3:] += 0.01
    cached.cap_p1[-3:] += 0.01
    fresh.cap_p0[-3:] += 0.01
    fresh.cap_p1[-3:] += 0.01
    _same(_rows(cached, config), _rows(fresh, config))
    # A tree array replaced (the tree's own __setattr__): a shifted base of the first joint.
    place_p = cached.tree.place_p.copy()
    place_p[1] += np.array([0.0, 0.0, 0.05])
    cached.tree.place_p = place_p
    fresh.tree.place_p = place_p.copy()
    _same(_rows(cached, config), _rows(fresh, config))
    before = _rows(cached, config)
    fresh.tree = cached.tree  # a whole tree assigned: the fresh limit's own cache dropped too
    _same(_rows(fresh, config), before)


def test_a_subclass_setting_computed_in_a_property_is_read_every_compute():
    """Oracle: a fresh limit built with the new gain. A subclass whose ``gain`` property reads a
    settings dict edited in place (no assignment to the limit) must get rows with the new gain.

    Bug caught (an audit's reproducer; planted by caching the arguments for subclasses too, seen
    failing): the cached argument tuple kept the first gain, 1.18 m/s off in h."""
    settings = {"gain": 0.5}

    class ScheduledGain(CollisionAvoidance):
        @property
        def gain(self):
            return settings["gain"]

        @gain.setter
        def gain(self, value):
            settings["gain"] = float(value)

    config = Configuration.dual_ur5e(HOME_Q + 0.3)
    centres = np.random.default_rng(0).normal([0.6, 0.0, 0.4], 0.2, (20, 3))
    limit = ScheduledGain.dual_ur5e(config, influence_distance=0.3)
    limit.set_obstacle_spheres(centres, 0.03)
    limit.compute(config, 0.002)
    settings["gain"] = 3.0
    h = limit.compute(config, 0.002).h[: limit.num_rows].copy()
    fresh = CollisionAvoidance.dual_ur5e(config, influence_distance=0.3, gain=3.0)
    fresh.set_obstacle_spheres(centres, 0.03)
    h_fresh = fresh.compute(config, 0.002).h[: fresh.num_rows]
    assert limit.num_rows == fresh.num_rows > 0
    assert np.array_equal(h, h_fresh)
