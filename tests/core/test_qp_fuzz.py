"""Fuzz states of every category in FINDINGS and crossing runs, judged by an independent geometry.

The full-size versions (20,000 states, 50 crossing runs) are ``python -m benchmarks.bench_fuzz``.
"""

import numpy as np
import pytest

from benchmarks.bench_fuzz import A_MAX, DT, FUZZ_CATEGORIES, CoalGeometry, fuzz_states, run_crossing
from harvest_qp.limits import CollisionAvoidance


def test_no_fallback_and_speed_change_within_the_acceleration_limit_on_fuzz_states():
    """320 collision-free states inside the limits (uniform, near limits, singular wrist, stretched
    elbow, arms within 4 cm, near obstacles, combinations, continuation with a moving previous
    command; references up to 1e3, weights 1e-4..1e3).

    Oracles: qdot = 0 is feasible at such states once the acceleration box is relaxed, so a
    fallback is a solver bug; the speed change per tick is checked against a_max dt by hand unless
    a position limit box conflicted (then the command is the nearest point of the position box) or
    the step reports a relaxation; the distances after the step come from pinocchio + coal, not
    from the kernel. Bugs caught (each planted by hand): no backend retry and an infeasibility
    report believed without the relaxation check (combination states fall back), dropping the
    acceleration limit when relaxing. The absolute feasibility tolerance itself is caught by
    ``test_qp_backends.py::test_feasibility_is_judged_relative_to_row_scale``: these states did
    not produce a DAQP solution off by 1e-7..1e-6 after the change.
    """
    per_category = {cat: 0 for cat in FUZZ_CATEGORIES}
    relaxed = 0
    geometries = {}
    for cat, configuration, controller, q, _ in fuzz_states(320, seed=7):
        per_category[cat] += 1
        collision = next(limit for limit in controller.limits if isinstance(limit, CollisionAvoidance))
        prev = controller.previous_qdot.copy()
        step = controller.step(q)
        assert step.ok, f"{cat}: {step.status}"
        x = step.qdot
        lo, hi = configuration.lower_limits, configuration.upper_limits
        assert np.all(np.abs(x) <= configuration.velocity_limits + 1e-12)
        assert np.all(q + x * DT <= hi + 1e-12) and np.all(q + x * DT >= lo - 1e-12)
        change = np.abs(x - prev)
        forced = np.zeros(12, dtype=bool)
        for conflict in step.conflicts:
            forced[conflict.joint] = True
        if "relaxed" in step.status:
            relaxed += 1
            slack = controller.solver_solution.box_relaxation
            assert np.all(change[~forced] <= A_MAX * DT + slack[~forced] + 1e-9)
        else:
            assert np.all(change[~forced] <= A_MAX * DT + 1e-9), cat
        # A step from a collision-free state keeps every pair outside d_s (independent geometry).
        key = id(collision)
        if key not in geometries:
            geometries[key] = CoalGeometry(configuration, collision)
        geometry = geometries[key]
        obstacles = [i for i, name in enumerate(collision.capsule_names) if name.startswith("obstacle_")]
        geometry.set_obstacles(collision.cap_p0[obstacles], collision.cap_radius[obstacles])
        d_after, pair = geometry.min_distance(q + x * DT)
        assert d_after >= collision.safety_distance - 1e-4, (cat, pair, d_after)
    assert min(per_category.values()) >= 30
    assert relaxed < 320 // 4


@pytest.mark.parametrize("seed", [104, 105])
def test_crossing_runs_with_obstacles_keep_the_safety_distance(seed):
    """Two pose tasks swap tool positions among 20 obstacle spheres (d_s 2 cm, d_i 12 cm, gain 5).

    Oracle: pinocchio frame placements + coal capsules every tick (exact minimum over every
    candidate pair). Bugs caught (planted by hand): no backend retry and no relaxation check
    (fallback ticks; FINDINGS' seed 104 braked for 535 of 2,000 ticks), pairs below d_s.
    """
    result = run_crossing(seed, ticks=700)
    assert result.fallbacks == 0
    assert result.moved > 0.1, "the arms must actually move"
    assert result.min_distance >= 0.02 - 1e-4, result
