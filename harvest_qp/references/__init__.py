"""The paper's reference velocities (Section ``sec:contr``), one law per module.

* :mod:`.reaching` -- V_cr, ROI reaching with centering (``eq:control_signal_rr_world``).
* :mod:`.unveiling` -- V_cu, unveiling (``eq:art_potential`` .. ``eq:v_c2``), bounded, and
  extended to a stem that is not seen at all (predicted stem points).
* :mod:`.grasping` -- V_g, stem stretching (``eq:gr_pos_contr`` .. ``eq:superimp_g``).
* :mod:`.coordination` -- the feed-forward of ``eq:final_vc`` and the switch thresholds.
* :mod:`.keep_out` -- an outward speed near the ROI centre (beyond the paper).
* :mod:`.roll` -- the camera's roll that turns the cutter across the stem (beyond the paper).
* :mod:`.hold` -- the grasping arm's hold of the crop during the approach (beyond the paper).
* :mod:`.look_around` -- the camera's opt-in sweep of its surroundings at the start of the approach (beyond the paper).

All vectors are world-frame float64; twists are [v (m/s); w (rad/s)]; poses (4, 4).
The ray/obstacle geometry (``eq:nearest``) stays in :mod:`harvest_qp.perception.unveiling`.
"""

from harvest_qp.references.coordination import GraspFeedForward, switch_ready
from harvest_qp.references.grasping import StemStretching
from harvest_qp.references.hold import HoldPose
from harvest_qp.references.keep_out import keep_out_velocity
from harvest_qp.references.look_around import LookAround
from harvest_qp.references.reaching import ReachingCentering, minimum_rotation
from harvest_qp.references.roll import roll_reference, wrap_half_turn
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
    "HoldPose",
    "LookAround",
    "ReachingCentering",
    "StemStretching",
    "Unveiling",
    "barrier_potential",
    "bounded_unveiling_velocity",
    "keep_out_velocity",
    "minimum_rotation",
    "predicted_stem_points",
    "repulsive_velocity",
    "roll_reference",
    "stem_angular_velocities",
    "switch_ready",
    "unveiling_velocity",
    "wrap_half_turn",
]
