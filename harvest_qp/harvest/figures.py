"""PNG figures of a paper episode, one per result figure of Section ``sec:exper``.

Every time plot marks the start of the bimanual motion with a green dotted line, as the
paper does. Files (in the episode's output folder):

* ``fig_exp_reach.png``: distance from the camera to the ROI centre, r dashed red;
* ``fig_exp_center.png``: theta between p_r - p_c and z_c;
* ``fig_exp_unv.png``: visible stem points;
* ``fig_exp_ep.png``: projected position error of the grasping arm;
* ``fig_exp_eo.png``: alignment angle between y_g and n_c;
* ``fig_exp_f.png``: force along n_c (tared), f_d dashed red;
* ``fig_exp_proc.png``: the camera's view at the start, the switch and the end, by label;
* ``fig_PC_proc.png``: the point-cloud processing panels of Fig. ``fig:PC_proc`` at the switch.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from harvest_qp.config import EpisodeConfig  # noqa: E402
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM  # noqa: E402

__all__ = ["write_figures", "label_image"]

_LABEL_RGB = {STEM: (0.9, 0.1, 0.1), OBSTACLE: (0.25, 0.6, 0.25), ROBOT: (0.55, 0.55, 0.6)}


def label_image(pixels: np.ndarray, labels: np.ndarray, image_size: tuple[int, int], depth=None) -> np.ndarray:
    """An RGB image (H, W, 3) of a labelled cloud: stem red, obstacles green, robot grey, shaded by depth."""
    h, w = image_size
    image = np.ones((h, w, 3))
    if len(labels) == 0:
        return image
    shade = np.ones(len(labels))
    if depth is not None and len(depth):
        d = np.asarray(depth, float)
        shade = 1.0 - 0.6 * np.clip((d - d.min()) / max(np.ptp(d), 1e-9), 0, 1)
    colours = np.array([_LABEL_RGB.get(int(lab), (0, 0, 0)) for lab in (STEM, OBSTACLE, ROBOT)])
    index = np.searchsorted(np.array([STEM, OBSTACLE, ROBOT]), labels)
    index = np.clip(index, 0, 2)
    rgb = colours[index] * shade[:, None]
    stem = labels == STEM
    rgb[stem] = colours[0]  # the stem keeps its colour so that it stands out
    image[pixels[:, 0], pixels[:, 1]] = rgb
    return image


def _time_plot(ax, t, y, t_switch, ylabel, title):
    ax.plot(t, y, lw=1.2)
    if t_switch is not None:
        ax.axvline(t_switch, color="green", ls=":", lw=1.5, label="bimanual start")
    ax.set_xlabel("t [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_figures(log: dict, controller, settings: EpisodeConfig, out_dir: Path, metrics: dict) -> list[Path]:
    """Write the figures listed in the module docstring; return their paths."""
    out_dir = Path(out_dir)
    t = log["t"]
    ts = controller.phases.t_switch
    f_d = settings.grasping.f_d
    r = settings.reaching.radius
    paths = []

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, t, log["value/roi_distance"], ts, r"$\|p_r - p_c\|$ [m]", "Reaching (fig:exp_reach)")
    ax.axhline(r, color="red", ls="--", lw=1, label=f"r = {r} m")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out_dir / "fig_exp_reach.png"))

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, t, np.degrees(log["value/theta"]), ts, r"$\theta$ [deg]", "Centering (fig:exp_center)")
    paths.append(_save(fig, out_dir / "fig_exp_center.png"))

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, log["frame_time"], log["frame_stem_points"], ts, "visible stem points", "Unveiling (fig:exp_unv)")
    paths.append(_save(fig, out_dir / "fig_exp_unv.png"))

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, t, 1e3 * log["value/position_error"], ts, "projected position error [mm]",
               "Position error (fig:exp_ep)")
    paths.append(_save(fig, out_dir / "fig_exp_ep.png"))

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, t, np.degrees(log["value/alignment"]), ts, r"angle($y_g$, $n_c$) [deg]",
               "Alignment (fig:exp_eo)")
    paths.append(_save(fig, out_dir / "fig_exp_eo.png"))

    fig, ax = plt.subplots(figsize=(5, 3.2))
    _time_plot(ax, t, log["value/force_nc"], ts, r"$n_c^T f$ [N]", "Applied force (fig:exp_f)")
    if "truth/stem_tension" in log and ts is not None:
        after = t >= ts
        ax.plot(t[after], log["truth/stem_tension"][after], lw=0.8, color="0.5", label="true tension")
    ax.axhline(f_d, color="red", ls="--", lw=1, label=f"f_d = {f_d} N")
    ax.legend(fontsize=8)
    paths.append(_save(fig, out_dir / "fig_exp_f.png"))

    snaps = controller.snapshots
    names = [("start", "(a) process start"), ("switch", "(b) bimanual start"), ("end", "(c) end")]
    fig, axes = plt.subplots(1, 3, figsize=(12, 2.9))
    for ax, (key, title) in zip(axes, names):
        snap = snaps.get(key)
        if snap is None:
            ax.text(0.5, 0.5, "no frame", ha="center")
            ax.set_title(title, fontsize=10)
            ax.axis("off")
            continue
        ax.imshow(label_image(snap.pixels, snap.labels, snap.image_size, snap.depth))
        n_stem = int(np.count_nonzero(snap.labels == STEM))
        ax.set_title(f"{title}, t = {snap.time:.2f} s, {n_stem} stem points", fontsize=9)
        ax.axis("off")
    paths.append(_save(fig, out_dir / "fig_exp_proc.png"))

    paths.append(_pc_proc(controller.switch_snapshot, out_dir / "fig_PC_proc.png"))
    return paths


def _pc_proc(snap, path: Path) -> Path:
    """The six panels of Fig. fig:PC_proc at the switch, seen from the camera (x right, y down)."""
    fig, axes = plt.subplots(3, 2, figsize=(9, 11))
    axes = axes.ravel()
    if snap is None:
        for ax in axes:
            ax.text(0.5, 0.5, "no switch: no bimanual phase", ha="center")
            ax.axis("off")
        return _save(fig, path)
    R, p = snap.camera_pose[:3, :3], snap.camera_pose[:3, 3]

    def cam(points):
        points = np.asarray(points, float).reshape(-1, 3)
        return (points - p) @ R  # camera coordinates

    centre = cam(snap.stem_base)[0]
    span = max(3.0 * snap.free_space.radius, 0.06)

    def panel(ax, title):
        ax.set_xlim(centre[0] - span, centre[0] + span)
        ax.set_ylim(centre[1] + span, centre[1] - span)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.set_xlabel("x_c [m]")
        ax.set_ylabel("y_c [m]")

    def scatter(ax, points, **kw):
        c = cam(points)
        if len(c):
            ax.scatter(c[:, 0], c[:, 1], **kw)

    near = snap.non_stem_points[np.linalg.norm(snap.non_stem_points - snap.stem_base, axis=1) < 1.5 * span]
    ax = axes[0]
    scatter(ax, near[::2], s=1, c="tab:blue", label="W - S")
    scatter(ax, snap.grasp_obstacles, s=2, c="navy", label="O")
    scatter(ax, snap.stem_points, s=3, c="cyan", label="S")
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, "(1) W with S (cyan) and O (blue)")

    ax = axes[1]
    stem = snap.stem
    scatter(ax, stem.points[stem.top_mask], s=3, c="green", label="top T")
    scatter(ax, stem.points[~stem.top_mask], s=3, c="red", label="bottom B")
    for seg, colour in ((stem.top, "green"), (stem.bottom, "red")):
        ends = cam(np.stack([seg.start, seg.end]))
        ax.plot(ends[:, 0], ends[:, 1], color=colour, lw=2)
    b = cam(snap.stem_base)
    ax.plot(b[:, 0], b[:, 1], "bx", ms=10, mew=2, label="p_sb")
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, f"(2) stem segments, l = {1e3 * stem.length:.0f} mm, p_sb")

    free = snap.free_space
    ax = axes[2]
    scatter(ax, snap.grasp_obstacles, s=2, c="navy")
    scatter(ax, free.projected_obstacles, s=3, c="purple", label="O_pr")
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, "(3) obstacles projected on S(p_sb, l): O_pr")

    ax = axes[3]
    scatter(ax, free.samples[~free.occupied], s=3, c="0.7", label="samples")
    scatter(ax, free.samples[free.occupied], s=4, c="black", label="near obstacles")
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, f"(4) sphere sampling ({len(free.samples)} samples)")

    ax = axes[4]
    scatter(ax, free.samples[~free.occupied], s=3, c="green", label="free")
    scatter(ax, free.samples[free.occupied], s=4, c="black", label="near obstacles")
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, "(5) free-space sphere points")

    ax = axes[5]
    scatter(ax, snap.grasp_obstacles, s=2, c="tab:blue", label="O")
    scatter(ax, free.samples[free.free], s=4, c="green", label="F")
    if free.plane is not None:
        n = free.plane.normal
        u = np.cross(n, [0.0, 0.0, 1.0])
        if np.linalg.norm(u) < 1e-6:
            u = np.cross(n, [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        for axis in (u, v):
            ends = cam(np.stack([free.plane.point - span * axis, free.plane.point + span * axis]))
            ax.plot(ends[:, 0], ends[:, 1], "k-", lw=1)
    tgt = cam(snap.target)
    ax.plot(tgt[:, 0], tgt[:, 1], "m*", ms=14, label="p_gd")
    ax.plot(b[:, 0], b[:, 1], "bx", ms=10, mew=2)
    ax.legend(fontsize=7, loc="upper right")
    panel(ax, "(6) free space F, plane fitted to O, p_gd")
    return _save(fig, path)
