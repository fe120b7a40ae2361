"""Base class of the QP limits (hard constraints on the joint velocities)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from harvest_qp.configuration import Configuration, as_configuration
from harvest_qp.exceptions import DimensionError, InvalidInputError
from harvest_qp.validation import as_instances, as_positive_scalar, check_limit_rows


def check_limit_output(limit: Limit, rows: LimitRows, nv: int) -> None:
    """Raise :class:`DimensionError` unless ``limit.compute``'s ``rows`` fit a model of ``nv`` joints.

    The solver calls it on every row limit's output (user code) before its compiled kernels,
    which index ``G`` by ``nv`` without bounds checks, see the rows.
    """
    if not isinstance(rows, LimitRows):
        raise DimensionError(f"{type(limit).__name__}.compute must return LimitRows, got {type(rows).__name__}")
    check_limit_rows(limit, rows.G, rows.h, nv)
    if rows.G is not None:
        # A NaN row would never be active in the backends: the constraint would be dropped silently.
        if rows.G.dtype.kind not in "fiu" or rows.h.dtype.kind not in "fiu":
            raise InvalidInputError(f"{type(limit).__name__}.compute returned rows of dtype G {rows.G.dtype}, "
                                    f"h {rows.h.dtype}; expected real numbers")
        if np.isnan(rows.G).any() or np.isnan(rows.h).any():
            raise InvalidInputError(f"{type(limit).__name__}.compute returned NaN in its rows G qdot <= h: "
                                    "the constraint cannot be kept")
    for side, value in (("lower", rows.lower), ("upper", rows.upper)):
        if value is not None and getattr(value, "shape", None) != (nv,):
            raise DimensionError(
                f"{type(limit).__name__}.compute returned a box {side} of shape "
                f"{getattr(value, 'shape', type(value).__name__)}, expected ({nv},) (one entry per joint)"
            )


@dataclass
class LimitRows:
    """What a limit contributes to the QP on ``qdot`` [rad/s].

    Either a box ``lower <= qdot <= upper`` or inequality rows ``G qdot <= h`` (or both).
    """

    lower: np.ndarray | None = None
    upper: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None


class Limit(ABC):
    """A hard constraint on the joint velocities.

    Box limits are intersected in ``priority`` order (lower number first): where two
    boxes do not overlap, the earlier one wins and the later one is moved onto it,
    so the speed limit always holds and joint position limits beat acceleration limits.

    A limit sized for one model is checked against the model it is used on
    (:meth:`check_configuration`, once per model) before its arrays reach a kernel.
    """

    #: Order in which box limits are intersected (velocity 0, position 1, acceleration 2).
    priority: int = 10
    #: True for limits whose :meth:`compute` returns a box (``lower``/``upper``) and no rows.
    #: The solver then calls :meth:`fill_box`, which writes into its buffers.
    has_box: bool = False
    #: The pinocchio model this limit was last checked against (None: not yet).
    _model: pin.Model | None = None

    def check_configuration(self, configuration: Configuration) -> None:
        """Raise unless this limit can run on ``configuration``'s model.

        Raises:
            InvalidInputError: ``configuration`` is not a :class:`Configuration`.
            DimensionError: a size of this limit disagrees with the model's ``nv``.
        """
        as_configuration(configuration, f"{type(self).__name__} configuration")

    def _check_joint_vectors(self, configuration: Configuration, **vectors: np.ndarray) -> None:
        """For limits with per-joint vectors: each must have the model's ``nv`` entries."""
        as_configuration(configuration, f"{type(self).__name__} configuration")
        nv = configuration.nv
        for name, vector in vectors.items():
            if vector.shape != (nv,):
                raise DimensionError(
                    f"{type(self).__name__} {name} has {vector.shape[0]} entries but the model has nv = {nv} "
                    f"joints; build the limit from the configuration it runs on"
                )

    def _ensure_bound(self, configuration: Configuration) -> None:
        """Check this limit against ``configuration``'s model once per model (the hot path is one ``is``)."""
        model = getattr(configuration, "model", None)
        if model is None or model is not self._model:
            self.check_configuration(configuration)
            self._model = model

    def fill_box(
        self,
        configuration: Configuration,
        dt: float,
        previous_qdot: np.ndarray | None,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> None:
        """Write this limit's box [rad/s] into ``lower`` and ``upper`` (box limits only).

        The default goes through :meth:`compute`; the built-in limits override it to
        skip the allocations (it runs every control tick).
        """
        rows = self.compute(configuration, dt, previous_qdot)
        n = lower.shape[0]
        check_limit_output(self, rows, n)
        for side, value in (("lower", rows.lower), ("upper", rows.upper)):
            if value is None:
                raise DimensionError(f"{type(self).__name__}.compute returned no box {side}: a box limit needs both")
        lower[:] = rows.lower
        upper[:] = rows.upper

    @abstractmethod
    def compute(self, configuration: Configuration, dt: float, previous_qdot: np.ndarray | None = None) -> LimitRows:
        """Rows of this limit at the configuration's state, for a step of ``dt`` [s]."""


class BoxLimit(Limit):
    """A limit that is a velocity box ``lower <= qdot <= upper`` [rad/s] and no rows.

    Subclasses write the box in :meth:`fill_box` (the solver calls it every tick with its own
    buffers); :meth:`compute` returns it in fresh arrays.
    """

    has_box = True

    def compute(self, configuration: Configuration, dt: float, previous_qdot: np.ndarray | None = None) -> LimitRows:
        """The velocity box [rad/s] for a step of ``dt`` [s] at the configuration's state."""
        dt = as_positive_scalar(dt, f"{type(self).__name__} dt")
        self._ensure_bound(configuration)
        lower, upper = np.empty(configuration.nv), np.empty(configuration.nv)
        self.fill_box(configuration, dt, previous_qdot, lower, upper)
        return LimitRows(lower=lower, upper=upper)

    @abstractmethod
    def fill_box(
        self,
        configuration: Configuration,
        dt: float,
        previous_qdot: np.ndarray | None,
        lower: np.ndarray,
        upper: np.ndarray,
    ) -> None:
        """Write this limit's box [rad/s] into ``lower`` and ``upper`` (one entry per joint)."""


def check_limits(
    limits: Iterable[Limit], configuration: Configuration | None = None, *, name: str = "limits"
) -> list[Limit]:
    """The limits as a list (may be empty), after checking each is a :class:`Limit`.

    With a ``configuration``, each limit's sizes are also checked against its model.

    Raises:
        InvalidInputError: not a sequence of limits, or an item that is not a Limit (the
            message names its position and type, e.g. ``limits[1] must be a Limit, got int``).
        DimensionError: a limit's size disagrees with the model.
    """
    items = as_instances(limits, Limit, name, allow_empty=True)
    if configuration is not None:
        as_configuration(configuration)
        for limit in items:
            limit.check_configuration(configuration)
    return items
