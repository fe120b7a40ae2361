"""The viewer in a real browser: headless Chromium screenshots checked pixel by pixel.

Each test draws a short synthetic episode, screenshots it with Debian's ``chromium`` (the
README's test command installs it; without it these tests fail with the install line,
they never skip) and checks that the robot's, the stem's and the point cloud's colours
appear where an independent pinhole model of meshcat's camera (``_browser.project``) puts
the robot's collision capsules (pinocchio forward kinematics), the scene's stem polyline and
the cloud's points. The screenshots are kept in ``$HARVEST_QP_SCREENSHOTS`` (default: pytest's
temporary directory).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from harvest_qp import Configuration
from harvest_qp.robot import description as desc
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM, PointCloud
from harvest_qp.runtime.runner import Observation
from harvest_qp.sim import VineSceneParams, build_vine_scene
from harvest_qp.viewer import LiveViewer, export_episode_html
from harvest_qp.viewer.replay import free_port
from harvest_qp.viewer.viewer import CAMERA_OFFSET, VIEW_CENTER

from . import _browser as br

POINT_SIZE = 0.012  # [m], large enough for a few pixels per point
P_GD_START, P_GD_END = np.array([0.6, -0.35, 1.55]), np.array([0.6, 0.15, 1.55])  # a moving marker [m]


def check_marker(img, position, other, where: str) -> None:
    """The p_gd marker is drawn at ``position`` and not at ``other`` (its other end)."""
    blue = br.p_gd_pixels(img)
    near = br.region([position], VIEW_CENTER, CAMERA_OFFSET, dilate_px=12)
    away = br.region([other], VIEW_CENTER, CAMERA_OFFSET, dilate_px=12)
    assert (blue & near).sum() >= 20, f"{where}: no p_gd marker at {position}"
    assert (blue & away).sum() == 0, f"{where}: p_gd marker drawn at {other}"


@pytest.fixture(scope="module")
def scene():
    return build_vine_scene(VineSceneParams())


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    folder = os.environ.get("HARVEST_QP_SCREENSHOTS")
    path = Path(folder) if folder else tmp_path_factory.mktemp("screenshots")
    path.mkdir(parents=True, exist_ok=True)
    return path


def trajectory(n: int) -> np.ndarray:
    """q (n, 12): the camera arm raises its upper arm and bends its elbow; the grasping arm holds."""
    q = np.tile(desc.HOME_Q, (n, 1))
    s = np.linspace(0.0, 1.0, n)
    q[:, 0] += 0.2 * s
    q[:, 1] -= 0.6 * s
    q[:, 2] += 0.5 * s
    return q


def synthetic_cloud(scene, rng) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Labelled points: along the stem (1.2 cm beside it, seen from the viewer, so both show), an
    obstacle blob, a ring around the stand (robot). Returns points, labels and the points of each label."""
    stem = scene.stem_polyline
    s = rng.uniform(0, 1, 400)[:, None]
    seg = rng.integers(0, len(stem) - 1, 400)
    side = np.cross(np.asarray(CAMERA_OFFSET), [0.0, 0.0, 1.0])
    stem_pts = stem[seg] + s * (stem[seg + 1] - stem[seg]) + 0.012 * side / np.linalg.norm(side)
    blob = np.array([0.70, 0.30, 1.45]) + rng.normal(0.0, 0.03, (800, 3))
    ang = rng.uniform(0, 2 * np.pi, 800)
    ring = np.column_stack([0.15 * np.cos(ang), 0.15 * np.sin(ang), rng.uniform(0.3, 0.6, 800)])
    points = np.concatenate([stem_pts, blob, ring])
    labels = np.concatenate([np.full(400, STEM), np.full(800, OBSTACLE), np.full(800, ROBOT)]).astype(np.int8)
    return points, labels, {"stem": stem_pts, "obstacle": blob, "robot": ring}


def make_cloud(points, labels, camera_pose, t) -> PointCloud:
    n = len(points)
    return PointCloud(
        points=points, labels=labels, colors=np.zeros((n, 3), np.uint8), camera_pose=camera_pose, timestamp=t,
        depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(160, 283),
    )  # fmt: skip


