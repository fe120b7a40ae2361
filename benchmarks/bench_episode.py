"""Real-time factor of the paper episode (``harvest-qp run tasks/paper.yaml``) on one core.

Runs the paper's closed loop (:class:`harvest_qp.loop.HarvestController` on the simulated
dual UR5e in the default vine scene, through :func:`harvest_qp.loop.episode.run_paper_episode`
without figures) at the paper's 283x160 (848x480 downsampled by 3) and at the full 848x480,
after a short warm-up episode that compiles the numba kernels. The process is pinned to one
CPU core and BLAS to one thread.

Per-tick breakdown (medians, and totals as shares of the wall-clock time):

* perception per frame (stem split, stem fit, unveiling pairs and V_cu target);
* reference laws per tick (V_cr, V_cu filter, V_g or the hold, feed-forward, switch and
  safety logic);
* QP step per tick inside the episode (``TaskController.step``);
* simulation: the rest of the wall-clock time (physics, camera ray casting, logging).

Usage::

    python benchmarks/bench_episode.py [--duration 20] [--settings tasks/paper.yaml] [--set k=v ...]

The last line printed is one JSON object with ``episode_rtf_283x160``, ``episode_rtf_848x480``,
``qp_tick_us_in_episode`` (median QP step at 283x160), ``perception_ms_283x160`` (median per
frame) and the other medians. Timings on a shared machine are noisy: run it alone.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from harvest_qp.loop.controller import HarvestController  # noqa: E402
from harvest_qp.loop.episode import build_robot, environment_capsules_for  # noqa: E402
from harvest_qp.loop.settings import load_settings  # noqa: E402
from harvest_qp.robot.paths import tasks_dir  # noqa: E402
from harvest_qp.runner import run_episode  # noqa: E402


def _pin() -> str:
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned"


def time_episode(settings: dict, duration: float) -> dict:
    """One episode with the controller's timers on; returns the breakdown."""
    robot = build_robot(settings, 0)
    controller = HarvestController(settings, environment=environment_capsules_for(robot, settings["qp"]["environment"]))
    controller.timing = {}
    wall0 = time.perf_counter()
    result = run_episode(robot, controller, duration=duration, log_timing=True)
    wall = time.perf_counter() - wall0
    timing = controller.timing
    perception = np.array(timing.get("perception", [np.nan]))
    references = np.array(timing.get("references", [np.nan]))
    mapper = np.array(timing.get("mapper", [np.nan]))
    controller_total = float(np.nansum(result.log["controller_time"]))
    return {
        "rtf": result.sim_time / wall,
        "sim_time": result.sim_time,
        "wall": wall,
        "phase": controller.phase.name.lower(),
        "perception_ms_median": 1e3 * float(np.median(perception)),
        "perception_ms_p90": 1e3 * float(np.percentile(perception, 90)),
        "references_us_median": 1e6 * float(np.median(references)),
        "qp_us_median": 1e6 * float(np.median(mapper)),
        "share_perception": float(np.sum(perception)) / wall,
        "share_references": float(np.sum(references)) / wall,
        "share_qp": float(np.sum(mapper)) / wall,
        "share_simulation_and_logging": (wall - controller_total) / wall,
        "stem_points_last": int(result.log["stem_points"][-1]),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float, default=20.0, help="simulated seconds per resolution")
    parser.add_argument("--settings", type=Path, default=tasks_dir() / "paper.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    args = parser.parse_args(argv)
    print(_pin())
    base = load_settings(args.settings, args.overrides)
    with tempfile.TemporaryDirectory():
        time_episode(load_settings(args.settings, [*args.overrides, "camera.downsample=6"]), 0.2)  # numba warm-up
    out = {}
    for name, downsample in (("283x160", 3), ("848x480", 1)):
        settings = load_settings(args.settings, [*args.overrides, f"camera.downsample={downsample}"])
        r = time_episode(settings, args.duration)
        print(f"{name}: real-time factor {r['rtf']:.2f} ({r['sim_time']:.1f} s in {r['wall']:.1f} s, ended in "
              f"{r['phase']}); perception {r['perception_ms_median']:.2f} ms/frame median "
              f"(p90 {r['perception_ms_p90']:.2f}), references {r['references_us_median']:.0f} us/tick, "
              f"QP {r['qp_us_median']:.0f} us/tick; wall-clock shares: perception {r['share_perception']:.0%}, "
              f"references {r['share_references']:.0%}, QP {r['share_qp']:.0%}, simulation+logging "
              f"{r['share_simulation_and_logging']:.0%}")
        out[name] = r
    del base
    summary = {
        "episode_rtf_283x160": out["283x160"]["rtf"],
        "episode_rtf_848x480": out["848x480"]["rtf"],
        "qp_tick_us_in_episode": out["283x160"]["qp_us_median"],
        "perception_ms_283x160": out["283x160"]["perception_ms_median"],
        "perception_ms_848x480": out["848x480"]["perception_ms_median"],
        "references_us_283x160": out["283x160"]["references_us_median"],
        "duration_s": args.duration,
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
