"""The obstacle map's live bits (one bit per cell: log-odds above clamp_min) against the kernel they replaced.

Oracle: main ce2c8f7's ``integrate_frame`` (``_reference_map_kernels.py``, copied verbatim), which
stamps every cell a clearing ray crosses and tests the stamp first. Both maps get the same
frames, exclusion regions, erases and clears; after every call the maps must be equal bit for
bit (log-odds, block lists, versions, stats), except the ``cells_cleared`` count, which now
counts only cells whose log-odds a miss lowered (checked against the log-odds themselves).
The live bits must equal ``log_odds > clamp_min`` after every call.
"""

from __future__ import annotations

import copy
import types

import numpy as np
import pytest

from harvest_qp.interface import OBSTACLE, STEM, PointCloud
from harvest_qp.perception import _map_kernels as K
from harvest_qp.perception import obstacle_map as om
from harvest_qp.perception.obstacle_map import ExclusionRegion, ObstacleMap
from tests.perception import _reference_map_kernels as R
from tests.perception.test_obstacle_map import SMALL, cast, look_at

# ObstacleMap.update with the reference kernel: the same module, integrate_frame without the live bits.
_OLD_K = types.SimpleNamespace(**{name: getattr(K, name) for name in dir(K) if not name.startswith("__")})
_OLD_K.integrate_frame = lambda *args: R.integrate_frame(*args[:-1])


def _old_update(m, cloud, **kw):
    om.K = _OLD_K
    try:
        return m.update(cloud, **kw)
    finally:
        om.K = K


def _live_bits(m):
    return np.packbits(m.log_odds > m.clamp_min, bitorder="little").view(np.uint64)


def _assert_same(old, new, s_old=None, s_new=None, before=None):
    assert np.array_equal(old.log_odds, new.log_odds)
    assert np.array_equal(old._block_count, new._block_count)
    assert np.array_equal(old._block_cells, new._block_cells)
    assert np.array_equal(old._block_stamp, new._block_stamp) and old._version == new._version
    assert np.array_equal(new._live, _live_bits(new)), "live bits differ from log_odds > clamp_min"
    # Stamps differ only where the old kernel stamped a cell already at clamp_min (later than the new one).
    differ = old._stamp != new._stamp
    assert np.all(old.log_odds[differ] == old.clamp_min) and np.all(old._stamp[differ] > new._stamp[differ])
    if s_old is not None:
        fields = [f for f in s_old.__dataclass_fields__ if f != "cells_cleared"]
        assert {f: getattr(s_old, f) for f in fields} == {f: getattr(s_new, f) for f in fields}
        # before: the log-odds after the frame's region erase, when the rays start.
        lowered = int(np.count_nonzero(new.log_odds < before)) - s_new.stem_erased
        assert s_new.cells_cleared == lowered


def _log_odds_after_erase(m, exclude):
    """The log-odds of ``m`` once ``update(..., exclude=exclude)`` has erased the regions (a copy)."""
    probe = copy.deepcopy(m)
    if exclude:
        probe.erase(exclude)
    return probe.log_odds


