"""The vine of the lab scene: its parameters, their sampling, and where its parts go.

:class:`VineSceneParams` holds every parameter of the scene (the defaults are the paper's
lab) and draws random ones (:meth:`VineSceneParams.sample`, ranges :data:`PARAM_RANGES`);
the helpers below place the stem, the leaves (the occluder among them), the berries and
the other clusters around the grasping arm's gripper, keeping the straight approach's
lines of sight as the parameters ask. :func:`harvest_qp.sim.scene.build_vine_scene` turns
them into the MuJoCo model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.sim.contacts import segment_distances
from harvest_qp.validation import check_field_types

__all__ = ["APPROACH_RADIUS", "HIDDEN_APPROACH_MIN", "HIDDEN_STEM_PROBABILITY", "LEAF_LAYOUT", "PARAM_RANGES",
           "VineSceneParams"]

#: Uniform sampling range (low, high) of every scalar in :class:`VineSceneParams`
#: used by :meth:`VineSceneParams.sample`. Lengths [m], angles [rad], masses [kg],
#: stiffness [N/m] or [N m/rad]; integer fields are drawn inclusively.
PARAM_RANGES: dict[str, tuple[float, float]] = {
    "stem_length": (0.05, 0.07),
    "stem_segments": (3, 5),
    "stem_radius": (0.0025, 0.004),
    "stem_bend": (0.0, 0.6),
    "stem_bend_azimuth": (-np.pi, np.pi),
    "stem_axial_stiffness": (300.0, 600.0),
    "stem_bend_stiffness": (0.01, 0.05),
    "cluster_mass": (0.2, 0.5),
    "berry_count": (30, 45),
    "berry_radius": (0.008, 0.01),
    "cluster_length": (0.12, 0.17),
    "cluster_radius": (0.04, 0.06),
    "branch_yaw": (-0.6, 0.6),
    "branch_pitch": (0.1, 0.6),
    "branch_radius": (0.008, 0.016),
    "branch_length": (0.25, 0.4),
    "leaf_count": (3, 8),
    "canopy_leaves": (6, 20),
    "leaf_size": (0.05, 0.08),
    "occluder_distance": (0.06, 0.1),
    "occluder_coverage": (0.5, 0.75),
    "other_clusters": (0, 3),
}

#: Probability that :meth:`VineSceneParams.sample` hides the stem along the whole approach.
HIDDEN_STEM_PROBABILITY = 0.25

#: Radius of the paper's region of interest around the stem base, r [m]: the approach
#: viewpoint that ``occluder_coverage`` refers to lies this far from the stem base.
APPROACH_RADIUS = 0.35

#: A stem hidden along the whole approach (``occluder_coverage = 1``) stays hidden from every
#: point of the straight approach this far or farther from the stem base [m].
HIDDEN_APPROACH_MIN = 0.3

#: Ranges of the per-leaf random draws (from ``seed``), for every scene:
#: ``distance`` of a free leaf's centre from the stem middle [m], ``size_scale`` of its
#: half-length relative to ``leaf_size``, ``width_ratio`` of its half-width to its
#: half-length, ``tilt`` of a leaf's normal away from its nominal direction [rad]
#: (occluder: facing the approach viewpoint; free leaves: facing away from the stem), and
#: for canopy leaves their
#: position along the cane from its middle (``canopy_along``), below it
#: (``canopy_drop``) and along x from it (``canopy_depth``, negative towards the robot) [m].
LEAF_LAYOUT: dict[str, tuple[float, float]] = {
    "distance": (0.09, 0.22),
    "size_scale": (0.8, 1.2),
    "width_ratio": (0.7, 0.9),
    "tilt": (-0.5, 0.5),
    "occluder_tilt": (-0.25, 0.25),
    "canopy_along": (-0.75, 0.75),
    "canopy_drop": (0.02, 0.25),
    "canopy_depth": (-0.08, 0.04),
}


#: Largest stem stiffnesses that integrate stably at the 2 ms timestep (measured: 3e4 N/m
#: and 10 N m/rad still ran, 1e5 N/m and 20 N m/rad diverged).
MAX_AXIAL_STIFFNESS = 2.0e4
MAX_BEND_STIFFNESS = 10.0

_INT_FIELDS = ("stem_segments", "berry_count", "leaf_count", "canopy_leaves", "other_clusters")
_LEAF_THICKNESS = 0.0015  # half-thickness of a leaf ellipsoid [m]
_PETIOLE_RADIUS = 0.0025
_SIGHT_MARGIN = 0.006  # lines of sight kept clear of free leaves and petioles by this much [m]
_COVERAGE_SAMPLES = 101  # stem points (by arc length) the occluder's coverage is counted on


@dataclass(frozen=True)
class VineSceneParams:
    """Parameters of the vine scene; the defaults are the paper's lab setup.

    Attributes:
        seed: seed of the leaf layout and berry positions (and of nothing else).
        stem_length: stem length from the cluster top to the branch [m] (paper: 0.07).
        stem_segments: number of capsule segments on ball joints.
        stem_radius: stem radius [m].
        stem_bend: total bend angle of the stem's rest shape [rad] (0 = straight).
        stem_bend_azimuth: world yaw towards which the stem base leans [rad] (0 = +x).
        stem_axial_stiffness: axial spring stiffness of the stem [N/m].
        stem_bend_stiffness: bending stiffness of each ball joint [N m/rad].
        cluster_mass: mass of the grape cluster [kg].
        berry_count: number of berries.
        berry_radius: berry radius [m].
        cluster_length: length of the berry part of the cluster [m] (it starts ~3 cm below the grasp).
        cluster_radius: radius of the cluster's widest (top) berry layer [m].
        branch_yaw: yaw of the branch from the stem base into the canopy [rad] (0 = +x).
        branch_pitch: upward slope of the branch [rad].
        branch_radius: branch radius [m].
        branch_length: branch length beyond the stem base [m].
        leaf_count: number of leaves around the stem, the occluding leaf included.
        other_clusters: number of other grape clusters hanging from the cane (static
            obstacles: green stems, purple berries; the paper's lab has none).
        canopy_leaves: number of leaves hanging from the cane behind the cluster (the
            canopy wall the camera sees from its start pose).
        leaf_size: nominal leaf half-length [m].
        occlude_stem: place one leaf between the camera's approach and the stem.
        occluder_distance: distance of the occluding leaf from the stem middle [m] (moved
            up to 6 cm further towards the camera when needed to clear the gripper).
        occluder_coverage: fraction of the stem's length the occluding leaf hides, seen
            from the approach viewpoint (:meth:`VineScene.approach_pose` at
            :data:`APPROACH_RADIUS` from the stem base). Below 1 the leaf hides the lower
            part (cluster side) and leaves the stem base visible; 1 hides the whole stem from
            every point of the straight approach from ``camera_start`` (to the stem base
            and to the cluster) down to :data:`HIDDEN_APPROACH_MIN` from the stem base.
        grasp_offset: distance from the gripper point up to the stem end [m].
        camera_start: camera position [m] the straight approach starts from (the
            occluder and the lines of sight kept clear refer to it); None = the camera
            position at ``HOME_Q``.
        stem_break_force: stem tension beyond which the stem tears [N] (well above the
            paper's 2 f_d = 6 N force limit, so a working force loop never tears it).
    """

    seed: int = 0
    stem_length: float = 0.07
    stem_segments: int = 3
    stem_radius: float = 0.003
    stem_bend: float = 0.3
    stem_bend_azimuth: float = 0.0
    stem_axial_stiffness: float = 400.0
    stem_bend_stiffness: float = 0.02
    cluster_mass: float = 0.3
    berry_count: int = 40
    berry_radius: float = 0.009
    cluster_length: float = 0.15
    cluster_radius: float = 0.05
    branch_yaw: float = 0.0
    branch_pitch: float = 0.35
    branch_radius: float = 0.012
    branch_length: float = 0.3
    leaf_count: int = 5
    canopy_leaves: int = 12
    other_clusters: int = 0
    leaf_size: float = 0.065
    occlude_stem: bool = True
    occluder_distance: float = 0.08
    occluder_coverage: float = 0.7
    grasp_offset: float = 0.015
    camera_start: tuple[float, float, float] | None = None
    stem_break_force: float = 15.0

    def __post_init__(self) -> None:
        check_field_types(self)  # text, None or a list never reaches the range checks
        positive = (
            "stem_length", "stem_radius", "stem_axial_stiffness", "cluster_mass", "berry_radius",
            "cluster_length", "cluster_radius", "branch_radius", "branch_length", "leaf_size",
            "occluder_distance", "stem_break_force",
        )  # fmt: skip
        for name in positive:
            value = getattr(self, name)
            if not isinstance(value, (int, float, np.floating, np.integer)) or not np.isfinite(value) or value <= 0:
                raise InvalidInputError(f"VineSceneParams.{name} must be a finite number > 0, got {value!r}")
        for name in ("stem_bend", "stem_bend_azimuth", "branch_yaw", "branch_pitch", "grasp_offset"):
            if not np.isfinite(getattr(self, name)):
                raise InvalidInputError(f"VineSceneParams.{name} must be finite, got {getattr(self, name)!r}")
        if not isinstance(self.occluder_coverage, (int, float, np.floating)) or not (
            0.0 <= self.occluder_coverage <= 1.0
        ):
            raise InvalidInputError(
                f"VineSceneParams.occluder_coverage must be a fraction in [0, 1], got {self.occluder_coverage!r}"
            )
        if not 0 <= self.stem_bend <= np.pi / 2:
            raise InvalidInputError(f"VineSceneParams.stem_bend must be in [0, pi/2] rad, got {self.stem_bend!r}")
        if not -1.2 <= self.branch_pitch <= 1.2:
            raise InvalidInputError(
                f"VineSceneParams.branch_pitch must be in [-1.2, 1.2] rad, got {self.branch_pitch!r}"
            )
        # Beyond these the stem's light segments make the 2 ms integration diverge.
        if self.stem_axial_stiffness > MAX_AXIAL_STIFFNESS:
            raise InvalidInputError(
                f"VineSceneParams.stem_axial_stiffness must be <= {MAX_AXIAL_STIFFNESS} N/m (stable at "
                f"dt = 2 ms), got {self.stem_axial_stiffness!r}"
            )
        if self.stem_bend_stiffness > MAX_BEND_STIFFNESS:
            raise InvalidInputError(
                f"VineSceneParams.stem_bend_stiffness must be <= {MAX_BEND_STIFFNESS} N m/rad (stable at "
                f"dt = 2 ms), got {self.stem_bend_stiffness!r}"
            )
        if self.stem_bend_stiffness < 0 or not np.isfinite(self.stem_bend_stiffness):
            raise InvalidInputError(
                f"VineSceneParams.stem_bend_stiffness must be >= 0 [N m/rad], got {self.stem_bend_stiffness!r}"
            )
        if not 0 <= self.grasp_offset < self.stem_length + self.cluster_length:
            raise InvalidInputError(
                f"VineSceneParams.grasp_offset must be in [0, {self.stem_length + self.cluster_length}) m, "
                f"got {self.grasp_offset!r}"
            )
        for name, low in (
            ("stem_segments", 1), ("berry_count", 1), ("leaf_count", 0), ("canopy_leaves", 0), ("other_clusters", 0),
        ):  # fmt: skip
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise InvalidInputError(f"VineSceneParams.{name} must be an integer >= {low}, got {value!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InvalidInputError(f"VineSceneParams.seed must be a non-negative integer, got {self.seed!r}")
        if self.stem_radius * 2 >= self.stem_length / self.stem_segments:
            raise InvalidInputError(
                f"stem segments of {self.stem_length / self.stem_segments:.4f} m are too short for a stem "
                f"radius of {self.stem_radius} m; use fewer segments or a thinner stem"
            )
        if self.camera_start is not None:
            try:
                start = np.asarray(self.camera_start, dtype=float)
            except (TypeError, ValueError):
                start = np.full(1, np.nan)  # reported below
            if start.shape != (3,) or not np.all(np.isfinite(start)):
                raise InvalidInputError(
                    f"camera_start must be 3 finite coordinates [m] or None, got {self.camera_start!r}"
                )

    @classmethod
    def sample(
        cls, seed: int, *, hidden_stem_probability: float = HIDDEN_STEM_PROBABILITY, **overrides
    ) -> VineSceneParams:
        """Random parameters: every field of :data:`PARAM_RANGES` uniform in its range.

        With probability ``hidden_stem_probability`` the occluding leaf hides the whole stem
        along the straight approach (``occluder_coverage = 1``) instead of the drawn
        fraction: the stem then stays hidden all the way into the region of interest.

        Args:
            seed: seed of the draws (also used as the layout ``seed``).
            hidden_stem_probability: probability of a stem hidden along the whole approach.
            **overrides: fields to set instead of drawing them.
        """
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InvalidInputError(f"seed must be a non-negative integer, got {seed!r}")
        if not isinstance(hidden_stem_probability, (int, float, np.floating)) or not (
            0.0 <= hidden_stem_probability <= 1.0
        ):
            raise InvalidInputError(
                f"hidden_stem_probability must be a probability in [0, 1], got {hidden_stem_probability!r}"
            )
        rng = np.random.default_rng([int(seed), 0x5EED])
        values: dict[str, float | int] = {}
        for name, (low, high) in PARAM_RANGES.items():
            if name in _INT_FIELDS:
                values[name] = int(rng.integers(int(low), int(high) + 1))
            else:
                values[name] = float(rng.uniform(low, high))
        unknown = set(overrides) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise InvalidInputError(f"unknown VineSceneParams fields: {sorted(unknown)}")
        # Its own stream: the other draws of a seed do not depend on it.
        if np.random.default_rng([int(seed), 0x41DE]).uniform() < hidden_stem_probability:
            values["occluder_coverage"] = 1.0
        values.update(overrides)
        values.setdefault("seed", int(seed))
        return cls(**values)


# --------------------------------------------------------------------------- geometry helpers


def _unit(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return v / np.linalg.norm(v)


def _frame_from_z(z: NDArray[np.float64], hint: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation whose z axis is ``z`` and whose x axis is ``hint`` made orthogonal to it."""
    z = _unit(z)
    x = hint - np.dot(hint, z) * z
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.cross(z, [0.0, 1.0, 0.0])
    x = _unit(x)
    return np.column_stack([x, np.cross(z, x), z])


def _quat(R: NDArray[np.float64]) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R).ravel())
    return q.tolist()


