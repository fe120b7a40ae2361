"""p_sb from the approach's close frames (:class:`harvest_qp.perception.StemTopMemory`).

Oracle: a hand-built stem, a cylinder of known axis and top end, whose near half is sampled as a
depth camera sees it; the "occluded" frames leave out its top part, as the branch did on sweep
scene 16291 (the closed-loop check is ``tests/loop/test_stem_memory_loop.py``).
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception import StemTopMemory, fit_stem

TOP = np.array([0.5, -0.1, 1.2])  # the true stem base [m]
AXIS = np.array([0.3, 0.0, -0.954])  # from the branch towards the crop
AXIS = AXIS / np.linalg.norm(AXIS)
RADIUS = 0.003  # [m]
LENGTH = 0.06  # [m]


def _stem_frame(camera: np.ndarray, hidden_top: float, *, step: float = 0.001) -> np.ndarray:
    """Points on the near half of the stem cylinder as seen from ``camera``, the top ``hidden_top`` [m]
    left out (an occluder in front of it)."""
    along = np.arange(hidden_top, LENGTH + 1e-9, step)
    view = camera - (TOP + 0.5 * LENGTH * AXIS)
    side = np.cross(AXIS, view)
    side /= np.linalg.norm(side)
    front = np.cross(side, AXIS)  # towards the camera, across the axis
    angles = np.linspace(-0.45 * np.pi, 0.45 * np.pi, 9)
    ring = RADIUS * (np.cos(angles)[:, None] * front + np.sin(angles)[:, None] * side)
    return ((TOP + along[:, None] * AXIS)[:, None, :] + ring[None]).reshape(-1, 3)


CAMERA_LOW = TOP + np.array([-0.30, 0.0, -0.03])  # level with the stem: the top in view
CAMERA_HIGH = TOP + np.array([-0.28, 0.0, 0.09])  # above it: the branch hides the top 12 mm
GRIPPER = TOP + LENGTH * AXIS + np.array([0.0, 0.0, -0.05])


def _fit(points):
    fit = fit_stem(points, GRIPPER)
    assert fit.valid, fit.reason
    return fit


def test_a_top_seen_in_an_earlier_frame_moves_p_sb_back_up_the_stem():
    """Catches p_sb taken from the last frame alone: that frame's fit lies 12 mm down the stem, the memory's
    p_sb within 2 mm of the true top end."""
    memory = StemTopMemory()
    early = _stem_frame(CAMERA_LOW, hidden_top=0.0)
    late = _stem_frame(CAMERA_HIGH, hidden_top=0.012)
    assert memory.add(early, camera_position=CAMERA_LOW, stem_base=_fit(early).base)
    fit = _fit(late)
    assert memory.add(late, camera_position=CAMERA_HIGH, stem_base=fit.base)
    assert np.linalg.norm(fit.base - TOP) > 0.010  # the frame's own p_sb
    reach = memory.extension(fit.base, fit.top.direction)
    p_sb = fit.base - reach * fit.top.direction
    assert np.linalg.norm(p_sb - TOP) < 0.002
    assert 0.009 < reach < 0.013


def test_a_base_in_view_is_left_as_the_frame_has_it():
    """Frames that all see the top: no extension at all (the frame's p_sb stands bit for bit)."""
    memory = StemTopMemory()
    for camera in (CAMERA_LOW, CAMERA_HIGH):
        points = _stem_frame(camera, hidden_top=0.0)
        memory.add(points, camera_position=camera, stem_base=_fit(points).base)
    fit = _fit(_stem_frame(CAMERA_HIGH, hidden_top=0.0))
    assert memory.extension(fit.base, fit.top.direction) == 0.0


def test_far_frames_stray_points_and_other_stems_do_not_move_p_sb():
    """A far view is not kept; up to ``rank`` points above the base, or points off the axis (another
    stem 2 cm aside), do not count."""
    memory = StemTopMemory(max_range=0.45)
    far_camera = TOP + np.array([-0.6, 0.0, 0.0])
    assert not memory.add(_stem_frame(far_camera, 0.0), camera_position=far_camera, stem_base=TOP)
    late = _stem_frame(CAMERA_HIGH, hidden_top=0.012)
    fit = _fit(late)
    memory.add(late, camera_position=CAMERA_HIGH, stem_base=fit.base)
    assert memory.extension(fit.base, fit.top.direction) == 0.0
    strays = TOP + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.004]])  # two single points up the axis
    memory.add(strays, camera_position=CAMERA_HIGH, stem_base=fit.base)
    aside = _stem_frame(CAMERA_HIGH, 0.0) + 0.02 * np.cross(AXIS, [0.0, 1.0, 0.0])
    memory.add(aside, camera_position=CAMERA_HIGH, stem_base=fit.base)
    assert memory.extension(fit.base, fit.top.direction) == 0.0
    memory.add(_stem_frame(CAMERA_LOW, 0.0), camera_position=CAMERA_LOW, stem_base=fit.base)
    assert memory.extension(fit.base, fit.top.direction) > 0.009
    memory.reset()
    assert memory.points.shape == (0, 3)
    assert memory.extension(fit.base, fit.top.direction) == 0.0


