"""RGB-D camera: analytic depth, labels, range handling, both ray casters, noise, rate, latency."""

from __future__ import annotations

import dataclasses
import os

import mujoco
import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.interface import OBSTACLE, ROBOT, STEM, PointCloud
from harvest_qp.sim import CameraConfig, SimRobot
from harvest_qp.sim.camera import RayCastCamera
from tests.sim.helpers import look_at

# A wall (plane x = 1.2, facing -x), a ball and a far ball in front of a camera at the origin.
TEST_XML = """
<mujoco>
  <worldbody>
    <geom name="wall" type="plane" pos="1.2 0 0" zaxis="-1 0 0" size="2 2 0.01"/>
    <geom name="ball" type="sphere" pos="0.8 0.1 -0.05" size="0.1"/>
    <geom name="far_ball" type="sphere" pos="1.0 -0.3 0.1" size="0.08"/>
    <body name="tool" pos="0.02 0 0"><geom name="own" type="sphere" size="0.01"/></body>
  </worldbody>
</mujoco>
"""
# Camera at the origin looking +x, image x = world -y, image y = world -z.
POSE = look_at((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))


@pytest.fixture(scope="module")
def test_scene():
    model = mujoco.MjModel.from_xml_string(TEST_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    labels = np.full(model.ngeom, OBSTACLE, np.int8)
    labels[model.geom("ball").id] = STEM
    labels[model.geom("far_ball").id] = STEM
    return model, data, labels


def _analytic_distance(origin: np.ndarray, direction: np.ndarray) -> tuple[float, str]:
    """Nearest hit of a ray with the wall plane and the two balls (closed form)."""
    best, name = np.inf, ""
    if direction[0] > 0:
        t = (1.2 - origin[0]) / direction[0]
        best, name = t, "wall"
    for ball, centre, r in (("ball", (0.8, 0.1, -0.05), 0.1), ("far_ball", (1.0, -0.3, 0.1), 0.08)):
        oc = origin - np.asarray(centre)
        b = oc @ direction
        disc = b * b - (oc @ oc - r * r)
        if disc >= 0:
            t = -b - np.sqrt(disc)
            if 0 <= t < best:
                best, name = t, ball
    return best, name


@pytest.mark.parametrize("engine", ["numba", "mujoco"])
def test_depth_matches_analytic_plane_and_sphere(test_scene, engine):
    model, data, labels = test_scene
    cfg = CameraConfig(width=320, height=240, downsample=2, stem_range=0.9, raycast_engine=engine)
    cam = RayCastCamera(model, cfg, geom_labels=labels, exclude_body=model.body("tool").id)
    cloud = cam.capture(data, POSE, 1.5)
    assert isinstance(cloud, PointCloud) and cloud.timestamp == 1.5
    h, w = cfg.image_size
    # Every pixel sees the wall or a ball: the sphere of the excluded "tool" body, 2 cm in
    # front of the camera, would otherwise blank the centre of the image.
    assert (h, w) == (120, 160) and len(cloud) == h * w
    rays = cfg.pixel_rays()
    names = {model.geom(g).name: g for g in range(model.ngeom)}
    hits = {"wall": 0, "ball": 0, "far_ball": 0}
    for i in range(len(cloud)):
        row, col = cloud.pixels[i]
        d_world = POSE[:3, :3] @ rays[row * w + col]
        t, name = _analytic_distance(np.zeros(3), d_world)
        hits[name] += 1
        expected_point = t * d_world
        assert np.linalg.norm(cloud.points[i] - expected_point) < 1e-3
        assert abs(cloud.depth[i] - t * rays[row * w + col, 2]) < 1e-3
        # Labels: the near ball is stem (within 0.9 m); the far ball is beyond the stem
        # range and becomes an obstacle; the wall is an obstacle.
        expected = STEM if (name == "ball" and t <= 0.9) else OBSTACLE
        assert cloud.labels[i] == expected, (name, t)
    assert min(hits.values()) > 50
    # Colours come from the geom colours.
    np.testing.assert_array_equal(cloud.colors[0], np.round(model.geom_rgba[names["wall"], :3] * 255))


def test_points_beyond_max_depth_are_dropped(test_scene):
    model, data, labels = test_scene
    cfg = CameraConfig(width=160, height=120, downsample=1, max_depth=1.0)
    cloud = RayCastCamera(model, cfg, geom_labels=labels, exclude_body=model.body("tool").id).capture(data, POSE, 0.0)
    # The wall at 1.2 m is gone, the balls remain.
    assert 0 < len(cloud) < 160 * 120
    assert np.all(cloud.depth <= 1.0) and np.all(cloud.depth >= cfg.min_depth)
    assert np.all(cloud.points[:, 0] < 1.0)


def test_default_camera_is_the_downsampled_d415():
    cfg = CameraConfig()
    assert cfg.image_size == (160, 283)
    assert cfg.vertical_fov == 40.0
    assert cfg.horizontal_fov == pytest.approx(65.6, abs=0.5)
    assert cfg.rate == 30.0 and cfg.stem_range == 0.7
    full = CameraConfig(downsample=1)
    assert full.image_size == (480, 848)
    rays = cfg.pixel_rays()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0)
    assert rays[0, 0] < 0 and rays[0, 1] < 0  # top-left pixel: left and up


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"downsample": 0}, "downsample"),
        ({"vertical_fov": 0.0}, "vertical_fov"),
        ({"dropout": 1.0}, "dropout"),
        ({"min_depth": 3.0}, "min_depth"),
        ({"backend": "vulkan"}, "backend"),
        ({"raycast_engine": "cuda"}, "raycast_engine"),
        ({"latency": -0.1}, "latency"),
    ],
)
def test_invalid_camera_config(kwargs, words):
    with pytest.raises(InvalidInputError, match=words):
        CameraConfig(**kwargs)


