"""Point-cloud perception for the bimanual harvesting controller.

Implements Section ``subsec:scePC_proc`` (classification, stem model and base p_sb, free
space and grasp target p_gd) and the geometry of Section ``subsec:occlusion_control_signal``
(ray/obstacle pairs and the unveiling velocity V_cu) of the paper.

Modules, one per concern: :mod:`.fibonacci` (sphere lattice and its inverse mapping),
:mod:`.classify` (stem / obstacle sets), :mod:`.stem` (two-segment stem model),
:mod:`.stem_memory` (p_sb from the approach's close frames), :mod:`.free_space` (free space and
p_gd), :mod:`.unveiling` (the ray/obstacle pairs of eq:nearest), :mod:`.pipeline`
(:func:`process_cloud`), :mod:`.cloud_split` (one labelled frame split into S, W - S and the
obstacle points), :mod:`.grasp_target` (p_gd within the swing bound, map-aware),
:mod:`.obstacle_map` and :mod:`.map_feed` (the persistent obstacle map and its feed to the
collision limit), :mod:`.line_prior` (the map's prior on a cane seen in part) and
:mod:`.synthetic` (test scenes).

Perception never imports the reference laws (:mod:`harvest_qp.references`): the data flows
from the cloud to the laws. The unveiling velocity V_cu of the pairs is
:func:`harvest_qp.references.unveiling.unveiling_velocity`.
"""

from harvest_qp.perception.classify import SceneSplit, obstacles_near_stem_base, red_stem_mask, split_scene
from harvest_qp.perception.cloud_split import LabelledFrame, obstacle_sphere_centres, outside_held_cluster
from harvest_qp.perception.fibonacci import fibonacci_sphere, nearest_fibonacci_index
from harvest_qp.perception.free_space import FreeSpace, ObstaclePlane, compute_free_space, fit_obstacle_plane
from harvest_qp.perception.grasp_target import GraspTarget, SwingCheck, choose_grasp_target
from harvest_qp.perception.line_prior import LinePrior, LineStructure, find_lines
from harvest_qp.perception.pipeline import PerceptionResult, process_cloud
from harvest_qp.perception.stem import LineSegment, StemModel, StemQuality, fit_stem
from harvest_qp.perception.stem_memory import StemTopMemory
from harvest_qp.perception.unveiling import (
    NEAREST_AT_CAMERA,
    NEAREST_AT_STEM_POINT,
    NEAREST_INTERIOR,
    RayObstaclePairs,
    ray_obstacle_pairs,
)

__all__ = [
    "NEAREST_AT_CAMERA",
    "NEAREST_AT_STEM_POINT",
    "NEAREST_INTERIOR",
    "FreeSpace",
    "GraspTarget",
    "LabelledFrame",
    "LinePrior",
    "LineStructure",
    "LineSegment",
    "ObstaclePlane",
    "PerceptionResult",
    "RayObstaclePairs",
    "SceneSplit",
    "StemModel",
    "StemQuality",
    "StemTopMemory",
    "SwingCheck",
    "choose_grasp_target",
    "compute_free_space",
    "fibonacci_sphere",
    "find_lines",
    "fit_obstacle_plane",
    "fit_stem",
    "nearest_fibonacci_index",
    "obstacle_sphere_centres",
    "obstacles_near_stem_base",
    "outside_held_cluster",
    "process_cloud",
    "ray_obstacle_pairs",
    "red_stem_mask",
    "split_scene",
]