def arm_capsule_samples(q) -> np.ndarray:
    """Surface points of the arms' capsules (links 1-6) at q, by pinocchio (the oracle)."""
    conf = Configuration.dual_ur5e(q)
    out = []
    for body in desc.collision_bodies():
        if body.arm and 1 <= body.link_index <= 6:
            T = conf.frame_pose(body.link).homogeneous
            p0 = T[:3, :3] @ body.capsule.p0 + T[:3, 3]
            p1 = T[:3, :3] @ body.capsule.p1 + T[:3, 3]
            out.append(br.capsule_samples(p0, p1, body.capsule.radius))
    return np.concatenate(out)


def check_scene(img, *, q, q_other, scene, cloud_parts, view_center, camera_offset, where: str) -> dict[str, int]:
    """The robot, stem and cloud colours lie where the oracle projects those objects.

    ``q_other`` is another configuration of the episode: where the arms' capsules are at ``q``
    but far from where they are at ``q_other``, most pixels must be robot-coloured (so a robot
    drawn at ``q_other`` fails).
    """
    counts = {}
    # Meshes stick out of the capsules by up to 3 cm (test_geometry): ~10 px at this distance.
    robot_region = br.region(arm_capsule_samples(q), view_center, camera_offset, dilate_px=12)
    robot = br.robot_pixels(img)
    counts["robot"] = int(robot.sum())
    inside = int((robot & robot_region).sum())
    assert robot.sum() > 3000, f"{where}: only {robot.sum()} robot-coloured pixels"
    assert inside >= 0.95 * robot.sum(), f"{where}: {robot.sum() - inside} robot pixels outside the arms' region"
    assert inside >= 0.2 * robot_region.sum(), f"{where}: the arms' region is mostly empty ({inside} px)"
    moved = br.region(arm_capsule_samples(q), view_center, camera_offset, dilate_px=0)
    moved = ndimage.binary_fill_holes(ndimage.binary_closing(moved, iterations=3))
    moved &= ~br.region(arm_capsule_samples(q_other), view_center, camera_offset, dilate_px=12)
    counts["moved region"] = int(moved.sum())
    counts["robot in moved region"] = int((robot & moved).sum())
    assert moved.sum() > 500, f"{where}: the test trajectory does not move the arm visibly"
    assert (robot & moved).sum() >= 0.5 * moved.sum(), f"{where}: the arm is not drawn at the expected q"

    stem_geom = []
    for a, b in zip(scene.stem_polyline[:-1], scene.stem_polyline[1:]):
        stem_geom.append(br.capsule_samples(a, b, scene.params.stem_radius))
    stem_region = br.region(np.concatenate(stem_geom), view_center, camera_offset, dilate_px=5)
    red = br.stem_pixels(img)
    counts["stem"] = int(red.sum())
    assert red.sum() >= 8, f"{where}: the stem is not visible ({red.sum()} red pixels)"
    assert (red & stem_region).sum() >= 0.9 * red.sum(), f"{where}: red pixels away from the stem"

    for name, pixels, points in (
        ("stem points", br.yellow_pixels(img), cloud_parts["stem"]),
        ("obstacle points", br.cyan_pixels(img), cloud_parts["obstacle"]),
        ("robot points", br.magenta_pixels(img), cloud_parts["robot"]),
    ):
        reg = br.region(points, view_center, camera_offset, dilate_px=6)
        counts[name] = int(pixels.sum())
        assert pixels.sum() >= 30, f"{where}: {name} not visible ({pixels.sum()} pixels)"
        assert (pixels & reg).sum() >= 0.95 * pixels.sum(), f"{where}: {name} drawn away from their positions"
    return counts


