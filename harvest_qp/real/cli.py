"""Command-line parts of the field side: ``run --robot ur`` options and ``harvest-qp calibrate``.

:mod:`harvest_qp.cli` adds these to its parser and hands over; nothing here is imported by the
lab's commands, and the hardware packages are imported only when a command needs them.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from harvest_qp.exceptions import HarvestQPError

__all__ = ["add_run_options", "check_sim_run", "run_ur", "add_calibrate_parser", "calibrate_main"]


def add_run_options(run: argparse.ArgumentParser) -> None:
    """``--robot ur --camera-arm IP --grasp-arm IP --camera realsense [--serial S] [--cell F] [--dry-run]``."""
    group = run.add_argument_group("real robots (--robot ur; see docs/real_robots.md)")
    group.add_argument("--robot", choices=("sim", "ur"), default="sim",
                       help="sim: the MuJoCo lab (default); ur: two UR5e through ur-rtde")
    group.add_argument("--camera-arm", metavar="IP", help="the camera arm's address (with --robot ur)")
    group.add_argument("--grasp-arm", metavar="IP", help="the grasping arm's address (with --robot ur)")
    group.add_argument("--camera", choices=("realsense", "none"), default="realsense",
                       help="the camera of --robot ur (none: arms only, for a dry run)")
    group.add_argument("--serial", default=None, help="the RealSense's serial number (default: the only one)")
    group.add_argument("--cell", type=Path, default=None,
                       help="the cell file (default tasks/real/ur5e.yaml): calibration, F/T, watchdog, camera")
    group.add_argument("--dry-run", action="store_true",
                       help="with --robot ur: connect, read and print the state (joints, force, one cloud, the "
                       "calibration); moves nothing")
    group.add_argument("--no-warmup", action="store_true",
                       help="with --robot ur: skip running the lab episode first (it loads the compiled kernels, "
                       "whose first calls would otherwise come mid-episode and trip the watchdog)")


def check_sim_run(args: argparse.Namespace) -> None:
    """The real-robot options are errors on the lab (``--robot sim``), not silently ignored."""
    given = [name for name, value in (("--camera-arm", args.camera_arm), ("--grasp-arm", args.grasp_arm),
                                      ("--serial", args.serial), ("--cell", args.cell), ("--dry-run", args.dry_run),
                                      ("--no-warmup", getattr(args, "no_warmup", False)))
             if value]
    if given:
        raise HarvestQPError(f"{', '.join(given)} only apply with --robot ur (the lab is --robot sim, the default)")


def run_ur(args: argparse.Namespace, **test_hooks: Any) -> int:
    """``harvest-qp run CONFIG --robot ur ...``: the exit code (0 success or dry run, 1 failed criteria)."""
    from harvest_qp.real.episode import run_real

    if not args.camera_arm or not args.grasp_arm:
        raise HarvestQPError("--robot ur needs --camera-arm IP and --grasp-arm IP")
    if args.viewer != "none":
        raise HarvestQPError("--viewer is not available with --robot ur (replay the run afterwards: harvest-qp replay)")
    if args.camera == "none" and not args.dry_run:
        raise HarvestQPError("--camera none only with --dry-run: the episode needs the camera (the arms would move "
                             "without perception)")
    result = run_real(args.config, camera_arm=args.camera_arm, grasp_arm=args.grasp_arm,
                      camera=None if args.camera == "none" else args.camera, serial=args.serial, cell_path=args.cell,
                      dry_run=args.dry_run, out=args.out, duration=args.duration, overrides=args.overrides,
                      mapper=args.mapper, figures=not args.no_figures,
                      **{"warmup": not getattr(args, "no_warmup", False), **test_hooks})
    if args.dry_run:
        print(f"harvest_qp dry run (nothing moved): camera arm {args.camera_arm}, grasping arm {args.grasp_arm}")
        for key, value in result.items():
            print(f"  {key:<34} {value}")
        return 0
    print(f"harvest_qp paper episode on the UR5e cell ({args.config.name}, {result['mapper']})")
    for key in ("success", "episode_status", "stop_reason", "phase_reached", "abort_reason", "t_bimanual_start",
                "t_precut", "visible_stem_points_start", "visible_stem_points_end", "final_position_error",
                "final_alignment_deg", "force_mean_last_1s", "force_max", "qp_failures", "out_dir"):
        value = result.get(key)
        print(f"  {key:<34} {f'{value:.4g}' if isinstance(value, float) else value}")
    if not result["success"]:
        print(f"  failed criteria: {', '.join(k for k, ok in result['criteria'].items() if not ok)}")
    return 0 if result["success"] else 1


def add_calibrate_parser(sub) -> None:
    """``harvest-qp calibrate board|capture|solve``."""
    calibrate = sub.add_parser("calibrate", help="camera hand-eye and base-to-base calibration from ChArUco board "
                               "views (docs/real_robots.md)")
    steps = calibrate.add_subparsers(dest="step", required=True)
    board = steps.add_parser("board", help="write the ChArUco board to print")
    board.add_argument("--out", type=Path, default=Path("charuco_board.png"))
    capture = steps.add_parser("capture", help="record views: joints of both arms and a colour image per Enter "
                               "(move the arms on the pendant or in freedrive; nothing is commanded)")
    capture.add_argument("folder", type=Path, help="views folder (views.yaml and the images)")
    capture.add_argument("--kind", choices=("hand_eye", "bases"), required=True,
                         help="hand_eye: board fixed, camera arm moves; bases: board on the grasping flange")
    capture.add_argument("--camera-arm", metavar="IP", required=True)
    capture.add_argument("--grasp-arm", metavar="IP", required=True)
    capture.add_argument("--serial", default=None)
    capture.add_argument("--cell", type=Path, default=None)
    solve = steps.add_parser("solve", help="detect the board in every view and write the calibration YAML")
    solve.add_argument("folder", type=Path, help="views folder (views.yaml and the images)")
    solve.add_argument("--out", type=Path, required=True, help="calibration file to write (the cell file names it)")


def calibrate_main(args: argparse.Namespace) -> int:
    from harvest_qp.real import calibration as cal

    if args.step == "board":
        import cv2

        board = cal.Board()
        cv2.imwrite(str(args.out), board.image())
        print(f"wrote {args.out}: print it flat at {1e3 * board.square:g} mm squares "
              f"({board.squares[0]}x{board.squares[1]}, {board.dictionary}); measure a square after printing")
        return 0
    if args.step == "solve":
        calibration = cal.calibrate_folder(args.folder)
        cal.save_calibration(args.out, calibration)
        print(f"wrote {args.out}")
        for key, value in calibration.info.items():
            if key != "board_in_grasp_flange":
                print(f"  {key:<28} {value}")
        return 0
    return _capture(args)


def _capture(args: argparse.Namespace) -> int:
    """Record views until the operator types q (reads only: no control interface is opened)."""
    import cv2

    from harvest_qp.real.calibration import Board
    from harvest_qp.real.cell import load_cell
    from harvest_qp.real.realsense import open_pipeline
    from harvest_qp.real.ur_rtde_robot import RTDE_PORT, _probe, _ur_rtde

    cell = load_cell(args.cell)
    rtde = _ur_rtde()
    receivers = []
    for role, host in (("camera arm", args.camera_arm), ("grasping arm", args.grasp_arm)):
        _probe(host, role, 2.0)
        try:
            receivers.append(rtde.RTDEReceiveInterface(host))
        except RuntimeError as err:
            raise HarvestQPError(f"cannot read the {role} at {host}:{RTDE_PORT}: {err}") from None
    pipeline, _ = open_pipeline(cell.camera, args.serial)
    folder = args.folder
    folder.mkdir(parents=True, exist_ok=True)
    index = folder / "views.yaml"
    data = yaml.safe_load(index.read_text()) if index.exists() else None
    try:
        frames = pipeline.wait_for_frames()
        intr = frames.get_color_frame().profile.as_video_stream_profile().get_intrinsics()
        if data is None:
            K = [[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]]
            data = {"board": Board().as_dict(), "intrinsics": {"K": K, "dist": list(intr.coeffs)}, "views": []}
        while True:
            answer = input(f"[{args.kind}] move the arm, then Enter to record a view (q + Enter to finish): ")
            if answer.strip().lower() == "q":
                break
            frames = pipeline.wait_for_frames()
            image = np.asanyarray(frames.get_color_frame().get_data())
            q = [float(x) for r in receivers for x in r.getActualQ()]
            name = f"{args.kind}_{time.strftime('%Y%m%d-%H%M%S')}_{len(data['views']):03d}.png"
            cv2.imwrite(str(folder / name), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            data["views"].append({"image": name, "kind": args.kind, "q": q})
            index.write_text(yaml.safe_dump(data, sort_keys=False))
            print(f"  view {len(data['views'])}: {name}", file=sys.stderr)
    finally:
        pipeline.stop()
        for r in receivers:
            r.disconnect()
    return 0
