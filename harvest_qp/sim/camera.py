"""RGB-D camera on the camera arm, modelled on the RealSense D415 of the paper's lab.

The camera is a pinhole with square pixels at the *downsampled* resolution: the paper's
D415 streams 848x480 at 30 FPS and the point cloud is downsampled by 3, so the default
image is ``ceil(480/3) x ceil(848/3) = 160 x 283`` pixels with a vertical field of view
of 40 deg (65.6 deg horizontally, the D415's depth FOV of about 65 x 40 deg).

Two backends produce the same :class:`~harvest_qp.runtime.interface.PointCloud`:

* ``"raycast"`` (default): a ray from the optical centre through every pixel centre gives
  the distance and the geom hit per pixel: depth and segmentation in one pass, no OpenGL
  needed. The rays are cast by :func:`mujoco.mj_multiRay` (``raycast_engine="mujoco"``, the
  reference) or, by default when the model only has primitive geoms, by an equivalent
  numba kernel (``"numba"``) that gives the same hits ~25x faster;
* ``"opengl"``: MuJoCo's offscreen renderer (depth + segmentation passes, and the RGB pass
  when ``rendered_rgb``), available when ``MUJOCO_GL`` is set (``egl`` or ``osmesa``).

Each valid pixel becomes a world-frame point with a label from the geom it hit
(stem -> STEM, robot -> ROBOT, anything else -> OBSTACLE) and an RGB colour (the geom's
colour, or the rendered one). Pixels with no hit, or a depth outside
[``min_depth``, ``max_depth``], are dropped. Stem points farther than ``stem_range``
(0.7 m, where the paper's stem stops being reliably detectable) are kept but labelled
OBSTACLE, as in the paper ("any other points are obstacles"). The camera tool's own geoms
(the camera housing and the cutter) are never seen.

Options: depth noise (Gaussian, std ``depth_noise`` at 1 m, growing with depth squared as
a stereo camera's), pixel dropout, and latency (a frame captured at t is delivered at
t + latency).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import mujoco
import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.runtime.interface import OBSTACLE, STEM, PointCloud
from harvest_qp.sim import _raycast
from harvest_qp.validation import check_field_types

__all__ = ["DEFAULT_CAMERA", "CameraConfig", "DepthCamera", "RayCastCamera", "OpenGLCamera", "make_camera"]


@dataclass(frozen=True)
class CameraConfig:
    """RGB-D camera settings (defaults: the paper's D415 setup).

    Attributes:
        width, height: sensor resolution before downsampling [pixels].
        downsample: keep one pixel in ``downsample`` along each image axis.
        vertical_fov: vertical field of view [deg]; the horizontal one follows from
            square pixels (65.6 deg at 848x480).
        rate: frame rate [Hz].
        min_depth, max_depth: valid depth interval along the view direction [m].
        stem_range: stem points beyond this distance from the camera are labelled
            OBSTACLE [m] (paper: 0.7).
        depth_noise: depth noise std at 1 m depth [m]; it scales with depth^2.
        dropout: probability that a pixel returns no depth.
        latency: delay between capture and delivery [s].
        backend: ``"raycast"`` or ``"opengl"``.
        raycast_engine: ray caster of the ``"raycast"`` backend: ``"mujoco"``
            (``mj_multiRay``), ``"numba"`` (same hits, several times faster, primitive geoms
            only) or ``"auto"`` (numba when the model allows it).
        rendered_rgb: with ``"opengl"``, colour points from the rendered image instead of
            the geom colours (an extra render pass).
    """

    width: int = 848
    height: int = 480
    downsample: int = 3
    vertical_fov: float = 40.0
    rate: float = 30.0
    min_depth: float = 0.1
    max_depth: float = 2.0
    stem_range: float = 0.7
    depth_noise: float = 0.0
    dropout: float = 0.0
    latency: float = 0.0
    backend: str = "raycast"
    raycast_engine: str = "auto"
    rendered_rgb: bool = False

    def __post_init__(self) -> None:
        check_field_types(self)  # text, None or a list never reaches the range checks
        for name in ("width", "height", "downsample"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InvalidInputError(f"CameraConfig.{name} must be a positive integer, got {value!r}")
        if not 1.0 <= self.vertical_fov <= 170.0:
            raise InvalidInputError(f"CameraConfig.vertical_fov must be in [1, 170] deg, got {self.vertical_fov!r}")
        for name in ("rate", "max_depth", "stem_range"):
            value = getattr(self, name)
            if not np.isfinite(value) or value <= 0:
                raise InvalidInputError(f"CameraConfig.{name} must be finite and > 0, got {value!r}")
        for name in ("min_depth", "depth_noise", "latency"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0:
                raise InvalidInputError(f"CameraConfig.{name} must be finite and >= 0, got {value!r}")
        if self.min_depth >= self.max_depth:
            raise InvalidInputError(
                f"CameraConfig.min_depth ({self.min_depth} m) must be below max_depth ({self.max_depth} m)"
            )
        if not 0.0 <= self.dropout < 1.0:
            raise InvalidInputError(f"CameraConfig.dropout must be a probability in [0, 1), got {self.dropout!r}")
        if self.backend not in ("raycast", "opengl"):
            raise InvalidInputError(f"CameraConfig.backend must be 'raycast' or 'opengl', got {self.backend!r}")
        if self.raycast_engine not in ("auto", "numba", "mujoco"):
            raise InvalidInputError(
                f"CameraConfig.raycast_engine must be 'auto', 'numba' or 'mujoco', got {self.raycast_engine!r}"
            )

    @property
    def image_size(self) -> tuple[int, int]:
        """(height, width) of the downsampled image [pixels]."""
        return math.ceil(self.height / self.downsample), math.ceil(self.width / self.downsample)

    @property
    def horizontal_fov(self) -> float:
        """Horizontal field of view [deg] of the downsampled image."""
        h, w = self.image_size
        return math.degrees(2 * math.atan(math.tan(math.radians(self.vertical_fov) / 2) * w / h))

    def focal_length(self) -> float:
        """Focal length of the downsampled image [pixels]."""
        h, _ = self.image_size
        return (h / 2) / math.tan(math.radians(self.vertical_fov) / 2)

    def pixel_rays(self) -> NDArray[np.float64]:
        """(h * w, 3) unit ray directions in the camera frame {C}, row-major from the top-left pixel."""
        h, w = self.image_size
        f = self.focal_length()
        v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
        rays = np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u)], axis=-1).reshape(-1, 3)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)


#: The paper's camera: D415 at 848x480 downsampled by 3, 30 Hz, stem detected within 0.7 m.
DEFAULT_CAMERA = CameraConfig()


class DepthCamera:
    """Shared post-processing of both backends: validity, noise, dropout, labels, colours.

    Args:
        model: compiled model.
        config: camera settings.
        geom_labels: (ngeom,) label per geom (default: all OBSTACLE).
        exclude_body: body whose geoms the camera never sees (its own tool), -1 for none.
        seed: seed of the noise and dropout draws.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        config: CameraConfig,
        *,
        geom_labels: ArrayLike | None = None,
        exclude_body: int = -1,
        seed: int = 0,
    ) -> None:
        if not isinstance(model, mujoco.MjModel):
            raise InvalidInputError(f"model must be a mujoco.MjModel, got {model!r}")
        if not isinstance(config, CameraConfig):
            raise InvalidInputError(f"config must be a CameraConfig, got {config!r}")
        for name, value, low in (("exclude_body", exclude_body, -1), ("seed", seed, 0)):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidInputError(f"{name} must be an integer >= {low}, got {value!r}")
        self.model = model
        self.config = config
        labels = np.full(model.ngeom, OBSTACLE, np.int8) if geom_labels is None else np.asarray(geom_labels)
        if labels.shape != (model.ngeom,):
            raise InvalidInputError(f"geom_labels must have shape ({model.ngeom},), got {labels.shape}")
        self._labels = np.ascontiguousarray(labels, dtype=np.int8)
        self._colors = np.clip(np.round(model.geom_rgba[:, :3] * 255.0), 0, 255).astype(np.uint8)
        self.exclude_body = int(exclude_body)
        # The camera never sees its own tool (housing and cutter).
        self._geom_ok = np.asarray(model.geom_bodyid != self.exclude_body)
        self._rays_c = config.pixel_rays()
        self._ray_x = self._rays_c[:, 0].copy()
        self._ray_y = self._rays_c[:, 1].copy()
        self._ray_z = self._rays_c[:, 2].copy()
        self._no_bool = np.zeros(0, np.bool_)
        self._no_float = np.zeros(0)
        self._no_color = np.zeros((0, 3), np.uint8)
        self._seed = int(seed)
        self._rng = np.random.default_rng([self._seed, 0xCA3])

    def reset(self, *, seed: int | None = None) -> None:
        """Restart the noise sequence (optionally with a new seed)."""
        if seed is not None:
            self._seed = int(seed)
        self._rng = np.random.default_rng([self._seed, 0xCA3])

    @property
    def n_pixels(self) -> int:
        return int(self._rays_c.shape[0])

    def _frame_arrays(self, n: int) -> tuple:
        """The frame's dropout mask and depth noise, and the output buffers of the compaction.

        The random numbers are drawn for every pixel whatever the scene, so the noise
        sequence only depends on the seed and the frame count.
        """
        cfg = self.config
        keep = self._rng.random(n) >= cfg.dropout if cfg.dropout > 0 else self._no_bool
        noise = self._rng.standard_normal(n) if cfg.depth_noise > 0 else self._no_float
        buffers = (np.empty((n, 3)), np.empty(n, np.int8), np.empty((n, 3), np.uint8), np.empty(n),
                   np.empty((n, 2), np.int32))
        return keep, noise, buffers

    def _cloud(self, pose, timestamp, count, points, labels, rgb, z, pixels) -> PointCloud:
        """The first ``count`` compacted points as the frame's :class:`PointCloud`."""
        return PointCloud(
            points=points[:count],
            labels=labels[:count],
            colors=rgb[:count],
            camera_pose=np.array(pose, dtype=float),
            timestamp=float(timestamp),
            depth=z[:count],
            pixels=pixels[:count],
            image_size=self.config.image_size,
        )

    def _finish(
        self,
        pose: NDArray[np.float64],
        depth: NDArray[np.float64],
        geom: NDArray[np.int32],
        timestamp: float,
        *,
        along_ray: bool = False,
        colors: NDArray[np.uint8] | None = None,
    ) -> PointCloud:
        """Turn per-pixel z-depth (or ray length, ``along_ray``) [m] and geom id (-1: none) into a
        labelled world cloud."""
        cfg = self.config
        keep, noise, (points, labels, rgb, z, pixels) = self._frame_arrays(depth.shape[0])
        h, w = cfg.image_size
        count = _raycast.compact_cloud(
            depth, along_ray, geom, self._ray_x, self._ray_y, self._ray_z, np.ascontiguousarray(pose[:3, :3]),
            np.ascontiguousarray(pose[:3, 3]), cfg.min_depth, cfg.max_depth, cfg.stem_range, noise, cfg.depth_noise,
            keep, self._geom_ok, self._labels, self._colors, self._no_color if colors is None else colors, STEM,
            OBSTACLE, points, labels, rgb, z, pixels, h, w,
        )  # fmt: skip
        return self._cloud(pose, timestamp, count, points, labels, rgb, z, pixels)

    def capture(self, data: mujoco.MjData, pose: NDArray[np.float64], timestamp: float) -> PointCloud:
        """Capture a frame from camera ``pose`` (4x4, {C} in the world) in the current ``data`` state."""
        raise NotImplementedError


