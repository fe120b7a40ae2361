"""The next-best-view step of the predicted mode: its geometry against brute force and hand
cases, and its rules (goal, minimum distance, stall) on small scenes."""

import math

import numpy as np
import pytest

from harvest_qp.references import Unveiling
from harvest_qp.references.next_best_view import VoxelMemory, sight_lines


def _brute_force(viewpoints, targets, obstacles, clearance, ignore_radius):
    counts = np.zeros((len(viewpoints), len(targets)), dtype=int)
    for i, v in enumerate(viewpoints):
        for j, p in enumerate(targets):
            for o in obstacles:
                s = np.clip((o - v) @ (p - v) / ((p - v) @ (p - v)), 0.0, 1.0)
                if np.linalg.norm(v + s * (p - v) - o) < clearance and np.linalg.norm(o - p) >= ignore_radius:
                    counts[i, j] += 1
    return counts


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sight_lines_equal_brute_force(seed):
    """The two-stage test (coarse cull against the targets' centroid, then exact) counts the
    same blockers as the double loop over every segment and obstacle.  Catches: a coarse
    threshold without the targets' spread (it would drop true blockers)."""
    rng = np.random.default_rng(seed)
    viewpoints = rng.normal(size=(7, 3)) * 0.3 + [0.0, 0.0, 0.4]
    targets = np.linspace([0.0, 0.0, -0.03], [0.01, 0.0, 0.03], 12) + rng.normal(size=(12, 3)) * 0.003
    obstacles = rng.normal(size=(400, 3)) * [0.1, 0.1, 0.2] + [0.0, 0.0, 0.2]
    counts = sight_lines(viewpoints, targets, obstacles, clearance=0.01, ignore_radius=0.03)
    np.testing.assert_array_equal(counts, _brute_force(viewpoints, targets, obstacles, 0.01, 0.03))
    assert counts.sum() > 20 and (counts == 0).sum() > 5  # both outcomes occur


def test_sight_lines_by_hand():
    """Viewpoint (0, 0, 1), targets (0, 0, 0) and (0.1, 0, 0); an obstacle at (0.004, 0, 0.5)
    is 4 mm from the first segment (blocked at 6 mm clearance) and ~46 mm from the second; one
    at (0.01, 0, 0.01) lies within the 3 cm ignore radius of the first target."""
    counts = sight_lines(
        np.array([[0.0, 0.0, 1.0]]),
        np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]]),
        np.array([[0.004, 0.0, 0.5], [0.01, 0.0, 0.01]]),
        clearance=0.006,
        ignore_radius=0.03,
    )
    np.testing.assert_array_equal(counts, [[1, 0]])


def test_voxel_memory_accumulates_distinct_voxels():
    """Three points in two 1 cm voxels, then one more voxel: 3 voxel centres, idempotent."""
    memory = VoxelMemory(0.01)
    memory.add(np.array([[0.001, 0.002, 0.003], [0.009, 0.001, 0.0], [0.015, 0.0, 0.0]]))
    np.testing.assert_allclose(memory.points, [[0.005, 0.005, 0.005], [0.015, 0.005, 0.005]])
    memory.add(np.array([[-0.004, 0.0, 0.0], [0.002, 0.002, 0.002]]))
    assert memory.points.shape == (3, 3)
    np.testing.assert_allclose(memory.points[0], [-0.005, 0.005, 0.005])


