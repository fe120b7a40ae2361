"""``sweep.md`` and the sweep's figures."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from harvest_qp.sweep.engines import MissingDependencyError
from harvest_qp.sweep.stats import SweepSummary, is_number, is_success

REPORT_NAME = "sweep.md"

#: Final errors of the closed-loop episode (`fig:exp_reach`, `fig:exp_center`, `fig:exp_ep`, `fig:exp_eo`);
#: with the default ``error_metrics=None`` every numeric ``final_*`` column is plotted.
FINAL_ERROR_PREFIX = "final_"
#: Times of the episode's events [s] (``t_bimanual_start``, the time the pre-cut state is reached, ...).
TIME_PREFIX = "t_"


def _percent(value: float) -> str:
    return "n/a" if math.isnan(value) else f"{100 * value:.1f} %"


def _number(value: float) -> str:
    return f"{value:.4g}"


def render_markdown(
    summary: SweepSummary, *, title: str = "Sweep", meta: Mapping[str, Any] | None = None, figures: Sequence[str] = ()
) -> str:
    """The text of ``sweep.md``."""
    low, high = summary.interval
    lines = [f"# {title}", ""]
    for key, value in (meta or {}).items():
        lines.append(f"- {key}: {value}")
    if meta:
        lines.append("")
    lines += [
        f"**Success: {summary.successes} / {summary.episodes} episodes = {_percent(summary.success_rate)}** "
        f"(95 % Wilson interval {_percent(low)} to {_percent(high)}; episodes that raised or whose "
        "process died count as failures).",
        "",
        "Episodes by status: " + ", ".join(f"{k} {v}" for k, v in sorted(summary.status_counts.items())) + ".",
        "",
        "## Failure reasons",
        "",
    ]
    if summary.failure_reasons:
        lines += ["| reason | episodes |", "| --- | ---: |"]
        lines += [f"| {reason.replace('|', '/')} | {count} |" for reason, count in summary.failure_reasons]
    else:
        lines.append("None: every episode succeeded." if summary.episodes else "No episodes.")
    lines += ["", "## Medians of the numeric metrics", ""]
    if summary.medians:
        lines += ["| metric | median | min | max | episodes |", "| --- | ---: | ---: | ---: | ---: |"]
        lines += [
            f"| {m.name} | {_number(m.median)} | {_number(m.minimum)} | {_number(m.maximum)} | {m.count} |"
            for m in summary.medians
        ]
    else:
        lines.append("No numeric metrics.")
    if summary.fractions:
        lines += ["", "## Boolean metrics", "", "| metric | true | episodes |", "| --- | ---: | ---: |"]
        lines += [f"| {name} | {true} | {n} |" for name, (true, n) in summary.fractions.items()]
    if figures:
        lines += ["", "## Figures", ""] + [f"![{Path(f).stem}]({Path(f).name})" for f in figures]
    return "\n".join(lines) + "\n"


@dataclass
class SweepFigures:
    """What :func:`plot_sweep` drew.

    Attributes:
        paths: figure name -> PNG file.
        plotted: metric -> the finite values drawn, in seed order.
        skipped: metrics asked for but absent from every row (or never finite).
    """

    paths: dict[str, Path] = field(default_factory=dict)
    plotted: dict[str, list[float]] = field(default_factory=dict)
    skipped: list[str] = field(default_factory=list)


def _metric_names(rows: Sequence[Mapping[str, Any]], prefix: str) -> list[str]:
    names: dict[str, None] = {}
    for row in rows:
        names.update({k: None for k, v in row.items() if k.startswith(prefix) and is_number(v)})
    return sorted(names)


def plot_sweep(
    rows: Sequence[Mapping[str, Any]],
    out_dir: str | Path,
    *,
    error_metrics: Sequence[str] | None = None,
    time_metrics: Sequence[str] | None = None,
) -> SweepFigures:
    """Strip plots with histograms of the final errors and of the event times of a sweep.

    Writes ``sweep_final_errors.png`` (default: every numeric ``final_*`` metric) and
    ``sweep_times.png`` (default: every numeric ``t_*`` metric, e.g. ``t_bimanual_start``
    and the time to the pre-cut state), one panel per metric: a histogram of the episodes
    (successes and failures stacked) over a strip of one dot per episode. Metrics that no
    row reports are skipped (listed in the result); a figure with no metric is not written.

    Raises:
        MissingDependencyError: matplotlib is not installed.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")  # headless: no display, no GUI toolkit
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise MissingDependencyError(f"sweep figures need matplotlib ({exc}): pip install matplotlib") from exc
    import numpy as np

    out_dir = Path(out_dir)
    result = SweepFigures()
    groups = {
        "sweep_final_errors": list(error_metrics)
        if error_metrics is not None
        else _metric_names(rows, FINAL_ERROR_PREFIX),
        "sweep_times": list(time_metrics) if time_metrics is not None else _metric_names(rows, TIME_PREFIX),
    }
    for figure_name, metrics in groups.items():
        panels: list[tuple[str, list[float], list[bool]]] = []
        for metric in metrics:
            pairs = [
                (float(row[metric]), is_success(row))
                for row in rows
                if is_number(row.get(metric)) and math.isfinite(float(row[metric]))
            ]
            if not pairs:
                result.skipped.append(metric)
                continue
            values = [v for v, _ in pairs]
            result.plotted[metric] = values
            panels.append((metric, values, [ok for _, ok in pairs]))
        if not panels:
            continue
        fig, axes = plt.subplots(len(panels), 1, figsize=(7.0, 2.2 * len(panels)), squeeze=False)
        rng = np.random.default_rng(0)  # jitter only; fixed so the picture is reproducible
        for ax, (metric, values, ok) in zip(axes[:, 0], panels):
            data = np.asarray(values)
            mask = np.asarray(ok)
            bins = np.histogram_bin_edges(data, bins=min(30, max(5, int(np.sqrt(data.size)) + 1)))
            ax.hist(
                [data[mask], data[~mask]],
                bins=bins,
                stacked=True,
                color=["tab:green", "tab:red"],
                label=[f"success ({mask.sum()})", f"failure ({(~mask).sum()})"],
                alpha=0.75,
            )
            top = max(1.0, ax.get_ylim()[1])
            jitter = -top * (0.08 + 0.12 * rng.random(data.size))
            ax.scatter(data[mask], jitter[mask], s=9, color="tab:green", zorder=3)
            ax.scatter(data[~mask], jitter[~mask], s=9, color="tab:red", marker="x", zorder=3)
            median = float(np.median(data))
            ax.axvline(median, color="k", linestyle="--", linewidth=1, label=f"median {median:.4g}")
            ax.set_ylim(-top * 0.25, top * 1.05)
            ax.set_yticks([t for t in ax.get_yticks() if 0 <= t <= top * 1.05])  # the strip below 0 has no count
            ax.set_xlabel(metric)
            ax.set_ylabel("episodes")
            ax.legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        path = out_dir / f"{figure_name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        result.paths[figure_name] = path
    return result
