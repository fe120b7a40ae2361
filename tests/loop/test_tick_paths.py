"""Per-tick helpers of HarvestController equal the numpy expressions they replace, bit for bit.

Oracles: the previous numpy formulas written out here (on numpy float64 scalars), and the
item-by-item dict of the previous ``_log_values``. Exact equality (bit patterns) is asserted:
the closed loop's results must not move (``/work/notes/compare_golden.py``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.loop.controller import HarvestController, _wrap_half_turn
from harvest_qp.loop.settings import check_settings


def _bits(value: float) -> int:
    return int(np.array(value, dtype=np.float64).view(np.int64))


def _wrap_numpy(angle) -> float:
    """The previous implementation: the arithmetic on numpy float64 scalars."""
    angle = np.float64(angle)
    return float((angle + np.pi / 2) % np.pi - np.pi / 2)


def test_wrap_half_turn_equals_the_numpy_scalar_formula():
    """Catches: ``math.fmod`` for the floor remainder (other sign for negative angles), the
    half turn added after the remainder, a wrap into [0, pi) instead of [-pi/2, pi/2)."""
    rng = np.random.default_rng(21)
    angles = np.concatenate((
        rng.uniform(-math.pi, math.pi, 4000),
        rng.uniform(-1e-12, 1e-12, 200),
        np.array([0.0, -0.0, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 3 * math.pi / 2, -3 * math.pi / 2,
                  np.nextafter(math.pi / 2, 0), np.nextafter(-math.pi / 2, 0), 1e-300, -1e-300]),
    ))
    for a in angles.tolist():
        got = _wrap_half_turn(np.float64(a))
        assert type(got) is float
        assert _bits(got) == _bits(_wrap_numpy(a)), a
        assert _bits(_wrap_half_turn(a)) == _bits(got)
    assert -math.pi / 2 <= _wrap_half_turn(2.0) < math.pi / 2


@pytest.fixture(scope="module")
def controller():
    return HarvestController(check_settings({}))


def test_log_values_keys_and_values_as_item_by_item(controller):
    """The logged values keep their keys, order (after the tick's own ``roll_error``) and
    objects. Catches: a key renamed or dropped, the NaN vector for a missing p_sb replaced by
    None, ``unveiling_pairs`` logged as an int."""
    c = controller
    c.reaching.reset(np.array([0.1, 0.2, 0.3]))
    T_c = np.eye(4)
    T_c[:3, 3] = (0.5, 0.0, 0.4)
    V_c, V_g = np.arange(6.0), -np.arange(6.0)
    values = c._log_values(T_c, V_c, V_g, 1.5, into={"roll_error": 0.25}, roi_distance=0.7)
    assert list(values) == ["roll_error", "phase", "p_r", "p_c", "z_c", "x_c", "p_sb", "p_gd", "n_c", "V_c", "V_g",
                            "force_nc", "theta", "roi_distance", "position_error", "alignment", "unveiling_pairs"]
    assert values["roll_error"] == 0.25 and values["phase"] == 0.0 and type(values["phase"]) is float
    assert values["V_c"] is V_c and values["V_g"] is V_g and values["force_nc"] == 1.5
    np.testing.assert_array_equal(values["p_c"], T_c[:3, 3])
    np.testing.assert_array_equal(values["x_c"], T_c[:3, 0])
    np.testing.assert_array_equal(values["z_c"], T_c[:3, 2])
    assert values["p_r"] is c.reaching.roi_centre
    assert np.isnan(values["p_sb"]).all() and values["p_sb"].shape == (3,)
    assert math.isnan(values["position_error"]) and math.isnan(values["alignment"])
    assert values["roi_distance"] == 0.7 and type(values["unveiling_pairs"]) is float
    fresh = c._log_values(T_c, V_c, V_g, 1.5)
    assert list(fresh)[0] == "phase"
    assert _bits(fresh["roi_distance"]) == _bits(np.linalg.norm(c.reaching.roi_centre - T_c[:3, 3]))


def test_math_degrees_is_numpys_degrees():
    """The pre-cut alignment test converts with math.degrees where it used np.degrees.
    Catches: a conversion as x / (pi / 180) (another rounding on ~1/3 of the angles)."""
    rng = np.random.default_rng(22)
    for a in np.concatenate((rng.uniform(-4, 4, 5000), [0.0, -0.0, 1e-300, math.pi])).tolist():
        assert _bits(math.degrees(a)) == _bits(np.degrees(a))


def test_force_filter_fraction_is_numpys_expm1_per_step(controller):
    """Catches: the cached fraction kept after dt or the time constant changed."""
    c = controller
    for dt, tau in ((0.002, 0.1), (0.002, 0.1), (0.001, 0.1), (0.001, 0.37)):
        got = c._force_filter_fraction(dt, tau)
        assert _bits(got) == _bits(-np.expm1(-dt / tau))
