"""The grasp target p_gd of ``eq:attr_point`` within the swing bound, map-aware (beyond the paper).

The paper takes p_gd over the whole free-space hemisphere F
(:func:`~harvest_qp.perception.free_space.compute_free_space`). Here, measured on the default
scene and seeds 1 and 5 of the MuJoCo lab:

* p_gd is taken among the free samples within ``max_swing_deg`` of the hanging stem (a p_gd
  48-53 deg off it swung the crop up beside the branch: arm-vine contacts, 6 N at the wrist);
* with an obstacle map (:class:`SwingCheck`), among those whose swing keeps the grasping arm
  (the gripper and wrist turning with it, the forearm and upper arm moving with the joints)
  ``clearance`` plus the map's short bias from every mapped cell (on seeds 1 and 5 the
  gripper otherwise swung the crop into the occluding leaf: a 6 N abort, 19,068 contact
  ticks);
* when no sample passes, the arm pulls along the stem itself (no swing). Earlier fallbacks
  (the least swing outside the cone, the most clearance anywhere) picked targets 55-167 deg
  off the stem on held-out scenes, once 7 cm above p_sb, where compression reads as stretch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_point
from harvest_qp.perception.free_space import FreeSpace
from harvest_qp.perception.obstacle_map import ObstacleMap
from harvest_qp.validation import as_instances, as_positive_scalar

__all__ = ["ARM_SWING_CAPSULES", "MAX_SWING_LIMIT_DEG", "SWING_CAPSULES", "SWING_FRACTIONS", "ArmCapsule",
           "GraspTarget", "SwingCheck", "arm_capsule_motion", "choose_grasp_target", "rotations_between"]

#: Capsules of the grasping arm checked along the swing to p_gd: the gripper and the two wrist
#: links next to it, which move (nearly) rigidly with the gripper while it swings the crop.
SWING_CAPSULES = ("grasp_gripper", "grasp_wrist_3", "grasp_wrist_2")

#: The rest of the grasping arm, moved with its joints along the swing (:class:`ArmCapsule`): on
#: held-out scenes the forearm, not the gripper, was what blocked the swing.
ARM_SWING_CAPSULES = ("grasp_wrist_1", "grasp_forearm", "grasp_upper_arm")

#: Fractions of the swing (hanging stem -> p_gd) at which the gripper is checked against the map.
SWING_FRACTIONS = (0.25, 0.5, 0.75, 1.0)


def _turns(a: NDArray[np.float64], b: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit axes ``(n, 3)`` and angles ``(n,)`` [rad] of the shortest turns from unit ``a`` to each unit ``b[i]``
    (axis 0 where b is parallel to a)."""
    axis = np.cross(a, b)
    sin = np.linalg.norm(axis, axis=1)
    cos = np.clip(b @ a, -1.0, 1.0)
    unit = np.where(sin[:, None] > 1e-12, axis / np.maximum(sin, 1e-12)[:, None], 0.0)
    return unit, np.arctan2(sin, cos)


