"""Input checks shared by the public API.

Every check raises :class:`~harvest_qp.exceptions.InvalidInputError` (or its subclass
:class:`~harvest_qp.exceptions.DimensionError` for sizes that disagree with the robot
model) with a message naming the argument, the value received and what was expected.
The value is shown as received: ``None`` is reported as ``None``, never as the NaN that
numpy would make of it.
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from harvest_qp.exceptions import DimensionError, InvalidInputError
from harvest_qp.qp_kernels import all_finite

#: Largest deviation of ``R^T R`` from ``I`` (and of ``det R`` from 1) accepted for a rotation.
ROTATION_TOLERANCE = 1e-6

# numpy's native float64 dtype (a singleton): an identity test is ~3x cheaper than ``==``; any
# other float64 dtype (byte-swapped, with metadata) takes the general path, which gives the same copy.
_FLOAT64 = np.dtype(np.float64)


def describe(value: Any, *, limit: int = 120) -> str:
    """A short, faithful description of ``value`` for an error message."""
    if isinstance(value, np.ndarray):
        text = np.array2string(value, threshold=12, precision=6, separator=", ")
        text = f"array of shape {value.shape}: {text}" if value.ndim != 1 or value.size > 6 else text
    else:
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _numeric_array(value: Any, name: str, expected: str) -> np.ndarray:
    """``value`` as a float array; only real numbers (and bools) are accepted, never ``None`` or text."""
    if value is None or isinstance(value, (str, bytes)):
        raise InvalidInputError(f"{name} must be {expected}, got {describe(value)}")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError):  # ragged nested sequences
        raise InvalidInputError(f"{name} must be {expected}, got {describe(value)}") from None
    # Object arrays hold None or text (numpy would turn None into NaN); complex numbers have no order.
    if raw.dtype.kind not in "biuf":
        raise InvalidInputError(f"{name} must be {expected} (real numbers), got {describe(value)}")
    return raw.astype(float)


def _non_finite_message(name: str, arr: np.ndarray) -> str:
    bad = np.flatnonzero(~np.isfinite(arr.ravel()))
    return (
        f"{name} must be finite (no NaN or inf), got {describe(arr)} "
        f"(non-finite at flat index {bad[:6].tolist()}{'...' if bad.size > 6 else ''})"
    )


def as_vector(value: np.ndarray | Sequence[float] | float, size: int, name: str) -> np.ndarray:
    """``value`` as a finite float vector of length ``size`` (a scalar is broadcast); a copy."""
    if type(value) is np.ndarray and value.dtype is _FLOAT64 and value.shape == (size,):
        # Fast path for the control loop: already the right kind of array.
        if not all_finite(value):
            raise InvalidInputError(_non_finite_message(name, value))
        return value.copy()
    arr = _numeric_array(value, name, f"a number or a vector of shape ({size},)")
    if arr.ndim == 0:
        arr = np.full(size, float(arr))
    if arr.shape != (size,):
        raise InvalidInputError(f"{name} must have shape ({size},), got shape {arr.shape}: {describe(value)}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(_non_finite_message(name, arr))
    return arr


def as_nonnegative_vector(value: np.ndarray | Sequence[float] | float, size: int, name: str) -> np.ndarray:
    """Like :func:`as_vector` and every entry >= 0 (weights, gains)."""
    arr = as_vector(value, size, name)
    if np.any(arr < 0.0):
        raise InvalidInputError(
            f"{name} must be >= 0, got {describe(arr)} (negative at {np.flatnonzero(arr < 0).tolist()})"
        )
    return arr


def as_scalar(
    value: float,
    name: str,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    exclusive_minimum: bool = False,
) -> float:
    """A finite real number in ``[minimum, maximum]`` (``(minimum, maximum]`` with ``exclusive_minimum``)."""
    if type(value) is float and np.isfinite(value):
        x = value  # fast path for the control loop
    else:
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.ndarray)):
            raise InvalidInputError(f"{name} must be a real number, got {describe(value)}")
        if isinstance(value, np.ndarray) and (value.ndim != 0 or value.dtype.kind not in "iuf"):
            raise InvalidInputError(f"{name} must be a real number (a scalar), got {describe(value)}")
        x = float(value)
        if not np.isfinite(x):
            raise InvalidInputError(f"{name} must be finite, got {describe(value)}")
    below = minimum is not None and (x <= minimum if exclusive_minimum else x < minimum)
    if below or (maximum is not None and x > maximum):
        low = "" if minimum is None else f"{'(' if exclusive_minimum else '['}{minimum:g}, "
        high = "inf)" if maximum is None else f"{maximum:g}]"
        interval = f"in {low or '(-inf, '}{high}"
        raise InvalidInputError(f"{name} must be {interval}, got {describe(value)}")
    return x


def as_positive_scalar(value: float, name: str, *, allow_zero: bool = False) -> float:
    """A finite scalar > 0 (or >= 0 with ``allow_zero``)."""
    if type(value) is float and 0.0 < value < np.inf:  # fast path for the control loop
        return value
    bound = ">= 0" if allow_zero else "> 0"
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.ndarray)):
        raise InvalidInputError(f"{name} must be a number (finite and {bound}), got {describe(value)}")
    if isinstance(value, np.ndarray) and (value.ndim != 0 or value.dtype.kind not in "iuf"):
        raise InvalidInputError(f"{name} must be a number (a scalar, finite and {bound}), got {describe(value)}")
    x = float(value)
    if not np.isfinite(x) or x < 0.0 or (x == 0.0 and not allow_zero):
        raise InvalidInputError(f"{name} must be finite and {bound}, got {describe(value)}")
    return x


def as_integer(value: int, name: str, *, minimum: int | None = None) -> int:
    """An integer (an ``int``, numpy integer or integral float such as ``2.0``) >= ``minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.integer)):
        raise InvalidInputError(f"{name} must be an integer, got {describe(value)}")
    if isinstance(value, numbers.Integral):
        k = int(value)
    else:
        x = float(value)
        if not np.isfinite(x) or x != int(x):
            raise InvalidInputError(f"{name} must be an integer, got {describe(value)}")
        k = int(x)
    if minimum is not None and k < minimum:
        raise InvalidInputError(f"{name} must be an integer >= {minimum}, got {describe(value)}")
    return k


