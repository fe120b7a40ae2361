"""One picture of the episode: :class:`ViewerFrame`, and frames from an episode log.

Every field but ``time`` and ``q`` is optional: the viewer draws what it is given and hides
the rest, so the same code shows today's runner log and the closed loop's richer one.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.interface import N_JOINTS, PointCloud

__all__ = ["ViewerFrame", "LOG_KEYS", "frames_from_log", "frame_from_observation"]


@dataclass(eq=False)
class ViewerFrame:
    """What to draw at one instant. World frame, metres, seconds, newtons.

    Attributes:
        time: episode time [s].
        q: joint positions (12,) [rad], camera arm first.
        force: measured wrist force (3,) [N], drawn as an arrow at the gripper.
        phase: the closed loop's phase name (text panel).
        theta: the loop's angle theta [rad] (text panel, shown in degrees).
        stem_points: visible stem points in the latest cloud (text panel).
        status: controller status (text panel).
        cloud_points: (n, 3) latest point cloud [m]; ``cloud_labels`` (n,) STEM / OBSTACLE / ROBOT.
        cloud_key: identifies the cloud (e.g. its timestamp); the cloud is only re-sent
            when it changes (default: the identity of ``cloud_points``).
        camera_pose: (4, 4) camera optical frame {C} of the cloud (frustum).
        roi_center, roi_radius: region of interest sphere [m].
        p_r, p_sb, p_gd: reference point, stem base and grasp/attraction point (3,) [m].
        p_c: the camera position the controller drove (3,) [m] (a calibrated camera on the real cell
            is not the robot description's): the v_c arrow starts there (None: the description's).
        stem_segments: (k, 2, 3) stem model segments, start and end points [m].
        samples_kept, samples_removed: (m, 3) Fibonacci samples of the free space [m].
        v_c, v_g: camera / gripper reference velocity, (3,) linear or (6,) twist
            [m/s, rad/s]; the linear part is drawn at the camera / gripper.
        closest_pair: (2, 3) witness points of the closest collision pair [m];
            ``closest_distance`` [m] is written next to it in the text panel.
        body_poses: vine body name -> (4, 4) world pose (moving stem segments, cluster).
        extra_text: more lines for the text panel.
    """

    time: float
    q: NDArray[np.float64]
    force: NDArray[np.float64] | None = None
    phase: str | None = None
    theta: float | None = None
    stem_points: int | None = None
    status: str | None = None
    cloud_points: NDArray[np.floating] | None = None
    cloud_labels: NDArray[np.integer] | None = None
    cloud_key: Any = None
    camera_pose: NDArray[np.float64] | None = None
    roi_center: NDArray[np.float64] | None = None
    roi_radius: float | None = None
    p_r: NDArray[np.float64] | None = None
    p_sb: NDArray[np.float64] | None = None
    p_gd: NDArray[np.float64] | None = None
    p_c: NDArray[np.float64] | None = None
    stem_segments: NDArray[np.float64] | None = None
    samples_kept: NDArray[np.float64] | None = None
    samples_removed: NDArray[np.float64] | None = None
    v_c: NDArray[np.float64] | None = None
    v_g: NDArray[np.float64] | None = None
    closest_pair: NDArray[np.float64] | None = None
    closest_distance: float | None = None
    body_poses: Mapping[str, NDArray[np.float64]] | None = None
    extra_text: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if not np.isfinite(self.time):
            raise InvalidInputError(f"ViewerFrame.time must be finite [s], got {self.time!r}")
        q = np.asarray(self.q, dtype=float)
        if q.shape != (N_JOINTS,) or not np.all(np.isfinite(q)):
            raise InvalidInputError(f"ViewerFrame.q must be {N_JOINTS} finite joint positions [rad], got {self.q!r}")
        self.q = q
        for name, shape in (("force", (3,)), ("p_r", (3,)), ("p_sb", (3,)), ("p_gd", (3,)), ("p_c", (3,)),
                            ("roi_center", (3,)),
                            ("camera_pose", (4, 4)), ("closest_pair", (2, 3))):  # fmt: skip
            value = getattr(self, name)
            if value is not None:
                arr = np.asarray(value, dtype=float)
                if arr.shape != shape:
                    raise InvalidInputError(f"ViewerFrame.{name} must have shape {shape}, got {arr.shape}")
                setattr(self, name, arr)
        for name in ("v_c", "v_g"):
            value = getattr(self, name)
            if value is not None:
                arr = np.asarray(value, dtype=float)
                if arr.shape not in ((3,), (6,)):
                    raise InvalidInputError(
                        f"ViewerFrame.{name} must be a (3,) velocity or (6,) twist, got {arr.shape}"
                    )
                setattr(self, name, arr[:3])
        if self.cloud_points is not None:
            pts = np.asarray(self.cloud_points)
            if pts.ndim != 2 or pts.shape[1] != 3:
                raise InvalidInputError(f"ViewerFrame.cloud_points must have shape (n, 3), got {pts.shape}")
            labels = self.cloud_labels
            if labels is None or np.shape(labels) != (len(pts),):
                raise InvalidInputError(
                    f"ViewerFrame.cloud_labels must have shape ({len(pts)},) to match cloud_points, got "
                    f"{None if labels is None else np.shape(labels)}"
                )
        for name in ("samples_kept", "samples_removed"):
            value = getattr(self, name)
            if value is not None and (np.ndim(value) != 2 or np.shape(value)[1] != 3):
                raise InvalidInputError(f"ViewerFrame.{name} must have shape (m, 3), got {np.shape(value)}")
        if self.stem_segments is not None:
            seg = np.asarray(self.stem_segments, dtype=float)
            if seg.ndim != 3 or seg.shape[1:] != (2, 3):
                raise InvalidInputError(f"ViewerFrame.stem_segments must have shape (k, 2, 3), got {seg.shape}")
            self.stem_segments = seg

    def text_lines(self) -> list[str]:
        """The text panel's lines."""
        lines = [f"t = {self.time:6.2f} s"]
        if self.phase is not None:
            lines.insert(0, f"phase: {self.phase}")
        if self.theta is not None and np.isfinite(self.theta):
            lines.append(f"theta = {np.degrees(self.theta):6.1f} deg")
        if self.force is not None and np.all(np.isfinite(self.force)):
            lines.append(f"|f| = {np.linalg.norm(self.force):5.2f} N")
        if self.stem_points is not None and self.stem_points >= 0:
            lines.append(f"stem points: {int(self.stem_points)}")
        if self.closest_distance is not None and np.isfinite(self.closest_distance):
            lines.append(f"closest pair: {100 * self.closest_distance:5.1f} cm")
        if self.status:
            lines.append(f"status: {self.status}")
        lines.extend(self.extra_text)
        return lines