def rotations_between(a: NDArray[np.float64], b: NDArray[np.float64], fractions: ArrayLike) -> NDArray[np.float64]:
    """Rotations by ``fractions`` of the shortest turn from unit ``a`` to each unit ``b[i]``: ``(n, f, 3, 3)``.

    Rodrigues' formula about the axis a x b (a turn of 0 where b is parallel to a).
    """
    unit, angle = _turns(a, b)
    K = np.zeros((len(b), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -unit[:, 2], unit[:, 1], -unit[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = unit[:, 2], -unit[:, 1], unit[:, 0]
    th = angle[:, None] * np.asarray(fractions, float)[None, :]
    return np.eye(3) + np.sin(th)[..., None, None] * K[:, None] + (1 - np.cos(th))[..., None, None] * (K @ K)[:, None]


@dataclass(frozen=True)
class ArmCapsule:
    """A capsule of the grasping arm that does not move rigidly with the gripper (forearm, wrist 1, ...).

    Its ends move with the joints: ``end + motion @ [dp; dtheta]`` for a gripper displacement dp [m]
    and turn dtheta [rad] (rotation vector), to first order (``motion = J_end J_g^-1`` of the
    grasping arm's six joints, :func:`arm_capsule_motion`).

    Attributes:
        p0, p1: the capsule's ends now [m] (world).
        radius: [m].
        motion0, motion1: ``(3, 6)`` motion of each end per gripper twist displacement.
    """

    p0: NDArray[np.float64]
    p1: NDArray[np.float64]
    radius: float
    motion0: NDArray[np.float64]
    motion1: NDArray[np.float64]


def arm_capsule_motion(end_jacobian: NDArray[np.float64], gripper_jacobian: NDArray[np.float64]) -> NDArray[np.float64]:
    """``(3, 6)``: how a point of the arm moves per gripper twist, ``J_end J_g^+`` [m/m, m/rad].

    Args:
        end_jacobian: ``(3, n)`` linear Jacobian of the point over the arm's joints.
        gripper_jacobian: ``(6, n)`` the gripper's Jacobian ``[v; w]`` (world-aligned) over the same joints.

    The least-squares inverse (``lstsq``) keeps a gripper near a singularity from giving huge motions.
    """
    return end_jacobian @ np.linalg.pinv(gripper_jacobian, rcond=1e-3)


@dataclass(frozen=True)
class SwingCheck:
    """The grasping arm's swing to a candidate p_gd, measured on an obstacle map.

    Attributes:
        obstacle_map: the map (its occupied cells are the obstacles).
        gripper_position: the gripper point p_g now [m].
        capsules: the capsules that move rigidly with the gripper, ``(p0, p1, radius)`` in the
            world frame now [m] (e.g. those of :data:`SWING_CAPSULES`).
        clearance: the clearance [m] a swing must keep from every mapped cell.
        stretch: how far beyond the sphere S(p_sb, l) the gripper moves out along n_c as the
            stem stretches [m] (checked at half and all of it; 0: not checked).
        arm: the rest of the grasping arm (:class:`ArmCapsule`: forearm, wrist 1, ...), moved
            with the joints to first order.
        map_bias: how far the map's cells may lie short of the true surface [m], added to
            ``clearance`` (a cell 1 cm in front of a branch seen from the far side is 1 cm
            farther than the wood).
    """

    obstacle_map: ObstacleMap
    gripper_position: NDArray[np.float64]
    capsules: Sequence[tuple[NDArray[np.float64], NDArray[np.float64], float]]
    clearance: float
    stretch: float = 0.0
    arm: Sequence[ArmCapsule] = ()
    map_bias: float = 0.0

    def __post_init__(self) -> None:
        """Check the inputs (:class:`~harvest_qp.exceptions.InvalidInputError` naming the value)."""
        if not isinstance(self.obstacle_map, ObstacleMap):
            raise InvalidInputError(f"SwingCheck.obstacle_map must be an ObstacleMap, got "
                                    f"{type(self.obstacle_map).__name__}")
        object.__setattr__(self, "gripper_position", as_point("SwingCheck.gripper_position", self.gripper_position))
        if isinstance(self.capsules, (str, bytes)) or not hasattr(self.capsules, "__len__") or not len(self.capsules):
            raise InvalidInputError(f"SwingCheck.capsules must be a non-empty list of (p0 [m], p1 [m], radius [m]) "
                                    f"that move with the gripper, got {self.capsules!r}")
        capsules = []
        for i, capsule in enumerate(self.capsules):
            if not isinstance(capsule, (tuple, list)) or len(capsule) != 3:
                raise InvalidInputError(f"SwingCheck.capsules[{i}] must be (p0 [m], p1 [m], radius [m]), "
                                        f"got {capsule!r}")
            p0, p1, radius = capsule
            capsules.append((as_point(f"SwingCheck.capsules[{i}] p0", p0), as_point(f"SwingCheck.capsules[{i}] p1", p1),
                             as_positive_scalar(radius, f"SwingCheck.capsules[{i}] radius", allow_zero=True)))
        object.__setattr__(self, "capsules", tuple(capsules))
        for name in ("clearance", "stretch", "map_bias"):
            object.__setattr__(self, name, as_positive_scalar(getattr(self, name), f"SwingCheck.{name} [m]",
                                                              allow_zero=True))
        if not isinstance(self.arm, (tuple, list)):  # a generator would be used up here and read as empty later
            raise InvalidInputError(f"SwingCheck.arm must be a list of ArmCapsule, got {type(self.arm).__name__}")
        object.__setattr__(self, "arm", tuple(as_instances(self.arm, ArmCapsule, "SwingCheck.arm")))

    @property
    def needed(self) -> float:
        """The clearance a swing must keep on the map [m]: ``clearance + map_bias``."""
        return self.clearance + self.map_bias

    @property
    def limit(self) -> float:
        """Clearances are measured up to this distance [m] (twice :attr:`needed`)."""
        return 2.0 * self.needed

    def clearances(
        self,
        samples: NDArray[np.float64],
        stem_base: NDArray[np.float64],
        hanging: NDArray[np.float64],
        *,
        fractions: Sequence[float] = SWING_FRACTIONS,
        stretches: Sequence[float] | None = None,
    ) -> NDArray[np.float64]:
        """``(n, c)``: each capsule's smallest map distance [m] along the swing to each of ``(n, 3)``
        ``samples`` (capsules: :attr:`capsules`, then :attr:`arm`), capped at :attr:`limit`.

        The swing to a sample, as ``eq:superimp_g`` commands it: the gripper point turns about
        p_sb with the stem, from the hanging direction ``hanging`` (unit, p_sb -> top of the
        crop) to the sample's, while the gripper turns by the same rotation about its own
        point, twice as fast (``k_og`` = 2 ``k_pg``: when the position has done a fraction f of
        its way, the orientation has done 1 - (1 - f)^2); :attr:`capsules` move rigidly with
        it, :attr:`arm` with the joints that make that motion (first order). At the end of the
        turn the gripper also moves out along n_c by each of ``stretches`` (default: half and
        all of :attr:`stretch`; measured 22 mm beyond S(p_sb, l) on seed 5 at 3 N). The held
        cluster and the stem must be kept out of the map by the caller.
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
        ends0 = [points + np.einsum("nmij,j->nmi", R_turn, a - p_g) for a, _, _ in self.capsules]
        ends1 = [points + np.einsum("nmij,j->nmi", R_turn, b - p_g) for _, b, _ in self.capsules]
        radii = [r for _, _, r in self.capsules]
        if self.arm:
            unit, angle = _turns(hanging, directions)
            # the gripper's displacement and turn (rotation vector) at each step: (n, m, 6)
            twist = np.concatenate([points - p_g, (angle[:, None] * turn[None, :])[..., None] * unit[:, None]], axis=2)
            for c in self.arm:
                ends0.append(c.p0 + twist @ c.motion0.T)
                ends1.append(c.p1 + twist @ c.motion1.T)
                radii.append(c.radius)
        p0, p1 = np.stack(ends0, axis=2), np.stack(ends1, axis=2)
        n, m = R_move.shape[:2]
        radii = np.tile(np.asarray(radii, float), n * m)
        limit = self.limit
        query = self.obstacle_map.closest_cells(p0.reshape(-1, 3), p1.reshape(-1, 3), radii, max_distance=limit,
                                                per_capsule=1)
        distance = np.minimum(query.min_distances(), limit).reshape(n, m, p0.shape[2])
        return distance.min(axis=1)


@dataclass(frozen=True)
class GraspTarget:
    """The chosen p_gd and how it was chosen.

    Attributes:
        point: p_gd [m], ``None`` when F has no free sample.
        choice: which rule chose it (for metrics.json), e.g. ``"eq:attr_point"``.
        swing_clearance: ``(per-sample swing clearance [m] (n, c) of each capsule, the clearance
            asked of each capsule [m] (c,))`` when the map was checked, else ``None``; NaN for the
            samples that were not candidates (not free, outside the swing bound or above p_sb).
    """

    point: NDArray[np.float64] | None
    choice: str
    swing_clearance: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None


#: :attr:`GraspTarget.choice` of each rule of :func:`choose_grasp_target`.
CHOICE_PAPER = "eq:attr_point"
CHOICE_CONE = "eq:attr_point over the free samples in the cone"
CHOICE_CONE_CLEAR = "free, in the cone, swing clear (eq:attr_point among them)"
CHOICE_ALONG_STEM = "along the stem: nothing in the cone is free and swing clear (no swing)"
CHOICE_NO_TARGET = "no target: the crop hangs level with or above the stem base"
CHOICE_NO_FREE = "no target: F has no free sample"

#: The largest swing bound [deg], exclusive: a p_gd 90 deg or more off the stem now puts the crop where
#: it hangs now level with or behind p_sb along n_c = (p_gd - p_sb)/|...|, where compression reads as stretch.
MAX_SWING_LIMIT_DEG = 90.0


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
        max_swing_deg: the swing bound [deg], in (0, 90); ``None`` with a ``swing`` check: the cone is
            the crop's side of p_sb (less than 90 deg off the stem now); ``None`` and no ``swing``
            keeps the paper's choice ``free.target`` over the whole hemisphere.
        swing: the map check of the swing (``None``: none).

    Rules, in order (:attr:`GraspTarget.choice` says which chose):

    1. ``eq:attr_point`` among the samples that are free, within ``max_swing_deg`` of the stem
       now, below p_sb, and (with ``swing``) swing clear: each capsule of the arm keeps
       :attr:`SwingCheck.needed` from every mapped cell, or its own clearance now if that is
       less (a gripper already close to the branch must not get closer).
    2. Else the stem's own direction: p_sb + l (top of the crop - p_sb)/|...| -- the arm pulls
       along the stem without swinging the crop (forcing this on the scenes where earlier
       fallbacks picked targets 55-167 deg off the stem gave pre-cut in 13-14 s at 3 N true
       tension, no contact).
    3. No target (``point`` None: the episode does not switch and says why) when the crop is
       not below p_sb: a target there would put the crop on the wrong side of the stem base,
       where compression reads as stretch along n_c.

    With a swing bound or a map check, the target never leaves the swing bound, never lies
    above the stem base and never puts the crop behind it along n_c; with neither, it is the
    paper's ``free.target`` as it is (``point`` None, :data:`CHOICE_NO_FREE`, when F has no free
    sample).

    Raises:
        InvalidInputError: ``free`` not a :class:`~harvest_qp.perception.free_space.FreeSpace`, a
            non-finite ``stem_base`` or ``top_of_crop``, a stem of no length (``top_of_crop`` at
            ``stem_base``), or ``max_swing_deg`` not in (0, 90).
    """
    if not isinstance(free, FreeSpace):
        raise InvalidInputError(f"free must be a FreeSpace (compute_free_space's answer), got {type(free).__name__}")
    stem_base = as_point("stem_base", stem_base)
    top_of_crop = as_point("top_of_crop", top_of_crop)
    if max_swing_deg is not None:
        max_swing_deg = as_positive_scalar(max_swing_deg, "max_swing_deg")
        if max_swing_deg >= MAX_SWING_LIMIT_DEG:
            raise InvalidInputError(
                f"max_swing_deg must be in (0, {MAX_SWING_LIMIT_DEG:g}) [deg] or None, got {max_swing_deg!r}: a "
                "swing that large puts the crop level with or behind the stem base along n_c")
    if max_swing_deg is None and swing is None:
        if free.target is None:
            return GraspTarget(None, CHOICE_NO_FREE)
        return GraspTarget(free.target.copy(), CHOICE_PAPER)
    hanging = top_of_crop - stem_base
    length = float(np.linalg.norm(hanging))
    if length < 1e-9:
        raise InvalidInputError(f"top_of_crop must differ from stem_base (the stem now has no direction), "
                                f"got both {stem_base.tolist()}")
    hanging = hanging / length
    if hanging[2] >= 0.0:
        return GraspTarget(None, CHOICE_NO_TARGET)
    samples = free.samples
    directions = (samples - stem_base) / np.linalg.norm(samples - stem_base, axis=1)[:, None]
    cos_swing = directions @ hanging
    # With no bound the cone is the crop's side of p_sb: a sample 90 deg or more off the stem now would
    # leave the crop level with or behind p_sb along n_c.
    cone = (cos_swing >= np.cos(np.radians(max_swing_deg))) if max_swing_deg is not None else (cos_swing > 1e-9)
    candidates = free.free & cone & (directions[:, 2] < 0.0)
    choice, record = CHOICE_CONE, None
    if swing is not None and np.any(candidates):
        # Only the candidates' swings are checked (~1 in 7 samples at a 40 deg bound): all 500
        # swings took 10-30 ms on the switch tick, beyond the real cell's 20 ms cycle limit.
        clearance = np.full((len(samples), len(swing.capsules) + len(swing.arm)), np.nan)
        clearance[candidates] = swing.clearances(samples[candidates], stem_base, hanging)
        now = swing.clearances(top_of_crop[None], stem_base, hanging, fractions=(0.0,), stretches=(0.0,))[0]
        # Per capsule: one already close to a cell must not get closer, the others keep the full
        # clearance (an arm-wide minimum let one stray cell at the forearm switch the check off for
        # the gripper).
        needed = np.minimum(swing.needed, now)
        record = (clearance, needed)
        candidates &= np.all(clearance >= needed - 1e-9, axis=1)
        choice = CHOICE_CONE_CLEAR
    if not np.any(candidates):
        return GraspTarget(stem_base + free.radius * hanging, CHOICE_ALONG_STEM, record)
    obstacles = free.projected_obstacles
    if len(obstacles) == 0:
        pool = np.flatnonzero(candidates)
        return GraspTarget(samples[pool[np.argmax(cos_swing[pool])]].copy(), choice, record)
    projected_clearance, _ = cKDTree(obstacles).query(samples[candidates])
    return GraspTarget(samples[candidates][int(np.argmax(projected_clearance))].copy(), choice, record)
