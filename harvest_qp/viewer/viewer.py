"""The meshcat scene of the harvester: UR5e arms, vine, point cloud, markers and a text panel.

:class:`MeshcatViewer` builds the static scene once and then draws :class:`ViewerFrame`
objects. One frame is one batch: every changed transform and property is sent at once and
acknowledged together (:class:`~harvest_qp.viewer.server.Connection`), and geometry (the
point cloud, the Fibonacci samples, the text panel) is only re-sent when it changes.

:meth:`MeshcatViewer.load_animation` turns a list of frames into a meshcat animation (time
slider, play/pause in the viewer's "Animations" menu) and :meth:`MeshcatViewer.export_html`
writes the whole scene, animation included, to one self-contained HTML file.

Deviation from meshcat's defaults: the scene is shifted so that the region around the vine
sits at meshcat's origin (its orbit camera always looks at the origin), the grid and axes
are hidden (the grid would cut through the scene at the origin) and a floor is drawn at z = 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import umsgpack
from meshcat import geometry as mg
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.robot import description as desc
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM
from harvest_qp.viewer.commands import (
    Batch,
    mesh_object,
    points_object,
    render_text_png,
    rgba_int,
    segment_transform,
    stl_object,
    translation,
    y_to,
)
from harvest_qp.viewer.frame import ViewerFrame
from harvest_qp.viewer.geometry import VineGeom, robot_link_meshes, vine_body_poses, vine_geoms
from harvest_qp.viewer.server import Connection, ViewerServer

__all__ = ["MeshcatViewer", "COLORS", "VIEW_CENTER", "CAMERA_OFFSET", "CAMERA_FOVY"]

#: Colours (0xRRGGBB) of everything the viewer draws besides the vine (which keeps the
#: MuJoCo scene's colours). Point cloud colours are unlit, so they stay exact on screen.
COLORS: dict[str, int] = {
    "robot": 0x8FA9D8,
    "tool": 0x3A3A40,
    "stand": 0x707075,
    "capsule": 0xFF9F1C,
    "floor": 0x505050,
    "cloud_stem": 0xFFE600,
    "cloud_obstacle": 0x00E5E5,
    "cloud_robot": 0xE040FB,
    "roi": 0x4CAF50,
    "p_r": 0xFFFFFF,
    "p_sb": 0xFF3D00,
    "p_gd": 0x2979FF,
    "stem_segment": 0xFF80AB,
    "samples_kept": 0x76FF03,
    "samples_removed": 0x9E9E9E,
    "frustum": 0xFFFFFF,
    "v_c": 0x00B0FF,
    "v_g": 0xFFC400,
    "force": 0xFF9100,
    "closest_pair": 0xF50057,
}
_CLOUD_LABELS = ((STEM, "stem"), (OBSTACLE, "obstacle"), (ROBOT, "robot"))

#: World point [m] shown at meshcat's origin (between the arms and the vine).
VIEW_CENTER = (0.45, 0.0, 1.05)
#: Default camera position relative to VIEW_CENTER, world frame [m].
CAMERA_OFFSET = (0.12, -1.00, 0.80)
#: meshcat's camera: three.js PerspectiveCamera with a 75 deg vertical field of view.
CAMERA_FOVY = 75.0

ROOT = "/harvest_qp"
_PANEL_WIDTH = 0.4  # text panel width before scaling [m]


class MeshcatViewer:
    """The harvester scene in meshcat.

    Args:
        vine: what to draw as the vine: a ``mujoco.MjModel`` of the vine scene (e.g.
            ``SimRobot.model``), a :class:`~harvest_qp.sim.VineScene`, a
            :class:`~harvest_qp.sim.VineSceneParams`, or None for no vine.
        server: a running :class:`ViewerServer`; None starts one on ``host``:``port``
            (closed with this viewer).
        zmq_url: connect to a meshcat server started elsewhere instead (not closed here).
        host, port: where a new server serves the page (default 127.0.0.1:7000).
        show_capsules: show the robot's collision capsules at start (toggle with
            :meth:`set_capsules_visible` or the "capsules" entry of meshcat's scene menu).
        max_cloud_points: points drawn per cloud at most (a fixed-stride subset) [-].
        point_size: point size [m].
        velocity_scale: arrow length per speed [m per m/s] (V_c, V_g).
        force_scale: arrow length per force [m per N].
        text_interval: shortest wall time between two text panel updates [s] (each is a new
            PNG); 0: every frame.
        view_center: world point shown at the centre of the view (the orbit camera's target) [m].
        camera_offset: initial camera position relative to ``view_center``, world frame [m].
        verbose: print the URL when a server is started.
    """

    def __init__(
        self,
        vine: Any = None,
        *,
        server: ViewerServer | None = None,
        zmq_url: str | None = None,
        host: str = "127.0.0.1",
        port: int = 7000,
        show_capsules: bool = False,
        max_cloud_points: int = 10000,
        point_size: float = 0.006,
        velocity_scale: float = 1.0,
        force_scale: float = 0.02,
        text_interval: float = 0.1,
        view_center: tuple[float, float, float] = VIEW_CENTER,
        camera_offset: tuple[float, float, float] = CAMERA_OFFSET,
        verbose: bool = True,
    ) -> None:
        for name, value in (("max_cloud_points", max_cloud_points),):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise InvalidInputError(f"{name} must be a positive integer, got {value!r}")
        for name, value in (("point_size", point_size), ("velocity_scale", velocity_scale),
                            ("force_scale", force_scale)):  # fmt: skip
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise InvalidInputError(f"{name} must be a finite number > 0, got {value!r}")
        if not isinstance(text_interval, (int, float)) or not text_interval >= 0:
            raise InvalidInputError(f"text_interval must be >= 0 [s], got {text_interval!r}")
        self.max_cloud_points = max_cloud_points
        self.point_size = float(point_size)
        self.velocity_scale = float(velocity_scale)
        self.force_scale = float(force_scale)
        self.text_interval = float(text_interval)
        for name, value in (("view_center", view_center), ("camera_offset", camera_offset)):
            arr = np.asarray(value, dtype=float) if np.ndim(value) == 1 else np.zeros(0)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise InvalidInputError(f"{name} must be 3 finite coordinates [m], got {value!r}")
        if np.linalg.norm(camera_offset) < 0.05:
            raise InvalidInputError(
                f"camera_offset must be at least 0.05 m from the view centre, got {camera_offset!r}"
            )
        self.view_center = tuple(float(x) for x in view_center)
        self.camera_offset = tuple(float(x) for x in camera_offset)
        vine_model = self._vine_model(vine)

        self._own_server = None
        if zmq_url is None:
            if server is None:
                server = ViewerServer(host, port, verbose=verbose)
                self._own_server = server
            zmq_url = server.zmq_url
        self.server = server
        try:
            self.connection = Connection(zmq_url, batch=server is not None)
            self.url = server.web_url if server is not None else self.connection.request(b"url").decode()
            self._setup_kinematics()
            self._state: dict[str, Any] = {}
            self._last_text_wall = -math.inf
            self._build_scene(vine_model, show_capsules)
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ set-up
    @staticmethod
    def _vine_model(vine: Any):
        if vine is None:
            return None
        import mujoco

        if isinstance(vine, mujoco.MjModel):
            return vine
        from harvest_qp.sim.scene import VineScene, VineSceneParams, build_vine_scene

        if isinstance(vine, VineScene):
            return vine.model
        if isinstance(vine, VineSceneParams):
            return build_vine_scene(vine).model
        raise InvalidInputError(
            f"vine must be a mujoco.MjModel, VineScene, VineSceneParams or None, got {type(vine).__name__}"
        )

    def _setup_kinematics(self) -> None:
        from harvest_qp.robot.paths import urdf_path

        self._model = pin.buildModelFromUrdf(str(urdf_path()))
        self._data = self._model.createData()
        self._meshes = robot_link_meshes()
        bodies = desc.collision_bodies()
        frames = [m.frame for m in self._meshes] + [t.name for t in desc.TOOLS.values()]
        frames += [b.link for b in bodies if b.link not in frames]
        self._frames = list(dict.fromkeys(frames))
        self._fids = [self._model.getFrameId(name) for name in self._frames]
        self._moving = [self._model.frames[f].parentJoint > 0 for f in self._fids]
        for name, fid in zip(self._frames, self._fids):
            if fid >= self._model.nframes:
                raise InvalidInputError(f"frame {name!r} is not in the robot model")
        tool_links = {desc.CAMERA_TOOL.name: desc.CAMERA_ARM, desc.GRASP_TOOL.name: desc.GRASP_ARM}
        self._tool_links = tool_links

    def frame_poses(self, q: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        """World poses (4, 4) of the frames that carry meshes and capsules, at ``q`` [rad]."""
        pin.framesForwardKinematics(self._model, self._data, np.asarray(q, dtype=float))
        return {name: self._data.oMf[fid].homogeneous for name, fid in zip(self._frames, self._fids)}

    def _build_scene(self, vine_model, show_capsules: bool) -> None:
        b = Batch()
        b.delete(ROOT)
        # meshcat's orbit camera looks at its origin: put the scene's centre there.
        b.transform(ROOT, translation(-np.asarray(self.view_center)))
        b.property("/Grid", "visible", False)
        b.property("/Axes", "visible", False)
        b.property("/Background", "top_color", [0.22, 0.23, 0.25])
        b.property("/Background", "bottom_color", [0.09, 0.09, 0.10])
        d = np.asarray(self.camera_offset)
        # The camera node is turned by Rx(90 deg) (three.js is y-up): world (x, y, z) = (x, -z, y).
        b.property("/Cameras/default/rotated/<object>", "position", [float(d[0]), float(d[2]), float(-d[1])])
        b.object(f"{ROOT}/floor", mesh_object(mg.Box([4.0, 4.0, 0.01]), COLORS["floor"]))
        b.transform(f"{ROOT}/floor", translation([0.5, 0.0, -0.005]))

        # robot: meshes under robot/<frame>, capsules under capsules/<frame> (one toggle)
        for mesh in self._meshes:
            path = f"{ROOT}/robot/{mesh.frame}/mesh"
            b.object(path, stl_object(mesh.path, COLORS["robot"]))
            b.transform(path, mesh.origin)
        for body in desc.collision_bodies():
            tool = body.link in self._tool_links
            color = COLORS["tool"] if tool else COLORS["stand"] if body.arm == "" else COLORS["capsule"]
            group = "robot" if tool or body.arm == "" else "capsules"
            self._capsule(b, f"{ROOT}/{group}/{body.link}/{body.name}", body.capsule, color,
                          opacity=1.0 if group == "robot" else 0.45)  # fmt: skip
        b.property(f"{ROOT}/capsules", "visible", bool(show_capsules))
        self._state["capsules"] = bool(show_capsules)

        # vine, one node per MuJoCo body so moving bodies can be updated
        self._vine_bodies: list[str] = []
        if vine_model is not None:
            poses = vine_body_poses(vine_model)
            for geom in vine_geoms(vine_model):
                self._vine_geom(b, geom)
            for body, T in poses.items():
                b.transform(f"{ROOT}/vine/{body}", T)
            self._vine_bodies = sorted(poses)

        self._build_markers(b)
        self._draw_robot(b, np.array(desc.HOME_Q))
        self.connection.send(b.messages)

    def _capsule(self, b: Batch, path: str, capsule, color: int, *, opacity: float = 1.0) -> None:
        p0, p1 = np.asarray(capsule.p0, float), np.asarray(capsule.p1, float)
        r = float(capsule.radius)
        length = float(np.linalg.norm(p1 - p0))
        if length > 1e-9:
            b.object(f"{path}/cyl", mesh_object(mg.Cylinder(length, r), color, opacity=opacity))
            T = np.eye(4)
            T[:3, :3] = y_to(p1 - p0)
            T[:3, 3] = 0.5 * (p0 + p1)
            b.transform(f"{path}/cyl", T)
        for k, p in enumerate((p0, p1)):
            b.object(f"{path}/end{k}", mesh_object(mg.Sphere(r), color, opacity=opacity))
            b.transform(f"{path}/end{k}", translation(p))

    def _vine_geom(self, b: Batch, geom: VineGeom) -> None:
        path = f"{ROOT}/vine/{geom.body}/{geom.name}"
        color = rgba_int(geom.rgba)
        if geom.kind == "capsule":
            r, half = geom.size
            # MuJoCo capsules run along local z, meshcat cylinders along y: turn by Rx(90 deg).
            turn = np.eye(4)
            turn[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
            b.object(f"{path}/cyl", mesh_object(mg.Cylinder(2 * half, r), color))
            b.transform(f"{path}/cyl", geom.local @ turn)
            for k, z in enumerate((-half, half)):
                b.object(f"{path}/end{k}", mesh_object(mg.Sphere(r), color))
                b.transform(f"{path}/end{k}", geom.local @ translation([0.0, 0.0, z]))
        elif geom.kind == "sphere":
            b.object(path, mesh_object(mg.Sphere(geom.size[0]), color))
            b.transform(path, geom.local)
        else:
            b.object(path, mesh_object(mg.Ellipsoid(list(geom.size)), color))
            b.transform(path, geom.local)

    def _build_markers(self, b: Batch) -> None:
        m = f"{ROOT}/markers"
        # Objects sit one level below the node that moves: meshcat's exported HTML does not
        # animate a node that carries an object itself (measured in headless Chromium).
        b.object(f"{m}/roi/shape", mesh_object(mg.Sphere(1.0), COLORS["roi"], opacity=0.15))
        for name, radius in (("p_r", 0.012), ("p_sb", 0.01), ("p_gd", 0.012)):
            b.object(f"{m}/{name}/shape", mesh_object(mg.Sphere(radius), COLORS[name]))
        for k in range(4):
            self._unit_rod(b, f"{m}/stem_segment_{k}", 0.004, COLORS["stem_segment"])
        self._unit_rod(b, f"{m}/closest_pair/line", 0.003, COLORS["closest_pair"])
        for k in range(2):
            b.object(f"{m}/closest_pair/end{k}/shape", mesh_object(mg.Sphere(0.008), COLORS["closest_pair"]))
        for name in ("v_c", "v_g", "force"):
            self._unit_rod(b, f"{m}/{name}/shaft", 0.006, COLORS[name])
            b.object(f"{m}/{name}/head/cone", mesh_object(mg.Cylinder(0.04, radiusTop=0.0, radiusBottom=0.016),
                                                           COLORS[name]))  # fmt: skip
            b.transform(f"{m}/{name}/head/cone", translation([0.0, 0.02, 0.0]))
        # camera frustum in {C}: z forward, x right, y down; 40 deg vertical fov, 16:9, 0.3 m deep
        depth, tan_v = 0.3, math.tan(math.radians(20.0))
        hx, hy = depth * tan_v * 848 / 480, depth * tan_v
        corners = np.array([[-hx, -hy, depth], [hx, -hy, depth], [hx, hy, depth], [-hx, hy, depth]])
        segments = []
        for k in range(4):
            segments += [np.zeros(3), corners[k], corners[k], corners[(k + 1) % 4]]
        frustum = mg.LineSegments(mg.PointsGeometry(np.array(segments, np.float32).T),
                                  mg.LineBasicMaterial(color=COLORS["frustum"]))  # fmt: skip
        b.object(f"{m}/frustum/shape", frustum.lower())
        for name in self.MARKERS:
            b.property(f"{m}/{name}", "visible", False)
        b.property(f"{ROOT}/text", "visible", False)
        for _, label in _CLOUD_LABELS:
            b.property(f"{ROOT}/cloud/{label}", "visible", False)

    MARKERS = ("roi", "p_r", "p_sb", "p_gd", "stem_segment_0", "stem_segment_1", "stem_segment_2",
               "stem_segment_3", "closest_pair", "v_c", "v_g", "force", "frustum", "samples_kept",
               "samples_removed")  # fmt: skip

    @staticmethod
    def _unit_rod(b: Batch, path: str, radius: float, color: int) -> None:
        """A cylinder from y = 0 to y = 1 under ``path`` (scale the node along y to a length)."""
        b.object(f"{path}/rod", mesh_object(mg.Cylinder(1.0, radius), color))
        b.transform(f"{path}/rod", translation([0.0, 0.5, 0.0]))

    # ------------------------------------------------------------------ drawing
    def _draw_robot(self, b: Batch, q: NDArray[np.float64]) -> dict[str, NDArray[np.float64]]:
        poses = self.frame_poses(q)
        # Hidden capsules are not moved (half the robot's commands); showing them sends all.
        capsules = self._state.get("capsules", False) or self._state.get("animating", False)
        first = "robot_static" not in self._state
        for name, moving in zip(self._frames, self._moving):
            if moving or first:
                b.transform(f"{ROOT}/robot/{name}", poses[name])
                if capsules or first:
                    b.transform(f"{ROOT}/capsules/{name}", poses[name])
        self._state["robot_static"] = True
        self._state["q"] = np.array(q, dtype=float)
        return poses

    def _visible(self, b: Batch, path: str, visible: bool) -> None:
        key = "visible:" + path
        if self._state.get(key) != visible:
            b.property(path, "visible", visible)
            self._state[key] = visible

    def _arrow(self, b: Batch, name: str, origin: NDArray[np.float64] | None, vector: NDArray[np.float64] | None,
               scale: float) -> None:  # fmt: skip
        path = f"{ROOT}/markers/{name}"
        if origin is None or vector is None or not np.all(np.isfinite(vector)):
            self._visible(b, path, False)
            return
        length = float(np.linalg.norm(vector)) * scale
        if length < 1e-4:
            self._visible(b, path, False)
            return
        head = min(0.04, 0.5 * length)
        R = y_to(np.asarray(vector, float))
        shaft = np.eye(4)
        shaft[:3, :3] = R * np.array([1.0, max(length - head, 1e-6), 1.0])
        shaft[:3, 3] = origin
        b.transform(f"{path}/shaft", shaft)
        tip = np.eye(4)
        tip[:3, :3] = R * np.array([1.0, head / 0.04, 1.0])
        tip[:3, 3] = origin + R[:, 1] * (length - head)
        b.transform(f"{path}/head", tip)
        self._visible(b, path, True)

    def _point(self, b: Batch, name: str, p: NDArray[np.float64] | None, scale: float = 1.0) -> None:
        path = f"{ROOT}/markers/{name}"
        if p is None:
            self._visible(b, path, False)
            return
        b.transform(path, translation(p, scale))
        self._visible(b, path, True)

    def _changed(self, key: str, value: Any) -> bool:
        if self._state.get(key, object()) is value:
            return False
        self._state[key] = value
        return True

    def _points(self, b: Batch, path: str, points: NDArray[np.floating] | None, color: int, key: Any) -> None:
        if points is None or len(points) == 0:
            self._visible(b, path, False)
            return
        if self._changed("points:" + path, key):
            stride = max(1, int(math.ceil(len(points) / self.max_cloud_points)))
            b.object(f"{path}/shape", points_object(np.asarray(points)[::stride], color, self.point_size))
        self._visible(b, path, True)

    def draw(self, frame: ViewerFrame, *, wall_time: float | None = None) -> int:
        """Draw one frame (one batch of commands); returns the number of commands sent.

        Args:
            frame: what to draw.
            wall_time: current wall time [s] for the text panel's rate limit (None: always update).
        """
        if not isinstance(frame, ViewerFrame):
            raise InvalidInputError(f"frame must be a ViewerFrame, got {type(frame).__name__}")
        b = Batch()
        self.frame_commands(b, frame, wall_time=wall_time)
        self.connection.send(b.messages)
        return len(b.messages)

    def frame_commands(
        self, b: Batch, frame: ViewerFrame, *, wall_time: float | None = None, text: bool = True
    ) -> None:
        """Append the commands that draw ``frame`` to the batch ``b`` (see :meth:`draw`)."""
        poses = self._draw_robot(b, frame.q)
        if frame.body_poses:
            for body, T in frame.body_poses.items():
                if body in self._vine_bodies:
                    b.transform(f"{ROOT}/vine/{body}", np.asarray(T, float))
        # point cloud, one object per label, re-sent only when the cloud changes
        if frame.cloud_points is not None:
            key = frame.cloud_key if frame.cloud_key is not None else id(frame.cloud_points)
            if self._changed("cloud", key):
                labels = np.asarray(frame.cloud_labels)
                stride = max(1, int(math.ceil(len(labels) / self.max_cloud_points)))
                pts = np.asarray(frame.cloud_points)[::stride]
                lab = labels[::stride]
                for value, name in _CLOUD_LABELS:
                    b.object(f"{ROOT}/cloud/{name}", points_object(pts[lab == value], COLORS[f"cloud_{name}"],
                                                                   self.point_size))  # fmt: skip
            for _, name in _CLOUD_LABELS:
                self._visible(b, f"{ROOT}/cloud/{name}", True)
        else:
            for _, name in _CLOUD_LABELS:
                self._visible(b, f"{ROOT}/cloud/{name}", False)
        m = f"{ROOT}/markers"
        self._points(b, f"{m}/samples_kept", frame.samples_kept, COLORS["samples_kept"], id(frame.samples_kept))
        self._points(b, f"{m}/samples_removed", frame.samples_removed, COLORS["samples_removed"],
                     id(frame.samples_removed))  # fmt: skip
        radius = frame.roi_radius if frame.roi_radius is not None and frame.roi_radius > 0 else None
        self._point(b, "roi", frame.roi_center if radius else None, radius or 1.0)
        for name in ("p_r", "p_sb", "p_gd"):
            self._point(b, name, getattr(frame, name))
        segments = frame.stem_segments if frame.stem_segments is not None else np.zeros((0, 2, 3))
        for k in range(4):
            path = f"{m}/stem_segment_{k}"
            if k < len(segments) and np.all(np.isfinite(segments[k])):
                b.transform(path, segment_transform(segments[k, 0], segments[k, 1]))
                self._visible(b, path, True)
            else:
                self._visible(b, path, False)
        pair = frame.closest_pair
        if pair is not None and np.all(np.isfinite(pair)):
            b.transform(f"{m}/closest_pair/line", segment_transform(pair[0], pair[1]))
            b.transform(f"{m}/closest_pair/end0", translation(pair[0]))
            b.transform(f"{m}/closest_pair/end1", translation(pair[1]))
            self._visible(b, f"{m}/closest_pair", True)
        else:
            self._visible(b, f"{m}/closest_pair", False)
        camera = poses["camera"] if "camera" in poses else self._frame_world("camera")
        gripper = self._frame_world("gripper")
        self._arrow(b, "v_c", camera[:3, 3] if frame.p_c is None else frame.p_c, frame.v_c, self.velocity_scale)
        self._arrow(b, "v_g", gripper[:3, 3], frame.v_g, self.velocity_scale)
        self._arrow(b, "force", gripper[:3, 3], frame.force, self.force_scale)
        if frame.camera_pose is not None:
            b.transform(f"{m}/frustum", frame.camera_pose)
            self._visible(b, f"{m}/frustum", True)
        else:
            self._visible(b, f"{m}/frustum", False)
        if text:
            self._text(b, frame, wall_time)

    def _frame_world(self, name: str) -> NDArray[np.float64]:
        return self._data.oMf[self._model.getFrameId(name)].homogeneous

    # ------------------------------------------------------------------ text panel
    def _text_transform(self, lines: int) -> NDArray[np.float64]:
        """Panel pose: facing the default camera, halfway to it, in the upper left of its view."""
        d = np.asarray(self.camera_offset, float)
        forward = -d / np.linalg.norm(d)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        distance = 0.5 * float(np.linalg.norm(d))
        half_h = distance * math.tan(math.radians(CAMERA_FOVY / 2))
        T = np.eye(4)
        T[:3, :3] = np.column_stack([right, up, -forward]) * (0.9 * half_h / _PANEL_WIDTH)
        T[:3, 3] = np.asarray(self.view_center) + 0.5 * d - 1.15 * half_h * right + 0.62 * half_h * up
        return T

    def _text(self, b: Batch, frame: ViewerFrame, wall_time: float | None) -> None:
        lines = frame.text_lines()
        if lines == self._state.get("text"):
            return
        if wall_time is not None and wall_time - self._last_text_wall < self.text_interval:
            return
        self._last_text_wall = wall_time if wall_time is not None else -math.inf
        self._state["text"] = lines
        b.object(f"{ROOT}/text", self._text_object(lines))
        if "text_pose" not in self._state:
            b.transform(f"{ROOT}/text", self._text_transform(len(lines)))
            self._state["text_pose"] = True
        self._visible(b, f"{ROOT}/text", True)

    @staticmethod
    def _text_object(lines: Sequence[str], compress_level: int = 0) -> dict:
        png = render_text_png(lines, compress_level=compress_level)
        w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")  # PNG IHDR
        width = _PANEL_WIDTH
        texture = mg.ImageTexture(mg.PngImage(png))
        return mesh_object(mg.Box([width, width * h / w, 0.002]), 0xFFFFFF, basic=True, texture=texture)

    # ------------------------------------------------------------------ controls
    def set_capsules_visible(self, visible: bool) -> None:
        """Show or hide the robot's collision capsules (the links keep their meshes)."""
        b = Batch()
        self._state["capsules"] = bool(visible)
        if visible and "q" in self._state:
            poses = self.frame_poses(self._state["q"])
            for name in self._frames:
                b.transform(f"{ROOT}/capsules/{name}", poses[name])
        b.property(f"{ROOT}/capsules", "visible", bool(visible))
        self.connection.send(b.messages)

    def static_html(self) -> str:
        """The current scene (and animation) as one self-contained HTML page."""
        return self.connection.request(b"get_scene").decode("utf-8")

    def export_html(self, path: str | Path) -> Path:
        """Write :meth:`static_html` to ``path`` (opens offline in any browser); returns the path."""
        path = Path(path)
        if path.suffix.lower() not in (".html", ".htm"):
            raise InvalidInputError(f"export_html path must end in .html, got {str(path)!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(self.static_html(), encoding="utf-8")
        return path

    # ------------------------------------------------------------------ animation
    def load_animation(
        self,
        frames: Sequence[ViewerFrame],
        *,
        play: bool = True,
        repetitions: int = 1,
        cloud_interval: float = 0.2,
        text_interval: float = 0.1,
        max_cloud_points: int = 3000,
    ) -> None:
        """Load ``frames`` as a meshcat animation (time slider and play button in the viewer).

        Transforms are animated; meshcat cannot animate geometry, so point clouds and text
        panels become snapshots (at most one per ``cloud_interval`` / ``text_interval``
        seconds of episode time, clouds thinned to ``max_cloud_points``) switched on and off
        by the animation. Showing and hiding is animated as a scale of 1 or 1e-6: meshcat's
        ``visible`` tracks stop working in exported HTML once a node's visibility was set as
        a property (measured in headless Chromium), and the viewer sets it for every marker.
        A paused scene shows the first frame; a playing one starts as soon as the page has
        the animation (possibly before every mesh is loaded: use the viewer's Animations
        menu, reset and play, to watch again).

        Args:
            frames: the frames, in time order (e.g. :func:`frames_from_log`).
            play: start playing when the page opens.
            repetitions: times to play.
            cloud_interval, text_interval: episode time between snapshots [s].
            max_cloud_points: points per cloud snapshot at most.
        """
        if not frames:
            raise InvalidInputError("load_animation needs at least one frame, got none")
        times = np.array([f.time for f in frames], float)
        if np.any(np.diff(times) < 0):
            raise InvalidInputError("frames must be in time order")
        t0 = float(times[0])
        # path -> list of (time, own transform, shown); transforms and visibility carried forward
        history: dict[str, list[tuple[float, NDArray[np.float64], bool]]] = {}
        current: dict[str, list[Any]] = {}

        b = Batch()
        b.delete(f"{ROOT}/replay")
        # Forget the visibility sent so far so the first frame states every marker's.
        self._state = {k: v for k, v in self._state.items() if not k.startswith("visible:")}
        self._state["animating"] = True  # capsule poses too, so the toggle works in the replay
        cloud_snaps: list[tuple[float, str, NDArray[np.float64]]] = []
        text_snaps: list[tuple[float, str, NDArray[np.float64]]] = []
        last_cloud_key, last_cloud_t, last_text, last_text_t = object(), -math.inf, None, -math.inf
        try:
            for frame in frames:
                fb = Batch()
                self.frame_commands(fb, _without_geometry(frame), wall_time=None, text=False)
                for command, path, data in fb.messages:
                    p = path.decode()
                    entry = current.setdefault(p, [np.eye(4), True])
                    if command == b"set_transform":
                        entry[0] = np.array(umsgpack.unpackb(data)["matrix"], float).reshape(4, 4).T
                    elif command == b"set_property":
                        msg = umsgpack.unpackb(data)
                        if msg["property"] == "visible":
                            entry[1] = bool(msg["value"])
                for p, (M, shown) in current.items():
                    history.setdefault(p, []).append((frame.time, M, shown))
                if frame.cloud_points is not None:
                    ck = frame.cloud_key if frame.cloud_key is not None else id(frame.cloud_points)
                    if ck != last_cloud_key and frame.time - last_cloud_t >= cloud_interval - 1e-9:
                        last_cloud_key, last_cloud_t = ck, frame.time
                        path = f"{ROOT}/replay/cloud_{len(cloud_snaps)}"
                        labels = np.asarray(frame.cloud_labels)
                        stride = max(1, int(math.ceil(len(labels) / max_cloud_points)))
                        pts, lab = np.asarray(frame.cloud_points)[::stride], labels[::stride]
                        for value, name in _CLOUD_LABELS:
                            b.object(f"{path}/{name}", points_object(pts[lab == value], COLORS[f"cloud_{name}"],
                                                                      self.point_size))  # fmt: skip
                        cloud_snaps.append((frame.time, path, np.eye(4)))
                lines = frame.text_lines()
                if lines != last_text and frame.time - last_text_t >= text_interval - 1e-9:
                    last_text, last_text_t = lines, frame.time
                    path = f"{ROOT}/replay/text_{len(text_snaps)}"
                    b.object(f"{path}/panel", self._text_object(lines, compress_level=6))
                    text_snaps.append((frame.time, path, self._text_transform(len(lines))))
        finally:
            self._state["animating"] = False
        for snaps in (cloud_snaps, text_snaps):
            for j, (t, path, M) in enumerate(snaps):
                entries = [(t0, M, j == 0)]
                if j > 0:
                    entries.append((t, M, True))
                if j + 1 < len(snaps):
                    entries.append((snaps[j + 1][0], M, False))
                history[path] = entries
        b.property(f"{ROOT}/text", "visible", False)
        for _, name in _CLOUD_LABELS:
            b.property(f"{ROOT}/cloud/{name}", "visible", False)

        animations = []
        for path, entries in history.items():
            hides = any(not shown for _, _, shown in entries)
            moves = any(not np.array_equal(M, entries[0][1]) for _, M, _ in entries)
            if not hides and not moves:
                continue
            keys: dict[str, list[dict]] = {"position": [], "quaternion": [], "scale": []}
            previous = None
            for t, M, shown in entries:
                if previous is not None and previous[2] != shown:
                    # a key just before the switch keeps showing/hiding discrete
                    _transform_keys(keys, previous[1], previous[2], max(t - t0 - 1e-4, previous[0] - t0))
                _transform_keys(keys, M, shown, t - t0)
                previous = (t, M, shown)
            # A paused page shows the first key. A playing one must not get static transforms: the
            # exported HTML applies its commands asynchronously (fetch of data URLs), and a static
            # transform applied after a short animation has finished would undo its last frame.
            if not play:
                first = entries[0]
                b.transform(path, _scaled(first[1], first[2]))
            b.property(path, "visible", True)
            tracks = [{"name": "." + prop, "type": "quaternion" if prop == "quaternion" else "vector3",
                       "keys": _dedupe(k)} for prop, k in keys.items()]  # fmt: skip
            animations.append({"path": path, "clip": {"fps": 1, "name": "default", "tracks": tracks}})
        b.animation(animations, play=play, repetitions=repetitions)
        self._state = {k: v for k, v in self._state.items() if not k.startswith(("points:", "cloud", "visible:"))}
        self.connection.send(b.messages)

    def close(self) -> None:
        """Close the connection and, if this viewer started it, the server."""
        connection = getattr(self, "connection", None)
        if connection is not None:
            connection.close()
            self.connection = None
        if self._own_server is not None:
            self._own_server.close()
            self._own_server = None

    def __enter__(self) -> MeshcatViewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _without_geometry(frame: ViewerFrame) -> ViewerFrame:
    """A copy of ``frame`` without the parts drawn as geometry (cloud, samples)."""
    import dataclasses

    return dataclasses.replace(frame, cloud_points=None, cloud_labels=None, samples_kept=None,
                               samples_removed=None)  # fmt: skip


def _scaled(M: NDArray[np.float64], shown: bool) -> NDArray[np.float64]:
    """``M``, shrunk to 1e-6 of its size when hidden."""
    if shown:
        return M
    out = M.copy()
    out[:3, :3] *= 1e-6
    return out


def _transform_keys(keys: dict[str, list[dict]], M: NDArray[np.float64], shown: bool, t: float) -> None:
    """Animation keys (position, quaternion as x y z w, scale) of a transform at time ``t`` [s]."""
    scale = np.linalg.norm(M[:3, :3], axis=0)
    R = M[:3, :3] / np.where(scale > 0, scale, 1.0)
    quat = pin.Quaternion(R)
    keys["position"].append({"time": float(t), "value": M[:3, 3].tolist()})
    keys["quaternion"].append({"time": float(t), "value": [quat.x, quat.y, quat.z, quat.w]})
    keys["scale"].append({"time": float(t), "value": (scale * (1.0 if shown else 1e-6)).tolist()})


def _dedupe(keys: list[dict]) -> list[dict]:
    """Drop keys equal to both neighbours (static nodes keep two keys)."""
    if len(keys) <= 2:
        return keys
    out = [keys[0]]
    for i in range(1, len(keys) - 1):
        if keys[i]["value"] != out[-1]["value"] or keys[i]["value"] != keys[i + 1]["value"]:
            out.append(keys[i])
    out.append(keys[-1])
    return out
