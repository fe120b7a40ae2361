"""Episode runner: a fixed-rate control loop around any :class:`~harvest_qp.runtime.interface.RobotInterface`.

Every control period (2 ms on the paper's UR5e) the runner reads the robot, hands an
:class:`Observation` to the controller, sends the returned joint velocities and steps the
robot. Camera frames arrive at the camera's own rate (30 Hz); the observation carries the
latest one. Everything is logged to arrays, optionally written to a compressed ``.npz``
that is byte-identical for identical runs (fixed zip timestamps, no wall-clock data unless
``log_timing``).

The runner never crashes on a controller error: an exception in ``reset``/``step`` or an
invalid command (wrong shape, NaN) stops the arms within their acceleration limits,
records the status and the error message, and ends the episode.

Controller protocol::

    class MyController:
        def reset(self, robot: RobotInterface) -> None: ...   # read the initial state only
        def step(self, obs: Observation) -> Command | np.ndarray: ...

A controller needs no robot handle after ``reset``: the observation carries the robot
clock (``obs.time``) and ``obs.tare_force()``, which zeroes the wrist force sensor (as a
real F/T sensor's tare) from the next tick on. A :class:`Command` may also carry named
per-tick values (``values``, scalars or fixed-shape arrays, logged as ``value/<name>``),
the collision pairs its QP step had active (``collision_pairs``: ``(name_a, name_b,
distance [m])``), and ``done=True`` to end the episode after this tick.

Log keys (N control ticks, F camera frames):

* ``t`` (N,) [s], ``q`` / ``qdot`` (N, 12) [rad, rad/s], ``qdot_cmd`` (N, 12) [rad/s],
  ``force`` (N, 3) [N, world];
* ``status`` (N,) str: the controller's status per tick (``"error"`` on a failing tick);
* ``stem_points`` (N,) int32: STEM points in the latest cloud (-1 before the first frame),
  ``cloud_time`` (N,) [s]: capture time of the latest cloud (NaN before the first);
* ``task_error/<name>`` (N,): the controller's task errors (NaN on ticks without them);
* ``value/<name>`` (N, ...): the controller's named per-tick values (NaN where absent);
* ``collision/pair_names`` (P,) str ``"a|b"``: every collision pair that was active at
  least once; ``collision/active_pair`` (N, K) int32 index into it (-1 = none) and
  ``collision/active_distance`` (N, K) float32 [m] per tick, K the most pairs active at once;
* ``truth/<name>``: the robot's ``ground_truth()`` per tick when it has one (simulation);
* ``frame_time``, ``frame_n_points``, ``frame_stem_points`` (F,), ``frame_camera_pose`` (F, 4, 4);
  with ``log_clouds``: ``cloud_points`` (P, 3) float32, ``cloud_labels`` (P,) int8,
  ``cloud_offsets`` (C + 1,) int64 (logged cloud j is rows offsets[j]:offsets[j+1]),
  ``cloud_frame`` (C,) int64 (the camera frame each logged cloud is);
* ``episode_status`` (``"completed"``, ``"controller_error"``, ``"invalid_command"`` or
  ``"robot_error"``), ``error`` (message or ""), ``control_period``, ``duration``, ``n_ticks``,
  ``seed`` (when the robot has one), ``meta/<key>`` from ``metadata``;
* with ``log_timing``: ``controller_time`` (N,) [s] of wall-clock per controller step.
"""

from __future__ import annotations

import io
import math
import time
import traceback
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.runtime.interface import N_JOINTS, STEM, PointCloud, RobotInterface

__all__ = [
    "Observation",
    "Command",
    "Controller",
    "EpisodeResult",
    "run_episode",
    "write_npz",
]


@dataclass(frozen=True, eq=False)
class Observation:
    """What the controller sees at one control tick.

    Attributes:
        time: robot clock [s].
        q: joint positions (12,) [rad].
        qdot: joint velocities (12,) [rad/s].
        force: wrist force (3,) [N, world] (see :meth:`RobotInterface.wrist_force`).
        cloud: the latest camera frame received so far (None before the first).
        new_cloud: True when ``cloud`` arrived at this tick.
        tare_force: zeroes the wrist force sensor at its current reading (the robot's
            :meth:`RobotInterface.tare_force`); readings from the next tick on are tared.
    """

    time: float
    q: NDArray[np.float64]
    qdot: NDArray[np.float64]
    force: NDArray[np.float64]
    cloud: PointCloud | None
    new_cloud: bool
    tare_force: Callable[[], None] = field(default=lambda: None, repr=False)


_new_object = object.__new__


def _observation(time: float, q: NDArray[np.float64], qdot: NDArray[np.float64], force: NDArray[np.float64],
                 cloud: PointCloud | None, new_cloud: bool, tare_force: Callable[[], None]) -> Observation:
    """``Observation(time=..., ..., tare_force=...)`` for the runner's loop: the same attributes
    in the same order, without the frozen dataclass's ``__init__`` (one ``object.__setattr__``
    per field: ~4 us of the 2 ms tick; tests/sim/test_sim_runner.py compares the two)."""
    obs = _new_object(Observation)
    obs.__dict__.update(time=time, q=q, qdot=qdot, force=force, cloud=cloud, new_cloud=new_cloud,
                        tare_force=tare_force)
    return obs