def _rotate(v: NDArray[np.float64], axis: NDArray[np.float64], angle: float) -> NDArray[np.float64]:
    """Rodrigues rotation of ``v`` about the unit ``axis``."""
    return v * np.cos(angle) + np.cross(axis, v) * np.sin(angle) + axis * np.dot(axis, v) * (1 - np.cos(angle))


def _segment_distance(a0, a1, b0, b1) -> float:
    """Distance between segments a0-a1 and b0-b1 (sampled, good to ~1 mm here)."""
    s = np.linspace(0.0, 1.0, 25)
    pa = a0 + s[:, None] * (a1 - a0)
    pb = b0 + s[:, None] * (b1 - b0)
    return float(np.min(np.linalg.norm(pa[:, None] - pb[None], axis=2)))


def _point_segment_distance(p, a, b) -> tuple[float, NDArray[np.float64]]:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
    closest = a + t * ab
    return float(np.linalg.norm(p - closest)), closest


def _stem_samples(stem: NDArray[np.float64], n: int) -> NDArray[np.float64]:
    """``n`` points evenly spaced by arc length along the stem polyline, end to base."""
    seg = np.linalg.norm(np.diff(stem, axis=0), axis=1)
    arc = np.r_[0.0, np.cumsum(seg)]
    at = np.linspace(0.0, arc[-1], n)
    return np.column_stack([np.interp(at, arc, stem[:, k]) for k in range(3)])