def test_the_extension_is_bounded():
    memory = StemTopMemory(max_extension=0.005)
    early = _stem_frame(CAMERA_LOW, 0.0)
    memory.add(early, camera_position=CAMERA_LOW, stem_base=TOP)
    fit = _fit(_stem_frame(CAMERA_HIGH, hidden_top=0.012))
    assert memory.extension(fit.base, fit.top.direction) == pytest.approx(0.005)


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda m: m.add([[0.0, 0.0, np.nan]], camera_position=TOP, stem_base=TOP), "stem_points"),
        (lambda m: m.add(np.zeros((2, 2)), camera_position=TOP, stem_base=TOP), "stem_points"),
        (lambda m: m.add(np.zeros((2, 3)), camera_position=0.1, stem_base=TOP), "camera_position"),
        (lambda m: m.extension(TOP, [0.0, 0.0, 0.0]), "direction"),
        (lambda m: m.extension([np.inf, 0.0, 0.0], AXIS), "stem_base"),
        (lambda m: StemTopMemory(voxel=0.0), "voxel"),
        (lambda m: StemTopMemory(rank=-1), "rank"),
    ],
)
def test_bad_arguments_raise_the_package_error_naming_them(call, name):
    with pytest.raises(InvalidInputError, match=name):
        call(StemTopMemory())


def _memory_with_heights(heights, **kwargs) -> StemTopMemory:
    """A memory holding one point on the axis at each height [m] above TOP, plus the stem below it (0.1 mm
    cells, so that every point keeps its own)."""
    memory = StemTopMemory(voxel=1e-4, **kwargs)
    points = np.vstack([TOP - np.asarray(heights, float)[:, None] * AXIS, _stem_frame(CAMERA_HIGH, 0.0)])
    memory.add(points, camera_position=CAMERA_HIGH, stem_base=TOP)
    return memory


def test_rank_points_above_do_not_count_and_one_more_does():
    """With ``rank`` = 2 the 3rd highest point counts: a run up to 4 mm with two more points at 5 mm reaches
    4 mm, with three 5 mm (an off-by-one that wraps to the highest point would give 5 mm for two)."""
    heights = [0.001, 0.002, 0.003, 0.004]  # a continuous run up to 4 mm, then the points at 5 mm
    assert _memory_with_heights(heights + [0.005, 0.00505]).extension(TOP, AXIS) == pytest.approx(0.004, abs=6e-4)
    three = _memory_with_heights(heights + [0.005, 0.0051, 0.0052])
    assert three.extension(TOP, AXIS) == pytest.approx(0.005, abs=6e-4)
    only_two = StemTopMemory(voxel=1e-4)  # nothing but two points, 2 and 4.5 mm up
    only_two.add(TOP - np.array([[0.002], [0.0045]]) * AXIS, camera_position=CAMERA_HIGH, stem_base=TOP)
    assert only_two.extension(TOP, AXIS) == 0.0


def test_a_reach_under_min_extension_counts_as_none_and_the_axis_may_have_any_length():
    """A top hidden by 2.5 mm gives 0 (under the 3 mm floor); 5 n_st gives what n_st gives."""
    near = _memory_with_heights(np.arange(0.0005, 0.0026, 0.0005))
    assert near.extension(TOP, AXIS) == 0.0
    far = _memory_with_heights(np.arange(0.0005, 0.0101, 0.0005))
    assert far.extension(TOP, 5.0 * AXIS) == far.extension(TOP, AXIS) == pytest.approx(0.009, abs=6e-4)


def test_a_detached_patch_of_stem_labels_does_not_lift_p_sb():
    """A segmenter's mistake kept from one frame: 13 stem-labelled points 15-17 mm up the axis, past a gap
    of 12 mm, give no extension; the same patch joined to p_sb by stem points does (the review's case)."""
    patch = np.linspace(0.015, 0.017, 13)
    assert _memory_with_heights(patch).extension(TOP, AXIS) == 0.0
    joined = np.concatenate([np.arange(0.0005, 0.015, 0.001), patch])
    assert _memory_with_heights(joined).extension(TOP, AXIS) > 0.0165


def test_inconsistent_bounds_are_refused():
    with pytest.raises(InvalidInputError, match="min_extension"):
        StemTopMemory(min_extension=0.05, max_extension=0.03)
    with pytest.raises(InvalidInputError, match="voxel"):
        StemTopMemory(voxel=1e-12)
