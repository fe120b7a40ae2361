"""The grasp target p_gd of ``eq:attr_point`` within the swing bound, map-aware (beyond the paper).

The paper takes p_gd over the whole free-space hemisphere F
(:func:`~harvest_qp.perception.free_space.compute_free_space`). Here, measured on the default
scene and seeds 1 and 5 of the MuJoCo lab:

* p_gd is taken among the free samples within ``max_swing_deg`` of the hanging stem (a p_gd
  48-53 deg off it swung the crop up beside the branch: arm-vine contacts, 6 N at the wrist);
* with an obstacle map (:class:`SwingCheck`), among those whose swing keeps the gripper and
  the wrist links next to it ``clearance`` [m] from every mapped cell (on seeds 1 and 5 the
  gripper otherwise swung the crop into the occluding leaf: a 6 N abort, 19,068 contact
  ticks); when no free sample swings clear, the hanging direction itself or the least swing
  of the cone that does, else the most clearance.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from harvest_qp.perception.free_space import FreeSpace
from harvest_qp.perception.obstacle_map import ObstacleMap

__all__ = ["SWING_CAPSULES", "SWING_FRACTIONS", "GraspTarget", "SwingCheck", "choose_grasp_target",
           "rotations_between"]

#: Capsules of the grasping arm checked along the swing to p_gd: the gripper and the two wrist
#: links next to it, which move (nearly) rigidly with the gripper while it swings the crop.
SWING_CAPSULES = ("grasp_gripper", "grasp_wrist_3", "grasp_wrist_2")

#: Fractions of the swing (hanging stem -> p_gd) at which the gripper is checked against the map.
SWING_FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def rotations_between(a: NDArray[np.float64], b: NDArray[np.float64], fractions: ArrayLike) -> NDArray[np.float64]:
    """Rotations by ``fractions`` of the shortest turn from unit ``a`` to each unit ``b[i]``: ``(n, f, 3, 3)``.

    Rodrigues' formula about the axis a x b (a turn of 0 where b is parallel to a).
    """
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=1)
    cos = np.clip(b @ a, -1.0, 1.0)
    angle = np.arctan2(sin, cos)
    unit = np.where(sin[:, None] > 1e-12, axis / np.maximum(sin, 1e-12)[:, None], 0.0)
    K = np.zeros((len(b), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -unit[:, 2], unit[:, 1], -unit[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = unit[:, 2], -unit[:, 1], unit[:, 0]
    th = angle[:, None] * np.asarray(fractions, float)[None, :]
    return np.eye(3) + np.sin(th)[..., None, None] * K[:, None] + (1 - np.cos(th))[..., None, None] * (K @ K)[:, None]


@dataclass(frozen=True)
class SwingCheck:
    """The gripper's swing to a candidate p_gd, measured on an obstacle map.

    Attributes:
        obstacle_map: the map (its occupied cells are the obstacles).
        gripper_position: the gripper point p_g now [m].
        capsules: the capsules that swing with the gripper, ``(p0, p1, radius)`` in the world
            frame now [m] (e.g. those of :data:`SWING_CAPSULES`).
        clearance: the clearance [m] a swing must keep from every mapped cell.
        stretch: how far beyond the sphere S(p_sb, l) the gripper moves out along n_c as the
            stem stretches [m] (checked at half and all of it; 0: not checked).
    """

    obstacle_map: ObstacleMap
    gripper_position: NDArray[np.float64]
    capsules: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], float]]
    clearance: float
    stretch: float = 0.0

    @property
    def limit(self) -> float:
        """Clearances are measured up to this distance [m] (twice ``clearance``)."""
        return 2.0 * self.clearance

    def clearances(
        self,
        samples: NDArray[np.float64],
        stem_base: NDArray[np.float64],
        hanging: NDArray[np.float64],
        *,
        fractions: Sequence[float] = SWING_FRACTIONS,
        stretches: Sequence[float] | None = None,
    ) -> NDArray[np.float64]:
        """Smallest map distance [m] of the capsules along the swing to each of ``(n, 3)`` ``samples``, capped at
        :attr:`limit`.

        The swing to a sample: the gripper point turns about p_sb with the stem, from the
        hanging direction ``hanging`` (unit, p_sb -> top of the crop) to the sample's, while
        the gripper turns by the same rotation about its own point, twice as fast (``k_og`` =
        2 ``k_pg`` in ``eq:superimp_g``: when the position has done a fraction f of its way,
        the orientation has done 1 - (1 - f)^2); the capsules move rigidly with it. At the end
        of the turn the gripper also moves out along n_c by each of ``stretches`` (default:
        half and all of :attr:`stretch`; measured 22 mm beyond S(p_sb, l) on seed 5 at 3 N).
        The held cluster and the stem must be kept out of the map by the caller.
        """
        if stretches is None:
            stretches = (0.5 * self.stretch, self.stretch) if self.stretch > 0 else ()
        fractions = np.asarray(fractions, float)
        turn = np.concatenate([1.0 - (1.0 - fractions) ** 2, np.ones(len(stretches))])
        move = np.concatenate([fractions, np.ones(len(stretches))])
        out = np.concatenate([np.zeros(len(fractions)), np.asarray(stretches, float)])
        directions = samples - stem_base
        directions /= np.linalg.norm(directions, axis=1)[:, None]
        R_move = rotations_between(hanging, directions, move)  # (n, m, 3, 3)
        R_turn = rotations_between(hanging, directions, turn)
        p_g = self.gripper_position
        # the gripper point along the swing
        points = (stem_base + np.einsum("nmij,j->nmi", R_move, p_g - stem_base)
                  + out[None, :, None] * directions[:, None])
        p0 = np.stack([points + np.einsum("nmij,j->nmi", R_turn, a - p_g) for a, _, _ in self.capsules], axis=2)
        p1 = np.stack([points + np.einsum("nmij,j->nmi", R_turn, b - p_g) for _, b, _ in self.capsules], axis=2)
        n, m = R_move.shape[:2]
        radii = np.tile(np.array([r for _, _, r in self.capsules], float), n * m)
        limit = self.limit
        query = self.obstacle_map.closest_cells(p0.reshape(-1, 3), p1.reshape(-1, 3), radii, max_distance=limit,
                                                per_capsule=1)
        distance = np.minimum(query.min_distances(), limit).reshape(n, m * len(self.capsules))
        return distance.min(axis=1)


@dataclass(frozen=True)
class GraspTarget:
    """The chosen p_gd and how it was chosen.

    Attributes:
        point: p_gd [m], ``None`` when F has no free sample.
        choice: which rule chose it (for metrics.json), e.g. ``"eq:attr_point"``.
        swing_clearance: ``(per-sample swing clearance [m], the clearance asked [m])`` when
            the map was checked, else ``None``.
    """

    point: NDArray[np.float64] | None
    choice: str
    swing_clearance: tuple[NDArray[np.float64], float] | None = None


def choose_grasp_target(
    free: FreeSpace,
    stem_base: NDArray[np.float64],
    top_of_crop: NDArray[np.float64],
    *,
    max_swing_deg: float | None,
    swing: SwingCheck | None = None,
) -> GraspTarget:
    """p_gd of ``eq:attr_point`` over the free samples within ``max_swing_deg`` of the stem now.

    Args:
        free: the free space F and its samples on S(p_sb, l).
        stem_base: p_sb [m].
        top_of_crop: where the stem meets the held crop now [m]; the stem now runs from p_sb
            to it.
        max_swing_deg: the swing bound [deg]; ``None`` (and no ``swing``) keeps the paper's
            choice ``free.target``.
        swing: the map check of the swing (``None``: none). In tiers: free, in the cone and
            clear (then ``eq:attr_point`` among them); free and clear (the least swing); the
            hanging direction itself or the least swing of the cone that is clear; else the
            most clearance. "Clear" is ``swing.clearance``, or the gripper's clearance now if
            that is less (a gripper already close to the branch must not get closer).
    """
    if max_swing_deg is None and swing is None:
        return GraspTarget(free.target.copy(), "eq:attr_point")
    cone_choice = "eq:attr_point over the free samples in the cone"
    if not np.any(free.free):
        return GraspTarget(None, cone_choice)
    hanging = top_of_crop - stem_base
    hanging = hanging / float(np.linalg.norm(hanging))
    samples = free.samples
    directions = (samples - stem_base) / np.linalg.norm(samples - stem_base, axis=1)[:, None]
    cos_swing = directions @ hanging
    cone = cos_swing >= (np.cos(np.radians(max_swing_deg)) if max_swing_deg is not None else -1.0)
    in_cone = free.free & cone
    record = None
    if swing is not None:
        clearance = swing.clearances(samples, stem_base, hanging)
        now = swing.clearances(top_of_crop[None], stem_base, hanging, fractions=(0.0,), stretches=(0.0,))[0]
        needed = min(swing.clearance, now)
        record = (clearance, needed)
        clear = clearance >= needed - 1e-9
        if np.any(in_cone & clear):
            in_cone = in_cone & clear
            cone_choice = "free, in the cone, swing clear (eq:attr_point among them)"
        elif np.any(free.free & clear):  # outside the cone: the least swing that is clear
            pool = np.flatnonzero(free.free & clear)
            return GraspTarget(samples[pool[np.argmax(cos_swing[pool])]].copy(),
                               "free, swing clear, outside the cone (least swing)", record)
        else:
            # No sample of F swings clear (measured on seeds 1 and 5: F lies on the camera's
            # side, where the occluding leaf hangs). Leave F.
            hang_point = stem_base + free.radius * hanging
            hang_clearance = swing.clearances(hang_point[None], stem_base, hanging)[0]
            if hang_clearance >= needed - 1e-9:
                return GraspTarget(hang_point, "no free sample swings clear: the hanging direction (no swing)", record)
            pool = np.flatnonzero(cone & clear)
            if pool.size:
                return GraspTarget(samples[pool[np.argmax(cos_swing[pool])]].copy(),
                                   "no free sample swings clear: the least clear swing of the cone", record)
            pool = np.flatnonzero(cone) if np.any(cone) else np.arange(len(samples))
            best = pool[np.argmax(clearance[pool])]
            point = samples[best].copy() if clearance[best] > hang_clearance else hang_point
            return GraspTarget(point, "no sample swings clear: the most clearance", record)
    if not np.any(in_cone):  # nothing free within the cone: the free sample nearest to it
        closest = np.flatnonzero(free.free)[np.argmax(cos_swing[free.free])]
        return GraspTarget(samples[closest].copy(), "nothing free in the cone: the free sample nearest to it", record)
    candidates = samples[in_cone]
    obstacles = free.projected_obstacles
    if len(obstacles) == 0:
        return GraspTarget(candidates[np.argmax(cos_swing[in_cone])].copy(), cone_choice, record)
    projected_clearance, _ = cKDTree(obstacles).query(candidates)
    return GraspTarget(candidates[int(np.argmax(projected_clearance))].copy(), cone_choice, record)