def _leaf(centre, normal, radius, spacing=0.004):
    """Points of a flat disc."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    first = np.cross(normal, [0.0, 0.0, 1.0])
    first /= np.linalg.norm(first)
    second = np.cross(normal, first)
    grid = np.arange(-radius, radius + 1e-9, spacing)
    u, v = np.meshgrid(grid, grid)
    inside = u**2 + v**2 <= radius**2
    return centre + u[inside][:, None] * first + v[inside][:, None] * second


STEM = np.linspace([0.0, 0.0, 0.0], [0.0, 0.0, 0.06], 12)
ROI = np.array([0.0, 0.0, -0.04])


def test_clear_view_commands_nothing_and_a_hidden_stem_moves_the_camera_sideways():
    """A leaf 8 cm in front of the predicted stem (seen from +x): the camera at 0.35 m moves
    tangentially (|v . radial| ~ 0) at the bounded speed, with the bearing feed-forward; with no
    leaf it is clear and nothing is commanded.  Catches: a step that moves while the stem
    is clear (it would fight the paper mode) or one that moves radially."""
    camera = ROI + np.array([0.35, 0.0, 0.0])
    law = Unveiling(time_constant=0.0)
    law.observe(camera, [], [[0.5, 0.5, 0.5]], predicted_stem_points=STEM, roi_centre=ROI)
    assert law.mode == "predicted" and law.clear_fraction == 1.0 and not law.raw.any()
    law.reset()
    leaf = _leaf([0.08, 0.0, 0.03], [1.0, 0.0, 0.0], 0.05)
    law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI)
    assert law.clear_fraction == 0.0
    v, w = law.raw[:3], law.raw[3:]
    # nbv_speed 0.1 m/s needs |w| = 0.1 / 0.35 > max_angular = 0.2 rad/s: scaled to 0.07 m/s.
    assert np.linalg.norm(v) == pytest.approx(0.2 * 0.35, rel=1e-9)
    assert abs(v @ [1.0, 0.0, 0.0]) < 1e-9  # tangential
    np.testing.assert_allclose(w, np.cross(v, ROI - camera) / 0.35**2, atol=1e-12)


def test_camera_flown_by_the_step_clears_the_leaf():
    """Integrating the camera under the raw step (frames every 0.1 s) from behind the leaf:
    within 5 s at least 80 % of the predicted points are clear, and the camera stays at
    0.35 m from the ROI (tangential motion).  Catches: targets that are never committed to
    (dithering) and a wrong tangent direction."""
    leaf = _leaf([0.08, 0.0, 0.03], [1.0, 0.0, 0.0], 0.05)
    camera = ROI + np.array([0.35, 0.0, 0.0])
    law = Unveiling()
    for k in range(50):
        law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.1 * k)
        if law.clear_fraction >= 0.8:
            break
        camera = camera + 0.1 * law.raw[:3]
        camera = ROI + 0.35 * (camera - ROI) / np.linalg.norm(camera - ROI)  # exact sphere
    assert law.clear_fraction >= 0.8, k


def test_minimum_distance_pushes_outwards():
    """Closer than min_distance (0.25 m) to the ROI, the step adds gain x deficit outwards:
    at 0.15 m with a clear view, v = 2 (0.25 - 0.15) = 0.2 m/s radially, saturated to 0.1."""
    camera = ROI + np.array([0.15, 0.0, 0.0])
    law = Unveiling()
    law.observe(camera, [], [[0.5, 0.5, 0.5]], predicted_stem_points=STEM, roi_centre=ROI)
    np.testing.assert_allclose(law.raw[:3], [0.1, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(law.raw[3:], 0.0, atol=1e-12)


def test_stall_rule_abandons_a_viewpoint_the_camera_cannot_reach():
    """A camera that never moves (held by a collision row) keeps its first target for
    stall_time (1.5 s), then abandons it and picks another direction.  Catches: a stall
    rule that never fires (lab measurements: 20 s pinned on seed 3)."""
    leaf = _leaf([0.08, 0.0, 0.03], [1.0, 0.0, 0.0], 0.05)
    camera = ROI + np.array([0.35, 0.0, 0.0])
    law = Unveiling(stall_time=1.5)
    law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.0)
    first = law.next_best_view.target.copy()
    for k in range(1, 15):
        law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.1 * k)
        np.testing.assert_array_equal(law.next_best_view.target, first)
    for k in range(15, 18):
        law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.1 * k)
    assert len(law.next_best_view.avoided) == 1
    assert law.next_best_view.target @ first < math.cos(math.radians(15.0))


def test_seen_stem_hands_over_to_the_paper_mode():
    """With >= min_stem_points seen stem points the paper mode runs even if predicted points
    are given; below that the predicted mode keeps searching."""
    law = Unveiling(min_stem_points=10)
    seen = np.linspace([0.0, 0.0, 0.5], [0.0, 0.01, 0.5], 10)
    law.observe(np.zeros(3), seen, [[0.004, 0.0, 0.25]], predicted_stem_points=seen)
    assert law.mode == "paper"
    law.observe(np.zeros(3), seen[:9], [[0.004, 0.0, 0.25]], predicted_stem_points=seen)
    assert law.mode == "predicted"


def test_step_plans_at_most_every_nbv_period():
    """At 30 Hz frames the step plans on every third frame (nbv_period 0.1 s) and keeps its
    last twist in between, even if the view changed.  Catches: the period ignored (3x the cost)
    or never re-planning."""
    leaf = _leaf([0.08, 0.0, 0.03], [1.0, 0.0, 0.0], 0.05)
    camera = ROI + np.array([0.35, 0.0, 0.0])
    law = Unveiling(nbv_period=0.1)
    law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.0)
    moving = law.raw.copy()
    assert moving.any()
    far = ROI + np.array([0.0, 0.35, 0.0])  # a clear side view (the leaf faces +x)
    law.observe(far, [], [[0.5, 0.5, 0.5]], predicted_stem_points=STEM, roi_centre=ROI, timestamp=1 / 30)
    np.testing.assert_array_equal(law.raw, moving)  # not re-planned yet
    law.observe(far, [], [[0.5, 0.5, 0.5]], predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.1)
    assert law.clear_fraction == 1.0 and not law.raw.any()  # re-planned: clear, stop


def test_voxel_memory_forgets_what_it_no_longer_sees():
    """With a 5 s lifetime a voxel seen at t = 0 and not since is gone at t = 5.1 s; one seen
    again at t = 3 s stays.  Catches: refresh times not updated (both would go) or no expiry."""
    memory = VoxelMemory(0.01, lifetime=5.0)
    memory.add(np.array([[0.001, 0.0, 0.0], [0.101, 0.0, 0.0]]), 0.0)
    memory.add(np.array([[0.102, 0.001, 0.0]]), 3.0)
    memory.add(np.zeros((0, 3)), 5.1)
    np.testing.assert_allclose(memory.points, [[0.105, 0.005, 0.005]])
    memory.add(np.zeros((0, 3)), 8.1)
    assert memory.points.shape == (0, 3)


def test_a_blind_view_is_not_a_clear_one():
    """A frame without a single point (a leaf closer than the camera's range) neither ages the memory
    nor reads as a clear view: after the leaf was seen, 6 s of empty frames (past the 5 s lifetime)
    keep its voxels, the clear fraction stays 0 and the camera keeps moving sideways; the first frame
    with points again (a side view, leaf not in it) ages the memory as before. Catches the lab failure
    this rule fixes: the camera at rest against the leaf hiding the stem, its memory expired, and the
    empty view then read as "the stem is clear" (it stopped for good)."""
    leaf = _leaf([0.08, 0.0, 0.03], [1.0, 0.0, 0.0], 0.05)
    camera = ROI + np.array([0.35, 0.0, 0.0])
    law = Unveiling(time_constant=0.0, stall_time=100.0)
    law.observe(camera, [], leaf, predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.0)
    remembered = law.next_best_view.memory.points.shape[0]
    assert remembered > 0 and law.clear_fraction == 0.0
    for k in range(1, 61):
        law.observe(camera, [], np.zeros((0, 3)), predicted_stem_points=STEM, roi_centre=ROI, timestamp=0.1 * k)
        assert law.clear_fraction == 0.0 and np.linalg.norm(law.raw[:3]) > 0.0
    assert law.next_best_view.memory.points.shape[0] == remembered
    law.observe(camera, [], [[0.5, 0.5, 0.5]], predicted_stem_points=STEM, roi_centre=ROI, timestamp=6.2)
    assert law.next_best_view.memory.points.shape[0] < remembered  # expired on a frame that saw something
