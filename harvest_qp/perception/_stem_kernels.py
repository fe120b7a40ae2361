"""Compiled (numba) kernels of :func:`harvest_qp.perception.stem.fit_stem`.

Each replaces a library call on the ~100-1,000 stem points of a frame whose Python overhead
was most of its cost (together ~0.5 ms per approach frame), and is tested against that
library call in ``tests/perception/test_kernels.py``:

* :func:`nearest_neighbour_distances`: what ``cKDTree(p).query(p, k=2)[0][:, 1]`` returns
  (squared distance summed over x, y, z in that order, then its square root), by a sweep
  along the coordinate axis of the largest extent (a stem's length: fewer points within the
  sweep's window than along x) over the points sorted along it;
* :func:`distinct_rows`: the rows ``np.unique(points, axis=0)`` keeps, in lexicographic order;
* :func:`median_nearest_neighbour_distance`: ``np.median`` of the above over the distinct
  rows, in one call (the point spacing of ``fit_stem``);
* :func:`kmeans_labels`: the labels of ``scipy.cluster.vq.kmeans2(data, initial, iter,
  minit="matrix", missing="raise")`` (scipy's compiled ``vq``: the first code at the smallest
  squared distance summed per feature, and ``update_cluster_means``: per-cluster sums in
  point order divided by the count), with an empty cluster reported instead of raised.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def nearest_neighbour_distances(points):
    """``(n,)`` distance [m] from each of ``n >= 2`` distinct points to its nearest other point."""
    n = points.shape[0]
    # Sweep along the axis of the largest extent: the window of points whose gap along it is
    # below the nearest distance holds the fewest points there.
    axis, widest = 0, -1.0
    for a in range(3):
        extent = points[:, a].max() - points[:, a].min()
        if extent > widest:
            axis, widest = a, extent
    order = np.argsort(points[:, axis])
    keys = np.empty(n)
    for p in range(n):
        keys[p] = points[order[p], axis]
    out = np.empty(n)
    for p in range(n):
        i = order[p]
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        key = keys[p]
        best = np.inf
        # Neighbours in sweep order, outwards while the gap along the sweep axis alone is below
        # the best distance: a farther point has d >= gap * gap >= best (d adds non-negative
        # terms to the rounded gap * gap, and rounding is monotone) and cannot be strictly
        # closer.  d itself is summed over x, y, z in that order, whatever the sweep axis.
        for step in (-1, 1):
            q = p + step
            while 0 <= q < n:
                gap = key - keys[q]
                if gap * gap >= best:
                    break
                j = order[q]
                dx = x - points[j, 0]
                dy = y - points[j, 1]
                dz = z - points[j, 2]
                d = dx * dx + dy * dy + dz * dz
                if d < best:
                    best = d
                q += step
        out[i] = np.sqrt(best)
    return out


@njit(cache=True)
def _row_before(points, i, j):
    """Whether row i sorts strictly before row j by (y, z) (x being equal)."""
    if points[i, 1] != points[j, 1]:
        return points[i, 1] < points[j, 1]
    return points[i, 2] < points[j, 2]


@njit(cache=True)
def distinct_rows(points):
    """The distinct rows of ``(n, 3)`` finite ``points`` in lexicographic (x, y, z) order:
    those of ``np.lexsort((z, y, x))`` followed by dropping rows equal to their predecessor
    (a stable sort, so of equal rows the first in input order is kept, as with lexsort; -0.0
    and 0.0 compare equal in both)."""
    n = points.shape[0]
    order = np.argsort(points[:, 0], kind="mergesort")  # stable
    # Runs of equal x (few points each) by (y, z), stably, by insertion.
    start = 0
    while start < n:
        stop = start + 1
        x = points[order[start], 0]
        while stop < n and points[order[stop], 0] == x:
            stop += 1
        for a in range(start + 1, stop):
            row = order[a]
            b = a - 1
            while b >= start and _row_before(points, row, order[b]):
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = row
        start = stop
    out = np.empty((n, 3))
    m = 0
    for p in range(n):
        i = order[p]
        if m > 0 and points[i, 0] == out[m - 1, 0] and points[i, 1] == out[m - 1, 1] and points[i, 2] == out[m - 1, 2]:
            continue
        out[m, 0] = points[i, 0]
        out[m, 1] = points[i, 1]
        out[m, 2] = points[i, 2]
        m += 1
    return out[:m]


@njit(cache=True)
def median_nearest_neighbour_distance(points):
    """``np.median(nearest_neighbour_distances(distinct_rows(points)))`` [m]; 0.0 when fewer than
    two distinct rows.  The median as numpy takes it: the middle value, or the mean
    ``(a + b) / 2`` of the two middle ones (order-free, so the rows' order does not matter)."""
    distinct = distinct_rows(points)
    m = distinct.shape[0]
    if m < 2:
        return 0.0
    distances = np.sort(nearest_neighbour_distances(distinct))
    half = m // 2
    if m % 2 == 1:
        return distances[half]
    return (distances[half - 1] + distances[half]) / 2.0


@njit(cache=True)
def kmeans_labels(data, initial, iterations, labels):
    """Lloyd's iterations of k-means from the code book ``initial``; the labels of the last
    assignment go to ``labels``. Returns False when a cluster was left empty (scipy's
    ``ClusterError`` with ``missing="raise"``)."""
    n, n_features = data.shape
    k = initial.shape[0]
    code_book = initial.copy()
    sums = np.empty((k, n_features))
    counts = np.empty(k)
    for iteration in range(iterations):
        changed = iteration == 0
        for i in range(n):
            best = np.inf
            label = 0
            for j in range(k):
                dist = 0.0
                for f in range(n_features):
                    diff = code_book[j, f] - data[i, f]
                    dist += diff * diff
                if dist < best:
                    best = dist
                    label = j
            if labels[i] != label:
                changed = True
            labels[i] = label
        if not changed:
            # The same labels as the last iteration give the same code book (the same sums in
            # the same order) and so the same labels again: the remaining iterations are no-ops.
            return True
        sums[:, :] = 0.0
        counts[:] = 0.0
        for i in range(n):
            label = labels[i]
            for f in range(n_features):
                sums[label, f] += data[i, f]
            counts[label] += 1.0
        for j in range(k):
            if counts[j] == 0.0:
                return False
            for f in range(n_features):
                code_book[j, f] = sums[j, f] / counts[j]
    return True
