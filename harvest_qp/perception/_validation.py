"""Point-cloud input checks for the perception modules.

Every public function validates its arguments so that a wrong shape or a non-finite value
fails early with an :class:`~harvest_qp.exceptions.InvalidInputError` that names the
argument and what was expected, instead of a numpy error deep inside.  Scalars and vectors
use the package-wide checks of :mod:`harvest_qp.validation`; the point-cloud checks live here.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.validation import as_vector


def _as_float_array(name: str, value: ArrayLike) -> NDArray[np.float64]:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise InvalidInputError(f"{name} must be numeric, got {type(value).__name__}: {error}") from None


def as_points(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """``value`` as an ``(n, 3)`` float64 array (``n`` may be 0); rows are not checked for finiteness."""
    points = _as_float_array(name, value)
    if points.shape in ((0,), (0, 0)):
        return points.reshape(0, 3)  # [] and np.empty(0) mean "no points" too
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (n, 3), got shape {points.shape}")
    return points


def as_finite_points(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """``value`` as an ``(n, 3)`` float64 array whose entries are all finite."""
    points = as_points(name, value)
    if not np.isfinite(points).all():  # whole-array test first: 20x faster than per row
        bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
        raise InvalidInputError(
            f"{name} must contain only finite values; {bad.size} row(s) contain NaN or inf (first at row {bad[0]})"
        )
    return points


def as_grid_points(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """Finite ``(n, 3)`` points within 1000 km of the origin [m] (cell keys stay far from integer overflow)."""
    points = as_finite_points(name, value)
    if points.shape[0] and np.abs(points).max() > 1e6:
        raise InvalidInputError(
            f"{name} must lie within 1000 km of the origin [m], got a coordinate {np.abs(points).max()}"
        )
    return points


def as_point(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """``value`` as a finite ``(3,)`` float64 vector; unlike :func:`as_vector`, a scalar is an
    error here (a position is never the same number on all axes by intent)."""
    if np.ndim(value) == 0:
        raise InvalidInputError(f"{name} must have shape (3,), got the scalar {value!r}")
    return as_vector(value, 3, name)


def as_unit_vector(name: str, value: ArrayLike, *, min_norm: float = 1e-9) -> NDArray[np.float64]:
    """``value``, a finite ``(3,)`` vector of norm at least ``min_norm``, scaled to unit length (by its
    largest entry first, so that entries near the float range do not overflow the norm)."""
    vector = as_vector(value, 3, name)
    scale = float(np.abs(vector).max())
    scaled = vector / scale if scale > 0.0 else vector
    length = float(np.linalg.norm(scaled))
    if scale * length < min_norm:
        raise InvalidInputError(f"{name} must be a non-zero vector, got {value!r}")
    return scaled / length


def as_mask(name: str, value: ArrayLike, n: int) -> NDArray[np.bool_]:
    """``value`` as a boolean ``(n,)`` mask; integer 0/1 labels are accepted."""
    mask = np.asarray(value)
    if mask.shape != (n,):
        raise InvalidInputError(f"{name} must have shape ({n},) to match the points, got shape {mask.shape}")
    if mask.dtype == np.bool_:
        return mask
    if not np.issubdtype(mask.dtype, np.integer) or not np.isin(mask, (0, 1)).all():
        raise InvalidInputError(f"{name} must be boolean (or 0/1 integer labels), got dtype {mask.dtype}")
    return mask.astype(bool)


def positive_int(name: str, value: int, *, minimum: int = 1) -> int:
    """``value`` as an int >= ``minimum`` (bools are rejected)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise InvalidInputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)
