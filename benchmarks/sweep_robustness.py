"""The paper episode on many randomised scenes: success with its interval, every failure with its class,
and the time to pre-cut, per configuration (issue 20's evidence).

Each configuration is one ``harvest-qp sweep`` (one interpreter per episode, resumable): the clean
scenes (``tasks/paper.yaml``), the lab's mild sensor noise (``tasks/paper_randomized.yaml``) and a
faults configuration (``paper.yaml`` with 30 % of the camera frames lost, 50 ms of camera latency and
0.2 N of force noise, given as ``--set``). Success is judged as a grower would, on top of the
episode's own ``success``: the true stem never torn, the true stem tension never above 2 f_d, and at
most 25 ticks (50 ms) with a robot contact.

Seeds: development sweeps use 10000-19999 (``--seeds``); ``--held-out`` names a range kept unseen
during development, reported separately. Never tune on a failing seed and report it as evidence.

Usage::

    python benchmarks/sweep_robustness.py --seeds 10000:10200 [--held-out 19800:20000] [--workers 2]
        [--configs paper randomized faults] [--out runs/robustness]

Prints one block per configuration and range, and, last, one JSON object with the same figures.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from harvest_qp.robot.paths import tasks_dir  # noqa: E402
from harvest_qp.sweep import parse_seeds  # noqa: E402
from harvest_qp.sweep.cli import config_fingerprint, run_command_episode  # noqa: E402
from harvest_qp.sweep.robustness import summarise  # noqa: E402
from harvest_qp.sweep.runner import run_sweep  # noqa: E402

#: name -> (config file, --set overrides)
CONFIGS: dict[str, tuple[str, tuple[str, ...]]] = {
    "paper": ("paper.yaml", ()),
    "randomized": ("paper_randomized.yaml", ()),
    "faults": ("paper.yaml", ("camera.frame_loss=0.3", "camera.latency=0.05", "force_sensor.noise_std=0.2")),
}
def _print(name: str, label: str, s: Mapping[str, Any]) -> None:
    n = s["episodes"]
    lo, hi = s["grower_interval"]
    rate = 100 * s["grower_success"] / max(n, 1)
    print(f"{name} ({label}): grower's success {s['grower_success']}/{n} = {rate:.1f} % "
          f"(95 % CI {100 * lo:.1f}-{100 * hi:.1f} %); episode's own success {s['success']}/{n}; "
          f"torn {s['torn']}, contact > 50 ms {s['contact_over_50ms']}; "
          f"time to pre-cut median {s['t_precut_median']:.1f} s, p90 {s['t_precut_p90']:.1f} s")
    for cls, seeds in s["failures"].items():
        print(f"  {cls}: {len(seeds)} ({', '.join(map(str, seeds))})")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="10000:10200", help="development seeds (default 10000:10200)")
    parser.add_argument("--held-out", default=None, help="seeds kept unseen during development, reported apart")
    parser.add_argument("--configs", nargs="+", choices=sorted(CONFIGS), default=list(CONFIGS))
    parser.add_argument("--workers", type=int, default=None)
    parser.add_argument("--out", type=Path, default=Path("runs") / "robustness")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="an override for every configuration (e.g. camera.downsample=6 for a quick look)")
    args = parser.parse_args(argv)
    ranges = [("development", parse_seeds(args.seeds))]
    if args.held_out:
        ranges.append(("held out", parse_seeds(args.held_out)))
    report: dict[str, Any] = {}
    for name in args.configs:
        file, overrides = CONFIGS[name]
        overrides = (*overrides, *args.overrides)
        config = (tasks_dir() / file).resolve()
        out = args.out / name
        result = run_sweep(
            run_command_episode(config, (out / "episodes").resolve(), overrides, figures=False),
            sorted({s for _, seeds in ranges for s in seeds}),
            out_dir=out, workers=args.workers, progress=True, figures=False,
            fingerprint=config_fingerprint(config, overrides), title=f"Robustness: {name}",
        )
        by_seed = {int(row["seed"]): row for row in result.rows}
        for label, seeds in ranges:
            summary = summarise([by_seed[s] for s in seeds if s in by_seed])
            _print(name, label, summary)
            report[f"{name}/{label}"] = summary
    print(json.dumps(report, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