class RayCastCamera(DepthCamera):
    """Depth camera by ray casting (no OpenGL).

    ``config.raycast_engine`` picks the caster: ``"mujoco"`` is one :func:`mujoco.mj_multiRay`
    call per frame (the reference); ``"numba"`` is a kernel giving the same hits (to 1e-9 m:
    a test holds it to ``mj_multiRay``) ~25x faster by culling geoms per image row (bounding
    spheres and each geom's quadric) and intersecting spheres, ellipsoids and capsules a row
    span at a time in vectorised loops (:mod:`harvest_qp.sim._raycast`, primitive geoms
    only); ``"auto"``
    uses the kernel when the model allows it.
    """

    def __init__(self, model: mujoco.MjModel, config: CameraConfig, **kwargs) -> None:
        super().__init__(model, config, **kwargs)
        n = self.n_pixels
        self._geomid = np.zeros(n, np.int32)
        self._dist = np.zeros(n, np.float64)
        # Rays longer than this cannot give a valid depth (corner rays are the longest).
        self._cutoff = config.max_depth / float(self._ray_z.min())
        engine = config.raycast_engine
        if engine == "auto":
            engine = "numba" if _raycast.supports_model(model) else "mujoco"
        elif engine == "numba" and not _raycast.supports_model(model):
            raise ModelError(
                "the numba ray caster only handles plane, sphere, capsule, ellipsoid, cylinder and box "
                "geoms; use raycast_engine='mujoco' for this model"
            )
        self.engine = engine
        # Same geoms as mj_multiRay with flg_static=1: all but transparent geoms, those of the
        # excluded body and visual-only ones (group 2 without contacts, e.g. UR5e meshes
        # drawn over the collision capsules).
        visual = _raycast.visual_only_geoms(model)
        self._mask = (model.geom_rgba[:, 3] != 0) & (model.geom_bodyid != self.exclude_body) & ~visual
        # mj_multiRay filters by group: leave group 2 out when it only holds visual-only geoms.
        self._geomgroup = None
        in_group = np.asarray(model.geom_group) == _raycast.VISUAL_GROUP
        if visual.any() and np.array_equal(in_group, visual):
            self._geomgroup = np.ones(6, np.uint8)
            self._geomgroup[_raycast.VISUAL_GROUP] = 0
        elif visual.any() and engine == "mujoco":
            raise ModelError(
                "mj_multiRay cannot leave out the visual-only geoms: geom group 2 also holds geoms with "
                "contacts; move those to another group or use raycast_engine='numba'"
            )
        self._geom_type = model.geom_type.astype(np.int64)
        h, w = config.image_size
        self._hw = (h, w)
        self._focal = config.focal_length()

    def cast(self, data: mujoco.MjData, pose: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
        """Per-pixel ray length [m] (-1: no hit) and geom id (-1: none) from camera ``pose``."""
        origin = np.ascontiguousarray(pose[:3, 3])
        if self.engine == "numba":
            h, w = self._hw
            _raycast.cast_rays(
                h, w, self._focal, origin, np.ascontiguousarray(pose[:3, :3]),
                self._geom_type, self.model.geom_size, data.geom_xpos, data.geom_xmat,
                self.model.geom_rbound, self._mask, self._cutoff, self._geomid, self._dist,
                self._ray_x, self._ray_y, self._ray_z,
            )  # fmt: skip
        else:
            vec = np.ascontiguousarray(self._rays_c @ pose[:3, :3].T).ravel()
            mujoco.mj_multiRay(
                self.model, data, origin, vec, self._geomgroup, 1, self.exclude_body, self._geomid, self._dist, None,
                self.n_pixels, self._cutoff,
            )  # fmt: skip
        return self._dist, self._geomid

    def capture(self, data: mujoco.MjData, pose: NDArray[np.float64], timestamp: float) -> PointCloud:
        pose = np.asarray(pose, dtype=float)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise InvalidInputError(f"pose must be a finite 4x4 transform, got shape {pose.shape}")
        dist, geomid = self.cast(data, pose)
        return self._finish(pose, dist, geomid, timestamp, along_ray=True)


class OpenGLCamera(DepthCamera):
    """Depth camera by MuJoCo's OpenGL renderer (needs ``MUJOCO_GL=egl`` or ``osmesa``).

    Args:
        camera: name of the MuJoCo camera at the optical frame (MuJoCo convention: looks
            along -z, y up), whose pose must equal the ``pose`` passed to :meth:`capture`.
    """

    def __init__(self, model: mujoco.MjModel, config: CameraConfig, *, camera: str, **kwargs) -> None:
        super().__init__(model, config, **kwargs)
        if not os.environ.get("MUJOCO_GL"):
            raise ModelError("the OpenGL camera needs MUJOCO_GL set (egl or osmesa) before mujoco is imported")
        h, w = config.image_size
        try:
            self._camera_id = model.camera(camera).id
        except KeyError as error:
            raise ModelError(f"no camera named {camera!r} in the model") from error
        if model.vis.global_.offwidth < w or model.vis.global_.offheight < h:
            raise ModelError(
                f"the model's offscreen buffer {model.vis.global_.offwidth}x{model.vis.global_.offheight} "
                f"is smaller than the image {w}x{h}; raise <visual><global offwidth/offheight>"
            )
        # The MuJoCo camera must have the same field of view as the configuration.
        model.cam_fovy[self._camera_id] = config.vertical_fov
        try:
            self._renderer = mujoco.Renderer(model, height=h, width=w)
        except Exception as error:  # no GL context available
            raise ModelError(
                f"cannot create an OpenGL renderer (MUJOCO_GL={os.environ.get('MUJOCO_GL')}): {error}"
            ) from error
        self._option = mujoco.MjvOption()
        self._option.geomgroup[:] = 1  # the robot's geoms are in group 3
        # Visual-only geoms (group 2 without contacts, e.g. UR5e meshes) are not seen, as by
        # the ray caster; a group 2 that also holds geoms with contacts stays drawn.
        visual = _raycast.visual_only_geoms(model)
        if visual.any() and np.array_equal(np.asarray(model.geom_group) == _raycast.VISUAL_GROUP, visual):
            self._option.geomgroup[_raycast.VISUAL_GROUP] = 0
        self._option.sitegroup[:] = 0

    def close(self) -> None:
        """Free the OpenGL context."""
        self._renderer.close()

    def capture(self, data: mujoco.MjData, pose: NDArray[np.float64], timestamp: float) -> PointCloud:
        r = self._renderer
        r.update_scene(data, camera=self._camera_id, scene_option=self._option)
        r.enable_depth_rendering()
        depth = r.render().astype(np.float64).ravel()
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        seg = r.render()
        r.disable_segmentation_rendering()
        geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1).ravel().astype(np.int32)
        colors = None
        if self.config.rendered_rgb:
            colors = r.render().reshape(-1, 3)
        return self._finish(np.asarray(pose, dtype=float), depth, geom, timestamp, colors=colors)


def make_camera(
    model: mujoco.MjModel,
    config: CameraConfig,
    *,
    geom_labels: ArrayLike | None = None,
    exclude_body: int = -1,
    camera: str | None = None,
    seed: int = 0,
) -> DepthCamera:
    """The camera backend named by ``config.backend``."""
    if config.backend == "opengl":
        if camera is None:
            raise InvalidInputError("the OpenGL camera needs the name of a MuJoCo camera")
        return OpenGLCamera(model, config, camera=camera, geom_labels=geom_labels, exclude_body=exclude_body, seed=seed)
    return RayCastCamera(model, config, geom_labels=geom_labels, exclude_body=exclude_body, seed=seed)
