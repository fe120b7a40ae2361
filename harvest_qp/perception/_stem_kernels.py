"""Compiled (numba) kernels of :func:`harvest_qp.perception.stem.fit_stem`.

Both replace a library call on the ~100-1,000 stem points of a frame whose Python overhead
was most of its cost, with the same arithmetic, so the same bits (checked against the
library calls in ``tests/perception/test_compiled_paths.py``):

* :func:`nearest_neighbour_distances`: what ``cKDTree(p).query(p, k=2)[0][:, 1]`` returns
  (squared distance summed over x, y, z in that order, then its square root), by a sweep
  along x over the points sorted by x;
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
    order = np.argsort(points[:, 0])
    xs = np.empty(n)
    for p in range(n):
        xs[p] = points[order[p], 0]
    out = np.empty(n)
    for p in range(n):
        i = order[p]
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        best = np.inf
        # Neighbours in x order, outwards while the x gap alone is below the best distance:
        # a farther point has d >= dx * dx >= best and cannot be strictly closer.
        q = p - 1
        while q >= 0:
            dx = x - xs[q]
            if dx * dx >= best:
                break
            j = order[q]
            dy = y - points[j, 1]
            dz = z - points[j, 2]
            d = dx * dx + dy * dy + dz * dz
            if d < best:
                best = d
            q -= 1
        q = p + 1
        while q < n:
            dx = x - xs[q]
            if dx * dx >= best:
                break
            j = order[q]
            dy = y - points[j, 1]
            dz = z - points[j, 2]
            d = dx * dx + dy * dy + dz * dz
            if d < best:
                best = d
            q += 1
        out[i] = np.sqrt(best)
    return out


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
    for _ in range(iterations):
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
            labels[i] = label
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
