"""The paper's bimanual episode from Python: settings -> lab -> HarvestController -> metrics.

This is what ``harvest-qp run tasks/paper.yaml`` does, through the library API so that you
can change any part of it: the settings are a checked dictionary (edit keys before the run),
and ``run_paper_episode`` builds the MuJoCo lab (the vine scene and the dual UR5e with its
depth camera and wrist force sensor), runs the closed loop of Section ``sec:contr``
(perception -> reference velocities -> QP -> joints) and writes ``metrics.json`` and the
episode log (``episode.npz``) to ``--out``.

The full experiment needs ~30-50 s of simulated time (the switch to the bimanual phase comes
at ~5-12 s); ``--duration 2`` shows the camera arm's approach in a few seconds of wall time.
``--viewer meshcat`` opens the live 3-D view (URL printed; the loop is paced to real time
unless ``--fast``).

    python examples/03_paper_episode.py [--duration 50] [--seed 0] [--out runs/example-03]
                                        [--set grasping.f_d=2.5] [--viewer meshcat] [--figures]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from harvest_qp.config.settings import load_settings
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim.paper_episode import run_paper_episode


def run(
    *,
    duration: float = 50.0,
    seed: int = 0,
    out_dir: Path = Path("runs/example-03"),
    overrides: list[str] | None = None,
    viewer: bool = False,
    realtime: bool = True,
    port: int = 7000,
    figures: bool = False,
):
    """Run one episode; returns the :class:`~harvest_qp.sim.paper_episode.EpisodeReport`."""
    # 1. Settings: tasks/paper.yaml (the paper's values) plus "section.key=value" overrides,
    #    all checked: a typo or an out-of-range value raises ConfigError naming the key.
    settings = load_settings(tasks_dir() / "paper.yaml", overrides or [])

    # 2. Optional live viewer. It only observes: it wraps the controller and sees each tick,
    #    so the control loop is the same with and without it.
    live = None

    def with_viewer(robot, controller):
        nonlocal live
        from harvest_qp.viewer import LiveViewer, RealTimePacer, ViewedController, paper_episode_extras

        live = LiveViewer(vine=robot.model, port=port)  # prints the URL to open
        return ViewedController(controller, live, extras=paper_episode_extras(settings.reaching.radius,
                                                                  cell_resolution=settings.obstacle_map.resolution,
                                                                  controller=controller),
                                pacer=RealTimePacer() if realtime else None)  # fmt: skip

    # 3. The episode. seed 0 is the paper's default scene, seed N > 0 a randomised vine.
    try:
        report = run_paper_episode(
            settings, seed=seed, duration=duration, out_dir=out_dir, figures=figures,
            wrap_controller=with_viewer if viewer else None,
        )  # fmt: skip
    finally:
        if live is not None:
            live.close()  # draws the last tick and stops the viewer's server
    if live is not None and live.error is not None:
        # The viewer never raises into the control loop; it keeps its error for us instead.
        raise SystemExit(f"the viewer stopped drawing: {live.error!r}")
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=50.0, help="simulated time [s] (default 50)")
    parser.add_argument("--seed", type=int, default=0, help="0: the paper's scene; N > 0: a randomised vine")
    parser.add_argument("--out", type=Path, default=Path("runs/example-03"), help="output folder")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a setting, e.g. grasping.f_d=2.5 (repeatable)",
    )
    parser.add_argument("--viewer", choices=("none", "meshcat"), default="none", help="live 3-D viewer")
    parser.add_argument("--fast", action="store_true", help="with --viewer: do not pace the loop to real time")
    parser.add_argument("--port", type=int, default=7000, help="viewer web port")
    parser.add_argument("--figures", action="store_true", help="also write the paper-style PNG figures")
    args = parser.parse_args()
    report = run(
        duration=args.duration,
        seed=args.seed,
        out_dir=args.out,
        overrides=args.overrides,
        viewer=args.viewer == "meshcat",
        realtime=not args.fast,
        port=args.port,
        figures=args.figures,
    )

    # 4. What happened. The controller saw only joint states, the wrist force and the
    #    camera's clouds; the metrics compare with the lab's ground truth afterwards.
    m = report.metrics
    log = report.result.log
    p_sb = log["value/p_sb"][-1]  # the controller's last estimate of the stem base [m] (NaN: none yet)
    print(f"phase reached: {m['phase_reached']} (success: {m['success']})")
    print(f"bimanual phase started at t = {m['t_bimanual_start']} s")
    print(
        f"camera to the true stem base at the end: {m['final_distance_to_roi_center']:.4f} m "
        f"(ROI radius r = {m['roi_radius']} m)"
    )
    print(f"visible stem points: start {m['visible_stem_points_start']}, end {m['visible_stem_points_end']}")
    if np.all(np.isfinite(p_sb)):
        print(f"estimated p_sb: {np.array2string(p_sb, precision=4, separator=', ')} m")
    print(f"contacts with the vine: {m['contacts']}, QP failures: {m['qp_failures']}")
    print(f"closest collision pair distance: {1e3 * m['min_collision_distance']:.1f} mm")
    print(f"wrote {report.out_dir / 'metrics.json'} and {report.log_path}")
    sys.stdout.flush()


if __name__ == "__main__":
    main()
