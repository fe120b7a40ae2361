"""The paper episode's viewer extras: the controller's per-tick values as ViewerFrame fields."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from harvest_qp.harvest.harvest_controller import Phase
from harvest_qp.viewer import ViewerFrame, paper_episode_extras


def _command(**values):
    base = {"phase": float(Phase.BIMANUAL), "theta": 0.01, "p_r": [0.1, 0.2, 0.3], "p_sb": [0.1, 0.2, 0.31],
            "p_gd": [np.nan] * 3, "V_c": np.arange(6.0), "V_g": -np.arange(6.0)}
    base.update(values)
    return SimpleNamespace(values={k: np.asarray(v, dtype=float) for k, v in base.items()})


def test_extras_name_the_phase_draw_the_roi_and_leave_out_unknown_points():
    """Catches: the ROI sphere missing from `harvest-qp run --viewer meshcat` (the CLI drew no
    markers before), NaN points (p_gd before the switch) sent to the viewer, a field name the
    viewer does not know."""
    extras = paper_episode_extras(0.35)(None, _command())
    assert extras["phase"] == "bimanual" and extras["theta"] == 0.01
    np.testing.assert_array_equal(extras["roi_center"], [0.1, 0.2, 0.3])
    assert extras["roi_radius"] == 0.35
    assert "p_gd" not in extras
    np.testing.assert_array_equal(extras["v_g"], -np.arange(6.0))
    assert set(extras) <= set(ViewerFrame.__dataclass_fields__)


def test_extras_copy_the_values_the_viewer_draws_later():
    """The viewer draws on its own thread: a controller that reuses its arrays must not change
    what was observed."""
    command = _command(p_gd=[0.0, 0.1, 0.2])
    extras = paper_episode_extras(0.35)(None, command)
    command.values["p_gd"][:] = 9.0
    np.testing.assert_array_equal(extras["p_gd"], [0.0, 0.1, 0.2])


def _coal_capsule(p0, p1, radius):
    import coal

    axis = p1 - p0
    length = float(np.linalg.norm(axis))
    z = axis / length
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    return coal.Capsule(radius, length), coal.Transform3s(R, (p0 + p1) / 2)


def test_closest_pair_points_match_coal_on_random_states():
    """The viewer's witness points against coal's capsule distance at pinocchio placements.

    Catches: a capsule placed in the wrong frame (the link's, not the world's), radii not
    subtracted, a witness point on the wrong body."""
    import coal

    from harvest_qp.configuration import Configuration
    from harvest_qp.robot import description as desc
    from harvest_qp.viewer.closest import ClosestPairLocator

    locator = ClosestPairLocator()
    bodies = {b.name: b for b in desc.collision_bodies()}
    config = Configuration.dual_ur5e()
    rng = np.random.default_rng(3)
    pairs = [("cam_forearm", "grasp_gripper"), ("cam_cutter", "grasp_wrist_3"), ("cam_upper_arm", "cam_wrist_2"),
             ("grasp_forearm", "stand")]
    checked = 0
    for _ in range(20):
        q = rng.uniform(-np.pi, np.pi, 12)
        config.update(q)
        for a, b in pairs:
            geoms = []
            for name in (a, b):
                pose = config.frame_pose(bodies[name].link)
                cap = bodies[name].capsule
                geoms.append(_coal_capsule(pose.rotation @ np.asarray(cap.p0) + pose.translation,
                                           pose.rotation @ np.asarray(cap.p1) + pose.translation, cap.radius))
            result = coal.DistanceResult()
            distance = coal.distance(geoms[0][0], geoms[0][1], geoms[1][0], geoms[1][1], coal.DistanceRequest(),
                                     result)
            if distance <= 1e-3:
                continue  # penetrating: coal's witness points are not the surface points
            points = locator.points(q, a, b)
            assert abs(np.linalg.norm(points[1] - points[0]) - distance) < 1e-6
            np.testing.assert_allclose(points[0], result.getNearestPoint1(), atol=1e-5)
            np.testing.assert_allclose(points[1], result.getNearestPoint2(), atol=1e-5)
            checked += 1
    assert checked > 40


def test_closest_pair_extras_pick_the_nearest_row_and_a_cell_centre():
    """A map cell's witness is its centre; the closest of the active rows is drawn.
    Hand-computed: cell [45,18,118] at 1 cm has its centre at (0.455, 0.185, 1.185)."""
    from harvest_qp.viewer.closest import ClosestPairLocator

    command = _command()
    command.collision_pairs = [("cam_forearm", "grasp_gripper", 0.30), ("cam_cutter", "cell[45,18,118]", 0.05)]
    extras = paper_episode_extras(0.35, cell_resolution=0.01)(SimpleNamespace(q=np.zeros(12)), command)
    np.testing.assert_allclose(extras["closest_pair"][1], [0.455, 0.185, 1.185])
    assert extras["closest_distance"] == 0.05
    expected = ClosestPairLocator().points(np.zeros(12), "cam_cutter", "cell[45,18,118]")
    np.testing.assert_allclose(extras["closest_pair"], expected)


def test_switch_snapshot_draws_the_stem_segments_and_the_samples_once_switched():
    """Catches: the live CLI view without Fig. fig:PC_proc's stem segments and free space F."""
    seg = lambda a, b: SimpleNamespace(start=np.array(a, float), end=np.array(b, float))  # noqa: E731
    controller = SimpleNamespace(switch_snapshot=None)
    extras = paper_episode_extras(0.35, controller=controller)
    obs = SimpleNamespace(q=np.zeros(12))
    assert "samples_kept" not in extras(obs, _command())
    controller.switch_snapshot = SimpleNamespace(
        stem=SimpleNamespace(top=seg([0, 0, 1], [0, 0, 0.9]), bottom=seg([0, 0, 0.9], [0, 0.01, 0.85])),
        free_space=SimpleNamespace(kept_samples=np.ones((5, 3)), removed_samples=np.zeros((7, 3))),
    )
    out = extras(obs, _command())
    assert out["stem_segments"].shape == (2, 2, 3) and out["stem_segments"][1, 1, 1] == 0.01
    assert out["samples_kept"].shape == (5, 3) and out["samples_removed"].shape == (7, 3)
