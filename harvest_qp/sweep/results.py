"""``sweep.csv``: one row per seed, written as episodes finish, safe to resume.

Values are written so they read back as the same Python values: ``None`` as an empty
cell, bools as ``true``/``false``, ints as digits, floats with ``repr`` (which
round-trips exactly, ``nan``/``inf`` included), lists and nested values as JSON.
A text metric that looks like a number or a bool (``"3"``, ``"true"``) reads back as one.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import re
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.sweep.stats import BOOKKEEPING_COLUMNS

try:  # POSIX only; elsewhere two sweeps writing one folder are not detected
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None  # type: ignore[assignment]

CSV_NAME = "sweep.csv"
MANIFEST_NAME = "sweep.json"
LOCK_NAME = ".sweep.lock"

#: Metrics shown right after the bookkeeping columns when present; the rest follow alphabetically.
LEADING_METRICS = ("success", "phase_reached", "abort_reason")

_INT_TEXT = re.compile(r"-?[0-9]+")


def normalize_metrics(metrics: Any) -> dict[str, Any]:
    """The episode's metrics as flat, CSV-safe Python values.

    Nested mappings are flattened with dotted keys (``{"contacts": {"arm": 2}}`` ->
    ``contacts.arm``); numpy scalars become Python numbers; sequences and arrays become
    lists (written as JSON). A metric named like a bookkeeping column (``seed``, ``status``,
    ``error``, ``wall_time_s``) is kept as ``metric_<name>`` unless it repeats the value
    the sweep writes anyway (``seed`` equal to the episode's seed is dropped by the caller).

    Raises:
        TypeError: ``metrics`` is not a mapping with string keys (reported in the row's error).
    """
    if not isinstance(metrics, Mapping):
        raise TypeError(f"the episode returned {type(metrics).__name__}, expected a mapping of metric name to value")
    flat: dict[str, Any] = {}
    _flatten(metrics, "", flat)
    return flat


def _flatten(mapping: Mapping, prefix: str, out: dict[str, Any]) -> None:
    for key, value in mapping.items():
        if not isinstance(key, str) or not key:
            raise TypeError(f"metric names must be non-empty strings, got {key!r}")
        name = prefix + key
        if isinstance(value, Mapping):
            _flatten(value, name + ".", out)
        else:
            out[name] = _plain(value, name)


def _plain(value: Any, name: str) -> Any:
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return int(value)
    if isinstance(value, float):
        return float(value)
    if hasattr(value, "tolist") and callable(value.tolist):  # numpy scalars and arrays
        return _plain(value.tolist(), name)
    if isinstance(value, (list, tuple)):
        return [_plain(item, name) for item in value]
    raise TypeError(
        f"metric {name!r} has a value of type {type(value).__name__} ({value!r:.60}); "
        "expected a number, bool, string, None, a list or a mapping of those"
    )


def format_value(value: Any) -> str:
    """One CSV cell (see the module docstring)."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return value
    return json.dumps(value, allow_nan=True, separators=(",", ":"))


def parse_value(text: str) -> Any:
    """The Python value of one CSV cell written by :func:`format_value`."""
    if text == "":
        return None
    if text == "true":
        return True
    if text == "false":
        return False
    if _INT_TEXT.fullmatch(text):
        return int(text)
    try:
        return float(text)
    except ValueError:
        pass
    if text[0] in "[{":
        try:
            return json.loads(text)
        except ValueError:
            pass
    return text


def column_order(columns: list[str] | set[str]) -> list[str]:
    """Bookkeeping columns, then :data:`LEADING_METRICS`, then the other metrics alphabetically."""
    present = set(columns)
    head = [c for c in (*BOOKKEEPING_COLUMNS, *LEADING_METRICS) if c in present]
    return head + sorted(present - set(head))


class SweepStore:
    """The rows of ``out_dir/sweep.csv``, appended one at a time and rewritten sorted at the end.

    Each finished episode is appended and flushed to disk at once, so a sweep that is
    killed keeps every episode it finished. A row with a column the header lacks makes
    the file be rewritten whole (into a temporary file, then renamed over the old one).
    A torn last line from a killed writer is dropped on load (that seed runs again).
    """

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.csv_path = out_dir / CSV_NAME
        self.rows: dict[int, dict[str, Any]] = {}
        self.columns: list[str] = []
        self._declared: set[str] = set()  # every column a row has named, None-valued ones included
        self._load()

    def _load(self) -> None:
        if not self.csv_path.exists():
            return
        header, rows, torn = _parse_csv(self.csv_path)
        if not header:
            return
        if "seed" not in header:
            raise InvalidInputError(
                f"out_dir: {str(self.csv_path)!r} has no 'seed' column (header {header[:6]}); "
                "expected a sweep.csv written by harvest-qp sweep: use another --out folder"
            )
        self.rows = {row["seed"]: row for row in rows}
        self.columns = header
        if torn:  # an interrupted write: drop the torn line now, before anything is appended after it
            self.rewrite()

    def add(self, row: Mapping[str, Any]) -> None:
        """Record one episode's row (replacing an earlier row of the same seed) and flush it to disk."""
        seed = int(row["seed"])
        replacing = seed in self.rows
        # A metric that is None (e.g. abort_reason of an episode that did not abort) gets its
        # column, an empty cell, and is left out of the row, as when it is read back.
        self._declared.update(row)
        self.rows[seed] = {k: v for k, v in row.items() if v is not None}
        if replacing or not self.columns or not set(row) <= set(self.columns):
            self.rewrite()
            return
        with open(self.csv_path, "a", encoding="utf-8", newline="") as handle:
            csv.writer(handle, lineterminator="\n").writerow([format_value(row.get(c)) for c in self.columns])
            handle.flush()
            os.fsync(handle.fileno())

    def rewrite(self) -> None:
        """Write every row, sorted by seed, with the canonical column order; atomic (temp file + rename)."""
        columns: set[str] = set(self.columns) | self._declared
        for row in self.rows.values():
            columns.update(row)
        self.columns = column_order(columns) if columns else list(BOOKKEEPING_COLUMNS)
        self.out_dir.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".sweep-", suffix=".csv.tmp", dir=self.out_dir)
        try:
            with os.fdopen(fd, "w", encoding="utf-8", newline="") as handle:
                writer = csv.writer(handle, lineterminator="\n")
                writer.writerow(self.columns)
                for seed in sorted(self.rows):
                    writer.writerow([format_value(self.rows[seed].get(c)) for c in self.columns])
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, self.csv_path)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            raise

    def sorted_rows(self) -> list[dict[str, Any]]:
        """All rows, by seed."""
        return [self.rows[seed] for seed in sorted(self.rows)]


