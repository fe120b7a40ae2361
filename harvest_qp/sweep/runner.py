"""``run_sweep``: one episode per seed, locally or on Ray, resumable, with a report."""

from __future__ import annotations

import os
import pickle
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.sweep.engines import MissingDependencyError, Outcome, default_workers, import_ray, run_local, run_ray
from harvest_qp.sweep.report import REPORT_NAME, SweepFigures, plot_sweep, render_markdown
from harvest_qp.sweep.results import SweepStore, read_manifest, sweep_lock, write_manifest
from harvest_qp.sweep.seeds import check_seeds
from harvest_qp.sweep.stats import STATUS_OK, SweepSummary, is_success, summarize

ENGINES = ("local", "ray")
ERRORS_DIR = "errors"


@dataclass
class SweepResult:
    """The state of a sweep folder after :func:`run_sweep`.

    Attributes:
        out_dir: the folder; ``csv_path`` / ``report_path`` are its ``sweep.csv`` / ``sweep.md``.
        rows: every row of ``sweep.csv`` (earlier runs included), by seed, values parsed.
        ran: seeds run by this call, in the order they finished.
        skipped: requested seeds already in ``sweep.csv``, not run again.
        summary: success rate, Wilson interval, failure reasons and medians over ``rows``.
        figures: the figures written (empty when ``figures=False`` or matplotlib is missing).
        wall_time_s: wall-clock time of this call [s].
    """

    out_dir: Path
    csv_path: Path
    report_path: Path
    rows: list[dict[str, Any]]
    ran: list[int]
    skipped: list[int]
    summary: SweepSummary
    figures: SweepFigures = field(default_factory=SweepFigures)
    wall_time_s: float = 0.0