def _segment_hits_ellipsoid(
    origins: NDArray[np.float64], targets: NDArray[np.float64], centre: NDArray, R: NDArray, semi: NDArray
) -> NDArray[np.bool_]:
    """Whether each segment origin -> target crosses the ellipsoid (centre, axes R, semi-axes)."""
    o = ((origins - centre) @ R) / semi
    d = ((targets - centre) @ R) / semi - o
    a = np.sum(d * d, axis=1)
    b = 2.0 * np.sum(o * d, axis=1)
    c = np.sum(o * o, axis=1) - 1.0
    disc = b * b - 4.0 * a * c
    root = np.sqrt(np.maximum(disc, 0.0))
    s1 = (-b - root) / (2.0 * a)
    s2 = (-b + root) / (2.0 * a)
    return (disc >= 0.0) & (s2 >= 0.0) & (s1 <= 1.0)


def _petiole_blocks(petiole, origins: NDArray, targets: NDArray) -> bool:
    """Whether a petiole capsule (with a margin) crosses any segment origin -> target."""
    a, b = petiole
    if np.linalg.norm(b - a) <= 1e-3:
        return False
    dist = segment_distances(np.asarray(origins, float), np.asarray(targets, float), a[None], b[None])
    return bool(np.any(dist < _PETIOLE_RADIUS + _SIGHT_MARGIN))


