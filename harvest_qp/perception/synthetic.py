"""Synthetic stem scenes with known ground truth, for tests, benchmarks and demos.

* :func:`bent_stem` samples a two-segment stem with a known base.
* :func:`render_scene` ray-casts a vine-like scene (bent stem, branch, berries, leaves,
  background) from a pinhole depth camera, giving a point cloud with the density,
  occlusions and stem labels of a real frame (D415-like field of view).
* frames of the MuJoCo lab itself, with their ground truth, come from
  :class:`harvest_qp.sim.lab_views.LabViews` (the lab is above perception in the data flow).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.perception._validation import as_point, positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = [
    "RenderedScene", "VineScene", "bent_stem", "fibonacci_unit", "look_at", "render_scene", "unit_vector", "view_poses",
]


def unit_vector(vector: ArrayLike) -> NDArray[np.float64]:
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
    top_axis, bottom_axis = unit_vector(top_direction), unit_vector(bottom_direction)
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
    forward = unit_vector(np.asarray(target, dtype=np.float64) - np.asarray(eye, dtype=np.float64))
    right = unit_vector(np.cross(forward, np.asarray(up, dtype=np.float64)))
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
        bend = base + 0.03 * unit_vector([0.0, 0.35, -1.0])
        end = bend + 0.03 * unit_vector([0.0, -0.2, -1.0])
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
        normals = np.array([
            unit_vector([1.0, 0.15, 0.1]), unit_vector([0.3, -1.0, 0.2]), unit_vector([0.2, 1.0, 0.1]), [0.0, 0.0, 1.0]
        ])
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


def fibonacci_unit(n: int) -> NDArray[np.float64]:
    """``n`` near-uniform unit vectors (golden-angle spiral), independent of :mod:`.fibonacci`."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    s = np.sqrt(1.0 - z * z)
    return np.column_stack((s * np.cos(phi), s * np.sin(phi), z))
