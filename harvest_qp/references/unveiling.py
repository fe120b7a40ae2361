"""OOI unveiling reference V_cu of the camera arm (``subsec:occlusion_control_signal``).

The paper's law, given the ray/obstacle pairs of ``eq:nearest``
(:func:`harvest_qp.perception.unveiling.ray_obstacle_pairs`)::

    V(r)     = 1/2 ln^2(d_a^2 / (d_a^2 - (d_a - r)^2))   for r < d_a, else 0   (eq:art_potential)
    u_jk     = -dV/dp_hat                                                      (eq:u_ij)
    w_jk     = S(p_hat - p_sj) u_jk / |p_hat - p_sj|^2   on the interior branch (eq:omega_pivot)
    w_sj     = sum_k w_jk                                                      (eq:omega_i)
    V_cu     = k_c sum_j [S(p_sj - p_c); I_3] w_sj                              (eq:v_c2)

is :func:`unveiling_velocity` (literal) with its parts :func:`barrier_potential`,
:func:`repulsive_velocity` and :func:`stem_angular_velocities`.

:class:`Unveiling` is the reference object the closed loop uses.  It deviates from the paper
in two measured ways (the numbers are in the README's section on the reference laws):

1. Bounded (the "paper" mode).  On this project's clouds the literal law with the paper's
   k_c reaches 1e4-1e5 rad/s and grows with the cloud's resolution: the sums run over every
   ray/obstacle pair, and obstacle points touching the stem (the grape, the branch, the
   gripper) make ``eq:omega_pivot``'s denominator |p_hat - p_sj|^2 tiny.  No per-point scaling
   gives a usable magnitude, only the direction is usable.  So pairs whose pivot arm
   |p_hat - p_sj| is below ``min_pivot`` (3 cm) are dropped (an obstacle touching the stem
   point does not occlude it), and the resulting twist is scaled *as a whole* (one factor
   for v and w, which keeps it a rotation about the same screw axis, i.e. still a rotation about
   the stem points) so that |w| <= ``max_angular`` and |v| <= ``max_linear``; a first-order
   low-pass (``time_constant``, the paper's own remedy for the law's discontinuity in time)
   follows in :meth:`Unveiling.update`.
2. Beyond the paper (the "predicted" mode).  While no stem point is seen (n_S = 0, where the
   paper's V_cu is zero), a stem hidden along the whole approach would never be unveiled.  The
   paper's potential applied to predicted stem points does not help: a ray through a leaf is
   symmetric about it, the repulsions cancel and the camera dithers (the lab measurements; reproduced in
   ``tests/references/test_unveiling_closed_loop.py``).  Instead a next-best-view step scores
   candidate viewpoints on the sphere around the ROI centre by how many predicted stem points
   they see past the observed non-stem points, and moves the camera tangentially towards the
   best one, with the bearing feed-forward that keeps the ROI centred.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import (
    as_points,
    as_pose,
    as_position,
    as_positive_scalar,
    as_time_step,
    cross_rows,
)
from harvest_qp.references.next_best_view import NextBestView

if TYPE_CHECKING:  # a module-level import would be circular (perception re-exports this module)
    from harvest_qp.perception.unveiling import RayObstaclePairs

__all__ = [
    "Unveiling",
    "barrier_potential",
    "bounded_unveiling_velocity",
    "predicted_stem_points",
    "repulsive_velocity",
    "stem_angular_velocities",
    "unveiling_velocity",
]


# ---------------------------------------------------------------- the paper's law, literal


def barrier_potential(surface_distance: ArrayLike, d_a: float) -> NDArray[np.float64]:
    """Barrier potential V(r_hat) of ``eq:art_potential`` (dimensionless).

    V = 1/2 ln^2(d_a^2 / (d_a^2 - (d_a - r_hat)^2)) for 0 < r_hat < d_a, 0 for r_hat >= d_a,
    +inf for r_hat <= 0 (on or inside the obstacle sphere).
    """
    r_hat = np.asarray(surface_distance, dtype=np.float64)
    d_a = as_positive_scalar(d_a, "d_a")
    with np.errstate(divide="ignore", invalid="ignore"):
        log_ratio = np.log(d_a * d_a / (d_a * d_a - (d_a - r_hat) ** 2))
        potential = 0.5 * log_ratio**2
    return np.where(r_hat >= d_a, 0.0, np.where(r_hat <= 0.0, np.inf, potential))


def _repulsive_gain(surface_distance: NDArray[np.float64], d_a: float, floor: float) -> NDArray[np.float64]:
    """||u_jk|| of ``eq:u_ij`` as a function of r_hat [m], with r_hat floored at ``floor``.

    ||u|| = 2 / (d_a^2 - (d_a - r)^2) ln(d_a^2 / (d_a^2 - (d_a - r)^2)) (d_a - r); clamping r
    to d_a makes it exactly zero outside the influence distance without a mask.
    """
    r_hat = np.clip(surface_distance, floor, d_a)
    barrier = d_a * d_a - (d_a - r_hat) ** 2
    return 2.0 / barrier * np.log(d_a * d_a / barrier) * (d_a - r_hat)


def repulsive_velocity(
    nearest_points: ArrayLike,
    obstacle_points: ArrayLike,
    *,
    d_a: float,
    d_o: float,
    min_surface_distance: float = 1e-6,
) -> NDArray[np.float64]:
    """Virtual repulsive velocity u_jk = -dV/dp_hat of ``eq:u_ij``, one row per pair.

    u = 2 / (d_a^2 - (d_a - r)^2) ln(d_a^2 / (d_a^2 - (d_a - r)^2)) e_jk with
    e_jk = (d_a - r) (p_hat - p_o) / ||p_hat - p_o|| for r = r_hat < d_a, zero otherwise.

    Args:
        nearest_points: ``(P, 3)`` p_hat_jk [m].
        obstacle_points: ``(P, 3)`` p_ok [m], paired row by row.
        d_a: influence distance [m].
        d_o: obstacle radius [m].
        min_surface_distance: r_hat is floored at this [m] so that a ray touching or crossing
            an obstacle sphere (r_hat <= 0, where the paper's potential is infinite) gives a
            large but finite velocity.  A pair with p_hat exactly at the obstacle centre has no
            direction and gives zero.

    Returns:
        ``(P, 3)`` velocities [1/m: the gradient of the dimensionless potential].
    """
    nearest = as_points(nearest_points, "nearest_points")
    obstacles = as_points(obstacle_points, "obstacle_points")
    if nearest.shape != obstacles.shape:
        raise InvalidInputError(
            f"nearest_points and obstacle_points must have the same shape (P, 3), got "
            f"{nearest.shape} and {obstacles.shape}"
        )
    d_a = as_positive_scalar(d_a, "d_a")
    d_o = as_positive_scalar(d_o, "d_o", allow_zero=True)
    floor = as_positive_scalar(min_surface_distance, "min_surface_distance")
    gap = nearest - obstacles
    distance = np.sqrt(np.einsum("ij,ij->i", gap, gap))
    gain = _repulsive_gain(distance - d_o, d_a, floor)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(distance[:, None] > 0.0, gain[:, None] * gap / distance[:, None], 0.0)


def _checked_cloud(points: object) -> bool:
    """Whether ``points`` is already a float64 ``(n, 3)`` ndarray (no conversion needed)."""
    return type(points) is np.ndarray and points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3


def _pair_weights(pairs: RayObstaclePairs, floor: float, min_pivot: float) -> NDArray[np.float64]:
    """Per pair |u_jk| / (1 - s) on the interior branch of ``eq:nearest`` with pivot arm
    |p_hat - p_sj| = (1 - s)|p_cs_j| >= ``min_pivot``, zero otherwise."""
    from harvest_qp.perception.unveiling import NEAREST_INTERIOR  # noqa: PLC0415 (circular at module level)

    gain = _repulsive_gain(pairs.surface_distance, pairs.influence_distance, floor)
    keep = pairs.case == NEAREST_INTERIOR
    remaining = 1.0 - pairs.segment_parameter
    if min_pivot > 0.0:
        ray_length = np.linalg.norm(pairs.stem_points - pairs.camera_position, axis=1)
        keep = keep & (remaining * np.take(ray_length, pairs.stem_index) >= min_pivot)
    # The floor on 1 - s only avoids 0/0 at s = 1 (such pairs are not interior anyway).
    return gain * keep / np.maximum(remaining, np.finfo(np.float64).tiny)


def stem_angular_velocities(
    pairs: RayObstaclePairs, *, min_surface_distance: float = 1e-6, min_pivot: float = 0.0
) -> NDArray[np.float64]:
    """Angular velocity omega_sj about each stem point: ``eq:omega_pivot`` summed by ``eq:omega_i``.

    omega_jk = S(p_hat - p_sj) u_jk / ||p_hat - p_sj||^2 for pairs in the interior branch of
    ``eq:nearest``, zero otherwise; omega_sj = sum_k omega_jk.

    On the interior branch p_hat - p_sj = -(1 - s) p_cs_j, so omega_jk =
    -(p_cs_j x u_jk) / ((1 - s) ||p_cs_j||^2) and the sum over k only needs, per stem point,
    the sum of u_jk / (1 - s): one ``np.bincount`` per component, then one cross product per
    stem point instead of one per pair.

    Args:
        pairs: output of :func:`harvest_qp.perception.unveiling.ray_obstacle_pairs`.
        min_surface_distance: floor on r_hat [m], see :func:`repulsive_velocity`.
        min_pivot: pairs whose pivot arm |p_hat - p_sj| is shorter are dropped [m] (0: the
            paper; see :class:`Unveiling` for why the bounded law drops them).

    Returns:
        ``(n_S, 3)`` omega_sj [1/m^2, the paper's unscaled units; times k_c it is rad/s].
    """
    floor = as_positive_scalar(min_surface_distance, "min_surface_distance")
    min_pivot = as_positive_scalar(min_pivot, "min_pivot", allow_zero=True)
    return _stem_angular_velocities_from_weights(pairs, _pair_weights(pairs, floor, min_pivot))


def _stem_angular_velocities_from_weights(pairs: RayObstaclePairs, weight: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`stem_angular_velocities` from the pairs' :func:`_pair_weights`."""
    n_stem = pairs.stem_points.shape[0]
    summed = np.stack(
        [
            np.bincount(pairs.stem_index, weights=weight * component, minlength=n_stem)
            for component in pairs.away_directions.T
        ],
        axis=1,
    ).reshape(n_stem, 3)
    rays = pairs.stem_points - pairs.camera_position
    if n_stem == 0:
        return np.zeros((0, 3))
    return -cross_rows(rays, summed) / np.einsum("ij,ij->i", rays, rays)[:, None]


def unveiling_velocity(
    pairs: RayObstaclePairs, *, k_c: float, min_surface_distance: float = 1e-6, min_pivot: float = 0.0
) -> NDArray[np.float64]:
    """Unveiling twist V_cu of ``eq:v_c2`` (unbounded, literal), [linear; angular] in the world frame.

    V_cu = k_c sum_j [S(p_sj - p_c); I_3] omega_sj, with omega_sj from
    :func:`stem_angular_velocities`; d_a and d_o are those the pairs were computed with.
    Zero when there are no stem points (n_S = 0) or no pairs.

    Args:
        pairs: output of :func:`harvest_qp.perception.unveiling.ray_obstacle_pairs`.
        k_c: gain (0.00025 in Section ``sec:exper``).
        min_surface_distance: floor on r_hat [m], see :func:`repulsive_velocity`.
        min_pivot: see :func:`stem_angular_velocities` (0: the paper).

    Returns:
        ``(6,)`` twist: linear [m/s] then angular [rad/s].
    """
    k_c = as_positive_scalar(k_c, "k_c")
    floor = as_positive_scalar(min_surface_distance, "min_surface_distance")
    min_pivot = as_positive_scalar(min_pivot, "min_pivot", allow_zero=True)
    return _unveiling_velocity_from_weights(pairs, _pair_weights(pairs, floor, min_pivot), k_c)


def _unveiling_velocity_from_weights(
    pairs: RayObstaclePairs, weight: NDArray[np.float64], k_c: float
) -> NDArray[np.float64]:
    """:func:`unveiling_velocity` from the pairs' :func:`_pair_weights`."""
    omega = _stem_angular_velocities_from_weights(pairs, weight)
    rays = pairs.stem_points - pairs.camera_position
    linear = cross_rows(rays, omega).sum(axis=0)  # S(p_cs) omega = p_cs x omega
    return k_c * np.concatenate((linear, omega.sum(axis=0)))


def saturate_twist(twist: NDArray[np.float64], max_linear: float, max_angular: float) -> NDArray[np.float64]:
    """``twist`` scaled by one factor in (0, 1] so that |v| <= max_linear and |w| <= max_angular.

    One factor for both parts keeps the twist's screw axis (a rotation about the stem points
    stays one), unlike clipping each part separately.
    """
    linear = float(np.linalg.norm(twist[:3]))
    angular = float(np.linalg.norm(twist[3:]))
    scale = 1.0
    if linear > max_linear:
        scale = max_linear / linear
    if angular * scale > max_angular:
        scale = max_angular / angular
    return twist * scale


def bounded_unveiling_velocity(
    pairs: RayObstaclePairs,
    *,
    k_c: float = 0.00025,
    min_pivot: float = 0.03,
    max_linear: float = 0.1,
    max_angular: float = 0.2,
    min_surface_distance: float = 1e-6,
) -> NDArray[np.float64]:
    """The paper's V_cu (``eq:v_c2``) without pairs whose pivot arm is below ``min_pivot`` [m],
    scaled as a whole to |v| <= ``max_linear`` [m/s] and |w| <= ``max_angular`` [rad/s].

    Why each step, measured: see :class:`Unveiling`.  Returns ``(6,)`` [m/s; rad/s].
    """
    twist = unveiling_velocity(pairs, k_c=k_c, min_surface_distance=min_surface_distance, min_pivot=min_pivot)
    return saturate_twist(twist, max_linear, max_angular)


# ---------------------------------------------------------------- predicted stem points


def predicted_stem_points(
    gripper_pose: ArrayLike, *, offset: float = 0.015, length: float = 0.06, n: int = 12
) -> NDArray[np.float64]:
    """Where the stem of the grasped crop is expected, from the gripper pose {G} alone.

    The crop hangs along y_g of {G} (the paper's convention, ``subsec:grasp_contr``: y_g is the
    grasped crop's direction, pointing down the cluster, away from the stem base), so the stem
    rises from the grasp along -y_g.  Returns ``(n, 3)`` points [m] evenly spaced on the segment
    from ``offset`` to ``offset + length`` above the grasp origin along -y_g.  The defaults
    (1.5 cm, 6 cm) match the lab's grasp offset and a typical 5-7 cm stem; real stems bend
    5-15 deg off that axis (lab measurements, README), which the consumer must tolerate.
    """
    pose = as_pose(gripper_pose, "gripper_pose")
    offset = as_positive_scalar(offset, "offset", allow_zero=True)
    length = as_positive_scalar(length, "length")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise InvalidInputError(f"n must be an integer >= 1, got {n!r}")
    up = -pose[:3, 1]
    along = offset + length * (np.arange(n) / (n - 1) if n > 1 else np.array([0.5]))
    return pose[:3, 3] + along[:, None] * up


class Unveiling:
    """Unveiling reference V_cu of the camera arm (``eq:art_potential`` .. ``eq:v_c2``), bounded,
    low-passed, and extended to a stem not seen at all (module docstring).

    Per new camera frame call :meth:`observe`; every control tick call :meth:`update`.

    Args:
        k_c: gain of ``eq:v_c2`` (0.00025 in ``sec:exper``).
        d_a: influence distance of ``eq:art_potential`` [m] (0.01).
        d_o: obstacle sphere radius [m] (0.001).
        time_constant: first-order low-pass on V_cu [s] (the paper's remedy for its
            discontinuity; 0.2 s worked in the lab measurements).
        max_linear, max_angular: bounds on the raw twist [m/s], [rad/s] (0.1, 0.2: the lab measurements'
            closed-loop variant that unveiled most; the low-pass only shrinks it further).
        min_pivot: pairs whose pivot arm |p_hat - p_sj| is shorter are dropped [m] (3 cm).
        min_stem_points: with predicted points given, the paper mode takes over from the
            predicted mode only once this many stem points are seen (10: a handful of noisy
            points is not yet a stem).  Without predicted points any n_S >= 1 uses the paper mode.
        nbv_angles: polar angles of the candidate viewpoints from the current one [rad].
        nbv_azimuths: number of azimuths per polar angle.
        nbv_speed: top tangential speed of the next-best-view step [m/s] (0.1).
        nbv_gain: tangential speed = min(nbv_speed, nbv_gain x arc length to the target) [1/s].
        clearance: a line of sight is clear when it passes farther than this from every
            remembered 1 cm voxel centre [m] (9 mm; never below the voxel's half-diagonal,
            8.7 mm, or a voxelised leaf would have gaps: measured with 6 mm, a disc leaf in
            front of the stem read 33 % clear).
        ignore_radius: obstacle points this close to a predicted point do not hide it [m]
            (3 cm: the grape and gripper around the stem's bottom).
        goal_fraction: the step stops when this fraction of predicted points is clear from the
            current viewpoint.
        min_distance: the step never brings the camera closer to the ROI centre than this [m];
            below it an outward speed gain x deficit is added (lab measurements: without it the camera
            drifted to 3 cm from the grape).
        stall_time: a target viewpoint towards which the camera made less than 1 deg of
            progress for this long [s] is abandoned and its direction avoided (lab measurements: a
            collision row held the arm 20 s aiming at an unreachable viewpoint).
        memory_radius: non-stem points within this of the ROI centre are remembered as 1 cm
            voxels for the viewpoint search [m] (0.45, as in the lab measurements).
        memory_lifetime: a voxel not seen again for this long is forgotten [s] (5 s; ``inf``:
            never).  Leaves are static, but the gripper and the crop move in the bimanual phase
            and would leave stale obstacles; the hidden-stem flights first see the stem within
            3.5-4.4 s, inside the lifetime.
        nbv_period: the next-best-view step plans at most this often [s] (0.1: 10 Hz, as
            measured in the lab; frames in between keep its last twist), which keeps its
            average cost per 30 Hz frame at a third of one step's (~6 ms at 283x160).
        frame_period: assumed time between frames [s] when :meth:`observe` gets no timestamp.
        max_stem_points, max_obstacle_points: in the paper mode, more stem / non-stem points
            than these are thinned by a uniform stride before the ray/obstacle pairs (``None``:
            never).  Not in the paper: at 848x480 the pairs took 44 ms median per lab frame
            (``benchmarks/bench_references.py``); only the bounded law's direction is used, and
            thinning to these counts changed it by cos >= 0.92 (mostly >= 0.99) on synthetic
            848x480 frames (README, reference laws).

    Attributes:
        raw: last unfiltered V_cu ``(6,)`` [m/s; rad/s].
        value: last filtered V_cu returned by :meth:`update`.
        n_pairs: ray/obstacle pairs used by the last paper-mode :meth:`observe`.
        mode: "paper", "predicted" or "idle".
        clear_fraction: fraction of predicted points clear from the camera (predicted mode).
        next_best_view: the :class:`~harvest_qp.references.next_best_view.NextBestView` state.
    """

    def __init__(
        self,
        *,
        k_c: float = 0.00025,
        d_a: float = 0.01,
        d_o: float = 0.001,
        time_constant: float = 0.2,
        max_linear: float = 0.1,
        max_angular: float = 0.2,
        min_pivot: float = 0.03,
        min_stem_points: int = 10,
        nbv_angles: tuple[float, ...] = (math.radians(15.0), math.radians(30.0), math.radians(50.0)),
        nbv_azimuths: int = 8,
        nbv_speed: float = 0.1,
        nbv_gain: float = 2.0,
        clearance: float = 0.009,
        ignore_radius: float = 0.03,
        goal_fraction: float = 0.8,
        min_distance: float = 0.25,
        stall_time: float = 1.5,
        memory_radius: float = 0.45,
        memory_lifetime: float = 5.0,
        nbv_period: float = 0.1,
        frame_period: float = 1.0 / 30.0,
        max_stem_points: int | None = 300,
        max_obstacle_points: int | None = 45_000,
    ) -> None:
        self.k_c = as_positive_scalar(k_c, "k_c")
        self.d_a = as_positive_scalar(d_a, "d_a")
        self.d_o = as_positive_scalar(d_o, "d_o", allow_zero=True)
        self.time_constant = as_positive_scalar(time_constant, "time_constant", allow_zero=True)
        self.max_linear = as_positive_scalar(max_linear, "max_linear")
        self.max_angular = as_positive_scalar(max_angular, "max_angular")
        self.min_pivot = as_positive_scalar(min_pivot, "min_pivot", allow_zero=True)
        if (
            isinstance(min_stem_points, bool)
            or not isinstance(min_stem_points, (int, np.integer))
            or min_stem_points < 1
        ):
            raise InvalidInputError(f"min_stem_points must be an integer >= 1, got {min_stem_points!r}")
        self.min_stem_points = int(min_stem_points)
        angles = np.asarray(nbv_angles, dtype=np.float64).ravel()
        if angles.size == 0 or not np.all((angles > 0.0) & (angles < math.pi / 2)):
            raise InvalidInputError(f"nbv_angles must be angles in (0, pi/2) [rad], got {nbv_angles!r}")
        self.nbv_angles = angles
        if isinstance(nbv_azimuths, bool) or not isinstance(nbv_azimuths, (int, np.integer)) or nbv_azimuths < 3:
            raise InvalidInputError(f"nbv_azimuths must be an integer >= 3, got {nbv_azimuths!r}")
        self.nbv_azimuths = int(nbv_azimuths)
        self.nbv_speed = as_positive_scalar(nbv_speed, "nbv_speed")
        self.nbv_gain = as_positive_scalar(nbv_gain, "nbv_gain")
        self.clearance = as_positive_scalar(clearance, "clearance")
        self.ignore_radius = as_positive_scalar(ignore_radius, "ignore_radius", allow_zero=True)
        self.goal_fraction = as_positive_scalar(goal_fraction, "goal_fraction")
        if self.goal_fraction > 1.0:
            raise InvalidInputError(f"goal_fraction must be in (0, 1], got {goal_fraction!r}")
        self.min_distance = as_positive_scalar(min_distance, "min_distance", allow_zero=True)
        self.stall_time = as_positive_scalar(stall_time, "stall_time")
        self.memory_radius = as_positive_scalar(memory_radius, "memory_radius")
        self.memory_lifetime = (
            math.inf if memory_lifetime == math.inf else as_positive_scalar(memory_lifetime, "memory_lifetime")
        )
        self.frame_period = as_positive_scalar(frame_period, "frame_period")
        self.nbv_period = as_positive_scalar(nbv_period, "nbv_period", allow_zero=True)
        for name, value in (("max_stem_points", max_stem_points), ("max_obstacle_points", max_obstacle_points)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
                raise InvalidInputError(f"{name} must be None or an integer >= 1, got {value!r}")
        self.max_stem_points = None if max_stem_points is None else int(max_stem_points)
        self.max_obstacle_points = None if max_obstacle_points is None else int(max_obstacle_points)
        self.next_best_view = NextBestView(
            angles=self.nbv_angles,
            azimuths=self.nbv_azimuths,
            speed=self.nbv_speed,
            gain=self.nbv_gain,
            clearance=self.clearance,
            ignore_radius=self.ignore_radius,
            goal_fraction=self.goal_fraction,
            min_distance=self.min_distance,
            stall_time=self.stall_time,
            memory_radius=self.memory_radius,
            memory_lifetime=self.memory_lifetime,
        )
        self.reset()

    def reset(self) -> None:
        """Zero the filter and forget the next-best-view state."""
        self.raw = np.zeros(6)
        self.value = np.zeros(6)
        self.n_pairs = 0
        self.mode = "idle"
        self._time = 0.0
        self._last_plan = -math.inf
        self.next_best_view.reset()

    # ------------------------------------------------------------ per frame

    def observe(
        self,
        camera_position: ArrayLike,
        stem_points: ArrayLike,
        obstacle_points: ArrayLike,
        *,
        predicted_stem_points: ArrayLike | None = None,
        roi_centre: ArrayLike | None = None,
        timestamp: float | None = None,
    ) -> None:
        """Compute the raw (bounded) V_cu target from one camera frame.

        Args:
            camera_position: p_c [m].
            stem_points: ``(n_S, 3)`` seen stem points [m] (may be empty).
            obstacle_points: ``(n_O, 3)`` seen non-stem points [m] (for the camera arm the
                paper's obstacles are all non-stem points).
            predicted_stem_points: ``(m, 3)`` where the stem is expected [m]
                (:func:`predicted_stem_points`); enables the predicted mode while fewer than
                ``min_stem_points`` stem points are seen.
            roi_centre: p_r [m], centre of the candidate sphere and of the bearing
                feed-forward in the predicted mode (default: the predicted points' mean).
            timestamp: frame time [s] for the stall rule (default: ``frame_period`` after the
                previous frame).
        """
        as_position(camera_position, "camera_position")
        stem = as_points(stem_points, "stem_points")
        obstacles = as_points(obstacle_points, "obstacle_points")
        self._observe_points(camera_position, stem, obstacles, predicted_stem_points=predicted_stem_points,
                             roi_centre=roi_centre, timestamp=timestamp)

    def _observe_points(
        self,
        camera_position: ArrayLike,
        stem: NDArray[np.float64],
        obstacles: NDArray[np.float64],
        *,
        predicted_stem_points: ArrayLike | None = None,
        roi_centre: ArrayLike | None = None,
        timestamp: float | None = None,
        thinned_obstacles: NDArray[np.float64] | None = None,
    ) -> None:
        """:meth:`observe` on ``stem`` and ``obstacles`` already known to be finite float64
        ``(n, 3)`` arrays (the control loop checks its whole cloud once); the few small
        arguments are still checked.

        ``obstacles`` may also be a lazy row source (``.shape`` and ``[::k]`` slicing give
        arrays): the control loop gathers the whole non-stem cloud only when it is used.
        ``thinned_obstacles``: ``obstacles[::obstacle_stride(n_O)]`` if the caller already
        gathered it (the paper mode uses only those rows)."""
        camera = as_position(camera_position, "camera_position")
        predicted = None if predicted_stem_points is None else as_points(predicted_stem_points, "predicted_stem_points")
        self._time = self._time + self.frame_period if timestamp is None else float(timestamp)
        if predicted is not None and predicted.shape[0] > 0 and stem.shape[0] < self.min_stem_points:
            centre = predicted.mean(axis=0) if roi_centre is None else as_position(roi_centre, "roi_centre")
            if self.mode == "predicted" and self._time - self._last_plan < self.nbv_period - 1e-9:
                return  # between planning frames the last step's twist stands (see nbv_period)
            self.mode = "predicted"
            self.n_pairs = 0
            self._last_plan = self._time
            if not isinstance(obstacles, np.ndarray):
                obstacles = obstacles[::1]
            twist = self.next_best_view.step(camera, predicted, obstacles, centre, self._time)
            self.raw = saturate_twist(twist, self.max_linear, self.max_angular)
            return
        self.next_best_view.drop_target()  # a seen stem ends the search (the memory stays)
        if stem.shape[0] == 0:
            self.mode, self.n_pairs, self.raw = "idle", 0, np.zeros(6)
            return
        from harvest_qp.perception.unveiling import (  # noqa: PLC0415 (circular at module level)
            _ray_obstacle_pairs_unchecked,
            ray_obstacle_pairs,
        )

        # Only the law's direction is used; uniform strides over the (image-ordered) points keep
        # it while the cost stays about that of a 283x160 frame (see max_stem_points).
        if self.max_stem_points is not None and stem.shape[0] > self.max_stem_points:
            stem = stem[:: -(-stem.shape[0] // self.max_stem_points)]
        if thinned_obstacles is not None:
            obstacles = thinned_obstacles
        else:
            stride = self.obstacle_stride(obstacles.shape[0])
            if stride > 1 or not isinstance(obstacles, np.ndarray):
                obstacles = obstacles[::stride]
        if _checked_cloud(stem) and _checked_cloud(obstacles):
            # Finite by this method's contract: the unchecked kernel skips re-testing the ~20,000
            # obstacle points (~15 % of ray_obstacle_pairs). The attributes may have been reassigned.
            d_a = as_positive_scalar(self.d_a, "d_a")
            d_o = as_positive_scalar(self.d_o, "d_o", allow_zero=True)
            pairs = _ray_obstacle_pairs_unchecked(stem, obstacles, camera, d_a, d_o)
        else:
            pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=self.d_a, d_o=self.d_o)
        self.mode = "paper"
        # The pair weights once, for the count and the law (bounded_unveiling_velocity with its
        # default 1e-6 floor would compute the same weights a second time).
        weight = _pair_weights(pairs, 1e-6, self.min_pivot)
        self.n_pairs = int(np.count_nonzero(weight))
        twist = _unveiling_velocity_from_weights(pairs, weight, self.k_c)
        self.raw = saturate_twist(twist, self.max_linear, self.max_angular)

    def obstacle_stride(self, n_obstacles: int) -> int:
        """The stride k the paper mode thins ``n_obstacles`` non-stem points with (it uses
        ``obstacles[::k]``; 1 when ``max_obstacle_points`` is None or not exceeded)."""
        if self.max_obstacle_points is not None and n_obstacles > self.max_obstacle_points:
            return -(-n_obstacles // self.max_obstacle_points)
        return 1

    # ------------------------------------------------------------ per tick

    def update(self, dt: float) -> NDArray[np.float64]:
        """Advance the first-order low-pass towards :attr:`raw` by ``dt`` [s]; returns V_cu ``(6,)``."""
        dt = as_time_step(dt)
        if self.time_constant == 0.0:
            self.value = self.raw.copy()
        else:
            self.value = self.value + (-math.expm1(-dt / self.time_constant)) * (self.raw - self.value)
        return self.value.copy()

    @property
    def clear_fraction(self) -> float:
        """Fraction of predicted stem points with a clear line of sight from the camera at the
        last predicted-mode frame (NaN before)."""
        return self.next_best_view.clear_fraction