def _scene_frames(rng, n_frames):
    """A camera swaying in front of a wall, leaves that come and go (so cells reach clamp_min and
    are hit again), a stem, noise points; per frame an exclusion capsule that moves."""
    wall = ([0.805, 0.0, 1.005], [0.0, 0.3, 0.0], [0.0, 0.0, 0.25], OBSTACLE)
    frames = []
    for k in range(n_frames):
        eye = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.02, 3)
        pose = look_at(eye, [1.0, rng.normal(0, 0.05), 1.0 + rng.normal(0, 0.05)])
        rects = [wall]
        # A leaf that is there for 8 frames, gone for 8 (its cells cleared to clamp_min), back...
        if (k // 8) % 2 == 0:
            rects.append(([0.5 + 0.005, 0.02 * (k % 3), 1.005], [0.0, 0.04, 0.0], [0.0, 0.0, 0.04], OBSTACLE))
        rects.append(([0.65, -0.12, 1.0], [0.0, 0.008, 0.0], [0.0, 0.0, 0.15], STEM))
        c = cast(pose, rects, size=(48, 64))
        noise = rng.random(len(c)) < 0.01  # a few points pulled toward the camera (hits in cleared space)
        pts = c.points.copy()
        pts[noise] = eye + rng.uniform(0.2, 0.9, (int(noise.sum()), 1)) * (pts[noise] - eye)
        cloud = PointCloud(pts, c.labels, c.colors, c.camera_pose, 0.0, c.depth, c.pixels, c.image_size)
        centre = (0.45 + 0.01 * k % 0.2, -0.1, 1.0)
        frames.append((cloud, [ExclusionRegion(centre, (centre[0], 0.0, 1.05), 0.04)]))
    return frames


@pytest.mark.parametrize("options", [{}, {"no_return_range": (0.1, 0.6)}, {"clear_stride": 1}])
def test_live_bits_give_the_reference_kernels_map_frame_by_frame(options):
    """60 frames (leaves hit, cleared to clamp_min, hit again; a stem; exclusion regions; an erase
    and a clear on the way): the same map as main's kernel after every call. Catches a live bit
    not set when a hit lifts a cell off clamp_min (the rays then skip it: the log-odds differ),
    a bit not cleared when a miss reaches clamp_min or not reset by clear() (the bit check), a
    ray that still stamps or skips a cell wrongly, and a wrong cells_cleared count."""
    rng = np.random.default_rng(7)
    old, new = ObstacleMap(bounds=SMALL, **options), ObstacleMap(bounds=SMALL, **options)
    reached_clamp = False
    for k, (cloud, exclude) in enumerate(_scene_frames(rng, 60)):
        before = _log_odds_after_erase(new, exclude)
        s_old = _old_update(old, cloud, exclude=exclude)
        s_new = new.update(cloud, exclude=exclude)
        _assert_same(old, new, s_old, s_new, before)
        reached_clamp = reached_clamp or bool(np.any(new.log_odds == new.clamp_min))
        if k == 30:
            region = [ExclusionRegion((0.5, -0.2, 1.0), (0.8, 0.2, 1.0), 0.05)]
            assert old.erase(region) == new.erase(region)
            _assert_same(old, new)
        if k == 45:
            old.clear()
            new.clear()
            _assert_same(old, new)
    assert reached_clamp and new.num_occupied > 0


def test_live_bits_on_random_clouds_match_the_reference_kernel():
    """Random clouds (points anywhere in and around the grid, random labels, NaNs) from random
    camera positions, 40 frames: the same map as main's kernel after every frame."""
    rng = np.random.default_rng(3)
    old, new = ObstacleMap(bounds=SMALL, clear_stride=1), ObstacleMap(bounds=SMALL, clear_stride=1)
    lo, hi = np.array(SMALL[0]), np.array(SMALL[1])
    for _ in range(40):
        pose = look_at(rng.uniform(lo, hi), rng.uniform(lo, hi))
        n = 3000
        # Points clustered on a few spots, so cells get hits and many misses in the same frames.
        spots = rng.uniform(lo - 0.05, hi + 0.05, (5, 3))
        pts = spots[rng.integers(0, 5, n)] + rng.normal(0, 0.05, (n, 3))
        pts[rng.random(n) < 0.01, 1] = np.nan
        labels = rng.choice(np.array([STEM, OBSTACLE, OBSTACLE, OBSTACLE], np.int8), n)
        pixels = np.column_stack([rng.integers(0, 60, n), rng.integers(0, 80, n)]).astype(np.int32)
        cloud = PointCloud(pts, labels, np.zeros((n, 3), np.uint8), pose, 0.0, np.ones(n), pixels, (60, 80))
        before = new.log_odds.copy()
        s_old = _old_update(old, cloud)
        s_new = new.update(cloud)
        _assert_same(old, new, s_old, s_new, before)
    assert np.any(new.log_odds == new.clamp_min)