@dataclass
class Command:
    """A controller's output for one tick.

    Attributes:
        qdot: joint velocities (12,) [rad/s].
        status: solver/controller status, logged per tick (e.g. ``"ok"``, ``"infeasible"``).
        task_errors: task name -> scalar error, logged per tick.
        values: name -> scalar or fixed-shape array, logged per tick as ``value/<name>``
            (the shape of a name's first value fixes it for the episode).
        collision_pairs: ``(name_a, name_b, distance [m])`` of the collision rows active
            in this tick's QP.
        done: end the episode after this tick (e.g. a controller that has stopped).

    The library's own :class:`~harvest_qp.harvest.HarvestController` hands ``values`` and
    ``collision_pairs`` as read-only views (a row and columns the runner logs in one copy); a
    wrapper that adds its own builds a new command, e.g.
    ``dataclasses.replace(command, values={**command.values, "x": 1.0})``.
    """

    qdot: ArrayLike
    status: str = "ok"
    task_errors: Mapping[str, float] = field(default_factory=dict)
    values: Mapping[str, ArrayLike] = field(default_factory=dict)
    collision_pairs: Sequence[tuple[str, str, float]] = ()
    done: bool = False


def _command(qdot: NDArray[np.float64], status: str, values: Mapping[str, Any],
             collision_pairs: Sequence[tuple[str, str, float]], done: bool) -> Command:
    """``Command(qdot=..., status=..., values=..., collision_pairs=..., done=...)`` (no task
    errors) for the library's own controller: the same attributes in the same order, set
    without the dataclass's ``__init__`` (tests/sim/test_sim_runner.py compares the two)."""
    command = _new_object(Command)
    command.__dict__.update(qdot=qdot, status=status, task_errors={}, values=values,
                            collision_pairs=collision_pairs, done=done)
    return command


@runtime_checkable
class Controller(Protocol):
    """A controller the runner can drive."""

    def reset(self, robot: RobotInterface) -> None:
        """Prepare for an episode (read the initial state, tare the force sensor, ...)."""

    def step(self, obs: Observation) -> Command | ArrayLike:
        """Joint velocity command for this tick (a :class:`Command` or a (12,) array)."""


@dataclass(eq=False)
class EpisodeResult:
    """Outcome of :func:`run_episode`.

    Attributes:
        status: ``"completed"``, ``"controller_error"``, ``"invalid_command"`` or ``"robot_error"``.
        error: the error message with its traceback (None when completed).
        n_ticks: control ticks run.
        sim_time: robot time at the end [s].
        wall_time: wall-clock duration [s].
        log: the logged arrays (see the module docstring).
        log_path: where the log was written, if anywhere.
    """

    status: str
    error: str | None
    n_ticks: int
    sim_time: float
    wall_time: float
    log: dict[str, NDArray[Any]]
    log_path: Path | None

    @property
    def ok(self) -> bool:
        """True when the episode ran to the end without error."""
        return self.status == "completed"

    @property
    def realtime_factor(self) -> float:
        """Simulated time per wall-clock time."""
        return self.sim_time / self.wall_time if self.wall_time > 0 else math.inf


def write_npz(path: str | Path, arrays: Mapping[str, ArrayLike]) -> Path:
    """Write ``arrays`` to a compressed ``.npz`` whose bytes only depend on the arrays.

    ``numpy.savez_compressed`` stamps each member with the current time; this writer uses a
    fixed timestamp so identical logs give identical files. Load with :func:`numpy.load`.
    """
    path = Path(path)
    if path.suffix != ".npz":
        path = path.with_name(path.name + ".npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            array = np.asanyarray(arrays[name])
            if array.dtype == object:
                raise InvalidInputError(f"log entry {name!r} has dtype object; only plain arrays are written")
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, array, allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buffer.getvalue())
    return path


def _as_command(out: Any) -> Command:
    """Normalise a controller output to a validated :class:`Command`."""
    cmd = out if isinstance(out, Command) else Command(qdot=out)
    try:
        qd = np.asarray(cmd.qdot, dtype=float)
    except (TypeError, ValueError) as error:
        raise InvalidInputError(f"command qdot must be numeric (12,) [rad/s]: {error}") from None
    if qd.shape != (N_JOINTS,):
        raise InvalidInputError(f"command qdot must have shape ({N_JOINTS},) [rad/s], got shape {qd.shape}")
    if not np.all(np.isfinite(qd)):
        raise InvalidInputError(f"command qdot must be finite [rad/s], got {qd.tolist()}")
    if not isinstance(cmd.status, str):
        raise InvalidInputError(f"command status must be a str, got {type(cmd.status).__name__}")
    errors = {}
    for name, value in dict(cmd.task_errors).items():
        if not isinstance(name, str):
            raise InvalidInputError(f"task error names must be str, got {name!r}")
        try:
            errors[name] = float(value)
        except (TypeError, ValueError):
            raise InvalidInputError(f"task error {name!r} must be a number, got {value!r}") from None
    values = {}
    for name, value in dict(cmd.values).items():
        if not isinstance(name, str):
            raise InvalidInputError(f"value names must be str, got {name!r}")
        try:
            values[name] = np.asarray(value, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"value {name!r} must be numeric, got {value!r}") from None
    pairs = []
    for pair in cmd.collision_pairs:
        try:
            a, b, distance = pair
            pairs.append((str(a), str(b), float(distance)))
        except (TypeError, ValueError):
            raise InvalidInputError(
                f"collision_pairs entries must be (name_a, name_b, distance), got {pair!r}"
            ) from None
    return Command(qdot=qd, status=cmd.status, task_errors=errors, values=values, collision_pairs=pairs,
                   done=bool(cmd.done))


