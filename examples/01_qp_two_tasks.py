"""Library basics, no simulation: two QP tasks on the dual UR5e under joint and collision limits.

The camera arm follows a 5-D twist (roll about the optical axis left free, as in the
paper's Sec. III-B) that drives its camera 10 cm towards +x, while the grasping arm holds
its gripper still (6-D twist task with a zero reference). Joint velocities are integrated
kinematically at 500 Hz. Prints the camera's displacement and the gripper's drift.

    python examples/01_qp_two_tasks.py [--steps 500]
"""

from __future__ import annotations

import argparse

import numpy as np

from harvest_qp import Configuration, TaskController
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask


def run(steps: int = 500, dt: float = 0.002) -> dict[str, np.ndarray]:
    """Run the two-task loop for ``steps`` ticks; returns start/end camera and gripper positions [m]."""
    config = Configuration.dual_ur5e()
    camera = FrameTwistTask("camera", weight=[1, 1, 1, 1, 1, 0], weight_frame="local")
    gripper = FrameTwistTask("gripper")
    tasks = [camera, gripper, PostureTask(config.q, weight=1e-3), DampingTask(config.nv, weight=1e-4)]
    collision = CollisionAvoidance.dual_ur5e(config, safety_distance=0.01, influence_distance=0.10)
    controller = TaskController(config, tasks, [collision], dt=dt)

    start_camera = config.frame_pose("camera").translation.copy()
    start_gripper = config.frame_pose("gripper").translation.copy()
    target = start_camera + np.array([0.10, 0.0, 0.0])
    q = config.q.copy()
    for _ in range(steps):
        p_c = config.frame_pose("camera").translation
        # Proportional twist towards the target [m/s], saturated at 0.1 m/s; no rotation.
        v = np.clip(2.0 * (target - p_c), -0.1, 0.1)
        camera.set_reference(np.concatenate((v, np.zeros(3))))
        gripper.set_reference(np.zeros(6))
        step = controller.step(q)
        q = q + step.qdot * dt
    controller.configuration.update(q)
    return {
        "camera_start": start_camera,
        "camera_end": config.frame_pose("camera").translation.copy(),
        "gripper_start": start_gripper,
        "gripper_end": config.frame_pose("gripper").translation.copy(),
        "q": q,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=500, help="control ticks at 500 Hz (default 500 = 1 s)")
    args = parser.parse_args()
    out = run(args.steps)
    moved = out["camera_end"] - out["camera_start"]
    drift = np.linalg.norm(out["gripper_end"] - out["gripper_start"])
    print(f"camera moved {np.round(moved * 1000, 1)} mm (target +100 mm along x)")
    print(f"gripper drift {drift * 1000:.3f} mm")


if __name__ == "__main__":
    main()
