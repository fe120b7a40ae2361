"""Real-time factor of the simulated closed loop: 500 Hz control with a QP step, 30 Hz camera.

For each camera setting, :func:`harvest_qp.runtime.runner.run_episode` drives a
:class:`harvest_qp.sim.SimRobot` in the paper's default vine scene with a controller that
builds and solves one QP per 2 ms tick, and the real-time factor is simulated time over
wall-clock time. The process is pinned to one CPU core (and BLAS to one thread).

Settings timed:

* ``283x160``: the paper's D415 848x480 downsampled by 3, ray-cast camera (default caster);
* ``848x480``: full resolution, ray-cast camera;
* ``283x160_mj_multiray``: 283x160 with the plain ``mj_multiRay`` caster;
* ``283x160_opengl``: 283x160 with MuJoCo's OpenGL renderer, in a child process with
  ``MUJOCO_GL=egl`` (skipped, ``null``, when no GL context can be made);
* ``no_camera``: control loop and physics alone.

The QP (see :func:`make_controller`): harvest_qp's ``TaskController`` with two 6-D frame
pose tasks (the camera frame moving into the region of interest to look at the stem, as
in the paper's reaching phase, so most frames show the vine up close; the gripper frame
holding its pose), posture and damping, joint position/speed/acceleration limits and the
dual-UR5e collision dampers. ``--plain-qp`` times a bare daqp QP instead (two frame
tasks, damping, velocity bounds) to show the library's own share of the loop.

Usage::

    python benchmarks/bench_sim.py [--duration 6] [--no-gl]

The last line printed is one JSON object with ``realtime_factor_283x160``,
``realtime_factor_848x480``, ``realtime_factor_283x160_mj_multiray``,
``realtime_factor_283x160_opengl``, ``realtime_factor_no_camera`` and the median QP step
time ``qp_step_us``.
"""

from __future__ import annotations

import os

# One core: BLAS single-threaded (set before numpy loads).
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:  # run from a checkout without installing the package
    sys.path.insert(0, str(_REPO))

from harvest_qp.robot import description as desc  # noqa: E402
from harvest_qp.robot.paths import urdf_path  # noqa: E402
from harvest_qp.runtime.interface import RobotInterface  # noqa: E402
from harvest_qp.runtime.runner import Command, Observation, run_episode  # noqa: E402
from harvest_qp.runtime.task_episode import QPEpisodeController  # noqa: E402
from harvest_qp.sim import CameraConfig, SimRobot  # noqa: E402


