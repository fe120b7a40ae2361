"""The paper's closed loop: :class:`HarvestController`, the paper episode, its metrics and figures.

perception (point cloud -> S, O, p_sb, p_gd) -> :mod:`harvest_qp.references` (V_cr, V_cu,
V_g, feed-forward) -> QP tasks -> :class:`~harvest_qp.TaskController` -> joint velocities.
"""

from harvest_qp.loop.controller import HarvestController, Phase
from harvest_qp.loop.settings import DEFAULTS, load_settings

__all__ = ["HarvestController", "Phase", "DEFAULTS", "load_settings"]