class _Progress:
    """``sweep: 37/100 episodes done, 30 succeeded (81 %), 1 failed to run, 1m12s elapsed, ETA 2m03s`` on stderr.

    Redrawn in place on a terminal; elsewhere (CI logs, files) one line at most every
    ``interval`` seconds, and always the last one.
    """

    def __init__(self, total: int, stream: TextIO | None, *, interval: float = 5.0) -> None:
        self.total, self.stream, self.interval = total, stream, interval
        self.done = self.successes = self.lost = 0
        self.start = time.monotonic()
        self.last_print = -float("inf")
        self.tty = bool(stream is not None and getattr(stream, "isatty", lambda: False)())

    def log(self, message: str) -> None:
        if self.stream is not None:
            self.stream.write(("\n" if self.tty else "") + f"sweep: {message}\n")
            self.stream.flush()

    def update(self, outcome: Outcome, row: Mapping[str, Any]) -> None:
        self.done += 1
        self.successes += is_success(row)
        self.lost += outcome["status"] != STATUS_OK
        if self.stream is None:
            return
        now = time.monotonic()
        last = self.done == self.total
        if not (self.tty or last or now - self.last_print >= self.interval):
            return
        self.last_print = now
        elapsed = now - self.start
        eta = elapsed / self.done * (self.total - self.done)
        line = (
            f"sweep: {self.done}/{self.total} episodes done, {self.successes} succeeded"
            f" ({100 * self.successes / self.done:.0f} %), {self.lost} failed to run,"
            f" {_duration(elapsed)} elapsed, ETA {_duration(eta)}"
        )
        if self.tty:
            self.stream.write("\r" + line.ljust(100) + ("\n" if last else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()


def _duration(seconds: float) -> str:
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours}h{minutes:02d}m{secs:02d}s" if hours else f"{minutes}m{secs:02d}s" if minutes else f"{secs}s"


def _row(outcome: Outcome) -> dict[str, Any]:
    """The ``sweep.csv`` row of one outcome: bookkeeping columns, then the metrics."""
    row: dict[str, Any] = {"seed": outcome["seed"], "status": outcome["status"]}
    if outcome.get("error"):
        row["error"] = outcome["error"]
    if outcome.get("wall_time_s") is not None:
        row["wall_time_s"] = outcome["wall_time_s"]
    for name, value in outcome["metrics"].items():
        if name == "seed" and value == outcome["seed"]:
            continue  # the episode repeating its own seed
        if name in ("seed", "status", "error", "wall_time_s"):
            name = f"metric_{name}"
        row[name] = value  # None too: the store gives it a column (an empty cell), e.g. abort_reason
    return row


def run_sweep(
    episode: Callable[[int], Mapping[str, Any]],
    seeds: Sequence[int],
    *,
    out_dir: str | os.PathLike,
    workers: int | None = None,
    engine: str = "local",
    address: str | None = None,
    progress: bool | TextIO = True,
    episode_timeout: float | None = None,
    retry_failed: bool = False,
    fingerprint: Mapping[str, Any] | None = None,
    figures: bool = True,
    title: str = "Sweep",
    ray_init_kwargs: Mapping[str, Any] | None = None,
) -> SweepResult:
    """Run ``episode(seed)`` once per seed and write ``sweep.csv``, ``sweep.md`` and figures to ``out_dir``.

    The episode gets the seed itself (the closed loop builds its scene with
    ``VineSceneParams.sample(seed)``), so each row depends on its seed alone: the same
    for any ``workers`` and either engine (only ``wall_time_s`` differs).

    Args:
        episode: ``seed -> metrics`` (a mapping of name to number / bool / text / None /
            list / nested mapping). For the local engine it must be picklable: a module-level
            function or a ``functools.partial`` of one.
        seeds: non-negative, distinct seeds (see :func:`~harvest_qp.sweep.parse_seeds`).
        out_dir: the sweep's folder (created). Seeds already in its ``sweep.csv`` are skipped,
            so re-running a command resumes it.
        workers: local processes (default: the CPUs this process may use); with Ray, the CPUs
            of the local instance, or the most tasks in flight on a cluster.
        engine: ``"local"`` (spawned processes) or ``"ray"``.
        address: Ray only: ``HOST:PORT`` of a running cluster's head (or ``"auto"``); without it a
            private local Ray instance is started and stopped.
        progress: print progress on stderr (or on the given stream); ``False`` for silence.
        episode_timeout: stop an episode after this many seconds [s] (recorded as ``timeout``).
        retry_failed: also run again the seeds whose row is not ``ok`` (errors, dead workers, timeouts).
        fingerprint: what identifies the experiment (e.g. the config's path and hash), stored in
            ``sweep.json``; resuming a folder whose fingerprint differs raises instead of mixing
            two experiments in one table.
        figures: write the figures (skipped with a note when matplotlib is missing).
        title: first line of ``sweep.md``.
        ray_init_kwargs: extra keyword arguments for ``ray.init`` (e.g. ``runtime_env``).

    Raises:
        InvalidInputError: bad seeds, workers, engine, address, timeout or episode; a folder
            holding another experiment or in use by another sweep.
        MissingDependencyError: ``engine="ray"`` without Ray installed (names the extra to install).
        SweepEngineError: the engine itself failed (not one episode).
    """
    started = time.monotonic()
    seeds = check_seeds(seeds)
    if engine not in ENGINES:
        raise InvalidInputError(f"engine must be one of {ENGINES}, got {engine!r}")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise InvalidInputError(f"workers must be a positive integer or None, got {workers!r}")
    if address is not None and engine != "ray":
        raise InvalidInputError(
            f"address is for engine='ray' (a Ray cluster), got address={address!r} with engine={engine!r}"
        )
    if address is not None and (not isinstance(address, str) or not address.strip()):
        raise InvalidInputError(f"address must be 'HOST:PORT' of a Ray head node or 'auto', got {address!r}")
    if episode_timeout is not None and not (
        isinstance(episode_timeout, (int, float)) and not isinstance(episode_timeout, bool) and episode_timeout > 0
    ):
        raise InvalidInputError(
            f"episode_timeout must be a positive number of seconds or None, got {episode_timeout!r}"
        )
    if not callable(episode):
        raise InvalidInputError(f"episode must be a callable seed -> metrics, got {episode!r}")
    if engine == "local":
        try:
            pickle.dumps(episode)
        except Exception as exc:
            raise InvalidInputError(
                f"episode must be picklable for engine='local' (a module-level function or a functools.partial "
                f"of one, not a lambda or a nested function), got {episode!r}: {exc}"
            ) from None
    else:
        import_ray()  # fail before touching the folder
    stream: TextIO | None = sys.stderr if progress is True else (progress or None)
    out_dir = Path(out_dir)
    with sweep_lock(out_dir):
        manifest = read_manifest(out_dir)
        wanted = dict(fingerprint) if fingerprint is not None else None
        if manifest is not None and wanted is not None and manifest.get("fingerprint") not in (None, wanted):
            raise InvalidInputError(
                f"out_dir: {str(out_dir)!r} holds a sweep of another experiment (fingerprint "
                f"{manifest.get('fingerprint')!r}, this one {wanted!r}); use another --out folder "
                "(or delete its sweep.json to add to it anyway)"
            )
        store = SweepStore(out_dir)
        if manifest is None or (wanted is not None and manifest.get("fingerprint") is None):
            write_manifest(out_dir, {"fingerprint": wanted})
        done = {seed for seed, row in store.rows.items() if not (retry_failed and row.get("status") != STATUS_OK)}
        todo = [seed for seed in seeds if seed not in done]
        skipped = [seed for seed in seeds if seed in done]
        reporter = _Progress(len(todo), stream)
        if skipped and stream is not None:
            reporter.log(f"{len(skipped)} of {len(seeds)} seeds already in {store.csv_path}, skipped")
        ran: list[int] = []

        def record(outcome: Outcome) -> None:
            row = _row(outcome)
            store.add(row)
            ran.append(outcome["seed"])
            if outcome.get("traceback"):
                errors = out_dir / ERRORS_DIR
                errors.mkdir(exist_ok=True)
                (errors / f"seed_{outcome['seed']}.txt").write_text(outcome["traceback"], encoding="utf-8")
            reporter.update(outcome, row)

        n_workers = workers or default_workers()
        if todo and engine == "local":
            run_local(episode, todo, record, workers=n_workers, episode_timeout=episode_timeout, log=reporter.log)
        elif todo:
            run_ray(
                episode,
                todo,
                record,
                workers=workers,
                address=address,
                episode_timeout=episode_timeout,
                init_kwargs=ray_init_kwargs,
                log=reporter.log,
            )
        store.rewrite()  # sorted by seed, canonical columns
        rows = store.sorted_rows()
        summary = summarize(rows, columns=store.columns)
        drawn = SweepFigures()
        if figures:
            try:
                drawn = plot_sweep(rows, out_dir)
            except MissingDependencyError as exc:
                reporter.log(f"figures skipped: {exc}")
        seed_list = sorted(store.rows)
        meta = {
            "seeds": f"{len(seed_list)} ({seed_list[0]}..{seed_list[-1]})" if seed_list else "none",
            "last run": f"{len(ran)} episodes on engine={engine}"
            + (f" at {address}" if address else f" with {n_workers} workers" if engine == "local" else "")
            + f", {_duration(time.monotonic() - started)}",
        }
        if wanted:
            meta.update({f"fingerprint.{k}": v for k, v in wanted.items()})
        report_path = out_dir / REPORT_NAME
        report_path.write_text(
            render_markdown(summary, title=title, meta=meta, figures=[str(p) for p in drawn.paths.values()]),
            encoding="utf-8",
        )
        return SweepResult(
            out_dir=out_dir,
            csv_path=store.csv_path,
            report_path=report_path,
            rows=rows,
            ran=ran,
            skipped=skipped,
            summary=summary,
            figures=drawn,
            wall_time_s=time.monotonic() - started,
        )
