"""What the viewer sends to meshcat, decoded and checked against pinocchio and hand computations."""

from __future__ import annotations

import numpy as np
import pytest
import umsgpack

from harvest_qp import Configuration
from harvest_qp.exceptions import InvalidInputError
from harvest_qp.robot.description import HOME_Q
from harvest_qp.runtime.interface import OBSTACLE, STEM
from harvest_qp.viewer import MeshcatViewer, ViewerFrame
from harvest_qp.viewer.commands import pack_transform
from harvest_qp.viewer.replay import free_port
from harvest_qp.viewer.viewer import ROOT


@pytest.fixture(scope="module")
def viewer():
    v = MeshcatViewer(None, port=free_port(), verbose=False)
    yield v
    v.close()


class Recorder:
    """Wraps the viewer's connection.send and keeps the decoded messages of each call."""

    def __init__(self, viewer):
        self.viewer, self.batches = viewer, []
        self._send = viewer.connection.send

    def __enter__(self):
        def send(messages):
            self.batches.append([(c.decode(), p.decode(), umsgpack.unpackb(d)) for c, p, d in messages])
            return self._send(messages)

        self.viewer.connection.send = send
        return self

    def __exit__(self, *exc):
        self.viewer.connection.send = self._send

    def last(self, command=None, path=None):
        return [m for m in self.batches[-1] if (command is None or m[0] == command) and (path is None or m[1] == path)]


def matrix(message) -> np.ndarray:
    return np.array(message[2]["matrix"], float).reshape(4, 4).T


def test_pack_transform_is_umsgpack():
    M = np.random.default_rng(0).normal(size=(4, 4))
    _, data = pack_transform("/a/b", M)
    assert data == umsgpack.packb({"type": "set_transform", "path": "/a/b", "matrix": M.T.reshape(-1).tolist()})


def test_robot_links_follow_pinocchio(viewer, rng):
    """Each link node's transform is pinocchio's frame pose at q (the meshes hang below it).

    Catches: joint order mixed between the arms, transforms sent row-major (meshcat wants
    column-major), a frame left at its previous pose.
    """
    q = HOME_Q + rng.uniform(-0.5, 0.5, 12)
    conf = Configuration.dual_ur5e(q)
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.5, q=q))
    sent = {m[1]: matrix(m) for m in rec.last("set_transform")}
    for arm in ("cam_", "grasp_"):
        for link in ("shoulder_link", "forearm_link", "wrist_3_link"):
            np.testing.assert_allclose(sent[f"{ROOT}/robot/{arm}{link}"], conf.frame_pose(arm + link).homogeneous,
                                       atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(sent[f"{ROOT}/robot/grasp_tool"], conf.frame_pose("grasp_tool").homogeneous, atol=1e-12)


def test_capsules_move_only_when_shown(viewer):
    """Hidden capsules cost nothing; showing them sends their current poses first.

    Catches: capsules shown at a stale pose after the toggle, capsule transforms sent while hidden.
    """
    q = np.array(HOME_Q) + 0.2
    viewer.set_capsules_visible(False)
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.0, q=q))
        assert not [m for m in rec.last("set_transform") if "/capsules/" in m[1]]
        viewer.set_capsules_visible(True)
        shown = {m[1]: matrix(m) for m in rec.last("set_transform")}
        assert rec.last("set_property", f"{ROOT}/capsules")[0][2]["value"] is True
        viewer.draw(ViewerFrame(time=0.1, q=q + 0.1))
        moved = {m[1] for m in rec.last("set_transform")}
    viewer.set_capsules_visible(False)
    conf = Configuration.dual_ur5e(q)
    expected = conf.frame_pose("cam_forearm_link").homogeneous
    np.testing.assert_allclose(shown[f"{ROOT}/capsules/cam_forearm_link"], expected, atol=1e-12)
    assert f"{ROOT}/capsules/grasp_wrist_2_link" in moved