_FLOAT64 = np.dtype(np.float64)


class _ValueLayout:
    """Names and shapes of a fixed set of per-tick values stored in one flat float64 row.

    The library's own controller (:class:`harvest_qp.harvest.HarvestController`) declares its
    logged values once as a layout and hands them each tick as a :class:`_ValueRow`: the runner
    checks the row's dtype and length and copies it into its log in one assignment, instead
    of checking and copying ~18 named arrays and floats one by one (~20 us per 2 ms tick in
    the episode). Any other mapping takes the generic path; the log is the same either way.
    """

    __slots__ = ("names", "shapes", "starts", "stops", "scalar", "width", "index")

    def __init__(self, entries: Sequence[tuple[str, tuple[int, ...]]]) -> None:
        names, shapes, starts, stops = [], [], [], []
        width = 0
        for name, shape in entries:
            shape = tuple(int(n) for n in shape)
            if type(name) is not str or name in names or any(n < 0 for n in shape):
                raise InvalidInputError(f"value layout entries must be distinct names with shapes, got {name!r} {shape}")
            names.append(name)
            shapes.append(shape)
            starts.append(width)
            width += math.prod(shape)
            stops.append(width)
        self.names = tuple(names)
        self.shapes = tuple(shapes)
        self.starts = tuple(starts)
        self.stops = tuple(stops)
        self.scalar = tuple(shape == () for shape in shapes)
        self.width = width
        self.index = {name: i for i, name in enumerate(names)}


_READ_ONLY_HINT = (
    "HarvestController's Command.{what} is read-only; to add to it, build a new Command: "
    "dataclasses.replace(command, {what}={new})"
)


class _ValueRow(Mapping):
    """A tick's named values as one float64 row of a :class:`_ValueLayout` (read as a mapping).

    ``name -> value`` as :attr:`Command.values` gives it: a Python float for a scalar entry, a
    view of the row for an array entry. ``missing``: the names not given this tick (not in the
    mapping; their slots are set to NaN here, which is what the log holds for an absent value).
    """

    __slots__ = ("layout", "row", "missing")

    def __setitem__(self, name: str, value: Any) -> None:
        # A wrapper extending the command in place (a dict before the row protocol): say how.
        raise TypeError(_READ_ONLY_HINT.format(what="values", new="{**command.values, name: value}"))

    __delitem__ = __setitem__

    def __init__(self, layout: _ValueLayout, row: NDArray[np.float64], missing: tuple[str, ...] = ()) -> None:
        if type(row) is not np.ndarray or row.dtype is not _FLOAT64 or row.shape != (layout.width,):
            raise InvalidInputError(f"value row must be a float64 array of shape ({layout.width},), got {row!r}")
        for name in missing:
            i = layout.index[name]
            row[layout.starts[i]:layout.stops[i]] = math.nan
        self.layout = layout
        self.row = row
        self.missing = missing

    @classmethod
    def _built(cls, layout: _ValueLayout, row: NDArray[np.float64], missing: tuple[str, ...]) -> _ValueRow:
        """A row the library's controller built itself (a new float64 ``(layout.width,)`` array
        from ``np.fromiter``, NaN already in the missing names' slots): the constructor's checks
        skipped, every tick (the runner still checks the row's dtype and length)."""
        values = _new_object(cls)
        values.layout, values.row, values.missing = layout, row, missing
        return values

    def __getitem__(self, name: str) -> float | NDArray[np.float64]:
        layout = self.layout
        i = layout.index[name]  # KeyError for an unknown name
        if name in self.missing:
            raise KeyError(name)
        if layout.scalar[i]:
            return float(self.row[layout.starts[i]])
        return self.row[layout.starts[i]:layout.stops[i]].reshape(layout.shapes[i])

    def __iter__(self):
        missing = self.missing
        return iter([name for name in self.layout.names if name not in missing])

    def __len__(self) -> int:
        return len(self.layout.names) - len(self.missing)

    def __repr__(self) -> str:
        return f"_ValueRow({dict(self)!r})"


