"""A free-flying camera for closed-loop checks of the camera-arm references without a robot.

The camera's pose is integrated kinematically under V_c = V_cr + V_cu (exact rotation
increments); frames are ray-cast by :func:`harvest_qp.perception.synthetic.render_scene` at a
lower rate than the control ticks, as a real camera is.  ``render_scene`` always aims its
rays at the stem's midpoint instead of using the integrated orientation: V_cr keeps the ROI
(near that midpoint) centred, and the 65 deg field of view covers the whole scene around the
stem, so what is seen is the same; it keeps the renderer out of this helper.  Ground-truth
labels stand in for perception's stem/obstacle split.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from harvest_qp.perception.synthetic import VineScene, render_scene
from harvest_qp.references import ReachingCentering, Unveiling


def rotation_increment(omega: np.ndarray, dt: float) -> np.ndarray:
    """exp(S(omega) dt) by Rodrigues."""
    angle = float(np.linalg.norm(omega)) * dt
    if angle == 0.0:
        return np.eye(3)
    k = omega / np.linalg.norm(omega)
    skew = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * skew + (1.0 - math.cos(angle)) * skew @ skew


def look_at_pose(eye, target) -> np.ndarray:
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack((right, np.cross(forward, right), forward))
    pose[:3, 3] = eye
    return pose


@dataclass
class Flight:
    times: list = field(default_factory=list)  # frame times [s]
    stem_points: list = field(default_factory=list)  # visible stem points per frame
    modes: list = field(default_factory=list)
    raw_angular: list = field(default_factory=list)  # |w| of the raw V_cu per frame [rad/s]
    max_linear: float = 0.0  # max |v_cu| over ticks [m/s]
    max_angular: float = 0.0  # max |w_cu| over ticks [rad/s]
    positions: list = field(default_factory=list)
    thetas: list = field(default_factory=list)


def fly(
    scene: VineScene,
    start,
    roi_centre,
    *,
    unveiling: Unveiling | None,
    duration: float,
    predicted=None,
    frame_rate: float = 10.0,
    tick: float = 0.02,
    width: int = 141,
    height: int = 80,
) -> Flight:
    """Fly from ``start`` under V_cr (+ V_cu when ``unveiling`` is given) for ``duration`` [s]."""
    pose = look_at_pose(start, roi_centre)
    reaching = ReachingCentering()
    reaching.reset(roi_centre=roi_centre)
    if unveiling is not None:
        unveiling.reset()
    flight = Flight()
    frame_every = max(1, round(1.0 / (frame_rate * tick)))
    for step in range(round(duration / tick)):
        t = step * tick
        if step % frame_every == 0:
            cloud = render_scene(scene, pose[:3, 3], width=width, height=height, seed=step)
            stem, obstacles = cloud.points[cloud.stem_mask], cloud.points[~cloud.stem_mask]
            flight.times.append(t)
            flight.stem_points.append(int(stem.shape[0]))
            flight.positions.append(pose[:3, 3].copy())
            if unveiling is not None:
                unveiling.observe(
                    pose[:3, 3], stem, obstacles, predicted_stem_points=predicted, roi_centre=roi_centre, timestamp=t
                )
                flight.modes.append(unveiling.mode)
                flight.raw_angular.append(float(np.linalg.norm(unveiling.raw[3:])))
        twist = reaching.update(pose, tick)
        flight.thetas.append(reaching.theta)
        if unveiling is not None:
            v_cu = unveiling.update(tick)
            flight.max_linear = max(flight.max_linear, float(np.linalg.norm(v_cu[:3])))
            flight.max_angular = max(flight.max_angular, float(np.linalg.norm(v_cu[3:])))
            twist = twist + v_cu
        pose[:3, 3] += tick * twist[:3]
        pose[:3, :3] = rotation_increment(twist[3:], tick) @ pose[:3, :3]
    return flight


def without_leaves(scene: VineScene) -> VineScene:
    """The same scene with every leaf moved far away (for the unoccluded stem count)."""
    return replace(scene, leaf_centres=scene.leaf_centres + 100.0)


def hidden_stem_scene(
    *, seed: int = 0, leaf_offset: float = 0.08, leaf_radius: float = 0.05, leaf_shift=(0.0, 0.0)
) -> VineScene:
    """The default scene with its leaves replaced by one leaf ``leaf_offset`` [m] in front of
    the stem's midpoint as seen from +x (the approach direction), shifted by ``leaf_shift``
    (y, z) [m].  Unshifted, the stem stays hidden along the whole straight approach, as in
    the lab measurements "A stem hidden along the whole approach"; shifted, it is partly occluded."""
    scene = VineScene.default(seed=seed)
    mid = 0.5 * (scene.stem_base + scene.stem_end)
    centre = mid + np.array([leaf_offset, *leaf_shift])
    return replace(
        scene,
        leaf_centres=np.array([centre]),
        leaf_normals=np.array([[1.0, 0.0, 0.0]]),
        leaf_radius=leaf_radius,
    )


class LabCamera:
    """The MuJoCo lab's depth camera (``harvest_qp.sim``), detached from the arm: frames from
    any camera pose in the static vine scene at the robot's home configuration.  Robot points
    count as obstacles, as in the closed loop (the paper's O is every non-stem point)."""

    def __init__(self, params=None, *, downsample: int = 3) -> None:
        import mujoco

        from harvest_qp.runtime.interface import STEM
        from harvest_qp.sim.camera import CameraConfig, make_camera
        from harvest_qp.sim.scene import build_vine_scene

        self.scene = build_vine_scene(params)
        self.data = mujoco.MjData(self.scene.model)
        self.data.qpos[:] = self.scene.model.qpos0
        mujoco.mj_forward(self.scene.model, self.data)
        self.config = CameraConfig(downsample=downsample)
        self.camera = make_camera(
            self.scene.model,
            self.config,
            geom_labels=self.scene.geom_labels,
            exclude_body=self.scene.ids["cam_tool"],
        )
        self._stem = STEM

    def shift_occluder(self, distance: float) -> None:
        """Move the occluding leaf by ``distance`` [m] along its long axis (a partly occluded stem)."""
        import mujoco

        model, data = self.scene.model, self.data
        geom = self.scene.ids["occluder"]
        axis = data.geom_xmat[geom].reshape(3, 3)[:, int(np.argmax(model.geom_size[geom]))]
        body_rotation = data.xmat[model.geom_bodyid[geom]].reshape(3, 3)
        model.geom_pos[geom] += body_rotation.T @ (distance * axis)
        mujoco.mj_forward(model, data)

    def frame(self, pose: np.ndarray, t: float):
        cloud = self.camera.capture(self.data, pose, t)
        stem = cloud.labels == self._stem
        return cloud.points[stem], cloud.points[~stem]


def fly_lab(
    lab: LabCamera,
    *,
    unveiling: Unveiling | None,
    duration: float,
    roi_centre=None,
    predicted=None,
    frame_rate: float = 10.0,
    tick: float = 0.02,
) -> Flight:
    """Fly the lab camera from its home pose under V_cr (+ V_cu), ROI on the grape by default."""
    gripper = lab.scene.gripper_home
    if roi_centre is None:
        roi_centre = gripper[:3, 3] + 0.04 * gripper[:3, 1]  # on the grasped cluster, below {G}
    pose = lab.scene.camera_home.copy()
    reaching = ReachingCentering()
    reaching.reset(roi_centre=roi_centre)
    if unveiling is not None:
        unveiling.reset()
    flight = Flight()
    frame_every = max(1, round(1.0 / (frame_rate * tick)))
    for step in range(round(duration / tick)):
        t = step * tick
        if step % frame_every == 0:
            stem, obstacles = lab.frame(pose, t)
            flight.times.append(t)
            flight.stem_points.append(int(stem.shape[0]))
            flight.positions.append(pose[:3, 3].copy())
            if unveiling is not None:
                unveiling.observe(
                    pose[:3, 3], stem, obstacles, predicted_stem_points=predicted, roi_centre=roi_centre, timestamp=t
                )
                flight.modes.append(unveiling.mode)
                flight.raw_angular.append(float(np.linalg.norm(unveiling.raw[3:])))
        twist = reaching.update(pose, tick)
        flight.thetas.append(reaching.theta)
        if unveiling is not None:
            v_cu = unveiling.update(tick)
            flight.max_linear = max(flight.max_linear, float(np.linalg.norm(v_cu[:3])))
            flight.max_angular = max(flight.max_angular, float(np.linalg.norm(v_cu[3:])))
            twist = twist + v_cu
        pose[:3, 3] += tick * twist[:3]
        pose[:3, :3] = rotation_increment(twist[3:], tick) @ pose[:3, :3]
    return flight
