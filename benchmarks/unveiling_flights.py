"""Closed-loop unveiling measurements with a free-flying camera (not a timed benchmark).

The camera is integrated kinematically under V_cr + V_cu (``tests/references/flying_camera.py``);
the oracle is the renderer's ground-truth stem labels (visible stem points per frame).

Tables (``--table``):

* ``partial``: synthetic scene, one leaf over the stem's lower half, approach from 0.5 m for
  8 s: V_cr alone, the bounded law (two bounds), the literal law, the literal law with the
  pivot drop only, saturation only.  ``--width/--height`` pick the resolution.
* ``lab-partial``: the lab's default scene and seeds 1, 3, 4, 5 (the leaf hides 61-70 % of the
  stem from the approach), 20 s from home: V_cr alone and two bounds; ``--shift`` [m] moves the
  occluding leaf along its long axis (default 0).
* ``magnitude``: one frame at 0.5 m and 0.35 m at 141x80, 283x160, 848x480: |w| of the literal
  law, with the 3 cm pivot drop, and the bounded law, and the bounded direction's agreement.
* ``hidden``: the MuJoCo lab's default scene and seeds 1-5 with ``occluder_coverage = 1``
  (stem hidden along the whole straight approach; seed 2 is drawn so anyway), 15 s from the
  camera's home pose, ROI on the grape: V_cr alone, the paper's (bounded) potential on the
  predicted points with d_a = 1 cm and 5 cm, and the extension.
* ``prediction``: the same hidden scenes, the extension with the predicted segment tilted 20 deg
  (about x_g, z_g) or 30 % short / long.

Usage::

    python benchmarks/unveiling_flights.py --table hidden
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from harvest_qp.perception.synthetic import render_scene  # noqa: E402
from harvest_qp.perception.unveiling import ray_obstacle_pairs  # noqa: E402
from harvest_qp.references import Unveiling, predicted_stem_points  # noqa: E402
from harvest_qp.references.unveiling import bounded_unveiling_velocity, unveiling_velocity  # noqa: E402
from harvest_qp.sim.scene import VineSceneParams  # noqa: E402
from tests.references.flying_camera import LabCamera, fly, fly_lab, hidden_stem_scene  # noqa: E402


class PaperOnPredicted(Unveiling):
    """The paper's (bounded) potential applied to the predicted points as if they were seen."""

    def observe(self, camera_position, stem_points, obstacle_points, *, predicted_stem_points=None, **kwargs):
        if len(stem_points) < self.min_stem_points and predicted_stem_points is not None:
            stem_points = predicted_stem_points
        super().observe(camera_position, stem_points, obstacle_points)


def partial(width: int, height: int) -> None:
    scene = hidden_stem_scene(leaf_shift=(0.0, -0.04))
    mid = 0.5 * (scene.stem_base + scene.stem_end)
    start = mid + 0.5 * np.array([1.0, 0.0, 0.1]) / np.linalg.norm([1.0, 0.0, 0.1])
    eye = mid + 0.35 * np.array([1.0, 0.0, 0.1]) / np.linalg.norm([1.0, 0.0, 0.1])
    unoccluded = render_scene(hidden_stem_scene(leaf_offset=-10.0), eye, width=width, height=height).stem_mask.sum()
    print(f"{width}x{height}: unoccluded stem points at 0.35 m: {unoccluded}")
    variants = {
        "V_cr alone": None,
        "bounded 0.2 rad/s, 0.1 m/s": Unveiling(),
        "bounded 0.1 rad/s, 0.05 m/s": Unveiling(max_angular=0.1, max_linear=0.05),
        "literal (+ low-pass)": Unveiling(min_pivot=0.0, max_angular=1e9, max_linear=1e9),
        "pivot drop only (+ low-pass)": Unveiling(max_angular=1e9, max_linear=1e9),
        "saturation only (+ low-pass)": Unveiling(min_pivot=0.0),
    }
    print("| variant | stem points at 0/2/4/6/8 s | mean last 2 s | max |w| [rad/s] | end d [m] | end theta [deg] |")
    print("|---|---|---|---|---|---|")
    for name, law in variants.items():
        flight = fly(scene, start, mid, unveiling=law, duration=8.0, width=width, height=height)
        n = np.array(flight.stem_points)
        print(
            f"| {name} | {n[0]}/{n[20]}/{n[40]}/{n[60]}/{n[-1]} | {n[-20:].mean():.0f} | {flight.max_angular:.3g} | "
            f"{np.linalg.norm(flight.positions[-1] - mid):.3f} | {np.degrees(flight.thetas[-1]):.2f} |",
            flush=True,
        )


def lab_partial(shift: float) -> None:
    print("| scene | variant | stem points at 2/5/8/12/16 s | last 5 s | max |w| [rad/s] | end d/r | end theta [deg] |")
    print("|---|---|---|---|---|---|---|")
    for seed in (None, 1, 3, 4, 5):
        lab = LabCamera(None if seed is None else VineSceneParams.sample(seed))
        if shift:
            lab.shift_occluder(shift)
        gripper = lab.scene.gripper_home
        roi = gripper[:3, 3] + 0.04 * gripper[:3, 1]
        laws = {
            "V_cr alone": None,
            "bounded 0.2 rad/s, 0.1 m/s": Unveiling(),
            "bounded 0.1 rad/s, 0.05 m/s": Unveiling(max_angular=0.1, max_linear=0.05),
        }
        for name, law in laws.items():
            flight = fly_lab(lab, unveiling=law, duration=20.0)
            n = np.array(flight.stem_points)
            print(
                f"| {'default' if seed is None else seed} | {name} | "
                f"{'/'.join(str(n[int(t * 10)]) for t in (2, 5, 8, 12, 16))} | {n[-50:].mean():.0f} | "
                f"{flight.max_angular:.3g} | {np.linalg.norm(flight.positions[-1] - roi) / 0.35:.2f} | "
                f"{np.degrees(flight.thetas[-1]):.2f} |",
                flush=True,
            )