class DaqpTwoTaskController:
    """One QP per tick: two 6-D frame tasks + damping + velocity bounds, solved by daqp.

    minimise  sum_i w_i |J_i qdot - v_i|^2 + lambda |qdot|^2   s.t.  |qdot| <= qdot_max

    with v_camera a P law towards a viewpoint 0.3 m from the stem looking at it (swaying by
    +-3 cm so the view keeps changing) and v_gripper a P law holding the gripper's start pose.

    Args:
        stem: a point on the stem [m] the camera turns to (from the scene here; a real
            controller would take it from the point cloud).
    """

    def __init__(self, stem, *, weights=(1.0, 1.0), damping: float = 1e-3, gain: float = 2.0) -> None:
        import daqp
        import pinocchio as pin

        self.pin = pin
        self.model = pin.buildModelFromUrdf(str(urdf_path()))
        self.data = self.model.createData()
        names = list(self.model.names)
        self.index = np.array([self.model.joints[names.index(n)].idx_q for n in desc.joint_names()])
        self.frames = [self.model.getFrameId("camera"), self.model.getFrameId("gripper")]
        self.weights = weights
        self.damping = damping
        self.gain = gain
        self.vmax = np.full(12, 0.5 * np.pi)
        self.solver = daqp.Model()
        self.solver.setup(np.eye(12), np.zeros(12), np.zeros((0, 12)), self.vmax, -self.vmax)
        self.solve_times: list[float] = []
        # Viewpoint in the region of interest, to the robot's side of the stem, looking at it.
        stem = np.asarray(stem, dtype=float)
        position = stem + 0.3 * np.array([-np.cos(0.6), np.sin(0.6), 0.05])
        z = (stem - position) / np.linalg.norm(stem - position)
        x = np.cross([0.0, 0.0, -1.0], z)
        x /= np.linalg.norm(x)
        self.view = np.eye(4)
        self.view[:3, :3] = np.column_stack([x, np.cross(z, x), z])
        self.view[:3, 3] = position

    def _pose_jacobian(self, fid: int) -> tuple[np.ndarray, np.ndarray]:
        J = self.pin.getFrameJacobian(self.model, self.data, fid, self.pin.LOCAL_WORLD_ALIGNED)
        return self.data.oMf[fid].homogeneous, J[:, self.index]

    def _kinematics(self, q: np.ndarray) -> None:
        qp = np.zeros(self.model.nq)
        qp[self.index] = q
        self.pin.computeJointJacobians(self.model, self.data, qp)
        self.pin.updateFramePlacements(self.model, self.data)

    def reset(self, robot: RobotInterface) -> None:
        self._kinematics(robot.joint_positions())
        self.start = [self._pose_jacobian(f)[0].copy() for f in self.frames]

    def _twist(self, T: np.ndarray, target: np.ndarray) -> np.ndarray:
        """P law towards ``target`` (linear; angular) [m/s, rad/s]."""
        dR = target[:3, :3] @ T[:3, :3].T
        angle_axis = self.pin.log3(dR)
        return self.gain * np.concatenate([target[:3, 3] - T[:3, 3], angle_axis])

    def step(self, obs: Observation) -> Command:
        t0 = time.perf_counter()
        self._kinematics(obs.q)
        cam_target = self.view.copy()
        cam_target[:3, 3] += 0.03 * np.sin(2 * np.pi * 0.5 * obs.time) * np.array([0.0, 1.0, 0.0])
        H = self.damping * np.eye(12)
        f = np.zeros(12)
        errors = {}
        for fid, target, w, name in zip(
            self.frames, (cam_target, self.start[1]), self.weights, ("camera", "gripper"), strict=True
        ):
            T, J = self._pose_jacobian(fid)
            v = self._twist(T, target)
            H += w * J.T @ J
            f -= w * J.T @ v
            errors[name] = float(np.linalg.norm(v[:3]) / self.gain)
        self.solver.update(H=H, f=f)
        x, _, exitflag, _ = self.solver.solve()
        self.solve_times.append(time.perf_counter() - t0)
        status = "ok" if exitflag == 1 else f"daqp exitflag {exitflag}"
        return Command(qdot=np.asarray(x) if exitflag == 1 else np.zeros(12), status=status, task_errors=errors)


class HarvestQPController(QPEpisodeController):
    """The same two frame tasks with harvest_qp's :class:`~harvest_qp.TaskController`.

    Camera and gripper :class:`~harvest_qp.tasks.FramePoseTask` (the camera's target as in
    :class:`DaqpTwoTaskController`, the gripper holding its start pose), posture and
    damping tasks, joint position, speed (pi/2 rad/s) and acceleration limits and the
    dual-UR5e collision dampers (same arm, arm to arm, stand): the full per-tick work of
    the library's controller, as the runner drives it (task errors for the log included).
    """

    def __init__(self, stem) -> None:
        from harvest_qp import Configuration, TaskController
        from harvest_qp.limits import CollisionAvoidance, JointVelocityLimit
        from harvest_qp.tasks import DampingTask, FramePoseTask, PostureTask

        self.view = DaqpTwoTaskController(stem).view  # same camera viewpoint as the plain QP
        config = Configuration.dual_ur5e()
        self.camera = FramePoseTask("camera", gain=2.0)
        tasks = [
            self.camera,
            FramePoseTask("gripper", gain=2.0),
            PostureTask(desc.HOME_Q, weight=1e-4),
            DampingTask(12, weight=1e-3),
        ]
        limits = [CollisionAvoidance.dual_ur5e(config), JointVelocityLimit(config, max_velocity=0.5 * np.pi)]
        super().__init__(TaskController(config, tasks, limits, dt=0.002), update_references=self._sway)
        self.solve_times: list[float] = []

    def _sway(self, obs: Observation, controller) -> None:
        position = self.view[:3, 3] + 0.03 * np.sin(2 * np.pi * 0.5 * obs.time) * np.array([0.0, 1.0, 0.0])
        self.camera.set_target(position, self.view[:3, :3])

    def step(self, obs: Observation) -> Command:
        t0 = time.perf_counter()
        command = super().step(obs)
        self.solve_times.append(time.perf_counter() - t0)
        return command


