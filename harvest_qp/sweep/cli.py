"""``harvest-qp sweep``: the sub-command's arguments and body, for ``harvest_qp.cli`` to mount.

Wiring in ``harvest_qp/cli.py``::

    from harvest_qp.sweep.cli import add_sweep_parser, sweep_main
    add_sweep_parser(sub)                       # next to the other sub-parsers
    ...
    if args.command == "sweep":                 # inside the try: HarvestQPError -> exit code 2
        return sweep_main(args)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.sweep.command import CommandEpisode
from harvest_qp.sweep.runner import run_sweep
from harvest_qp.sweep.seeds import parse_seeds

EpisodeFactory = Callable[[Path, Path, tuple[str, ...]], Callable[[int], Mapping[str, Any]]]


def run_command_episode(
    config: Path, runs_dir: Path, overrides: tuple[str, ...] = (), *, figures: bool = True
) -> Callable[[int], Mapping[str, Any]]:
    """The default episode: ``python -m harvest_qp.cli run CONFIG [--set K=V ...] --seed N --out RUNS_DIR/seed_N``.

    One interpreter per episode (its crash or leak stays there); each seed keeps its run folder.
    ``overrides`` are ``section.key=value`` items passed to every episode as ``--set``;
    ``figures=False`` adds ``--no-figures`` (the log and metrics are still written).
    """
    sets = tuple(arg for item in overrides for arg in ("--set", item))
    argv = (sys.executable, "-m", "harvest_qp.cli", "run", str(config), *sets, *(() if figures else ("--no-figures",)))
    return CommandEpisode(argv, runs_dir=str(runs_dir))


def config_fingerprint(config: Path, overrides: tuple[str, ...] = ()) -> dict[str, str]:
    """What identifies a sweep's experiment: the config's name and the hash of its RESOLVED settings.

    The hash covers the settings the episodes run with (``extends`` followed, ``--set`` overrides
    applied, every default filled in, canonical JSON), not the file's text: editing a comment or spelling out a default
    keeps the fingerprint (the sweep resumes), while changing a value in a file this one
    ``extends`` changes it (the sweep refuses to mix the two experiments).

    Raises:
        ConfigError: the config is not a valid episode configuration (before any episode runs).
    """
    from harvest_qp.config.settings import load_settings

    settings = load_settings(config, list(overrides)).model_dump(exclude={"extends"})
    canonical = json.dumps(settings, sort_keys=True, separators=(",", ":"), default=str)
    return {"config": config.name, "settings_sha256": hashlib.sha256(canonical.encode()).hexdigest()}


def add_sweep_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``sweep`` to the ``harvest-qp`` sub-commands."""
    sweep = subparsers.add_parser(
        "sweep",
        help="run one episode per seed on randomised scenes, locally or on Ray, and summarise",
        description="One closed-loop episode per seed (scene VineSceneParams.sample(seed)); writes sweep.csv "
        "(one row per seed), sweep.md (success rate with a 95 % Wilson interval, failure reasons, medians) "
        "and figures. Re-running the same command skips the seeds already done.",
    )
    sweep.add_argument("config", type=Path, help="YAML config of the episode")
    sweep.add_argument(
        "--seeds", default="0:100", help="'0:100' (seeds 0..99), '3', '1,2,5' or '0:10:2' (default 0:100)"
    )
    sweep.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="override a key of the config for every episode, as for `run` (repeatable), "
        "e.g. --set camera.frame_loss=0.3 --set force_sensor.noise_std=0.2",
    )
    sweep.add_argument("--workers", type=int, default=None, help="parallel episodes (default: the CPUs available)")
    sweep.add_argument("--out", type=Path, default=None, help="sweep folder (default: runs/sweep-<config name>)")
    sweep.add_argument("--engine", choices=("local", "ray"), default="local", help="local processes (default) or Ray")
    sweep.add_argument(
        "--address", default=None, help="Ray head HOST:PORT (or 'auto'); default: a private local Ray instance"
    )
    sweep.add_argument(
        "--episode-timeout", type=float, default=None, metavar="S", help="stop an episode after S seconds"
    )
    sweep.add_argument("--retry-failed", action="store_true", help="run again seeds that raised, died or timed out")
    sweep.add_argument("--no-figures", action="store_true", help="skip the figures")
    sweep.add_argument("--quiet", action="store_true", help="no progress line")
    return sweep


def sweep_main(args: argparse.Namespace, *, episode_for: EpisodeFactory = run_command_episode) -> int:
    """Run the sweep the parsed ``args`` describe; print where the results are. Exit code 0.

    Args:
        args: from the parser of :func:`add_sweep_parser`.
        episode_for: ``(config, runs_dir, overrides) -> episode``; the default runs ``harvest-qp run`` per
            seed with ``--set`` for each override.

    Raises:
        InvalidInputError: a missing config, bad seeds or arguments (the CLI turns it into exit code 2).
        ConfigError: an invalid config (exit code 2 as well), found before any episode runs.
    """
    config = Path(args.config)
    if not config.is_file():
        raise InvalidInputError(f"CONFIG: {str(config)!r} is not a file")
    seeds = parse_seeds(args.seeds)
    out = Path(args.out) if args.out is not None else Path("runs") / f"sweep-{config.stem}"
    overrides = tuple(args.set)
    fingerprint = config_fingerprint(config, overrides)
    result = run_sweep(
        episode_for(config.resolve(), (out / "episodes").resolve(), overrides),
        seeds,
        out_dir=out,
        workers=args.workers,
        engine=args.engine,
        address=args.address,
        progress=not args.quiet,
        episode_timeout=args.episode_timeout,
        retry_failed=args.retry_failed,
        fingerprint=fingerprint,
        figures=not args.no_figures,
        title=f"Sweep of {config.name}",
    )
    summary = result.summary
    low, high = summary.interval
    print(
        f"{summary.successes}/{summary.episodes} episodes succeeded "
        f"({100 * summary.success_rate:.1f} %, 95 % CI {100 * low:.1f}-{100 * high:.1f} %); "
        f"ran {len(result.ran)}, skipped {len(result.skipped)} already done"
    )
    print(f"results: {result.csv_path}\nreport:  {result.report_path}")
    for path in result.figures.paths.values():
        print(f"figure:  {path}")
    return 0
