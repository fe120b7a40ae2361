"""The compiled per-tick kernels of the loop and the laws equal the Python/numpy paths, bit for bit.

``references._kernels.dot3`` reproduces numpy's dot product of two 3-vectors (OpenBLAS's ddot,
a fused multiply-add chain); ``HarvestController._camera_references`` (one compiled call for
V_cr + keep-out + V_cu and the roll reference) must equal ``_camera_twist`` + ``_roll_reference``
(the Python paths, themselves tested against the checked laws and the numpy formulas in
test_fast_paths.py); ``StemStretching._update_floats`` must equal the checked ``update``.
Oracles: numpy's ``dot``, exact rational arithmetic (``fractions.Fraction``), the Python paths.
Exact equality of bit patterns is asserted (-0.0 differs from 0.0) where numpy's dot is the
kernels' fused chain (``tests.helpers.assert_as_numpy``; this project's machines): the closed
loop's logged results must not move. On a machine whose BLAS sums without fma (e.g.
``OPENBLAS_CORETYPE=Sandybridge``) numpy's paths differ from the kernels in the last bits, and
the comparisons with numpy are to round-off; ``dot3`` against exact rational arithmetic stays exact.
"""

from __future__ import annotations

import copy
import math
from fractions import Fraction

import numpy as np
import pytest

from harvest_qp.loop.controller import HarvestController
from harvest_qp.loop.settings import check_settings
from harvest_qp.references import StemStretching
from harvest_qp.references._kernels import dot3
from tests.helpers import assert_as_numpy, random_pose


def _bits(values) -> list[int]:
    """The IEEE bit patterns (so that -0.0 differs from 0.0, and NaN equals itself)."""
    return np.asarray(values, dtype=np.float64).reshape(-1).view(np.int64).tolist()


def _fused(a: float, b: float, c: float) -> float:
    """a * b + c rounded once, from exact rationals (float(Fraction) rounds to nearest even)."""
    return float(Fraction(a) * Fraction(b) + Fraction(c))


def test_dot3_equals_numpys_dot_and_the_exact_fused_chain():
    """numpy's ``a.dot(b)`` on contiguous and strided 3-vectors (as the loop's poses give them),
    over magnitudes from 1e-6 to 1e6, and the correctly rounded chain fma(a2, b2, fma(a1, b1,
    fma(a0, b0, 0))) computed with exact rationals. Catches: a plain sum of products (differs in
    the last bit on ~1/3 of these), the chain summed from the other end, the first product not
    added to +0.0 (its sign of zero)."""
    rng = np.random.default_rng(31)
    poses = rng.normal(size=(3000, 4, 4)) * 10.0 ** rng.integers(-6, 7, size=(3000, 1, 1))
    others = rng.normal(size=(3000, 3)) * 10.0 ** rng.integers(-3, 4, size=(3000, 1))
    for i in range(3000):
        a, b = poses[i, :3, 2], others[i]  # a: a strided column view
        expected = float(a.dot(b))
        got = dot3(*a.tolist(), *b.tolist())
        assert_as_numpy(got, expected)
        assert_as_numpy(got, float(a.copy().dot(b)))
        if i < 500:
            (a0, a1, a2), (b0, b1, b2) = a.tolist(), b.tolist()
            assert _bits(got) == _bits(_fused(a2, b2, _fused(a1, b1, _fused(a0, b0, 0.0))))
    # Signed zeros: numpy's ddot starts from +0.0.
    for a, b in (((-0.0, 0.0, -0.0), (1.0, 1.0, 1.0)), ((0.0, -1.0, 0.0), (-1.0, 0.0, -1.0))):
        assert_as_numpy(dot3(*a, *b), float(np.array(a).dot(np.array(b))))


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def _state(c: HarvestController, rng, i: int) -> tuple[np.ndarray, np.ndarray]:
    """A random reference state of ``c``: ROI filter, V_cu filter, camera pose, stem direction.
    Every 3rd pose lies inside the keep-out distance, every 7th direction is along the
    optical axis (no roll), every 2nd a strided view (the gripper's y axis, as in the loop)."""
    r = c.settings["reaching"]
    centre = 0.3 * rng.normal(size=3)
    c.reaching.reset(centre)
    c.reaching.set_roi_centre(centre + 0.05 * rng.normal(size=3))
    c.unveiling.reset()
    c.unveiling.raw = 0.1 * rng.normal(size=6)
    c.unveiling.value = 0.1 * rng.normal(size=6)
    pose = random_pose(rng)
    if i % 3 == 0:
        pose[:3, 3] = centre + rng.uniform(0.1, 0.95) * r["min_distance_factor"] * r["radius"] * pose[:3, 2]
    if i % 7 == 0:
        direction = pose[:3, 2].copy()
    elif i % 2:
        direction = random_pose(rng)[:3, 1]
    else:
        direction = rng.normal(size=3)
    return pose, direction


