"""Perception on frames rendered from the MuJoCo lab, against the lab's ground truth.

Frames come from the lab's ray-cast camera (283x160, the paper's D415 set-up) placed 0.3-0.45 m
from the stem on the robot's side, over several scene seeds (`VineSceneParams.sample`) and
random view directions; the ground truth is the settled stem's capsules (base p_sb, axis,
the length between the branch and where it enters the gripper or cluster) and every other
geom's surface (:class:`harvest_qp.sim.lab_views.LabViews`).  The frames are rendered
once per module (~1-2 s).
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import pytest

from harvest_qp.perception import compute_free_space, fit_stem, obstacles_near_stem_base, process_cloud
from harvest_qp.perception.stem import StemModel
from harvest_qp.perception.synthetic import fibonacci_unit, view_poses
from harvest_qp.sim.lab_views import LabFrame, LabViews

# The default scene and sampled scenes, with views of their own (rng 1000 + seed).  The
# thresholds were tuned on seeds 1-20 (other views); the hidden-base rule was revised once
# (the short-fragment test) after a check on seeds 21-44.
SEEDS = (None, 3, 21, 24, 27, 30, 33, 36, 39, 42)
VIEWS_PER_SEED = 10
# (seed, view) of `benchmarks/bench_perception.py --accuracy` (rng `seed`, 12 views 0.3-0.45 m)
# where the straight stem p_sb -> p_gd chosen by the clearance selection entered the branch
# (0.8-5.1 mm deep) before the stem-visibility test: it ran just behind the observed wood.
WOOD_VIEWS = ((13, 5), (14, 0), (15, 11), (27, 6))


@dataclass
class View:
    views: LabViews
    frame: LabFrame
    gripper: np.ndarray
    model: StemModel | None

    @property
    def stem(self) -> np.ndarray:
        return self.frame.points[self.frame.stem_mask]

    @property
    def other(self) -> np.ndarray:
        return self.frame.points[~self.frame.stem_mask]

    @property
    def base_error(self) -> float:
        return float(np.linalg.norm(self.model.base - self.frame.true_base))


@pytest.fixture(scope="module")
def lab() -> list[View]:
    records = []
    for seed in SEEDS:
        views = LabViews(seed)
        gripper = views.robot.site_pose("gripper")[:3, 3]
        rng = np.random.default_rng(1000 + (0 if seed is None else seed))
        for pose in view_poses(views.stem_middle, rng, VIEWS_PER_SEED, distance=(0.3, 0.45)):
            frame = views.render(pose)
            stem = frame.points[frame.stem_mask]
            model = None
            if stem.shape[0] >= 10:
                model = fit_stem(
                    stem, gripper, camera_position=frame.camera_position, non_stem_points=frame.points[~frame.stem_mask]
                )
            records.append(View(views, frame, gripper, model))
    return records


def _seeing_base(lab):
    return [v for v in lab if v.model is not None and v.frame.base_seen]


def test_ground_truth_surface_distance_matches_mujoco_ray_casts(lab):
    """The oracle itself, checked against MuJoCo's ray caster: from points around the stem, the
    nearest hit over 4,000 ray directions is the distance to the nearest non-stem surface.
    Catches a wrong geom frame (capsule axis, rotation) in `LabViews.surface_distance`."""
    views = lab[0].views
    model, data = views.robot.model, views.robot.data
    rng = np.random.default_rng(5)
    directions = fibonacci_unit(4000)
    stem_body = {int(model.geom_bodyid[g]) for g in views.scene.stem_geoms}
    # mj_multiRay excludes one body: cast from points away from the stem so that it is never
    # the nearest surface, and leave the camera tool out as the oracle does.
    checked = 0
    for _ in range(40):
        point = views.stem_middle + rng.uniform(-0.06, 0.06, 3)
        expected = float(views.surface_distance(point)[0])
        stem_distance = float(np.linalg.norm(views.stem_axis - point, axis=1).min())
        if expected <= 0.002 or stem_distance < expected + 0.01:
            continue
        geom_ids = np.zeros(len(directions), np.int32)
        distances = np.zeros(len(directions))
        mujoco.mj_multiRay(
            model, data, point, directions.ravel(), None, 1, views.scene.ids["cam_tool"], geom_ids, distances, None,
            len(directions), 1.0,
        )  # fmt: skip
        hit = distances[(geom_ids >= 0) & ~np.isin(model.geom_bodyid[np.maximum(geom_ids, 0)], list(stem_body))]
        # 4,000 directions are 3.2 deg apart: the nearest hit overshoots by < 0.2 %, plus leaf sampling.
        assert hit.min() == pytest.approx(expected, abs=0.001 + 0.01 * expected)
        checked += 1
    assert checked >= 10


def test_base_error_and_acceptance_on_views_that_see_it(lab):
    """p_sb on lab views 0.3-0.45 m from the stem that see its base: median <= 4 mm, 95th
    percentile <= 8 mm, the fit accepted in >= 90 % of them.  Catches the former
    `max_spread_ratio=0.5` check (rejects thick bent stems) and the paper's mean(T) - l_t/2
    n_st on partly occluded stems."""
    seeing = _seeing_base(lab)
    assert len(seeing) >= 40
    accepted = [v for v in seeing if v.model.valid]
    assert len(accepted) >= 0.9 * len(seeing)
    errors = np.array([v.base_error for v in accepted])
    assert np.median(errors) <= 0.004
    assert np.percentile(errors, 95) <= 0.008


def test_no_bias_towards_the_camera(lab):
    """Only the near half of the stem is seen: without the near-surface correction p_sb sits
    2-3 mm towards the camera (measured mean -2.3 mm along the view ray).  The mean error
    along the ray must be under 1 mm, and the estimated radius within 1 mm of the truth."""
    along, radius_error = [], []
    for v in _seeing_base(lab):
        if not v.model.valid:
            continue
        ray = v.frame.true_base - v.frame.camera_position
        along.append((v.model.base - v.frame.true_base) @ ray / np.linalg.norm(ray))
        radius_error.append(v.model.quality.radius - v.frame.stem_radius)
    assert abs(np.mean(along)) < 0.001
    assert np.median(np.abs(radius_error)) < 0.001


def test_hidden_base_is_flagged(lab):
    """Where the branch (seen from above) or a leaf hides the base, p_sb lands on the stem below
    it, 6-35 mm off: `quality.base_hidden` must say so for every fit that is more than 7 mm
    off, and must not flag most of the views that do see the base."""
    fitted = [v for v in lab if v.model is not None and v.model.valid]
    far_off = [v for v in fitted if v.base_error > 0.007]
    assert len(far_off) >= 5  # the set holds such views
    assert all(v.model.quality.base_hidden for v in far_off)
    seeing = [v for v in fitted if v.frame.base_seen]
    flagged = np.mean([v.model.quality.base_hidden for v in seeing])
    assert flagged <= 0.5
    # Trusted fits are the ones a controller may use: all within 7 mm.
    trusted = [v for v in fitted if v.model.trusted()]
    assert len(trusted) >= 15
    assert max(v.base_error for v in trusted) <= 0.007


def test_uncertainty_covers_the_error(lab):
    """`base_uncertainty` is a per-axis 1-sigma of p_sb: |error| <= 3 sigma in >= 90 % of the
    views that see the base and are not flagged.  Catches an uncertainty that ignores the
    resolution (a few tenths of a mm)."""
    ratios = [
        v.base_error / v.model.quality.base_uncertainty
        for v in _seeing_base(lab)
        if v.model.valid and not v.model.quality.base_hidden
    ]
    assert len(ratios) >= 20
    assert np.mean(np.array(ratios) <= 3.0) >= 0.9


def test_length_within_15_percent_where_little_is_hidden(lab):
    """l against the true length between the branch and where the stem enters the gripper or
    the cluster, in views that see >= 90 % of it including its base: within 15 % in >= 90 %
    of them.  Catches the paper's l = l_t + l_b (the joint between the clusters is lost where
    a leaf crosses it) and a missed segment."""
    covered = [
        v for v in lab if v.model is not None and v.model.valid and v.frame.coverage >= 0.9 and v.frame.base_seen
    ]
    assert len(covered) >= 20
    ratio = np.array([v.model.length / v.frame.true_free_length for v in covered])
    assert np.mean(np.abs(ratio - 1.0) <= 0.15) >= 0.9


@pytest.fixture(scope="module")
def wood_views() -> list[View]:
    """The benchmark views of ``WOOD_VIEWS``."""
    records = []
    for seed, index in WOOD_VIEWS:
        views = LabViews(seed)
        gripper = views.robot.site_pose("gripper")[:3, 3]
        pose = view_poses(views.stem_middle, np.random.default_rng(seed), 12, distance=(0.3, 0.45))[index]
        frame = views.render(pose)
        other = frame.points[~frame.stem_mask]
        model = fit_stem(
            frame.points[frame.stem_mask], gripper, camera_position=frame.camera_position, non_stem_points=other
        )
        records.append(View(views, frame, gripper, model))
    return records


@pytest.fixture(scope="module")
def targets(lab, wood_views):
    """p_gd on the trusted views (``lab`` and ``WOOD_VIEWS``), chosen by the clearance selection
    and by eq:attr_point alone."""
    assert all(v.model.trusted() for v in wood_views)
    out = []
    for v in [*lab, *wood_views]:
        if v.model is None or not v.model.trusted():
            continue
        obstacles = obstacles_near_stem_base(v.other, v.model.base, v.model.length)
        selected = compute_free_space(
            obstacles, v.model.base, v.model.length, v.frame.camera_position, scene_points=v.other
        )
        paper = compute_free_space(obstacles, v.model.base, v.model.length, v.frame.camera_position)
        out.append((v, selected, paper))
    return out


def _target_clearances(view: View, target: np.ndarray) -> tuple[float, float]:
    """True distance from p_gd to the nearest non-stem surface, and the smallest distance to
    the branch or cane along the straight stem p_sb -> p_gd past its first 5 mm (where it
    leaves the branch)."""
    surface = float(view.views.surface_distance(target)[0])
    wood = view.views.segment_clearance(view.model.base, target, skip=0.005, wood_only=True)
    return surface, wood


def test_target_keeps_clear_of_every_surface_and_the_stem_of_the_wood(targets):
    """p_gd keeps >= 10 mm from every non-stem surface (gripper and cluster included) and the
    straight stem p_sb -> p_gd never enters the branch or cane (past its first 5 mm), on every
    trusted view, ``WOOD_VIEWS`` included, with no straight stem blocked.  The selection never
    does worse than the paper's eq:attr_point alone (obstacles projected from S(p_sb, l)) on
    the same views.  Catches a selection that trusts the observed points alone: without the
    stem-visibility test (``stem_visibility_skip`` = l, planted once) the stem of each of the
    4 ``WOOD_VIEWS`` runs 0.8-5.1 mm inside the branch behind its observed front."""
    assert len(targets) >= 19
    paper_worst, selected_worst = np.inf, np.inf
    for view, selected, paper in targets:
        assert selected.valid, selected.reason
        surface, wood = _target_clearances(view, selected.target)
        assert wood > 0.0, (wood, view.frame.camera_position)
        assert surface >= 0.010, (surface, view.frame.camera_position)
        index = int(np.argmin(np.linalg.norm(selected.samples - selected.target, axis=1)))
        assert not selected.blocked[index], selected.reason
        paper_worst = min(paper_worst, _target_clearances(view, paper.target)[0])
        selected_worst = min(selected_worst, surface)
    assert selected_worst >= paper_worst


def test_target_is_on_the_sphere_in_view(targets):
    """p_gd stays a sample of S(p_sb, l), not occupied and not behind an observed surface; on
    the camera side of the obstacle plane (the paper's hemisphere F) unless every straight
    stem into F passes behind an observed surface, which ``reason`` then says.  Catches a
    target taken from behind the plane while F holds a stem in view."""
    behind = 0
    for _, selected, _ in targets:
        index = int(np.argmin(np.linalg.norm(selected.samples - selected.target, axis=1)))
        assert np.array_equal(selected.samples[index], selected.target)
        assert not selected.occupied[index] and not selected.occluded[index]
        if selected.stem_hidden[index]:
            # Allowed only where no sample in view, behind the plane or not, has a stem in view.
            assert "passes behind an observed surface" in selected.reason
            assert not (~selected.occupied & ~selected.occluded & ~selected.stem_hidden & ~selected.blocked).any()
        if selected.behind_plane[index]:
            behind += 1
            assert "behind the obstacle plane" in selected.reason
            assert not (selected.free & ~selected.occluded & ~selected.stem_hidden & ~selected.blocked).any()
        else:
            assert selected.free[index]
    assert behind <= 0.25 * len(targets)


def test_process_cloud_on_a_lab_frame(lab):
    """The pipeline passes the camera and the non-stem points on: the same p_sb, quality and
    target as the parts called directly."""
    view = next(v for v in lab if v.model is not None and v.model.trusted())
    result = process_cloud(
        view.frame.points,
        view.frame.stem_mask,
        camera_position=view.frame.camera_position,
        gripper_position=view.gripper,
    )
    np.testing.assert_allclose(result.stem_base, view.model.base)
    assert result.stem.quality == view.model.quality
    direct = compute_free_space(
        obstacles_near_stem_base(view.other, view.model.base, view.model.length),
        view.model.base, view.model.length, view.frame.camera_position, scene_points=view.other,
    )  # fmt: skip
    np.testing.assert_allclose(result.target, direct.target)
