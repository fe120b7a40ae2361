"""The paper's reference velocities (Section ``sec:contr``), one law per module.

* :mod:`.reaching` -- V_cr, ROI reaching with centering (``eq:control_signal_rr_world``).
* :mod:`.unveiling` -- V_cu, unveiling (``eq:art_potential`` .. ``eq:v_c2``), bounded, and
  extended to a stem that is not seen at all (predicted stem points).
* :mod:`.grasping` -- V_g, stem stretching (``eq:gr_pos_contr`` .. ``eq:superimp_g``).
* :mod:`.coordination` -- the feed-forward of ``eq:final_vc`` and the switch thresholds.

All vectors are world-frame float64; twists are [v (m/s); w (rad/s)]; poses (4, 4).
The ray/obstacle geometry (``eq:nearest``) stays in :mod:`harvest_qp.perception.unveiling`.
"""

from harvest_qp.references.coordination import GraspFeedForward, switch_ready
from harvest_qp.references.grasping import StemStretching
from harvest_qp.references.reaching import ReachingCentering, minimum_rotation
from harvest_qp.references.unveiling import (
    Unveiling,
    barrier_potential,
    bounded_unveiling_velocity,
    predicted_stem_points,
    repulsive_velocity,
    stem_angular_velocities,
    unveiling_velocity,
)

__all__ = [
    "GraspFeedForward",
    "ReachingCentering",
    "StemStretching",
    "Unveiling",
    "barrier_potential",
    "bounded_unveiling_velocity",
    "minimum_rotation",
    "predicted_stem_points",
    "repulsive_velocity",
    "stem_angular_velocities",
    "switch_ready",
    "unveiling_velocity",
]
