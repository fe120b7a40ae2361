"""Free space around the stem and the grasping arm's target p_gd (``subsec:scePC_proc``).

1. The obstacles O are projected onto the sphere S(p_sb, l) (the set O_pr of
   Table ``table:PCs``).
2. The sphere is sampled by the spherical Fibonacci lattice; the sample nearest to each
   projected obstacle is found by the O(1) inverse mapping (:mod:`.fibonacci`) and removed.
3. A plane is fitted to O by PCA; samples behind it, seen from the camera, are removed
   because the camera cannot see behind the obstacles.  What is left is the free space F.
4. p_gd is the free sample furthest from its nearest projected obstacle (``eq:attr_point``),
   found with a KD-tree over O_pr instead of the brute-force double loop.

Deviation (with ``scene_points``, as :func:`~harvest_qp.perception.pipeline.process_cloud`
does): p_gd is chosen as a selection among the free samples of steps 1-3 (the paper's
hemisphere is kept, unless no straight stem into it stays in view: see below), scored by
their real clearance instead of ``eq:attr_point``'s distance to projected obstacles
(``eq:attr_point`` still breaks ties, and without ``scene_points`` it alone decides, as in
the paper).  On lab frames (FINDINGS, "p_gd and n_c") ``eq:attr_point`` put p_gd
12-47 mm from the nearest non-stem surface where 42-63 mm was possible, once 0.8 mm from the
branch: projecting only the obstacles inside S(p_sb, r_o) onto the sphere forgets how far
they are, and ignores the gripper, the cluster and the wood just outside r_o.  Here:

* a sample is known free only when no observed non-stem point within ``context_radius`` of
  p_sb lies in front of it as seen from the camera (a point behind an observed surface may be
  inside the branch or behind a leaf);
* the straight stem from p_sb to the sample should keep ``segment_clearance`` from every
  such point (``FreeSpace.blocked`` otherwise);
* samples more than ``max_elevation`` above p_sb's horizontal plane are avoided (the stem
  hangs from the branch; pulled upwards it runs along the branch's unseen underside);
* the straight stem should not pass behind an observed surface (``FreeSpace.stem_hidden``:
  a point of it past ``stem_visibility_skip`` lies more than ``visibility_margin`` behind
  the depth buffer of the observed points, one cell around): the cloud holds only the
  wood's camera side, so a stem running just behind the observed front of the branch looks
  clear of every observed point while it runs through the wood's unseen back.  Measured
  (``benchmarks/bench_perception.py --accuracy --seeds 40``, 207 trusted lab views): without
  this test the straight stem entered the branch (past its first 5 mm, up to 5.1 mm deep)
  in 4 views although it kept 10-30 mm from every observed point; all 4 stems ran behind
  the observed branch;
* where no sample of F has a stem that is not hidden, the samples behind the obstacle plane
  (not occupied, not occluded) are candidates too (deviation from the paper's hemisphere,
  ``reason`` says so): in those views (a camera above the branch) the plane removes the
  hanging directions, and 69-99 % of F's straight stems entered the branch (ground truth);
  7 of the 207 views take p_gd from behind the plane, none with its stem in the wood;
* these preferences are tiers, the first non-empty one is the pool: in F, visible, not
  rising, not blocked and not hidden; in F, visible, not blocked and not hidden; the same
  two behind the plane; then in F: visible, not rising and not blocked; visible and not
  rising; visible and not blocked; visible; any free sample (``reason`` says when the chosen
  stem is blocked);
* among those, p_gd maximises the clearance of the whole straight stem p_sb -> sample
  (``FreeSpace.stem_clearance``: l times the smallest clearance/distance ratio along it, so
  the end's clearance at most), ties broken by ``eq:attr_point``'s projected clearance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import minimum_filter
from scipy.spatial import cKDTree

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_finite_points, as_point, positive_int
from harvest_qp.perception.fibonacci import fibonacci_sphere, nearest_index_of_unit_vectors
from harvest_qp.validation import as_positive_scalar

__all__ = ["FreeSpace", "ObstaclePlane", "compute_free_space", "fit_obstacle_plane"]


@dataclass(frozen=True)
class ObstaclePlane:
    """The PCA plane of the obstacles O.

    Attributes:
        point: a point of the plane, the mean of O [m].
        normal: unit normal, oriented towards the camera.
    """

    point: NDArray[np.float64]
    normal: NDArray[np.float64]


@dataclass(frozen=True)
class FreeSpace:
    """Result of :func:`compute_free_space`, with everything a viewer needs.

    Attributes:
        valid: whether a target p_gd was found.
        reason: why not (``valid=False``), or a note on how it was found; empty otherwise.
        centre: sphere centre, the stem base p_sb [m].
        radius: sphere radius, the stem length l [m].
        samples: ``(n_samples, 3)`` Fibonacci samples of S(p_sb, l) [m].
        occupied: ``(n_samples,)`` True for samples nearest to a projected obstacle.
        behind_plane: ``(n_samples,)`` True for samples on the far side of the obstacle plane
            from the camera (all False when there is no plane).
        projected_obstacles: ``(n_O, 3)`` O_pr, the obstacles projected on the sphere [m].
        plane: PCA plane of O, or ``None`` when O has fewer than 3 points, is collinear, or
            contains the camera (no side can be chosen); then no half-space is removed.
        target: p_gd [m] (``eq:attr_point``), ``None`` when there is no free sample.
        target_clearance: distance from p_gd to its nearest projected obstacle [m]; inf when
            there are no obstacles, NaN when there is no target.
        clearance: ``(n_samples,)`` distance from each free sample to the nearest observed
            non-stem point within the context radius [m], capped at ``clearance_cap`` (the
            cap for samples not scored); NaN everywhere without ``scene_points``.
        stem_clearance: ``(n_samples,)`` score of the straight stem p_sb -> sample [m]: l times
            the smallest ratio of clearance to distance from p_sb along it (past
            ``segment_skip``); the end's ``clearance`` bounds it.  inf for samples not
            scored, NaN everywhere without ``scene_points``.
        occluded: ``(n_samples,)`` True for samples behind an observed surface as seen from
            the camera (all False without ``scene_points``).
        blocked: ``(n_samples,)`` True for samples whose ``stem_clearance`` is below
            ``segment_clearance`` (all False without ``scene_points``).
        target_point_clearance: ``clearance`` of p_gd [m]; NaN without a target or without
            ``scene_points``.
        stem_hidden: ``(n_samples,)`` True for samples whose straight stem passes behind an
            observed surface past ``stem_visibility_skip`` (all False without
            ``scene_points``; samples not scored stay False: occupied ones, and those behind
            the plane unless F holds no clear stem in view).
    """

    valid: bool
    reason: str
    centre: NDArray[np.float64]
    radius: float
    samples: NDArray[np.float64]
    occupied: NDArray[np.bool_]
    behind_plane: NDArray[np.bool_]
    projected_obstacles: NDArray[np.float64]
    plane: ObstaclePlane | None
    target: NDArray[np.float64] | None
    target_clearance: float
    clearance: NDArray[np.float64] | None = None
    stem_clearance: NDArray[np.float64] | None = None
    occluded: NDArray[np.bool_] | None = None
    blocked: NDArray[np.bool_] | None = None
    target_point_clearance: float = float("nan")
    stem_hidden: NDArray[np.bool_] | None = None

    @property
    def free(self) -> NDArray[np.bool_]:
        """``(n_samples,)`` True for samples of the free space F."""
        return ~self.occupied & ~self.behind_plane

    @property
    def candidates(self) -> NDArray[np.bool_]:
        """``(n_samples,)`` True for free samples that are neither occluded, blocked nor hidden."""
        mask = self.free
        for flags in (self.occluded, self.blocked, self.stem_hidden):
            if flags is not None:
                mask = mask & ~flags
        return mask

    @property
    def kept_samples(self) -> NDArray[np.float64]:
        """The free-space points F [m]."""
        return self.samples[self.free]

    @property
    def removed_samples(self) -> NDArray[np.float64]:
        """Samples removed as occupied or behind the obstacle plane [m]."""
        return self.samples[~self.free]


def fit_obstacle_plane(
    obstacles: ArrayLike, camera_position: ArrayLike, *, min_planarity: float = 1e-6
) -> ObstaclePlane | None:
    """The PCA plane of the obstacles O, with its normal towards the camera.

    The plane is spanned by the two major PCA eigenvectors of O and passes through its mean
    (``subsec:scePC_proc``, Fig. ``fig:PC_proc_7``).

    Args:
        obstacles: ``(n_O, 3)`` finite obstacle points [m].
        camera_position: camera position p_c [m].
        min_planarity: the plane is undefined (``None``) when the second PCA variance is
            below this fraction of the first (collinear or coincident obstacles).

    Returns:
        The plane, or ``None`` when fewer than 3 obstacles, collinear obstacles, or the
        camera lies on the plane.
    """
    points = as_finite_points("obstacles", obstacles)
    camera = as_point("camera_position", camera_position)
    if points.shape[0] < 3:
        return None
    centroid = points.mean(axis=0)
    centred = points - centroid
    eigenvalues, eigenvectors = np.linalg.eigh(centred.T @ centred)
    if eigenvalues[1] <= min_planarity * eigenvalues[2]:
        return None
    normal = eigenvectors[:, 0]  # smallest variance: perpendicular to the two major axes
    camera_side = normal @ (camera - centroid)
    if abs(camera_side) <= 1e-12 * max(1.0, np.linalg.norm(camera - centroid)):
        return None
    return ObstaclePlane(point=centroid, normal=normal if camera_side > 0.0 else -normal)


def compute_free_space(
    obstacles: ArrayLike,
    stem_base: ArrayLike,
    stem_length: float,
    camera_position: ArrayLike,
    *,
    n_samples: int = 500,
    scene_points: ArrayLike | None = None,
    context_radius: float = 0.05,
    segment_clearance: float = 0.008,
    segment_skip: float | None = None,
    visibility_margin: float = 0.004,
    visibility_cell: float = 0.004,
    stem_visibility_skip: float | None = None,
    clearance_cap: float = 0.03,
    up: ArrayLike = (0.0, 0.0, 1.0),
    max_elevation: float = 0.2,
    tie_break: str = "paper",
) -> FreeSpace:
    """Free space F on the sphere S(p_sb, l) and the target p_gd (``eq:attr_point``).

    Args:
        obstacles: ``(n_O, 3)`` finite obstacle points O [m], e.g. from
            :func:`~harvest_qp.perception.classify.obstacles_near_stem_base`.  Points at the
            stem base itself have no direction and are ignored.
        stem_base: sphere centre p_sb [m].
        stem_length: sphere radius l [m].
        camera_position: camera position p_c [m], to keep the camera side of the plane.
        n_samples: number of Fibonacci samples of the sphere (500 in Fig. ``fig:PC_proc_4``).
        scene_points: ``(n, 3)`` every observed non-stem point W - S of the frame [m]
            (robot included); switches the choice of p_gd to the clearance selection of the
            module docstring.  ``None``: the paper's ``eq:attr_point``.
        context_radius: only observed points within ``stem_length + context_radius`` [m] of
            p_sb are scored against (farther ones, e.g. a leaf near the camera, do not touch
            the stem).
        segment_clearance: the straight stem p_sb -> sample must keep this distance [m] from
            observed points past ``segment_skip``.
        segment_skip: length [m] of the stem's first part, at the branch, left out of the
            segment test; ``None``: 3 mm.
        visibility_margin: a point more than this [m] behind an observed surface (along the
            view ray) is occluded.
        visibility_cell: lateral size [m] (at p_sb's range) of the cells of the depth
            buffer used for the occlusion test; each test looks one cell around.
        stem_visibility_skip: length [m] of the stem's first part left out of the test that it
            does not pass behind an observed surface; ``None``: two ``visibility_cell`` (the
            depth buffer, widened one cell around, covers the branch's edge up to two cells
            from p_sb, so every stem's first part is behind it; measured: 3 mm left no
            sample with a visible stem in the views above, 8 mm and 15 mm both removed the
            4 stems in the wood).
        clearance_cap: clearances are counted up to this [m]; candidates clear by more are
            equal and ``eq:attr_point`` decides between them.
        up: world up direction (against gravity).
        tie_break: between candidates of equal (capped) clearance, ``"paper"`` prefers
            ``eq:attr_point``'s projected clearance, then the sample facing the camera;
            ``"camera"`` the other way round.
        max_elevation: samples more than this angle [rad] above p_sb's horizontal plane are
            avoided (see the tiers in the module docstring) (measured: a stem pulled 35 deg up ran
            2.6 mm inside the branch's unseen underside).

    Returns:
        A :class:`FreeSpace`.  With no obstacles every sample is free and all are equally
        far from an obstacle; the target is then the sample nearest to the direction of the
        camera (the best-seen free point) and ``reason`` says so.  With every sample removed
        the result has ``valid=False`` and no target.
    """
    points = as_finite_points("obstacles", obstacles)
    centre = as_point("stem_base", stem_base)
    radius = as_positive_scalar(stem_length, "stem_length")
    camera = as_point("camera_position", camera_position)
    if np.linalg.norm(camera - centre) < 1e-6:
        raise InvalidInputError(f"camera_position must differ from stem_base (the camera side of the plane needs a "
                                f"direction), got both {centre.tolist()} [m]")
    n_samples = positive_int("n_samples", n_samples)

    samples = centre + radius * fibonacci_sphere(n_samples)
    offsets = points - centre
    distances = np.sqrt(np.einsum("ij,ij->i", offsets, offsets))
    has_direction = distances > 0.0
    directions = offsets[has_direction] / distances[has_direction, None]
    projected = centre + radius * directions

    occupied = np.zeros(n_samples, dtype=bool)
    occupied[nearest_index_of_unit_vectors(directions, n_samples)] = True

    plane = fit_obstacle_plane(points, camera)
    if plane is None:
        behind_plane = np.zeros(n_samples, dtype=bool)
    else:
        behind_plane = (samples - plane.point) @ plane.normal < 0.0

    context = None
    if scene_points is not None:
        context = as_finite_points("scene_points", scene_points)
        context_radius = as_positive_scalar(context_radius, "context_radius", allow_zero=True)
        segment_clearance = as_positive_scalar(segment_clearance, "segment_clearance", allow_zero=True)
        segment_skip = (
            0.003 if segment_skip is None else as_positive_scalar(segment_skip, "segment_skip", allow_zero=True)
        )
        visibility_margin = as_positive_scalar(visibility_margin, "visibility_margin", allow_zero=True)
        visibility_cell = as_positive_scalar(visibility_cell, "visibility_cell")
        stem_visibility_skip = (
            2.0 * visibility_cell
            if stem_visibility_skip is None
            else as_positive_scalar(stem_visibility_skip, "stem_visibility_skip", allow_zero=True)
        )
        clearance_cap = as_positive_scalar(clearance_cap, "clearance_cap")
        if tie_break not in ("paper", "camera"):
            raise InvalidInputError(f"tie_break must be 'paper' or 'camera', got {tie_break!r}")
        up = as_point("up", up)
        if np.linalg.norm(up) == 0.0:
            raise InvalidInputError("up must be a non-zero direction, got [0, 0, 0]")
        up = up / np.linalg.norm(up)
        max_elevation = float(max_elevation)
        if not -np.pi / 2 <= max_elevation <= np.pi / 2:
            raise InvalidInputError(f"max_elevation must be in [-pi/2, pi/2] rad, got {max_elevation!r}")

    free_mask = ~occupied & ~behind_plane
    clearance = stem_clearance = occluded = blocked = stem_hidden = None
    if context is not None:
        settings = dict(
            context_radius=context_radius, segment_clearance=segment_clearance, segment_skip=segment_skip,
            visibility_margin=visibility_margin, visibility_cell=visibility_cell, clearance_cap=clearance_cap,
            stem_visibility_skip=stem_visibility_skip,
        )  # fmt: skip
        scores = _score_samples(samples, free_mask, centre, radius, camera, context, **settings)
        _, _, occluded, blocked, stem_hidden = scores
        if not (free_mask & ~occluded & ~blocked & ~stem_hidden).any():
            # No clear stem in view into F: the samples behind the plane are the fallback (scored
            # only then, the segment queries are most of the cost).
            scores = _score_samples(samples, ~occupied, centre, radius, camera, context, **settings)
        clearance, stem_clearance, occluded, blocked, stem_hidden = scores
    free_index = np.flatnonzero(free_mask)

    def result(valid: bool, reason: str, target_index: int | None, projected_clearance: float) -> FreeSpace:
        return FreeSpace(
            valid=valid,
            reason=reason,
            centre=centre,
            radius=radius,
            samples=samples,
            occupied=occupied,
            behind_plane=behind_plane,
            projected_obstacles=projected,
            plane=plane,
            target=None if target_index is None else samples[target_index],
            target_clearance=projected_clearance,
            clearance=clearance if clearance is not None else np.full(n_samples, np.nan),
            stem_clearance=stem_clearance if stem_clearance is not None else np.full(n_samples, np.nan),
            occluded=occluded,
            blocked=blocked,
            target_point_clearance=(
                float("nan") if target_index is None or clearance is None else float(clearance[target_index])
            ),
            stem_hidden=stem_hidden,
        )

    if context is not None:
        return _select(
            result, samples, centre, radius, camera, projected, occupied, behind_plane,
            clearance_inputs=(stem_clearance, occluded, blocked, stem_hidden),
            up=up, max_elevation=max_elevation, segment_clearance=segment_clearance, tie_break=tie_break,
        )  # fmt: skip
    if free_index.size == 0:
        return result(False, "no free sample: every sample is occupied or behind the obstacle plane", None, np.nan)
    # eq:attr_point's score: distance to the nearest projected obstacle (inf without any).
    projected_clearance = _projected_clearance(projected, samples[free_index])
    if projected.shape[0] == 0:
        # Every sample is infinitely far from an obstacle: prefer the one facing the camera.
        best = free_index[np.argmax(samples[free_index] @ (camera - centre))]
        return result(True, "no obstacles: target is the free sample facing the camera", best, np.inf)
    # eq:attr_point: maximise, over free samples, the distance to the nearest projected obstacle.
    best_position = int(np.argmax(projected_clearance))
    return result(True, "", free_index[best_position], float(projected_clearance[best_position]))


def _projected_clearance(projected: NDArray[np.float64], points: NDArray[np.float64]) -> NDArray[np.float64]:
    """eq:attr_point's score: distance [m] from each point to the nearest projected obstacle (inf without any)."""
    if projected.shape[0] == 0:
        return np.full(points.shape[0], np.inf)
    # Built once per frame and queried by at most n_samples points: an unbalanced tree with
    # large leaves builds about twice as fast and answers the few queries just as well.
    tree = cKDTree(projected, leafsize=64, balanced_tree=False, compact_nodes=False)
    return tree.query(points)[0]


def _select(
    result,
    samples: NDArray[np.float64],
    centre: NDArray[np.float64],
    radius: float,
    camera: NDArray[np.float64],
    projected: NDArray[np.float64],
    occupied: NDArray[np.bool_],
    behind_plane: NDArray[np.bool_],
    *,
    clearance_inputs: tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]],
    up: NDArray[np.float64],
    max_elevation: float,
    segment_clearance: float,
    tie_break: str,
) -> FreeSpace:
    """The clearance selection of the module docstring, among the samples that are not occupied."""
    stem_clearance, occluded, blocked, stem_hidden = clearance_inputs
    open_index = np.flatnonzero(~occupied)
    in_f = ~behind_plane[open_index]
    visible = ~occluded[open_index]
    elevation = (samples[open_index] - centre) @ up / radius
    falling = elevation <= np.sin(max_elevation)
    clear = ~blocked[open_index]
    shown = ~stem_hidden[open_index]
    tiers = (
        # The paper's hemisphere F, with a straight stem that stays in view and clear.
        in_f & visible & falling & clear & shown,
        in_f & visible & clear & shown,
        # Behind the obstacle plane (not occupied, end in view): the stem hanging below the branch.
        visible & falling & clear & shown,
        visible & clear & shown,
        # No stem stays in view: F as before the stem-visibility test.
        in_f & visible & falling & clear,
        in_f & visible & falling,
        in_f & visible & clear,
        in_f & visible,
        in_f,
    )
    pool = next((tier for tier in tiers if tier.any()), None)
    if pool is None:
        return result(False, "no free sample: every sample is occupied or behind the obstacle plane", None, np.nan)
    projected_clearance = _projected_clearance(projected, samples[open_index])
    # Max-min clearance of the whole straight stem; ties (e.g. no observed point near any
    # sample): eq:attr_point's score, then the camera.
    score = np.where(pool, stem_clearance[open_index], -np.inf)
    finite_projected = np.where(np.isfinite(projected_clearance), projected_clearance, 1e3)
    facing = samples[open_index] @ (camera - centre)
    if tie_break == "camera":
        best_position = int(np.lexsort((finite_projected, facing, score))[-1])
    else:
        best_position = int(np.lexsort((facing, finite_projected, score))[-1])
    best = open_index[best_position]
    notes = []
    if not (in_f & visible).any():
        notes.append("every free sample is behind an observed surface")
    if stem_hidden[best]:
        notes.append("no clear straight stem in view: each passes behind an observed surface")
    if behind_plane[best]:
        notes.append("behind the obstacle plane: every straight stem into F passes behind an observed surface")
    if blocked[best]:
        notes.append(
            f"the best straight stem keeps only {stem_clearance[best] * 1e3:.1f} mm "
            f"< segment_clearance={segment_clearance * 1e3:.1f} mm"
        )
    return result(True, "; ".join(notes), best, float(projected_clearance[best_position]))


