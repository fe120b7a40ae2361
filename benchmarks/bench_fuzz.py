"""Fuzz and crossing scenarios for the QP core, measured with an independent geometry.

Run by hand (the full size takes minutes on a loaded 2-core machine)::

    python -m benchmarks.bench_fuzz                 # 20,000 fuzz states, 50 crossing runs
    python -m benchmarks.bench_fuzz --fuzz 2000 --crossing 10 --ticks 1000

It prints, for the fuzz states (collision-free, inside the joint limits): how many
ticks fell back to the safe stop, how many relaxed the acceleration limit and by how
much, and the worst speed change beyond what the limits allow; for the crossing
runs (two FramePoseTasks swapping tool positions among random obstacle spheres): the
fallback ticks and the smallest pair distance measured with pinocchio frame
placements and coal capsules (not with the controller's own kernel).

The scenario generators are imported by ``tests/core/test_qp_fuzz.py`` at a small size.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

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
    """

    def __init__(self, configuration: Configuration, collision: CollisionAvoidance, environment=()) -> None:
        import coal
        import pinocchio as pin

        self._coal, self._pin = coal, pin
        self.configuration = configuration
        self.collision = collision
        self.bodies = {b.name: b for b in desc.collision_bodies()}
        self._frame = {name: configuration.frame_id(b.link) for name, b in self.bodies.items()}
        self._shapes = {}
        self._local = {}
        for name, b in self.bodies.items():
            self._shapes[name], self._local[name] = self._capsule(b.capsule.p0, b.capsule.p1, b.capsule.radius)
        self.obstacles: list[tuple[np.ndarray, float]] = []
        self.environment = {}
        for cap in environment:  # world-fixed capsules (frame None)
            shape, local = self._capsule(cap.p0, cap.p1, cap.radius)
            self.environment[cap.name] = (shape, coal.Transform3s(local.rotation, local.translation))

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
        self.obstacles = [(np.asarray(c, float), float(r)) for c, r in zip(centres, radii)]

    def _placements(self, q: np.ndarray) -> dict:
        pin = self._pin
        model, data = self.configuration.model, self.configuration.model.createData()
        pin.framesForwardKinematics(model, data, q)
        return {name: data.oMf[self._frame[name]] * self._local[name] for name in self.bodies}

    def pair_distances(self, q: np.ndarray, pairs=None) -> dict[tuple[str, str], float]:
        """Surface distance [m] of every candidate pair of the controller (or of ``pairs``), by names."""
        coal = self._coal
        placements = self._placements(q)
        out = {}
        for a, b in self.collision.pair_names() if pairs is None else pairs:
            if b.startswith("obstacle_"):
                c, r = self.obstacles[int(b.split("_")[1])]
                T2, shape2 = coal.Transform3s(np.eye(3), c), coal.Sphere(r)
            elif b in self.environment:
                shape2, T2 = self.environment[b]
            elif a in placements and b in placements:
                T2, shape2 = coal.Transform3s(placements[b].rotation, placements[b].translation), self._shapes[b]
            else:
                continue
            Pa = placements[a]
            req, res = coal.DistanceRequest(), coal.DistanceResult()
            d = coal.distance(self._shapes[a], coal.Transform3s(Pa.rotation, Pa.translation), shape2, T2, req, res)
            out[(a, b)] = float(d)
        return out

    def min_distance(self, q: np.ndarray) -> tuple[float, tuple[str, str]]:
        d = self.pair_distances(q)
        pair = min(d, key=d.get)
        return d[pair], pair


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


def _pull_arms_together(configuration, collision, q, rng):
    """Bisect between q and a configuration with the tools swapped until arms are 1.5-4 cm apart."""
    q_far = q.copy()
    q_near = q.copy()
    q_near[:6], q_near[6:] = q[:6] + rng.normal(0, 0.5, 6), q[6:] + rng.normal(0, 0.5, 6)
    q_near[0] += 1.2
    q_near[6] -= 1.2
    q_near = np.clip(q_near, configuration.lower_limits, configuration.upper_limits)
    names = collision.pair_names()
    arm_pair = np.array([{a.split("_")[0], b.split("_")[0]} == {"cam", "grasp"} for a, b in names])
    lo_t, hi_t = 0.0, 1.0
    for _ in range(25):
        t = 0.5 * (lo_t + hi_t)
        configuration.update(q_far + t * (q_near - q_far))
        d = collision.distances(configuration)
        if d[arm_pair].min() < 0.04:
            hi_t = t
        else:
            lo_t = t
        if 0.015 < d[arm_pair].min() < 0.04:
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
    states: int
    fallbacks: int
    fallback_reasons: dict
    relaxed: int
    worst_excess_accel: float  # [rad/s^2] beyond a_max on relaxed ticks
    worst_unforced_excess: float  # [rad/s] beyond a_max dt on ticks not relaxed


def run_fuzz(n: int, seed: int = 0) -> FuzzResult:
    fallbacks, relaxed, reasons = 0, 0, {}
    worst_excess, worst_unforced = 0.0, 0.0
    for cat, _, controller, q, _ in fuzz_states(n, seed):
        prev = controller.previous_qdot.copy()
        step = controller.step(q)
        if not step.ok:
            fallbacks += 1
            key = f"{cat}: {step.status.split(':')[1].strip()}"
            reasons[key] = reasons.get(key, 0) + 1
            continue
        change = np.max(np.abs(step.qdot - prev))
        if "relaxed" in step.status:
            relaxed += 1
            worst_excess = max(worst_excess, change / DT - A_MAX)
        else:
            worst_unforced = max(worst_unforced, change - A_MAX * DT)
    return FuzzResult(n, fallbacks, reasons, relaxed, worst_excess, worst_unforced)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fuzz", type=int, default=20_000)
    parser.add_argument("--crossing", type=int, default=50)
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--first-seed", type=int, default=100)
    args = parser.parse_args()
    if args.fuzz:
        t0 = time.perf_counter()
        r = run_fuzz(args.fuzz)
        took = time.perf_counter() - t0
        print(f"fuzz: {r.states} states ({took:.0f} s), fallbacks {r.fallbacks} {r.fallback_reasons}")
        print(f"  relaxed acceleration ticks {r.relaxed}, worst excess over a_max on them "
              f"{r.worst_excess_accel:.3g} rad/s^2")
        print(f"  worst speed change beyond a_max*dt on other ticks {r.worst_unforced_excess:.3g} rad/s")
    worst = None
    for seed in range(args.first_seed, args.first_seed + args.crossing):
        t0 = time.perf_counter()
        r = run_crossing(seed, args.ticks)
        print(
            f"crossing seed {seed}: min {1e3 * r.min_distance:.2f} mm {r.min_pair}, fallbacks {r.fallbacks}, "
            f"relaxed {r.relaxed}, worst accel {r.worst_accel:.3g} rad/s^2, camera moved {r.moved:.2f} m "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
        if worst is None or r.min_distance < worst.min_distance:
            worst = r
    if worst is not None:
        closest = 1e3 * worst.min_distance
        print(f"crossing: {args.crossing} runs, closest {closest:.2f} mm (seed {worst.seed}, d_s 20 mm)")


if __name__ == "__main__":
    main()