def _both(c: HarvestController, pose: np.ndarray, direction: np.ndarray):
    """(the kernel path's outputs and states, the Python path's), from the same state."""
    reaching, unveiling = copy.deepcopy(c.reaching), copy.deepcopy(c.unveiling)
    rows = pose[:3].tolist()
    V, roll, angle = c._camera_references(pose, 0.002, rows, direction)
    got = (V, roll, angle, c.reaching.roi_centre, c.reaching.theta, c.reaching.distance, c.unveiling.value)
    c.reaching, c.unveiling = reaching, unveiling
    V = c._camera_twist(pose, 0.002, rows)
    roll, angle = c._roll_reference(pose, direction, rows)
    expected = (V, roll, angle, c.reaching.roi_centre, c.reaching.theta, c.reaching.distance, c.unveiling.value)
    return got, expected


@pytest.mark.parametrize("unveil", [True, False])
def test_camera_references_equal_the_python_paths(controller, unveil):
    """V (6 floats), the roll twist and angle, and the new p_r, theta, |p_r - p_c| and V_cu value
    of the kernel path equal ``_camera_twist`` + ``_roll_reference``'s, with V_cu on and off,
    inside and outside the keep-out distance, with and without a roll. Catches: y x d swapped,
    the p_r filter reassociated, the keep-out read from the old p_r, a state not committed."""
    c = controller
    rng = np.random.default_rng(32)
    c.settings["unveiling"]["enabled"] = unveil
    kinds = {"keep_out": 0, "no_roll": 0}
    try:
        for i in range(900):
            pose, direction = _state(c, rng, i)
            got, expected = _both(c, pose, direction)
            for a, b in zip(got, expected):
                assert_as_numpy(a, b)
            assert type(got[0]) is list and type(got[0][0]) is float
            kinds["keep_out"] += c.reaching.distance < 0.9 * c.settings["reaching"]["radius"]
            kinds["no_roll"] += math.isnan(got[2])
    finally:
        c.settings["unveiling"]["enabled"] = True
    assert kinds["keep_out"] > 200 and kinds["no_roll"] > 100


def test_camera_references_without_unveiling_keep_the_sign_of_zero(controller):
    """With V_cu off, inside the ROI (between the keep-out distance 0.9 r and V_cr's 0.95 r) V_cr's
    linear part is 0 * e_pc, -0.0 where e_pc < 0, which the numpy sum V_cr + zeros(6) turned
    into 0.0. Catches: the kernel's ``+ 0.0`` steps left out (-0.0 handed on)."""
    c = controller
    rng = np.random.default_rng(36)
    c.settings["unveiling"]["enabled"] = False
    try:
        r = c.settings["reaching"]
        for _ in range(50):
            centre = 0.3 * rng.normal(size=3)
            c.reaching.reset(centre)
            pose = random_pose(rng)
            ahead = pose[:3, 2] + 0.3 * pose[:3, 0]  # off the optical axis (not the degenerate rotation)
            pose[:3, 3] = centre - 0.925 * r["radius"] * ahead / np.linalg.norm(ahead)  # p_r at 0.925 r
            got, expected = _both(c, pose, pose[:3, 1].copy())
            assert c.reaching.theta > 0.1
            assert not any(expected[0][:3])
            for a, b in zip(got, expected):
                assert_as_numpy(a, b, exact_zeros=True)
    finally:
        c.settings["unveiling"]["enabled"] = True


