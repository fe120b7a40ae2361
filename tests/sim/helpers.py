"""Shared helpers of the simulation tests: simple controllers and camera poses."""

from __future__ import annotations

import numpy as np
import pinocchio as pin

from harvest_qp.robot import description as desc
from harvest_qp.robot.paths import urdf_path
from harvest_qp.runtime.interface import RobotInterface
from harvest_qp.runtime.runner import Command, Observation


def look_at(position, target, down=(0.0, 0.0, -1.0)) -> np.ndarray:
    """Camera pose {C} (z = view direction, y = image down) at ``position`` looking at ``target``."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    z = target - position
    z /= np.linalg.norm(z)
    x = np.cross(np.asarray(down, float), z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = position
    return T


class PinocchioArm:
    """Frame Jacobians of the dual arm from the URDF, in the interface's joint order."""

    def __init__(self) -> None:
        self.model = pin.buildModelFromUrdf(str(urdf_path()))
        self.data = self.model.createData()
        names = list(self.model.names)
        # Index of each interface joint in pinocchio's q vector (all joints are 1-DOF).
        self.index = np.array([self.model.joints[names.index(n)].idx_q for n in desc.joint_names()])

    def pin_q(self, q: np.ndarray) -> np.ndarray:
        out = np.zeros(self.model.nq)
        out[self.index] = q
        return out

    def frame(self, q: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World pose (4x4) and 6x12 world-aligned Jacobian (linear; angular) of frame ``name``."""
        fid = self.model.getFrameId(name)
        qp = self.pin_q(q)
        pin.computeJointJacobians(self.model, self.data, qp)
        pin.updateFramePlacements(self.model, self.data)
        J = pin.getFrameJacobian(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED)
        return self.data.oMf[fid].homogeneous.copy(), J[:, self.index]


class JointPD:
    """Joint-space P controller with velocity feed-forward towards a target trajectory."""

    def __init__(self, target=None, gain: float = 2.0) -> None:
        self.target = target
        self.gain = gain

    def reset(self, robot: RobotInterface) -> None:
        self.q0 = robot.joint_positions()

    def step(self, obs: Observation) -> Command:
        target = self.q0 if self.target is None else self.target(obs.time, self.q0)
        e = target - obs.q
        return Command(qdot=self.gain * e, status="ok", task_errors={"joint_error": float(np.linalg.norm(e))})


class ForcePull:
    """Pull the gripper along ``direction`` until the tared wrist force along it reaches ``force``.

    A P force loop (a velocity-controlled arm on a spring has no steady-state error) on the
    grasping arm through the gripper Jacobian's pseudo-inverse,
    holding the gripper orientation; the camera arm holds still. Tares the sensor at reset.
    """

    def __init__(self, direction, force: float = 3.0, kp: float = 0.005, ki: float = 0.0) -> None:
        self.n = np.asarray(direction, float) / np.linalg.norm(direction)
        self.force, self.kp, self.ki = force, kp, ki
        self.arm = PinocchioArm()

    def reset(self, robot: RobotInterface) -> None:
        robot.tare_force()
        self.integral = 0.0
        self.R0 = self.arm.frame(robot.joint_positions(), "gripper")[0][:3, :3]

    def step(self, obs: Observation) -> Command:
        T, J = self.arm.frame(obs.q, "gripper")
        e = float(self.n @ obs.force) - self.force
        self.integral += e * 0.002
        v = -self.n * np.clip(self.kp * e + self.ki * self.integral, -0.02, 0.02)
        R = T[:3, :3]
        w = 0.5 * sum(np.cross(R[:, i], self.R0[:, i]) for i in range(3))  # orientation hold
        qd = np.zeros(12)
        Jg = J[:, 6:]
        qd[6:] = np.linalg.lstsq(Jg, np.concatenate([v, 2.0 * w]), rcond=None)[0]
        return Command(qdot=qd, status="ok", task_errors={"force_error": e})


def arm_qpos_addresses(model) -> np.ndarray:
    """qpos addresses of the 12 arm joints, in the interface's joint order."""
    return np.array([model.joint(name).qposadr[0] for name in desc.joint_names()])


def arm_dof_addresses(model) -> np.ndarray:
    """qvel (dof) addresses of the 12 arm joints, in the interface's joint order."""
    return np.array([model.joint(name).dofadr[0] for name in desc.joint_names()])
