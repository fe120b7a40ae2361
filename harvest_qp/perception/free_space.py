"""Free space around the stem and the grasping arm's target p_gd (``subsec:scePC_proc``).

1. The obstacles O are projected onto the sphere S(p_sb, l) (the set O_pr of
   Table ``table:PCs``).
2. The sphere is sampled by the spherical Fibonacci lattice; the sample nearest to each
   projected obstacle is found by the O(1) inverse mapping (:mod:`.fibonacci`) and removed.
3. A plane is fitted to O by PCA; samples behind it, seen from the camera, are removed
   because the camera cannot see behind the obstacles.  What is left is the free space F.
4. p_gd is the free sample furthest from its nearest projected obstacle (``eq:attr_point``),
   found with a KD-tree over O_pr instead of the brute-force double loop.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from harvest_qp.perception._validation import as_finite_points, as_point, positive_int
from harvest_qp.perception.fibonacci import fibonacci_sphere, nearest_index_of_unit_vectors
from harvest_qp.validation import as_positive_scalar

__all__ = ["FreeSpace", "ObstaclePlane", "compute_free_space", "fit_obstacle_plane"]


@dataclass(frozen=True)
class ObstaclePlane:
    """The PCA plane of the obstacles O.

    Attributes:
        point: a point of the plane, the mean of O [m].
        normal: unit normal, oriented towards the camera.
    """

    point: NDArray[np.float64]
    normal: NDArray[np.float64]


@dataclass(frozen=True)
class FreeSpace:
    """Result of :func:`compute_free_space`, with everything a viewer needs.

    Attributes:
        valid: whether a target p_gd was found.
        reason: why not (``valid=False``), or a note on how it was found; empty otherwise.
        centre: sphere centre, the stem base p_sb [m].
        radius: sphere radius, the stem length l [m].
        samples: ``(n_samples, 3)`` Fibonacci samples of S(p_sb, l) [m].
        occupied: ``(n_samples,)`` True for samples nearest to a projected obstacle.
        behind_plane: ``(n_samples,)`` True for samples on the far side of the obstacle plane
            from the camera (all False when there is no plane).
        projected_obstacles: ``(n_O, 3)`` O_pr, the obstacles projected on the sphere [m].
        plane: PCA plane of O, or ``None`` when O has fewer than 3 points, is collinear, or
            contains the camera (no side can be chosen); then no half-space is removed.
        target: p_gd [m] (``eq:attr_point``), ``None`` when there is no free sample.
        target_clearance: distance from p_gd to its nearest projected obstacle [m]; inf when
            there are no obstacles, NaN when there is no target.
    """

    valid: bool
    reason: str
    centre: NDArray[np.float64]
    radius: float
    samples: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    behind_plane: NDArray[np.bool_]
    projected_obstacles: NDArray[np.float64]
    plane: ObstaclePlane | None
    target: NDArray[np.float64] | None
    target_clearance: float

    @property
    def free(self) -> NDArray[np.bool_]:
        """``(n_samples,)`` True for samples of the free space F."""
        return ~self.occupied & ~self.behind_plane

    @property
    def kept_samples(self) -> NDArray[np.float64]:
        """The free-space points F [m]."""
        return self.samples[self.free]

    @property
    def removed_samples(self) -> NDArray[np.float64]:
        """Samples removed as occupied or behind the obstacle plane [m]."""
        return self.samples[~self.free]


def fit_obstacle_plane(
    obstacles: ArrayLike, camera_position: ArrayLike, *, min_planarity: float = 1e-6
) -> ObstaclePlane | None:
    """The PCA plane of the obstacles O, with its normal towards the camera.

    The plane is spanned by the two major PCA eigenvectors of O and passes through its mean
    (``subsec:scePC_proc``, Fig. ``fig:PC_proc_7``).

    Args:
        obstacles: ``(n_O, 3)`` finite obstacle points [m].
        camera_position: camera position p_c [m].
        min_planarity: the plane is undefined (``None``) when the second PCA variance is
            below this fraction of the first (collinear or coincident obstacles).

    Returns:
        The plane, or ``None`` when fewer than 3 obstacles, collinear obstacles, or the
        camera lies on the plane.
    """
    points = as_finite_points("obstacles", obstacles)
    camera = as_point("camera_position", camera_position)
    if points.shape[0] < 3:
        return None
    centroid = points.mean(axis=0)
    centred = points - centroid
    eigenvalues, eigenvectors = np.linalg.eigh(centred.T @ centred)
    if eigenvalues[1] <= min_planarity * eigenvalues[2]:
        return None
    normal = eigenvectors[:, 0]  # smallest variance: perpendicular to the two major axes
    camera_side = normal @ (camera - centroid)
    if abs(camera_side) <= 1e-12 * max(1.0, np.linalg.norm(camera - centroid)):
        return None
    return ObstaclePlane(point=centroid, normal=normal if camera_side > 0.0 else -normal)


def compute_free_space(
    obstacles: ArrayLike,
    stem_base: ArrayLike,
    stem_length: float,
    camera_position: ArrayLike,
    *,
    n_samples: int = 500,
) -> FreeSpace:
    """Free space F on the sphere S(p_sb, l) and the target p_gd (``eq:attr_point``).

    Args:
        obstacles: ``(n_O, 3)`` finite obstacle points O [m], e.g. from
            :func:`~harvest_qp.perception.classify.obstacles_near_stem_base`.  Points at the
            stem base itself have no direction and are ignored.
        stem_base: sphere centre p_sb [m].
        stem_length: sphere radius l [m].
        camera_position: camera position p_c [m], to keep the camera side of the plane.
        n_samples: number of Fibonacci samples of the sphere (500 in Fig. ``fig:PC_proc_4``).

    Returns:
        A :class:`FreeSpace`.  With no obstacles every sample is free and all are equally
        far from an obstacle; the target is then the sample nearest to the direction of the
        camera (the best-seen free point) and ``reason`` says so.  With every sample removed
        the result has ``valid=False`` and no target.
    """
    points = as_finite_points("obstacles", obstacles)
    centre = as_point("stem_base", stem_base)
    radius = as_positive_scalar(stem_length, "stem_length")
    camera = as_point("camera_position", camera_position)
    n_samples = positive_int("n_samples", n_samples)

    samples = centre + radius * fibonacci_sphere(n_samples)
    offsets = points - centre
    distances = np.sqrt(np.einsum("ij,ij->i", offsets, offsets))
    has_direction = distances > 0.0
    directions = offsets[has_direction] / distances[has_direction, None]
    projected = centre + radius * directions

    occupied = np.zeros(n_samples, dtype=bool)
    occupied[nearest_index_of_unit_vectors(directions, n_samples)] = True

    plane = fit_obstacle_plane(points, camera)
    if plane is None:
        behind_plane = np.zeros(n_samples, dtype=bool)
    else:
        behind_plane = (samples - plane.point) @ plane.normal < 0.0

    free_index = np.flatnonzero(~occupied & ~behind_plane)

    def result(valid: bool, reason: str, target_index: int | None, clearance: float) -> FreeSpace:
        return FreeSpace(
            valid=valid,
            reason=reason,
            centre=centre,
            radius=radius,
            samples=samples,
            occupied=occupied,
            behind_plane=behind_plane,
            projected_obstacles=projected,
            plane=plane,
            target=None if target_index is None else samples[target_index],
            target_clearance=clearance,
        )

    if free_index.size == 0:
        return result(False, "no free sample: every sample is occupied or behind the obstacle plane", None, np.nan)
    if projected.shape[0] == 0:
        # Every sample is infinitely far from an obstacle: prefer the one facing the camera.
        best = free_index[np.argmax(samples[free_index] @ (camera - centre))]
        return result(True, "no obstacles: target is the free sample facing the camera", best, np.inf)

    # eq:attr_point: maximise, over free samples, the distance to the nearest projected obstacle.
    # Built once per frame and queried by at most n_samples points: an unbalanced tree with
    # large leaves builds about twice as fast and answers the few queries just as well.
    tree = cKDTree(projected, leafsize=64, balanced_tree=False, compact_nodes=False)
    clearance, _ = tree.query(samples[free_index])
    best_position = int(np.argmax(clearance))
    return result(True, "", free_index[best_position], float(clearance[best_position]))
