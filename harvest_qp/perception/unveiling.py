"""Unveiling geometry of ``subsec:occlusion_control_signal``: the ray/obstacle pairs (``eq:nearest``).

For every camera-to-stem-point ray j and obstacle k the paper needs the point p_hat_jk of
the ray segment [p_c, p_sj] nearest to the obstacle (``eq:nearest``) and its distance to
the obstacle sphere's surface r_hat_jk = ||p_hat_jk - p_ok|| - d_o.  Only pairs with
r_hat_jk < d_a contribute (the potential ``eq:art_potential`` is zero beyond), so the kernel
:func:`ray_obstacle_pairs` returns only those, without visiting all n_S x n_O pairs:

1. Obstacle cull, O(n_O) vectorised: an obstacle within R = d_a + d_o of a segment lies
   within the depth range of the segments and within R of the cone of ray directions.
2. Ray bundles: the rays are split into compact bundles (recursive median splits of their
   directions).  For each bundle, the obstacles that can be within R of its cone are found
   with the same cone test, and the bundle's rays and those obstacles are evaluated as a
   dense block (one matrix product for the dot products), which keeps numpy on contiguous
   in-cache arrays instead of gathering pair by pair.
3. ``eq:nearest`` and r_hat evaluated exactly on the pairs of the block that pass,
   keeping r_hat < d_a.

The control law on these pairs (``eq:art_potential`` .. ``eq:v_c2``, V_cu) lives in
:mod:`harvest_qp.references.unveiling`.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import _unveiling_kernels as _kernels
from harvest_qp.perception._validation import as_finite_points, as_point
from harvest_qp.validation import as_positive_scalar

__all__ = [
    "NEAREST_AT_CAMERA",
    "NEAREST_AT_STEM_POINT",
    "NEAREST_INTERIOR",
    "RayObstaclePairs",
    "ray_obstacle_pairs",
]

# Which branch of eq:nearest gave p_hat: the camera, a point inside the segment, the stem point.
NEAREST_AT_CAMERA = 0
NEAREST_INTERIOR = 1
NEAREST_AT_STEM_POINT = 2

# Rays per bundle: larger bundles mean wider cones, hence more obstacle candidates per ray.
_BUNDLE_SIZE = 64


@dataclass(frozen=True)
class RayObstaclePairs:
    """Ray/obstacle pairs inside the influence distance, from :func:`ray_obstacle_pairs`.

    The order of the pairs is deterministic but unspecified (sorting 10^5 pairs would cost
    more than finding them).

    Attributes:
        stem_index: ``(P,)`` index j into ``stem_points``.
        obstacle_index: ``(P,)`` index k into ``obstacle_points``.
        surface_distance: ``(P,)`` r_hat_jk = ||p_hat_jk - p_ok|| - d_o [m], all < d_a.
        case: ``(P,)`` branch of ``eq:nearest``: :data:`NEAREST_AT_CAMERA`,
            :data:`NEAREST_INTERIOR` (the only one ``eq:omega_pivot`` uses) or
            :data:`NEAREST_AT_STEM_POINT`.
        segment_parameter: ``(P,)`` s in [0, 1] with p_hat = p_c + s (p_sj - p_c).
        away_directions: ``(P, 3)`` unit vectors (p_hat - p_ok) / ||p_hat - p_ok||, the
            direction of e_jk and u_jk in ``eq:u_ij`` (zero when p_hat = p_ok).
        stem_points: ``(n_S, 3)`` stem points p_sj [m].
        obstacle_points: ``(n_O, 3)`` obstacle points p_ok [m].
        camera_position: p_c [m].
        influence_distance: d_a [m].
        obstacle_radius: d_o [m].
        n_candidate_obstacles: obstacles left after the cull (step 1), for diagnostics.

    :attr:`nearest_points` (p_hat_jk, ``(P, 3)`` [m]) is computed from ``segment_parameter``
    on first access: the velocity does not need it, and not writing it saves time on large
    frames.
    """

    stem_index: NDArray[np.intp]
    obstacle_index: NDArray[np.intp]
    surface_distance: NDArray[np.float64]
    case: NDArray[np.int8]
    segment_parameter: NDArray[np.float64]
    away_directions: NDArray[np.float64]
    stem_points: NDArray[np.float64]
    obstacle_points: NDArray[np.float64]
    camera_position: NDArray[np.float64]
    influence_distance: float
    obstacle_radius: float
    n_candidate_obstacles: int

    def __len__(self) -> int:
        return int(self.stem_index.shape[0])

    @functools.cached_property
    def nearest_points(self) -> NDArray[np.float64]:
        """``(P, 3)`` p_hat_jk of ``eq:nearest`` [m]: p_c + s (p_sj - p_c), exactly p_sj on the
        third branch."""
        rays = self.stem_points - self.camera_position
        nearest = self.camera_position + self.segment_parameter[:, None] * np.take(rays, self.stem_index, axis=0)
        at_stem = np.flatnonzero(self.case == NEAREST_AT_STEM_POINT)
        nearest[at_stem] = np.take(self.stem_points, np.take(self.stem_index, at_stem), axis=0)
        return nearest


@dataclass(frozen=True)
class _Cone:
    """A cone of directions from the camera: unit ``axis`` and half-angle via cos/sin."""

    axis: NDArray[np.float64]
    cos_half_angle: float
    sin_half_angle: float

    @classmethod
    def around(cls, directions: NDArray[np.float64]) -> _Cone | None:
        """The cone about the mean of unit ``directions``, ``None`` if 90 degrees or wider."""
        axis = directions.sum(axis=0)
        norm = np.linalg.norm(axis)
        if norm == 0.0:
            return None
        axis /= norm
        # The half-angle from its cosine is ill-conditioned near 0 (an error of 1e-16 in the
        # cosine is 1.5e-8 rad); widening the cone by ~1e-6 rad keeps the tests conservative.
        cos_half_angle = min(1.0, float((directions @ axis).min())) - 1e-12
        if cos_half_angle <= 0.0:
            return None
        return cls(axis, cos_half_angle, float(np.sqrt(1.0 - cos_half_angle**2)))


def _slant(squared_distance: NDArray[np.float64], reach: float) -> NDArray[np.float64]:
    """sqrt(max(rho^2 - reach^2, 0)) for the cone test of the kernels.

    A point at distance rho >= reach from a cone's apex can only be within reach of a ray of
    the cone (axis a, half-angle alpha) if its angle psi to the axis is below
    alpha + asin(reach / rho), i.e. rho cos(psi) > cos(alpha) sqrt(rho^2 - reach^2) - sin(alpha) reach.
    """
    return np.sqrt(np.maximum(squared_distance - reach * reach, 0.0))


def _candidate_obstacles(
    rays: NDArray[np.float64],
    ray_directions: NDArray[np.float64],
    obstacles: NDArray[np.float64],
    camera: NDArray[np.float64],
    reach: float,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Obstacles that may lie within ``reach`` of some ray segment (step 1).

    Returns their indices and offsets p_o - p_c [m].  Conservative: only obstacles further
    than ``reach`` from every segment are dropped.  One compiled pass over the cloud
    (:func:`._unveiling_kernels.candidate_obstacles`: 1.8 ms -> ~0.2 ms per 848x480 frame).
    """
    cone = _Cone.around(ray_directions)
    if cone is None:  # rays spread over a hemisphere or more: nothing to cull by direction
        return np.arange(obstacles.shape[0]), obstacles - camera
    longest_ray = np.sqrt(np.einsum("ij,ij->i", rays, rays).max())
    index = np.empty(obstacles.shape[0], dtype=np.intp)
    offsets = np.empty((obstacles.shape[0], 3))
    n = _kernels.candidate_obstacles(
        np.ascontiguousarray(obstacles), camera, cone.axis, float(camera @ cone.axis),
        float((rays @ cone.axis).max() + reach), cone.cos_half_angle, cone.sin_half_angle, reach,
        float((longest_ray + reach) ** 2), index, offsets,
    )  # fmt: skip
    return index[:n], offsets[:n]