def magnitude() -> None:
    scene = hidden_stem_scene(leaf_shift=(0.0, -0.04))
    mid = 0.5 * (scene.stem_base + scene.stem_end)
    print("| distance | resolution | n_S | pairs | literal |w| | pivots >= 3 cm |w| | bounded |w|, |v| |")
    print("|---|---|---|---|---|---|---|")
    for distance in (0.5, 0.35):
        eye = mid + distance * np.array([1.0, 0.0, 0.1]) / np.linalg.norm([1.0, 0.0, 0.1])
        directions = {}
        for width, height in ((141, 80), (283, 160), (848, 480)):
            cloud = render_scene(scene, eye, width=width, height=height)
            stem, obstacles = cloud.points[cloud.stem_mask], cloud.points[~cloud.stem_mask]
            pairs = ray_obstacle_pairs(stem, obstacles, eye)
            literal = unveiling_velocity(pairs, k_c=0.00025)
            dropped = unveiling_velocity(pairs, k_c=0.00025, min_pivot=0.03)
            bounded = bounded_unveiling_velocity(pairs)
            directions[width] = bounded / np.linalg.norm(bounded)
            print(
                f"| {distance} m | {width}x{height} | {len(stem)} | {len(pairs)} | {np.linalg.norm(literal[3:]):.3g} | "
                f"{np.linalg.norm(dropped[3:]):.3g} | "
                f"{np.linalg.norm(bounded[3:]):.3g}, {np.linalg.norm(bounded[:3]):.3g} |",
                flush=True,
            )
        print(
            f"bounded direction at {distance} m: cos(283x160, 848x480) = {directions[283] @ directions[848]:.4f}, "
            f"cos(141x80, 848x480) = {directions[141] @ directions[848]:.4f}"
        )


def _first(flight, threshold=10):
    n = np.array(flight.stem_points)
    hits = np.flatnonzero(n >= threshold)
    return None if hits.size == 0 else flight.times[hits[0]]


def _hidden_params(seed):
    params = VineSceneParams() if seed is None else VineSceneParams.sample(seed)
    return dataclasses.replace(params, occluder_coverage=1.0)


def hidden() -> None:
    print("| scene | law | first >= 10 stem points [s] | stem points at 5/10/15 s | end d/r | end theta [deg] |")
    print("|---|---|---|---|---|---|")
    for seed in (None, 1, 2, 3, 4, 5):
        lab = LabCamera(_hidden_params(seed))
        gripper = lab.scene.gripper_home
        predicted = predicted_stem_points(gripper)
        roi = gripper[:3, 3] + 0.04 * gripper[:3, 1]
        laws = {
            "V_cr + paper V_cu (n_S = 0: zero)": Unveiling(),
            "paper potential on predicted, d_a 1 cm": PaperOnPredicted(),
            "paper potential on predicted, d_a 5 cm": PaperOnPredicted(d_a=0.05),
            "extension (next-best-view)": Unveiling(),
        }
        for name, law in laws.items():
            given = None if name.startswith("V_cr") else predicted
            flight = fly_lab(lab, unveiling=law, duration=15.0, predicted=given)
            n = np.array(flight.stem_points)
            first = _first(flight)
            print(
                f"| {'default' if seed is None else seed} | {name} | {'never' if first is None else f'{first:.1f}'} | "
                f"{n[50]}/{n[100]}/{n[-1]} | {np.linalg.norm(flight.positions[-1] - roi) / 0.35:.2f} | "
                f"{np.degrees(flight.thetas[-1]):.2f} |",
                flush=True,
            )


def _rotation(axis, angle):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * skew + (1 - np.cos(angle)) * skew @ skew


def prediction() -> None:
    print("| scene | 20 deg about x_g | 20 deg about z_g | 30 % short | 30 % long |")
    print("|---|---|---|---|---|")
    for seed in (None, 1, 2, 3, 4, 5):
        lab = LabCamera(_hidden_params(seed))
        gripper = lab.scene.gripper_home
        cells = []
        for axis, length in ((0, 0.06), (2, 0.06), (None, 0.042), (None, 0.078)):
            pose = gripper.copy()
            if axis is not None:
                pose[:3, :3] = _rotation(gripper[:3, axis], np.radians(20.0)) @ gripper[:3, :3]
            flight = fly_lab(
                lab, unveiling=Unveiling(), duration=15.0, predicted=predicted_stem_points(pose, length=length)
            )
            first = _first(flight)
            n = np.array(flight.stem_points)
            lost = None if first is None else int(np.sum(n[np.flatnonzero(n >= 10)[0] :] == 0))
            cells.append(f"{'never' if first is None else f'{first:.1f} s'}, end {n[-1]}, lost {lost}")
        print(f"| {'default' if seed is None else seed} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--table", choices=("partial", "lab-partial", "magnitude", "hidden", "prediction"), required=True
    )
    parser.add_argument("--shift", type=float, default=0.0)
    parser.add_argument("--width", type=int, default=283)
    parser.add_argument("--height", type=int, default=160)
    args = parser.parse_args()
    start = time.perf_counter()
    {"partial": lambda: partial(args.width, args.height), "lab-partial": lambda: lab_partial(args.shift),
     "magnitude": magnitude, "hidden": hidden, "prediction": prediction}[args.table]()  # fmt: skip
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
