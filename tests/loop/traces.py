"""Stored regression traces of the paper episode: what they hold, how they are recorded and compared.

A trace is the episode of ``harvest-qp run tasks/paper.yaml --seed N`` with the scene tests'
settings (``conftest.SCENE_ARGS``), thinned to every :data:`STRIDE`-th tick: joint positions,
the controller's force along n_c, the lab's true stem tension, the phase, and the metrics that
decide success. They replace bit identity with an earlier version: a change that is meant to keep
behaviour (a refactor, a faster kernel) must stay within :data:`TOLERANCES` of them; a change
that is meant to alter behaviour re-records them (``python -m tests.loop.traces``) and says why in
its commit message.

Re-record: ``python -m tests.loop.traces`` (seeds 0-5, ~2 min once the kernels are compiled).
"""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent / "traces"
SEEDS = (0, 1, 2, 3, 4, 5)
#: Every STRIDE-th tick is stored (2 ms ticks: 0.1 s apart).
STRIDE = 50
#: Per-tick series stored, by log key.
SERIES = ("t", "q", "value/force_nc", "truth/stem_tension", "value/phase", "value/position_error")
#: Metrics stored and compared exactly (booleans, counts, phase names).
EXACT_METRICS = ("success", "phase_reached", "stem_torn", "contacts", "qp_failures", "abort_reason")
#: Metrics stored and compared with an absolute tolerance, by name: [s], [s], [m], [N], [m].
CLOSE_METRICS = {
    "t_bimanual_start": 0.05,
    "t_precut": 0.5,
    "final_position_error": 2e-3,
    "force_mean_last_1s": 0.1,
    "min_collision_distance": 2e-3,
}
#: Largest difference allowed per series over the common time span: [rad], [N], [N], [m].
#: Round-off alone stays orders of magnitude below these (a reordered sum moved q by <= 2e-11 rad
#: over 20 s); a phase switch moved by a few ticks moves q by ~1e-3 rad at the arms' speeds.
TOLERANCES = {"q": 5e-3, "value/force_nc": 0.25, "truth/stem_tension": 0.25, "value/position_error": 3e-3}


def thin(log: dict, metrics: dict) -> dict[str, np.ndarray]:
    """The stored part of an episode's log and metrics."""
    out = {key: np.asarray(log[key])[::STRIDE] for key in SERIES}
    out["metrics"] = np.array(json.dumps({k: metrics.get(k) for k in (*EXACT_METRICS, *CLOSE_METRICS)}))
    return out


def load(seed: int) -> dict:
    data = np.load(HERE / f"seed{seed}.npz")
    out = {key: data[key] for key in SERIES}
    out["metrics"] = json.loads(str(data["metrics"]))
    return out


def differences(stored: dict, log: dict, metrics: dict) -> list[str]:
    """What lies outside the tolerances between a stored trace and a new episode (empty: none)."""
    new = thin(log, metrics)
    problems = []
    old_metrics = stored["metrics"]
    for key in EXACT_METRICS:
        if old_metrics[key] != metrics.get(key):
            problems.append(f"{key}: stored {old_metrics[key]!r}, now {metrics.get(key)!r}")
    for key, tol in CLOSE_METRICS.items():
        a, b = old_metrics[key], metrics.get(key)
        if (a is None) != (b is None) or (a is not None and abs(float(a) - float(b)) > tol):
            problems.append(f"{key}: stored {a!r}, now {b!r} (tolerance {tol})")
    n = min(len(stored["t"]), len(new["t"]))
    if not np.allclose(stored["t"][:n], new["t"][:n], atol=1e-9):
        problems.append("t: the ticks' times differ")
    for key, tol in TOLERANCES.items():
        diff = np.abs(np.asarray(stored[key][:n], float) - np.asarray(new[key][:n], float))
        worst = float(np.nanmax(diff)) if diff.size else 0.0
        if not worst <= tol:
            i = int(np.nanargmax(diff.reshape(n, -1).max(axis=1)))
            problems.append(f"{key}: max difference {worst:.3g} > {tol} (first worst at t = {new['t'][i]:.2f} s)")
    return problems


def record(seeds=SEEDS) -> None:  # pragma: no cover (a maintenance command)
    from harvest_qp.cli import main
    from harvest_qp.robot.paths import tasks_dir
    from tests.loop.conftest import SCENE_ARGS

    HERE.mkdir(exist_ok=True)
    for seed in seeds:
        with tempfile.TemporaryDirectory() as out:
            main(["run", str(tasks_dir() / "paper.yaml"), "--seed", str(seed), "--out", out, *SCENE_ARGS,
                  "--no-figures"])
            log = dict(np.load(Path(out) / "episode.npz"))
            metrics = json.loads((Path(out) / "metrics.json").read_text())
        np.savez_compressed(HERE / f"seed{seed}.npz", **thin(log, metrics))
        print(f"seed {seed}: {len(log['t'])} ticks, success {metrics['success']}, t_precut {metrics['t_precut']}")


if __name__ == "__main__":  # pragma: no cover
    record(tuple(int(s) for s in sys.argv[1:]) or SEEDS)
