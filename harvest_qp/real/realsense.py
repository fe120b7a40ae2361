"""A RealSense D415 as the lab's camera: aligned depth and colour become the same :class:`PointCloud`.

Per frame (:meth:`RealSenseSource.process`):

1. depth is aligned to the colour stream (``rs.align(rs.stream.color)``);
2. the image is decimated by the episode's ``camera.downsample`` (the paper's x3): one pixel,
   the centre of each ``k x k`` block, per point, so pixel (i, j) of the cloud is the block
   (i, j) of the 848x480 image, as in the lab's downsampled image;
3. invalid depth (0) and depth outside [min_depth, max_depth] is dropped, the one-pixel seams that
   ``rs.align`` leaves included (never filled: a filled seam would be a point nobody measured);
4. each pixel's ray comes from the colour intrinsics (``rs2_deproject_pixel_to_point``, any
   distortion model), scaled by its depth; world points through the camera pose at the capture
   time: the camera arm's measured flange pose (robot description) times the hand-eye transform
   of the calibration file;
5. labels: STEM where the stem detector (default: the red threshold) fires within
   ``camera.stem_range`` of the camera, ROBOT within ``robot_margin`` of the robot's own
   capsules at the measured joints, OBSTACLE otherwise;
6. the timestamp is the capture time on the robot clock (the frame's host timestamp mapped
   through the robot's clock).

On the robot the frames are processed in a worker thread, so :meth:`latest` never blocks the
2 ms loop; a failure there ends the episode through the robot's watchdog.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from harvest_qp.real.cell import CameraCellConfig
from harvest_qp.real.errors import CameraError, missing_package
from harvest_qp.real.stem_detector import StemDetector, load_detector
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM, PointCloud

__all__ = ["RealSenseSource", "open_pipeline", "decimation_indices", "RobotSelfFilter"]


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError:
        raise missing_package("pyrealsense2", "the RealSense camera (--camera realsense)") from None
    except OSError as err:  # libusb missing: Debian package libusb-1.0-0
        raise CameraError(f"pyrealsense2 cannot load: {err} (install the system package libusb-1.0-0)") from None
    return rs


def decimation_indices(size: int, k: int) -> NDArray[np.int64]:
    """Full-image indices of the ``ceil(size / k)`` decimated pixels: each ``k``-block's centre pixel."""
    return np.minimum(np.arange(-(-size // k)) * k + (k - 1) // 2, size - 1).astype(np.int64)


class RobotSelfFilter:
    """Which world points lie on the robot: within ``margin`` of its collision capsules at joints ``q``."""

    def __init__(self, margin: float) -> None:
        from harvest_qp.configuration import Configuration
        from harvest_qp.robot.description import collision_bodies

        self.margin = float(margin)
        self.bodies = collision_bodies()
        self.configuration = Configuration.dual_ur5e()

    def __call__(self, points: NDArray[np.float64], q: NDArray[np.float64]) -> NDArray[np.bool_]:
        self.configuration.update(q)
        on_robot = np.zeros(len(points), dtype=bool)
        for body in self.bodies:
            if body.link == "base":
                R, p = np.eye(3), np.zeros(3)
            else:
                pose = self.configuration.frame_pose(body.link)
                R, p = pose.rotation, pose.translation
            a = R @ np.asarray(body.capsule.p0) + p
            b = R @ np.asarray(body.capsule.p1) + p
            ab = b - a
            t = np.clip((points - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0)
            d2 = np.sum((points - (a + t[:, None] * ab)) ** 2, axis=1)
            on_robot |= d2 <= (body.capsule.radius + self.margin) ** 2
        return on_robot


def open_pipeline(config: CameraCellConfig, serial: str | None = None) -> tuple[Any, float]:
    """Start a D415's depth (z16) and colour (rgb8) streams; return the pipeline and the depth scale [m].

    Raises:
        CameraError: no camera (or not the one with ``serial``), or the mode is not supported.
    """
    rs = _rs()
    pipeline, rs_config = rs.pipeline(), rs.config()
    if serial:
        rs_config.enable_device(str(serial))
    rs_config.enable_stream(rs.stream.depth, config.width, config.height, rs.format.z16, config.fps)
    rs_config.enable_stream(rs.stream.color, config.width, config.height, rs.format.rgb8, config.fps)
    try:
        profile = pipeline.start(rs_config)
    except RuntimeError as err:
        which = f"with serial {serial}" if serial else "(any serial)"
        raise CameraError(f"cannot start the RealSense camera {which} at {config.width}x{config.height} "
                          f"{config.fps} FPS: {err}; check the USB 3 cable and `rs-enumerate-devices`") from None
    scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
    return pipeline, scale


class RealSenseSource:
    """D415 frames as labelled world clouds (see the module docstring).

    Args:
        frames: where framesets come from: an ``rs.pipeline`` (:func:`open_pipeline`) or an
            ``rs.syncer`` of a ``software_device`` (tests); anything with ``try_wait_for_frames``.
        depth_scale: metres per depth unit (the D415's default 0.001).
        downsample: keep one pixel per ``k x k`` block (the episode's ``camera.downsample``).
        stem_range: the stem is detectable within this distance [m] (``camera.stem_range``).
        cell: the cell file's camera section (depth interval, stem detector, robot margin).
        detector: overrides the cell's stem detector.
        wall_clock: the clock of the frames' host timestamps [s] (``time.time``: librealsense's
            global/system time domains).
    """

    def __init__(self, frames: Any, *, depth_scale: float = 0.001, downsample: int = 3, stem_range: float = 0.7,
                 cell: CameraCellConfig | None = None, detector: StemDetector | None = None,
                 wall_clock: Callable[[], float] = time.time) -> None:
        self.rs = _rs()
        self.frames = frames
        self.depth_scale = float(depth_scale)
        if isinstance(downsample, bool) or not isinstance(downsample, (int, np.integer)) or downsample < 1:
            raise CameraError(f"downsample must be an integer >= 1, got {downsample!r}")
        self.k = int(downsample)
        self.stem_range = float(stem_range)
        self.cell = cell if cell is not None else CameraCellConfig()
        self.detector = detector if detector is not None else load_detector(self.cell.stem_detector)
        self.wall_clock = wall_clock
        self.align = self.rs.align(self.rs.stream.color)
        self._rays: NDArray[np.float64] | None = None
        self._rays_key: tuple | None = None
        self._self_filter = RobotSelfFilter(self.cell.robot_margin) if self.cell.robot_margin >= 0 else None
        self._latest: PointCloud | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._running = False
        self.error: str | None = None
        self.frames_processed = 0
        self.frames_skipped = 0
        self.robot = None

    # ------------------------------------------------------------------ CloudSource

    def attach(self, robot) -> None:
        """Start the worker thread that turns framesets into clouds for ``robot``."""
        self.robot = robot
        self._running = True
        self._thread = threading.Thread(target=self._worker, name="realsense", daemon=True)
        self._thread.start()

    def latest(self) -> PointCloud | None:
        if self.error is not None:
            raise CameraError(self.error)
        with self._lock:
            cloud, self._latest = self._latest, None
        return cloud

    def close(self) -> None:
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        stop = getattr(self.frames, "stop", None)
        if callable(stop):
            try:
                stop()
            except RuntimeError:
                pass  # already stopped

    # ------------------------------------------------------------------ processing

    def wait(self, timeout_ms: int = 1000) -> Any:
        """The next frameset holding both depth and colour (None when none came within the timeout)."""
        deadline = time.monotonic() + timeout_ms / 1e3
        while time.monotonic() < deadline:
            ok, frameset = self.frames.try_wait_for_frames(max(1, int(1e3 * (deadline - time.monotonic()))))
            if ok and frameset.get_depth_frame() and frameset.get_color_frame():
                return frameset
        return None

    def process(self, frameset: Any, camera_pose: NDArray | None = None, timestamp: float | None = None,
                q: NDArray | None = None) -> PointCloud:
        """One frameset as a cloud; the pose, robot-clock timestamp and joints default to the attached
        robot's at the frame's capture time."""
        aligned = self.align.process(frameset)
        depth_frame, color_frame = aligned.get_depth_frame(), aligned.get_color_frame()
        if not depth_frame or not color_frame:
            raise CameraError("the frameset has no aligned depth and colour frames")
        depth = np.asanyarray(depth_frame.get_data())
        rgb = np.asanyarray(color_frame.get_data())
        if rgb.ndim != 3 or rgb.shape[:2] != depth.shape:
            raise CameraError(f"colour {rgb.shape} and aligned depth {depth.shape} differ; the colour stream "
                              "must be rgb8")
        intrinsics = color_frame.profile.as_video_stream_profile().get_intrinsics()
        rays = self._ray_table(intrinsics)
        rows, cols = decimation_indices(depth.shape[0], self.k), decimation_indices(depth.shape[1], self.k)
        # Invalid depth (0), the one-pixel seams rs.align leaves included, is dropped below, never filled:
        # a filled seam would be a point nobody measured.
        d = depth[np.ix_(rows, cols)].astype(np.float64) * self.depth_scale
        c = rgb[np.ix_(rows, cols)]
        if timestamp is None:
            timestamp = self._robot_time(color_frame)
        if camera_pose is None:
            camera_pose = self.robot.camera_pose_at(timestamp)
        if q is None and self.robot is not None:
            q = self.robot.joints_at(timestamp)
        return self.cloud(d, c, rays, np.asarray(camera_pose, float), float(timestamp), q)

    def cloud(self, depth: NDArray[np.float64], rgb: NDArray[np.uint8], rays: NDArray[np.float64],
              camera_pose: NDArray[np.float64], timestamp: float, q: NDArray | None = None) -> PointCloud:
        """The cloud of a decimated depth [m] and colour image with per-pixel rays (z = 1) in {C}."""
        h, w = depth.shape
        valid = (depth > 0) & (depth >= self.cell.min_depth) & (depth <= self.cell.max_depth)
        stem = np.asarray(self.detector(rgb, depth), dtype=bool)
        if stem.shape != depth.shape:
            raise CameraError(f"the stem detector returned a mask of shape {stem.shape}, expected {depth.shape}")
        v, u = np.nonzero(valid)
        z = depth[v, u]
        local = rays[v, u] * z[:, None]
        points = local @ camera_pose[:3, :3].T + camera_pose[:3, 3]
        labels = np.full(len(z), OBSTACLE, dtype=np.int8)
        labels[stem[v, u] & (np.linalg.norm(local, axis=1) <= self.stem_range)] = STEM
        if q is not None and self._self_filter is not None:
            labels[self._self_filter(points, np.asarray(q, float))] = ROBOT
        return PointCloud(points=points, labels=labels, colors=np.ascontiguousarray(rgb[v, u], dtype=np.uint8),
                          camera_pose=camera_pose.copy(), timestamp=timestamp, depth=z,
                          pixels=np.stack([v, u], axis=1).astype(np.int32), image_size=(h, w))

    def _ray_table(self, intrinsics: Any) -> NDArray[np.float64]:
        """(h, w, 3) rays with z = 1 of the decimated pixels (librealsense's deprojection, any model)."""
        key = (intrinsics.width, intrinsics.height, intrinsics.fx, intrinsics.fy, intrinsics.ppx, intrinsics.ppy,
               str(intrinsics.model), tuple(intrinsics.coeffs), self.k)
        if key != self._rays_key:
            rows = decimation_indices(intrinsics.height, self.k)
            cols = decimation_indices(intrinsics.width, self.k)
            deproject = self.rs.rs2_deproject_pixel_to_point
            self._rays = np.array([[deproject(intrinsics, [float(u), float(v)], 1.0) for u in cols] for v in rows])
            self._rays_key = key
        return self._rays

    def _robot_time(self, frame: Any) -> float:
        """The frame's capture time on the robot clock (host timestamps; others: the arrival time)."""
        robot = self.robot
        if robot is None:
            return float(frame.get_timestamp()) / 1e3
        domain = frame.get_frame_timestamp_domain()
        age = 0.0
        if domain in (self.rs.timestamp_domain.global_time, self.rs.timestamp_domain.system_time):
            age = max(0.0, self.wall_clock() - frame.get_timestamp() / 1e3)
        return robot.robot_time_at(robot.clock() - age)

    def _worker(self) -> None:
        while self._running:
            try:
                frameset = self.wait(200)
                if frameset is None:
                    continue
                cloud = self.process(frameset)
            except Exception as err:  # reported to the control loop, which stops the arms
                self.error = f"the RealSense camera failed: {type(err).__name__}: {err}"
                return
            with self._lock:
                if self._latest is not None:
                    self.frames_skipped += 1
                self._latest = cloud
            self.frames_processed += 1
