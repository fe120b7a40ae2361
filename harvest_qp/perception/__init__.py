"""Point-cloud perception for the bimanual harvesting controller.

Implements Section ``subsec:scePC_proc`` (classification, stem model and base p_sb, free
space and grasp target p_gd) and the geometry of Section ``subsec:occlusion_control_signal``
(ray/obstacle pairs and the unveiling velocity V_cu) of the paper.

Modules, one per concern: :mod:`.fibonacci` (sphere lattice and its inverse mapping),
:mod:`.classify` (stem / obstacle sets), :mod:`.stem` (two-segment stem model),
:mod:`.free_space` (free space and p_gd), :mod:`.unveiling` (eq:nearest kernel and V_cu),
:mod:`.pipeline` (:func:`process_cloud`) and :mod:`.synthetic` (test scenes).
"""

from harvest_qp.perception.classify import SceneSplit, obstacles_near_stem_base, red_stem_mask, split_scene
from harvest_qp.perception.fibonacci import fibonacci_sphere, nearest_fibonacci_index
from harvest_qp.perception.free_space import FreeSpace, ObstaclePlane, compute_free_space, fit_obstacle_plane
from harvest_qp.perception.pipeline import PerceptionResult, process_cloud
from harvest_qp.perception.stem import LineSegment, StemModel, StemQuality, fit_stem
from harvest_qp.perception.unveiling import (
    NEAREST_AT_CAMERA,
    NEAREST_AT_STEM_POINT,
    NEAREST_INTERIOR,
    RayObstaclePairs,
    ray_obstacle_pairs,
)

# The unveiling control law moved to harvest_qp.references.unveiling; re-exported here so that
# existing imports keep working.
from harvest_qp.references.unveiling import (  # noqa: E402
    barrier_potential,
    repulsive_velocity,
    stem_angular_velocities,
    unveiling_velocity,
)

__all__ = [
    "NEAREST_AT_CAMERA",
    "NEAREST_AT_STEM_POINT",
    "NEAREST_INTERIOR",
    "FreeSpace",
    "LineSegment",
    "ObstaclePlane",
    "PerceptionResult",
    "RayObstaclePairs",
    "SceneSplit",
    "StemModel",
    "StemQuality",
    "barrier_potential",
    "compute_free_space",
    "fibonacci_sphere",
    "fit_obstacle_plane",
    "fit_stem",
    "nearest_fibonacci_index",
    "obstacles_near_stem_base",
    "process_cloud",
    "ray_obstacle_pairs",
    "red_stem_mask",
    "repulsive_velocity",
    "split_scene",
    "stem_angular_velocities",
    "unveiling_velocity",
]