class _PairColumns(Sequence):
    """A tick's active collision pairs ``(name_a, name_b, distance [m])`` as three columns.

    Built by the library's own controller from its collision limit (names: the limit's capsule
    names; distances: Python floats from a float64 array); reads as the sequence of tuples
    :attr:`Command.collision_pairs` holds. The runner logs it without building or checking a
    tuple per pair (~24 pairs per tick in the paper episode); a new pair name is checked (and
    converted with ``str`` as the generic check does) when the log first meets it.
    """

    __slots__ = ("first", "second", "distances")

    def append(self, pair: tuple[str, str, float]) -> None:
        # A wrapper extending the command in place (a list before the column protocol): say how.
        raise TypeError(_READ_ONLY_HINT.format(what="collision_pairs", new="[*command.collision_pairs, pair]"))

    extend = append

    def __init__(self, first: list[str], second: list[str], distances: NDArray[np.float64]) -> None:
        """``first``, ``second``: the pairs' capsule names; ``distances``: a float64 ``(n,)`` array [m]."""
        if (
            type(first) is not list
            or type(second) is not list
            or type(distances) is not np.ndarray
            or distances.dtype is not _FLOAT64
            or distances.shape != (len(first),)
            or len(second) != len(first)
        ):
            raise InvalidInputError("pair columns must be two lists of names and a float64 array of as many distances")
        self.first = first
        self.second = second
        self.distances = distances.tolist()  # Python floats, as the generic check's float(distance)

    @classmethod
    def _built(cls, first: list[str], second: list[str], distances: list[float]) -> _PairColumns:
        """Columns the library's controller built itself (two name lists and the distances as a
        list of Python floats, all of one length): the constructor's checks skipped, every tick."""
        columns = _new_object(cls)
        columns.first, columns.second, columns.distances = first, second, distances
        return columns

    def __len__(self) -> int:
        return len(self.distances)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return list(zip(self.first[index], self.second[index], self.distances[index]))
        return (self.first[index], self.second[index], self.distances[index])

    def __iter__(self):
        return zip(self.first, self.second, self.distances)

    def __eq__(self, other: object) -> bool:
        if isinstance(other, (_PairColumns, list, tuple)):
            return list(self) == list(other)
        return NotImplemented

    __hash__ = None  # mutable columns, like a list

    def __repr__(self) -> str:
        return repr(list(self))


def _as_command_fast(out: Any) -> Command:
    """:func:`_as_command` for the common case, without rebuilding what is already valid.

    A :class:`Command` whose qdot is a finite float64 (12,) array, whose task errors and
    values are floats or float64 arrays and whose collision pairs are ``(str, str, float)``
    tuples is returned with the same contents as :func:`_as_command` gives (qdot, values
    and pairs are passed through, as ``np.asarray`` would pass them); anything else goes
    through :func:`_as_command`, which raises the same errors as before.

    The library's own controller hands its values as a :class:`_ValueRow` and its pairs as
    :class:`_PairColumns`: the row's dtype and length are checked here and the command is
    passed through as it is (nothing to normalise); the log checks a pair's names when it
    first meets them. Any controller may hand plain dicts and tuples: same log.
    """
    if type(out) is not Command:
        return _as_command(out)
    qd = out.qdot
    if (
        type(qd) is not np.ndarray
        or qd.dtype is not _FLOAT64
        or qd.shape != (N_JOINTS,)
        # On the 12 Python floats (a fifth of np.isfinite(qd).all()'s time): a finite sum has
        # only finite terms (a NaN or an infinity stays in a float sum). A sum that is not finite
        # (a bad entry, or finite entries overflowing) takes _as_command's full check.
        or not math.isfinite(sum(qd.tolist()))
        or type(out.status) is not str
    ):
        return _as_command(out)
    errors = out.task_errors
    if errors:
        if type(errors) is not dict:
            return _as_command(out)
        for name, value in errors.items():
            if type(name) is not str or type(value) is not float:
                return _as_command(out)
    values = out.values
    if type(values) is _ValueRow:
        # The library's controller's row (checked when built): passed through, logged in one copy.
        row = values.row
        if type(row) is not np.ndarray or row.dtype is not _FLOAT64 or row.shape != (values.layout.width,):
            return _as_command(out)
    else:
        if values:
            if type(values) is not dict:
                return _as_command(out)
            for name, value in values.items():
                kind = type(value)
                scalar = kind is float or kind is np.float64
                if type(name) is not str or not (scalar or (kind is np.ndarray and value.dtype is _FLOAT64)):
                    return _as_command(out)
        values = dict(values)
    pairs = out.collision_pairs
    if type(pairs) is _PairColumns:
        # Names are checked by the log when it first meets a pair; distances are floats by
        # construction. Nothing to normalise: the command itself is what _as_command would build.
        if type(values) is _ValueRow and type(errors) is dict and type(out.done) is bool:
            return out
        return Command(qdot=qd, status=out.status, task_errors=dict(errors), values=values,
                       collision_pairs=pairs, done=bool(out.done))
    if type(pairs) is not list and type(pairs) is not tuple:
        return _as_command(out)  # e.g. a generator, which the check below would consume
    if pairs:
        for pair in pairs:
            if (
                type(pair) is not tuple
                or len(pair) != 3
                or type(pair[0]) is not str
                or type(pair[1]) is not str
                or type(pair[2]) is not float
            ):
                return _as_command(out)
    return Command(qdot=qd, status=out.status, task_errors=dict(errors), values=values,
                   collision_pairs=list(pairs), done=bool(out.done))


