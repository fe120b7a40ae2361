"""What the camera can see of the stem in a lab scene: measurements for reports and tools.

Run ``python -m harvest_qp.sim.visibility [SEEDS...]`` to print, for the default scene
(``-1``) and the given seeds (default 1-5), the occluder's requested and measured coverage,
how much stem lies inside a robot geom, and how many stem points the paper's camera sees at
the start pose and along the straight approach. The measurements use MuJoCo's ray caster
(``mj_ray``) and the ray-cast camera on the settled scene.
"""

from __future__ import annotations

import argparse
import dataclasses

import mujoco
import numpy as np
from numpy.typing import NDArray

from harvest_qp.runtime.interface import ROBOT, STEM
from harvest_qp.sim.camera import DEFAULT_CAMERA, CameraConfig, RayCastCamera
from harvest_qp.sim.robot import SimRobot
from harvest_qp.sim.scene import APPROACH_RADIUS, VineSceneParams

__all__ = ["stem_axis_points", "stem_length_inside_robot", "occluder_coverage_seen", "stem_points_seen"]


def stem_axis_points(robot: SimRobot, per_segment: int = 40) -> NDArray[np.float64]:
    """(n, 3) points along the stem's capsule axes in the current state [m]."""
    m, d = robot.model, robot.data
    out = []
    for g in robot.scene.stem_geoms:
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        half = m.geom_size[g, 1]
        out.append(d.geom_xpos[g] + np.linspace(-half, half, per_segment)[:, None] * axis)
    return np.vstack(out)


def stem_length_inside_robot(robot: SimRobot, per_segment: int = 200) -> float:
    """Length of stem [m] whose cross-section touches a robot capsule in the current state."""
    m, d = robot.model, robot.data
    points = stem_axis_points(robot, per_segment)
    stem_radius = float(m.geom_size[robot.scene.stem_geoms[0], 0])
    inside = np.zeros(len(points), dtype=bool)
    for g in np.flatnonzero(robot.scene.geom_labels == ROBOT):
        axis = d.geom_xmat[g].reshape(3, 3)[:, 2]
        half, radius = m.geom_size[g, 1], m.geom_size[g, 0]
        a, b = d.geom_xpos[g] - half * axis, d.geom_xpos[g] + half * axis
        t = np.clip((points - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        inside |= np.linalg.norm(points - (a + t[:, None] * (b - a)), axis=1) < radius + stem_radius
    lengths = 2 * m.geom_size[robot.scene.stem_geoms, 1]
    return float(np.sum(inside.reshape(len(lengths), per_segment).mean(axis=1) * lengths))


def occluder_coverage_seen(robot: SimRobot, view: NDArray[np.float64]) -> tuple[float, float]:
    """Fractions of the stem axis hidden from ``view`` [m]: by the occluding leaf, by anything else."""
    m, d = robot.model, robot.data
    points = stem_axis_points(robot)
    stem = set(robot.scene.stem_geoms.tolist())
    radius = float(m.geom_size[robot.scene.stem_geoms[0], 0])
    occluder = robot.scene.ids["occluder"]
    by_leaf = by_other = 0
    gid = np.zeros(1, np.int32)
    for x in points:
        ray = x - view
        length = float(np.linalg.norm(ray))
        dist = mujoco.mj_ray(m, d, view, ray / length, None, 1, robot.scene.ids["cam_tool"], gid, None)
        if 0 <= dist < length - 1.5 * radius and int(gid[0]) not in stem:
            by_leaf += int(gid[0]) == occluder
            by_other += int(gid[0]) != occluder
    return by_leaf / len(points), by_other / len(points)


def stem_points_seen(robot: SimRobot, pose: NDArray[np.float64], config: CameraConfig = DEFAULT_CAMERA) -> int:
    """STEM-labelled points of a ray-cast frame from camera ``pose`` (4x4 {C}) in the current state."""
    camera = RayCastCamera(
        robot.model, config, geom_labels=robot.scene.geom_labels, exclude_body=robot.scene.ids["cam_tool"]
    )
    return camera.capture(robot.data, np.asarray(pose, dtype=float), 0.0).count(STEM)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="*", type=int, default=[-1, 1, 2, 3, 4, 5], help="-1: the default scene")
    args = parser.parse_args(argv)
    print(
        "| scene | occluder_coverage | seen hidden by the leaf / by others | stem inside robot [mm] "
        "| stem points: start | 0.6 m | 0.45 m | 0.35 m | 0.35 m without the leaf | 0.35 m towards the gripper |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for seed in args.seeds:
        params = VineSceneParams() if seed < 0 else VineSceneParams.sample(seed)
        robot = SimRobot(params, camera=None)
        scene = robot.scene
        leaf, other = occluder_coverage_seen(robot, scene.approach_pose(APPROACH_RADIUS)[:3, 3])
        seen = [stem_points_seen(robot, scene.approach_pose(dist)) for dist in (0.6, 0.45, APPROACH_RADIUS)]
        bare = SimRobot(dataclasses.replace(params, occlude_stem=False), camera=None)
        without = stem_points_seen(bare, scene.approach_pose(APPROACH_RADIUS))
        towards_gripper = stem_points_seen(
            robot, scene.approach_pose(APPROACH_RADIUS, target=scene.gripper_home[:3, 3])
        )
        name = "default" if seed < 0 else f"seed {seed}"
        print(
            f"| {name} | {params.occluder_coverage:.2f} | {leaf:.2f} / {other:.2f} | "
            f"{1000 * stem_length_inside_robot(robot):.1f} | {stem_points_seen(robot, robot.site_pose('camera'))} | "
            f"{seen[0]} | {seen[1]} | {seen[2]} | {without} | {towards_gripper} |"
        )


if __name__ == "__main__":
    main()
