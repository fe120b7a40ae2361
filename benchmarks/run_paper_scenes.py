"""The paper episode on the default scene and seeds 1-5, with the QP and the paper's pseudo-inverse.

Each episode goes through the CLI's own code path (``harvest_qp.cli.run_paper``, what
``harvest-qp run`` executes) and writes its folder under ``--out`` (default ``runs/``). Prints
one markdown table (the README's) and, last, one JSON object with every episode's metrics.

Usage::

    python benchmarks/run_paper_scenes.py [--seeds 0 1 2 3 4 5] [--mappers qp pinv] [--jobs 2]
        [--set section.key=value ...] [--no-figures]
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

_REPO = Path(__file__).resolve().parents[1]
if str(_REPO) not in sys.path:
    sys.path.insert(0, str(_REPO))

from harvest_qp.cli import run_paper  # noqa: E402
from harvest_qp.perception import grasp_target  # noqa: E402
from harvest_qp.robot.paths import tasks_dir  # noqa: E402

COLUMNS = (
    ("seed", "seed"), ("mapper", "mapper"), ("success", "success"), ("phase_reached", "phase"),
    ("t_bimanual_start", "switch [s]"), ("t_precut", "pre-cut [s]"), ("final_distance_to_roi_center", "d/r"),
    ("final_theta_deg", "theta [deg]"),
    ("visible_stem_points_start", "stem pts start"), ("visible_stem_points_switch", "switch"),
    ("visible_stem_points_end", "end"), ("final_position_error", "e_p [mm]"), ("final_alignment_deg", "e_o [deg]"),
    ("final_cutter_stem_angle_deg", "cutter [deg]"), ("force_mean_last_1s", "f last 1 s [N]"),
    ("force_max", "f max [N]"), ("true_tension_mean_last_1s", "true T last 1 s [N]"),
    ("min_collision_distance", "min dist [mm]"),
    ("min_vine_distance", "min vine dist [mm]"), ("contacts", "contacts"),
    ("stem_torn", "torn"), ("max_joint_limit_violation", "joint lim viol [rad]"),
    ("peak_joint_speed", "peak qdot [rad/s]"), ("qp_failures", "QP fail"), ("p_gd_choice", "p_gd"),
    ("target_angle_off_stem_deg", "p_gd off stem [deg]"), ("abort_reason", "abort"),
)

#: Short names of the grasp target's tiers (``harvest_qp.perception.grasp_target``) for the table.
_CHOICES = {
    grasp_target.CHOICE_PAPER: "eq:attr_point", grasp_target.CHOICE_CONE: "cone",
    grasp_target.CHOICE_CONE_CLEAR: "cone, swing clear", grasp_target.CHOICE_ALONG_STEM: "along the stem",
    grasp_target.CHOICE_NO_TARGET: "none",
}


def _one(args: tuple) -> dict:
    config, seed, mapper, out, overrides, figures = args
    folder = Path(out) / f"paper-{seed}{'-pinv' if mapper == 'pinv' else ''}"
    try:
        return run_paper(config, seed=seed, mapper=mapper, out=folder, overrides=overrides, figures=figures)
    except Exception as err:  # keep the table going; report the failure in it
        return {"seed": seed, "mapper": mapper, "success": False, "abort_reason": f"{type(err).__name__}: {err}"}


def _cell(key: str, value) -> str:
    if value is None:
        return "-"
    if key == "p_gd_choice":
        return _CHOICES.get(value, str(value))
    if key == "final_distance_to_roi_center":
        return f"{value / 0.35:.3f}"
    if key in ("final_position_error", "min_collision_distance", "min_vine_distance"):
        return f"{1e3 * value:.1f}"
    if isinstance(value, float):
        return f"{value:.3g}"
    return str(value)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=tasks_dir() / "paper.yaml")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5])
    parser.add_argument("--mappers", nargs="+", default=["qp", "pinv"], choices=["qp", "pinv"])
    parser.add_argument("--out", type=Path, default=Path("runs"))
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--no-figures", action="store_true")
    args = parser.parse_args(argv)
    figures = not args.no_figures
    work = [(args.config, s, m, args.out, args.overrides, figures) for m in args.mappers for s in args.seeds]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            results = list(pool.map(_one, work))
    else:
        results = [_one(w) for w in work]
    print("| " + " | ".join(title for _, title in COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for r in results:
        print("| " + " | ".join(_cell(k, r.get(k)) for k, _ in COLUMNS) + " |")
    print(json.dumps(results, default=str))


if __name__ == "__main__":
    main()