@pytest.fixture(scope="module")
def vine_robot():
    return SimRobot(camera=CameraConfig(stem_range=5.0))


def _views(robot):
    mid = 0.5 * (robot.scene.stem_base + robot.scene.stem_end)
    return [
        robot.site_pose("camera"),
        look_at(robot.scene.camera_home[:3, 3], mid),
        look_at(mid + 0.3 * np.array([-np.cos(0.6), np.sin(0.6), 0.05]), mid),
        look_at(mid + np.array([-0.12, 0.05, 0.02]), mid),
        look_at(robot.site_pose("gripper")[:3, 3] + [-0.25, 0.2, 0.0], mid),
    ]


def test_numba_caster_agrees_with_mj_multiray(vine_robot):
    cfg = vine_robot.camera_config
    common = {"geom_labels": vine_robot.scene.geom_labels, "exclude_body": vine_robot.scene.ids["cam_tool"]}
    fast = RayCastCamera(vine_robot.model, dataclasses.replace(cfg, raycast_engine="numba"), **common)
    ref = RayCastCamera(vine_robot.model, dataclasses.replace(cfg, raycast_engine="mujoco"), **common)
    assert fast.engine == "numba" and ref.engine == "mujoco"
    for pose in _views(vine_robot):
        da, ga = (x.copy() for x in fast.cast(vine_robot.data, pose))
        db, gb = (x.copy() for x in ref.cast(vine_robot.data, pose))
        # Same pixels with a depth in range (beyond it the two cutoffs differ and are unused).
        valid = (db >= 0) & (db * fast._ray_z <= cfg.max_depth)
        np.testing.assert_array_equal(valid, (da >= 0) & (da * fast._ray_z <= cfg.max_depth))
        assert np.max(np.abs(da - db)[valid], initial=0.0) < 1e-9
        # Geom ids only differ where two geoms are hit at the same distance (touching capsules).
        labels = vine_robot.scene.geom_labels
        np.testing.assert_array_equal(labels[ga[valid]], labels[gb[valid]])
        assert np.mean(ga[valid] == gb[valid]) > 0.98


def test_labels_and_colours_in_the_vine_scene(vine_robot):
    views = _views(vine_robot)
    cloud = vine_robot._camera.capture(vine_robot.data, views[2], 0.0)
    counts = np.bincount(cloud.labels, minlength=3)
    assert counts[STEM] > 20 and counts[OBSTACLE] > 1000 and counts[ROBOT] > 100
    # Stem points are red and lie on the stem, robot points on the robot's capsules.
    stem_rgb = cloud.colors[cloud.labels == STEM].astype(float)
    assert np.all(stem_rgb[:, 0] > 0.5 * stem_rgb.sum(axis=1))
    other_rgb = cloud.colors[cloud.labels != STEM].astype(float)
    assert np.all(other_rgb[:, 0] < 0.46 * np.maximum(other_rgb.sum(axis=1), 1))
    polyline = vine_robot.scene.stem_polyline
    for p in cloud.stem_points:
        d = min(_seg_dist(p, a, b) for a, b in zip(polyline[:-1], polyline[1:], strict=True))
        assert d < vine_robot.scene.params.stem_radius + 2e-3
    # The camera never sees its own tool: no point within the tool's capsules.
    cam_pos = vine_robot.site_pose("camera")[:3, 3]
    for pose in views:
        c = vine_robot._camera.capture(vine_robot.data, pose, 0.0)
        assert np.all(c.depth >= vine_robot.camera_config.min_depth)
    assert np.all(np.linalg.norm(cloud.points - cam_pos, axis=1) > 0.05)