def _approach_views(
    camera_start: NDArray, stem_base: NDArray, cluster_axis: tuple[NDArray, NDArray]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Camera positions along the straight approach, and the viewpoint coverage refers to.

    The approach runs from ``camera_start`` straight towards the stem base (the ROI centre
    once the stem is seen) or towards the cluster centre (the ROI centre before, as in the
    paper); both are sampled down to :data:`HIDDEN_APPROACH_MIN` from their target.
    """
    cluster_centre = 0.5 * (cluster_axis[0] + cluster_axis[1])
    views = []
    for target in (stem_base, cluster_centre):
        span = float(np.linalg.norm(camera_start - target))
        u = _unit(camera_start - target)
        for dist in np.linspace(min(HIDDEN_APPROACH_MIN, span), span, 10):
            views.append(target + dist * u)
    coverage_view = stem_base + APPROACH_RADIUS * _unit(camera_start - stem_base)
    return np.array(views), coverage_view


def _place_occluder(
    p: VineSceneParams,
    rng: np.random.Generator,
    stem: NDArray,
    *,
    coverage_view: NDArray,
    approach_views: NDArray,
    tool_axis: tuple[NDArray, NDArray],
    supports: tuple[tuple[NDArray, NDArray], ...],
) -> _Leaf:
    """The occluding leaf: hides ``occluder_coverage`` of the stem seen from ``coverage_view``.

    The leaf faces the viewpoint (tilted by the seeded draws) ``occluder_distance`` in front
    of the stem middle, its long axis along the stem's image. With full coverage it is
    sized to hide the stem from every approach viewpoint; otherwise it slides along the
    stem's image towards the cluster until exactly that fraction of the stem (sampled by
    arc length) is behind it, by bisection. It moves further from the stem, by 1 cm steps,
    until it clears the grasping tool by 15 mm.
    """
    mid = 0.5 * (stem[0] + stem[-1])
    stem_dir = _unit(stem[-1] - stem[0])
    tilts = rng.uniform(*LEAF_LAYOUT["occluder_tilt"], size=2)
    half_length0 = p.leaf_size * rng.uniform(*LEAF_LAYOUT["size_scale"])
    half_width0 = half_length0 * rng.uniform(*LEAF_LAYOUT["width_ratio"])
    samples = _stem_samples(stem, _COVERAGE_SAMPLES)
    full = p.occluder_coverage >= 1.0
    views = approach_views if full else coverage_view[None]
    margin = 1.5 * p.stem_radius + 0.004
    tool_r = desc.GRASP_TOOL.capsules[0].radius
    best: tuple[float, _Leaf] | None = None
    for extra in np.arange(0.0, 0.0601, 0.01):
        u = _unit(coverage_view - mid)
        side = np.cross(u, stem_dir)
        side = _unit(side) if np.linalg.norm(side) > 1e-6 else _frame_from_z(u, stem_dir)[:, 1]
        normal = _rotate(_rotate(u, side, tilts[0]), stem_dir, tilts[1])
        R = _frame_from_z(normal, stem_dir)  # x: along the stem's image, z: the leaf's normal
        centre0 = mid + (p.occluder_distance + extra) * u
        # Where the lines of sight to the stem cross the leaf's plane, in the leaf frame.
        origin = np.repeat(views, len(samples), axis=0)
        target = np.tile(samples, (len(views), 1))
        ray = target - origin
        t = ((centre0 - origin) @ normal) / (ray @ normal)
        local = (origin + t[:, None] * ray - centre0) @ R
        lo, hi = local.min(axis=0), local.max(axis=0)
        half_x, half_y = 0.5 * (hi[0] - lo[0]) + margin, 0.5 * (hi[1] - lo[1]) + margin
        # An ellipse with semi-axes sqrt(2) times a rectangle's half-sides contains it.
        semi = np.array(
            [max(half_length0, np.sqrt(2) * half_x), max(half_width0, np.sqrt(2) * half_y), _LEAF_THICKNESS]
        )
        centred = centre0 + 0.5 * (lo[0] + hi[0]) * R[:, 0] + 0.5 * (lo[1] + hi[1]) * R[:, 1]
        if full:
            centre = centred
        else:
            # Slide towards the cluster end of the stem's image: the base emerges first.
            towards_end = np.sign(local[0, 0] - local[-1, 0]) or 1.0
            origin1 = np.repeat(coverage_view[None], len(samples), axis=0)

            def coverage(shift: float, _c=centred, _R=R, _semi=semi, _o=origin1, _e=towards_end) -> float:
                return float(np.mean(_segment_hits_ellipsoid(_o, samples, _c + _e * shift * _R[:, 0], _R, _semi)))

            low, high = 0.0, semi[0] + (hi[0] - lo[0]) + 0.01
            for _ in range(40):
                half = 0.5 * (low + high)
                low, high = (half, high) if coverage(half) >= p.occluder_coverage else (low, half)
            shift = (
                low if abs(coverage(low) - p.occluder_coverage) <= abs(coverage(high) - p.occluder_coverage) else high
            )
            centre = centred + towards_end * shift * R[:, 0]
        # Clearance to the grasping tool, from points on the leaf's rim and centre.
        phi = np.linspace(0.0, 2 * np.pi, 48, endpoint=False)
        rim = centre + np.outer(semi[0] * np.cos(phi), R[:, 0]) + np.outer(semi[1] * np.sin(phi), R[:, 1])
        rim = np.vstack([rim, centre])
        clearance = min(_point_segment_distance(x, *tool_axis)[0] for x in rim) - tool_r
        leaf = _Leaf(
            centre, R, float(semi[0]), float(semi[1]), _occluder_petiole(centre, R, semi, supports, views, samples)
        )
        if best is None or clearance > best[0]:
            best = (clearance, leaf)
        if clearance >= 0.015:
            break
    assert best is not None
    return best[1]


def _occluder_petiole(centre, R, semi, supports, views, samples) -> tuple[NDArray, NDArray]:
    """A petiole from the occluder's rim to the branch or cane that crosses no line of sight.

    Tries the rim points at 8 angles against the nearest point of each support; a leaf with
    no clear petiole gets none (a zero-length one).
    """
    origin = np.repeat(views, len(samples), axis=0)
    target = np.tile(samples, (len(views), 1))
    for angle in np.linspace(0.0, 2 * np.pi, 8, endpoint=False):
        base = centre + 0.9 * (semi[0] * np.cos(angle) * R[:, 0] + semi[1] * np.sin(angle) * R[:, 1])
        for support in supports:
            _, on_support = _point_segment_distance(base, *support)
            if not _petiole_blocks((base, on_support), origin, target):
                return base, on_support
    return centre, centre


# --------------------------------------------------------------------------- builder


def _robot_home(spec: mujoco.MjSpec, home_q: NDArray[np.float64]) -> dict[str, Any]:
    """Poses of the task frames, the robot's collision capsules and the joint-space inertia diagonal at ``home_q``."""
    model = spec.compile()
    data = mujoco.MjData(model)
    data.qpos[:12] = home_q
    mujoco.mj_forward(model, data)
    out: dict[str, NDArray[np.float64]] = {}
    for name in ("gripper", "camera", "ft_sensor"):
        sid = model.site(name).id
        T = np.eye(4)
        T[:3, :3] = data.site_xmat[sid].reshape(3, 3)
        T[:3, 3] = data.site_xpos[sid]
        out[name] = T
    # The robot's collision capsules at home (world ends [m], radius [m]): no leaf may touch them at
    # the start (a sampled leaf once lay 0.6 mm inside the grasping arm's forearm from t = 0).
    capsules = []
    for g in np.flatnonzero((model.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE) & (model.geom_contype != 0)):
        axis = data.geom_xmat[g].reshape(3, 3)[:, 2] * model.geom_size[g, 1]
        capsules.append((data.geom_xpos[g] - axis, data.geom_xpos[g] + axis, float(model.geom_size[g, 0])))
    out["robot_capsules"] = capsules
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)  # MuJoCo 4.0 signature (takes MjData)
    out["inertia"] = np.diag(M)[:12].copy()
    return out