def test_arrows_have_the_right_length_and_direction(viewer):
    """V_c is drawn from the camera along the velocity, ``velocity_scale`` m per m/s long.

    Catches: an arrow from the wrong frame, a length not scaled, a direction turned.
    """
    conf = Configuration.dual_ur5e(HOME_Q)
    v_c = np.array([0.0, 0.3, 0.4])  # 0.5 m/s -> 0.5 m with velocity_scale = 1
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.0, q=HOME_Q, force=np.array([0.0, 0.0, -4.0])))
        viewer.draw(ViewerFrame(time=0.0, q=HOME_Q, v_c=v_c, force=None))
    shaft = matrix(rec.last("set_transform", f"{ROOT}/markers/v_c/shaft")[0])
    head = matrix(rec.last("set_transform", f"{ROOT}/markers/v_c/head")[0])
    np.testing.assert_allclose(shaft[:3, 3], conf.frame_position("camera"), atol=1e-12)
    # shaft: unit rod along y scaled to (length - head); head: 4 cm cone starting at the shaft's end
    shaft_end = shaft[:3, 3] + shaft[:3, 1]
    np.testing.assert_allclose(head[:3, 3], shaft_end, atol=1e-12)
    tip = head[:3, 3] + head[:3, :3] @ np.array([0.0, 0.04, 0.0])
    np.testing.assert_allclose(tip, conf.frame_position("camera") + v_c, atol=1e-12)
    assert rec.last("set_property", f"{ROOT}/markers/v_c")[0][2]["value"] is True
    assert rec.last("set_property", f"{ROOT}/markers/force")[0][2]["value"] is False


def test_the_v_c_arrow_starts_at_the_camera_the_controller_drove(viewer):
    """A real run's camera is where its hand-eye calibration puts it (the logged p_c), not where the
    robot description does: the arrow starts at p_c when the frame has it. Catches: the description's
    camera frame used for a calibrated run (15 mm off here)."""
    conf = Configuration.dual_ur5e(HOME_Q)
    p_c = conf.frame_position("camera") + np.array([0.01, -0.008, 0.008])
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.0, q=HOME_Q, v_c=np.array([0.0, 0.3, 0.4]), p_c=p_c))
    shaft = matrix(rec.last("set_transform", f"{ROOT}/markers/v_c/shaft")[0])
    np.testing.assert_allclose(shaft[:3, 3], p_c, atol=1e-12)


def test_markers_hidden_when_absent_and_visibility_sent_once(viewer):
    p = np.array([0.5, 0.0, 1.2])
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.0, q=HOME_Q))
        viewer.draw(ViewerFrame(time=0.1, q=HOME_Q, p_sb=p, roi_center=p, roi_radius=0.15))
        assert rec.last("set_property", f"{ROOT}/markers/p_sb")[0][2]["value"] is True
        np.testing.assert_allclose(matrix(rec.last("set_transform", f"{ROOT}/markers/p_sb")[0])[:3, 3], p)
        roi = matrix(rec.last("set_transform", f"{ROOT}/markers/roi")[0])
        np.testing.assert_allclose(np.diag(roi)[:3], 0.15)  # unit sphere scaled to the radius
        viewer.draw(ViewerFrame(time=0.2, q=HOME_Q, p_sb=p + 0.01))
        assert not rec.last("set_property", f"{ROOT}/markers/p_sb")
        assert rec.last("set_property", f"{ROOT}/markers/roi")[0][2]["value"] is False


