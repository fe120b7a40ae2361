"""Cost of one meshcat viewer frame, and what a live viewer does to a 2 ms control loop.

Timed (medians over ``--frames`` frames, no browser attached; a browser adds the server's
websocket writes, in the server process):

* ``frame_ms``: one :meth:`MeshcatViewer.draw` of a moving robot with every marker
  (ROI, p_r, p_sb, p_gd, two stem segments, V_c, V_g, force arrows, closest pair, frustum):
  the kinematics, packing and one batched round trip; the text panel and cloud unchanged.
* ``frame_text_ms``: the same with a new text panel (a PNG; sent at most 10 times a second).
* ``frame_cloud_ms``: the same with a new ``--cloud-points`` cloud (sent when a camera frame arrives, 30 Hz).
* the same commands as ``frame_ms`` sent pipelined without the batch command, and one
  blocking round trip per command as meshcat's ``Visualizer`` does.
* ``loop``: a 2 ms-period loop doing ``--work-us`` of numpy work per tick, alone, while a
  :class:`LiveViewer` observes every tick and draws at 30 Hz in a worker thread, and while the
  default :class:`LiveViewer` draws in a child process: median and 99th percentile tick work
  time and the share of ticks over 2 ms.

Usage::

    python benchmarks/bench_viewer.py [--frames 300] [--cloud-points 15000]

The last line printed is one JSON object with every figure.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import zmq  # noqa: E402

from harvest_qp.robot.description import HOME_Q  # noqa: E402
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM  # noqa: E402
from harvest_qp.runtime.runner import Observation  # noqa: E402
from harvest_qp.viewer import LiveViewer, MeshcatViewer, ViewerFrame  # noqa: E402
from harvest_qp.viewer.commands import Batch  # noqa: E402
from harvest_qp.viewer.replay import free_port  # noqa: E402
from harvest_qp.viewer.server import Connection  # noqa: E402


def full_frame(k: int, rng: np.random.Generator, **extra) -> ViewerFrame:
    q = np.array(HOME_Q) + 0.2 * np.sin(0.01 * k + np.arange(12))
    p = np.array([0.5, -0.12, 1.23])
    return ViewerFrame(
        time=0.002 * k, q=q, force=np.array([0.0, 0.0, -3.0 - 0.01 * k]), phase="approach", theta=0.3,
        stem_points=120, roi_center=p, roi_radius=0.15, p_r=p + 0.05, p_sb=p, p_gd=p - 0.06,
        stem_segments=np.array([[p - 0.06, p - 0.03], [p - 0.03, p]]), v_c=np.array([0.1, 0.0, 0.02]),
        v_g=np.array([0.0, 0.0, 0.05]), closest_pair=np.array([[0.3, 0.2, 1.0], [0.35, 0.1, 1.1]]),
        closest_distance=0.11, camera_pose=np.eye(4), **extra,
    )  # fmt: skip


def median_ms(samples: list[float]) -> float:
    return 1e3 * float(np.median(samples))


def time_frames(viewer: MeshcatViewer, frames: list[ViewerFrame], wall_time=None) -> list[float]:
    out = []
    for frame in frames:
        t0 = time.perf_counter()
        viewer.draw(frame, wall_time=wall_time)
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--cloud-points", type=int, default=15000)
    parser.add_argument("--work-us", type=float, default=300.0)
    parser.add_argument("--loop-seconds", type=float, default=3.0)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    results: dict[str, float] = {}

    viewer = MeshcatViewer(None, port=free_port(), verbose=False)
    try:
        n = args.frames
        time_frames(viewer, [full_frame(k, rng) for k in range(20)], wall_time=0.0)  # warm-up
        # text unchanged (wall_time fixed: the panel's rate limit holds it), cloud absent
        samples = time_frames(viewer, [full_frame(k, rng) for k in range(n)], wall_time=0.0)
        results["frame_ms"] = median_ms(samples)
        b = Batch()
        viewer.frame_commands(b, full_frame(n + 1, rng), wall_time=0.0)
        results["frame_commands"] = len(b.messages)

        samples = []
        for k in range(n // 3):
            frame = full_frame(k, rng, extra_text=(f"frame {k}",))
            t0 = time.perf_counter()
            viewer.draw(frame, wall_time=None)
            samples.append(time.perf_counter() - t0)
        results["frame_text_ms"] = median_ms(samples)

        m = args.cloud_points
        labels = rng.choice([STEM, OBSTACLE, ROBOT], size=m, p=[0.05, 0.85, 0.10]).astype(np.int8)
        samples = []
        for k in range(n // 3):
            pts = rng.normal(0.0, 0.2, (m, 3)) + [0.6, 0.0, 1.2]
            frame = full_frame(k, rng, cloud_points=pts, cloud_labels=labels, cloud_key=k)
            t0 = time.perf_counter()
            viewer.draw(frame, wall_time=0.0)
            samples.append(time.perf_counter() - t0)
        results["frame_cloud_ms"] = median_ms(samples)
        results["cloud_points"] = m

        # the same commands pipelined without the batch command, then one round trip each
        messages = []
        for k in range(n):
            b = Batch()
            viewer.frame_commands(b, full_frame(k + 1000, rng), wall_time=0.0)
            messages.append(b.messages)
        piped = Connection(viewer.server.zmq_url, batch=False)
        samples = []
        for batch in messages:
            t0 = time.perf_counter()
            piped.send(batch)
            samples.append(time.perf_counter() - t0)
        results["commands_pipelined_ms"] = median_ms(samples)
        piped.close()
        context = zmq.Context()
        req = context.socket(zmq.REQ)
        req.connect(viewer.server.zmq_url)
        samples = []
        for batch in messages[: n // 3]:
            t0 = time.perf_counter()
            for command, path, data in batch:
                req.send_multipart([command, path, data])
                req.recv()
            samples.append(time.perf_counter() - t0)
        results["commands_one_round_trip_each_ms"] = median_ms(samples)
        req.close(linger=0)
        context.term()

        # a 2 ms control loop, alone and with a live viewer drawing at 30 Hz
        work = rng.normal(size=(40, 40))

        def loop(live: LiveViewer | None) -> list[float]:
            ticks = int(args.loop_seconds / 0.002)
            durations = []
            next_tick = time.perf_counter()
            for k in range(ticks):
                t0 = time.perf_counter()
                while (time.perf_counter() - t0) * 1e6 < args.work_us:
                    np.linalg.solve(work + np.eye(40), work[0])  # QP-sized linear algebra
                if live is not None:
                    q = np.array(HOME_Q) + 0.2 * np.sin(0.002 * k)
                    live.observe(Observation(time=0.002 * k, q=q, qdot=np.zeros(12), force=np.zeros(3),
                                             cloud=None, new_cloud=False), {"phase": "approach"})  # fmt: skip
                durations.append(time.perf_counter() - t0)
                next_tick += 0.002
                pause = next_tick - time.perf_counter()
                if pause > 0:
                    time.sleep(pause)
            return durations

        contenders = (
            ("alone", lambda: None),
            ("live_viewer", lambda: LiveViewer(viewer, max_rate=30.0)),  # worker thread draws
            ("live_viewer_process", lambda: LiveViewer(port=free_port(), verbose=False)),  # child process draws
        )
        for name, make in contenders:
            live = make()
            durations = np.array(loop(live))
            results[f"loop_{name}_tick_median_us"] = 1e6 * float(np.median(durations))
            results[f"loop_{name}_tick_p99_us"] = 1e6 * float(np.percentile(durations, 99))
            results[f"loop_{name}_ticks_over_2ms_percent"] = 100.0 * float(np.mean(durations > 0.002))
            if live is not None:
                live.close()
                results[f"{name}_frames_drawn"] = live.frames_drawn
                results[f"{name}_draw_median_ms"] = median_ms(live.draw_times)
    finally:
        viewer.close()

    print(f"one viewer frame ({results['frame_commands']} commands, batched): {results['frame_ms']:.2f} ms median")
    print(f"  with a new text panel: {results['frame_text_ms']:.2f} ms")
    print(f"  with a new {args.cloud_points}-point cloud: {results['frame_cloud_ms']:.2f} ms")
    print(f"  same commands pipelined, no batch: {results['commands_pipelined_ms']:.2f} ms")
    print(f"  same commands, one round trip each (meshcat's Visualizer): "
          f"{results['commands_one_round_trip_each_ms']:.2f} ms")  # fmt: skip
    for name in ("alone", "live_viewer", "live_viewer_process"):
        print(f"2 ms loop, {name}: tick work median {results[f'loop_{name}_tick_median_us']:.0f} us, "
              f"p99 {results[f'loop_{name}_tick_p99_us']:.0f} us, "
              f"{results[f'loop_{name}_ticks_over_2ms_percent']:.2f} % ticks over 2 ms")  # fmt: skip
    print(json.dumps(results))


if __name__ == "__main__":
    main()