def _stem_polyline(p: VineSceneParams, stem_end: NDArray, up: NDArray) -> NDArray[np.float64]:
    """Rest shape of the stem from its end (cluster top) to its base: an arc of angle stem_bend."""
    lean = np.array([np.cos(p.stem_bend_azimuth), np.sin(p.stem_bend_azimuth), 0.0])
    lean = lean - np.dot(lean, up) * up
    lean = _unit(lean) if np.linalg.norm(lean) > 1e-9 else _frame_from_z(up, np.array([1.0, 0, 0]))[:, 0]
    axis = _unit(np.cross(up, lean))
    n = p.stem_segments
    seg = p.stem_length / n
    pts = [stem_end]
    for i in range(n):
        # The tangent turns from "up" towards "lean" along the stem, bottom to top.
        t = _rotate(up, axis, p.stem_bend * (i + 0.5) / n)
        pts.append(pts[-1] + seg * t)
    return np.array(pts)


def _berry_positions(p: VineSceneParams, rng: np.random.Generator) -> NDArray[np.float64]:
    """Berry centres in the cluster frame (z down the cluster): an inverted cone below the grasp.

    The berries fill ``cluster_length`` below the grasped part of the rachis, from
    ``cluster_radius`` at the top tapering to 30 % at the tip, by random sequential
    placement; the allowed overlap grows in stages when the cluster is crowded.
    """
    r = p.berry_radius
    top = p.grasp_offset + 0.03 + r  # leave the grasped part of the rachis free
    bottom = top + max(p.cluster_length - 2 * r, 2 * r)
    centres: list[NDArray] = []
    for gap in (1.8, 1.6, 1.4, 1.2, 1.0):  # centre distance / r: slight overlap, as in a real bunch
        for _attempt in range(3000):
            if len(centres) == p.berry_count:
                return np.array(centres)
            h = rng.uniform(top, bottom)
            envelope = max(p.cluster_radius * (1.0 - 0.7 * (h - top) / (bottom - top)) - r, 0.0)
            rho = envelope * np.sqrt(rng.uniform())
            phi = rng.uniform(0, 2 * np.pi)
            c = np.array([rho * np.cos(phi), rho * np.sin(phi), h])
            if not centres or np.min(np.linalg.norm(np.array(centres) - c, axis=1)) >= gap * r:
                centres.append(c)
    if len(centres) < p.berry_count:
        raise ModelError(
            f"cannot fit {p.berry_count} berries of radius {r} m into a cluster of length "
            f"{p.cluster_length} m and radius {p.cluster_radius} m"
        )
    return np.array(centres)


