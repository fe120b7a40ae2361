"""The robot interface the controllers talk to: the simulation implements it, a UR5e driver can too.

Controllers and the episode runner (:mod:`harvest_qp.runtime.runner`) only use
:class:`RobotInterface`, so the same controller runs on
:class:`harvest_qp.sim.SimRobot` and on a real dual-UR5e driver.

Conventions:

* joints: 12 values, camera arm first then grasping arm (the paper's q = [q_c; q_g]),
  in the order of :func:`harvest_qp.robot.description.joint_names`;
* positions [rad], velocities [rad/s], time [s], forces [N], points [m], all in the
  world frame (z up, x from the robot towards the vine).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError

__all__ = [
    "STEM",
    "OBSTACLE",
    "ROBOT",
    "LABEL_NAMES",
    "N_JOINTS",
    "PointCloud",
    "RobotInterface",
]

#: Point label: the crop's stem (the paper's set S), only within the stem detection range.
STEM: int = 0
#: Point label: anything that is neither stem nor robot (leaves, branch, berries, floor,
#: and stem points beyond the detection range).
OBSTACLE: int = 1
#: Point label: the robot itself (either arm, the stand, the grasping tool).
ROBOT: int = 2
#: Label value -> name.
LABEL_NAMES: dict[int, str] = {STEM: "stem", OBSTACLE: "obstacle", ROBOT: "robot"}

#: Number of actuated joints of the dual arm.
N_JOINTS = 12


@dataclass(frozen=True, eq=False)
class PointCloud:
    """One RGB-D camera frame as a labelled world-frame point cloud.

    Attributes:
        points: ``(n, 3)`` float64 point positions in the world frame [m].
        labels: ``(n,)`` int8 labels, :data:`STEM`, :data:`OBSTACLE` or :data:`ROBOT`.
        colors: ``(n, 3)`` uint8 RGB colours.
        camera_pose: ``(4, 4)`` world pose of the camera optical frame {C} at capture
            (z = view direction, x right, y down in the image).
        timestamp: capture time [s] (robot clock; with latency, the frame is delivered later).
        depth: ``(n,)`` float64 depth of each point along the camera's z axis [m].
        pixels: ``(n, 2)`` int32 (row, column) of each point in the (downsampled) image.
        image_size: (height, width) of the (downsampled) image [pixels].
    """

    points: NDArray[np.float64]
    labels: NDArray[np.int8]
    colors: NDArray[np.uint8]
    camera_pose: NDArray[np.float64]
    timestamp: float
    depth: NDArray[np.float64]
    pixels: NDArray[np.int32]
    image_size: tuple[int, int]

    def __post_init__(self) -> None:
        n = self.points.shape[0] if self.points.ndim == 2 else -1
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise InvalidInputError(f"points must have shape (n, 3), got {self.points.shape}")
        for name, arr, shape in (
            ("labels", self.labels, (n,)),
            ("colors", self.colors, (n, 3)),
            ("depth", self.depth, (n,)),
            ("pixels", self.pixels, (n, 2)),
            ("camera_pose", self.camera_pose, (4, 4)),
        ):
            if arr.shape != shape:
                raise InvalidInputError(f"{name} must have shape {shape} to match {n} points, got {arr.shape}")

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def camera_position(self) -> NDArray[np.float64]:
        """Camera position p_c in the world [m]."""
        return self.camera_pose[:3, 3]

    @property
    def view_direction(self) -> NDArray[np.float64]:
        """Camera view direction z_c in the world (unit vector)."""
        return self.camera_pose[:3, 2]

    def mask(self, label: int) -> NDArray[np.bool_]:
        """Boolean mask of the points with ``label``."""
        return self.labels == label

    @property
    def stem_points(self) -> NDArray[np.float64]:
        """``(n_S, 3)`` points labelled :data:`STEM` [m]."""
        return self.points[self.labels == STEM]

    @property
    def obstacle_points(self) -> NDArray[np.float64]:
        """``(n_O, 3)`` points labelled :data:`OBSTACLE` [m]."""
        return self.points[self.labels == OBSTACLE]

    def count(self, label: int) -> int:
        """Number of points with ``label``."""
        return int(np.count_nonzero(self.labels == label))


class RobotInterface(ABC):
    """What a controller may do with the dual-arm robot.

    The robot is velocity controlled like a UR5e under ``speedj``: the last command is
    held until the next one, ramped within the robot's acceleration limits. Time only
    advances in :meth:`step` / :meth:`advance` (a real driver blocks there until the
    next control cycle).
    """

    #: Control period [s] (the paper's UR5e: 2 ms).
    control_period: float

    @property
    @abstractmethod
    def time(self) -> float:
        """Robot clock [s] (0 at the episode start)."""

    @abstractmethod
    def joint_positions(self) -> NDArray[np.float64]:
        """Measured joint positions q (12,) [rad]."""

    @abstractmethod
    def joint_velocities(self) -> NDArray[np.float64]:
        """Measured joint velocities qdot (12,) [rad/s]."""

    @abstractmethod
    def wrist_force(self) -> NDArray[np.float64]:
        """Force (3,) [N, world frame] the grasping arm's tool applies to what it holds.

        The F/T reading rotated to the world frame with the tool's own weight removed and
        the tare offset subtracted: pulling a held crop away from its stem gives a force
        along the pull direction, equal in magnitude to the stem tension once tared.
        """

    @abstractmethod
    def tare_force(self) -> None:
        """Zero :meth:`wrist_force` at the current reading (as a real F/T sensor's tare)."""

    @abstractmethod
    def camera_cloud(self) -> PointCloud | None:
        """The newest camera frame not yet returned, or None when no new frame arrived."""

    @abstractmethod
    def send_joint_velocities(self, qdot: NDArray[np.float64]) -> None:
        """Command joint velocities (12,) [rad/s]; held until the next command."""

    @abstractmethod
    def step(self) -> None:
        """Advance one control period (apply the current command)."""

    def advance(self, duration: float) -> None:
        """Advance ``duration`` [s] (rounded to whole control periods), holding the command."""
        if not np.isfinite(duration) or duration < 0:
            raise InvalidInputError(f"duration must be a finite non-negative time [s], got {duration!r}")
        for _ in range(int(round(duration / self.control_period))):
            self.step()

    @abstractmethod
    def stop(self) -> None:
        """Bring both arms to rest within the acceleration limits; returns once at rest."""
