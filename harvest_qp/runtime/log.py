"""The episode's log: the typed per-tick record a controller hands the runner, and the arrays it fills.

* :class:`ValueLayout` / :class:`ValueRow`: a controller's per-tick values (``value/<name>``) as one
  typed record, names and shapes declared once, filled each tick as one float64 row (the library's
  :class:`~harvest_qp.harvest.HarvestController` does); a plain mapping of names to values is
  accepted too and stored the same way.
* :class:`PairColumns`: the collision pairs active in a tick's QP as three columns.
* :class:`EpisodeLog`: the arrays the runner fills per tick and per camera frame; :func:`write_npz`
  writes them (see :mod:`harvest_qp.runtime.runner` for the keys).
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.runtime.interface import N_JOINTS, STEM, PointCloud

__all__ = ["EpisodeLog", "PairColumns", "ValueLayout", "ValueRow", "write_npz"]

_FLOAT64 = np.dtype(np.float64)
_new_object = object.__new__

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





class ValueLayout:
    """Names and shapes of a fixed set of per-tick values stored in one flat float64 row.

    The library's own controller (:class:`harvest_qp.harvest.HarvestController`) declares its
    logged values once as a layout and hands them each tick as a :class:`ValueRow`: the runner
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
                raise InvalidInputError(
                    f"value layout entries must be distinct names with shapes, got {name!r} {shape}")
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


class ValueRow(Mapping):
    """A tick's named values as one float64 row of a :class:`ValueLayout` (read as a mapping).

    ``name -> value`` as :attr:`Command.values` gives it: a Python float for a scalar entry, a
    view of the row for an array entry. ``missing``: the names not given this tick (not in the
    mapping; their slots are set to NaN here, which is what the log holds for an absent value).
    """

    __slots__ = ("layout", "row", "missing")

    def __setitem__(self, name: str, value: Any) -> None:
        # A wrapper extending the command in place (a dict before the row protocol): say how.
        raise TypeError(_READ_ONLY_HINT.format(what="values", new="{**command.values, name: value}"))

    __delitem__ = __setitem__

    def __init__(self, layout: ValueLayout, row: NDArray[np.float64], missing: tuple[str, ...] = ()) -> None:
        if type(row) is not np.ndarray or row.dtype is not _FLOAT64 or row.shape != (layout.width,):
            raise InvalidInputError(f"value row must be a float64 array of shape ({layout.width},), got {row!r}")
        for name in missing:
            i = layout.index[name]
            row[layout.starts[i]:layout.stops[i]] = math.nan
        self.layout = layout
        self.row = row
        self.missing = missing

    @classmethod
    def _built(cls, layout: ValueLayout, row: NDArray[np.float64], missing: tuple[str, ...]) -> ValueRow:
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
        return f"ValueRow({dict(self)!r})"


class PairColumns(Sequence):
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
    def _built(cls, first: list[str], second: list[str], distances: list[float]) -> PairColumns:
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
        if isinstance(other, (PairColumns, list, tuple)):
            return list(self) == list(other)
        return NotImplemented

    __hash__ = None  # mutable columns, like a list

    def __repr__(self) -> str:
        return repr(list(self))



class EpisodeLog:
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
        # The values of a controller that hands one ValueRow layout (the library's own): one
        # (n, width) array, one row per tick, split into value/<name> columns at the end;
        # _row_order: the layout's entries in the order they were first given (the order the
        # generic path creates its columns in). _row_layout False: rows are off for this log
        # (a generic mapping or another layout was met: everything goes to self.values).
        self._row_layout: ValueLayout | None | bool = None
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
        # The last PairColumns' names and their indices (consecutive ticks mostly repeat them).
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
        if type(values) is ValueRow:
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

    def _see(self, values: ValueRow) -> None:
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
        if type(pairs) is PairColumns:
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

    def _pair_columns(self, k: int, pairs: PairColumns) -> None:
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
        ticks = np.array(self._call_ticks, dtype=np.int64)
        return np.repeat(ticks, np.array(self._call_sizes, dtype=np.int64)).tolist()

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