class _Log:
    """Preallocated per-tick arrays plus per-frame lists."""

    def __init__(
        self, n: int, truth: Mapping[str, Any] | None, log_timing: bool, log_clouds: bool | int,
        cloud_max_points: int | None = None,
    ) -> None:
        self.n = n
        self.t = np.full(n, np.nan)
        self.q = np.full((n, N_JOINTS), np.nan)
        self.qdot = np.full((n, N_JOINTS), np.nan)
        self.qdot_cmd = np.zeros((n, N_JOINTS))
        self.force = np.full((n, 3), np.nan)
        self.status: list[str] = [""] * n
        self.stem_points = np.full(n, -1, np.int32)
        self.cloud_time = np.full(n, np.nan)
        self.task_errors: dict[str, NDArray[np.float64]] = {}
        self.values: dict[str, NDArray[np.float64]] = {}
        # The values of a controller that hands one _ValueRow layout (the library's own): one
        # (n, width) array, one row per tick, split into value/<name> columns at the end;
        # _row_order: the layout's entries in the order they were first given (the order the
        # generic path creates its columns in). _row_layout False: rows are off for this log
        # (a generic mapping or another layout was met: everything goes to self.values).
        self._row_layout: _ValueLayout | None | bool = None
        self._rows: NDArray[np.float64] | None = None
        self._row_order: list[int] = []
        self._row_pending = 0
        self.pair_index: dict[str, int] = {}
        self._pair_key: dict[tuple[str, str], int] = {}  # (a, b) -> index into pair_index's order
        # Active pair events, in tick order: per pairs() call its tick and number of events,
        # and per event its pair index and distance (one entry per call, not per event, for
        # the ticks: ~22 events per tick in the paper episode).
        self._call_ticks: list[int] = []
        self._call_sizes: list[int] = []
        self.pair_ids: list[int] = []
        self.pair_distances: list[float] = []
        # The last _PairColumns' names and their indices (consecutive ticks mostly repeat them).
        self._last_first: list[Any] | None = None
        self._last_second: list[Any] | None = None
        self._last_ids: list[int] = []
        self.truth = {k: np.full((n, *np.shape(v)), np.nan) for k, v in (truth or {}).items()}
        self.controller_time = np.full(n, np.nan) if log_timing else None
        # every how many camera frames a cloud is logged (0: none); True = every frame
        self.cloud_every = int(log_clouds)
        self.log_clouds = self.cloud_every > 0
        self.cloud_max_points = cloud_max_points
        self.cloud_frame: list[int] = []
        self.frames: list[tuple[float, int, int, NDArray[np.float64]]] = []
        self.cloud_points: list[NDArray[np.float32]] = []
        self.cloud_labels: list[NDArray[np.int8]] = []

    def frame(self, cloud: PointCloud, stem_points: int | None = None) -> None:
        """Log a camera frame; ``stem_points``: its STEM count when the caller has it already."""
        index = len(self.frames)
        stem = cloud.count(STEM) if stem_points is None else stem_points
        self.frames.append((cloud.timestamp, len(cloud), stem, cloud.camera_pose))
        if self.log_clouds and index % self.cloud_every == 0:
            # thinned by a regular stride (keeps the labels' proportions; a viewer snapshot, not data)
            stride = 1 if not self.cloud_max_points else max(1, -(-len(cloud) // self.cloud_max_points))
            self.cloud_points.append(cloud.points[::stride].astype(np.float32))
            self.cloud_labels.append(cloud.labels[::stride].astype(np.int8))
            self.cloud_frame.append(index)

    def task(self, k: int, errors: Mapping[str, float]) -> None:
        for name, value in errors.items():
            if name not in self.task_errors:
                self.task_errors[name] = np.full(self.n, np.nan)
            self.task_errors[name][k] = value

    def value(self, k: int, values: Mapping[str, NDArray[np.float64] | float]) -> None:
        if type(values) is _ValueRow:
            layout = values.layout
            if layout is self._row_layout:
                self._rows[k] = values.row
                if self._row_pending:
                    self._see(values)
                return
            if self._row_layout is None and not self.values:
                self._row_layout = layout
                self._rows = np.full((self.n, layout.width), np.nan)
                self._row_pending = len(layout.names)
                self._rows[k] = values.row
                self._see(values)
                return
        if self._row_layout:
            self._rows_to_columns()
        self._row_layout = False
        self._value_items(k, values)

    def _see(self, values: _ValueRow) -> None:
        """Note the layout entries given for the first time (column order of the generic path)."""
        order = self._row_order
        missing = values.missing
        for i, name in enumerate(values.layout.names):
            if name not in missing and i not in order:
                order.append(i)
        self._row_pending = len(values.layout.names) - len(order)

    def _row_columns(self, k: int) -> dict[str, NDArray[np.float64]]:
        """The rows' first ``k`` ticks as ``name -> (k, *shape)`` columns, in first-given order."""
        layout, rows = self._row_layout, self._rows
        return {
            layout.names[i]: rows[:k, layout.starts[i]:layout.stops[i]].reshape(k, *layout.shapes[i]).copy()
            for i in self._row_order
        }

    def _rows_to_columns(self) -> None:
        """Hand the rows logged so far to the generic per-name columns (a mapping of another kind
        arrived): every tick not written is NaN in both, so the log is the same."""
        self.values.update(self._row_columns(self.n))
        self._rows = None

    def _value_items(self, k: int, values: Mapping[str, NDArray[np.float64] | float]) -> None:
        store = self.values
        for name, value in values.items():
            if type(value) is float or type(value) is np.float64:  # a scalar (passed through by the fast check)
                column = store.get(name)
                if column is None:
                    column = store[name] = np.full(self.n, np.nan)
                elif column.ndim != 1:
                    raise InvalidInputError(f"value {name!r} changed shape from {column.shape[1:]} to ()")
                column[k] = value
                continue
            column = store.get(name)
            if column is None:
                column = store[name] = np.full((self.n, *value.shape), np.nan)
            elif column.shape[1:] != value.shape:
                raise InvalidInputError(f"value {name!r} changed shape from {column.shape[1:]} to {value.shape}")
            column[k] = value

    def pairs(self, k: int, pairs: Sequence[tuple[str, str, float]]) -> None:
        if not pairs:
            return
        if type(pairs) is _PairColumns:
            self._pair_columns(k, pairs)
            return
        keys = self._pair_key
        ids = self.pair_ids
        distances = self.pair_distances
        for a, b, distance in pairs:
            index = keys.get((a, b))
            if index is None:
                name = f"{a}|{b}"
                index = keys[(a, b)] = self.pair_index.setdefault(name, len(self.pair_index))
            ids.append(index)
            distances.append(distance)
        self._call_ticks.append(k)
        self._call_sizes.append(len(pairs))

    def _pair_columns(self, k: int, pairs: _PairColumns) -> None:
        """:meth:`pairs` for the library's own pair columns: one dict lookup per pair, the types of
        a pair's names checked (and converted by ``str`` as :func:`_as_command` does) when it is new."""
        first, second = pairs.first, pairs.second
        if first == self._last_first and second == self._last_second:
            # The same pairs as the last tick's (most ticks): the same indices (an index, once
            # given to a name pair, never changes). List equality compares identical strings
            # by identity: ~0.2 us instead of a lookup per pair.
            ids = self._last_ids
            self.pair_ids.extend(ids)
            self.pair_distances.extend(pairs.distances)
            self._call_ticks.append(k)
            self._call_sizes.append(len(ids))
            return
        keys = self._pair_key
        get = keys.get
        ids = [get(key) for key in zip(first, second)]
        if None in ids:
            for j, index in enumerate(ids):
                if index is None:
                    a, b = pairs.first[j], pairs.second[j]
                    if type(a) is not str or type(b) is not str:
                        try:
                            a, b = str(a), str(b)
                        except Exception:
                            raise InvalidInputError(
                                f"collision_pairs entries must be (name_a, name_b, distance), got {pairs[j]!r}"
                            ) from None
                    index = keys.get((a, b))
                    if index is None:
                        index = keys[(a, b)] = self.pair_index.setdefault(f"{a}|{b}", len(self.pair_index))
                    keys[(pairs.first[j], pairs.second[j])] = ids[j] = index
        self._last_first, self._last_second, self._last_ids = first, second, ids
        self.pair_ids.extend(ids)
        self.pair_distances.extend(pairs.distances)
        self._call_ticks.append(k)
        self._call_sizes.append(len(ids))

    @property
    def pair_ticks(self) -> list[int]:
        """The tick of each active pair event, in tick order."""
        return np.repeat(np.array(self._call_ticks, dtype=np.int64), np.array(self._call_sizes, dtype=np.int64)).tolist()

    @property
    def pair_events(self) -> list[tuple[int, int, float]]:
        """The active pair events as (tick, pair index, distance), in tick order."""
        return list(zip(self.pair_ticks, self.pair_ids, self.pair_distances))

    def pair_arrays(self, k: int) -> dict[str, NDArray[Any]]:
        names = sorted(self.pair_index, key=self.pair_index.get)
        width = max([len(n) for n in names] + [1])
        call_ticks = np.array(self._call_ticks, dtype=np.int64)
        ticks = np.repeat(call_ticks, np.array(self._call_sizes, dtype=np.int64))
        counts = np.bincount(ticks, minlength=max(k, 1)) if ticks.size else np.zeros(max(k, 1), np.int64)
        columns = int(counts.max()) if ticks.size else 0
        index = np.full((k, columns), -1, np.int32)
        distance = np.full((k, columns), np.nan, np.float32)
        if ticks.size and bool(np.all(call_ticks[1:] >= call_ticks[:-1])):
            # Events in tick order (the runner's): row by row, a tick's events fill its first
            # columns, which is the order a boolean mask assigns in (~4x faster than
            # scattering by (tick, rank)); events of ticks >= k are the last ones, left out.
            shown = counts[:k]
            filled = np.arange(columns) < shown[:, None]
            m = int(shown.sum())
            index[filled] = np.array(self.pair_ids, dtype=np.int64)[:m]
            distance[filled] = np.array(self.pair_distances, dtype=np.float64)[:m]
        elif ticks.size:
            # Events are in tick order: an event's column is its rank among its tick's events.
            starts = np.cumsum(counts) - counts
            fill = np.arange(ticks.size) - starts[ticks]
            inside = ticks < k
            index[ticks[inside], fill[inside]] = np.array(self.pair_ids, dtype=np.int64)[inside]
            distance[ticks[inside], fill[inside]] = np.array(self.pair_distances, dtype=np.float64)[inside]
        return {
            "collision/pair_names": np.array(names, dtype=f"<U{width}"),
            "collision/active_pair": index,
            "collision/active_distance": distance,
        }

    def arrays(self, k: int) -> dict[str, NDArray[Any]]:
        """The first ``k`` ticks as a dict of arrays."""
        width = max([len(s) for s in self.status[:k]] + [1])
        out: dict[str, NDArray[Any]] = {
            "t": self.t[:k],
            "q": self.q[:k],
            "qdot": self.qdot[:k],
            "qdot_cmd": self.qdot_cmd[:k],
            "force": self.force[:k],
            "status": np.array(self.status[:k], dtype=f"<U{width}"),
            "stem_points": self.stem_points[:k],
            "cloud_time": self.cloud_time[:k],
        }
        for name, values in self.task_errors.items():
            out[f"task_error/{name}"] = values[:k]
        for name, values in self.values.items():
            out[f"value/{name}"] = values[:k]
        if self._row_layout:
            for name, values in self._row_columns(k).items():
                out[f"value/{name}"] = values
        out.update(self.pair_arrays(k))
        for name, values in self.truth.items():
            out[f"truth/{name}"] = values[:k]
        if self.controller_time is not None:
            out["controller_time"] = self.controller_time[:k]
        f = self.frames
        out["frame_time"] = np.array([x[0] for x in f], dtype=float)
        out["frame_n_points"] = np.array([x[1] for x in f], dtype=np.int64)
        out["frame_stem_points"] = np.array([x[2] for x in f], dtype=np.int64)
        out["frame_camera_pose"] = np.array([x[3] for x in f], dtype=float).reshape(len(f), 4, 4)
        if self.log_clouds:
            sizes = [len(p) for p in self.cloud_points]
            out["cloud_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
            out["cloud_points"] = (
                np.concatenate(self.cloud_points) if self.cloud_points else np.zeros((0, 3), np.float32)
            )
            out["cloud_labels"] = np.concatenate(self.cloud_labels) if self.cloud_labels else np.zeros(0, np.int8)
            out["cloud_frame"] = np.array(self.cloud_frame, dtype=np.int64)
        return out


def _format_error(error: BaseException) -> str:
    return (
        "".join(traceback.format_exception_only(type(error), error)).strip()
        + "\n"
        + "".join(traceback.format_tb(error.__traceback__))
    )


def run_episode(
    robot: RobotInterface,
    controller: Controller,
    *,
    duration: float,
    log_path: str | Path | None = None,
    metadata: Mapping[str, Any] | None = None,
    stop_at_end: bool = True,
    log_clouds: bool | int = False,
    cloud_max_points: int | None = None,
    log_timing: bool = False,
    ground_truth: Callable[[], Mapping[str, Any]] | None = None,
) -> EpisodeResult:
    """Run ``controller`` on ``robot`` for ``duration`` seconds at the robot's control rate.

    Args:
        robot: the robot (simulated or real), already reset to the episode's start.
        controller: object with ``reset(robot)`` and ``step(obs) -> Command | array``.
        duration: episode length [s] (rounded to whole control periods).
        log_path: where to write the compressed ``.npz`` log (None: not written).
        metadata: scalars or strings stored as ``meta/<key>`` in the log.
        stop_at_end: bring the arms to rest after the last tick (not logged).
        log_clouds: also log the camera frames' points and labels: ``True`` every frame, an
            integer ``N > 0`` every N-th frame (``cloud_frame`` says which), 0 or False none.
        cloud_max_points: thin each logged cloud by a regular stride to at most this many points.
        log_timing: log the controller's wall-clock time per step (makes logs differ
            between runs).
        ground_truth: what to log as ``truth/<name>`` per tick (default: the robot's
            ``ground_truth()`` method, if it has one). Never shown to the controller.

    Returns:
        The :class:`EpisodeResult` (also when the controller failed).
    """
    if not isinstance(robot, RobotInterface):
        raise InvalidInputError(f"robot must implement RobotInterface, got {type(robot).__name__}")
    if not callable(getattr(controller, "step", None)) or not callable(getattr(controller, "reset", None)):
        raise InvalidInputError(
            f"controller must have reset(robot) and step(obs) methods, got {type(controller).__name__}"
        )
    if not isinstance(duration, (int, float)) or not np.isfinite(duration) or duration <= 0:
        raise InvalidInputError(f"duration must be a finite time > 0 [s], got {duration!r}")
    n_ticks = int(round(duration / robot.control_period))
    truth_fn = ground_truth if ground_truth is not None else getattr(robot, "ground_truth", None)
    if truth_fn is not None and not callable(truth_fn):
        truth_fn = None
    truth0 = truth_fn() if truth_fn is not None else None
    if isinstance(log_clouds, float) or not isinstance(log_clouds, (bool, int, np.integer)) or log_clouds < 0:
        raise InvalidInputError(f"log_clouds must be a bool or an integer >= 0 (every N-th frame), got {log_clouds!r}")
    bad_count = isinstance(cloud_max_points, bool) or not isinstance(cloud_max_points, (int, np.integer))
    if cloud_max_points is not None and (bad_count or cloud_max_points < 1):
        raise InvalidInputError(f"cloud_max_points must be an integer >= 1 or None, got {cloud_max_points!r}")
    log = _Log(n_ticks, truth0, log_timing, log_clouds, cloud_max_points)
    send = robot.send_joint_velocities
    truth_log = log.truth
    # The log's per-tick arrays and methods, looked up once (the same objects every tick).
    log_t, log_q, log_qdot, log_force = log.t, log.q, log.qdot, log.force
    log_qdot_cmd, log_status = log.qdot_cmd, log.status
    log_stem_points, log_cloud_time, log_controller_time = log.stem_points, log.cloud_time, log.controller_time
    log_value, log_pairs = log.value, log.pairs
    perf_counter = time.perf_counter

    status, error = "completed", None
    latest: PointCloud | None = None
    latest_stem = -1
    wall0 = time.perf_counter()
    k = 0
    try:
        try:
            controller.reset(robot)
        except Exception as exc:
            status, error = "controller_error", "controller.reset failed: " + _format_error(exc)
        while status == "completed" and k < n_ticks:
            cloud = robot.camera_cloud()
            if cloud is not None:
                latest, latest_stem = cloud, cloud.count(STEM)
                log.frame(cloud, latest_stem)
            now, q, qdot, force = robot.time, robot.joint_positions(), robot.joint_velocities(), robot.wrist_force()
            obs = _observation(now, q, qdot, force, latest, cloud is not None, robot.tare_force)
            log_t[k], log_q[k], log_qdot[k], log_force[k] = now, q, qdot, force
            if latest is not None:
                log_stem_points[k] = latest_stem
                log_cloud_time[k] = latest.timestamp
            if truth_fn is not None:
                for name, value in truth_fn().items():
                    truth_log[name][k] = value
            t0 = perf_counter()
            try:
                out = controller.step(obs)
            except Exception as exc:
                status, error = "controller_error", "controller.step failed: " + _format_error(exc)
            else:
                try:
                    cmd = _as_command_fast(out)
                    # The log refuses a value whose shape changes from tick to tick.
                    if cmd.task_errors:
                        log.task(k, cmd.task_errors)
                    log_value(k, cmd.values)
                    log_pairs(k, cmd.collision_pairs)  # a new pair's names are checked here
                except InvalidInputError as exc:
                    status, error = "invalid_command", str(exc)
            if log_controller_time is not None:
                log_controller_time[k] = perf_counter() - t0
            if status != "completed":
                log_status[k] = "error"
                k += 1
                break
            log_qdot_cmd[k] = cmd.qdot
            log_status[k] = cmd.status
            send(cmd.qdot)
            k += 1
            try:
                robot.step()
            except HarvestQPError as exc:
                status, error = "robot_error", "robot.step failed: " + _format_error(exc)
                break
            if cmd.done:
                break
    finally:
        # Whatever happened (controller error, end of episode, Ctrl-C), leave the arms at rest.
        if status in ("controller_error", "invalid_command") or stop_at_end:
            try:
                robot.stop()
            except HarvestQPError as exc:
                if status == "completed":
                    status, error = "robot_error", "robot.stop failed: " + _format_error(exc)
    wall = time.perf_counter() - wall0

    arrays = log.arrays(k)
    arrays["episode_status"] = np.array(status)
    arrays["error"] = np.array(error or "")
    arrays["control_period"] = np.array(robot.control_period)
    arrays["duration"] = np.array(float(duration))
    arrays["n_ticks"] = np.array(k)
    seed = getattr(robot, "seed", None)
    if isinstance(seed, (int, np.integer)):
        arrays["seed"] = np.array(int(seed))
    for key, value in (metadata or {}).items():
        arrays[f"meta/{key}"] = np.asarray(value)
    path = write_npz(log_path, arrays) if log_path is not None else None
    return EpisodeResult(
        status=status,
        error=error,
        n_ticks=k,
        sim_time=k * robot.control_period,
        wall_time=wall,
        log=arrays,
        log_path=path,
    )
