"""Per-frame and per-tick cost of the reference laws (harvest_qp.references).

Frames come from the MuJoCo lab's ray-cast camera (default scene with the stem hidden along the
whole approach, ``VineSceneParams(occluder_coverage=1.0)``),
detached from the arm and flown kinematically under V_cr + V_cu from the camera's home pose
(``tests/references/flying_camera.py``): 10 s, frames at 10 Hz, at 283x160 (downsample 3) and
848x480 (downsample 1).  Timed on the recorded frames:

* ``Unveiling.observe`` in the "predicted" mode (one full next-best-view step, while the stem
  is hidden; with the default ``nbv_period`` only every third 30 Hz frame runs one)
  and in the "paper" mode (ray/obstacle pairs + bounded V_cu, once the stem is seen);
* per control tick: ``ReachingCentering.update`` (V_cr), ``Unveiling.update`` (V_cu's filter),
  ``StemStretching.update`` (V_g), ``GraspFeedForward`` (``eq:final_vc``), ``keep_out_velocity``,
  ``roll_reference`` and ``HoldPose.update``.

BLAS is limited to one thread as in the other benchmarks (2-core machine shared with other
jobs: medians, and they are noisy).

Usage::

    python benchmarks/bench_references.py [--repeats 5]

The last line is one JSON object.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from harvest_qp.references import (  # noqa: E402
    GraspFeedForward,
    HoldPose,
    ReachingCentering,
    StemStretching,
    Unveiling,
    keep_out_velocity,
    predicted_stem_points,
    roll_reference,
)
from harvest_qp.sim.scene import VineSceneParams  # noqa: E402
from tests.references.flying_camera import LabCamera, fly_lab  # noqa: E402


def median_ms(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def frames_along_a_flight(downsample: int):
    """(pose, stem, obstacles, mode) of every frame of a 10 s unveiling flight."""
    lab = LabCamera(VineSceneParams(occluder_coverage=1.0), downsample=downsample)
    gripper = lab.scene.gripper_home
    predicted = predicted_stem_points(gripper)
    roi = gripper[:3, 3] + 0.04 * gripper[:3, 1]
    recorder = Unveiling()
    frames = []
    original = recorder.observe

    def observe(camera, stem, obstacles, **kwargs):
        original(camera, stem, obstacles, **kwargs)
        frames.append((camera.copy(), stem, obstacles, recorder.mode))

    recorder.observe = observe
    fly_lab(lab, unveiling=recorder, duration=10.0, predicted=predicted, roi_centre=roi)
    return frames, predicted, roi


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    result: dict[str, float] = {}
    for downsample, label in ((3, "283x160"), (1, "848x480")):
        frames, predicted, roi = frames_along_a_flight(downsample)
        for mode in ("predicted", "paper"):
            chosen = [f for f in frames if f[3] == mode]
            # nbv_period=0: every call plans (the timed figure is one full step; at 30 Hz frames
            # the default nbv_period = 0.1 s plans on every third frame only).
            law = Unveiling(nbv_period=0.0)
            per_frame = []
            for camera, stem, obstacles, _ in chosen:
                per_frame.append(
                    median_ms(
                        lambda camera=camera, stem=stem, obstacles=obstacles, law=law, predicted=predicted, roi=roi: (
                            law.observe(camera, stem, obstacles, predicted_stem_points=predicted, roi_centre=roi)
                        ),
                        args.repeats,
                    )
                )
            key = f"observe_{mode}_ms_{label}"
            result[key] = float(np.median(per_frame)) if per_frame else float("nan")
            result[key.replace("_ms_", "_max_ms_")] = float(np.max(per_frame)) if per_frame else float("nan")
            sizes = [len(f[2]) for f in chosen]
            print(
                f"{label} {mode:9s}: {len(chosen)} frames, {int(np.median(sizes)) if sizes else 0} non-stem points, "
                f"observe median {result[key]:.2f} ms, max {result[key.replace('_ms_', '_max_ms_')]:.2f} ms",
                flush=True,
            )
    reaching = ReachingCentering()
    reaching.reset(roi_centre=[0.5, 0.0, 1.2])
    pose = np.eye(4)
    unveiling = Unveiling()
    stretching = StemStretching()
    stretching.set_target([0.0, 0.0, 1.0], [0.0, 0.05, 0.9])
    force = np.array([0.1, 0.2, -2.0])
    feed_forward = GraspFeedForward()
    hold = HoldPose(np.eye(4), k_hold=1.0)
    p_c, p_r, v_gt, direction = np.zeros(3), np.array([0.1, 0.0, 0.2]), np.array([0.0, 0.01, 0.0]), np.eye(3)[1]
    n = 2000
    per_tick = {
        "reaching": lambda: reaching.update(pose, 0.002),
        "unveiling": lambda: unveiling.update(0.002),
        "stretching": lambda: stretching.update(pose, force, 0.002),
        "feed_forward": lambda: feed_forward(v_gt, p_c, p_r),
        "keep_out": lambda: keep_out_velocity(p_c, p_r, min_distance=0.3, gain=2.0),
        "roll": lambda: roll_reference(pose, direction, k_roll=1.0),
        "hold": lambda: hold.update(pose),
    }
    for name, call in per_tick.items():
        result[f"tick_{name}_us"] = 1e3 * median_ms(lambda call=call: [call() for _ in range(n)], 3) / n
    print("per tick: " + ", ".join(f"{name} {result[f'tick_{name}_us']:.1f} us" for name in per_tick))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
