"""Cost of the obstacle map: update per camera frame, capsule query, and the QP tick with its rows.

Frames: the default lab scene (``harvest_qp.sim``) seen by its ray-cast camera from
viewpoints around the region of interest, at 283x160 (the paper's D415 848x480
downsampled by 3) and at 848x480. The map update is timed on those frames in turn, on a
map that already holds the earlier ones (the steady state of an episode).

The QP tick: ``TaskController.step`` on the dual UR5e (gripper twist towards the vine,
camera twist, posture, damping, joint limits, ``CollisionAvoidance.dual_ur5e``) in closed
loop on the kinematic model, without the map and with it (``MapCollisionFeed.update()``
then ``step``), in interleaved rounds (the host's speed drifts), median of round medians.

The feed alone (``MapCollisionFeed.update`` at a fixed pose: between map changes it reuses
its candidate cells) and the full query (``ObstacleMap._query``, the block search) are
timed on this thread's CPU time (``_cpu_us`` keys) and on the wall clock.

Usage: ``python benchmarks/bench_map.py [--frames 12] [--ticks 400] [--rounds 5] [--clear-rays 6000,3000]``
(``--clear-rays``: also time the update with those clearing-ray budgets, each on a fresh map).
The last line printed is one JSON object with the medians (update [ms], query and ticks [us]).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from harvest_qp import Configuration, TaskController  # noqa: E402
from harvest_qp.limits import CollisionAvoidance  # noqa: E402
from harvest_qp.perception.map_feed import MapCollisionFeed  # noqa: E402
from harvest_qp.perception.obstacle_map import ExclusionRegion, ObstacleMap  # noqa: E402
from harvest_qp.robot import description as desc  # noqa: E402
from harvest_qp.sim import CameraConfig, SimRobot, make_camera  # noqa: E402
from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask  # noqa: E402


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def held_cluster(robot: SimRobot) -> ExclusionRegion:
    """The cluster the gripper holds: a capsule along the gripper's y axis (down the cluster)."""
    G = robot.site_pose("gripper")
    y = G[:3, 1]
    p = G[:3, 3]
    top, bottom = p - 0.03 * y, p + (robot.scene.params.cluster_length + 0.05) * y
    return ExclusionRegion(tuple(top), tuple(bottom), robot.scene.params.cluster_radius + 0.02)


def lab_frames(robot: SimRobot, downsample: int, n: int) -> list:
    scene = robot.scene
    cam = make_camera(robot.model, CameraConfig(downsample=downsample), geom_labels=scene.geom_labels,
                      exclude_body=scene.ids["cam_tool"])  # fmt: skip
    target = scene.stem_base + np.array([0.05, 0.0, -0.08])
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(n):
        azimuth = np.pi + rng.uniform(-0.9, 0.9)  # from the robot's side, as the camera arm sees it
        elevation = rng.uniform(-0.2, 0.5)
        eye = target + rng.uniform(0.3, 0.6) * np.array(
            [np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)]
        )
        frames.append(cam.capture(robot.data, look_at(eye, target + rng.normal(0, 0.03, 3)), 0.0))
    return frames


def time_updates(frames: list, exclude, repeats: int, clear_rays: int | None = None) -> tuple[float, float, dict]:
    m = ObstacleMap() if clear_rays is None else ObstacleMap(clear_rays=clear_rays)
    m.update(frames[0], exclude=exclude)  # compile and warm up
    wall, cpu, rays = [], [], []
    for _ in range(repeats):
        for f in frames:
            t0, c0 = time.perf_counter(), time.process_time()
            stats = m.update(f, exclude=exclude)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            rays.append(stats.rays)
    # Median over the frames (the last frame's count alone can be 0: a view with no point in the grid).
    info = {"points": int(np.median([len(f) for f in frames])), "rays": int(np.median(rays)),
            "occupied": m.num_occupied}
    return 1e3 * float(np.median(wall)), 1e3 * float(np.median(cpu)), info


class Tick:
    """The QP tick on the dual UR5e, optionally fed by the map before each step."""

    def __init__(self, obstacle_map: ObstacleMap | None) -> None:
        self.q0 = desc.HOME_Q.copy()
        self.config = Configuration.dual_ur5e(self.q0)
        self.gripper = FrameTwistTask("gripper", weight=1.0)
        self.camera = FrameTwistTask("camera", weight=np.array([1, 1, 1, 1, 1, 0.0]), weight_frame="local")
        self.limit = CollisionAvoidance.dual_ur5e(self.config)
        tasks = [self.camera, self.gripper, PostureTask(self.q0, weight=1e-3), DampingTask(self.config.nv)]
        self.controller = TaskController(self.config, tasks, [self.limit], dt=0.002)
        self.feed = MapCollisionFeed(self.limit, obstacle_map, self.config) if obstacle_map is not None else None
        self.reset()

    def reset(self) -> None:
        self.feed_times: list[float] = []
        self.q = self.q0.copy()
        self.t = 0.0
        self.controller.reset(self.q)

    def step(self) -> None:
        # Gripper towards the vine and back, camera sideways: the arms sweep through the map.
        s = np.sin(2 * np.pi * 0.25 * self.t)
        self.gripper.set_reference(np.array([0.08 * s, 0.03, 0.0, 0.0, 0.0, 0.0]))
        self.camera.set_reference(np.array([0.05 * s, -0.05, 0.02, 0.0, 0.1 * s, 0.0]))
        if self.feed is not None:
            t0 = time.perf_counter()
            self.feed.update(self.q)
            self.feed_times.append(time.perf_counter() - t0)
        result = self.controller.step(self.q)
        self.q = self.q + result.qdot * 0.002
        self.t += 0.002


