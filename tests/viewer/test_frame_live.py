"""Frames from episode logs and observations; the live observer never blocks the loop."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.robot.description import HOME_Q
from harvest_qp.runtime.runner import Command, Observation, run_episode
from harvest_qp.sim import CameraConfig, SimRobot, VineSceneParams
from harvest_qp.viewer import (
    LiveViewer,
    RealTimePacer,
    ViewedController,
    ViewerFrame,
    frame_from_observation,
    frames_from_log,
    load_log,
    vine_params_from_log,
)


class Hold:
    def reset(self, robot):
        pass

    def step(self, obs):
        return Command(np.zeros(12), status="ok", task_errors={"e": 0.0})


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    """A real runner log: 0.12 s of the MuJoCo scene with camera frames and their clouds."""
    robot = SimRobot(VineSceneParams(), seed=0, camera=CameraConfig(rate=30.0, downsample=6))
    path = tmp_path_factory.mktemp("run") / "episode.npz"
    result = run_episode(robot, Hold(), duration=0.12, log_clouds=True, log_path=path)
    assert result.ok, result.error
    return path


def test_frames_from_a_runner_log(episode):
    """Frames sample the runner's arrays at 1/fps and carry the latest camera frame's cloud.

    Oracle: the runner's own log arrays (t, q, frame_time, cloud_offsets rows).
    Catches: a cloud from a frame captured after the tick (looking into the future), an
    off-by-one in the cloud offsets, q from another tick.
    """
    log = load_log(episode.parent)  # a run directory works too
    frames = frames_from_log(log, fps=50.0)
    t = log["t"]
    assert len(frames) == len(np.arange(t[0], t[-1] + 1e-9, 1 / 50))
    for frame in frames:
        k = int(np.flatnonzero(np.isclose(t, frame.time))[0])
        np.testing.assert_array_equal(frame.q, log["q"][k])
        i = int(np.flatnonzero(log["frame_time"] <= frame.time + 1e-12)[-1])
        a, b = log["cloud_offsets"][i], log["cloud_offsets"][i + 1]
        np.testing.assert_array_equal(frame.cloud_points, log["cloud_points"][a:b])
        np.testing.assert_array_equal(frame.camera_pose, log["frame_camera_pose"][i])
        assert frame.stem_points == log["stem_points"][k]
        assert frame.status == "ok"
    assert vine_params_from_log(log) == VineSceneParams()


def test_richer_log_keys_are_picked_up():
    n = 5
    log = {
        "t": 0.002 * np.arange(n), "q": np.tile(HOME_Q, (n, 1)),
        "phase": np.array(["approach"] * 3 + ["grasp"] * 2), "loop/p_r": np.tile([0.5, 0.0, 1.2], (n, 1)),
        "V_c": np.tile([0.1, 0, 0, 0, 0, 0.2], (n, 1)), "theta": np.full(n, np.nan),
        "value/p_c": np.tile([0.3, 0.5, 1.1], (n, 1)),
        "meta/scene_sample_seed": np.array(7),
    }  # fmt: skip
    frames = frames_from_log(log, fps=500.0)
    assert [f.phase for f in frames] == ["approach"] * 3 + ["grasp"] * 2
    np.testing.assert_array_equal(frames[0].p_r, [0.5, 0.0, 1.2])
    np.testing.assert_array_equal(frames[0].v_c, [0.1, 0.0, 0.0])  # linear part of the twist
    np.testing.assert_array_equal(frames[0].p_c, [0.3, 0.5, 1.1])
    assert frames[0].theta is None  # NaN means "not defined at this tick"
    assert vine_params_from_log(log) == VineSceneParams.sample(7)


def test_frame_validation():
    with pytest.raises(InvalidInputError, match="ViewerFrame.q"):
        ViewerFrame(time=0.0, q=np.zeros(6))
    with pytest.raises(InvalidInputError, match="ViewerFrame.v_g"):
        ViewerFrame(time=0.0, q=HOME_Q, v_g=np.zeros(4))
    with pytest.raises(InvalidInputError, match="cloud_labels"):
        ViewerFrame(time=0.0, q=HOME_Q, cloud_points=np.zeros((3, 3)), cloud_labels=np.zeros(2))
    obs = Observation(time=0.0, q=HOME_Q, qdot=np.zeros(12), force=np.zeros(3), cloud=None, new_cloud=False)
    with pytest.raises(InvalidInputError, match="unknown viewer extras"):
        frame_from_observation(obs, {"p_x": 1})
    with pytest.raises(InvalidInputError, match="'q'"):
        frames_from_log({"t": np.zeros(2)})
    with pytest.raises(InvalidInputError, match="does not exist"):
        load_log("/nonexistent/run")


class SlowViewer:
    """Stands in for MeshcatViewer: draw() blocks until released."""

    def __init__(self, fail: bool = False):
        self.release = threading.Event()
        self.drawn: list[ViewerFrame] = []
        self.fail = fail

    def draw(self, frame, *, wall_time=None):
        if self.fail:
            raise RuntimeError("server gone")
        self.release.wait()
        self.drawn.append(frame)


def observation(k: int) -> Observation:
    return Observation(time=0.002 * k, q=np.array(HOME_Q), qdot=np.zeros(12), force=np.zeros(3), cloud=None,
                       new_cloud=False)  # fmt: skip


def test_observe_never_waits_for_drawing():
    """While the worker is stuck in draw(), observe() keeps returning; stale ticks are dropped,
    and the frame drawn next is the latest observation.

    Catches: a queue that grows or a lock held across draw() (observe would block: this
    test would hang and fail on the join timeout), drawing an old tick instead of the latest.
    """
    stub = SlowViewer()
    live = LiveViewer(stub, max_rate=1000.0)
    done = threading.Event()

    def loop():
        for k in range(2000):
            live.observe(observation(k), {"phase": f"tick {k}"})
        done.set()

    thread = threading.Thread(target=loop)
    thread.start()
    thread.join(timeout=20.0)
    assert done.is_set(), "observe() blocked while the viewer was drawing"
    stub.release.set()
    assert live.flush(10.0)
    live.close()
    assert 1 <= len(stub.drawn) <= 3
    assert stub.drawn[-1].time == pytest.approx(0.002 * 1999)
    assert stub.drawn[-1].phase == "tick 1999"


def test_draw_rate_is_limited():
    """Observing every 2 ms for 0.4 s draws at most max_rate frames per second (+1)."""
    stub = SlowViewer()
    stub.release.set()
    live = LiveViewer(stub, max_rate=20.0)
    start = time.perf_counter()
    k = 0
    while time.perf_counter() - start < 0.4:
        live.observe(observation(k))
        k += 1
        time.sleep(0.002)
    elapsed = time.perf_counter() - start
    live.close()
    assert 2 <= len(stub.drawn) <= 20.0 * elapsed + 2


def test_draw_errors_stay_in_the_viewer():
    live = LiveViewer(SlowViewer(fail=True))
    for k in range(10):
        live.observe(observation(k))
    assert live.flush(5.0) is False
    assert isinstance(live.error, RuntimeError)
    live.close()


def test_viewed_controller_observes_every_tick_and_paces():
    """The wrapper passes commands through unchanged, observes each tick and keeps real time."""

    class Recorder:
        def __init__(self):
            self.times = []

        def observe(self, obs, extras=None):
            self.times.append((obs.time, extras))

    robot = SimRobot(VineSceneParams(), seed=0, camera=None)
    recorder = Recorder()
    wrapped = ViewedController(Hold(), recorder, extras=lambda obs, cmd: {"status": cmd.status},
                               pacer=RealTimePacer())  # fmt: skip
    start = time.perf_counter()
    result = run_episode(robot, wrapped, duration=0.1)
    elapsed = time.perf_counter() - start
    assert result.ok and result.log["task_error/e"].shape == (50,)
    assert [t for t, _ in recorder.times] == pytest.approx(list(result.log["t"]))
    assert recorder.times[0][1] == {"status": "ok"}
    assert elapsed >= 0.098 - 0.002, "the pacer let the episode run faster than real time"


def test_viewed_controller_uses_viewer_extras_and_wait_for_interrupt_returns_on_sigterm():
    import os
    import signal

    from harvest_qp.viewer import wait_for_interrupt

    class WithExtras(Hold):
        def viewer_extras(self):
            return {"phase": "grasp"}

    seen = []

    class Recorder:
        def observe(self, obs, extras=None):
            seen.append(extras)

    wrapped = ViewedController(WithExtras(), Recorder())
    wrapped.step(observation(0))
    assert seen == [{"phase": "grasp"}]

    before = signal.getsignal(signal.SIGTERM)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGTERM))
    timer.start()
    start = time.perf_counter()
    wait_for_interrupt("waiting")
    assert time.perf_counter() - start < 5.0
    assert signal.getsignal(signal.SIGTERM) is before


def test_control_path_does_not_import_the_viewer():
    """The controller, runner, simulation and CLI load neither harvest_qp.viewer nor meshcat.

    Catches: an eager ``import harvest_qp.viewer`` in the control path (the CLI must import it
    only under ``--viewer meshcat`` / ``replay``).
    """
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys, harvest_qp, harvest_qp.runtime.runner, harvest_qp.task_controller, harvest_qp.sim\n"
        "import harvest_qp.cli\n"
        "bad = sorted(m for m in sys.modules if m.startswith(('harvest_qp.viewer', 'meshcat')))\n"
        "assert not bad, bad\n"
    )
    repo = Path(__file__).resolve().parents[2]
    result = subprocess.run([sys.executable, "-c", code], cwd=repo, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]


def test_thinned_cloud_log_gives_each_frame_the_latest_logged_cloud(tmp_path):
    """``log_clouds=N``: every N-th camera frame's cloud, thinned to ``cloud_max_points``; the
    replay shows the latest logged cloud captured by the tick, never a later one.

    Oracle: the frame indices hand-computed from ``frame_time`` and N.
    Catches: an index into the per-frame arrays used for the thinned clouds (the wrong cloud,
    or one from the future), clouds not thinned."""
    class Pan(Hold):  # the camera arm turns, so every frame's cloud differs
        def step(self, obs):
            return Command(np.r_[0.4, np.zeros(11)], status="ok")

    robot = SimRobot(VineSceneParams(), seed=0, camera=CameraConfig(rate=30.0, downsample=6))
    path = tmp_path / "episode.npz"
    result = run_episode(robot, Pan(), duration=0.3, log_clouds=3, cloud_max_points=500, log_path=path)
    assert result.ok, result.error
    log = load_log(path.parent)
    n_frames = len(log["frame_time"])
    np.testing.assert_array_equal(log["cloud_frame"], np.arange(0, n_frames, 3))
    sizes = np.diff(log["cloud_offsets"])
    assert len(sizes) == len(log["cloud_frame"]) and sizes.max() <= 500 and sizes.min() > 100
    for frame in frames_from_log(log, fps=100.0):
        i = int(np.flatnonzero(log["frame_time"] <= frame.time + 1e-12)[-1])  # latest camera frame
        j = i // 3  # latest logged cloud: frames 0, 3, 6, ...
        a, b = log["cloud_offsets"][j], log["cloud_offsets"][j + 1]
        np.testing.assert_array_equal(frame.cloud_points, log["cloud_points"][a:b])


def test_log_clouds_rejects_bad_counts():
    robot = SimRobot(VineSceneParams(), seed=0, camera=None)
    with pytest.raises(InvalidInputError, match="log_clouds"):
        run_episode(robot, Hold(), duration=0.01, log_clouds=-1)
    with pytest.raises(InvalidInputError, match="cloud_max_points"):
        run_episode(robot, Hold(), duration=0.01, log_clouds=2, cloud_max_points=0)


def test_numeric_phase_is_named_by_the_logs_phase_names():
    """The paper loop logs its phase as a number; the replay's text panel must name it."""
    n = 3
    log = {"t": 0.002 * np.arange(n), "q": np.tile(HOME_Q, (n, 1)), "value/phase": np.array([0.0, 1.0, 2.0]),
           "meta/phase_names": np.array("approach,bimanual,precut,abort")}
    assert [f.phase for f in frames_from_log(log, fps=500.0)] == ["approach", "bimanual", "precut"]
