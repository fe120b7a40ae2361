"""Fuzz and crossing scenarios for the QP core, measured with an independent geometry.

Run by hand::

    python -m benchmarks.bench_fuzz                 # 20,000 fuzz states, 50 crossing runs, 2 processes
    python -m benchmarks.bench_fuzz --fuzz 2000 --crossing 10 --ticks 1000 --jobs 1

The full size took 415 s wall with 2 processes on the shared 2-core machine (load ~6).
Progress is printed per job (500 fuzz states of one category, or one crossing run); each
job has its own seed, so the figures do not depend on ``--jobs``.

It prints, for the fuzz states (collision-free, inside the joint limits): how many ticks
fell back to the safe stop, the worst per-tick speed change (overall, and on ticks where
neither a relaxation nor a position-limit box conflict allowed more than a_max dt), the
ticks that relaxed the acceleration limit (with a collision row binding or not), by how
much, and whether the command stayed within the widened box; the closest pair after each
step. For the crossing runs (two FramePoseTasks swapping tool positions among random
obstacle spheres): the fallback and relaxed ticks, the worst acceleration and the
smallest pair distance, all distances measured with pinocchio frame placements and coal
capsules (not with the controller's own kernel).

The scenario generators are imported by ``tests/core/test_qp_fuzz.py`` at a small size.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np

from harvest_qp import Configuration, TaskController
from harvest_qp.limits import CollisionAvoidance
from harvest_qp.robot import description as desc
from harvest_qp.robot.description import HOME_Q
from harvest_qp.tasks import DampingTask, FramePoseTask, FrameTwistTask, PostureTask

DT = 0.002
A_MAX = 10.0

FUZZ_CATEGORIES = (
    "uniform",
    "near_limits",
    "singular_wrist",
    "stretched_elbow",
    "arms_close",
    "near_obstacles",
    "combination",
    "continuation",
)


# ----------------------------------------------------------------------------- independent geometry
class CoalGeometry:
    """Capsule distances from pinocchio frame placements and coal (independent of the kernels).

    Each robot capsule is placed with ``data.oMf`` of its link frame (pinocchio's own forward
    kinematics) and measured with ``coal.distance``; obstacles are coal spheres.
    :meth:`min_distance` skips only pairs whose bounding spheres (from the same placements) are
    farther apart than the closest pair already measured, so it returns the exact minimum at a
    fraction of the cost of measuring every pair (the oracle runs every tick of a crossing run).
    """

    def __init__(self, configuration: Configuration, collision: CollisionAvoidance, environment=()) -> None:
        import coal
        import pinocchio as pin

        self._coal, self._pin = coal, pin
        self.configuration = configuration
        self.collision = collision
        self.bodies = {b.name: b for b in desc.collision_bodies()}
        self._frame = {name: configuration.frame_id(b.link) for name, b in self.bodies.items()}
        self._data = configuration.model.createData()
        self._shapes = {}
        self._local = {}
        self._bound = {}  # bounding-sphere radius [m] (half length + radius)
        for name, b in self.bodies.items():
            self._shapes[name], self._local[name] = self._capsule(b.capsule.p0, b.capsule.p1, b.capsule.radius)
            half = 0.5 * float(np.linalg.norm(np.asarray(b.capsule.p1, float) - np.asarray(b.capsule.p0, float)))
            self._bound[name] = half + float(b.capsule.radius)
        self.obstacles: list[tuple[np.ndarray, float]] = []
        self._obstacle_objects: list = []
        self.environment = {}
        for cap in environment:  # world-fixed capsules (frame None)
            shape, local = self._capsule(cap.p0, cap.p1, cap.radius)
            self.environment[cap.name] = (shape, coal.Transform3s(local.rotation, local.translation))
            half = 0.5 * float(np.linalg.norm(np.asarray(cap.p1, float) - np.asarray(cap.p0, float)))
            self._bound[cap.name] = half + float(cap.radius)
        self._pairs_key = None

    def _capsule(self, p0, p1, radius):
        coal, pin = self._coal, self._pin
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        length = float(np.linalg.norm(p1 - p0))
        shape = coal.Capsule(radius, length) if length > 1e-12 else coal.Sphere(radius)
        z = (p1 - p0) / length if length > 1e-12 else np.array([0.0, 0.0, 1.0])
        x = np.cross(z, [1.0, 0.0, 0.0])
        if np.linalg.norm(x) < 1e-6:
            x = np.cross(z, [0.0, 1.0, 0.0])
        x /= np.linalg.norm(x)
        return shape, pin.SE3(np.column_stack([x, np.cross(z, x), z]), 0.5 * (p0 + p1))

    def set_obstacles(self, centres: np.ndarray, radii: np.ndarray) -> None:
        coal = self._coal
        self.obstacles = [(np.asarray(c, float), float(r)) for c, r in zip(centres, radii)]
        self._obstacle_objects = [(coal.Sphere(r), coal.Transform3s(np.eye(3), c)) for c, r in self.obstacles]

    def _placements(self, q: np.ndarray) -> dict:
        pin = self._pin
        model, data = self.configuration.model, self._data
        pin.framesForwardKinematics(model, data, q)
        return {name: data.oMf[self._frame[name]] * self._local[name] for name in self.bodies}

    def _objects(self, q: np.ndarray):
        """Names, (shape, coal transform) per name, centres [m] and bounding radii [m] of every object."""
        coal = self._coal
        names, objects, centres, bounds = [], [], [], []
        for name, P in self._placements(q).items():
            names.append(name)
            objects.append((self._shapes[name], coal.Transform3s(P.rotation, P.translation)))
            centres.append(P.translation)
            bounds.append(self._bound[name])
        for k, (c, r) in enumerate(self.obstacles):
            names.append(f"obstacle_{k}")
            objects.append(self._obstacle_objects[k])
            centres.append(c)
            bounds.append(r)
        for name, (shape, T) in self.environment.items():
            names.append(name)
            objects.append((shape, T))
            centres.append(np.asarray(T.getTranslation()))
            bounds.append(self._bound[name])
        return names, objects, np.array(centres), np.array(bounds)

    def _pairs(self, names: list[str], pairs=None):
        """Object indices ``(ia, ib)`` of the candidate pairs (or of ``pairs``) present among ``names``."""
        key = (id(self.collision), self.collision.num_candidate_pairs, tuple(names)) if pairs is None else None
        if key is None or key != self._pairs_key:
            index = {name: i for i, name in enumerate(names)}
            wanted = self.collision.pair_names() if pairs is None else pairs
            kept = [(index[a], index[b]) for a, b in wanted if a in index and b in index]
            ia = np.array([a for a, _ in kept], dtype=int)
            ib = np.array([b for _, b in kept], dtype=int)
            if key is None:
                return ia, ib
            self._pairs_key, self._pair_index = key, (ia, ib)
        return self._pair_index

    def _distance(self, objects, a: int, b: int) -> float:
        coal = self._coal
        shape_a, T_a = objects[a]
        shape_b, T_b = objects[b]
        # A fresh result per call: coal keeps a past penetration in a reused DistanceResult.
        return float(coal.distance(shape_a, T_a, shape_b, T_b, coal.DistanceRequest(), coal.DistanceResult()))

    def pair_distances(self, q: np.ndarray, pairs=None) -> dict[tuple[str, str], float]:
        """Surface distance [m] of every candidate pair of the controller (or of ``pairs``), by names."""
        names, objects, _, _ = self._objects(q)
        ia, ib = self._pairs(names, pairs)
        return {(names[a], names[b]): self._distance(objects, a, b) for a, b in zip(ia, ib)}

    def min_distance(self, q: np.ndarray) -> tuple[float, tuple[str, str]]:
        """Smallest surface distance [m] over the candidate pairs, and that pair (exact, see the class)."""
        names, objects, centres, bounds = self._objects(q)
        ia, ib = self._pairs(names)
        lower = np.linalg.norm(centres[ia] - centres[ib], axis=1) - bounds[ia] - bounds[ib]  # <= true distance
        best, best_k = np.inf, -1
        for k in np.argsort(lower):
            if lower[k] >= best:
                break
            d = self._distance(objects, ia[k], ib[k])
            if d < best:
                best, best_k = d, k
        return best, (names[ia[best_k]], names[ib[best_k]])


# ----------------------------------------------------------------------------- crossing runs
@dataclass
class CrossingResult:
    seed: int
    ticks: int
    fallbacks: int
    relaxed: int
    min_distance: float
    min_pair: tuple[str, str]
    moved: float
    worst_accel: float  # largest |qdot_k - qdot_{k-1}| / dt [rad/s^2]


def crossing_setup(seed: int, *, n_obstacles: int = 20, safety: float = 0.02, influence: float = 0.12):
    """Two FramePoseTasks swap tool positions (gain 5) among random obstacle spheres (damper gain 0.5)."""
    rng = np.random.default_rng(seed)
    configuration = Configuration.dual_ur5e(q=HOME_Q.copy())
    collision = CollisionAvoidance.dual_ur5e(
        configuration, safety_distance=safety, influence_distance=influence, gain=0.5
    )
    p_cam, p_grasp = configuration.frame_pose("camera"), configuration.frame_pose("gripper")
    # Obstacles around the workspace, clear of the start pose by 3 d_s.
    centres, radii = [], []
    while len(centres) < n_obstacles:
        c = rng.uniform([0.15, -0.5, 0.7], [0.9, 0.8, 1.5])
        r = rng.uniform(0.01, 0.05)
        collision.set_obstacle_spheres(np.array([c]), np.array([r]))
        obstacle = [k for k, (_, b) in enumerate(collision.pair_names()) if b.startswith("obstacle")]
        if collision.distances(configuration)[obstacle].min() > 3 * safety:
            centres.append(c)
            radii.append(r)
    centres, radii = np.array(centres), np.array(radii)
    collision.set_obstacle_spheres(centres, radii)
    cam = FramePoseTask("camera", gain=5.0, weight=[1, 1, 1, 0.1, 0.1, 0.1])
    grasp = FramePoseTask("gripper", gain=5.0, weight=[1, 1, 1, 0.1, 0.1, 0.1])
    jitter = rng.normal(0.0, 0.05, (2, 3))
    cam.set_target(p_grasp.translation + jitter[0], p_cam.rotation)
    grasp.set_target(p_cam.translation + jitter[1], p_grasp.rotation)
    tasks = [cam, grasp, PostureTask(HOME_Q, weight=1e-3), DampingTask(12, weight=1e-4)]
    controller = TaskController(configuration, tasks, [collision], dt=DT, max_acceleration=A_MAX)
    return configuration, collision, controller, (centres, radii)


def run_crossing(seed: int, ticks: int = 2000, *, check_every: int = 1, **kwargs) -> CrossingResult:
    configuration, collision, controller, (centres, radii) = crossing_setup(seed, **kwargs)
    geometry = CoalGeometry(configuration, collision)
    geometry.set_obstacles(centres, radii)
    q = HOME_Q.copy()
    start = configuration.frame_position("camera").copy()
    fallbacks = relaxed = 0
    best, best_pair, moved, worst_accel = np.inf, ("", ""), 0.0, 0.0
    previous = np.zeros(12)
    for k in range(ticks):
        step = controller.step(q)
        fallbacks += not step.ok
        relaxed += "relaxed" in step.status
        worst_accel = max(worst_accel, float(np.max(np.abs(step.qdot - previous))) / DT)
        previous = step.qdot
        q = q + step.qdot * DT
        if k % check_every == 0 or k == ticks - 1:
            d, pair = geometry.min_distance(q)
            if d < best:
                best, best_pair = d, pair
            configuration.update(q)
            moved = max(moved, float(np.linalg.norm(configuration.frame_position("camera") - start)))
    return CrossingResult(seed, ticks, fallbacks, relaxed, best, best_pair, moved, worst_accel)


# ----------------------------------------------------------------------------- fuzz states
def _random_state(configuration: Configuration, category: str, rng: np.random.Generator) -> np.ndarray:
    lo, hi = configuration.lower_limits, configuration.upper_limits
    q = HOME_Q + rng.normal(0.0, 0.6, 12)
    if category == "near_limits" or (category == "combination" and rng.random() < 0.5):
        joints = rng.choice(12, size=rng.integers(1, 4 if category == "near_limits" else 2), replace=False)
        side = rng.random(joints.size) < 0.5
        margin = rng.uniform(0.0, 0.02, joints.size)
        q[joints] = np.where(side, lo[joints] + margin, hi[joints] - margin)
    if category == "singular_wrist" or (category == "combination" and rng.random() < 0.5):
        for arm in (0, 6):
            if rng.random() < 0.7:
                q[arm + 4] = rng.choice([0.0, np.pi, -np.pi]) + rng.normal(0, 1e-4)
    if category == "stretched_elbow":
        for arm in (0, 6):
            q[arm + 2] = rng.normal(0.0, 1e-3)
    return np.clip(q, lo, hi)


def fuzz_states(n: int, seed: int = 0, *, categories=FUZZ_CATEGORIES):
    """Yield ``(category, configuration, controller, q, tasks)`` for collision-free states inside the limits.

    One controller per category is reused (as in a loop); each state sets new references,
    weights (1e-4..1e3) and, for "continuation", a non-zero previous command.
    """
    rng = np.random.default_rng(seed)
    setups = {}
    for cat in categories:
        configuration = Configuration.dual_ur5e(q=HOME_Q.copy())
        collision = CollisionAvoidance.dual_ur5e(configuration, safety_distance=0.01, influence_distance=0.10)
        cam = FrameTwistTask("camera")
        grasp = FrameTwistTask("gripper")
        posture = PostureTask(HOME_Q, weight=1e-3)
        tasks = [cam, grasp, posture, DampingTask(12, weight=1e-6)]
        controller = TaskController(configuration, tasks, [collision], dt=DT, max_acceleration=A_MAX)
        setups[cat] = (configuration, collision, controller, tasks)
    vmax = Configuration.dual_ur5e().velocity_limits
    i = 0
    while i < n:
        cat = categories[i % len(categories)]
        configuration, collision, controller, tasks = setups[cat]
        q = _random_state(configuration, cat, rng)
        if cat in ("arms_close", "combination"):
            pulled = _pull_arms_together(configuration, collision, q, rng)
            if pulled is None and cat == "arms_close":
                continue
            q = q if pulled is None else pulled  # combination: near limits/singular may forbid it
        if cat in ("near_obstacles", "combination"):
            _obstacles_near(configuration, collision, q, rng)
        else:
            collision.set_obstacle_spheres(np.zeros((0, 3)), np.zeros(0))
        configuration.update(q)
        if collision.distances(configuration).min() <= collision.safety_distance * 1.05:
            continue  # not collision-free: another test covers penetrating states
        cam, grasp, posture = tasks[:3]
        scale = 10.0 ** rng.uniform(-3, 3)  # references up to 1e3
        cam.set_reference(rng.normal(0, 1, 6) * scale)
        grasp.set_reference(rng.normal(0, 1, 6) * 10.0 ** rng.uniform(-3, 3))
        cam.weight = np.full(6, 10.0 ** rng.uniform(-4, 3))
        grasp.weight = 10.0 ** rng.uniform(-4, 3, 6)
        posture.weight = np.full(12, 10.0 ** rng.uniform(-4, 0))
        if cat in ("continuation", "combination"):
            controller.previous_qdot = rng.uniform(-0.5, 0.5, 12) * vmax
            # a moving arm still inside its position limits after this tick
            controller.previous_qdot = np.clip(
                controller.previous_qdot,
                -np.sqrt(2 * A_MAX * np.maximum(q - configuration.lower_limits, 0)),
                np.sqrt(2 * A_MAX * np.maximum(configuration.upper_limits - q, 0)),
            )
        else:
            controller.previous_qdot = np.zeros(12)
        i += 1
        yield cat, configuration, controller, q, tasks


_ARM_PAIRS: dict = {}


def _arm_pair_mask(collision) -> np.ndarray:
    """Which candidate pairs join a camera-arm body to a grasping-arm body (cached per pair list)."""
    key = (id(collision), collision.num_candidate_pairs)
    if key not in _ARM_PAIRS:
        names = collision.pair_names()
        _ARM_PAIRS[key] = np.array([{a.split("_")[0], b.split("_")[0]} == {"cam", "grasp"} for a, b in names])
    return _ARM_PAIRS[key]


def _pull_arms_together(configuration, collision, q, rng):
    """Bisect between q and a configuration with the tools swapped until arms are 1.5-4 cm apart."""
    q_far = q.copy()
    q_near = q.copy()
    q_near[:6], q_near[6:] = q[:6] + rng.normal(0, 0.5, 6), q[6:] + rng.normal(0, 0.5, 6)
    q_near[0] += 1.2
    q_near[6] -= 1.2
    q_near = np.clip(q_near, configuration.lower_limits, configuration.upper_limits)
    arm_pair = _arm_pair_mask(collision)

    def arm_distance(t: float) -> float:
        configuration.update(q_far + t * (q_near - q_far))
        return float(collision.distances(configuration)[arm_pair].min())

    # The bisection keeps d(t_lo) >= 4 cm > d(t_hi): it can only succeed from such a bracket.
    d_far = arm_distance(0.0)
    if 0.015 < d_far < 0.04:
        return q_far
    if d_far < 0.04 or arm_distance(1.0) >= 0.04:
        return None
    lo_t, hi_t = 0.0, 1.0
    for _ in range(25):
        t = 0.5 * (lo_t + hi_t)
        d = arm_distance(t)
        if d < 0.04:
            hi_t = t
        else:
            lo_t = t
        if 0.015 < d < 0.04:
            return configuration.q.copy()
    return None


def _obstacles_near(configuration, collision, q, rng, count: int = 10):
    """``count`` obstacle spheres, each 1.5-5 cm from a random robot capsule and clear of all others."""
    from harvest_qp.collision import kernels

    configuration.update(q)
    collision.tree.update(q)
    kernels.capsule_world(
        collision.cap_joint, collision.cap_p0, collision.cap_p1, collision.tree.joint_R, collision.tree.joint_p,
        collision._w0, collision._w1,
    )
    w0, w1 = collision._w0.copy(), collision._w1.copy()
    moving = collision._moving
    centres, radii = [], []
    for _ in range(4 * count):
        if len(centres) == count:
            break
        c = rng.choice(moving)
        p = w0[c] + rng.random() * (w1[c] - w0[c])
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        r = rng.uniform(0.01, 0.04)
        centre = p + direction * (collision.cap_radius[c] + r + rng.uniform(0.015, 0.05))
        # Clear of every moving capsule (segment distance minus both radii), in numpy.
        seg = w1[moving] - w0[moving]
        length2 = np.maximum(np.einsum("ij,ij->i", seg, seg), 1e-12)
        t = np.clip(np.einsum("ij,ij->i", centre - w0[moving], seg) / length2, 0, 1)
        gaps = np.linalg.norm(w0[moving] + t[:, None] * seg - centre, axis=1) - collision.cap_radius[moving] - r
        if gaps.min() > 0.015:
            centres.append(centre)
            radii.append(r)
    collision.set_obstacle_spheres(np.array(centres).reshape(-1, 3), np.array(radii))


@dataclass
class FuzzResult:
    """What one batch of fuzz states did (merge batches with :meth:`merge`)."""

    states: int = 0
    fallbacks: int = 0
    fallback_reasons: dict = field(default_factory=dict)
    relaxed: int = 0
    relaxed_by_rows: int = 0  # relaxed ticks with a collision row binding at the command
    worst_accel: float = 0.0  # [rad/s^2] largest |qdot - prev| / dt over every tick
    worst_accel_unforced: float = 0.0  # [rad/s^2] the same, ticks neither relaxed nor with a box conflict
    worst_excess_plain: float = -np.inf  # [rad/s] change beyond a_max dt, joints without a position-box conflict
    worst_excess_relaxed: float = -np.inf  # [rad/s] change beyond a_max dt + the reported least relaxation
    worst_relaxation: float = 0.0  # [rad/s] largest box widening reported
    conflict_ticks: int = 0  # ticks on which a position-limit box overrode the acceleration box
    min_distance_after: float = np.inf  # [m] coal, after each step
    seconds: float = 0.0

    def merge(self, other: FuzzResult) -> FuzzResult:
        reasons = dict(self.fallback_reasons)
        for key, value in other.fallback_reasons.items():
            reasons[key] = reasons.get(key, 0) + value
        return FuzzResult(
            self.states + other.states, self.fallbacks + other.fallbacks, reasons,
            self.relaxed + other.relaxed, self.relaxed_by_rows + other.relaxed_by_rows,
            max(self.worst_accel, other.worst_accel), max(self.worst_accel_unforced, other.worst_accel_unforced),
            max(self.worst_excess_plain, other.worst_excess_plain),
            max(self.worst_excess_relaxed, other.worst_excess_relaxed),
            max(self.worst_relaxation, other.worst_relaxation), self.conflict_ticks + other.conflict_ticks,
            min(self.min_distance_after, other.min_distance_after), self.seconds + other.seconds,
        )


def run_fuzz_batch(n: int, seed: int = 0, *, categories=FUZZ_CATEGORIES) -> FuzzResult:
    """``n`` fuzz states of ``categories``: one controller step each, judged by hand and by coal."""
    t0 = time.perf_counter()
    r = FuzzResult()
    geometries = {}
    for cat, configuration, controller, q, _ in fuzz_states(n, seed, categories=categories):
        r.states += 1
        collision = controller._collisions[0]
        prev = controller.previous_qdot.copy()
        step = controller.step(q)
        if not step.ok:
            r.fallbacks += 1
            key = f"{cat}: {step.status.split(':')[1].strip()}"
            r.fallback_reasons[key] = r.fallback_reasons.get(key, 0) + 1
            continue
        change = np.abs(step.qdot - prev)
        r.worst_accel = max(r.worst_accel, float(change.max()) / DT)
        forced = np.zeros(12, dtype=bool)
        for conflict in step.conflicts:
            forced[conflict.joint] = True
        r.conflict_ticks += bool(forced.any())
        solution = controller.solver_solution
        if "relaxed" in step.status:
            r.relaxed += 1
            slack = solution.box_relaxation
            r.worst_relaxation = max(r.worst_relaxation, float(slack.max()))
            r.worst_excess_relaxed = max(r.worst_excess_relaxed, float(np.max(change - A_MAX * DT - slack)))
            problem = solution.problems[-1]
            live = problem.h < 1e29
            # A row binds when its slack is within 1e-8 of its scale (the backends' feasibility
            # is judged the same way, see harvest_qp.backends).
            G_live, h_live = problem.G[live], problem.h[live]
            residual = G_live @ step.qdot - h_live
            scale = 1.0 + np.abs(h_live) + np.abs(G_live) @ np.abs(step.qdot)
            r.relaxed_by_rows += bool(np.any(residual > -1e-8 * scale))
        else:
            if (~forced).any():
                r.worst_excess_plain = max(r.worst_excess_plain, float(np.max(change[~forced] - A_MAX * DT)))
            if not forced.any():
                r.worst_accel_unforced = max(r.worst_accel_unforced, float(change.max()) / DT)
        if id(collision) not in geometries:
            geometries[id(collision)] = CoalGeometry(configuration, collision)
        geometry = geometries[id(collision)]
        obstacles = [i for i, name in enumerate(collision.capsule_names) if name.startswith("obstacle_")]
        geometry.set_obstacles(collision.cap_p0[obstacles], collision.cap_radius[obstacles])
        r.min_distance_after = min(r.min_distance_after, geometry.min_distance(q + step.qdot * DT)[0])
    r.seconds = time.perf_counter() - t0
    return r


def run_fuzz(n: int, seed: int = 0) -> FuzzResult:
    """``n`` fuzz states over every category, in one process (see :func:`main` for the parallel run)."""
    return run_fuzz_batch(n, seed)


def _fuzz_job(job: tuple[str, int, int]) -> tuple[str, int, FuzzResult]:
    category, chunk, n = job
    # One seed per (category, chunk): the figures do not depend on how many processes ran them.
    seed = 1_000 * (FUZZ_CATEGORIES.index(category) + 1) + chunk
    return category, chunk, run_fuzz_batch(n, seed, categories=(category,))


def _crossing_job(args: tuple[int, int]) -> CrossingResult:
    seed, ticks = args
    return run_crossing(seed, ticks)


def _pool(jobs: int):
    import multiprocessing

    return multiprocessing.get_context("fork").Pool(jobs) if jobs > 1 else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fuzz", type=int, default=20_000, help="fuzz states over all categories")
    parser.add_argument("--crossing", type=int, default=50, help="crossing runs (seeds first-seed...)")
    parser.add_argument("--ticks", type=int, default=2000, help="ticks per crossing run (2 ms each)")
    parser.add_argument("--first-seed", type=int, default=100)
    parser.add_argument("--chunk", type=int, default=500, help="fuzz states per job (progress is printed per job)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes")
    args = parser.parse_args()
    pool = _pool(args.jobs)
    imap = pool.imap_unordered if pool else map
    t_start = time.perf_counter()
    print(f"bench_fuzz: {args.fuzz} fuzz states, {args.crossing} crossing runs x {args.ticks} ticks, "
          f"{args.jobs} process(es)", flush=True)
    if args.fuzz:
        per_cat = -(-args.fuzz // len(FUZZ_CATEGORIES))
        jobs = []
        for cat in FUZZ_CATEGORIES:
            for chunk, first in enumerate(range(0, per_cat, args.chunk)):
                jobs.append((cat, chunk, min(args.chunk, per_cat - first)))
        total = FuzzResult()
        by_cat: dict[str, FuzzResult] = {}
        for done, (cat, chunk, r) in enumerate(imap(_fuzz_job, jobs), 1):
            total = total.merge(r)
            by_cat[cat] = by_cat.get(cat, FuzzResult()).merge(r)
            print(f"  [{done}/{len(jobs)}] {cat} chunk {chunk}: {r.states} states, fallbacks {r.fallbacks}, "
                  f"relaxed {r.relaxed}, worst accel {r.worst_accel:.3g} rad/s^2, closest after step "
                  f"{1e3 * r.min_distance_after:.2f} mm ({r.seconds:.0f} s cpu)", flush=True)
        for cat in FUZZ_CATEGORIES:
            c = by_cat[cat]
            print(f"  {cat}: {c.states} states, fallbacks {c.fallbacks}, relaxed {c.relaxed} "
                  f"({c.relaxed_by_rows} with a collision row binding), position-box conflicts {c.conflict_ticks}, "
                  f"worst accel {c.worst_accel:.4g} rad/s^2 (ticks neither relaxed nor conflicted "
                  f"{c.worst_accel_unforced:.4g})", flush=True)
        r = total
        print(f"fuzz: {r.states} states ({time.perf_counter() - t_start:.0f} s wall), fallbacks {r.fallbacks} "
              f"{r.fallback_reasons}")
        print(f"  speed change per tick: worst {r.worst_accel:.4g} rad/s^2 (a_max {A_MAX:g}); on ticks neither "
              f"relaxed nor with a position-box conflict {r.worst_accel_unforced:.4g} rad/s^2; beyond a_max dt on "
              f"joints without a conflict {r.worst_excess_plain:.3g} rad/s")
        print(f"  relaxed ticks {r.relaxed} ({r.relaxed_by_rows} with a collision row binding), largest widening "
              f"{r.worst_relaxation:.4g} rad/s ({r.worst_relaxation / DT:.4g} rad/s^2 beyond a_max), change beyond "
              f"a_max dt + widening {r.worst_excess_relaxed:.3g} rad/s; position-box conflicts {r.conflict_ticks}")
        print(f"  closest pair after a step (coal): {1e3 * r.min_distance_after:.3f} mm (d_s 10 mm)", flush=True)
    if args.crossing:
        t0 = time.perf_counter()
        worst, fallbacks, relaxed, accel = None, 0, 0, 0.0
        seeds = [(seed, args.ticks) for seed in range(args.first_seed, args.first_seed + args.crossing)]
        for done, r in enumerate(imap(_crossing_job, seeds), 1):
            print(
                f"  [{done}/{len(seeds)}] crossing seed {r.seed}: min {1e3 * r.min_distance:.3f} mm {r.min_pair}, "
                f"fallbacks {r.fallbacks}, relaxed {r.relaxed}, worst accel {r.worst_accel:.4g} rad/s^2, "
                f"camera moved {r.moved:.2f} m",
                flush=True,
            )
            fallbacks, relaxed, accel = fallbacks + r.fallbacks, relaxed + r.relaxed, max(accel, r.worst_accel)
            if worst is None or r.min_distance < worst.min_distance:
                worst = r
        closest = 1e3 * worst.min_distance
        print(f"crossing: {args.crossing} runs x {args.ticks} ticks ({time.perf_counter() - t0:.0f} s wall), "
              f"closest {closest:.3f} mm {worst.min_pair} (seed {worst.seed}, d_s 20 mm, target >= 19.9 mm), "
              f"fallback ticks {fallbacks}, relaxed ticks {relaxed}, worst accel {accel:.4g} rad/s^2")
    if pool:
        pool.close()
        pool.join()
    print(f"total {time.perf_counter() - t_start:.0f} s wall", flush=True)


if __name__ == "__main__":
    main()