def time_ticks(ticks: dict[str, Tick], n: int, rounds: int) -> tuple[dict[str, float], dict]:
    medians: dict[str, list[float]] = {k: [] for k in ticks}
    extra = {"rows_from_map_max": 0, "cells_fed_max": 0, "fallbacks": 0}
    feed_medians: list[float] = []
    for _ in range(rounds):
        for name, tick in ticks.items():
            tick.reset()
            times = []
            for _ in range(n):
                t0 = time.perf_counter()
                tick.step()
                times.append(time.perf_counter() - t0)
                if tick.feed is not None:
                    names = tick.limit.pair_names()
                    rows = sum(names[k][1].startswith("cell[") for k in tick.limit.active_pairs)
                    extra["rows_from_map_max"] = max(extra["rows_from_map_max"], rows)
                    extra["cells_fed_max"] = max(extra["cells_fed_max"], int(tick.feed.cells.shape[0]))
            extra["fallbacks"] += int(not tick.controller.step(tick.q).ok)
            medians[name].append(float(np.median(times)))
            if tick.feed is not None:
                feed_medians.append(float(np.median(tick.feed_times)))
    extra["feed_in_tick_us"] = round(1e6 * float(np.median(feed_medians)), 1)
    return {k: 1e6 * float(np.median(v)) for k, v in medians.items()}, extra


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12, help="lab frames per resolution")
    parser.add_argument("--ticks", type=int, default=400, help="QP ticks per round and variant")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--clear-rays", default="", help="comma-separated clearing-ray budgets to time besides the "
                        "default (ObstacleMap's clear_rays), e.g. 6000,3000")
    args = parser.parse_args(argv)
    budgets = [int(x) for x in args.clear_rays.split(",") if x.strip()]

    robot = SimRobot(camera=None)
    exclude = [held_cluster(robot)]
    out: dict[str, float | int] = {}
    for ds, label in ((3, "283x160"), (1, "848x480")):
        frames = lab_frames(robot, ds, args.frames)
        wall, cpu, info = time_updates(frames, exclude, repeats=3 if ds == 3 else 2)
        print(f"map update {label}: median {wall:.2f} ms wall, {cpu:.2f} ms CPU "
              f"({info['points']} points/frame, {info['rays']} clearing rays, {info['occupied']} occupied cells)")
        out[f"update_ms_{label}"] = round(wall, 3)
        out[f"update_cpu_ms_{label}"] = round(cpu, 3)
        for n in budgets:  # a fresh map per budget, same frames (not interleaved: compare in one run only)
            wall, cpu, info = time_updates(frames, exclude, repeats=3 if ds == 3 else 2, clear_rays=n)
            print(f"  clear_rays={n}: median {wall:.2f} ms wall, {cpu:.2f} ms CPU ({info['rays']} clearing rays)")
            out[f"update_cpu_ms_{label}_clear_rays_{n}"] = round(cpu, 3)

    m = ObstacleMap()
    for f in lab_frames(robot, 3, 20):
        m.update(f, exclude=exclude)
    with_map = Tick(m)
    # Query alone: the 15 arm capsules at the starting pose, with the feed's settings.
    feed = with_map.feed
    w0, w1 = feed.capsule_world()
    for _ in range(200):
        m.closest_cells(w0, w1, feed.radii, max_distance=0.11, per_capsule=4, min_separation=0.03)
    def timed(call, n=2000):
        wall, cpu = [], []
        for _ in range(n):
            t0, c0 = time.perf_counter(), time.thread_time()
            call()
            cpu.append(time.thread_time() - c0)
            wall.append(time.perf_counter() - t0)
        return round(1e6 * float(np.median(wall)), 1), round(1e6 * float(np.median(cpu)), 1)

    out["feed_update_us"], out["feed_update_cpu_us"] = timed(feed.update)
    out["query_us_15_capsules"], out["query_cpu_us_15_capsules"] = timed(
        lambda: m.closest_cells(w0, w1, feed.radii, max_distance=0.11, per_capsule=4, min_separation=0.03)
    )
    print(f"query, 15 capsules: {out['query_us_15_capsules']} us ({out['query_cpu_us_15_capsules']} us CPU); "
          f"MapCollisionFeed.update: {out['feed_update_us']} us ({out['feed_update_cpu_us']} us CPU)"
          f" ({m.num_occupied} occupied cells)")
    ticks, extra = time_ticks({"without_map": Tick(None), "with_map": with_map}, args.ticks, args.rounds)
    out["tick_us_without_map"] = round(ticks["without_map"], 1)
    out["tick_us_with_map"] = round(ticks["with_map"], 1)
    out.update(extra)
    print(f"QP tick (TaskController.step): {out['tick_us_without_map']} us without the map, "
          f"{out['tick_us_with_map']} us with it (of which the feed {extra['feed_in_tick_us']} us; up to "
          f"{extra['rows_from_map_max']} rows from {extra['cells_fed_max']} cells)")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