def _score_samples(
    samples: NDArray[np.float64],
    free_mask: NDArray[np.bool_],
    centre: NDArray[np.float64],
    radius: float,
    camera: NDArray[np.float64],
    scene: NDArray[np.float64],
    *,
    context_radius: float,
    segment_clearance: float,
    segment_skip: float,
    visibility_margin: float,
    visibility_cell: float,
    clearance_cap: float,
    stem_visibility_skip: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """Clearance, stem clearance, occlusion, blocked-stem and hidden-stem flags of the sphere samples."""
    n_samples = samples.shape[0]
    reach = radius + context_radius
    # |p - c|^2 without an (n, 3) temporary (frames hold 10^4-10^5 points).
    # (einsum: numpy's gemv is several times slower on (n, 3) arrays.)
    squared = np.einsum("ij,ij->i", scene, scene) - 2.0 * np.einsum("ij,j->i", scene, centre) + centre @ centre
    near = squared < reach * reach
    # Observed surfaces are sampled more finely than the clearances that matter (>= 5 mm):
    # one point per voxel of a third of the segment clearance keeps distances within about
    # 1 mm and makes the queries below several times cheaper.
    context = np.compress(near, scene, axis=0)
    voxel = max(segment_clearance / 3.0, 0.001)
    if context.shape[0] > 0:
        cells = np.floor((context - centre) / voxel).astype(np.int64) + 1024  # within +-2 m
        keys = (cells[:, 0] << 22) | (cells[:, 1] << 11) | cells[:, 2]
        _, first = np.unique(keys, return_index=True)
        context = context[first]
    clearance = np.full(n_samples, np.inf)
    occluded = np.zeros(n_samples, dtype=bool)
    blocked = np.zeros(n_samples, dtype=bool)
    if context.shape[0] == 0:
        return clearance, clearance.copy(), occluded, blocked, blocked.copy()
    tree = cKDTree(context, balanced_tree=False, compact_nodes=False)  # built per frame: cheaper unbalanced
    # Clearances beyond the cap count the same (the queries stop there, several times faster);
    # ties are then broken by eq:attr_point.
    free_index = np.flatnonzero(free_mask)
    clearance[free_index], _ = tree.query(samples[free_index], distance_upper_bound=clearance_cap)
    clearance = np.minimum(clearance, clearance_cap)

    # Straight stems p_sb -> sample, every 3 mm past the skip, for the free samples: their
    # clearance grows with the distance t from p_sb (the stem leaves the branch at p_sb), so
    # each is scored by the smallest clearance/t ratio along it, times l (the end's clearance
    # at most).
    along = np.append(np.arange(segment_skip, radius, 0.003), radius)
    along = along[along > 0.0]
    fractions = along / radius
    segment_points = centre + fractions[None, :, None] * (samples[free_index] - centre)[:, None, :]
    segment_distance, _ = tree.query(segment_points.reshape(-1, 3), distance_upper_bound=clearance_cap)
    segment_distance = np.minimum(segment_distance, clearance_cap)
    ratio = segment_distance.reshape(free_index.size, fractions.size) / along[None, :]
    stem_clearance = np.full(n_samples, np.inf)
    stem_clearance[free_index] = radius * ratio.min(axis=1)
    too_close = stem_clearance[free_index] < segment_clearance

    # Known free space: a depth buffer of the observed points, over a view frame centred on p_sb.
    view = centre - camera
    view_range = float(np.linalg.norm(view))
    z_axis = view / view_range
    helper = np.array([1.0, 0.0, 0.0]) if abs(z_axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x_axis = np.cross(z_axis, helper)
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    rotation = np.stack((x_axis, y_axis, z_axis))
    angular_cell = visibility_cell / view_range

    def image(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        local = (points - camera) @ rotation.T
        depth = local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return local[:, 0] / depth / angular_cell, local[:, 1] / depth / angular_cell, depth

    u, v, depth = image(context)
    in_front = depth > 0.0
    half = int(np.ceil(1.5 * reach / max(view_range - reach, 1e-3) / angular_cell)) + 2
    size = 2 * half + 1
    buffer = np.full((size, size), np.inf)
    iu = np.floor(u[in_front]).astype(np.int64) + half
    iv = np.floor(v[in_front]).astype(np.int64) + half
    inside = (iu >= 0) & (iu < size) & (iv >= 0) & (iv < size)
    np.minimum.at(buffer, (iu[inside], iv[inside]), depth[in_front][inside])
    buffer = minimum_filter(buffer, size=3, mode="constant", cval=np.inf)

    def behind(points: NDArray[np.float64]) -> NDArray[np.bool_]:
        pu, pv, pdepth = image(points)
        ju = np.floor(pu).astype(np.int64) + half
        jv = np.floor(pv).astype(np.int64) + half
        valid = (ju >= 0) & (ju < size) & (jv >= 0) & (jv < size) & (pdepth > 0.0)
        out = np.zeros(points.shape[0], dtype=bool)
        out[valid] = pdepth[valid] > buffer[ju[valid], jv[valid]] + visibility_margin
        return out

    occluded = behind(samples)
    blocked[free_index] = too_close
    # A stem point behind an observed surface may be inside the wood: the cloud holds only the
    # surface's camera side (see the module docstring for the measurement).
    hidden_points = behind(segment_points.reshape(-1, 3)).reshape(free_index.size, fractions.size)
    stem_hidden = np.zeros(n_samples, dtype=bool)
    stem_hidden[free_index] = (hidden_points & (along >= stem_visibility_skip)[None, :]).any(axis=1)
    return clearance, stem_clearance, occluded, blocked, stem_hidden