def frame_from_observation(obs: Any, extras: Mapping[str, Any] | None = None) -> ViewerFrame:
    """A :class:`ViewerFrame` from a runner :class:`~harvest_qp.runtime.runner.Observation` plus optional fields.

    ``extras`` holds any :class:`ViewerFrame` field (``phase``, ``p_r``, ``v_c``, ...); unknown
    keys raise :class:`InvalidInputError`.
    """
    kwargs: dict[str, Any] = {"time": float(obs.time), "q": obs.q, "force": obs.force}
    cloud: PointCloud | None = getattr(obs, "cloud", None)
    if cloud is not None:
        kwargs.update(
            cloud_points=cloud.points, cloud_labels=cloud.labels, cloud_key=(id(cloud), cloud.timestamp),
            camera_pose=cloud.camera_pose, stem_points=cloud.count(0),
        )  # fmt: skip
    if extras:
        unknown = set(extras) - set(ViewerFrame.__dataclass_fields__)
        if unknown:
            raise InvalidInputError(
                f"unknown viewer extras {sorted(unknown)}; expected ViewerFrame fields "
                f"{sorted(ViewerFrame.__dataclass_fields__)}"
            )
        kwargs.update(extras)
    return ViewerFrame(**kwargs)


#: Log keys read by :func:`frames_from_log`, per ViewerFrame field, first match wins;
#: a key also matches with any ``prefix/`` (e.g. ``loop/p_r``).
LOG_KEYS: dict[str, tuple[str, ...]] = {
    "phase": ("phase",),
    "theta": ("theta",),
    "p_r": ("p_r",),
    "p_sb": ("p_sb",),
    "p_gd": ("p_gd",),
    "p_c": ("p_c",),
    "v_c": ("V_c", "v_c"),
    "v_g": ("V_g", "v_g"),
    "roi_center": ("roi_center", "p_roi"),
    "roi_radius": ("roi_radius", "r_roi"),
    "closest_distance": ("closest_distance", "min_distance"),
    "closest_pair": ("closest_pair",),
    "stem_segments": ("stem_segments",),
}


def _find_key(log: Mapping[str, Any], names: tuple[str, ...]) -> str | None:
    for name in names:
        if name in log:
            return name
    for name in names:
        for key in log:
            if key.endswith("/" + name) and not key.startswith(("task_error/", "truth/", "meta/")):
                return key
    return None


