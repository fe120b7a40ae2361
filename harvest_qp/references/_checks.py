"""Argument checks of the reference laws (scalars and vectors via :mod:`harvest_qp.validation`).

Kept free of :mod:`harvest_qp.perception` imports: ``harvest_qp.perception`` re-exports the
unveiling law from :mod:`harvest_qp.references.unveiling`, so a module-level import in the other
direction would be circular.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.validation import as_matrix, as_positive_scalar, as_vector

_IDENTITY = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])

__all__ = ["as_points", "as_pose", "as_position", "as_positive_scalar", "as_time_step", "cross_rows"]


def cross_rows(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise a x b for two ``(n, 3)`` float arrays: np.cross's own arithmetic (per entry
    the same two products and one difference), without its axis moving (~20 us per call)."""
    a0, a1, a2 = a[:, 0], a[:, 1], a[:, 2]
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    out = np.empty((max(a.shape[0], b.shape[0]), 3))
    np.subtract(a1 * b2, a2 * b1, out=out[:, 0])
    np.subtract(a2 * b0, a0 * b2, out=out[:, 1])
    np.subtract(a0 * b1, a1 * b0, out=out[:, 2])
    return out


def as_position(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """A finite ``(3,)`` float64 vector [m]; a scalar is an error (never meant for a position)."""
    if type(value) is np.ndarray and value.shape == (3,):
        return as_vector(value, 3, name)  # not a scalar: np.ndim's dispatch skipped (per tick)
    if np.ndim(value) == 0:
        raise InvalidInputError(f"{name} must have shape (3,), got the scalar {value!r}")
    return as_vector(value, 3, name)


def as_pose(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """A finite ``(4, 4)`` homogeneous pose whose rotation block is orthonormal (to 1e-6).

    A float64 ``(4, 4)`` array (what the control loop hands, every tick) is checked on Python
    floats and returned as is (~2 us; the numpy form of the same test costs ~10 us); anything
    else is converted (a copy) and checked with numpy.
    """
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (4, 4):
        if _is_pose(value.tolist()):
            return value
    pose = as_matrix(value, (4, 4), name)
    rotation = pose[:3, :3]
    orthonormality = float(np.abs(rotation.T @ rotation - _IDENTITY).max())
    if not orthonormality <= 1e-6 or not float(np.abs(pose[3] - _LAST_ROW).max()) <= 1e-12:
        raise InvalidInputError(
            f"{name} must be a homogeneous pose (orthonormal rotation, last row 0 0 0 1), got\n{pose}"
        )
    return pose


def _is_pose(rows: list[list[float]]) -> bool:
    """Whether ``rows`` (a (4, 4) matrix as nested floats) is a finite homogeneous pose: R^T R = I
    to 1e-6 entry by entry, last row 0 0 0 1 to 1e-12. NaN fails every comparison."""
    (a, b, c, x), (d, e, f, y), (g, h, i, z), last = rows
    tol = 1e-6
    return (
        abs(a * a + d * d + g * g - 1.0) <= tol and abs(b * b + e * e + h * h - 1.0) <= tol
        and abs(c * c + f * f + i * i - 1.0) <= tol and abs(a * b + d * e + g * h) <= tol
        and abs(a * c + d * f + g * i) <= tol and abs(b * c + e * f + h * i) <= tol
        and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)
        and abs(last[0]) <= 1e-12 and abs(last[1]) <= 1e-12 and abs(last[2]) <= 1e-12 and abs(last[3] - 1.0) <= 1e-12
    )


def as_points(value: ArrayLike, name: str) -> NDArray[np.float64]:
    """A finite ``(n, 3)`` float64 array [m]; ``n`` may be 0 (``[]`` means no points)."""
    try:
        points = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be numeric with shape (n, 3), got {type(value).__name__}") from None
    if points.size == 0:
        return points.reshape(0, 3)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"{name} must have shape (n, 3), got shape {points.shape}")
    if not np.isfinite(points).all():
        raise InvalidInputError(f"{name} must contain only finite values (no NaN or inf)")
    return points


def as_time_step(dt: float) -> float:
    """A finite time step > 0 [s]."""
    return as_positive_scalar(dt, "dt")