def _seg_dist(p, a, b) -> float:
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
    return float(np.linalg.norm(p - (a + t * (b - a))))


def test_stem_beyond_detection_range_is_labelled_obstacle():
    robot = SimRobot(camera=CameraConfig())
    mid = 0.5 * (robot.scene.stem_base + robot.scene.stem_end)
    direction = np.array([-np.cos(0.6), np.sin(0.6), 0.05])
    direction /= np.linalg.norm(direction)
    near = robot._camera.capture(robot.data, look_at(mid + 0.3 * direction, mid), 0.0)
    far = robot._camera.capture(robot.data, look_at(mid + 0.9 * direction, mid), 0.0)
    assert near.count(STEM) > 20
    assert far.count(STEM) == 0
    # The far stem pixels are still in the cloud, as red obstacle points.
    red = (far.colors[:, 0] > 150) & (far.colors[:, 1] < 60)
    assert np.any(red) and np.all(far.labels[red] == OBSTACLE)


def test_noise_and_dropout_are_seeded():
    noisy = CameraConfig(depth_noise=0.002, dropout=0.1)
    a = SimRobot(camera=noisy, seed=4).capture_cloud()
    b = SimRobot(camera=noisy, seed=4).capture_cloud()
    c = SimRobot(camera=noisy, seed=5).capture_cloud()
    clean = SimRobot(camera=CameraConfig(), seed=4).capture_cloud()
    np.testing.assert_array_equal(a.points, b.points)
    assert len(a) != len(c) or not np.array_equal(a.points, c.points)
    # About 10 % of the pixels dropped; depth noise of ~2 mm at 1 m scale (the canopy is ~0.5 m away).
    assert 0.85 * len(clean) < len(a) < 0.95 * len(clean)
    key = {tuple(p): z for p, z in zip(clean.pixels, clean.depth, strict=True)}
    dz = np.array([z - key[tuple(p)] for p, z in zip(a.pixels, a.depth, strict=True)])
    expected = 0.002 * np.mean(clean.depth**2)
    assert 0.7 * expected < np.std(dz) < 1.3 * expected


def test_frames_arrive_at_30_hz_with_latency():
    robot = SimRobot(camera=CameraConfig(latency=0.05), settle_time=0.0)
    times, arrivals = [], []
    for _ in range(500):
        cloud = robot.camera_cloud()
        if cloud is not None:
            times.append(cloud.timestamp)
            arrivals.append(robot.time)
        robot.step()
    times, arrivals = np.array(times), np.array(arrivals)
    assert len(times) in (28, 29)  # 1 s at 30 Hz minus the 50 ms latency
    assert np.all(np.abs(np.diff(times) - 1 / 30) <= 0.002 + 1e-9)
    assert np.all(arrivals - times >= 0.05 - 1e-9) and np.all(arrivals - times < 0.05 + 0.002 + 1e-9)


def test_camera_cloud_returns_each_frame_once():
    robot = SimRobot()
    assert robot.camera_cloud() is not None  # the frame taken at reset
    assert robot.camera_cloud() is None
    robot.advance(0.04)
    assert robot.camera_cloud() is not None
    assert robot.camera_cloud() is None


@pytest.mark.skipif(not os.environ.get("MUJOCO_GL"), reason="OpenGL camera needs MUJOCO_GL (egl or osmesa)")
def test_opengl_camera_matches_ray_casting():
    try:
        gl = SimRobot(camera=CameraConfig(backend="opengl", stem_range=5.0))
    except Exception as error:  # no usable GL context on this machine
        pytest.skip(f"no OpenGL context: {error}")
    ray = SimRobot(camera=CameraConfig(stem_range=5.0))
    # Turn the camera arm towards the vine so the view holds leaves, cluster and gripper.
    for robot in (gl, ray):
        qd = np.zeros(12)
        qd[0] = -0.8
        robot.send_joint_velocities(qd)
        robot.advance(1.0)
        robot.stop()
    a, b = gl.capture_cloud(), ray.capture_cloud()
    assert a.count(ROBOT) > 0 and len(a) > 5000
    common = {tuple(p): i for i, p in enumerate(b.pixels)}
    idx = [(i, common[tuple(p)]) for i, p in enumerate(a.pixels) if tuple(p) in common]
    assert len(idx) > 0.95 * min(len(a), len(b))
    ia, ib = np.array(idx).T
    assert np.median(np.abs(a.depth[ia] - b.depth[ib])) < 1e-3
    assert np.mean(a.labels[ia] == b.labels[ib]) > 0.98