def _phase_name(value: Any, names: list[str]) -> str:
    try:
        index = float(value)
    except (TypeError, ValueError):
        return str(value)
    if np.isfinite(index) and index == int(index) and 0 <= int(index) < len(names):
        return names[int(index)]
    return str(value)


def frames_from_log(
    log: Mapping[str, ArrayLike], *, fps: float = 30.0, max_frames: int | None = None
) -> list[ViewerFrame]:
    """Viewer frames from an episode log (the runner's ``.npz`` keys), one per ``1/fps`` seconds.

    Per-tick arrays (``t``, ``q``, ``force``, ``status``, ``stem_points`` and the fields in
    :data:`LOG_KEYS`) are sampled at the frame times; the camera pose and, with
    ``log_clouds``, the point cloud are those of the latest camera frame.

    Args:
        log: a mapping such as ``numpy.load("episode.npz")`` or ``EpisodeResult.log``.
        fps: frames per second of episode time.
        max_frames: keep at most this many frames (evenly spaced); None: no limit.
    """
    for key in ("t", "q"):
        if key not in log:
            raise InvalidInputError(f"the episode log has no {key!r} array; got keys {sorted(log)[:20]}")
    if not np.isfinite(fps) or fps <= 0:
        raise InvalidInputError(f"fps must be > 0 [1/s], got {fps!r}")
    t = np.asarray(log["t"], dtype=float)
    q = np.asarray(log["q"], dtype=float)
    if len(t) == 0:
        raise InvalidInputError("the episode log has no control ticks (empty 't')")
    times = np.arange(t[0], t[-1] + 1e-9, 1.0 / fps)
    ticks = np.minimum(np.searchsorted(t, times - 1e-9), len(t) - 1)
    ticks = np.unique(ticks)
    if max_frames is not None and len(ticks) > max_frames:
        ticks = ticks[np.linspace(0, len(ticks) - 1, max_frames).round().astype(int)]
    arrays = {k: np.asarray(log[k]) for k in ("force", "status", "stem_points") if k in log}
    found = {f: _find_key(log, names) for f, names in LOG_KEYS.items()}
    extra = {f: np.asarray(log[k]) for f, k in found.items() if k is not None}
    frame_time = np.asarray(log["frame_time"], dtype=float) if "frame_time" in log else np.zeros(0)
    poses = np.asarray(log["frame_camera_pose"], dtype=float) if "frame_camera_pose" in log else None
    has_clouds = all(k in log for k in ("cloud_points", "cloud_labels", "cloud_offsets"))
    if has_clouds:
        points, labels = np.asarray(log["cloud_points"]), np.asarray(log["cloud_labels"])
        offsets = np.asarray(log["cloud_offsets"])
        # which camera frame each logged cloud is (logs thinned to every N-th frame say so)
        cloud_frame = np.asarray(log["cloud_frame"]) if "cloud_frame" in log else np.arange(len(offsets) - 1)
    # a numeric phase (the paper loop logs its Phase as a number) is named by meta/phase_names
    phase_names = str(np.asarray(log["meta/phase_names"])).split(",") if "meta/phase_names" in log else []
    frames = []
    for k in ticks:
        kw: dict[str, Any] = {"time": float(t[k]), "q": q[k]}
        if "force" in arrays and np.all(np.isfinite(arrays["force"][k])):
            kw["force"] = arrays["force"][k]
        if "status" in arrays:
            kw["status"] = str(arrays["status"][k])
        if "stem_points" in arrays:
            kw["stem_points"] = int(arrays["stem_points"][k])
        for name, values in extra.items():
            value = values[k] if values.ndim >= 1 and len(values) == len(t) else values
            if name == "phase":
                kw[name] = _phase_name(value, phase_names)
            elif name in ("theta", "roi_radius", "closest_distance"):
                if np.isfinite(float(value)):
                    kw[name] = float(value)
            elif np.all(np.isfinite(value)):
                kw[name] = value
        i = int(np.searchsorted(frame_time, t[k] + 1e-9)) - 1  # latest frame captured by t[k]
        if i >= 0:
            if poses is not None and len(poses) > i:
                kw["camera_pose"] = poses[i]
            j = int(np.searchsorted(cloud_frame, i, side="right")) - 1 if has_clouds else -1  # latest logged cloud
            if j >= 0:
                a, b = int(offsets[j]), int(offsets[j + 1])
                kw.update(cloud_points=points[a:b], cloud_labels=labels[a:b], cloud_key=("log", j))
        frames.append(ViewerFrame(**kw))
    return frames
