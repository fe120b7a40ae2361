"""Synthetic stem scenes with known ground truth, for tests, benchmarks and demos.

* :func:`bent_stem` samples a two-segment stem with a known base.
* :func:`render_scene` ray-casts a vine-like scene (bent stem, branch, berries, leaves,
  background) from a pinhole depth camera, giving a point cloud with the density,
  occlusions and stem labels of a real frame (D415-like field of view).
* :class:`LabViews` renders frames of the MuJoCo lab (:mod:`harvest_qp.sim`) from chosen
  camera poses and gives their ground truth (stem axis and base, the stem length between
  the branch and where it enters the gripper or cluster, the distance from any point to the
  nearest non-stem surface).  :mod:`harvest_qp.sim` is imported only when it is used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import ModelError
from harvest_qp.perception._validation import as_point, positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = ["LabFrame", "LabViews", "RenderedScene", "VineScene", "bent_stem", "look_at", "render_scene", "view_poses"]


def _unit(vector: ArrayLike) -> NDArray[np.float64]:
    vector = np.asarray(vector, dtype=np.float64)
    return vector / np.linalg.norm(vector)


def bent_stem(
    base: ArrayLike,
    top_direction: ArrayLike,
    bottom_direction: ArrayLike,
    top_length: float,
    bottom_length: float,
    *,
    n_points: int = 400,
    radius: float = 0.0015,
    noise: float = 0.001,
    rng: np.random.Generator | None = None,
) -> NDArray[np.float64]:
    """Points on a bent stem: two cylinders joined at the bend, with Gaussian noise.

    The stem starts at ``base`` [m], runs ``top_length`` [m] along ``top_direction`` to the
    bend, then ``bottom_length`` [m] along ``bottom_direction``.  Points are spread uniformly
    along the axis, on the cylinder surface of ``radius`` [m], plus isotropic Gaussian noise
    of standard deviation ``noise`` [m].  Returns ``(n_points, 3)``.
    """
    base = as_point("base", base)
    top_axis, bottom_axis = _unit(top_direction), _unit(bottom_direction)
    top_length = as_positive_scalar(top_length, "top_length")
    bottom_length = as_positive_scalar(bottom_length, "bottom_length")
    n_points = positive_int("n_points", n_points)
    rng = np.random.default_rng() if rng is None else rng
    arc = rng.uniform(0.0, top_length + bottom_length, n_points)
    on_top = arc < top_length
    bend = base + top_length * top_axis
    axis_points = np.where(
        on_top[:, None], base + arc[:, None] * top_axis, bend + (arc - top_length)[:, None] * bottom_axis
    )
    axes = np.where(on_top[:, None], top_axis, bottom_axis)
    # A random unit vector perpendicular to each point's axis puts it on the cylinder surface.
    radial = rng.normal(size=(n_points, 3))
    radial -= np.einsum("ij,ij->i", radial, axes)[:, None] * axes
    radial /= np.linalg.norm(radial, axis=1)[:, None]
    return axis_points + radius * radial + rng.normal(scale=noise, size=(n_points, 3))


def look_at(eye: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> NDArray[np.float64]:
    """Rotation [x_c y_c z_c] of a camera at ``eye`` looking at ``target`` (z_c forward, y_c down)."""
    forward = _unit(np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64))
    right = _unit(np.cross(forward, np.asarray(up, dtype=np.float64)))
    down = np.cross(forward, right)
    return np.column_stack((right, down, forward))


@dataclass(frozen=True)
class VineScene:
    """Primitive shapes of a synthetic vine scene, world frame [m].

    Attributes:
        stem_base: where the stem leaves the branch.
        stem_bend: the stem's bend point.
        stem_end: where the stem meets the grape cluster.
        stem_radius: stem radius.
        branch_start, branch_end, branch_radius: the branch cylinder.
        berry_centres, berry_radius: the grape cluster's berries.
        leaf_centres, leaf_normals, leaf_radius: flat round leaves.
        background_point, background_normal: a wall of canopy behind the scene.
    """

    stem_base: NDArray[np.float64]
    stem_bend: NDArray[np.float64]
    stem_end: NDArray[np.float64]
    stem_radius: float
    branch_start: NDArray[np.float64]
    branch_end: NDArray[np.float64]
    branch_radius: float
    berry_centres: NDArray[np.float64]
    berry_radius: float
    leaf_centres: NDArray[np.float64]
    leaf_normals: NDArray[np.float64]
    leaf_radius: float
    background_point: NDArray[np.float64]
    background_normal: NDArray[np.float64]

    @classmethod
    def default(cls, *, seed: int = 0) -> VineScene:
        """A 6 cm bent stem under a branch, a 60-berry cluster, four leaves (one partly in
        front of the stem when seen from +x) and a background wall 0.6 m behind."""
        rng = np.random.default_rng(seed)
        base = np.array([0.0, 0.0, 1.2])
        bend = base + 0.03 * _unit([0.0, 0.35, -1.0])
        end = bend + 0.03 * _unit([0.0, -0.2, -1.0])
        # Berries packed in a cone below the stem end.
        height = rng.uniform(0.0, 1.0, 60)
        angle = rng.uniform(0.0, 2.0 * np.pi, 60)
        spread = 0.012 + 0.045 * (1.0 - height) * np.sqrt(rng.uniform(0.2, 1.0, 60))
        berries = end + np.column_stack((spread * np.cos(angle), spread * np.sin(angle), -0.02 - 0.16 * height))
        offsets = np.array(
            [
                [0.08, 0.06, -0.06],  # partly in front of the stem's lower half, seen from +x
                [-0.05, 0.11, 0.02],
                [-0.04, -0.12, -0.05],
                [0.02, 0.09, 0.12],
            ]
        )
        normals = np.array([_unit([1.0, 0.15, 0.1]), _unit([0.3, -1.0, 0.2]), _unit([0.2, 1.0, 0.1]), [0.0, 0.0, 1.0]])
        return cls(
            stem_base=base,
            stem_bend=bend,
            stem_end=end,
            stem_radius=0.0025,
            branch_start=base + np.array([0.0, -0.4, 0.01]),
            branch_end=base + np.array([0.0, 0.4, 0.01]),
            branch_radius=0.01,
            berry_centres=berries,
            berry_radius=0.009,
            leaf_centres=base + offsets,
            leaf_normals=normals,
            leaf_radius=0.04,
            background_point=np.array([-0.6, 0.0, 0.0]),
            background_normal=np.array([1.0, 0.0, 0.0]),
        )


@dataclass(frozen=True)
class RenderedScene:
    """A rendered frame: ``points`` ``(n, 3)`` [m] and their ``stem_mask`` ``(n,)``."""

    points: NDArray[np.float64]
    stem_mask: NDArray[np.bool_]
    camera_position: NDArray[np.float64]
    scene: VineScene = field(repr=False)


def _hit_cylinder(origin, rays, start, end, radius):
    """Ray parameter of the first hit with a finite cylinder (inf where missed)."""
    axis_vector = end - start
    height = np.linalg.norm(axis_vector)
    axis = axis_vector / height
    offset = origin - start
    ray_perp = rays - np.outer(rays @ axis, axis)
    offset_perp = offset - (offset @ axis) * axis
    a = np.einsum("ij,ij->i", ray_perp, ray_perp)
    b = 2.0 * ray_perp @ offset_perp
    c = offset_perp @ offset_perp - radius * radius
    disc = b * b - 4.0 * a * c
    with np.errstate(invalid="ignore", divide="ignore"):
        t = (-b - np.sqrt(disc)) / (2.0 * a)
    along = offset @ axis + t * (rays @ axis)
    return np.where((disc >= 0.0) & (t > 0.0) & (along >= 0.0) & (along <= height), t, np.inf)


def _hit_spheres(origin, rays, centres, radius):
    """Ray parameter of the first hit with any of the spheres (inf where missed)."""
    best = np.full(rays.shape[0], np.inf)
    for centre in centres:
        offset = origin - centre
        b = rays @ offset
        disc = b * b - (offset @ offset - radius * radius)
        with np.errstate(invalid="ignore"):
            t = -b - np.sqrt(disc)
        best = np.minimum(best, np.where((disc >= 0.0) & (t > 0.0), t, np.inf))
    return best


def _hit_disc(origin, rays, centre, normal, radius):
    """Ray parameter of the hit with a flat disc (inf where missed)."""
    facing = rays @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((centre - origin) @ normal) / facing
    hit = origin + t[:, None] * rays
    inside = np.einsum("ij,ij->i", hit - centre, hit - centre) <= radius * radius
    return np.where(inside & (t > 0.0) & np.isfinite(t), t, np.inf)


def render_scene(
    scene: VineScene,
    camera_position: ArrayLike,
    *,
    width: int = 283,
    height: int = 160,
    horizontal_fov: float = np.deg2rad(65.0),
    depth_noise: float = 0.001,
    max_range: float = 2.0,
    seed: int = 0,
) -> RenderedScene:
    """Ray-cast ``scene`` from a pinhole camera at ``camera_position`` looking at the stem.

    ``width`` x ``height`` pixels with a D415-like horizontal field of view [rad]; the depth of
    each hit gets Gaussian noise of ``depth_noise`` [m] along the ray; pixels with no hit
    closer than ``max_range`` [m] are dropped, as a depth camera drops invalid pixels.
    """
    eye = as_point("camera_position", camera_position)
    width, height = positive_int("width", width), positive_int("height", height)
    depth_noise = as_positive_scalar(depth_noise, "depth_noise", allow_zero=True)
    rotation = look_at(eye, 0.5 * (scene.stem_base + scene.stem_end))
    focal = 0.5 * width / np.tan(0.5 * horizontal_fov)
    u, v = np.meshgrid(np.arange(width) + 0.5 - 0.5 * width, np.arange(height) + 0.5 - 0.5 * height)
    camera_rays = np.column_stack((u.ravel() / focal, v.ravel() / focal, np.ones(u.size)))
    rays = camera_rays @ rotation.T
    rays /= np.linalg.norm(rays, axis=1)[:, None]

    stem = np.minimum(
        _hit_cylinder(eye, rays, scene.stem_base, scene.stem_bend, scene.stem_radius),
        _hit_cylinder(eye, rays, scene.stem_bend, scene.stem_end, scene.stem_radius),
    )
    others = [
        _hit_cylinder(eye, rays, scene.branch_start, scene.branch_end, scene.branch_radius),
        _hit_spheres(eye, rays, scene.berry_centres, scene.berry_radius),
        _hit_disc(eye, rays, scene.background_point, scene.background_normal, 10.0),
    ]
    others += [
        _hit_disc(eye, rays, centre, normal, scene.leaf_radius)
        for centre, normal in zip(scene.leaf_centres, scene.leaf_normals, strict=True)
    ]
    other = np.minimum.reduce(others)
    depth = np.minimum(stem, other)
    keep = depth < max_range
    rng = np.random.default_rng(seed)
    noisy_depth = depth[keep] + rng.normal(scale=depth_noise, size=int(np.count_nonzero(keep)))
    points = eye + noisy_depth[:, None] * rays[keep]
    return RenderedScene(points=points, stem_mask=(stem <= other)[keep], camera_position=eye, scene=scene)


# --------------------------------------------------------------------------- MuJoCo lab views


def view_poses(
    target: ArrayLike,
    rng: np.random.Generator,
    n_views: int,
    *,
    distance: tuple[float, float] = (0.3, 0.45),
    azimuth: tuple[float, float] = (-1.2, 1.2),
    elevation: tuple[float, float] = (-0.5, 0.8),
) -> list[NDArray[np.float64]]:
    """``n_views`` camera poses (4x4, {C}: z = view direction, y = image down) looking at ``target``.

    The camera stands on the robot's side of the vine (world -x), at a distance drawn
    uniformly in ``distance`` [m], an azimuth about z from -x in ``azimuth`` [rad] and an
    elevation above the horizontal in ``elevation`` [rad], as the camera arm sees the
    stem while it approaches.
    """
    target = as_point("target", target)
    poses = []
    for _ in range(positive_int("n_views", n_views)):
        a, e, r = rng.uniform(*azimuth), rng.uniform(*elevation), rng.uniform(*distance)
        direction = np.array([-np.cos(e) * np.cos(a), -np.cos(e) * np.sin(a), np.sin(e)])
        pose = np.eye(4)
        pose[:3, 3] = target + r * direction
        pose[:3, :3] = look_at(pose[:3, 3], target)
        poses.append(pose)
    return poses


@dataclass(frozen=True)
class LabFrame:
    """One lab frame and the ground truth of its stem.

    Attributes:
        points: ``(n, 3)`` world points [m].
        stem_mask: ``(n,)`` True for points labelled STEM by the camera.
        robot_mask: ``(n,)`` True for points on the robot (also non-stem).
        camera_position: camera position [m].
        true_base: the stem base p_sb where the stem leaves the branch [m].
        true_free_length: stem length from the base to where its axis enters the gripper or
            the cluster [m] (what a camera can see of it at best).
        base_seen: a stem point lies within ``stem_radius + 3 mm`` of ``true_base``.
        coverage: fraction of the free stem's axis (samples every 1 mm) with a stem point
            within ``stem_radius + 2 mm`` (1 = nothing hides it).
        stem_radius: true stem radius [m].
    """

    points: NDArray[np.float64]
    stem_mask: NDArray[np.bool_]
    robot_mask: NDArray[np.bool_]
    camera_position: NDArray[np.float64]
    true_base: NDArray[np.float64]
    true_free_length: float
    base_seen: bool
    coverage: float
    stem_radius: float


class LabViews:
    """Frames of a lab scene (:class:`harvest_qp.sim.SimRobot`) from any camera pose, with ground truth.

    The robot stands at its home pose holding the cluster after the scene settled; the
    camera is the lab's ray-cast camera (the paper's D415 set-up unless ``camera`` is
    given), placed at any pose without moving the camera arm.

    Args:
        seed: scene seed, ``VineSceneParams.sample(seed)``; ``None`` for the default scene.
        camera: a :class:`harvest_qp.sim.CameraConfig` (default: the lab's).
        **overrides: scene parameters passed to ``VineSceneParams``.
    """

    def __init__(self, seed: int | None = None, *, camera=None, **overrides) -> None:
        from harvest_qp.interface import OBSTACLE, ROBOT, STEM
        from harvest_qp.sim import CameraConfig, RayCastCamera, SimRobot, VineSceneParams

        params = VineSceneParams(**overrides) if seed is None else VineSceneParams.sample(seed, **overrides)
        self.robot = SimRobot(params, camera=None)
        self.scene = self.robot.scene
        self._labels = (STEM, OBSTACLE, ROBOT)
        model = self.robot.model
        self.camera = RayCastCamera(
            model,
            CameraConfig() if camera is None else camera,
            geom_labels=self.scene.geom_labels,
            exclude_body=self.scene.ids["cam_tool"],
        )
        self.stem_radius = float(params.stem_radius)
        self.stem_axis = self._stem_axis()
        self._surfaces = self._non_stem_surfaces()
        self.free_length, self.free_axis = self._free_stem()

    # ---------------------------------------------------------------- ground truth

    def _stem_axis(self) -> NDArray[np.float64]:
        """Stem axis polyline of the settled stem, from the base down to the cluster [m]."""
        model, data = self.robot.model, self.robot.data
        base = self.scene.stem_base
        ends = []
        for g in self.scene.stem_geoms:
            half = model.geom_size[g, 1]
            z = data.geom_xmat[g].reshape(3, 3)[:, 2]
            a, b = data.geom_xpos[g] - half * z, data.geom_xpos[g] + half * z
            ends.append((a, b) if np.linalg.norm(a - base) < np.linalg.norm(b - base) else (b, a))
        ends.sort(key=lambda e: np.linalg.norm(e[0] - base))
        return np.array([ends[0][0]] + [e[1] for e in ends])

    def _non_stem_surfaces(self) -> list[tuple[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
        """(type, size, position, rotation) of every visible non-stem geom except the camera tool."""
        model, data = self.robot.model, self.robot.data
        stem = set(int(g) for g in self.scene.stem_geoms)
        out = []
        for g in range(model.ngeom):
            if g in stem or model.geom_rgba[g, 3] == 0 or model.geom_bodyid[g] == self.scene.ids["cam_tool"]:
                continue
            out.append(
                (int(model.geom_type[g]), model.geom_size[g].copy(), data.geom_xpos[g].copy(),
                 data.geom_xmat[g].reshape(3, 3).copy())
            )  # fmt: skip
        return out

    def surface_distance(self, points: ArrayLike, *, wood_only: bool = False) -> NDArray[np.float64]:
        """Distance [m] from each point to the nearest non-stem surface (negative inside).

        Exact for planes, spheres and capsules; leaves (thin ellipsoids) are measured on 4,000
        surface samples (under 1 mm of error at the distances that matter here).  The camera
        tool, which the camera never sees, is left out.  ``wood_only``: the branch and cane.
        """
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        best = np.full(points.shape[0], np.inf)
        wood = {self.robot.model.geom("branch").id, self.robot.model.geom("cane").id}
        surfaces = self._surfaces if not wood_only else [self._surface_of(g) for g in sorted(wood)]
        for kind, size, position, rotation in surfaces:
            local = (points - position) @ rotation
            if kind == 0:  # plane
                d = local[:, 2]
            elif kind == 2:  # sphere
                d = np.linalg.norm(local, axis=1) - size[0]
            elif kind == 3:  # capsule along local z
                z = np.clip(local[:, 2], -size[1], size[1])
                d = np.linalg.norm(local - np.outer(z, [0.0, 0.0, 1.0]), axis=1) - size[0]
            elif kind == 4:  # ellipsoid
                d = self._ellipsoid_distance(local, size)
            else:
                raise ModelError(
                    f"LabViews.surface_distance: unhandled geom type {kind} (plane, sphere, capsule, ellipsoid only)"
                )
            best = np.minimum(best, d)
        return best

    def _surface_of(self, g: int):
        model, data = self.robot.model, self.robot.data
        return (
            int(model.geom_type[g]),
            model.geom_size[g].copy(),
            data.geom_xpos[g].copy(),
            data.geom_xmat[g].reshape(3, 3).copy(),
        )

    @staticmethod
    def _ellipsoid_distance(local: NDArray[np.float64], size: NDArray[np.float64]) -> NDArray[np.float64]:
        samples = fibonacci_unit(4000) * size
        inside = ((local / size) ** 2).sum(axis=1) < 1.0
        diff = local[:, None, :] - samples[None, :, :]
        d = np.sqrt((diff**2).sum(axis=2)).min(axis=1)
        return np.where(inside, -d, d)

    def segment_clearance(
        self, start: ArrayLike, end: ArrayLike, *, skip: float = 0.0, wood_only: bool = True
    ) -> float:
        """Smallest surface distance [m] along the segment start -> end, 1 mm steps, ignoring the first ``skip`` [m]."""
        start, end = as_point("start", start), as_point("end", end)
        length = float(np.linalg.norm(end - start))
        s = np.linspace(min(skip, length), length, max(2, int(length / 0.001) + 1))
        samples = start + np.outer(s / max(length, 1e-12), end - start)
        return float(self.surface_distance(samples, wood_only=wood_only).min())

    def _free_stem(self) -> tuple[float, NDArray[np.float64]]:
        """Length [m] and samples (1 mm apart) of the stem axis from the base to where it
        enters the gripper or the cluster (a robot or berry/rachis geom)."""
        model = self.robot.model
        cluster_body = self.scene.ids["cluster"]
        entering = [
            self._surface_of(g)
            for g in range(model.ngeom)
            if self.scene.geom_labels[g] == self._labels[2] or model.geom_bodyid[g] == cluster_body
        ]
        axis = self.stem_axis
        samples = [axis[0]]
        for a, b in zip(axis[:-1], axis[1:], strict=True):
            n = max(1, int(np.linalg.norm(b - a) / 0.001))
            samples.extend(a + np.outer(np.arange(1, n + 1) / n, b - a))
        samples = np.array(samples)
        inside = np.zeros(len(samples), dtype=bool)
        saved = self._surfaces
        try:
            self._surfaces = entering
            inside = self.surface_distance(samples) <= 0.0
        finally:
            self._surfaces = saved
        first = int(np.argmax(inside)) if inside.any() else len(samples)
        free = samples[: max(first, 1)]
        length = float(np.linalg.norm(np.diff(free, axis=0), axis=1).sum())
        return length, free

    # ---------------------------------------------------------------- frames

    @property
    def stem_middle(self) -> NDArray[np.float64]:
        """Middle of the free stem [m], where the views look."""
        return self.free_axis[len(self.free_axis) // 2]

    def render(self, pose: ArrayLike) -> LabFrame:
        """A frame from camera ``pose`` (4x4) with its ground truth."""
        stem_label, _, robot_label = self._labels
        pose = np.asarray(pose, dtype=np.float64)
        cloud = self.camera.capture(self.robot.data, pose, 0.0)
        stem_mask = cloud.labels == stem_label
        stem_points = cloud.points[stem_mask]
        base = self.stem_axis[0]
        if stem_points.shape[0]:
            base_seen = bool(np.linalg.norm(stem_points - base, axis=1).min() < self.stem_radius + 0.003)
            gaps = np.sqrt(((self.free_axis[:, None, :] - stem_points[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
            coverage = float(np.mean(gaps < self.stem_radius + 0.002))
        else:
            base_seen, coverage = False, 0.0
        return LabFrame(
            points=cloud.points,
            stem_mask=stem_mask,
            robot_mask=cloud.labels == robot_label,
            camera_position=pose[:3, 3].copy(),
            true_base=base.copy(),
            true_free_length=self.free_length,
            base_seen=base_seen,
            coverage=coverage,
            stem_radius=self.stem_radius,
        )


def fibonacci_unit(n: int) -> NDArray[np.float64]:
    """``n`` near-uniform unit vectors (golden-angle spiral), independent of :mod:`.fibonacci`."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return np.column_stack((s * np.cos(phi), s * np.sin(phi), z))
