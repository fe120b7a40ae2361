"""Two-segment stem model and stem base p_sb (``subsec:scePC_proc``, ``stem_basend``).

The stem cloud S is split into two clusters by k-means, named "top" (further from the
gripper, attached to the branch) and "bottom" (closer to the gripper, attached to the
crop).  A PCA line segment is fitted to each; the stem length is l = l_t + l_b and the stem
base is the branch end of the top segment,

    p_sb = mean(T) - (l_t / 2) n_st,                                     (stem_basend)

with n_st oriented from the branch towards the bottom cluster.

Segment length.  The paper does not say how l_t and l_b are measured.  We use the length of
a uniform segment with the same variance along the PCA axis, l = sqrt(12 lambda_1): unlike
the extent max - min it is not inflated by the noise at the segment ends (1 mm depth noise
would move p_sb by about 2.5 mm), and it places the segment's midpoint at the cluster mean,
which is what ``stem_basend`` assumes.

A stem that cannot be modelled (too few points, all points in one spot, a cluster that is
not line-like) gives a :class:`StemModel` with ``valid=False`` and a ``reason``, never an
exception from numpy or scipy internals.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.cluster.vq import ClusterError, kmeans2

from harvest_qp.perception._validation import as_finite_points, as_point, positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = ["LineSegment", "StemModel", "fit_stem"]


@dataclass(frozen=True)
class LineSegment:
    """A PCA line segment fitted to a stem cluster.

    Attributes:
        centroid: cluster mean, the segment midpoint [m].
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
class StemModel:
    """Result of :func:`fit_stem`.

    Attributes:
        valid: whether the two-segment model could be fitted.
        reason: why not, empty when ``valid``.
        points: ``(n_S, 3)`` stem points used [m].
        top_mask: ``(n_S,)`` True for points of the top cluster T (all False when the
            clustering did not run); the others form the bottom cluster B.
        top: segment of T (n_st, l_t), ``None`` when invalid.
        bottom: segment of B (n_sb, l_b), ``None`` when invalid.
        base: stem base p_sb [m] by ``stem_basend``, ``None`` when invalid.
    """

    valid: bool
    reason: str
    points: NDArray[np.float64]
    top_mask: NDArray[np.bool_]
    top: LineSegment | None = None
    bottom: LineSegment | None = None
    base: NDArray[np.float64] | None = None

    @property
    def length(self) -> float:
        """Stem length l = l_t + l_b [m]; NaN when invalid."""
        if self.top is None or self.bottom is None:
            return float("nan")
        return self.top.length + self.bottom.length


def _principal_axes(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Eigenvalues (descending) [m^2] and eigenvectors (columns) of the points' covariance."""
    centred = points - points.mean(axis=0)
    eigenvalues, eigenvectors = np.linalg.eigh(centred.T @ centred / points.shape[0])
    return np.maximum(eigenvalues[::-1], 0.0), eigenvectors[:, ::-1]


def _invalid(points: NDArray[np.float64], reason: str, top_mask: NDArray[np.bool_] | None = None) -> StemModel:
    if top_mask is None:
        top_mask = np.zeros(points.shape[0], dtype=bool)
    return StemModel(valid=False, reason=reason, points=points, top_mask=top_mask)


def fit_stem(
    stem_points: ArrayLike,
    gripper_position: ArrayLike,
    *,
    min_points: int = 10,
    min_cluster_points: int = 3,
    min_length: float = 0.005,
    max_spread_ratio: float = 0.5,
    kmeans_iterations: int = 10,
) -> StemModel:
    """Fit the two-segment stem model and the stem base p_sb (``stem_basend``).

    Args:
        stem_points: ``(n_S, 3)`` finite stem points S [m].
        gripper_position: grasping arm tip p_g [m]; the cluster whose mean is further from
            it is the top cluster T.
        min_points: fewer stem points give an invalid model.
        min_cluster_points: a cluster with fewer points gives an invalid model.
        min_length: a stem whose estimated length sqrt(12 lambda_1) along its major axis is
            below this [m] (e.g. duplicated or coincident points) is invalid.
        max_spread_ratio: a cluster whose second/first PCA standard deviation ratio exceeds
            this is not line-like (a noisy blob) and makes the model invalid.  A straight
            (collinear) stem has a ratio near 0 and is valid.
        kmeans_iterations: Lloyd iterations of the 2-means clustering (the initialisation
            along the major axis is already close, so few are needed).

    Returns:
        A :class:`StemModel`; check ``valid`` before using ``base``.

    Raises:
        InvalidInputError: wrong shapes, NaN/inf rows or invalid parameters.
    """
    points = as_finite_points("stem_points", stem_points)
    gripper = as_point("gripper_position", gripper_position)
    min_points = positive_int("min_points", min_points, minimum=2)
    min_cluster_points = positive_int("min_cluster_points", min_cluster_points, minimum=2)
    min_length = as_positive_scalar(min_length, "min_length")
    max_spread_ratio = as_positive_scalar(max_spread_ratio, "max_spread_ratio")
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
    try:
        _, labels = kmeans2(
            points, initial, iter=kmeans_iterations, minit="matrix", missing="raise", check_finite=False
        )
    except ClusterError:
        return _invalid(points, "k-means left a cluster empty")
    first = labels == 0
    sizes = (int(np.count_nonzero(first)), n_points - int(np.count_nonzero(first)))
    if min(sizes) < min_cluster_points:
        return _invalid(points, f"a stem cluster has {min(sizes)} < min_cluster_points={min_cluster_points} points")

    # Top = the cluster whose mean is further from the gripper (attached to the branch).
    clusters = (points[first], points[~first])
    means = (clusters[0].mean(axis=0), clusters[1].mean(axis=0))
    top_index = 0 if np.linalg.norm(means[0] - gripper) >= np.linalg.norm(means[1] - gripper) else 1
    top_mask = first if top_index == 0 else ~first
    top_to_bottom = means[1 - top_index] - means[top_index]

    segments = []
    for name, index in (("top", top_index), ("bottom", 1 - top_index)):
        cluster_eigenvalues, cluster_axes = _principal_axes(clusters[index])
        if cluster_eigenvalues[0] <= 0.0:
            return _invalid(points, f"the {name} cluster has all its points in one spot", top_mask)
        spread_ratio = np.sqrt(cluster_eigenvalues[1] / cluster_eigenvalues[0])
        if spread_ratio > max_spread_ratio:
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
        length = float(np.sqrt(12.0 * cluster_eigenvalues[0]))
        segments.append(LineSegment(centroid=means[index], direction=direction, length=length))
    top, bottom = segments
    base = top.centroid - 0.5 * top.length * top.direction  # stem_basend: mean(T) - (l_t / 2) n_st
    return StemModel(valid=True, reason="", points=points, top_mask=top_mask, top=top, bottom=bottom, base=base)
