"""What the camera can see of the stem: the gripper's tip, the start view, the occluder, the approach.

Oracles: MuJoCo's own ray caster (``mj_ray``) and geom poses of the compiled, settled scene,
and the pinhole model written out by hand from the camera's field of view; never the
scene builder's own placement maths.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
import pytest

from harvest_qp.runtime.interface import ROBOT, STEM
from harvest_qp.sim import CameraConfig, SimRobot, VineSceneParams, build_vine_scene
from harvest_qp.sim.camera import RayCastCamera
from harvest_qp.sim.scene import APPROACH_RADIUS, HIDDEN_APPROACH_MIN

#: The default scene and seeds 1-5 (seed 2 hides its stem along the whole approach).
SCENES = {"default": VineSceneParams(), **{f"seed{s}": VineSceneParams.sample(s) for s in range(1, 6)}}


def _stem_axis_samples(robot: SimRobot, per_segment: int = 60) -> np.ndarray:
    """Points along the settled stem's capsule axes [m] (from MuJoCo's geom poses)."""
    m, d = robot.model, robot.data
    out = []
    for g in robot.scene.stem_geoms:
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        half = m.geom_size[g, 1]
        out.append(d.geom_xpos[g] + np.linspace(-half, half, per_segment)[:, None] * axis)
    return np.vstack(out)


def _robot_capsules(robot: SimRobot) -> list[tuple[np.ndarray, np.ndarray, float]]:
    m, d = robot.model, robot.data
    caps = []
    for g in np.flatnonzero(robot.scene.geom_labels == ROBOT):
        assert m.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        half = m.geom_size[g, 1]
        caps.append((d.geom_xpos[g] - half * axis, d.geom_xpos[g] + half * axis, float(m.geom_size[g, 0])))
    return caps


def _point_segment(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def _stem_length_inside_robot(robot: SimRobot) -> float:
    """Length [m] of stem axis whose cross-section touches a robot capsule (stem surface inside)."""
    m = robot.model
    per = 200
    samples = _stem_axis_samples(robot, per)
    inside = np.zeros(len(samples), bool)
    radius = float(m.geom_size[robot.scene.stem_geoms[0], 0])
    for a, b, r in _robot_capsules(robot):
        inside |= _point_segment(samples, a, b) < r + radius
    seg_len = 2 * m.geom_size[robot.scene.stem_geoms, 1]
    return float(np.sum(inside.reshape(len(seg_len), per).mean(axis=1) * seg_len))


@pytest.mark.parametrize("seeds", [range(0, 20), range(20, 40)])
def test_stem_leaves_the_gripper_at_its_tip(seeds):
    """No more than 2 mm of any stem lies inside a robot geom, over 40 random scenes and the default.

    Bug caught: a grasping-tool capsule reaching past the grasp point (the old 0.11 m +
    45 mm capsule swallowed 18-19 mm of every stem: l was perceived 25-37 % short). Oracle:
    the compiled model's geom poses after the reset settled the scene, with the stem's own
    radius (the surface, not only the axis, must be outside).
    """
    params = [VineSceneParams.sample(s) for s in seeds]
    if seeds.start == 0:
        params.append(VineSceneParams())
    worst = 0.0
    for p in params:
        robot = SimRobot(p, camera=None, settle_time=0.1)
        worst = max(worst, _stem_length_inside_robot(robot))
        # MuJoCo's distance agrees: the stem's surface clears the gripper.
        gripper = robot.model.geom("grasp_gripper").id
        for g in robot.scene.stem_geoms:
            assert mujoco.mj_geomDistance(robot.model, robot.data, gripper, int(g), 0.1, None) > -2e-3
    assert worst <= 2e-3, worst


def _camera(robot: SimRobot, config: CameraConfig | None = None) -> RayCastCamera:
    return RayCastCamera(
        robot.model, config or CameraConfig(), geom_labels=robot.scene.geom_labels,
        exclude_body=robot.scene.ids["cam_tool"],
    )  # fmt: skip


@pytest.fixture(scope="module")
def robots() -> dict[str, SimRobot]:
    return {name: SimRobot(p, camera=None) for name, p in SCENES.items()}


def _stem_points(robot: SimRobot, pose: np.ndarray) -> int:
    return _camera(robot).capture(robot.data, pose, 0.0).count(STEM)


def test_start_view_sees_no_stem_because_of_the_field_of_view(robots):
    """At HOME_Q no stem point is seen; the reason is the field of view (and on the default, range).

    Bug caught: a start view that already sees the stem (the paper's approach would have
    nothing to find) or a README naming the wrong cause (it said the leaf). The cause is
    computed with the pinhole model written out by hand: f = (h/2) / tan(fovy/2).
    """
    config = CameraConfig()
    h, w = config.image_size
    f = (h / 2) / math.tan(math.radians(40.0) / 2)
    for name, robot in robots.items():
        pose = robot.site_pose("camera")
        assert _stem_points(robot, pose) == 0, name
        local = (_stem_axis_samples(robot) - pose[:3, 3]) @ pose[:3, :3]
        u = f * local[:, 0] / local[:, 2] + w / 2
        v = f * local[:, 1] / local[:, 2] + h / 2
        in_image = (local[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        in_range = np.linalg.norm(local, axis=1) <= config.stem_range
        # The field of view alone hides it on every one of these scenes; on the default scene
        # it is also beyond the 0.7 m range (on seed 1 the stem's top is 0.695 m away).
        assert not np.any(in_image), name
        if name == "default":
            assert not np.any(in_range), np.linalg.norm(local, axis=1).min()


def _blockers(robot: SimRobot, view: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Per target: the geom ``mj_ray`` hits first between ``view`` and it (-1: nothing, it is seen)."""
    m, d = robot.model, robot.data
    out = np.full(len(targets), -1)
    gid = np.zeros(1, np.int32)
    stem = set(robot.scene.stem_geoms.tolist())
    radius = float(m.geom_size[robot.scene.stem_geoms[0], 0])
    for i, x in enumerate(targets):
        ray = x - view
        length = float(np.linalg.norm(ray))
        dist = mujoco.mj_ray(m, d, view, ray / length, None, 1, robot.scene.ids["cam_tool"], gid, None)
        # A hit well before the stem's surface by anything but the stem hides the target.
        if 0 <= dist < length - 1.5 * radius and int(gid[0]) not in stem:
            out[i] = int(gid[0])
    return out


