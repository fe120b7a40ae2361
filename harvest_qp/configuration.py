"""Robot model plus joint positions: frame poses and Jacobians.

Frame convention: every Jacobian and twist in harvest_qp is *world-aligned at the
frame origin* (pinocchio's ``LOCAL_WORLD_ALIGNED``): a twist ``[v; w]`` stacks the
linear velocity [m/s] of the frame origin and the angular velocity [rad/s], both
expressed in the world frame. This is the convention of the paper's reference
velocities (``eq:control_signal_rr_world``, ``eq:superimp_g``).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pinocchio as pin

from harvest_qp.exceptions import InvalidInputError, ModelError, UnknownFrameError
from harvest_qp.qp_kernels import all_finite
from harvest_qp.validation import as_rigid_transform, as_scalar, as_vector, describe

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_FLOAT64 = np.dtype(np.float64)


class Configuration:
    """A pinocchio model with joint positions ``q`` [rad] and cached kinematics.

    Args:
        model: pinocchio model (revolute joints only: ``nq == nv``).
        q: joint positions [rad]; the model's neutral configuration when omitted.
    """

    def __init__(self, model: pin.Model, q: np.ndarray | Sequence[float] | None = None) -> None:
        if not isinstance(model, pin.Model):
            raise InvalidInputError(f"Configuration model must be a pinocchio.Model, got {type(model).__name__}")
        if model.nq != model.nv:
            raise ModelError(
                f"harvest_qp needs a model with nq == nv (revolute/prismatic joints), got nq={model.nq}, nv={model.nv}"
            )
        self.model = model
        self.data = model.createData()
        self._frame_ids = {model.frames[i].name: i for i in range(model.nframes)}
        self._joint_ids = {model.names[i]: i for i in range(1, model.njoints)}
        self._nframes = model.nframes
        self.update(pin.neutral(model) if q is None else q)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_urdf(cls, path: str | Path, q: np.ndarray | Sequence[float] | None = None) -> Configuration:
        """Load a URDF [file path] and return its configuration at ``q`` [rad]."""
        if not isinstance(path, (str, os.PathLike)):
            raise InvalidInputError(f"URDF path must be a str or path, got {describe(path)}")
        path = Path(path)
        if not path.is_file():
            raise ModelError(f"URDF file not found: {path}")
        return cls(pin.buildModelFromUrdf(str(path)), q)

    @classmethod
    def dual_ur5e(cls, q: np.ndarray | Sequence[float] | None = None, *,
                  camera_in_flange: np.ndarray | Sequence[Sequence[float]] | None = None) -> Configuration:
        """The shipped dual-UR5e harvester, at ``q`` [rad] or at the home configuration.

        ``camera_in_flange``: the camera optical frame in the camera arm's flange ``cam_flange``
        (4x4, [m]), e.g. a real cell's hand-eye calibration; None keeps the robot description's mount.
        The ``camera`` frame then is where the calibrated camera is (:meth:`place_frame`).
        """
        from harvest_qp.robot.description import HOME_Q
        from harvest_qp.robot.paths import urdf_path

        configuration = cls.from_urdf(urdf_path(), HOME_Q if q is None else q)
        if camera_in_flange is not None:
            configuration.place_frame("camera", "cam_flange", camera_in_flange)
        return configuration

    # ------------------------------------------------------------------ state
    @property
    def nv(self) -> int:
        """Number of joint velocities (12 for the dual UR5e)."""
        return self.model.nv

    @property
    def joint_names(self) -> list[str]:
        """Actuated joint names in the order of ``q``."""
        return [self.model.names[i] for i in range(1, self.model.njoints)]

    @property
    def frame_names(self) -> list[str]:
        """Every frame name of the model (links, joints and task frames)."""
        return list(self._frame_ids)

    @property
    def lower_limits(self) -> np.ndarray:
        """Joint position lower limits [rad]."""
        return self.model.lowerPositionLimit

    @property
    def upper_limits(self) -> np.ndarray:
        """Joint position upper limits [rad]."""
        return self.model.upperPositionLimit

    @property
    def velocity_limits(self) -> np.ndarray:
        """Joint speed limits [rad/s]."""
        return self.model.velocityLimit

    @property
    def q(self) -> np.ndarray:
        """Joint positions [rad] (nv,); assigning it is :meth:`update` (checked, kinematics recomputed)."""
        return self._q

    @q.setter
    def q(self, value: np.ndarray | Sequence[float]) -> None:
        self.update(value)

    def update(self, q: np.ndarray | Sequence[float]) -> None:
        """Set joint positions [rad] and recompute placements and joint Jacobians."""
        self._set_q(self._checked_q(q))

    def update_if_changed(self, q: np.ndarray | Sequence[float]) -> bool:
        """:meth:`update`, skipping the kinematics when ``q`` is bitwise the ``q`` of the last update.

        For a control loop that updates the configuration for its reference laws and then
        hands the same ``q`` to the QP step. Returns True when the kinematics were recomputed.
        """
        q = self._checked_q(q)
        if q.tobytes() == self._q_kinematics:  # bit patterns: 0.0 and -0.0 differ
            self._q = q
            return False
        self._set_q(q)
        return True

    def _checked_q(self, q: np.ndarray | Sequence[float]) -> np.ndarray:
        """A private float64 copy of ``q`` after :func:`as_vector`'s checks (size nq, finite)."""
        if type(q) is np.ndarray and q.dtype is _FLOAT64 and q.shape == (self.model.nq,) and all_finite(q):
            return q.copy()  # the control loop's case, without building the error message's name
        return as_vector(q, self.model.nq, "Configuration q")

    def _set_q(self, q: np.ndarray) -> None:
        self._q = q
        # The bytes of the q the kinematics were computed at, apart from ``self._q`` (which
        # the ``q`` property hands out, so a caller could change it in place).
        self._q_kinematics = q.tobytes()
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)

    def integrate(self, qdot: np.ndarray | Sequence[float], dt: float) -> np.ndarray:
        """Joint positions [rad] after applying ``qdot`` [rad/s] for ``dt`` [s] (does not update)."""
        qdot = as_vector(qdot, self.nv, "Configuration.integrate qdot")
        dt = as_scalar(dt, "Configuration.integrate dt", minimum=0.0)
        return self.q + qdot * dt

    # ------------------------------------------------------------------ frames
    def frame_id(self, name: str) -> int:
        """Index of frame ``name``; raises :class:`UnknownFrameError` listing the valid names."""
        try:
            return self._frame_ids[name]
        except (KeyError, TypeError):
            raise UnknownFrameError(
                f"unknown frame {name!r}; valid frames are: {', '.join(sorted(self._frame_ids))}"
            ) from None

    def joint_index(self, name: str) -> int:
        """Index in ``q`` of the joint ``name``."""
        if not isinstance(name, str) or name not in self._joint_ids:
            raise UnknownFrameError(f"unknown joint {name!r}; valid joints are: {', '.join(self.joint_names)}")
        return self.model.joints[self._joint_ids[name]].idx_q

    def place_frame(self, name: str, parent: str, pose: np.ndarray | Sequence[Sequence[float]]) -> None:
        """Move frame ``name`` so that its pose in frame ``parent`` is ``pose`` (4x4 rigid, [m]).

        Both frames must be carried by the same joint (e.g. a tool frame and the flange it is
        mounted on). The pose is absolute (calling again replaces it); frames placed relative to
        ``name`` in the URDF do not follow it. Tasks keep working on the moved frame; the
        kinematics are recomputed.

        Raises:
            UnknownFrameError: an unknown frame name.
            InvalidInputError: ``pose`` is not a finite rigid 4x4 transform, or the frames are
                carried by different joints.
        """
        frame_id, parent_id = self.frame_id(name), self.frame_id(parent)
        if frame_id == parent_id:  # the pose would compose with the frame's own, moved again at each call
            raise InvalidInputError(f"place_frame: the parent must be another frame than {name!r}")
        T = as_rigid_transform(pose, f"place_frame {name!r} pose")
        frame, parent_frame = self.model.frames[frame_id], self.model.frames[parent_id]
        if frame.parentJoint != parent_frame.parentJoint:
            raise InvalidInputError(
                f"place_frame: {name!r} and {parent!r} are carried by different joints "
                f"({self.model.names[frame.parentJoint]!r}, {self.model.names[parent_frame.parentJoint]!r})"
            )
        frame.placement = parent_frame.placement * pin.SE3(T[:3, :3], T[:3, 3])
        self.model.frames[frame_id] = frame  # (pinocchio hands out a copy of the frame)
        self._set_q(self._q)

    def frame_pose(self, name: str) -> pin.SE3:
        """World pose of frame ``name`` (position [m], rotation); a copy, not a live view."""
        return self.data.oMf[self.frame_id(name)].copy()

    def frame_position(self, name: str) -> np.ndarray:
        """World position [m] of frame ``name``."""
        return self.data.oMf[self.frame_id(name)].translation.copy()

    def frame_rotation(self, name: str) -> np.ndarray:
        """World rotation matrix (3x3) of frame ``name``; its columns are the frame axes."""
        return self.data.oMf[self.frame_id(name)].rotation.copy()

    def frame_jacobian(self, name: str) -> np.ndarray:
        """Jacobian (6 x nv) of frame ``name``: ``[v; w] = J qdot``, world-aligned at the frame origin."""
        return pin.getFrameJacobian(self.model, self.data, self.frame_id(name), _LWA)

    def frame_jacobian_by_id(self, frame_id: int) -> np.ndarray:
        """Like :meth:`frame_jacobian` for a frame index (no name lookup, for hot loops)."""
        is_index = type(frame_id) is int or isinstance(frame_id, np.integer)
        if not is_index or not 0 <= frame_id < self._nframes:
            raise InvalidInputError(
                f"frame_id must be an int in [0, {self._nframes}) (see frame_id()), got {describe(frame_id)}"
            )
        return pin.getFrameJacobian(self.model, self.data, frame_id, _LWA)

    def point_jacobian(self, name: str, point: np.ndarray) -> np.ndarray:
        """Linear Jacobian (3 x nv) of the world point [m] rigidly attached to frame ``name``."""
        J = self.frame_jacobian(name)
        r = as_vector(point, 3, "point_jacobian point") - self.frame_position(name)
        return J[:3] - np.cross(r[:, None], J[3:], axis=0)

    def world_joint_jacobians(self) -> np.ndarray:
        """All joint twists (6 x nv) in the WORLD convention (velocity of the point at the world origin).

        Column ``k`` moves every body supported by joint ``k``; the linear velocity of
        a world point ``p`` on such a body is ``J[:3] - p x J[3:]`` over its support.
        """
        return self.data.J

    def support_mask(self, frame_name: str) -> np.ndarray:
        """Boolean mask (nv,) of the joints that move frame ``frame_name``."""
        frame = self.model.frames[self.frame_id(frame_name)]
        mask = np.zeros(self.nv, dtype=bool)
        for j in self.model.supports[frame.parentJoint][1:]:
            joint = self.model.joints[j]
            mask[joint.idx_v : joint.idx_v + joint.nv] = True
        return mask

    def check_finite(self) -> None:
        """Raise :class:`InvalidInputError` if ``q`` holds NaN or inf."""
        if not np.all(np.isfinite(self.q)):
            raise InvalidInputError(f"q must be finite, got {self.q}")


def as_configuration(value: object, name: str = "configuration") -> Configuration:
    """``value`` if it is a :class:`Configuration`, else :class:`InvalidInputError` naming it."""
    if not isinstance(value, Configuration):
        raise InvalidInputError(
            f"{name} must be a harvest_qp Configuration, got {type(value).__name__}: {describe(value)}"
        )
    return value
