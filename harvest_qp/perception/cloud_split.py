"""One labelled camera frame split into the paper's point sets (``subsec:scePC_proc``).

W (the frame's cloud, world frame) -> S (stem points), W - S (every non-stem point: the
camera arm's obstacles in ``eq:nearest``) and the obstacle points (W - S without the robot's
own points). The stem rows are taken on every frame; the two other sets are gathered on
first use (only the frame at the switch and the predicted unveiling mode read them).

Also the cloud filters of the grasping arm that the controller applies beyond the paper:
the held cluster left out of O (:func:`outside_held_cluster`) and the cloud-sphere obstacles
of the collision limit (:func:`obstacle_sphere_centres`).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.interface import OBSTACLE, STEM, PointCloud

__all__ = ["LabelledFrame", "obstacle_sphere_centres", "outside_held_cluster"]


class LabelledFrame:
    """One camera frame split by label: S now, W - S and the obstacle points on first use.

    Args:
        cloud: the frame (world-frame points [m], int labels, camera pose, timestamp [s]).

    Attributes:
        time: the frame's timestamp [s].
        camera_pose: ``(4, 4)`` camera pose in the world frame (a copy).
        camera_position: p_c [m] (a copy).
        stem: ``(n_S, 3)`` stem points S [m].
        fit: the stem model of this frame (:class:`~harvest_qp.perception.stem.StemModel`),
            set by the caller when it fits one; ``None`` otherwise.
    """

    def __init__(self, cloud: PointCloud) -> None:
        if not isinstance(cloud, PointCloud):
            raise InvalidInputError(f"cloud must be a PointCloud, got {type(cloud).__name__}")
        self._points = np.asarray(cloud.points)
        self._labels = np.asarray(cloud.labels)
        if self._points.ndim != 2 or self._points.shape[1:] != (3,) or self._labels.shape != self._points.shape[:1]:
            raise InvalidInputError(
                f"cloud points must be (n, 3) with (n,) labels, got {self._points.shape} and {self._labels.shape}"
            )
        self.time = float(cloud.timestamp)
        self.camera_pose = np.array(cloud.camera_pose, dtype=float)
        self.camera_position = self.camera_pose[:3, 3].copy()
        self._stem_mask = self._labels == STEM
        # np.compress, not points[mask]: numpy's boolean indexing of an (n, 3) array copies
        # element by element (measured 4x slower on the 45,000 rows of a 283x160 frame).
        self.stem = np.compress(self._stem_mask, self._points, axis=0)
        self.fit = None

    @property
    def n_stem(self) -> int:
        """Number of stem points n_S."""
        return int(self.stem.shape[0])

    @property
    def n_non_stem(self) -> int:
        """Number of non-stem points (W - S)."""
        return int(self._points.shape[0]) - self.n_stem

    def non_stem_every(self, stride: int) -> NDArray[np.float64]:
        """``non_stem[::stride]``, gathered without the rows in between (a law that thins W - S
        reads a tenth of an 848x480 frame's 400,000 rows: ~1 ms less per frame, measured)."""
        if stride == 1 or "non_stem" in self.__dict__:
            return self.non_stem[::stride]
        return self._points.take(np.flatnonzero(~self._stem_mask)[::stride], axis=0)

    @functools.cached_property
    def non_stem(self) -> NDArray[np.float64]:
        """``(n, 3)`` W - S [m]: every non-stem point (leaves, branch, berries, the robot)."""
        return np.compress(~self._stem_mask, self._points, axis=0)

    @functools.cached_property
    def obstacles(self) -> NDArray[np.float64]:
        """``(n, 3)`` the obstacle-labelled points [m] (W - S without the robot's own points)."""
        return np.compress(self._labels == OBSTACLE, self._points, axis=0)


def outside_held_cluster(
    points: NDArray[np.float64], gripper_pose: NDArray[np.float64], *, cluster_length: float, cluster_radius: float
) -> NDArray[np.bool_]:
    """Which ``(n, 3)`` points [m] lie outside the cluster held by the gripper.

    The cluster is the capsule of radius ``cluster_radius`` [m] along the gripper's y axis
    (the hanging direction) from the gripper point to ``cluster_length`` [m] below it; it
    moves with the gripper, so it is never an obstacle to where it is taken.
    """
    p_g, y_g = gripper_pose[:3, 3], gripper_pose[:3, 1]
    offset = points - p_g
    along = np.clip(offset @ y_g, 0.0, cluster_length)
    radial = offset - along[:, None] * y_g
    return np.einsum("ij,ij->i", radial, radial) > cluster_radius**2


def obstacle_sphere_centres(
    points: NDArray[np.float64],
    gripper_pose: NDArray[np.float64],
    *,
    max_distance: float,
    cluster_length: float,
    cluster_radius: float,
    voxel: float,
) -> NDArray[np.float64]:
    """Collision-sphere centres [m] for the seen vine near the gripper (beyond the paper).

    The obstacle points within ``max_distance`` [m] of the gripper point and outside the held
    cluster (:func:`outside_held_cluster`), one per occupied voxel of edge ``voxel`` [m]: the
    first point of each voxel in the input order.
    """
    offset = points - gripper_pose[:3, 3]
    near = points[np.einsum("ij,ij->i", offset, offset) < max_distance**2]
    near = near[outside_held_cluster(near, gripper_pose, cluster_length=cluster_length, cluster_radius=cluster_radius)]
    if near.shape[0] == 0:
        return np.zeros((0, 3))
    keys = np.floor(near / voxel).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return near[np.sort(first)]