def test_live_viewer_in_chromium(scene, shots):
    """A live viewer fed by observe() shows the last tick's robot, the vine's stem and the cloud
    (drawn by the child process of the default LiveViewer).

    Catches: meshes placed with the wrong frames or the wrong q (robot pixels off the arms'
    capsules, checked by hand with HOME_Q instead of q), a cloud drawn with the wrong label
    colours or not at all, a stem missing from the vine, a frame never drawn by the worker.
    """
    rng = np.random.default_rng(3)
    points, labels, parts = synthetic_cloud(scene, rng)
    qs = trajectory(150)
    # The default LiveViewer: drawing in a child process that owns the viewer and its server.
    with LiveViewer(vine=scene.model, port=free_port(), point_size=POINT_SIZE, verbose=False) as live:
        cloud = None
        for k, q in enumerate(qs):
            t = 0.002 * k
            if k % 50 == 0:
                cloud = make_cloud(points, labels, scene.camera_home, t)
            obs = Observation(time=t, q=q, qdot=np.zeros(12), force=np.array([0.0, 0.0, -3.0]), cloud=cloud,
                              new_cloud=k % 50 == 0)  # fmt: skip
            live.observe(obs, {"phase": "approach", "theta": 0.2})
        assert live.flush(30.0), f"the live viewer did not draw: {live.error!r}"
        assert live.frames_drawn >= 1
        img = br.screenshot(live.url, shots / "viewer_live.png")
    counts = check_scene(
        img, q=qs[-1], q_other=qs[0], scene=scene, cloud_parts=parts, view_center=VIEW_CENTER,
        camera_offset=CAMERA_OFFSET, where="live",
    )  # fmt: skip
    print("live pixel counts", counts)


def synthetic_log(scene, rng) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    n = 250
    t = 0.002 * np.arange(n)
    q = trajectory(n)
    points, labels, parts = synthetic_cloud(scene, rng)
    frame_time = np.array([0.0, 0.2, 0.4])
    log = {
        "t": t, "q": q, "force": np.tile([0.0, 0.0, -3.0], (n, 1)), "status": np.array(["ok"] * n),
        "stem_points": np.full(n, 400, np.int32), "frame_time": frame_time,
        "frame_camera_pose": np.array([scene.camera_home] * 3),
        "cloud_points": np.concatenate([points] * 3).astype(np.float32),
        "cloud_labels": np.concatenate([labels] * 3),
        "cloud_offsets": np.arange(4) * len(points),
        "meta/scene_params": np.array(json.dumps(dataclasses.asdict(scene.params))),
        "p_gd": np.linspace(P_GD_START, P_GD_END, n),
    }  # fmt: skip
    return log, parts


def test_replay_html_in_chromium(scene, shots, tmp_path):
    """The exported replay HTML opens offline (file://) and shows the episode's first frame.

    Catches: an HTML that needs the server (blank page), an animation whose first frame is
    not the episode's start (robot pixels off the capsules at q[0]), cloud snapshots that are
    all hidden or all shown at once (colours outside the cloud's region would not catch the
    latter; the cloud is the same in all three frames, so it checks visibility of one).
    """
    rng = np.random.default_rng(4)
    log, parts = synthetic_log(scene, rng)
    html = export_episode_html(log, tmp_path / "episode.html", play=False, point_size=POINT_SIZE)
    text = html.read_text()
    assert "<script src=" not in text and "<link " not in text, "the HTML loads external files"
    img = br.screenshot(html.resolve().as_uri(), shots / "viewer_replay.png")
    counts = check_scene(
        img, q=log["q"][0], q_other=log["q"][-1], scene=scene, cloud_parts=parts, view_center=VIEW_CENTER,
        camera_offset=CAMERA_OFFSET, where="replay",
    )  # fmt: skip
    check_marker(img, P_GD_START, P_GD_END, "replay")
    print("replay pixel counts", counts, "html size [MB]", html.stat().st_size / 1e6)


def test_replay_html_plays_to_the_last_frame(scene, shots, tmp_path):
    """Opened with ``play=True``, the offline HTML runs the animation and stops on the last frame.

    Catches: an animation that does not play (robot still at q[0]: the moved-region check
    fails), keys in the wrong time unit (a 0.5 s episode stretched to minutes would still be
    near its start after the 8 s of browser time), a final frame not held (clamping), static
    transforms in the HTML that undo the animation once it has finished (the p_gd marker,
    read from the log's ``p_gd`` key, back at its start: this failed before the fix).
    """
    rng = np.random.default_rng(4)
    log, parts = synthetic_log(scene, rng)
    html = export_episode_html(log, tmp_path / "episode_play.html", play=True, point_size=POINT_SIZE)
    img = br.screenshot(html.resolve().as_uri(), shots / "viewer_replay_end.png")
    counts = check_scene(
        img, q=log["q"][-1], q_other=log["q"][0], scene=scene, cloud_parts=parts, view_center=VIEW_CENTER,
        camera_offset=CAMERA_OFFSET, where="replay end",
    )  # fmt: skip
    check_marker(img, P_GD_END, P_GD_START, "replay end")
    print("replay end pixel counts", counts)
