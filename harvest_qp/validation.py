"""Input checks shared by the public API: clear messages naming the value and what was expected."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.qp_kernels import all_finite


def as_vector(value: np.ndarray | Sequence[float] | float, size: int, name: str) -> np.ndarray:
    """``value`` as a finite float vector of length ``size`` (a scalar is broadcast); a copy."""
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (size,):
        # Fast path for the control loop: already the right kind of array.
        if not all_finite(value):
            raise InvalidInputError(f"{name} must be finite (no NaN or inf), got {value}")
        return value.copy()
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be numeric with shape ({size},), got {value!r}") from None
    if arr.ndim == 0:
        arr = np.full(size, float(arr))
    if arr.shape != (size,):
        raise InvalidInputError(f"{name} must have shape ({size},), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{name} must be finite (no NaN or inf), got {arr}")
    return arr.copy()


def as_nonnegative_vector(value, size: int, name: str) -> np.ndarray:
    """Like :func:`as_vector` and every entry >= 0 (weights, gains)."""
    arr = as_vector(value, size, name)
    if np.any(arr < 0.0):
        raise InvalidInputError(f"{name} must be >= 0, got {arr}")
    return arr


def as_positive_scalar(value: float, name: str, *, allow_zero: bool = False) -> float:
    """A finite scalar > 0 (or >= 0 with ``allow_zero``)."""
    if type(value) is float and 0.0 < value < np.inf:  # fast path for the control loop
        return value
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(x) or x < 0.0 or (x == 0.0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise InvalidInputError(f"{name} must be finite and {bound}, got {value!r}")
    return x


def as_matrix(value, shape: tuple[int, int], name: str) -> np.ndarray:
    """A finite float matrix of the given shape."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise InvalidInputError(f"{name} must have shape {shape}, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(f"{name} must be finite (no NaN or inf)")
    return arr