def read_rows(path: str | os.PathLike) -> list[dict[str, Any]]:
    """The rows of a ``sweep.csv`` (or of the ``sweep.csv`` in a folder), by seed, values parsed.

    Empty cells are left out of a row, so ``"abort_reason" in row`` says whether the episode reported one.
    """
    path = Path(path)
    if path.is_dir():
        path = path / CSV_NAME
    if not path.is_file():
        raise InvalidInputError(f"path: {str(path)!r} is not a sweep.csv (no such file)")
    _, rows, _ = _parse_csv(path)
    return sorted(rows, key=lambda row: row["seed"])


def _parse_csv(path: Path) -> tuple[list[str], list[dict[str, Any]], bool]:
    """Header, rows (empty cells left out) and whether a torn line (an interrupted write) was dropped."""
    raw = path.read_text(encoding="utf-8")
    torn = bool(raw) and not raw.endswith("\n")
    if torn:  # a line cut short may still have every field, the last one truncated: drop it whole
        raw = raw[: raw.rfind("\n") + 1]
    reader = csv.reader(io.StringIO(raw, newline=""))
    header = next(reader, None) or []
    rows: list[dict[str, Any]] = []
    for cells in reader:
        if len(cells) != len(header):
            torn = True
            continue
        row = {name: parse_value(cell) for name, cell in zip(header, cells)}
        if isinstance(row.get("seed"), int):
            rows.append({k: v for k, v in row.items() if v is not None})
    return header, rows, torn


def read_manifest(out_dir: Path) -> dict[str, Any] | None:
    """The ``sweep.json`` of a folder, or ``None``."""
    path = out_dir / MANIFEST_NAME
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except ValueError as exc:
        raise InvalidInputError(
            f"out_dir: {str(path)!r} is not valid JSON ({exc}); delete it or use another folder"
        ) from None


def write_manifest(out_dir: Path, manifest: Mapping[str, Any]) -> None:
    """Write ``sweep.json`` atomically."""
    fd, tmp = tempfile.mkstemp(prefix=".sweep-", suffix=".json.tmp", dir=out_dir)
    with os.fdopen(fd, "w", encoding="utf-8") as handle:
        json.dump(dict(manifest), handle, indent=2, sort_keys=True, default=str)
        handle.write("\n")
    os.replace(tmp, out_dir / MANIFEST_NAME)


@contextlib.contextmanager
def sweep_lock(out_dir: Path) -> Iterator[None]:
    """Hold ``out_dir/.sweep.lock`` so that two sweeps never write one ``sweep.csv`` together.

    Raises:
        InvalidInputError: another process holds the lock.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    if fcntl is None:  # pragma: no cover
        yield
        return
    with open(out_dir / LOCK_NAME, "a+") as handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise InvalidInputError(
                f"out_dir: {str(out_dir)!r} is in use by another running sweep; "
                "wait for it to finish or choose another --out folder"
            ) from None
        try:
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def is_finite_number(value: Any) -> bool:
    """A real, finite number (not a bool)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
