"""Frames of the MuJoCo lab from any camera pose, with the ground truth of their stem.

:class:`LabViews` renders frames of the lab (:class:`harvest_qp.sim.SimRobot`) from chosen camera
poses and gives their ground truth (stem axis and base, the stem length between the branch and where
it enters the gripper or cluster, the distance from any point to the nearest non-stem surface): the
oracle of the perception tests and benchmarks on lab clouds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import ModelError
from harvest_qp.perception._validation import as_point
from harvest_qp.perception.synthetic import fibonacci_unit

__all__ = ["LabFrame", "LabViews"]


@dataclass(frozen=True)
class LabFrame:
    """One lab frame and the ground truth of its stem.

    Attributes:
        points: ``(n, 3)`` world points [m].
        stem_mask: ``(n,)`` True for points labelled STEM by the camera.
        robot_mask: ``(n,)`` True for points on the robot (also non-stem).
        camera_position: camera position [m].
        true_base: the stem base p_sb where the stem leaves the branch [m].
        true_free_length: stem length from the base to where its axis enters the gripper or
            the cluster [m] (what a camera can see of it at best).
        base_seen: a stem point lies within ``stem_radius + 3 mm`` of ``true_base``.
        coverage: fraction of the free stem's axis (samples every 1 mm) with a stem point
            within ``stem_radius + 2 mm`` (1 = nothing hides it).
        stem_radius: true stem radius [m].
    """

    points: NDArray[np.float64]
    stem_mask: NDArray[np.bool_]
    robot_mask: NDArray[np.bool_]
    camera_position: NDArray[np.float64]
    true_base: NDArray[np.float64]
    true_free_length: float
    base_seen: bool
    coverage: float
    stem_radius: float


class LabViews:
    """Frames of a lab scene (:class:`harvest_qp.sim.SimRobot`) from any camera pose, with ground truth.

    The robot stands at its home pose holding the cluster after the scene settled; the
    camera is the lab's ray-cast camera (the paper's D415 set-up unless ``camera`` is
    given), placed at any pose without moving the camera arm.

    Args:
        seed: scene seed, ``VineSceneParams.sample(seed)``; ``None`` for the default scene.
        camera: a :class:`harvest_qp.sim.CameraConfig` (default: the lab's).
        **overrides: scene parameters passed to ``VineSceneParams``.
    """

    def __init__(self, seed: int | None = None, *, camera=None, **overrides) -> None:
        from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM
        from harvest_qp.sim import CameraConfig, RayCastCamera, SimRobot, VineSceneParams

        params = VineSceneParams(**overrides) if seed is None else VineSceneParams.sample(seed, **overrides)
        self.robot = SimRobot(params, camera=None)
        self.scene = self.robot.scene
        self._labels = (STEM, OBSTACLE, ROBOT)
        model = self.robot.model
        self.camera = RayCastCamera(
            model,
            CameraConfig() if camera is None else camera,
            geom_labels=self.scene.geom_labels,
            exclude_body=self.scene.ids["cam_tool"],
        )
        self.stem_radius = float(params.stem_radius)
        self.stem_axis = self._stem_axis()
        self._surfaces = self._non_stem_surfaces()
        self.free_length, self.free_axis = self._free_stem()

    # ---------------------------------------------------------------- ground truth

    def _stem_axis(self) -> NDArray[np.float64]:
        """Stem axis polyline of the settled stem, from the base down to the cluster [m]."""
        model, data = self.robot.model, self.robot.data
        base = self.scene.stem_base
        ends = []
        for g in self.scene.stem_geoms:
            half = model.geom_size[g, 1]
            z = data.geom_xmat[g].reshape(3, 3)[:, 2]
            a, b = data.geom_xpos[g] - half * z, data.geom_xpos[g] + half * z
            ends.append((a, b) if np.linalg.norm(a - base) < np.linalg.norm(b - base) else (b, a))
        ends.sort(key=lambda e: np.linalg.norm(e[0] - base))
        return np.array([ends[0][0]] + [e[1] for e in ends])

    def _non_stem_surfaces(self) -> list[tuple[int, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
        """(type, size, position, rotation) of every visible non-stem geom except the camera tool."""
        model, data = self.robot.model, self.robot.data
        stem = set(int(g) for g in self.scene.stem_geoms)
        out = []
        for g in range(model.ngeom):
            if g in stem or model.geom_rgba[g, 3] == 0 or model.geom_bodyid[g] == self.scene.ids["cam_tool"]:
                continue
            out.append(
                (int(model.geom_type[g]), model.geom_size[g].copy(), data.geom_xpos[g].copy(),
                 data.geom_xmat[g].reshape(3, 3).copy())
            )  # fmt: skip
        return out

    def surface_distance(self, points: ArrayLike, *, wood_only: bool = False) -> NDArray[np.float64]:
        """Distance [m] from each point to the nearest non-stem surface (negative inside).

        Exact for planes, spheres and capsules; leaves (thin ellipsoids) are measured on 4,000
        surface samples (under 1 mm of error at the distances that matter here).  The camera
        tool, which the camera never sees, is left out.  ``wood_only``: the branch and cane.
        """
        points = np.atleast_2d(np.asarray(points, dtype=np.float64))
        best = np.full(points.shape[0], np.inf)
        wood = {self.robot.model.geom("branch").id, self.robot.model.geom("cane").id}
        surfaces = self._surfaces if not wood_only else [self._surface_of(g) for g in sorted(wood)]
        for kind, size, position, rotation in surfaces:
            local = (points - position) @ rotation
            if kind == 0:  # plane
                d = local[:, 2]
            elif kind == 2:  # sphere
                d = np.linalg.norm(local, axis=1) - size[0]
            elif kind == 3:  # capsule along local z
                z = np.clip(local[:, 2], -size[1], size[1])
                d = np.linalg.norm(local - np.outer(z, [0.0, 0.0, 1.0]), axis=1) - size[0]
            elif kind == 4:  # ellipsoid
                d = self._ellipsoid_distance(local, size)
            else:
                raise ModelError(
                    f"LabViews.surface_distance: unhandled geom type {kind} (plane, sphere, capsule, ellipsoid only)"
                )
            best = np.minimum(best, d)
        return best

    def _surface_of(self, g: int):
        model, data = self.robot.model, self.robot.data
        return (
            int(model.geom_type[g]),
            model.geom_size[g].copy(),
            data.geom_xpos[g].copy(),
            data.geom_xmat[g].reshape(3, 3).copy(),
        )

    @staticmethod
    def _ellipsoid_distance(local: NDArray[np.float64], size: NDArray[np.float64]) -> NDArray[np.float64]:
        samples = fibonacci_unit(4000) * size
        inside = ((local / size) ** 2).sum(axis=1) < 1.0
        diff = local[:, None, :] - samples[None, :, :]
        d = np.sqrt((diff**2).sum(axis=2)).min(axis=1)
        return np.where(inside, -d, d)

    def segment_clearance(
        self, start: ArrayLike, end: ArrayLike, *, skip: float = 0.0, wood_only: bool = True
    ) -> float:
        """Smallest surface distance [m] along the segment start -> end, 1 mm steps, ignoring the first ``skip`` [m]."""
        start, end = as_point("start", start), as_point("end", end)
        length = float(np.linalg.norm(end - start))
        s = np.linspace(min(skip, length), length, max(2, int(length / 0.001) + 1))
        samples = start + np.outer(s / max(length, 1e-12), end - start)
        return float(self.surface_distance(samples, wood_only=wood_only).min())

    def _free_stem(self) -> tuple[float, NDArray[np.float64]]:
        """Length [m] and samples (1 mm apart) of the stem axis from the base to where it
        enters the gripper or the cluster (a robot or berry/rachis geom)."""
        model = self.robot.model
        cluster_body = self.scene.ids["cluster"]
        entering = [
            self._surface_of(g)
            for g in range(model.ngeom)
            if self.scene.geom_labels[g] == self._labels[2] or model.geom_bodyid[g] == cluster_body
        ]
        axis = self.stem_axis
        samples = [axis[0]]
        for a, b in zip(axis[:-1], axis[1:], strict=True):
            n = max(1, int(np.linalg.norm(b - a) / 0.001))
            samples.extend(a + np.outer(np.arange(1, n + 1) / n, b - a))
        samples = np.array(samples)
        inside = np.zeros(len(samples), dtype=bool)
        saved = self._surfaces
        try:
            self._surfaces = entering
            inside = self.surface_distance(samples) <= 0.0
        finally:
            self._surfaces = saved
        first = int(np.argmax(inside)) if inside.any() else len(samples)
        free = samples[: max(first, 1)]
        length = float(np.linalg.norm(np.diff(free, axis=0), axis=1).sum())
        return length, free

    # ---------------------------------------------------------------- frames

    @property
    def stem_middle(self) -> NDArray[np.float64]:
        """Middle of the free stem [m], where the views look."""
        return self.free_axis[len(self.free_axis) // 2]

    def render(self, pose: ArrayLike) -> LabFrame:
        """A frame from camera ``pose`` (4x4) with its ground truth."""
        stem_label, _, robot_label = self._labels
        pose = np.asarray(pose, dtype=np.float64)
        cloud = self.camera.capture(self.robot.data, pose, 0.0)
        stem_mask = cloud.labels == stem_label
        stem_points = cloud.points[stem_mask]
        base = self.stem_axis[0]
        if stem_points.shape[0]:
            base_seen = bool(np.linalg.norm(stem_points - base, axis=1).min() < self.stem_radius + 0.003)
            gaps = np.sqrt(((self.free_axis[:, None, :] - stem_points[None, :, :]) ** 2).sum(axis=2)).min(axis=1)
            coverage = float(np.mean(gaps < self.stem_radius + 0.002))
        else:
            base_seen, coverage = False, 0.0
        return LabFrame(
            points=cloud.points,
            stem_mask=stem_mask,
            robot_mask=cloud.labels == robot_label,
            camera_position=pose[:3, 3].copy(),
            true_base=base.copy(),
            true_free_length=self.free_length,
            base_seen=base_seen,
            coverage=coverage,
            stem_radius=self.stem_radius,
        )