def test_camera_references_fall_back_where_the_kernel_does_not_apply(controller):
    """The ROI on the optical axis (the degenerate minimum rotation, ahead and behind) and zero
    filter time constants take the Python paths: the same results. Catches: the kernel's
    degenerate flag ignored (its outputs are then not computed)."""
    c = controller
    rng = np.random.default_rng(33)
    for i in range(40):
        pose, direction = _state(c, rng, 1)
        centre = c.reaching.roi_centre.copy()
        c.reaching.reset(centre)
        pose[:3, 3] = centre - (0.4 if i % 2 else -0.4) * pose[:3, 2]
        got, expected = _both(c, pose, direction)
        for a, b in zip(got, expected):
            assert _bits(a) == _bits(b)
        assert c.reaching.theta in (0.0, math.pi)
    tau_r, tau_u = c.reaching.roi_time_constant, c.unveiling.time_constant
    try:
        c.reaching.roi_time_constant, c.unveiling.time_constant = 0.0, 0.0
        for i in range(20):
            pose, direction = _state(c, rng, i)
            got, expected = _both(c, pose, direction)
            for a, b in zip(got, expected):
                assert _bits(a) == _bits(b)
    finally:
        c.reaching.roi_time_constant, c.unveiling.time_constant = tau_r, tau_u


def test_camera_references_leave_new_arrays(controller):
    """The new p_r and V_cu value are new arrays each tick (as the Python paths leave them): an
    array read from the laws earlier keeps its values. Catches: the filter states written in place."""
    c = controller
    rng = np.random.default_rng(34)
    pose, direction = _state(c, rng, 1)
    before_p_r, before_value = c.reaching.roi_centre, c.unveiling.value
    kept = before_p_r.copy(), before_value.copy()
    c._camera_references(pose, 0.002, pose[:3].tolist(), direction)
    assert c.reaching.roi_centre is not before_p_r and c.unveiling.value is not before_value
    assert _bits(before_p_r) == _bits(kept[0]) and _bits(before_value) == _bits(kept[1])
    assert not np.array_equal(c.reaching.roi_centre, kept[0])


def test_stretching_floats_equal_update():
    """``StemStretching._update_floats`` (the compiled projections, v_gw, diagnostics) returns
    V_g as the checked ``update``'s floats and leaves the same diagnostics and v_gt, through the
    integral's latch and saturation, with strided force views. Catches: n . e_pg or n . f summed
    in Python, v_gw's sign, the alignment's atan2 arguments swapped, position_error from e_pg
    instead of its projection."""
    rng = np.random.default_rng(35)
    names = ("position_error", "alignment", "force_along_nc", "integral", "saturated")
    for _ in range(300):
        checked, fast = StemStretching(), StemStretching()
        stem_base = 0.3 * rng.normal(size=3)
        target = stem_base + 0.1 * rng.normal(size=3)
        checked.set_target(stem_base, target)
        fast.set_target(stem_base, target)
        for _ in range(5):
            pose = random_pose(rng)
            force = 4.0 * rng.normal(size=(3, 2))[:, 0]
            expected = checked.update(pose, force, 0.002)
            got = fast._update_floats(pose, force, 0.002)
            assert type(got) is list
            assert_as_numpy(got, expected)
            assert_as_numpy(fast.v_gt, checked.v_gt)
            assert_as_numpy([getattr(fast, n) for n in names], [getattr(checked, n) for n in names])


@pytest.mark.parametrize("layout", ["F", "C"])
def test_hold_terms_equal_numpys_matrix_product(layout):
    """R_g R_hold^T and k (p_g - p_hold) of ``_tick_kernels.hold_terms`` equal numpy's ``@`` and
    the element-wise formula, with R_hold^T as the loop keeps it (a transposed view, F order) and
    C-ordered. Catches: the product's entries summed in Python order (no fma) or transposed."""
    from harvest_qp.loop._tick_kernels import hold_terms

    rng = np.random.default_rng(37)
    linear, rotation = np.empty(3), np.empty((3, 3))
    for _ in range(2000):
        pose, hold = random_pose(rng), random_pose(rng)
        hold_rotation_T = hold[:3, :3].T if layout == "F" else hold[:3, :3].T.copy()
        hold_translation = hold[:3, 3].copy()
        hold_terms(pose, hold_translation, hold_rotation_T, -0.7, linear, rotation)
        assert_as_numpy(rotation, pose[:3, :3] @ hold_rotation_T)
        assert_as_numpy(linear, -0.7 * (pose[:3, 3] - hold_translation))