@dataclass
class _Leaf:
    centre: NDArray[np.float64]
    rotation: NDArray[np.float64]  # columns: long axis, short axis, normal
    half_length: float
    half_width: float
    petiole: tuple[NDArray[np.float64], NDArray[np.float64]]


def _leaf_layout(
    p: VineSceneParams,
    rng: np.random.Generator,
    *,
    stem: NDArray,
    cluster_axis: tuple[NDArray, NDArray],
    tool_axis: tuple[NDArray, NDArray],
    branch: tuple[NDArray, NDArray],
    cane: tuple[NDArray, NDArray],
    coverage_view: NDArray,
    approach_views: NDArray,
    robot_capsules: Sequence[tuple[NDArray, NDArray, float]] = (),
) -> list[_Leaf]:
    """Leaf poses: an occluder between the approach and the stem, then free leaves around it.

    No free or canopy leaf may cross a line of sight from the straight approach
    (``approach_views``) to the stem: only the occluder hides it, by ``occluder_coverage``.
    """
    mid = 0.5 * (stem[0] + stem[-1])
    leaves: list[_Leaf] = []
    sight_targets = _stem_samples(stem, 13)
    sight_from = np.repeat(approach_views, len(sight_targets), axis=0)
    sight_to = np.tile(sight_targets, (len(approach_views), 1))

    def petiole_for(centre, R, half_length, support=branch):
        _, on_branch = _point_segment_distance(centre, *support)
        towards = on_branch - centre
        in_plane = towards - np.dot(towards, R[:, 2]) * R[:, 2]
        base = centre + half_length * 0.9 * _unit(in_plane) if np.linalg.norm(in_plane) > 1e-9 else centre
        return base, on_branch

    def clear(centre, R, half_length, petiole) -> bool:
        reach = half_length + 0.01
        for a, b in zip(stem[:-1], stem[1:], strict=True):
            if _point_segment_distance(centre, a, b)[0] < reach + p.stem_radius:
                return False
            if _segment_distance(petiole[0], petiole[1], a, b) < 0.012 + p.stem_radius:
                return False
        if _point_segment_distance(centre, *cluster_axis)[0] < reach + p.cluster_radius:
            return False
        if _segment_distance(petiole[0], petiole[1], *cluster_axis) < p.cluster_radius + 0.01:
            return False
        if _point_segment_distance(centre, *tool_axis)[0] < reach + 0.06:
            return False
        if _segment_distance(petiole[0], petiole[1], *tool_axis) < 0.06:
            return False
        for a, b, radius in robot_capsules:  # nothing touches the arms at the start
            if _point_segment_distance(centre, a, b)[0] < reach + radius:
                return False
            if _segment_distance(petiole[0], petiole[1], a, b) < radius + 0.01:
                return False
        semi = np.array([half_length, half_length, _LEAF_THICKNESS]) + _SIGHT_MARGIN
        if np.any(_segment_hits_ellipsoid(sight_from, sight_to, centre, R, semi)):
            return False
        return not _petiole_blocks(petiole, sight_from, sight_to)

    if p.occlude_stem and p.leaf_count > 0:
        leaves.append(
            _place_occluder(
                p, rng, stem, coverage_view=coverage_view, approach_views=approach_views, tool_axis=tool_axis,
                supports=(branch, cane),
            )
        )  # fmt: skip
    free = p.leaf_count - len(leaves)
    for _ in range(free):
        for _attempt in range(200):
            d = rng.normal(size=3)
            d = _unit(d)
            centre = mid + rng.uniform(*LEAF_LAYOUT["distance"]) * d
            normal = _unit(d + rng.uniform(*LEAF_LAYOUT["tilt"]) * _unit(rng.normal(size=3)))
            R = _frame_from_z(normal, _unit(rng.normal(size=3)))
            half_length = p.leaf_size * rng.uniform(*LEAF_LAYOUT["size_scale"])
            half_width = half_length * rng.uniform(*LEAF_LAYOUT["width_ratio"])
            petiole = petiole_for(centre, R, half_length)
            if clear(centre, R, half_length, petiole):
                leaves.append(_Leaf(centre, R, half_length, half_width, petiole))
                break

    cane_mid = 0.5 * (cane[0] + cane[1])
    cane_dir = _unit(cane[1] - cane[0])
    for _ in range(p.canopy_leaves):
        for _attempt in range(50):
            centre = (
                cane_mid
                + rng.uniform(*LEAF_LAYOUT["canopy_along"]) * cane_dir
                - rng.uniform(*LEAF_LAYOUT["canopy_drop"]) * np.array([0.0, 0.0, 1.0])
                + rng.uniform(*LEAF_LAYOUT["canopy_depth"]) * np.array([1.0, 0.0, 0.0])
            )
            normal = _unit(np.array([-1.0, 0.0, 0.0]) + rng.uniform(*LEAF_LAYOUT["tilt"]) * _unit(rng.normal(size=3)))
            R = _frame_from_z(normal, _unit(rng.normal(size=3)))
            half_length = p.leaf_size * rng.uniform(*LEAF_LAYOUT["size_scale"])
            half_width = half_length * rng.uniform(*LEAF_LAYOUT["width_ratio"])
            petiole = petiole_for(centre, R, half_length, cane)
            if clear(centre, R, half_length, petiole):
                leaves.append(_Leaf(centre, R, half_length, half_width, petiole))
                break
    return leaves


