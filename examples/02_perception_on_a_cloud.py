"""Perception on one point cloud: stem points S -> two-segment stem -> p_sb -> free space -> p_gd.

The cloud comes from the MuJoCo lab: the default vine scene, the robot at home holding the
cluster, and the lab's ray-cast depth camera (the paper's D415 at 283x160) placed at a pose
of our choosing, here 0.3 m from the stem, slightly above it and to its side. Each
point carries the label the camera gives it (stem / obstacle / own robot); on a real robot
that label comes from a colour classifier (``harvest_qp.perception.classify``).

The script runs the per-frame pipeline of the paper (``subsec:scePC_proc``) with one call,
``process_cloud``, prints p_sb, the stem length l and p_gd, and writes a two-panel figure:
the labelled cloud as the camera sees it, and a close-up of the stem with both stem
segments, p_sb, the Fibonacci samples kept (free space F) and removed, and p_gd.

    python examples/02_perception_on_a_cloud.py [--out perception.png] [--distance 0.3]
                                                [--azimuth -0.6] [--elevation 0.2]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless: write a PNG, never open a window
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from harvest_qp.perception import process_cloud  # noqa: E402
from harvest_qp.perception.synthetic import look_at  # noqa: E402
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM  # noqa: E402
from harvest_qp.sim.lab_views import LabViews  # noqa: E402


def camera_pose(target: np.ndarray, distance: float, *, azimuth: float, elevation: float) -> np.ndarray:
    """A 4x4 camera pose {C} (z = view direction) at ``distance`` [m] from ``target``, looking at it.

    azimuth [rad] 0 puts the camera on the robot's side of the vine (-x), turning about +z;
    elevation [rad] lifts it.
    """
    c, s = np.cos(elevation), np.sin(elevation)
    direction = np.array([-c * np.cos(azimuth), -c * np.sin(azimuth), s])
    pose = np.eye(4)
    pose[:3, 3] = target + distance * direction
    pose[:3, :3] = look_at(pose[:3, 3], target)
    return pose


def run(out: Path, *, distance: float = 0.3, azimuth: float = -0.6, elevation: float = 0.2) -> dict:
    """Capture one lab frame, run the pipeline, draw the figure; returns what it found [m]."""
    # 1. The lab: a SimRobot on the default scene, settled, plus the ground truth we use
    #    only to report the error (the pipeline never sees it).
    views = LabViews()
    # The default view sees the stem's base; from straight ahead (azimuth 0) the branch
    # hides it and the pipeline flags p_sb as untrusted (result.stem.trusted() is False).
    pose = camera_pose(views.stem_middle, distance, azimuth=azimuth, elevation=elevation)
    cloud = views.camera.capture(views.robot.data, pose, 0.0)  # a harvest_qp.PointCloud

    # 2. The pipeline needs the cloud, which points are stem, the camera position and the
    #    gripper tip (it tells the top stem segment from the bottom one).
    gripper = views.robot.site_pose("gripper")[:3, 3]
    result = process_cloud(cloud.points, cloud.labels == STEM, camera_position=pose[:3, 3], gripper_position=gripper)
    if not result.stem.valid:
        raise SystemExit(f"no stem model from this view ({cloud.count(STEM)} stem points)")

    # 3. The figure.
    fig, (ax_img, ax_3d) = plt.subplots(1, 2, figsize=(11, 4.5))
    colours = {STEM: (0.9, 0.1, 0.1), OBSTACLE: (0.25, 0.6, 0.25), ROBOT: (0.55, 0.55, 0.6)}
    image = np.ones((*views.camera.config.image_size, 3))
    for label, colour in colours.items():
        rows, cols = cloud.pixels[cloud.labels == label].T
        image[rows, cols] = colour
    ax_img.imshow(image)
    ax_img.set_title("camera view: stem red, obstacles green, own robot grey", fontsize=9)
    ax_img.axis("off")

    # Close-up in camera coordinates (x right, y down), centred on p_sb.
    R, p = pose[:3, :3], pose[:3, 3]

    def cam(points):
        return (np.asarray(points, float).reshape(-1, 3) - p) @ R

    free = result.free_space
    others = cloud.points[(cloud.labels != STEM) & (np.linalg.norm(cloud.points - result.stem_base, axis=1) < 0.12)]
    for points, style in (
        (others, dict(s=1, c="0.7", label="W - S")),
        (result.stem_points, dict(s=3, c="red", label="S")),
        (free.removed_samples, dict(s=5, c="black", label="samples removed")),
        (free.kept_samples, dict(s=5, c="tab:cyan", label="free space F")),
    ):
        c = cam(points)
        ax_3d.scatter(c[:, 0], c[:, 1], **style)
    for segment, colour in ((result.stem.top, "green"), (result.stem.bottom, "orange")):
        ends = cam(np.stack([segment.start, segment.end]))
        ax_3d.plot(ends[:, 0], ends[:, 1], color=colour, lw=2)
    for point, marker, name in ((result.stem_base, "bx", "p_sb"), (result.target, "m*", "p_gd")):
        if point is not None:
            c = cam(point)
            ax_3d.plot(c[:, 0], c[:, 1], marker, ms=12, mew=2, label=name)
    centre = cam(result.stem_base)[0]
    ax_3d.set_xlim(centre[0] - 0.08, centre[0] + 0.08)
    ax_3d.set_ylim(centre[1] + 0.08, centre[1] - 0.08)
    ax_3d.set_aspect("equal")
    ax_3d.set_xlabel("x_c [m]")
    ax_3d.set_ylabel("y_c [m]")
    ax_3d.legend(fontsize=7, loc="upper right")
    ax_3d.set_title(f"stem segments, p_sb, free space and p_gd (l = {1e3 * result.stem.length:.0f} mm)", fontsize=9)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return {
        "p_sb": result.stem_base,
        "p_gd": result.target,
        "length": result.stem.length,
        "n_stem": int(cloud.count(STEM)),
        "n_points": len(cloud),
        "trusted": result.stem.trusted(),
        "true_base": views.stem_axis[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("perception.png"), help="figure file (PNG)")
    parser.add_argument("--distance", type=float, default=0.3, help="camera distance from the stem [m]")
    parser.add_argument("--azimuth", type=float, default=-0.6, help="camera azimuth about +z [rad], 0 = robot side")
    parser.add_argument("--elevation", type=float, default=0.2, help="camera elevation [rad]")
    args = parser.parse_args()
    found = run(args.out, distance=args.distance, azimuth=args.azimuth, elevation=args.elevation)
    fmt = np.array2string
    print(f"cloud: {found['n_points']} points, {found['n_stem']} on the stem")
    print(f"p_sb = {fmt(found['p_sb'], precision=4, separator=', ')} m (trusted: {found['trusted']})")
    print(f"l = {found['length']:.4f} m")
    print(f"p_gd = {fmt(found['p_gd'], precision=4, separator=', ')} m")
    error = np.linalg.norm(found["p_sb"] - found["true_base"])
    print(f"p_sb error against the lab's true stem base: {1e3 * error:.1f} mm")
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