def as_level(value: int, name: str = "level") -> int:
    """A task priority level: an integer >= 0 (0 = hard)."""
    try:
        return as_integer(value, name, minimum=0)
    except InvalidInputError:
        raise InvalidInputError(f"{name} must be an integer >= 0 (0 = hard), got {describe(value)}") from None


def as_matrix(value: np.ndarray | Sequence[Sequence[float]], shape: tuple[int, int], name: str) -> np.ndarray:
    """A finite float matrix of the given shape; a copy."""
    arr = _numeric_array(value, name, f"a matrix of shape {shape}")
    if arr.shape != shape:
        raise InvalidInputError(f"{name} must have shape {shape}, got shape {arr.shape}: {describe(value)}")
    if not np.all(np.isfinite(arr)):
        raise InvalidInputError(_non_finite_message(name, arr))
    return arr


def as_rotation(value: np.ndarray | Sequence[Sequence[float]], name: str) -> np.ndarray:
    """A 3x3 rotation matrix (orthonormal, det +1, to :data:`ROTATION_TOLERANCE`); a copy."""
    R = as_matrix(value, (3, 3), name)
    orthogonality = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if orthogonality > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise InvalidInputError(
            f"{name} must be a rotation matrix (R^T R = I and det R = +1 to {ROTATION_TOLERANCE:g}), got "
            f"max|R^T R - I| = {orthogonality:.3g}, det R = {det:.6g}: {describe(R)}"
        )
    return R


def as_rigid_transform(value: np.ndarray | Sequence[Sequence[float]], name: str) -> np.ndarray:
    """A 4x4 rigid transform (rotation per :func:`as_rotation`, last row 0 0 0 1 to the same tolerance,
    then set exactly), finite [m]; a copy."""
    T = as_matrix(value, (4, 4), name)
    as_rotation(T[:3, :3], f"{name} rotation")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=ROTATION_TOLERANCE):
        raise InvalidInputError(f"{name} must end with the row 0 0 0 1, got {T[3].tolist()}")
    T[3] = (0.0, 0.0, 0.0, 1.0)
    return T


def as_name(value: str, name: str) -> str:
    """A non-empty string (a frame or joint name)."""
    if not isinstance(value, str) or not value:
        raise InvalidInputError(f"{name} must be a non-empty str, got {describe(value)}")
    return value


def as_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """One of ``choices``."""
    if not isinstance(value, str) or value not in choices:
        raise InvalidInputError(f"{name} must be one of {list(choices)}, got {describe(value)}")
    return value