@dataclass
class _OtherCluster:
    stem: tuple[NDArray[np.float64], NDArray[np.float64]]  # from the cane down to the cluster top
    berries: NDArray[np.float64]  # (n, 3) world centres
    berry_radius: float


def _other_clusters(
    p: VineSceneParams,
    rng: np.random.Generator,
    *,
    cane: tuple[NDArray, NDArray],
    keep_clear: list[tuple[NDArray, NDArray, float]],
    sight: tuple[NDArray, NDArray],
) -> list[_OtherCluster]:
    """Clusters hanging from the cane, clear of ``keep_clear`` capsules and of the lines of sight."""
    cane_mid = 0.5 * (cane[0] + cane[1])
    cane_dir = _unit(cane[1] - cane[0])
    down = np.array([0.0, 0.0, -1.0])
    out: list[_OtherCluster] = []
    for _ in range(p.other_clusters):
        for _attempt in range(100):
            along = rng.choice([-1.0, 1.0]) * rng.uniform(0.15, 0.65)
            top = cane_mid + along * cane_dir
            stem_len = rng.uniform(0.03, 0.07)
            length = rng.uniform(0.09, 0.15)
            radius = rng.uniform(0.035, 0.05)
            r = rng.uniform(0.008, 0.01)
            count = int(rng.integers(15, 31))
            start = top + stem_len * down
            axis = (start, start + length * down)
            ok = all(_segment_distance(axis[0], axis[1], a, b) > radius + rad + 0.03 for a, b, rad in keep_clear)
            ok = ok and not np.any(segment_distances(sight[0], sight[1], axis[0][None], axis[1][None]) < radius + 0.01)
            if not ok:
                continue
            centres = []
            for _k in range(3000):
                if len(centres) == count:
                    break
                h = rng.uniform(r, length - r)
                envelope = max(radius * (1.0 - 0.7 * h / length) - r, 0.0)
                rho, phi = envelope * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
                c = start + h * down + rho * np.array([np.cos(phi), np.sin(phi), 0.0])
                if not centres or np.min(np.linalg.norm(np.array(centres) - c, axis=1)) >= 1.6 * r:
                    centres.append(c)
            out.append(_OtherCluster((top, start), np.array(centres), r))
            break
    return out
