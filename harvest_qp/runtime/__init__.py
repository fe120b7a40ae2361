"""The runtime: what a controller may do with a robot (:class:`RobotInterface`), the fixed-rate episode
runner and its log, and the glue that runs a :class:`~harvest_qp.TaskController` as an episode controller.

Below it: the QP core, perception and the reference laws; above it: the harvest application, the lab
(:mod:`harvest_qp.sim`) and the real robots (:mod:`harvest_qp.real`).
"""

from harvest_qp.runtime.interface import PointCloud, RobotInterface
from harvest_qp.runtime.runner import Command, EpisodeResult, Observation, run_episode

__all__ = ["Command", "EpisodeResult", "Observation", "PointCloud", "RobotInterface", "run_episode"]