def as_bounds(
    lower: np.ndarray | Sequence[float] | float,
    upper: np.ndarray | Sequence[float] | float,
    size: int,
    name: str,
) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of length ``size`` with ``lower <= upper`` everywhere.

    ``lower`` may hold ``-inf`` and ``upper`` ``+inf`` (an unbounded joint); NaN never.
    """
    arrays = []
    for side, value, allowed in (("lower", lower, -np.inf), ("upper", upper, np.inf)):
        arg = f"{name} {side}"
        arr = _numeric_array(value, arg, f"a number or a vector of shape ({size},)")
        if arr.ndim == 0:
            arr = np.full(size, float(arr))
        if arr.shape != (size,):
            raise InvalidInputError(f"{arg} must have shape ({size},), got shape {arr.shape}: {describe(value)}")
        bad = np.isnan(arr) | (np.isinf(arr) & (arr != allowed))
        if np.any(bad):
            raise InvalidInputError(
                f"{arg} must be finite (or {allowed} for an unbounded joint), got {describe(arr)} "
                f"(bad at {np.flatnonzero(bad).tolist()})"
            )
        arrays.append(arr)
    lo, hi = arrays
    crossed = np.flatnonzero(lo > hi)
    if crossed.size:
        i = int(crossed[0])
        raise InvalidInputError(
            f"{name} lower must be <= upper at every joint, got lower[{i}] = {lo[i]:g} > upper[{i}] = {hi[i]:g}"
            f" (crossed at {crossed.tolist()})"
        )
    return lo, hi


def as_instances(items: Any, kind: type, name: str, *, allow_empty: bool = True) -> list:
    """``items`` as a list after checking each is a ``kind`` (e.g. the tasks or limits of a QP).

    Raises:
        InvalidInputError: ``items`` is not a sequence (a single ``kind``, a string), is empty when
            ``allow_empty`` is False, or holds another type: the message names the position and
            the type, e.g. ``tasks[1] must be a Task, got str: 'posture'``.
    """
    kind_name = kind.__name__
    if isinstance(items, (kind, str, bytes)) or not isinstance(items, Iterable):
        raise InvalidInputError(f"{name} must be a sequence of {kind_name} objects, got {describe(items)}")
    listed = list(items)
    if not listed and not allow_empty:
        raise InvalidInputError(f"{name} must hold at least one {kind_name}, got an empty {type(items).__name__}")
    for i, item in enumerate(listed):
        if not isinstance(item, kind):
            raise InvalidInputError(f"{name}[{i}] must be a {kind_name}, got {type(item).__name__}: {describe(item)}")
    return listed


def check_task_rows(task: Any, J: np.ndarray | None, v: np.ndarray, nv: int) -> None:
    """Raise :class:`DimensionError` unless ``J`` (or ``None`` = identity) and ``v`` fit ``task`` and ``nv``.

    The solver's compiled kernels index ``H`` (nv x nv) by ``J``'s columns and read
    ``task.weight`` and ``v`` by ``J``'s rows, without bounds checks: a mismatch there is
    silent memory corruption. Cheap enough to run on every task every tick.
    """
    rows = task.weight.shape[0]
    if J is None:
        if rows == nv and type(v) is np.ndarray and v.shape == (nv,):
            return
        expected = f"J = None (identity) needs weight and v of shape ({nv},)"
    else:
        if type(J) is np.ndarray and J.shape == (rows, nv) and type(v) is np.ndarray and v.shape == (rows,):
            return
        expected = f"J must have shape ({rows}, {nv}) and v shape ({rows},)"
    got_J = "None" if J is None else f"J {getattr(J, 'shape', type(J).__name__)}"
    raise DimensionError(
        f"{task!r} rows do not fit the model (nv = {nv}): {expected}, got {got_J}, "
        f"v {getattr(v, 'shape', type(v).__name__)}, weight ({rows},)"
    )


def check_limit_rows(limit: Any, G: np.ndarray | None, h: np.ndarray | None, nv: int) -> None:
    """Raise :class:`DimensionError` unless inequality rows ``G qdot <= h`` of ``limit`` fit ``nv``.

    For the solver, on rows from :meth:`Limit.compute` (user code): the feasibility
    kernel reads ``G[r, i]`` for ``i < nv`` without bounds checks.
    """
    if G is None and h is None:
        return
    ok = (
        type(G) is np.ndarray
        and type(h) is np.ndarray
        and G.ndim == 2
        and G.shape[1] == nv
        and h.shape == (G.shape[0],)
    )
    if not ok:
        raise DimensionError(
            f"{type(limit).__name__}.compute returned G {getattr(G, 'shape', type(G).__name__)} and "
            f"h {getattr(h, 'shape', type(h).__name__)}; expected G of shape (m, {nv}) and h of shape (m,)"
        )


def _is_real(value: Any) -> bool:
    """A real number that is not a bool (``True`` is no gain or length)."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, np.ndarray):
        return value.ndim == 0 and value.dtype.kind in "iuf"
    return isinstance(value, numbers.Real)


def check_field_types(obj: Any) -> None:
    """Check that every field of the dataclass ``obj`` annotated ``float``, ``int`` or ``bool``
    (optionally ``| None``) holds such a value; raises :class:`InvalidInputError` naming
    ``Class.field``, the value and the expected type.

    Call it first in ``__post_init__`` so the range checks that follow never see text,
    ``None`` or a list (they used to raise numpy's ``TypeError`` or ``ValueError``). A
    ``float`` field accepts any real number except a bool and NaN; an ``int`` field an
    integral number; a ``bool`` field only ``True``/``False``.
    """
    import dataclasses

    owner = type(obj).__name__
    for field in dataclasses.fields(obj):
        kind = field.type if isinstance(field.type, str) else getattr(field.type, "__name__", "")
        kind = kind.replace(" ", "")
        optional = kind.endswith("|None")
        kind = kind.removesuffix("|None")
        if kind not in ("float", "int", "bool"):
            continue
        value = getattr(obj, field.name)
        if value is None and optional:
            continue
        name = f"{owner}.{field.name}"
        none = " or None" if optional else ""
        if kind == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise InvalidInputError(f"{name} must be True or False{none}, got {describe(value)}")
        elif not _is_real(value) or np.isnan(float(value)):
            expected = "an integer" if kind == "int" else "a real number"
            raise InvalidInputError(f"{name} must be {expected}{none}, got {describe(value)}")
        elif kind == "int" and (not np.isfinite(float(value)) or float(value) != int(value)):
            raise InvalidInputError(f"{name} must be an integer{none}, got {describe(value)}")
