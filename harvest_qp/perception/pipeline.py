"""One call for the per-frame perception pipeline of ``subsec:scePC_proc`` and
``subsec:occlusion_control_signal``.

classification -> stem model, p_sb and its quality -> free space and p_gd (grasping arm) ->
unveiling pairs (camera arm; V_cu from them is the reference law
:func:`harvest_qp.references.unveiling.unveiling_velocity`). ``result.stem.trusted()`` and
``result.stem.quality`` say whether p_sb can be used (see :class:`~harvest_qp.perception.stem.StemQuality`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_point, positive_int
from harvest_qp.perception.classify import obstacles_near_stem_base, split_scene
from harvest_qp.perception.free_space import FreeSpace, compute_free_space
from harvest_qp.perception.stem import StemModel, fit_stem
from harvest_qp.perception.unveiling import RayObstaclePairs, ray_obstacle_pairs
from harvest_qp.validation import as_positive_scalar

__all__ = ["PerceptionResult", "process_cloud"]


@dataclass(frozen=True)
class PerceptionResult:
    """Everything the controllers and a viewer need from one frame.

    Attributes:
        stem_points: ``(n_S, 3)`` stem points S [m].
        n_dropped: input rows dropped for NaN or inf.
        stem: the two-segment stem model; ``stem.valid`` tells whether p_sb exists.
        grasp_obstacles: ``(n_O, 3)`` the grasping arm's obstacles O = (W - S) inside
            S(p_sb, r_o) [m]; empty when the stem model is invalid.
        free_space: free space and p_gd, ``None`` when the stem model is invalid.
        unveiling: ray/obstacle pairs of the camera arm (``eq:nearest``), whose obstacles are
            all non-stem points (``unveiling.obstacle_points``).
    """

    stem_points: NDArray[np.float64]
    n_dropped: int
    stem: StemModel
    grasp_obstacles: NDArray[np.float64]
    free_space: FreeSpace | None
    unveiling: RayObstaclePairs

    @property
    def stem_base(self) -> NDArray[np.float64] | None:
        """p_sb [m], ``None`` when the stem model is invalid."""
        return self.stem.base

    @property
    def target(self) -> NDArray[np.float64] | None:
        """p_gd [m], ``None`` when the stem model is invalid or there is no free space."""
        return None if self.free_space is None else self.free_space.target


def process_cloud(
    points: ArrayLike,
    stem_mask: ArrayLike,
    *,
    camera_position: ArrayLike,
    gripper_position: ArrayLike,
    r_o: float | None = None,
    n_samples: int = 500,
    d_o: float = 0.001,
    d_a: float = 0.01,
    min_stem_points: int = 10,
    stem_radius: float | None = None,
    target_selection: str = "clearance",
) -> PerceptionResult:
    """Run the perception pipeline on one scene cloud.

    Args:
        points: ``(n_W, 3)`` scene cloud W in the world frame [m]; rows with NaN or inf are
            dropped (counted in ``n_dropped``).
        stem_mask: ``(n_W,)`` boolean stem labels (e.g. from
            :func:`~harvest_qp.perception.classify.red_stem_mask`).
        camera_position: camera position p_c [m].
        gripper_position: grasping arm tip p_g [m], names the top/bottom stem clusters.
        r_o: radius [m] of the sphere S(p_sb, r_o) bounding the grasping arm's obstacles;
            ``None`` uses the estimated stem length l, as in Section ``sec:exper``.
        n_samples: Fibonacci samples of the free-space sphere.
        d_o: obstacle sphere radius [m].
        d_a: influence distance of the unveiling potential [m].
        min_stem_points: fewer stem points make the stem model invalid.
        stem_radius: known stem radius [m] for the near-surface correction of p_sb;
            ``None`` estimates it (:func:`~harvest_qp.perception.stem.fit_stem`).
        target_selection: ``"clearance"`` (default) chooses p_gd by the clearance of the
            straight stem against every observed non-stem point
            (:func:`~harvest_qp.perception.free_space.compute_free_space` with
            ``scene_points``); ``"paper"`` uses ``eq:attr_point`` alone.

    Returns:
        A :class:`PerceptionResult`.  The unveiling part does not need the stem model and is
        always computed (no pairs when n_S = 0).

    Raises:
        InvalidInputError: wrong shapes, non-finite positions or invalid parameters.
    """
    camera = as_point("camera_position", camera_position)
    gripper = as_point("gripper_position", gripper_position)
    if r_o is not None:
        r_o = as_positive_scalar(r_o, "r_o")
    # Checked here too so that a bad value fails on every frame, not only on frames where
    # the stem model is valid and the free space is computed.
    n_samples = positive_int("n_samples", n_samples)
    if target_selection not in ("clearance", "paper"):
        raise InvalidInputError(f"target_selection must be 'clearance' or 'paper', got {target_selection!r}")
    scene = split_scene(points, stem_mask)

    stem = fit_stem(
        scene.stem,
        gripper,
        camera_position=camera,
        non_stem_points=scene.non_stem,
        stem_radius=stem_radius,
        min_points=min_stem_points,
    )
    grasp_obstacles = np.zeros((0, 3))
    free_space = None
    if stem.valid:
        grasp_obstacles = obstacles_near_stem_base(scene.non_stem, stem.base, stem.length if r_o is None else r_o)
        free_space = compute_free_space(
            grasp_obstacles,
            stem.base,
            stem.length,
            camera,
            n_samples=n_samples,
            scene_points=scene.non_stem if target_selection == "clearance" else None,
        )

    pairs = ray_obstacle_pairs(scene.stem, scene.non_stem, camera, d_a=d_a, d_o=d_o)
    return PerceptionResult(
        stem_points=scene.stem,
        n_dropped=scene.n_dropped,
        stem=stem,
        grasp_obstacles=grasp_obstacles,
        free_space=free_space,
        unveiling=pairs,
    )
