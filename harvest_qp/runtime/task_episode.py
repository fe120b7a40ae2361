"""Glue between the library controllers and the episode runner (simulation or real robot).

:class:`QPEpisodeController` turns a :class:`~harvest_qp.TaskController` into the
``reset(robot)`` / ``step(observation) -> Command`` object that
:func:`harvest_qp.runtime.runner.run_episode` drives, and helpers build demo targets.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import mujoco
import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.limits import CapsuleGeometry
from harvest_qp.runtime.interface import RobotInterface
from harvest_qp.runtime.runner import Command, Observation
from harvest_qp.task_controller import TaskController
from harvest_qp.tasks import FramePoseTask

ReferenceUpdate = Callable[[Observation, TaskController], None]


class QPEpisodeController:
    """A :class:`TaskController` as an episode-runner controller.

    At ``reset`` every :class:`FramePoseTask` without a target holds its frame's
    current pose. At each tick ``update_references(observation, controller)`` (if
    given) sets the task references, then the QP step runs; the command carries the
    controller status and the position error [m] of every frame pose task.

    Args:
        controller: the QP controller (its configuration is updated in place).
        update_references: optional callback run before each QP step.
    """

    def __init__(self, controller: TaskController, *, update_references: ReferenceUpdate | None = None) -> None:
        self.controller = controller
        self.update_references = update_references
        self.pose_tasks = [t for t in controller.tasks if isinstance(t, FramePoseTask)]

    def reset(self, robot: RobotInterface) -> None:
        self.controller.reset(robot.joint_positions())
        for task in self.pose_tasks:
            if task.target_position is None:
                task.set_target_from_configuration(self.controller.configuration)

    def step(self, obs: Observation) -> Command:
        if self.update_references is not None:
            self.update_references(obs, self.controller)
        result = self.controller.step(obs.q)
        config = self.controller.configuration
        errors = {f"{t.frame}_position": float(np.linalg.norm(t.error(config)[:3])) for t in self.pose_tasks}
        return Command(qdot=result.qdot, status=result.status, task_errors=errors)


def look_at(position: np.ndarray, target: np.ndarray, *, down: np.ndarray = (0.0, 0.0, -1.0)) -> np.ndarray:
    """Rotation of a camera frame at ``position`` [m] whose z axis points at ``target`` [m].

    The image y axis points as close to ``down`` as possible (x right, y down, z forward).
    """
    z = np.asarray(target, float) - np.asarray(position, float)
    norm = np.linalg.norm(z)
    if norm < 1e-9:
        raise InvalidInputError("look_at: position and target coincide")
    z /= norm
    x = np.cross(np.asarray(down, float), z)
    if np.linalg.norm(x) < 1e-9:
        raise InvalidInputError("look_at: the view direction is parallel to 'down'")
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def stem_viewpoint(
    stem_point: np.ndarray, *, distance: float = 0.3, azimuth: float = 0.6, elevation: float = 0.05
) -> tuple[np.ndarray, np.ndarray]:
    """A camera pose ``distance`` [m] from ``stem_point`` on the robot's side, looking at it.

    ``azimuth`` [rad] turns the viewpoint from -x (towards the robot) to +y (the camera
    arm's side); ``elevation`` raises it. Returns (position [m], rotation).
    """
    direction = np.array([-np.cos(azimuth), np.sin(azimuth), elevation])
    position = np.asarray(stem_point, float) + distance * direction / np.linalg.norm(direction)
    return position, look_at(position, stem_point)


def environment_capsules(model: mujoco.MjModel, data: mujoco.MjData, names: Sequence[str]) -> list[CapsuleGeometry]:
    """World capsules (:class:`CapsuleGeometry`, ``frame=None``) of static MuJoCo capsule geoms.

    Used to feed the scene's rigid parts (vine branch, cane) to
    :class:`~harvest_qp.limits.CollisionAvoidance` as environment primitives.
    """
    mujoco.mj_kinematics(model, data)
    capsules = []
    for name in names:
        geom = model.geom(name)
        if int(model.geom_type[geom.id]) != int(mujoco.mjtGeom.mjGEOM_CAPSULE):
            raise InvalidInputError(f"geom {name!r} is not a capsule")
        centre = data.geom_xpos[geom.id]
        axis = data.geom_xmat[geom.id].reshape(3, 3)[:, 2]
        radius, half = model.geom_size[geom.id][:2]
        capsules.append(
            CapsuleGeometry(name, None, tuple(centre - half * axis), tuple(centre + half * axis), float(radius))
        )
    return capsules
