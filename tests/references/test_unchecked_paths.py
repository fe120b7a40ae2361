"""The control loop's unchecked fast paths of the reference laws equal the checked numpy ones, bit for bit.

The closed loop (``harvest_qp.loop.controller``) calls private variants of the laws
(``ReachingCentering._update_unchecked``, ``StemStretching._update_unchecked``,
``GraspFeedForward._terms``, ``Unveiling._update_list``) that do the element-wise arithmetic
on Python floats instead of numpy. Oracle: the public, checked methods, which keep the
numpy formulas of the paper's equations (themselves tested against hand values in the other
files). Exact equality is asserted, not closeness: the loop's logged results must not move
(``/work/notes/compare_golden.py``), and any reordered operation shows as a last-bit
difference on some of these random poses.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.references import GraspFeedForward, ReachingCentering, StemStretching, Unveiling
from harvest_qp.references._checks import cross3, cross_rows
from tests.helpers import assert_as_numpy, random_pose


def _bits(values) -> list[int]:
    """The IEEE bit patterns (so that -0.0 differs from 0.0, and NaN equals itself)."""
    return np.asarray(values, dtype=np.float64).reshape(-1).view(np.int64).tolist()



def test_cross3_equals_np_cross_bit_for_bit():
    """Catches: a cross product written with another operand order or sign (e.g. b x a)."""
    rng = np.random.default_rng(1)
    for _ in range(2000):
        a, b = rng.normal(size=3) * rng.uniform(1e-3, 1e3), rng.normal(size=3)
        assert _bits(cross3(a, b)) == _bits(np.cross(a, b))


def test_cross_rows_equals_np_cross_bit_for_bit():
    """Row-wise cross products of the unveiling law (eq:omega_pivot, eq:v_c2) as np.cross gives them.
    Catches: a component's operands swapped, an empty (0, 3) input mishandled."""
    rng = np.random.default_rng(6)
    a, b = rng.normal(size=(500, 3)) * rng.uniform(1e-3, 1e3, size=(500, 1)), rng.normal(size=(500, 3))
    assert _bits(cross_rows(a, b)) == _bits(np.cross(a, b))
    assert cross_rows(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0, 3)


def test_reaching_fast_path_equals_update():
    """V_cr, theta, |e_pc| and the filtered p_r of ``_update_unchecked`` equal ``update``'s exactly,
    including the degenerate poses where the ROI lies on the optical axis (ahead and behind).

    Catches: the filter written as (1 - a) p_r + a p_target (same value, other bits), the
    cosine taken from Python floats instead of numpy's dot, a dropped degenerate branch."""
    rng = np.random.default_rng(2)
    for i in range(1500):
        checked, fast = ReachingCentering(radius=0.3), ReachingCentering(radius=0.3)
        centre = 0.3 * rng.normal(size=3)
        checked.reset(centre)
        fast.reset(centre)
        target = centre + 0.2 * rng.normal(size=3)
        checked.set_roi_centre(target)
        fast.set_roi_centre(target)
        pose = random_pose(rng)
        if i % 5 == 0:  # ROI on the optical axis: theta 0 or pi (k undefined)
            pose[:3, 3] = centre - (0.4 if i % 2 else -0.4) * pose[:3, 2]
            checked.reset(centre)
            fast.reset(centre)
        for _ in range(3):
            expected = checked.update(pose, 0.002)
            got = fast._update_unchecked(pose, 0.002)
            assert _bits(got) == _bits(expected)
            assert _bits([fast.theta, fast.distance]) == _bits([checked.theta, checked.distance])
            assert _bits(fast.roi_centre) == _bits(checked.roi_centre)


def test_stretching_fast_path_equals_update():
    """V_g and every diagnostic of ``_update_unchecked`` equal ``update``'s exactly, through the
    integral's latch and saturation (forces up to 12 N around f_d = 3 N).

    Catches: v_f's sign or the projection reassociated, the rotation term with n x y swapped."""
    rng = np.random.default_rng(3)
    names = ("position_error", "alignment", "force_along_nc", "integral", "saturated")
    for _ in range(400):
        checked, fast = StemStretching(), StemStretching()
        stem_base = 0.3 * rng.normal(size=3)
        target = stem_base + 0.1 * rng.normal(size=3)
        checked.set_target(stem_base, target)
        fast.set_target(stem_base, target)
        for _ in range(6):
            pose = random_pose(rng)
            force = 4.0 * rng.normal(size=3)
            expected = checked.update(pose, force, 0.002)
            got = fast._update_unchecked(pose, force.copy(), 0.002)
            assert_as_numpy(got, expected)
            assert_as_numpy(fast.v_gt, checked.v_gt)
            assert_as_numpy([getattr(fast, n) for n in names], [getattr(checked, n) for n in names])


@pytest.mark.parametrize("normalise", [True, False])
def test_feed_forward_fast_path_equals_call(normalise):
    """Catches: |p_c - p_sb|^2 summed in Python (differs from numpy's dot in the last bit)."""
    rng = np.random.default_rng(4)
    law = GraspFeedForward(normalise=normalise)
    for _ in range(2000):
        v, camera, stem_base = 0.05 * rng.normal(size=3), rng.normal(size=3), rng.normal(size=3)
        lever = (camera - stem_base).tolist()
        assert_as_numpy(law._terms(v.tolist(), lever), law(v, camera, stem_base))
    assert_as_numpy(law._terms([0.1, 0.0, 0.0], [0.0, 0.0, 0.0]), law([0.1, 0.0, 0.0], np.zeros(3), np.zeros(3)))


@pytest.mark.parametrize("time_constant", [0.2, 0.0])
def test_unveiling_filter_fast_path_equals_update(time_constant):
    """``_update_list`` leaves the same :attr:`value` as ``update`` and returns it as floats.

    Catches: the low-pass written as (1 - a) v + a raw."""
    rng = np.random.default_rng(5)
    checked, fast = Unveiling(time_constant=time_constant), Unveiling(time_constant=time_constant)
    for _ in range(300):
        raw = rng.normal(size=6)
        checked.raw, fast.raw = raw.copy(), raw.copy()
        expected = checked.update(0.002)
        got = fast._update_list(0.002)
        assert _bits(got) == _bits(expected)
        assert _bits(fast.value) == _bits(checked.value)
        assert math.isfinite(got[0])