def _ray_bundle_order(directions: NDArray[np.float64], max_size: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """The rays in compact bundles of at most ``max_size`` (sort-tile packing): the rays in bundle
    order and where each bundle after the first starts.

    The directions are sorted along their major principal axis and cut into strips, each
    strip is sorted along the minor axis and cut into bundles; the strip count makes the
    bundles roughly square in direction space.  Two sorts, no per-bundle Python work.
    """
    n_rays = directions.shape[0]
    if n_rays <= max_size:
        return np.arange(n_rays), np.zeros(0, dtype=np.intp)
    n_bundles = -(-n_rays // max_size)
    centred = directions - directions.mean(axis=0)
    _, spread, axes = np.linalg.svd(centred, full_matrices=False)
    major, minor = centred @ axes[0], centred @ axes[1]
    aspect = spread[0] / max(spread[1], spread[0] * 1e-6) if spread[0] > 0.0 else 1.0
    n_strips = int(np.clip(np.round(np.sqrt(n_bundles * aspect)), 1, n_bundles))
    strip_size = -(-n_rays // n_strips)
    strip = np.empty(n_rays, dtype=np.intp)
    strip[np.argsort(major, kind="stable")] = np.arange(n_rays) // strip_size
    order = np.lexsort((minor, strip))
    # Bundle boundaries restart in every strip so that no bundle spans two strips.
    rank_in_strip = np.arange(n_rays) - np.searchsorted(strip[order], strip[order])
    bundle_of = strip[order] * (-(-strip_size // max_size)) + rank_in_strip // max_size
    cuts = np.flatnonzero(np.diff(bundle_of)) + 1
    return order, cuts


def ray_obstacle_pairs(
    stem_points: ArrayLike,
    obstacle_points: ArrayLike,
    camera_position: ArrayLike,
    *,
    d_a: float = 0.01,
    d_o: float = 0.001,
) -> RayObstaclePairs:
    """Ray/obstacle pairs with r_hat < d_a, their p_hat (``eq:nearest``) and r_hat.

    Args:
        stem_points: ``(n_S, 3)`` finite stem points p_sj [m]; none may coincide with the camera.
        obstacle_points: ``(n_O, 3)`` finite obstacle points p_ok [m] (for the camera arm: all
            non-stem points).  Duplicated points give duplicated pairs, as in the sums.
        camera_position: camera position p_c [m].
        d_a: influence distance from the obstacle surface [m] (0.01 in Section ``sec:exper``).
        d_o: obstacle sphere radius [m] (0.001 in Section ``sec:exper``).

    Returns:
        The pairs (j, k) whose segment [p_c, p_sj] passes within d_a + d_o of p_ok, i.e.
        r_hat_jk < d_a, including pairs with r_hat <= 0 (rays through an obstacle sphere).

    Raises:
        InvalidInputError: wrong shapes, NaN/inf rows, d_a <= 0, d_o < 0, or a stem point at
            the camera position (its ray has no direction).
    """
    stem = as_finite_points("stem_points", stem_points)
    obstacles = as_finite_points("obstacle_points", obstacle_points)
    camera = as_point("camera_position", camera_position)
    d_a = as_positive_scalar(d_a, "d_a")
    d_o = as_positive_scalar(d_o, "d_o", allow_zero=True)
    return _ray_obstacle_pairs_unchecked(stem, obstacles, camera, d_a, d_o)


def _ray_obstacle_pairs_unchecked(
    stem: NDArray[np.float64], obstacles: NDArray[np.float64], camera: NDArray[np.float64], d_a: float, d_o: float
) -> RayObstaclePairs:
    """:func:`ray_obstacle_pairs` on arguments already checked: ``stem`` and ``obstacles`` finite
    float64 ``(n, 3)`` arrays, ``camera`` a finite float64 ``(3,)`` array, d_a > 0, d_o >= 0 [m].

    For the library's own callers (:meth:`harvest_qp.references.unveiling.Unveiling._observe_points`,
    whose clouds the control loop or :meth:`~harvest_qp.references.unveiling.Unveiling.observe` has
    checked): the finiteness test over the ~20,000 obstacle points of a 283x160 frame was ~15 % of
    this function's time. A stem point at the camera is still an error (no caller rules it out).
    """
    reach = d_a + d_o

    rays = stem - camera  # p_cs_j
    squared_lengths = np.einsum("ij,ij->i", rays, rays)
    if (squared_lengths == 0.0).any():
        raise InvalidInputError(
            f"stem_points must differ from camera_position; row {int(np.argmin(squared_lengths))} coincides with it"
        )
    ray_directions = rays / np.sqrt(squared_lengths)[:, None]
    # The culls get a hair of slack so that rounding never drops a pair; the pair test
    # itself uses the exact reach (membership is decided to rounding, ~1e-13 relative).
    slack_reach = reach * (1.0 + 1e-9)
    if stem.shape[0] and obstacles.shape[0]:
        candidates, offsets = _candidate_obstacles(rays, ray_directions, obstacles, camera, slack_reach)
    else:
        candidates, offsets = np.zeros(0, dtype=np.intp), np.zeros((0, 3))
    squared_offsets = np.einsum("ij,ij->i", offsets, offsets)
    slant = _slant(squared_offsets, slack_reach)
    near_camera = squared_offsets < slack_reach * slack_reach

    if candidates.size == 0:
        empty = np.zeros(0, dtype=np.intp)
        return _pairs_result(empty, empty, np.zeros(0), np.zeros(0), np.zeros((3, 0)), stem, obstacles, camera, d_a,
                             d_o, 0)  # fmt: skip
    # Steps 2-3 compiled (_unveiling_kernels.bundle_pairs: per bundle of rays, its cone culls the
    # candidates, then eq:nearest on each ray/obstacle pair).
    order, cuts = _ray_bundle_order(ray_directions, _BUNDLE_SIZE)
    starts = np.concatenate(([0], cuts, [order.size])).astype(np.int64)
    stem_index, local, s, distance, away = _kernels.bundle_pairs(
        rays, squared_lengths, ray_directions, order.astype(np.int64), starts, np.ascontiguousarray(offsets),
        squared_offsets, slant, near_camera, slack_reach, reach * reach,
    )  # fmt: skip
    obstacle_index = np.take(candidates, local)
    return _pairs_result(stem_index, obstacle_index, s, distance, away, stem, obstacles, camera, d_a, d_o,
                         candidates.size)  # fmt: skip


def _pairs_result(stem_index, obstacle_index, s, distance, away, stem, obstacles, camera, d_a, d_o, n_candidates):
    """The :class:`RayObstaclePairs` of the pairs found (``away``: ``(3, P)``)."""
    # Branch of eq:nearest: s <= 0 camera, 0 < s < 1 interior, s >= 1 stem point.
    case = (s > 0.0).astype(np.int8) + (s >= 1.0)
    return RayObstaclePairs(
        stem_index=stem_index,
        obstacle_index=obstacle_index,
        surface_distance=distance - d_o,
        case=case,
        segment_parameter=np.clip(s, 0.0, 1.0),
        away_directions=away.T,
        stem_points=stem,
        obstacle_points=obstacles,
        camera_position=camera,
        influence_distance=d_a,
        obstacle_radius=d_o,
        n_candidate_obstacles=int(n_candidates),
    )