@pytest.mark.parametrize("position", [0, 1, 2])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_stretching_refuses_a_non_finite_force_before_any_state_change(position, bad):
    """With ``check_force`` a non-finite force raises InvalidInputError naming the argument, and
    the force integral and diagnostics are left as they were (the loop hands the robot's reading
    unchecked to this path). Catches: the finiteness test skipping a position, or run after the
    force command advanced the integral."""
    from harvest_qp.exceptions import InvalidInputError

    law = StemStretching(integration_threshold=0.0)
    law.set_target(np.zeros(3), np.array([0.0, 0.0, 0.1]))
    pose = random_pose(np.random.default_rng(38))
    law._update_floats(pose, np.array([0.0, 0.0, 200.0]), 0.002, check_force="force")  # saturates
    state = ("integral", "saturated", "position_error", "alignment", "force_along_nc")
    before = [getattr(law, name) for name in state] + [law.v_gt.tolist()]
    assert law.saturated
    force = np.array([0.5, -0.3, 2.0])
    force[position] = bad
    with pytest.raises(InvalidInputError, match="force"):
        law._update_floats(pose, force, 0.002, check_force="force")
    assert [getattr(law, name) for name in state] + [law.v_gt.tolist()] == before
    assert len(law._update_floats(pose, force, 0.002)) == 6  # unchecked (as _update_unchecked): no error


def test_a_copied_controller_computes_the_same_references(controller):
    """A deep copy (or an unpickled controller) has its own kernel output buffer; the roll's
    np.arctan2 must read and write that buffer, not copies of the old views. Catches: the
    views kept after a copy (the roll angle then read from a slot nothing wrote)."""
    c = controller
    rng = np.random.default_rng(39)
    for i in (1, 3, 5, 9, 11, 13, 15, 17, 19, 23):  # none along the optical axis: every one rolls
        pose, direction = _state(c, rng, i)
        twin = copy.deepcopy(c)
        got = twin._camera_references(pose, 0.002, pose[:3].tolist(), direction)
        expected = c._camera_references(pose, 0.002, pose[:3].tolist(), direction)
        for a, b in zip(got, expected):
            assert _bits(a) == _bits(b)
        assert not math.isnan(expected[2])


def test_the_unchecked_row_and_columns_equal_the_checked_constructors():
    """``_ValueRow._built`` / ``_PairColumns._built`` (the controller's per-tick constructors without
    the checks) give what the checked constructors give for the same, well-formed data: same
    attributes (types, values, bytes), same reading. Catches: attributes swapped or a missing
    name dropped in the unchecked constructor."""
    from harvest_qp.runner import _PairColumns, _ValueLayout, _ValueRow

    layout = _ValueLayout([("a", ()), ("b", (3,)), ("c", ())])
    row = np.array([1.5, 2.0, -0.0, 3.0, math.nan])
    checked, built = _ValueRow(layout, row.copy(), ("c",)), _ValueRow._built(layout, row.copy(), ("c",))
    assert (built.layout, built.missing) == (checked.layout, checked.missing)
    assert built.row.tobytes() == checked.row.tobytes()
    assert list(built) == list(checked) == ["a", "b"] and built["a"] == 1.5
    assert _bits(built["b"]) == _bits(checked["b"])
    distances = np.array([0.25, -0.0, 1e-3])
    checked = _PairColumns(["x", "y", "z"], ["u", "v", "w"], distances)
    built = _PairColumns._built(["x", "y", "z"], ["u", "v", "w"], distances.tolist())
    assert (built.first, built.second) == (checked.first, checked.second)
    assert type(built.distances) is list and _bits(built.distances) == _bits(checked.distances)
    assert list(built) == list(checked) and built == checked
