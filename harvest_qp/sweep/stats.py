"""Statistics of a sweep: success rate with a Wilson interval, failure reasons, medians."""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from harvest_qp.exceptions import InvalidInputError

#: Two-sided standard-normal quantile for 95 % (``scipy.stats.norm.ppf(0.975)``).
Z_95 = 1.959963984540054

#: Columns written by the sweep itself (everything else in a row is a metric of the episode).
STATUS_OK = "ok"  # the episode returned its metrics
STATUS_ERROR = "error"  # the episode raised; ``error`` holds "ExceptionType: message"
STATUS_DIED = "died"  # the process running the episode exited (os._exit, segfault, OOM kill)
STATUS_TIMEOUT = "timeout"  # the episode ran past ``episode_timeout`` and was killed


def wilson_interval(successes: int, n: int, *, z: float = Z_95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (Wilson 1927).

    ``center = (p + z^2/(2n)) / (1 + z^2/n)``,
    ``half = z / (1 + z^2/n) * sqrt(p (1 - p) / n + z^2 / (4 n^2))``, with ``p = successes / n``.
    Unlike the normal (Wald) interval it stays inside [0, 1] and is not empty at 0 or n successes,
    which matters for small sweeps.

    Returns:
        ``(low, high)`` in [0, 1]; ``(nan, nan)`` when ``n == 0``.

    Raises:
        InvalidInputError: negative counts, ``successes > n`` or a non-positive ``z``.
    """
    for name, value in (("successes", successes), ("n", n)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise InvalidInputError(f"wilson_interval: {name} must be a non-negative integer, got {value!r}")
    if successes > n:
        raise InvalidInputError(f"wilson_interval: successes ({successes}) must not exceed n ({n})")
    if not (isinstance(z, (int, float)) and math.isfinite(z) and z > 0):
        raise InvalidInputError(f"wilson_interval: z must be a positive finite number, got {z!r}")
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    z2 = z * z
    denominator = 1.0 + z2 / n
    center = (p + z2 / (2 * n)) / denominator
    half = z / denominator * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return (max(0.0, center - half), min(1.0, center + half))


def is_number(value: Any) -> bool:
    """A real number that is not a bool (bools are counted, not averaged)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def is_success(row: Mapping[str, Any]) -> bool:
    """An episode that returned metrics with a true ``success``."""
    return row.get("status") == STATUS_OK and bool(row.get("success"))


def failure_reason(row: Mapping[str, Any]) -> str | None:
    """Why an episode failed (``None`` for a success).

    The episode's ``abort_reason`` (or its ``end_reason``: the pre-cut tests that failed when it ended
    in the bimanual phase) when it returned metrics; ``"error: <ExceptionType>"``
    when it raised (the message is in the row; grouping by type keeps seeds apart from the count);
    ``"worker died"`` / ``"timeout"`` when its process was lost.
    """
    if is_success(row):
        return None
    status = row.get("status")
    if status == STATUS_ERROR:
        error = str(row.get("error") or "")
        return f"error: {error.split(':', 1)[0].strip() or 'unknown'}"
    if status == STATUS_DIED:
        return "worker died"
    if status == STATUS_TIMEOUT:
        return "timeout"
    reason = row.get("abort_reason") or row.get("episode_error") or row.get("end_reason")
    if reason is None or reason == "":
        return "no abort_reason (success false)" if "success" in row else "no success metric"
    return str(reason)


@dataclass(frozen=True)
class MetricSummary:
    """Median, range and count of one numeric metric over the episodes that reported it."""

    name: str
    median: float
    minimum: float
    maximum: float
    count: int


@dataclass(frozen=True)
class SweepSummary:
    """What ``sweep.md`` reports.

    Attributes:
        episodes: rows summarised.
        successes: rows with status ok and a true ``success``.
        interval: 95 % Wilson interval of the success rate (errors and dead workers count as failures).
        status_counts: rows per status (ok / error / died / timeout).
        failure_reasons: failed rows per reason (see :func:`failure_reason`), most frequent first.
        medians: numeric metrics (NaN values left out), in column order.
        fractions: boolean metrics: fraction of the rows reporting them that are true.
    """

    episodes: int
    successes: int
    interval: tuple[float, float]
    status_counts: dict[str, int]
    failure_reasons: list[tuple[str, int]]
    medians: list[MetricSummary] = field(default_factory=list)
    fractions: dict[str, tuple[int, int]] = field(default_factory=dict)

    @property
    def success_rate(self) -> float:
        """Fraction of successful episodes (NaN for an empty sweep)."""
        return self.successes / self.episodes if self.episodes else math.nan


#: Columns the sweep adds to every row; they are not summarised as metrics.
BOOKKEEPING_COLUMNS = ("seed", "status", "error", "wall_time_s")


def summarize(rows: Sequence[Mapping[str, Any]], *, columns: Iterable[str] | None = None) -> SweepSummary:
    """Success rate, failure reasons and medians of sweep rows (as read by :func:`read_rows`)."""
    successes = sum(is_success(row) for row in rows)
    status_counts = Counter(str(row.get("status")) for row in rows)
    reasons = Counter(r for r in (failure_reason(row) for row in rows) if r is not None)
    if columns is None:
        seen: dict[str, None] = {}
        for row in rows:
            seen.update(dict.fromkeys(row))
        columns = list(seen)
    medians: list[MetricSummary] = []
    fractions: dict[str, tuple[int, int]] = {}
    for name in columns:
        if name in ("seed", "status", "error"):
            continue
        values = [row[name] for row in rows if name in row and row[name] is not None and row[name] != ""]
        if not values:
            continue
        if all(isinstance(v, bool) for v in values):
            fractions[name] = (sum(values), len(values))
        elif all(is_number(v) for v in values):
            finite = sorted(float(v) for v in values if not math.isnan(float(v)))
            if finite:
                medians.append(MetricSummary(name, _median(finite), finite[0], finite[-1], len(finite)))
    return SweepSummary(
        episodes=len(rows),
        successes=successes,
        interval=wilson_interval(successes, len(rows)),
        status_counts=dict(status_counts),
        failure_reasons=sorted(reasons.items(), key=lambda item: (-item[1], item[0])),
        medians=medians,
        fractions=fractions,
    )


def _median(sorted_values: Sequence[float]) -> float:
    n = len(sorted_values)
    mid = n // 2
    return sorted_values[mid] if n % 2 else 0.5 * (sorted_values[mid - 1] + sorted_values[mid])