COVERAGE_CASES = [(name, None) for name in SCENES] + [("default", c) for c in (0.0, 0.3, 0.55, 0.9, 1.0)]


@pytest.mark.parametrize(("name", "coverage"), COVERAGE_CASES)
def test_occluder_hides_the_requested_fraction_of_the_stem(robots, name, coverage):
    """Measured coverage (mj_ray from the approach viewpoint) matches ``occluder_coverage``.

    Bug caught: the parameter not reaching the geometry (leaf slid the wrong way, sized
    without it, placed for another viewpoint) and other leaves or petioles hiding the stem
    too. Oracle: MuJoCo's ray caster on the compiled scene after the reset settled it.
    """
    if coverage is None:
        robot = robots[name]
    else:
        robot = SimRobot(dataclasses.replace(SCENES[name], occluder_coverage=coverage), camera=None)
    view = robot.scene.approach_pose(APPROACH_RADIUS)[:3, 3]
    hit = _blockers(robot, view, _stem_axis_samples(robot, 40))
    occluder = robot.scene.ids["occluder"]
    expected = robot.scene.params.occluder_coverage
    assert abs(np.mean(hit == occluder) - expected) <= 0.03, (np.mean(hit == occluder), expected)
    assert np.mean((hit >= 0) & (hit != occluder)) <= 0.02  # nothing else hides it
    if 0 < expected < 1:
        # The leaf hides the cluster end and leaves the stem base visible.
        samples = _stem_axis_samples(robot, 40)
        seen = hit < 0
        base_side = np.linalg.norm(samples - robot.scene.stem_base, axis=1) < np.linalg.norm(
            samples - robot.scene.stem_end, axis=1
        )
        assert seen[base_side].mean() > seen[~base_side].mean()


def test_partly_hidden_stem_shows_a_few_points_once_the_camera_nears_the_roi(robots):
    """The paper's Fig. exp_unv set-up on the default scene and the partly hidden seeds 1-5.

    Nothing at the start, a few stem points along the straight approach once within 0.7 m,
    and at the ROI (0.35 m from p_sb) only part of what the same view sees without the
    occluder, so unveiling has work to do. Bug caught: a default scene on which the paper's
    own law cannot work (0 points at the ROI, the old layout) or one with nothing to unveil.
    """
    checked = []
    for name, robot in robots.items():
        if name != "default" and robot.scene.params.occluder_coverage >= 1.0:
            continue  # a sampled hidden-stem seed (the next test)
        checked.append(name)
        scene = robot.scene
        counts = {dist: _stem_points(robot, scene.approach_pose(dist)) for dist in (0.6, 0.45, APPROACH_RADIUS)}
        assert counts[0.6] > 0 and counts[APPROACH_RADIUS] >= 10, (name, counts)
        bare = SimRobot(dataclasses.replace(scene.params, occlude_stem=False), camera=None)
        full = _stem_points(bare, scene.approach_pose(APPROACH_RADIUS))
        assert counts[APPROACH_RADIUS] <= 0.6 * full, (name, counts, full)
    assert checked == ["default", "seed1", "seed3", "seed4", "seed5"]


@pytest.mark.parametrize("params", [SCENES["seed2"], dataclasses.replace(SCENES["default"], occluder_coverage=1.0)])
def test_hidden_stem_stays_hidden_along_the_whole_approach(params):
    """A hidden-stem scene: 0 stem points from every pose of the straight approach.

    Towards p_sb, the gripper point and the cluster centre, from the start down to 0.3 m,
    each view pointed at its target; without the occluder the same ROI view sees the stem.
    Bug caught: a "hidden" stem that peeks out past the leaf on the way in (the closed
    loop's hidden-stem test would then not test the extension).
    """
    assert params.occluder_coverage == 1.0
    robot = SimRobot(params, camera=None)
    scene = robot.scene
    for target in (scene.stem_base, scene.gripper_home[:3, 3], scene.cluster_centre):
        span = float(np.linalg.norm(scene.camera_start - target))
        for dist in np.linspace(HIDDEN_APPROACH_MIN, span, 8):
            assert _stem_points(robot, scene.approach_pose(dist, target=target)) == 0, (target, dist)
    bare = SimRobot(dataclasses.replace(params, occlude_stem=False), camera=None)
    assert _stem_points(bare, scene.approach_pose(APPROACH_RADIUS)) > 20


def test_approach_pose_points_the_camera_at_the_target():
    """``approach_pose``: on the line from the start, at the distance, optical axis on the target."""
    scene = build_vine_scene()
    for target in (None, scene.cluster_centre):
        goal = scene.stem_base if target is None else target
        T = scene.approach_pose(0.4, target=target)
        np.testing.assert_allclose(np.linalg.norm(T[:3, 3] - goal), 0.4, atol=1e-12)
        on_line = np.cross(T[:3, 3] - goal, scene.camera_start - goal)
        np.testing.assert_allclose(on_line, 0.0, atol=1e-12)
        np.testing.assert_allclose(T[:3, 2], (goal - T[:3, 3]) / 0.4, atol=1e-12)
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
