"""An episode that is a command: ``harvest-qp run CONFIG --seed N --out DIR``, then ``DIR/metrics.json``."""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harvest_qp.exceptions import HarvestQPError, InvalidInputError


class EpisodeCommandError(HarvestQPError):
    """The episode's command failed or wrote no readable ``metrics.json`` (one bad episode, not the sweep)."""


@dataclass(frozen=True)
class CommandEpisode:
    """``seed -> metrics`` by running a command once per seed (picklable, so any engine can use it).

    For seed ``N`` it runs ``[*argv, "--seed", "N", "--out", "<runs_dir>/seed_N"]`` and returns
    the JSON object in ``<runs_dir>/seed_N/<metrics_name>``. Each episode then runs in its own
    interpreter, so a crash or a leak in one never reaches the next, and each keeps its
    run folder (log, figures) for inspection or replay.

    Attributes:
        argv: the command before the seed, e.g. ``("harvest-qp", "run", "tasks/paper.yaml")``.
        runs_dir: where the per-seed run folders go (absolute, or relative to the sweep's cwd).
        metrics_name: the metrics file in a run folder.
        timeout: seconds [s] after which the command is killed (``None``: no limit).
        env: extra environment variables for the command.
        unsuccessful_codes: exit codes that mean "the episode ran and was not a success" (``harvest-qp
            run`` exits 1 then, after writing ``metrics.json``): with a fresh metrics file the row
            keeps the episode's metrics and its abort reason; any other non-zero code is an error.
    """

    argv: tuple[str, ...]
    runs_dir: str
    metrics_name: str = "metrics.json"
    timeout: float | None = None
    env: tuple[tuple[str, str], ...] = ()
    unsuccessful_codes: tuple[int, ...] = (1,)

    def __post_init__(self) -> None:
        if isinstance(self.argv, str) or not isinstance(self.argv, Sequence) or not self.argv:
            raise InvalidInputError(f"argv must be a non-empty sequence of strings, got {self.argv!r}")
        if not all(isinstance(a, str) for a in self.argv):
            raise InvalidInputError(f"argv must hold strings only, got {self.argv!r}")
        object.__setattr__(self, "argv", tuple(self.argv))
        if isinstance(self.env, Mapping):
            object.__setattr__(self, "env", tuple(sorted(self.env.items())))
        object.__setattr__(self, "runs_dir", str(Path(self.runs_dir).resolve()))

    def run_dir(self, seed: int) -> Path:
        """The run folder of one seed."""
        return Path(self.runs_dir) / f"seed_{seed}"

    def __call__(self, seed: int) -> dict[str, Any]:
        run_dir = self.run_dir(seed)
        metrics_path = run_dir / self.metrics_name
        if metrics_path.exists():
            metrics_path.unlink()  # a stale file from an interrupted earlier run must not pass for this one
        command = [*self.argv, "--seed", str(seed), "--out", str(run_dir)]
        try:
            completed = subprocess.run(
                command,
                capture_output=True,
                text=True,
                timeout=self.timeout,
                env={**os.environ, **dict(self.env)} if self.env else None,
                check=False,
            )
        except subprocess.TimeoutExpired:
            raise EpisodeCommandError(f"{' '.join(command)} ran longer than {self.timeout:g} s") from None
        except OSError as exc:
            raise EpisodeCommandError(f"cannot run {command[0]!r}: {exc}") from None
        ran_unsuccessfully = completed.returncode in self.unsuccessful_codes and metrics_path.is_file()
        if completed.returncode != 0 and not ran_unsuccessfully:
            tail = (completed.stderr or completed.stdout).strip().splitlines()[-3:]
            raise EpisodeCommandError(
                f"{' '.join(command)} exited with code {completed.returncode}: {' / '.join(tail) or 'no output'}"
            )
        try:
            metrics = json.loads(metrics_path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise EpisodeCommandError(f"{' '.join(command)} wrote no readable {metrics_path}: {exc}") from None
        if not isinstance(metrics, dict):
            raise EpisodeCommandError(f"{metrics_path} holds {type(metrics).__name__}, expected a JSON object")
        return metrics