def test_cloud_sent_once_per_new_cloud_with_label_colours(viewer):
    """The cloud goes as one object per label, only when a new cloud arrives.

    Catches: the cloud re-sent every frame (the cost that matters), labels mixed up.
    """
    rng = np.random.default_rng(5)
    pts = rng.normal(size=(300, 3)).astype(np.float32)
    labels = np.where(np.arange(300) < 100, STEM, OBSTACLE).astype(np.int8)
    frame = dict(cloud_points=pts, cloud_labels=labels, cloud_key=("cloud", 1))
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=0.0, q=HOME_Q, **frame))
        objects = {m[1]: m[2] for m in rec.last("set_object")}
        viewer.draw(ViewerFrame(time=0.01, q=HOME_Q, **frame))
        assert not [m for m in rec.last("set_object") if "/cloud/" in m[1]]
    stem = objects[f"{ROOT}/cloud/stem"]["object"]
    position = np.frombuffer(stem["geometries"][0]["data"]["attributes"]["position"]["array"].data, np.float32)
    np.testing.assert_array_equal(position.reshape(-1, 3), pts[:100])
    assert stem["materials"][0]["color"] == 0xFFE600
    assert objects[f"{ROOT}/cloud/obstacle"]["object"]["materials"][0]["color"] == 0x00E5E5


def test_text_panel_rate_limited(viewer):
    with Recorder(viewer) as rec:
        viewer.draw(ViewerFrame(time=1.0, q=HOME_Q, phase="grasp"), wall_time=100.0)
        assert rec.last("set_object", f"{ROOT}/text")
        viewer.draw(ViewerFrame(time=1.01, q=HOME_Q, phase="grasp"), wall_time=100.05)
        assert not rec.last("set_object", f"{ROOT}/text")
        viewer.draw(ViewerFrame(time=1.2, q=HOME_Q, phase="grasp"), wall_time=100.2)
        assert rec.last("set_object", f"{ROOT}/text")


def test_animation_tracks_follow_the_frames(viewer):
    """The replay animation's keys are the frames' times and pinocchio's link poses.

    Catches: times not relative to the first frame, keys of the wrong frame, cloud snapshots
    visible all at once (each must be shown only from its own time to the next one's).
    """
    qs = [np.array(HOME_Q) + d for d in (0.0, 0.2, 0.4)]
    pts = np.zeros((10, 3), np.float32)
    labels = np.zeros(10, np.int8)
    frames = [
        ViewerFrame(time=2.0 + 0.5 * k, q=qs[k], cloud_points=pts + k, cloud_labels=labels, cloud_key=k)
        for k in range(3)
    ]
    with Recorder(viewer) as rec:
        viewer.load_animation(frames, play=False)
    animation = rec.last("set_animation")[0][2]
    clips = {a["path"]: {t["name"]: t for t in a["clip"]["tracks"]} for a in animation["animations"]}
    keys = clips[f"{ROOT}/robot/cam_forearm_link"][".position"]["keys"]
    assert [k["time"] for k in keys] == [0.0, 0.5, 1.0]
    for k, key in enumerate(keys):
        expected = Configuration.dual_ur5e(qs[k]).frame_position("cam_forearm_link")
        np.testing.assert_allclose(key["value"], expected, atol=1e-12)
    # snapshots are shown by scale 1 and hidden by scale 1e-6, switching within 0.1 ms
    scale = clips[f"{ROOT}/replay/cloud_1"][".scale"]["keys"]
    times = np.array([k["time"] for k in scale])
    values = np.array([k["value"][0] for k in scale])
    for t, shown in ((0.0, False), (0.4998, False), (0.5, True), (0.9998, True), (1.0, False)):
        assert np.interp(t, times, values) == pytest.approx(1.0 if shown else 1e-6, abs=1e-3), t
    assert animation["options"]["play"] is False


def test_bad_input(viewer):
    with pytest.raises(InvalidInputError, match="ViewerFrame"):
        viewer.draw("frame")
    with pytest.raises(InvalidInputError, match=r"\.html"):
        viewer.export_html("scene.png")
    with pytest.raises(InvalidInputError, match="vine"):
        MeshcatViewer("vine.xml", port=free_port(), verbose=False)
    with pytest.raises(InvalidInputError, match="camera_offset"):
        MeshcatViewer(None, camera_offset=(0.0, 0.0), verbose=False)
    with pytest.raises(InvalidInputError, match="at least one frame"):
        viewer.load_animation([])
