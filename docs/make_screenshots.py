"""Regenerate the pictures of the paper episode in README.md, docs/viewer.md and docs/robot.md: meshcat and MuJoCo.

Runs the paper's episode (``tasks/paper.yaml``, seed 0) through the library API, keeps the
state at three moments (the approach, the switch to the bimanual phase, the end), then

* draws each moment in the meshcat viewer (arms as UR5e meshes, vine, point cloud by label,
  ROI, p_r, p_sb, p_gd, stem segments, free-space samples, frustum, V_c / V_g / force arrows,
  text panel) and screenshots it in headless Chromium through its DevTools port, as the
  browser tests do (``tests/viewer/_browser.py``; ``chromium --screenshot`` can hang);
* renders the scene at the switch with MuJoCo's OpenGL renderer
  (:class:`harvest_qp.sim.render.SceneRenderer`): the UR5e meshes, and the collision
  capsules the controller and the lab use (the capsule toggle).

Writes ``viewer_approach.png``, ``viewer_switch.png``, ``viewer_end.png``,
``viewer_switch_closeup.png`` (the stem at the switch, without the ROI sphere, which would
tint the whole close-up), ``mujoco_ur5e.png`` and ``mujoco_capsules.png`` to ``--out``
(PNG, palette, < 300 KB each).
Needs Debian's ``chromium`` and headless OpenGL (``MUJOCO_GL=egl``, set here by default).
About 2-4 minutes on a loaded 2-core machine.

    python docs/make_screenshots.py [--out docs/figures] [--duration 30] [--approach-time 4]
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")  # before mujoco is imported: headless OpenGL

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # this checkout's harvest_qp and the browser helper of its tests

from harvest_qp.config.settings import load_settings  # noqa: E402
from harvest_qp.harvest.harvest_controller import Phase  # noqa: E402
from harvest_qp.sim.paper_episode import run_paper_episode  # noqa: E402
from harvest_qp.sim.render import SceneRenderer  # noqa: E402
from harvest_qp.viewer import MeshcatViewer, ViewerFrame  # noqa: E402
from harvest_qp.viewer.replay import free_port  # noqa: E402
from tests.viewer._browser import screenshot  # noqa: E402

#: meshcat views (view centre, camera offset from it [m]): the whole scene from the grasping
#: arm's side, and a close-up of the stem at the switch (seen from below the camera arm).
OVERVIEW = ((0.45, 0.0, 1.12), (-0.6, -1.05, 0.65))
CLOSEUP = ((0.51, -0.11, 1.21), (-0.22, -0.26, 0.1))
#: MuJoCo orbit camera of the renders (degrees, metres), about the overview's direction.
MUJOCO_VIEW = dict(lookat=(0.4, 0.05, 1.05), distance=1.7, azimuth=60.0, elevation=-28.0)


class MomentRecorder:
    """Wraps the episode's controller and keeps what the pictures need at three moments.

    It only observes (the command is passed through unchanged), like the live viewer.
    """

    def __init__(self, controller, *, approach_time: float) -> None:
        self.controller = controller
        self.approach_time = approach_time
        self.robot = None
        self.moments: dict[str, tuple[ViewerFrame, np.ndarray]] = {}
        self._cloud = None
        self._last = None

    def reset(self, robot) -> None:
        self.robot = robot
        self.controller.reset(robot)

    def __getattr__(self, name):  # the episode reads the wrapped controller's attributes
        return getattr(self.controller, name)

    def step(self, obs):
        command = self.controller.step(obs)
        if obs.cloud is not None:
            self._cloud = obs.cloud
        self._last = (obs, command, self._cloud)
        if "approach" not in self.moments and obs.time >= self.approach_time:
            self.moments["approach"] = self._moment(obs, command, self._cloud)
        # One tick after the switch: the switch tick's wrist reading is the last one before the tare,
        # the held crop's weight (~2.9 N), which the overlay would show as if the stem pulled.
        t_switch = self.controller.phases.t_switch
        if "switch" not in self.moments and t_switch is not None and obs.time > t_switch:
            self.moments["switch"] = self._moment(obs, command, self._cloud)
        return command

    def finish(self) -> None:
        """Keep the last tick as the "end" moment."""
        self.moments["end"] = self._moment(*self._last)

    def _moment(self, obs, command, cloud) -> tuple[ViewerFrame, np.ndarray]:
        values = command.values
        radius = float(self.controller.settings.reaching.radius)
        kw = dict(time=float(obs.time), q=np.asarray(obs.q, float).copy(), force=np.asarray(obs.force, float).copy())
        if "phase" in values:
            kw["phase"] = Phase(int(values["phase"])).name.lower()
        if cloud is not None:
            kw.update(cloud_points=cloud.points, cloud_labels=cloud.labels, camera_pose=cloud.camera_pose,
                      stem_points=cloud.count(0), cloud_key=(id(cloud), cloud.timestamp))  # fmt: skip
        for name, key in (("p_r", "p_r"), ("p_sb", "p_sb"), ("p_gd", "p_gd"), ("v_c", "V_c"), ("v_g", "V_g")):
            value = np.asarray(values.get(key, np.nan), float)
            if value.shape and np.all(np.isfinite(value)):
                kw[name] = value.copy()
        if "theta" in values:
            kw["theta"] = float(values["theta"])
        if "p_r" in kw:
            kw["roi_center"], kw["roi_radius"] = kw["p_r"], radius
        snap = self.controller.switch_snapshot
        if snap is not None:
            # What perception found at the switch (Fig. fig:PC_proc): both stem segments and
            # the Fibonacci samples kept (free space F) and removed.
            stem = snap.stem
            kw["stem_segments"] = np.array([[stem.top.start, stem.top.end], [stem.bottom.start, stem.bottom.end]])
            kw["samples_kept"] = snap.free_space.kept_samples
            kw["samples_removed"] = snap.free_space.removed_samples
        return ViewerFrame(**kw), self.robot.data.qpos.copy()


def save_small_png(image: np.ndarray | Image.Image, path: Path, *, width: int = 960, limit: int = 300_000) -> int:
    """Save ``image`` scaled to ``width`` pixels as a palette PNG under ``limit`` bytes; returns its size."""
    img = image if isinstance(image, Image.Image) else Image.fromarray(np.asarray(image, np.uint8))
    img = img.convert("RGB")
    if img.width > width:
        img = img.resize((width, round(img.height * width / img.width)), Image.LANCZOS)
    for colors in (256, 128, 64):
        img.quantize(colors=colors, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
        if path.stat().st_size < limit:
            break
    return path.stat().st_size


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "figures", help="output folder")
    parser.add_argument("--duration", type=float, default=30.0, help="episode length [s] (pre-cut comes at ~23 s)")
    parser.add_argument("--approach-time", type=float, default=4.0, help="time of the approach picture [s]")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    settings = load_settings(ROOT / "tasks" / "paper.yaml")
    recorder = None

    def wrap(robot, controller):
        nonlocal recorder
        recorder = MomentRecorder(controller, approach_time=args.approach_time)
        return recorder

    with tempfile.TemporaryDirectory() as run_dir:
        report = run_paper_episode(settings, seed=0, duration=args.duration, out_dir=run_dir, figures=False,
                                   wrap_controller=wrap)  # fmt: skip
    recorder.finish()
    m = report.metrics
    print(f"episode: switch at {m['t_bimanual_start']} s, pre-cut at {m['t_precut']} s, success {m['success']}")

    robot = recorder.robot
    shots = [(name, name, OVERVIEW, False) for name in ("approach", "switch", "end")]
    shots.append(("switch_closeup", "switch", CLOSEUP, True))
    for out_name, moment, (centre, offset), hide_roi in shots:
        if moment not in recorder.moments:
            print(f"no {moment} moment in this episode: viewer_{out_name}.png skipped")
            continue
        frame, _ = recorder.moments[moment]
        if hide_roi:
            frame = dataclasses.replace(frame, roi_center=None, roi_radius=None)
        # One viewer per picture: its camera is set when it is built.
        with MeshcatViewer(robot.model, port=free_port(), view_center=centre, camera_offset=offset,
                           verbose=False) as viewer:  # fmt: skip
            viewer.draw(frame)
            with tempfile.TemporaryDirectory() as tmp:
                shot = screenshot(viewer.url, Path(tmp) / "shot.png", settle_s=3.0)
        path = args.out / f"viewer_{out_name}.png"
        print(f"wrote {path} (t = {frame.time:.2f} s, {save_small_png(shot, path) / 1e3:.0f} KB)")

    _, qpos = recorder.moments.get("switch", recorder.moments["end"])
    with SceneRenderer.for_spec(robot.scene.spec, width=1280, height=720) as renderer:
        for name, flags in (("mujoco_ur5e", {}), ("mujoco_capsules", {"show_meshes": False, "show_capsules": True})):
            renderer.set_visible(**flags)
            path = args.out / f"{name}.png"
            size = save_small_png(renderer.render(qpos, **MUJOCO_VIEW), path)
            print(f"wrote {path} ({size / 1e3:.0f} KB)")


if __name__ == "__main__":
    main()
