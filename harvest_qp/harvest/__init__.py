"""The paper's harvest application: :class:`HarvestController`, its phase machine, the paper episode,
its metrics and figures.

perception (point cloud -> S, O, p_sb, p_gd) -> :mod:`harvest_qp.references` (V_cr, V_cu,
V_g, feed-forward) -> QP tasks -> :class:`~harvest_qp.TaskController` -> joint velocities;
:mod:`.phases` decides approach -> bimanual -> pre-cut / abort.
"""

from harvest_qp.config.settings import DEFAULTS, load_settings
from harvest_qp.harvest.harvest_controller import HarvestController
from harvest_qp.harvest.phases import Phase, PhaseMachine, PhaseRules

__all__ = ["HarvestController", "Phase", "PhaseMachine", "PhaseRules", "DEFAULTS", "load_settings"]
