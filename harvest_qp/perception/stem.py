"""Two-segment stem model, stem base p_sb and the fit's quality (``subsec:scePC_proc``, ``stem_basend``).

The stem cloud S is split into two clusters by k-means, named "top" (further from the
gripper, attached to the branch) and "bottom" (closer to the gripper, attached to the
crop).  A PCA line segment is fitted to each; the stem length is l = l_t + l_b and the stem
base is the branch end of the top segment,

    p_sb = mean(T) - (l_t / 2) n_st,                                     (stem_basend)

with n_st oriented from the branch towards the bottom cluster.

Deviations from the paper, each measured on frames of the MuJoCo lab (283x160 ray-cast
camera, views 0.3-0.45 m from the stem; figures in the notes and ``benchmarks/bench_perception.py
--accuracy``):

* Segment ends from the extent of the points along each PCA axis, not from the cluster mean:
  ``stem_basend`` puts p_sb at mean(T) - (l_t / 2) n_st, which assumes the top cluster is
  seen uniformly from end to end; a leaf over part of the stem, or a thicker, bent stem,
  moves mean(T) and the PCA variance.  Here p_sb is the top end of the top cluster: the
  points within a pixel of its extreme along n_st give its position across the axis, the
  extreme (plus half a pixel) its position along it.  ``base == top.start`` still holds,
  with ``top`` the segment over the extent, so ``stem_basend`` is kept with mean(T) read as
  the segment midpoint.  ``base_estimator="paper"`` gives the paper's formula (with the
  variance length sqrt(12 lambda_1) as l_t).
* Near-surface correction: a depth camera only sees the stem's near half, whose points lie
  pi r / 4 in front of the axis on average (2-3 mm on the lab stems, the bias FINDINGS
  measured).  With ``camera_position`` the radius r is estimated from the points' width
  across the axis as seen from the camera, and every point is moved pi r / 4 along its
  view ray before the fit.
* The line-likeness check is a residual [m], not the PCA spread ratio: a 13-point cluster of
  a 4 mm-radius stem is 8 mm wide and 10 mm long (ratio ~0.8) and is still a stem.
* A quality record (:class:`StemQuality`): point count, radius, residual, an uncertainty of
  p_sb and whether the base looks hidden (the seen stem's top end continues behind
  non-stem points in front of it, e.g. the branch seen from above or a leaf).

A stem that cannot be modelled (too few points, all points in one spot, a cluster that is
not line-like) gives a :class:`StemModel` with ``valid=False`` and a ``reason``, never an
exception from numpy or scipy internals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import _stem_kernels
from harvest_qp.perception._validation import as_finite_points, as_point, positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = ["LineSegment", "StemModel", "StemQuality", "fit_stem"]


@dataclass(frozen=True)
class LineSegment:
    """A PCA line segment fitted to a stem cluster.

    Attributes:
        centroid: the segment midpoint [m] (the cluster mean with ``base_estimator="paper"``).
        direction: unit major PCA axis, oriented from the branch towards the crop.
        length: segment length [m].
    """

    centroid: NDArray[np.float64]
    direction: NDArray[np.float64]
    length: float

    @property
    def start(self) -> NDArray[np.float64]:
        """Branch-side end [m]."""
        return self.centroid - 0.5 * self.length * self.direction

    @property
    def end(self) -> NDArray[np.float64]:
        """Crop-side end [m]."""
        return self.centroid + 0.5 * self.length * self.direction


@dataclass(frozen=True)
class StemQuality:
    """How far a :class:`StemModel` can be trusted, from the points alone.

    Attributes:
        n_points: stem points used.
        n_top: points of the top cluster T.
        point_spacing: median distance between neighbouring stem points [m] (one pixel at
            the stem's range: the resolution of every length below).
        radius: stem radius used for the near-surface correction [m] (estimated, or the
            caller's ``stem_radius``; 0 when no camera position was given).
        residual: RMS distance of the points from their cluster's axis [m], after the
            near-surface correction (about r / sqrt(3) for a straight stem of radius r).
        spread_ratio: largest second/first PCA standard-deviation ratio of the clusters.
        base_uncertainty: 1-sigma uncertainty of p_sb [m] from the resolution, the radius
            correction and the scatter of the points at the top end; it does not cover a
            hidden base (see ``base_hidden``).
        base_hidden: True when the base looks hidden (the branch seen from above, a leaf):
            p_sb then lies on the stem below the true base.  Hidden means no non-stem point
            within ``max_base_gap`` of p_sb (a seen base touches the branch it hangs from), or
            a non-stem point more than ``max_front`` in front of the stem's continuation
            just past its seen end (an occlusion boundary), or a seen stem shorter than
            ``min_seen_length`` (a fragment).  None when unknown (no camera
            position or non-stem points given).
        base_gap: distance from p_sb to the nearest non-stem point [m] (inf: none; NaN:
            unknown).
        occluder_front: how far in front of the stem's continuation, just past its seen
            top end, the nearest non-stem point of its image neighbourhood lies [m]
            (negative: behind; NaN: none or unknown).
    """

    n_points: int
    n_top: int
    point_spacing: float
    radius: float
    residual: float
    spread_ratio: float
    base_uncertainty: float
    base_hidden: bool | None
    base_gap: float
    occluder_front: float


@dataclass(frozen=True)
class StemModel:
    """Result of :func:`fit_stem`.

    Attributes:
        valid: whether the two-segment model could be fitted.
        reason: why not, empty when ``valid``.
        points: ``(n_S, 3)`` stem points used [m] (as given, before any correction).
        top_mask: ``(n_S,)`` True for points of the top cluster T (all False when the
            clustering did not run); the others form the bottom cluster B.
        top: segment of T (n_st, l_t), ``None`` when invalid; ``top.start`` is p_sb.
        bottom: segment of B (n_sb, l_b), ``None`` when invalid.
        base: stem base p_sb [m] by ``stem_basend``, ``None`` when invalid.
        gap: distance between the top segment's crop end and the bottom segment's branch end
            [m], counted in ``length`` (0 with ``base_estimator="paper"``: the paper's l).
        quality: the fit's quality (:class:`StemQuality`), ``None`` when invalid.
    """

    valid: bool
    reason: str
    points: NDArray[np.float64]
    top_mask: NDArray[np.bool_]
    top: LineSegment | None = None
    bottom: LineSegment | None = None
    base: NDArray[np.float64] | None = None
    quality: StemQuality | None = None
    gap: float = 0.0

    @property
    def length(self) -> float:
        """Stem length l = l_t + gap + l_b [m] (the paper's l_t + l_b plus the unseen joint
        between the segments, e.g. a leaf across the middle); NaN when invalid."""
        if self.top is None or self.bottom is None:
            return float("nan")
        return self.top.length + self.gap + self.bottom.length

    def trusted(self, *, max_uncertainty: float = 0.004, min_points: int = 20) -> bool:
        """Whether p_sb can be used: valid, base not hidden, ``base_uncertainty`` <=
        ``max_uncertainty`` [m] and at least ``min_points`` stem points.

        A base of unknown visibility (``base_hidden is None``) is not trusted.
        """
        q = self.quality
        return bool(
            self.valid
            and q is not None
            and q.base_hidden is False
            and q.base_uncertainty <= max_uncertainty
            and q.n_points >= min_points
        )


def _principal_axes(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eigenvalues (descending) [m^2] and eigenvectors (columns) of the points' covariance."""
    centred = points - points.mean(axis=0)
    eigenvalues, eigenvectors = np.linalg.eigh(centred.T @ centred / points.shape[0])
    return np.maximum(eigenvalues[::-1], 0.0), eigenvectors[:, ::-1]


def _invalid(points: NDArray[np.float64], reason: str, top_mask: NDArray[np.bool_] | None = None) -> StemModel:
    if top_mask is None:
        top_mask = np.zeros(points.shape[0], dtype=bool)
    return StemModel(valid=False, reason=reason, points=points, top_mask=top_mask)


def _distinct_rows(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The distinct rows of an ``(n, 3)`` array, as ``np.unique(points, axis=0)`` finds them, in
    lexicographic order (compiled: 0.2 ms -> 0.03 ms on the ~400 points of an 848x480 frame's
    stem cluster)."""
    if points.shape[0] < 2:
        return points.copy()
    return _stem_kernels.distinct_rows(np.ascontiguousarray(points, dtype=np.float64))


def _point_spacing(points: NDArray[np.float64]) -> float:
    """Median nearest-neighbour distance [m] (the pixel pitch at the stem's range)."""
    # Over the distinct rows (duplicated points are not a finer sampling), the median of the
    # distances cKDTree(distinct).query(distinct, k=2) gives, in one compiled call (0.2 ms ->
    # 0.02 ms on 100 points, 0.45 -> ~0.1 ms on 800; see _stem_kernels).
    if points.shape[0] < 2:
        return 0.0
    return float(_stem_kernels.median_nearest_neighbour_distance(np.ascontiguousarray(points, dtype=np.float64)))


def _estimate_radius(
    points: NDArray[np.float64], labels: NDArray[np.intp], camera: NDArray[np.float64], pitch: float
) -> float:
    """Stem radius [m] from the width of each cluster across its axis, as seen from the camera.

    The seen width of a cylinder of radius r is 2 r wherever it is seen from; pixels sample it
    uniformly, k pixels of pitch p across: std = p sqrt((k^2 - 1) / 12) and 2 r = k p, so
    r = sqrt(3 std^2 + p^2 / 4).  Clusters are weighted by their point counts.
    """
    weighted, total = 0.0, 0
    for label in (0, 1):
        cluster = points[labels == label]
        if cluster.shape[0] < 3:
            continue
        centre = cluster.mean(axis=0)
        axis = _principal_axes(cluster)[1][:, 0]
        ray = centre - camera
        across = np.cross(axis, ray)
        norm = np.linalg.norm(across)
        if norm == 0.0:
            continue
        width = (cluster - centre) @ (across / norm)
        weighted += cluster.shape[0] * float(np.sqrt(3.0 * width.var() + 0.25 * pitch * pitch))
        total += cluster.shape[0]
    return weighted / total if total else 0.0


def _base_visibility(
    base: NDArray[np.float64],
    direction: NDArray[np.float64],
    radius: float,
    pitch: float,
    camera: NDArray[np.float64],
    non_stem: NDArray[np.float64],
    *,
    max_gap: float,
    probe_length: float,
    max_front: float,
) -> tuple[bool, float, float]:
    """Whether the stem's base is hidden, from the non-stem points around its seen top end.

    A stem hangs from a branch, so where the base is in view, non-stem points (the branch)
    lie next to the seen top end: within ``max_gap`` [m] of it.  Where the branch or a leaf
    hides the base, the nearest non-stem points are the occluder's, in front of the stem and
    further away.  A second test catches an occluder next to other non-stem surface: the
    image neighbourhood (within ``radius + pitch`` of the view ray) of the stem's
    continuation, up to ``probe_length`` past the end, holds a point more than
    ``max_front`` [m] in front of it (more than the branch the stem hangs from can be).

    Returns:
        (hidden, gap [m], front [m]): gap is the distance from p_sb to the nearest non-stem
        point (inf: none), front how far in front of the continuation the nearest point of
        its neighbourhood lies (NaN: none).
    """
    # Both tests only look at points seen near the base's direction: one pass over the frame
    # keeps those inside a cone around it (a leaf in front of the base is in the cone too).
    to_base = base - camera
    base_range = float(np.linalg.norm(to_base))
    # |p - c|^2 and (p - c).u through products with the (n, 3) array itself: no (n, 3)
    # temporaries, which dominate the cost on 848x480 frames (10^5 points).
    unit = to_base / base_range
    # einsum, not the matrix-vector product: numpy's BLAS gemv is several times slower on
    # (n, 3) arrays (measured 1 ms vs 8-16 ms for 2e5 points).
    squared_ranges = np.einsum("ij,ij->i", non_stem, non_stem) - 2.0 * np.einsum("ij,j->i", non_stem, camera)
    squared_ranges += camera @ camera
    along_base = np.einsum("ij,j->i", non_stem, unit) - camera @ unit
    cone = (max(max_gap, probe_length + radius + 2.0 * pitch) + pitch) / max(base_range - max_gap, 1e-3)
    cosine = np.cos(min(cone, 0.5))
    in_cone = (along_base > 0.0) & (along_base * along_base > cosine * cosine * squared_ranges)
    rays = np.compress(in_cone, non_stem, axis=0) - camera
    if rays.shape[0] == 0:
        return True, float("inf"), float("nan")
    ranges = np.sqrt(np.einsum("ij,ij->i", rays, rays))
    offsets = rays - to_base
    gap = float(np.sqrt(np.einsum("ij,ij->i", offsets, offsets).min()))
    units = rays / ranges[:, None]
    front = -np.inf
    n_probes = max(2, int(np.ceil(probe_length / max(pitch, 1e-4))) + 1)
    for probe in base - np.outer(np.linspace(0.0, probe_length, n_probes), direction):
        ray = probe - camera
        depth = float(np.linalg.norm(ray))
        ray /= depth
        along = units @ ray
        # Distance between the probe and each point's view ray, at the probe's range.
        close = depth * np.sqrt(np.maximum(0.0, 1.0 - along * along)) < radius + pitch
        if close.any():
            front = max(front, float(depth - (ranges[close] * along[close]).min()))
    front = float("nan") if front == -np.inf else front
    hidden = bool(gap > max_gap or (np.isfinite(front) and front > max_front))
    return hidden, gap, front


def fit_stem(
    stem_points: ArrayLike,
    gripper_position: ArrayLike,
    *,
    camera_position: ArrayLike | None = None,
    non_stem_points: ArrayLike | None = None,
    stem_radius: float | None = None,
    min_points: int = 10,
    min_cluster_points: int = 3,
    min_length: float = 0.005,
    max_residual: float = 0.005,
    max_spread_ratio: float | None = None,
    base_estimator: str = "extent",
    end_quantile: float = 0.02,
    max_base_gap: float = 0.011,
    probe_length: float = 0.004,
    max_front: float = 0.06,
    min_seen_length: float = 0.02,
    kmeans_iterations: int = 10,
) -> StemModel:
    """Fit the two-segment stem model, the stem base p_sb (``stem_basend``) and its quality.

    Args:
        stem_points: ``(n_S, 3)`` finite stem points S [m].
        gripper_position: grasping arm tip p_g [m]; the cluster whose mean is further from
            it is the top cluster T.
        camera_position: camera position p_c [m] of the frame; enables the near-surface
            correction (points moved pi r / 4 away from the camera along their rays).
        non_stem_points: ``(n, 3)`` the frame's other points W - S [m]; with
            ``camera_position``, tells whether the base is hidden (``quality.base_hidden``).
        stem_radius: known stem radius [m]; ``None`` estimates it from the points.
        min_points: fewer stem points give an invalid model.
        min_cluster_points: a cluster with fewer points gives an invalid model.
        min_length: a stem whose estimated length sqrt(12 lambda_1) along its major axis is
            below this [m] (e.g. duplicated or coincident points), or with a cluster
            shorter than half of it (a clump), is invalid.
        max_residual: a cluster whose RMS distance from its axis exceeds this [m] is not a
            stem (a blob, or two objects) and makes the model invalid; a 4 mm-radius stem
            has about 2.3 mm.
        max_spread_ratio: optional extra check, a cluster whose second/first PCA
            standard-deviation ratio exceeds this is invalid (``None``: no check; 0.5, the
            former default, rejects most thick stems seen from 0.3 m).
        base_estimator: ``"extent"`` (the top end of the seen top cluster, default) or
            ``"paper"`` (mean(T) - (l_t / 2) n_st with l_t = sqrt(12 lambda_1)).
        end_quantile: the segment ends are placed from the points' ``end_quantile`` and
            ``1 - end_quantile`` quantiles along the axis, extrapolated to a uniform spread's
            ends (robust to depth noise; 0 uses the extreme points).
        max_base_gap: the base is hidden when no non-stem point lies within this distance
            [m] of p_sb (a seen base touches the branch; measured on lab frames: 2-11 mm where
            the base is seen, 6-28 mm where it is hidden).
        probe_length: how far past the seen top end the occlusion-boundary test looks [m].
        max_front: the base is hidden when a non-stem point in the image neighbourhood of the
            stem's continuation lies more than this [m] in front of it.
        min_seen_length: a seen stem shorter than this [m] (a fragment, the rest hidden)
            marks the base as hidden too (stems are 50-70 mm long).
        kmeans_iterations: Lloyd iterations of the 2-means clustering (the initialisation
            along the major axis is already close, so few are needed).

    Returns:
        A :class:`StemModel`; check ``valid`` (and ``trusted()`` or ``quality``) before using
        ``base``.

    Raises:
        InvalidInputError: wrong shapes, NaN/inf rows or invalid parameters.
    """
    points = as_finite_points("stem_points", stem_points)
    gripper = as_point("gripper_position", gripper_position)
    camera = None if camera_position is None else as_point("camera_position", camera_position)
    non_stem = None if non_stem_points is None else as_finite_points("non_stem_points", non_stem_points)
    known_radius = None if stem_radius is None else as_positive_scalar(stem_radius, "stem_radius", allow_zero=True)
    min_points = positive_int("min_points", min_points, minimum=2)
    min_cluster_points = positive_int("min_cluster_points", min_cluster_points, minimum=2)
    min_length = as_positive_scalar(min_length, "min_length")
    max_residual = as_positive_scalar(max_residual, "max_residual")
    if max_spread_ratio is not None:
        max_spread_ratio = as_positive_scalar(max_spread_ratio, "max_spread_ratio")
    if base_estimator not in ("extent", "paper"):
        raise InvalidInputError(f"base_estimator must be 'extent' or 'paper', got {base_estimator!r}")
    end_quantile = as_positive_scalar(end_quantile, "end_quantile", allow_zero=True)
    if end_quantile >= 0.25:
        raise InvalidInputError(f"end_quantile must be in [0, 0.25), got {end_quantile!r}")
    max_base_gap = as_positive_scalar(max_base_gap, "max_base_gap")
    probe_length = as_positive_scalar(probe_length, "probe_length")
    max_front = as_positive_scalar(max_front, "max_front")
    min_seen_length = as_positive_scalar(min_seen_length, "min_seen_length", allow_zero=True)
    kmeans_iterations = positive_int("kmeans_iterations", kmeans_iterations)

    n_points = points.shape[0]
    if n_points < min_points:
        return _invalid(points, f"too few stem points: {n_points} < min_points={min_points}")
    eigenvalues, axes = _principal_axes(points)
    if np.sqrt(12.0 * eigenvalues[0]) < min_length:
        return _invalid(points, f"stem points span less than min_length={min_length} m along any axis")

    # Deterministic 2-means: start from the centroid +- one standard deviation along the
    # major axis, close to the optimum for points spread along a (bent) line.
    centre = points.mean(axis=0)
    offset = np.sqrt(eigenvalues[0]) * axes[:, 0]
    initial = np.stack((centre - offset, centre + offset))
    # The labels of scipy's kmeans2(points, initial, iter=kmeans_iterations, minit="matrix",
    # missing="raise"), compiled (0.16 -> 0.03 ms; see _stem_kernels).
    labels = np.empty(n_points, dtype=np.int32)
    if not _stem_kernels.kmeans_labels(np.ascontiguousarray(points), initial, kmeans_iterations, labels):
        return _invalid(points, "k-means left a cluster empty")
    first = labels == 0
    sizes = (int(np.count_nonzero(first)), n_points - int(np.count_nonzero(first)))
    if min(sizes) < min_cluster_points:
        return _invalid(points, f"a stem cluster has {min(sizes)} < min_cluster_points={min_cluster_points} points")

    # Top = the cluster whose mean is further from the gripper (attached to the branch).
    means = (points[first].mean(axis=0), points[~first].mean(axis=0))
    top_index = 0 if np.linalg.norm(means[0] - gripper) >= np.linalg.norm(means[1] - gripper) else 1
    top_mask = first if top_index == 0 else ~first

    pitch = _point_spacing(points)
    radius = 0.0
    corrected = points
    if camera is not None:
        # Only the near half of the stem is seen: its points lie pi r / 4 in front of the
        # axis on average.  Move each one that far away from the camera along its ray.
        radius = _estimate_radius(points, labels, camera, pitch) if known_radius is None else known_radius
        rays = points - camera
        rays /= np.linalg.norm(rays, axis=1)[:, None]
        corrected = points + (0.25 * np.pi * radius) * rays
    elif known_radius is not None:
        radius = known_radius
    clusters = (corrected[first], corrected[~first])
    means = (clusters[0].mean(axis=0), clusters[1].mean(axis=0))
    top_to_bottom = means[1 - top_index] - means[top_index]

    segments = []
    spread_ratios, squared_residuals = [], 0.0
    top_end = None
    for name, index in (("top", top_index), ("bottom", 1 - top_index)):
        cluster = clusters[index]
        cluster_eigenvalues, cluster_axes = _principal_axes(cluster)
        if cluster_eigenvalues[0] <= 0.0:
            return _invalid(points, f"the {name} cluster has all its points in one spot", top_mask)
        if np.sqrt(12.0 * cluster_eigenvalues[0]) < 0.5 * min_length:
            return _invalid(
                points, f"the {name} cluster spans less than min_length / 2 = {0.5 * min_length} m: a clump", top_mask
            )
        spread_ratio = float(np.sqrt(cluster_eigenvalues[1] / cluster_eigenvalues[0]))
        spread_ratios.append(spread_ratio)
        residual = float(np.sqrt(cluster_eigenvalues[1] + cluster_eigenvalues[2]))
        squared_residuals += cluster.shape[0] * residual * residual
        if residual > max_residual:
            return _invalid(
                points,
                f"the {name} cluster is not line-like: RMS distance from its axis {residual * 1e3:.1f} mm > "
                f"max_residual={max_residual * 1e3:.1f} mm",
                top_mask,
            )
        if max_spread_ratio is not None and spread_ratio > max_spread_ratio:
            return _invalid(
                points,
                f"the {name} cluster is not line-like: spread ratio {spread_ratio:.2f} > "
                f"max_spread_ratio={max_spread_ratio}",
                top_mask,
            )
        direction = cluster_axes[:, 0]
        # Orient both axes from the branch towards the crop, i.e. towards the bottom cluster.
        if direction @ top_to_bottom < 0.0:
            direction = -direction
        mean = means[index]
        if base_estimator == "paper":
            length = float(np.sqrt(12.0 * cluster_eigenvalues[0]))
            segments.append(LineSegment(centroid=mean, direction=direction, length=length))
            continue
        # Extent along the axis from the end_quantile quantiles, extrapolated to the ends of a
        # uniform spread (so that a few noisy points past an end do not stretch the stem);
        # each end sample also stands for half a pixel beyond its centre.
        along = (cluster - mean) @ direction
        # Duplicated points are not a denser sampling: the quantiles are taken over distinct ones.
        distinct_along = (_distinct_rows(cluster) - mean) @ direction
        # The linear quantiles (numpy's default method) by one interpolation on the sorted values:
        # np.quantile's call overhead was ~30 % of fit_stem on a 283x160 frame's ~45 points.
        last = distinct_along.shape[0] - 1
        q_low, q_high = np.interp((end_quantile * last, (1.0 - end_quantile) * last), np.arange(last + 1.0),
                                  np.sort(distinct_along))
        stretch = end_quantile / (1.0 - 2.0 * end_quantile) * (q_high - q_low)
        low, high = float(q_low - stretch) - 0.5 * pitch, float(q_high + stretch) + 0.5 * pitch
        if name == "top":
            # The top end: across the axis, where the points within a pixel of the end are;
            # along it, the end.
            end_slab = cluster[along <= max(low + 1.5 * pitch, float(along.min()))]
            across = end_slab.mean(axis=0) - mean
            across -= (across @ direction) * direction
            top_end = end_slab.shape[0]
            start = mean + across + low * direction
        else:
            start = mean + low * direction
        length = high - low
        segments.append(LineSegment(centroid=start + 0.5 * length * direction, direction=direction, length=length))
    top, bottom = segments
    base = top.start  # stem_basend: mean(T) - (l_t / 2) n_st with the segment's midpoint as mean(T)

    n_top = int(np.count_nonzero(top_mask))
    residual_rms = float(np.sqrt(squared_residuals / n_points))
    # 1-sigma error budget of p_sb: the end's position along the axis (a pixel, uniform: p /
    # sqrt(12), doubled for the ragged end of a cylinder cut by a curved silhouette), the radius
    # correction (pi/4 of the radius error, about p / 2), and the scatter across the axis of
    # the points that place the end.
    end_points = top_end if top_end is not None else n_top
    base_uncertainty = float(
        np.sqrt(
            (2.0 * pitch / np.sqrt(12.0)) ** 2
            + (0.25 * np.pi * 0.5 * pitch) ** 2 * (camera is not None)
            + residual_rms**2 / max(end_points, 1)
        )
    )
    base_hidden, base_gap, occluder_front = None, float("nan"), float("nan")
    if camera is not None and non_stem is not None:
        base_hidden, base_gap, occluder_front = _base_visibility(
            base, top.direction, radius, pitch, camera, non_stem,
            max_gap=max_base_gap, probe_length=probe_length, max_front=max_front,
        )  # fmt: skip
        # A short fragment (the rest hidden) cannot vouch for where its top end is.
        base_hidden = base_hidden or top.length + bottom.length < min_seen_length  # seen parts only
    quality = StemQuality(
        n_points=n_points,
        n_top=n_top,
        point_spacing=pitch,
        radius=radius,
        residual=residual_rms,
        spread_ratio=max(spread_ratios),
        base_uncertainty=base_uncertainty,
        base_hidden=base_hidden,
        base_gap=base_gap,
        occluder_front=occluder_front,
    )
    gap = 0.0 if base_estimator == "paper" else float(np.linalg.norm(bottom.start - top.end))
    return StemModel(
        valid=True, reason="", points=points, top_mask=top_mask, top=top, bottom=bottom, base=base, quality=quality,
        gap=gap,
    )  # fmt: skip
