"""See the episode: a meshcat viewer of the dual-UR5e harvester (live, replay, offline HTML).

Observing only: nothing in the control path imports this package. Entry points:

* :class:`MeshcatViewer` -- the scene (UR5e meshes, capsules, vine, point cloud, markers,
  text panel); ``draw(ViewerFrame)`` sends one batched frame.
* :class:`LiveViewer` -- ``observe(obs, extras)`` from the control loop, drawn by a worker
  thread at <= 30 Hz; :class:`ViewedController` wraps a runner controller to call it.
* :func:`replay` / :func:`export_episode_html` -- a saved ``.npz`` episode as a meshcat
  animation with a time slider, or one self-contained HTML file.
* :class:`ViewerServer` -- the meshcat server process: bound to 127.0.0.1 by default, a busy
  port raises :class:`ViewerPortInUseError`, never left running after its parent exits.
"""

from harvest_qp.viewer.extras import paper_episode_extras
from harvest_qp.viewer.frame import LOG_KEYS, ViewerFrame, frame_from_observation, frames_from_log
from harvest_qp.viewer.live import LiveViewer, RealTimePacer, ViewedController, wait_for_interrupt
from harvest_qp.viewer.replay import export_episode_html, load_log, replay, vine_params_from_log
from harvest_qp.viewer.server import Connection, ViewerError, ViewerPortInUseError, ViewerServer
from harvest_qp.viewer.viewer import COLORS, MeshcatViewer

__all__ = [
    "COLORS",
    "Connection",
    "LOG_KEYS",
    "LiveViewer",
    "MeshcatViewer",
    "RealTimePacer",
    "ViewedController",
    "ViewerError",
    "ViewerFrame",
    "ViewerPortInUseError",
    "ViewerServer",
    "export_episode_html",
    "frame_from_observation",
    "frames_from_log",
    "load_log",
    "paper_episode_extras",
    "replay",
    "vine_params_from_log",
    "wait_for_interrupt",
]
