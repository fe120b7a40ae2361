"""Many closed-loop episodes: ``harvest-qp sweep CONFIG --seeds 0:100``.

One episode per seed on randomised scenes, in K local processes or as Ray tasks; results in
``sweep.csv`` (one row per seed), ``sweep.md`` (success rate with a 95 % Wilson interval,
failure reasons, medians) and figures. Resumable: seeds already in ``sweep.csv`` are skipped.

Example::

    from functools import partial
    from harvest_qp.sweep import parse_seeds, run_sweep

    result = run_sweep(partial(my_episode, config_path), parse_seeds("0:100"), out_dir="runs/sweep")
    print(result.summary.success_rate, result.summary.interval)
"""

from harvest_qp.sweep.command import CommandEpisode, EpisodeCommandError
from harvest_qp.sweep.engines import MissingDependencyError, SweepEngineError, run_episode
from harvest_qp.sweep.report import SweepFigures, plot_sweep, render_markdown
from harvest_qp.sweep.results import normalize_metrics, read_rows
from harvest_qp.sweep.runner import SweepResult, run_sweep
from harvest_qp.sweep.seeds import check_seeds, parse_seeds
from harvest_qp.sweep.stats import MetricSummary, SweepSummary, failure_reason, summarize, wilson_interval

__all__ = [
    "CommandEpisode",
    "EpisodeCommandError",
    "MetricSummary",
    "MissingDependencyError",
    "SweepEngineError",
    "SweepFigures",
    "SweepResult",
    "SweepSummary",
    "check_seeds",
    "failure_reason",
    "normalize_metrics",
    "parse_seeds",
    "plot_sweep",
    "read_rows",
    "render_markdown",
    "run_episode",
    "run_sweep",
    "summarize",
    "wilson_interval",
]
