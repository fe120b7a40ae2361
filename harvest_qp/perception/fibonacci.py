"""Spherical Fibonacci lattice and its O(1) nearest-point inverse mapping.

Section ``subsec:scePC_proc`` samples the sphere S(p_sb, l) with a Fibonacci lattice and
matches every projected obstacle to its nearest lattice point "without resorting to an
exhaustive search", citing Keinert et al., *Spherical Fibonacci Mapping*, ACM TOG 34(6),
2015.  This module implements exactly the lattice that inverse mapping inverts,

    phi_i = 2 pi frac(i (Phi - 1)),    z_i = 1 - (2 i + 1) / n,    i = 0 .. n-1,

on the unit sphere (callers scale and translate).  Golden-angle or pole-including variants
are different lattices and would not match :func:`nearest_fibonacci_index`.

Two details make the inverse mapping exact in float64 (checked against a KD-tree oracle
in the tests, see also ``STACK_NOTES.md``):

* pole mirroring: the lattice is symmetric under (phi, z) -> (phi_{n-1} - phi, -z) with
  i -> n-1-i, so southern points are mirrored to the north, where the local lattice basis
  estimate is well conditioned, and their index is mirrored back;
* candidate indices are clipped to [0, n-1] near the poles, where the cell found by the
  basis inversion can reach past the first or last lattice point.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_finite_points, positive_int

__all__ = ["GOLDEN_RATIO", "fibonacci_sphere", "nearest_fibonacci_index"]

GOLDEN_RATIO = (1.0 + np.sqrt(5.0)) / 2.0
_TWO_PI = 2.0 * np.pi
# The four corners (u, v) in {0, 1}^2 of the lattice cell that contains a point.
_CELL_CORNERS = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])


def _lattice_azimuth(index: NDArray[np.float64]) -> NDArray[np.float64]:
    """phi_i = 2 pi frac(i (Phi - 1)) [rad] for (float-valued) integer indices."""
    turns = index * (GOLDEN_RATIO - 1.0)
    return _TWO_PI * (turns - np.floor(turns))


def _lattice_points(index: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """Unit vectors of the lattice points with the given (float-valued) indices."""
    phi = _lattice_azimuth(index)
    z = 1.0 - (2.0 * index + 1.0) / n
    sin_theta = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack((np.cos(phi) * sin_theta, np.sin(phi) * sin_theta, z), axis=-1)


def fibonacci_sphere(n: int) -> NDArray[np.float64]:
    """The ``n``-point spherical Fibonacci lattice on the unit sphere, shape ``(n, 3)``.

    Point i has azimuth phi_i = 2 pi frac(i (Phi - 1)) and height z_i = 1 - (2i + 1)/n, the
    lattice sampled in ``subsec:scePC_proc`` (Fig. ``fig:PC_proc_4``).  Scale by the radius
    [m] and add the centre [m] for the sphere S(p_sb, l).
    """
    n = positive_int("n", n)
    return _lattice_points(np.arange(n, dtype=np.float64), n)


def nearest_fibonacci_index(points: ArrayLike, n: int) -> NDArray[np.intp]:
    """Index of the nearest :func:`fibonacci_sphere` point for each direction, in O(1) each.

    Implements the inverse spherical Fibonacci mapping of Keinert et al. (2015), used in
    ``subsec:scePC_proc`` to find the lattice sample nearest to every projected obstacle
    without an exhaustive search.

    Args:
        points: ``(m, 3)`` directions; unit vectors are expected, other non-zero vectors are
            normalised first.  ``m`` may be 0.
        n: number of lattice points (>= 1).

    Returns:
        ``(m,)`` integer indices in ``[0, n-1]``.

    Raises:
        InvalidInputError: wrong shape, NaN/inf rows or zero vectors.
    """
    n = positive_int("n", n)
    directions = as_finite_points("points", points)
    if directions.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    norms = np.linalg.norm(directions, axis=1)
    if not (norms > 0.0).all():
        raise InvalidInputError(f"points must be non-zero directions; row {int(np.argmin(norms))} is the zero vector")
    return nearest_index_of_unit_vectors(directions / norms[:, None], n)


def nearest_index_of_unit_vectors(directions: NDArray[np.float64], n: int) -> NDArray[np.intp]:
    """:func:`nearest_fibonacci_index` without input checks, for ``(m, 3)`` unit vectors."""
    if n == 1:
        return np.zeros(directions.shape[0], dtype=np.intp)

    # Pole mirroring: solve every point in the northern hemisphere, where the basis estimate
    # below is well conditioned, then map the index back (i -> n-1-i).
    south = directions[:, 2] < 0.0
    z = np.abs(directions[:, 2])
    phi = np.arctan2(directions[:, 1], directions[:, 0])
    last_azimuth = _lattice_azimuth(np.array(n - 1.0))
    phi = np.where(south, last_azimuth - phi, phi)
    phi = np.mod(phi + np.pi, _TWO_PI) - np.pi  # the lattice is 2 pi periodic in phi

    # Local lattice basis: two consecutive Fibonacci numbers F_k, F_{k+1} whose index steps
    # are the shortest lattice vectors at this height (Keinert et al. 2015).
    with np.errstate(divide="ignore"):
        zoom = np.log(n * np.pi * np.sqrt(5.0) * (1.0 - z * z)) / np.log(GOLDEN_RATIO**2)
    k = np.maximum(2.0, np.floor(zoom))
    fib_k = GOLDEN_RATIO**k / np.sqrt(5.0)
    f0 = np.round(fib_k)
    f1 = np.round(fib_k * GOLDEN_RATIO)

    # Basis matrix B = [[dphi(F0), dphi(F1)], [dz(F0), dz(F1)]]: an index step of F moves
    # phi by the signed fractional part of F (Phi - 1) turns and z by -2F/n.
    def azimuth_step(fib: NDArray[np.float64]) -> NDArray[np.float64]:
        turns = (fib + 1.0) * (GOLDEN_RATIO - 1.0)
        return _TWO_PI * (turns - np.floor(turns)) - _TWO_PI * (GOLDEN_RATIO - 1.0)

    b00, b01 = azimuth_step(f0), azimuth_step(f1)
    b10, b11 = -2.0 * f0 / n, -2.0 * f1 / n
    determinant = b00 * b11 - b01 * b10
    # Cell containing (phi, z) in lattice coordinates, relative to point 0 at z = 1 - 1/n.
    dz = z - (1.0 - 1.0 / n)
    cell_u = np.floor((b11 * phi - b01 * dz) / determinant)
    cell_v = np.floor((-b10 * phi + b00 * dz) / determinant)

    # The nearest lattice point is one of the four corners of that cell; clipping keeps
    # corners past the first or last point valid near the poles.
    corners = f0[:, None] * (cell_u[:, None] + _CELL_CORNERS[:, 0]) + f1[:, None] * (
        cell_v[:, None] + _CELL_CORNERS[:, 1]
    )
    corners = np.minimum(np.maximum(corners, 0.0), n - 1.0).astype(np.intp)
    # Mirror the candidates back instead of the point: the mirroring is an isometry, so the
    # candidate nearest to the mirrored point is the mirror of the one nearest to the point.
    corners = np.where(south[:, None], n - 1 - corners, corners)
    # Unit vectors: the nearest candidate has the largest dot product.
    alignment = np.einsum("mcj,mj->mc", _candidate_points(corners, n), directions)
    return corners[np.arange(corners.shape[0]), np.argmax(alignment, axis=1)]


# Lattices up to this size are cached (<= 1.5 MB each), so candidates are looked up instead
# of recomputed with trigonometry, which dominates the cost of the inverse mapping.
_CACHED_LATTICE_MAX_N = 1 << 16


@functools.lru_cache(maxsize=8)
def _cached_lattice(n: int) -> NDArray[np.float64]:
    lattice = fibonacci_sphere(n)
    lattice.flags.writeable = False
    return lattice


def _candidate_points(index: NDArray[np.intp], n: int) -> NDArray[np.float64]:
    """Unit vectors of lattice points ``index`` (any shape), shape ``index.shape + (3,)``."""
    if n <= _CACHED_LATTICE_MAX_N:
        return np.take(_cached_lattice(n), index, axis=0)
    return _lattice_points(index.astype(np.float64), n)