def make_controller(robot: SimRobot, kind: str = "harvest_qp"):
    """The per-tick QP controller timed by the benchmark: harvest_qp's, or the plain daqp one."""
    scene = robot.scene
    stem = 0.5 * (scene.stem_base + scene.stem_end)
    return HarvestQPController(stem) if kind == "harvest_qp" else DaqpTwoTaskController(stem)


def time_closed_loop(camera: CameraConfig | None, duration: float, kind: str = "harvest_qp") -> dict[str, float]:
    """Run the closed loop for ``duration`` simulated seconds; real-time factor and QP time."""
    robot = SimRobot(camera=camera)
    controller = make_controller(robot, kind)
    # Warm-up (numba caches, first frames) outside the timed episode.
    run_episode(robot, make_controller(robot, kind), duration=0.1, stop_at_end=False)
    robot.reset()
    result = run_episode(robot, controller, duration=duration, stop_at_end=False)
    if not result.ok:
        raise RuntimeError(f"benchmark episode failed: {result.status}: {result.error}")
    ok = np.mean(np.char.startswith(result.log["status"].astype(str), "ok"))
    stem_points = result.log["frame_stem_points"]
    return {
        "realtime_factor": result.realtime_factor,
        "max_stem_points": float(stem_points.max(initial=0)),
        "qp_step_us": 1e6 * float(np.median(controller.solve_times)),
        "qp_ok_fraction": float(ok),
        "frames": float(len(result.log["frame_time"])),
    }


def _pin_one_core() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned (no sched_setaffinity)"


def _opengl_child(duration: float) -> float | None:
    """Real-time factor with the OpenGL camera, measured in a child with MUJOCO_GL set."""
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    try:
        out = subprocess.run(
            [sys.executable, __file__, "--opengl-only", "--duration", str(duration)],
            env=env, capture_output=True, text=True, timeout=600, check=False,
        )  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as error:
        print(f"opengl: skipped ({error})")
        return None
    lines = [line for line in out.stdout.splitlines() if line.startswith("{")]
    if out.returncode != 0 or not lines:
        reason = (out.stderr.strip().splitlines() or ["no output"])[-1]
        print(f"opengl: skipped ({reason})")
        return None
    return json.loads(lines[-1]).get("realtime_factor_283x160_opengl")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=6.0, help="simulated seconds per setting")
    parser.add_argument("--no-gl", action="store_true", help="skip the OpenGL camera")
    parser.add_argument("--opengl-only", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--plain-qp", action="store_true", help="time a bare daqp QP instead of harvest_qp's")
    args = parser.parse_args(argv)
    pinned = _pin_one_core()

    if args.opengl_only:
        cfg = CameraConfig(backend="opengl")
        r = time_closed_loop(cfg, args.duration, "plain" if args.plain_qp else "harvest_qp")
        print(json.dumps({"realtime_factor_283x160_opengl": r["realtime_factor"]}))
        return

    print(f"bench_sim: {args.duration:.1f} s simulated per setting, {pinned}")
    settings = {
        "no_camera": None,
        "283x160": CameraConfig(),
        "283x160_mj_multiray": CameraConfig(raycast_engine="mujoco"),
        "848x480": CameraConfig(downsample=1),
    }
    results: dict[str, float | None] = {}
    qp_us = []
    for name, cfg in settings.items():
        duration = args.duration if name != "848x480" else max(1.0, args.duration / 2)
        r = time_closed_loop(cfg, duration, "plain" if args.plain_qp else "harvest_qp")
        results[f"realtime_factor_{name}"] = round(r["realtime_factor"], 3)
        qp_us.append(r["qp_step_us"])
        print(
            f"{name:>22}: {r['realtime_factor']:6.2f}x real time  (QP step {r['qp_step_us']:.0f} us median, "
            f"{r['frames']:.0f} frames, up to {r['max_stem_points']:.0f} stem points, "
            f"QP ok {100 * r['qp_ok_fraction']:.0f} %)"
        )
    if args.no_gl:
        results["realtime_factor_283x160_opengl"] = None
    else:
        rtf = _opengl_child(args.duration)
        results["realtime_factor_283x160_opengl"] = None if rtf is None else round(rtf, 3)
        if rtf is not None:
            print(f"{'283x160_opengl':>22}: {rtf:6.2f}x real time")
    results["qp_step_us"] = round(float(np.median(qp_us)), 1)
    results["duration_s"] = args.duration
    print(json.dumps(results))


if __name__ == "__main__":
    main()
