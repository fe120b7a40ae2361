"""ObstacleMap and MapCollisionFeed against independent oracles.

Oracles: OctoMap itself (``pyoctomap``: same clouds, same log-odds in every known cell),
a small pinhole ray caster written here (exact hand-countable scenes), a brute-force numpy
search over the occupied cells, and the MuJoCo lab's true geometry measured with coal.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.perception.map_feed import MapCollisionFeed
from harvest_qp.perception.obstacle_map import (
    DEFAULT_CLEAR_RAYS,
    ExclusionRegion,
    ObstacleMap,
    held_crop_exclusions,
)
from harvest_qp.runtime.interface import OBSTACLE, ROBOT, STEM, PointCloud

RES = 0.01
# A small grid for the synthetic scenes (fast to allocate).
SMALL = ((-0.2, -0.4, 0.6), (1.0, 0.4, 1.4))


# --------------------------------------------------------------------------- synthetic camera


def look_at(position, target) -> np.ndarray:
    """Camera pose {C} (z = view direction, x right, y down in the image) looking at ``target``."""
    position, target = np.asarray(position, float), np.asarray(target, float)
    z = target - position
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = position
    return T


def cast(pose, rects, *, size=(96, 128), fov=40.0, noise=None) -> PointCloud:
    """A pinhole camera over rectangles ``(centre, u_half, v_half, label)`` (u, v: half-edge vectors).

    Independent of the lab's camera: the nearest rectangle hit per pixel becomes a point.
    """
    h, w = size
    f = (h / 2) / math.tan(math.radians(fov) / 2)
    v, u = np.meshgrid(np.arange(h) + 0.5, np.arange(w) + 0.5, indexing="ij")
    rays_c = np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u)], -1).reshape(-1, 3)
    rays = rays_c @ pose[:3, :3].T
    o = pose[:3, 3]
    best_t = np.full(rays.shape[0], np.inf)
    best_label = np.zeros(rays.shape[0], np.int8)
    for centre, uh, vh, label in rects:
        centre, uh, vh = (np.asarray(a, float) for a in (centre, uh, vh))
        n = np.cross(uh, vh)
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((centre - o) @ n) / denom
        p = o + t[:, None] * rays
        a = (p - centre) @ uh / (uh @ uh)
        b = (p - centre) @ vh / (vh @ vh)
        hit = (t > 0) & (np.abs(a) <= 1) & (np.abs(b) <= 1) & (t < best_t)
        best_t[hit] = t[hit]
        best_label[hit] = label
    ok = np.isfinite(best_t)
    pts = o + best_t[ok, None] * rays[ok]
    if noise is not None:
        pts = pts + noise
    rows, cols = np.divmod(np.flatnonzero(ok), w)
    return PointCloud(
        points=pts, labels=best_label[ok], colors=np.zeros((pts.shape[0], 3), np.uint8), camera_pose=pose,
        timestamp=0.0, depth=best_t[ok] * rays_c[ok, 2], pixels=np.column_stack([rows, cols]).astype(np.int32),
        image_size=size,
    )  # fmt: skip


CAM = look_at([0.0, 0.0, 1.0], [1.0, 0.0, 1.0])  # looking along +x
WALL = ([0.805, 0.0, 1.005], [0.0, 0.3, 0.0], [0.0, 0.0, 0.25], OBSTACLE)


def leaf_at(x, y=0.0, label=OBSTACLE):
    # Off the cell boundaries (multiples of 1 cm), so a surface is one cell thick.
    return ([x + 0.005, y + 0.005, 1.005], [0.0, 0.04, 0.0], [0.0, 0.0, 0.04], label)


def cells_of(rect) -> np.ndarray:
    """Points on a rectangle, one per ~2 mm (to ask the map about its cells)."""
    centre, uh, vh, _ = (np.asarray(a, float) if i < 3 else a for i, a in enumerate(rect))
    s = np.linspace(-0.95, 0.95, 40)
    a, b = np.meshgrid(s, s)
    return centre + a.reshape(-1, 1) * uh + b.reshape(-1, 1) * vh


# --------------------------------------------------------------------------- the rules


def test_moved_leaf_is_cleared_after_nine_frames():
    """A leaf seen for many frames, then gone: its cells are free after exactly 9 frames.

    OctoMap's defaults (hit 0.7, miss 0.4, clamp 0.971): logit(0.971) = 3.51 needs
    ceil(3.51 / 0.405) = 9 misses. Catches: no ray clearing, a wrong miss value, clearing
    skipped where the rays now end on the wall behind, or more than one miss per frame.
    """
    m = ObstacleMap(bounds=SMALL)
    leaf = leaf_at(0.5)
    for _ in range(20):
        m.update(cast(CAM, [WALL, leaf]))
    on_leaf = cells_of(leaf)
    assert m.is_occupied(on_leaf).all()
    assert m.is_occupied(cells_of(WALL)[np.abs(cells_of(WALL)[:, 1]) > 0.1]).all()
    moved = leaf_at(0.5, y=2.0)  # out of view
    for frame in range(1, 10):
        m.update(cast(CAM, [WALL, moved]))
        if frame < 9:
            assert m.is_occupied(on_leaf).any(), frame
    assert not m.is_occupied(on_leaf).any()
    # The wall behind the leaf, now seen, is in the map; the wall stayed.
    assert m.is_occupied(cells_of(WALL)).mean() > 0.95


def test_pixels_without_return_clear_only_when_asked():
    """A leaf in front of nothing (no return behind it) then gone: OctoMap's rule keeps it
    (no ray passes through); with ``no_return_range`` the empty pixels clear it in 9 frames.

    Catches no-return rays that are never traced, traced along wrong directions (a wrong
    pinhole fit: the leaf's cells would not be crossed) or traced by default.
    """
    leaf = leaf_at(0.5)
    maps = {None: ObstacleMap(bounds=SMALL), (0.1, 1.0): ObstacleMap(bounds=SMALL, no_return_range=(0.1, 1.0))}
    for m in maps.values():
        for _ in range(20):
            m.update(cast(CAM, [leaf]))
        assert m.is_occupied(cells_of(leaf)).all()
    gone = leaf_at(0.5, y=2.0)
    for frame in range(1, 10):
        for key, m in maps.items():
            stats = m.update(cast(CAM, [gone]))
            assert (stats.no_return_rays > 0) == (key is not None)
        if frame < 9:
            assert maps[(0.1, 1.0)].is_occupied(cells_of(leaf)).any()
    assert maps[None].is_occupied(cells_of(leaf)).all()
    assert not maps[(0.1, 1.0)].is_occupied(cells_of(leaf)).any()
    # Cells nearer than the start of the no-return range are kept (an object too close for
    # the camera returns nothing either).
    near_leaf = ([0.055, 0.005, 1.005], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01], OBSTACLE)
    m = ObstacleMap(bounds=SMALL, no_return_range=(0.1, 1.0))
    for _ in range(3):
        m.update(cast(CAM, [near_leaf, WALL]))
    assert m.is_occupied(cells_of(near_leaf)).all()
    for _ in range(10):
        m.update(cast(CAM, []))
    assert m.is_occupied(cells_of(near_leaf)).all()


def test_near_the_camera_the_coarser_clearing_grid_still_clears_moved_leaves_in_nine_frames():
    """With a pixel stride (here 2), rays off the twice coarser grid start near_skip (~0.4 m)
    from the camera. Leaves 0.25 m away (in that zone) and 0.95 m away (beyond it) are both
    cleared in 9 frames, and the map equals the one traced with all rays of the stride grid.

    Catches a near_skip so long that the coarse rays alone, too sparse there, leave cells
    uncrossed (the far leaf would stay)."""
    size = (192, 256)
    near, far = leaf_at(0.25, y=-0.05), leaf_at(0.95, y=0.15)  # side by side in the image
    back = ([1.3, 0.0, 1.0], [0.0, 0.6, 0.0], [0.0, 0.0, 0.5], OBSTACLE)  # beyond the grid: rays only
    maps = [ObstacleMap(bounds=SMALL, clear_stride=2), ObstacleMap(bounds=SMALL, clear_stride=2)]
    for _ in range(20):
        for m in maps:
            m.update(cast(CAM, [back, near, far], size=size))
    assert maps[0].is_occupied(np.vstack([cells_of(near), cells_of(far)])).all()
    maps[1]._pinhole[size] = (1e-9, 0.0, 0.0)  # a focal length that makes near_skip ~0: full rays
    for frame in range(1, 10):
        for m in maps:
            m.update(cast(CAM, [back], size=size))
        if frame < 9:
            assert maps[0].is_occupied(cells_of(near)).any() and maps[0].is_occupied(cells_of(far)).any()
    for m in maps:
        assert not m.is_occupied(np.vstack([cells_of(near), cells_of(far)])).any()
    assert np.array_equal(maps[0].occupied_keys(), maps[1].occupied_keys())


def test_noise_point_is_cleared_after_three_frames():
    """A single spurious point in free space: one hit (0.85), cleared by the 3rd miss (-0.41 each)."""
    m = ObstacleMap(bounds=SMALL, clear_stride=1)
    clean = cast(CAM, [WALL])
    noisy_pts = clean.points.copy()
    i = int(np.argmin(np.abs(clean.pixels[:, 0] - 24) + np.abs(clean.pixels[:, 1] - 32)))
    spurious = CAM[:3, 3] + 0.5 * (noisy_pts[i] - CAM[:3, 3])  # half way along that pixel's ray
    noisy_pts[i] = spurious
    noisy = PointCloud(noisy_pts, clean.labels, clean.colors, clean.camera_pose, 0.0, clean.depth, clean.pixels,
                       clean.image_size)  # fmt: skip
    m.update(noisy)
    assert m.is_occupied(spurious[None])[0]
    m.update(clean)
    m.update(clean)
    assert m.is_occupied(spurious[None])[0]  # 0.847 - 2 * 0.405 = 0.036 > 0
    m.update(clean)
    assert not m.is_occupied(spurious[None])[0]


def test_what_left_the_field_of_view_is_remembered():
    """Cells out of the camera's view keep their log-odds exactly (no decay, no clearing).

    Catches clearing that is not restricted to the rays (e.g. a frustum-wide or global decay).
    """
    m = ObstacleMap(bounds=SMALL)
    leaf = leaf_at(0.5)
    for _ in range(5):
        m.update(cast(CAM, [WALL, leaf]))
    before = m.log_odds_at(cells_of(leaf))
    away = look_at([0.0, 0.0, 1.0], [0.0, -1.0, 1.0])  # looking along -y
    side_wall = ([0.0, -0.35, 1.0], [0.3, 0.0, 0.0], [0.0, 0.0, 0.25], OBSTACLE)
    for _ in range(30):
        m.update(cast(away, [side_wall, WALL, leaf]))
    assert np.array_equal(m.log_odds_at(cells_of(leaf)), before)
    assert m.is_occupied(cells_of(leaf)).all()


def test_robot_and_stem_points_are_never_inserted_and_a_recognised_stem_is_erased():
    """ROBOT and STEM points never make cells occupied; a stem first seen as OBSTACLE
    (beyond the camera's stem range) is erased once seen as STEM; the rays to them still clear."""
    m = ObstacleMap(bounds=SMALL)
    arm = leaf_at(0.4, y=0.1, label=ROBOT)
    stem = leaf_at(0.6, y=-0.1, label=STEM)
    m.update(cast(CAM, [arm, stem]))
    assert m.num_occupied == 0
    far_stem = leaf_at(0.6, y=-0.1, label=OBSTACLE)
    for _ in range(20):
        m.update(cast(CAM, [far_stem]))
    assert m.is_occupied(cells_of(far_stem)).mean() > 0.9
    m.update(cast(CAM, [stem]))  # one frame where it is recognised
    assert not m.is_occupied(cells_of(stem)).any()
    # Space in front of a robot point is cleared like any other: a leaf there, then the arm.
    m2 = ObstacleMap(bounds=SMALL, clear_stride=1)
    m2.update(cast(CAM, [leaf_at(0.3)]))
    robot_wall = ([0.605, 0.0, 1.005], [0.0, 0.3, 0.0], [0.0, 0.0, 0.25], ROBOT)
    for _ in range(3):
        m2.update(cast(CAM, [robot_wall]))
    assert not m2.is_occupied(cells_of(leaf_at(0.3))).any()
    assert m2.num_occupied == 0


def test_exclusion_regions_keep_the_held_cluster_out_and_follow_it():
    """Points inside the exclusion capsules are not inserted; cells inside are erased; a moving region follows."""
    m = ObstacleMap(bounds=SMALL)
    leaf = leaf_at(0.5)
    region = ExclusionRegion.sphere([0.5, 0.0, 1.0], 0.03)
    stats = m.update(cast(CAM, [WALL, leaf]), exclude=[region])
    assert stats.excluded > 0
    pts = cells_of(leaf)
    inside = np.linalg.norm(pts - [0.5, 0.0, 1.0], axis=1) < 0.02
    outside = np.linalg.norm(pts - [0.5, 0.0, 1.0], axis=1) > 0.045
    assert not m.is_occupied(pts[inside]).any()
    assert m.is_occupied(pts[outside]).all()
    # The region moves (the gripper carried the cluster): the cells it now covers are erased
    # at once, the ones it left are filled again by the next frames.
    moved = np.array([[0.5, 0.03, 1.0, 0.5, 0.03, 1.0, 0.03]])
    m.update(cast(CAM, [WALL, leaf]), exclude=moved)
    now_inside = np.linalg.norm(pts - [0.5, 0.03, 1.0], axis=1) < 0.02
    assert not m.is_occupied(pts[now_inside]).any()
    assert m.is_occupied(pts[inside & ~(np.linalg.norm(pts - [0.5, 0.03, 1.0], axis=1) < 0.045)]).all()
    # erase() does the same on demand.
    assert m.erase([ExclusionRegion((0.5, -0.05, 1.0), (0.5, 0.05, 1.0), 0.05)]) > 0
    assert not m.is_occupied(pts).any()


# --------------------------------------------------------------------------- bad input


def _same_map(a: ObstacleMap, b: ObstacleMap) -> bool:
    return np.array_equal(a.log_odds, b.log_odds) and np.array_equal(a.occupied_keys(), b.occupied_keys())


@pytest.mark.parametrize("defect", ["nan", "inf", "far", "bad_label", "wide_label"])
def test_invalid_points_leave_the_map_as_without_them(defect):
    """NaN / inf coordinates, a point 100 m away and an unknown label change nothing: the map
    equals the one built from the cloud without those points (no NaN, no clearing along them)."""
    clean = cast(CAM, [WALL, leaf_at(0.5)])
    keep = np.ones(len(clean), bool)
    keep[::7] = False
    pts, labels = clean.points.copy(), clean.labels.copy()
    if defect == "nan":
        pts[~keep, 1] = np.nan
    elif defect == "inf":
        pts[~keep, 2] = np.inf
    elif defect == "far":
        pts[~keep] = CAM[:3, 3] + 100.0 * (pts[~keep] - CAM[:3, 3]) / np.linalg.norm(
            pts[~keep] - CAM[:3, 3], axis=1, keepdims=True
        )
    elif defect == "bad_label":
        labels[~keep] = 7
    else:  # 257 as int64 would wrap round to 1 (OBSTACLE) in an int8 cast
        labels = labels.astype(np.int64)
        labels[~keep] = 257
    bad = PointCloud(pts, labels, clean.colors, CAM, 0.0, clean.depth, clean.pixels, clean.image_size)
    sub = PointCloud(clean.points[keep], clean.labels[keep], clean.colors[keep], CAM, 0.0, clean.depth[keep],
                     clean.pixels[keep], clean.image_size)  # fmt: skip
    a, b = ObstacleMap(bounds=SMALL, clear_stride=1), ObstacleMap(bounds=SMALL, clear_stride=1)
    stats = a.update(bad)
    b.update(sub)
    assert _same_map(a, b)
    assert np.all(np.isfinite(a.log_odds))
    assert stats.invalid + stats.out_of_range == int((~keep).sum())


def test_empty_frame_and_non_finite_pose_leave_the_map_unchanged():
    m = ObstacleMap(bounds=SMALL)
    m.update(cast(CAM, [WALL, leaf_at(0.5)]))
    before = m.log_odds.copy()
    empty = cast(CAM, [])
    assert len(empty) == 0
    assert m.update(empty).frame_rejected == ""
    assert np.array_equal(m.log_odds, before)
    pose = CAM.copy()
    pose[0, 3] = np.nan
    cloud = cast(CAM, [WALL])
    bad_pose = PointCloud(cloud.points, cloud.labels, cloud.colors, pose, 0.0, cloud.depth, cloud.pixels,
                          cloud.image_size)  # fmt: skip
    assert "camera_pose" in m.update(bad_pose).frame_rejected
    assert np.array_equal(m.log_odds, before)
    far_pose = CAM.copy()
    far_pose[:3, 3] = 1e300
    far_cloud = PointCloud(cloud.points + 1e300, cloud.labels, cloud.colors, far_pose, 0.0, cloud.depth,
                           cloud.pixels, cloud.image_size)  # fmt: skip
    assert "camera position" in m.update(far_cloud).frame_rejected
    assert np.array_equal(m.log_odds, before)
    # Points outside the grid: counted, not inserted, no crash.
    far = cast(look_at([0.0, 0.0, 1.0], [-1.0, 0.0, 1.0]), [([-1.5, 0, 1.0], [0, 0.3, 0], [0, 0, 0.2], OBSTACLE)])
    assert m.update(far).outside_grid == len(far)


def test_frame_stamps_wrapping_around_change_nothing():
    """The per-cell frame stamps are 16-bit: across the wrap the map evolves exactly as without it."""
    a, b = ObstacleMap(bounds=SMALL), ObstacleMap(bounds=SMALL)
    b._frame = np.iinfo(np.uint16).max - 2
    b._stamp[:] = 1  # stamps left by frame 1, 65,535 frames ago: must not block frame 1 after the wrap
    away = look_at([0.0, 0.0, 1.0], [0.0, -1.0, 1.0])
    side_wall = ([0.0, -0.305, 1.005], [0.3, 0.0, 0.0], [0.0, 0.0, 0.25], OBSTACLE)
    # The 3rd frame (the first after the wrap) looks at cells the first two never touched.
    frames = [cast(CAM, [WALL, leaf_at(0.5)])] * 2 + [cast(away, [side_wall])] + [cast(CAM, [WALL])] * 6
    for f in frames:
        a.update(f)
        b.update(f)
        assert np.array_equal(a.log_odds, b.log_odds)
    assert b._frame < 10


def test_bad_arguments_raise_the_package_error_naming_them():
    with pytest.raises(InvalidInputError, match="resolution"):
        ObstacleMap(resolution=0.0)
    with pytest.raises(InvalidInputError, match="bounds"):
        ObstacleMap(bounds=((0, 0, 0), (0, 1, 1)))
    with pytest.raises(InvalidInputError, match="prob_hit"):
        ObstacleMap(prob_hit=1.5)
    with pytest.raises(InvalidInputError, match="clear_stride"):
        ObstacleMap(clear_stride=0)
    with pytest.raises(InvalidInputError, match="clear_rays"):
        ObstacleMap(clear_rays="many")
    with pytest.raises(InvalidInputError, match="no_return_range"):
        ObstacleMap(no_return_range=(1.0, 0.5))
    m = ObstacleMap(bounds=SMALL)
    with pytest.raises(InvalidInputError, match="PointCloud"):
        m.update(np.zeros((3, 3)))
    with pytest.raises(InvalidInputError, match="exclude"):
        m.update(cast(CAM, [WALL]), exclude=np.zeros((2, 6)))
    with pytest.raises(InvalidInputError, match="radius"):
        m.update(cast(CAM, [WALL]), exclude=[ExclusionRegion((0, 0, 1), (0, 0, 1), -1.0)])
    with pytest.raises(InvalidInputError, match="per_capsule"):
        m.closest_cells(np.zeros((1, 3)), np.zeros((1, 3)), 0.1, max_distance=0.1, per_capsule=0)
    with pytest.raises(HarvestQPError, match="finite"):
        m.closest_cells(np.full((1, 3), np.nan), np.zeros((1, 3)), 0.1, max_distance=0.1)
    sizes = dict(grasp_offset=0.015, cluster_start=0.04, cluster_length=0.22, cluster_radius=0.08, stem_length=0.08,
                 stem_radius=0.02)
    with pytest.raises(InvalidInputError, match=r"gripper_pose must have shape \(4, 4\), got shape \(3, 3\)"):
        held_crop_exclusions(np.eye(3), None, **sizes)  # was an IndexError
    with pytest.raises(InvalidInputError, match="stem_base must be finite"):
        held_crop_exclusions(np.eye(4), [np.nan, 0.0, 1.0], **sizes)
    with pytest.raises(InvalidInputError, match="stem_base"):
        held_crop_exclusions(np.eye(4), 0.5, **sizes)  # a number is not a point (it was spread to (0.5, 0.5, 0.5))
    with pytest.raises(InvalidInputError, match="grasp_offset must be a real number, got None"):
        held_crop_exclusions(np.eye(4), None, **(sizes | {"grasp_offset": None}))


# --------------------------------------------------------------------------- query


def test_a_cell_counts_as_the_sphere_that_covers_it():
    """Hand-computed: one occupied cell, a capsule beside it: distance = centre distance - capsule
    radius - sqrt(3)/2 * 1 cm. Catches a cell radius that does not cover the cell (unsafe rows)."""
    m = ObstacleMap(bounds=SMALL)
    tiny = ([0.5053, 0.0052, 1.0051], [0.0, 0.001, 0.0], [0.0, 0.0, 0.001], OBSTACLE)
    m.update(cast(CAM, [tiny]))
    assert np.array_equal(m.occupied_keys(), [[50, 0, 100]])
    centre = np.array([0.505, 0.005, 1.005])
    p0, p1 = centre + [0.0, 0.1, -0.05], centre + [0.0, 0.1, 0.05]  # segment 10 cm beside the cell, along z
    q = m.closest_cells(p0[None], p1[None], 0.04, max_distance=0.2)
    assert q.counts[0] == 1
    assert q.distances[0, 0] == pytest.approx(0.1 - 0.04 - 0.5 * math.sqrt(3) * 0.01, abs=1e-12)
    np.testing.assert_allclose(q.centres[0, 0], centre, atol=1e-12)


@pytest.mark.parametrize("separation", [0.0, 0.03])
def test_closest_cells_match_a_brute_force_search(separation):
    """The block-pruned query returns the same cells and distances as numpy over all cells.

    With a separation: of the 8k closest cells, greedily the closest ones at least that far
    from those already kept. Catches a block skipped although one of its cells is in range
    (a wrong block bound), a wrong top-k insertion, a distance that does not subtract both
    radii, or a separation measured wrongly.
    """
    rng = np.random.default_rng(3)
    m = ObstacleMap(bounds=SMALL)
    rects = [WALL, leaf_at(0.5), leaf_at(0.35, 0.15), leaf_at(0.6, -0.2)]
    for k in range(6):
        pose = look_at([0.0, 0.05 * k - 0.1, 1.0 + 0.02 * k], [1.0, 0.0, 1.0])
        m.update(cast(pose, rects, size=(60, 80)))
    centres = m.occupied_centres()
    assert centres.shape[0] > 500
    n, k = 40, 5
    p0 = rng.uniform([0.2, -0.3, 0.8], [0.8, 0.3, 1.2], (n, 3))
    p1 = p0 + rng.normal(0, 0.15, (n, 3))
    radii = rng.uniform(0.0, 0.06, n)
    q = m.closest_cells(p0, p1, radii, max_distance=0.1, per_capsule=k, min_separation=separation)
    for c in range(n):
        d = p1[c] - p0[c]
        t = np.clip(((centres - p0[c]) @ d) / (d @ d), 0, 1)
        dist = np.linalg.norm(centres - (p0[c] + t[:, None] * d), axis=1) - radii[c] - m.cell_radius
        order = np.argsort(dist, kind="stable")
        order = order[dist[order] <= 0.1]
        got = q.centres[c, : q.counts[c]]
        assert np.array_equal(q.keys[c, : q.counts[c]], np.floor(got / RES).astype(int))
        assert m.is_occupied(got).all()
        # Each reported distance is the brute-force distance of that cell.
        for j in range(q.counts[c]):
            i = int(np.argmin(np.linalg.norm(centres - got[j], axis=1)))
            assert abs(dist[i] - q.distances[c, j]) < 1e-12
        if separation == 0:
            np.testing.assert_allclose(q.distances[c, : q.counts[c]], dist[order][:k], atol=1e-12)
            assert q.counts[c] == min(k, order.shape[0])
            continue
        # Greedy separation: kept cells are pairwise >= separation apart, and every cell of
        # the 8k closest (away from distance ties at the end of that list) closer than the
        # last kept one is kept or within the separation of a kept cell at most as far.
        pair = np.linalg.norm(got[:, None] - got[None], axis=2)
        assert np.all(pair[np.triu_indices(len(got), 1)] >= separation - 1e-12)
        pool = order[: 8 * k]
        if pool.shape[0] == 8 * k:
            pool = pool[dist[pool] < dist[pool[-1]] - 1e-9]
        last = q.distances[c, q.counts[c] - 1] if q.counts[c] == k else np.inf
        for i in pool:
            if dist[i] >= last - 1e-12:
                continue
            near = np.linalg.norm(got - centres[i], axis=1) < separation
            assert np.any(near & (q.distances[c, : q.counts[c]] <= dist[i] + 1e-12))
        assert q.counts[c] >= min(1, order.shape[0])
    assert (q.counts > 1).sum() > 10 and (q.counts == 0).sum() > 0


# --------------------------------------------------------------------------- OctoMap and the lab


@pytest.fixture(scope="module")
def lab():
    """The default lab scene with a free-standing camera (the lab's own ray caster)."""
    from harvest_qp.sim import CameraConfig, SimRobot, make_camera

    robot = SimRobot(camera=None)
    scene = robot.scene
    cam = make_camera(robot.model, CameraConfig(), geom_labels=scene.geom_labels, exclude_body=scene.ids["cam_tool"])
    return robot, scene, cam


def lab_views(scene, n, *, radius=0.42, seed=0):
    """Camera poses around the region of interest (stem base), from the robot's side and around."""
    rng = np.random.default_rng(seed)
    target = scene.stem_base + np.array([0.05, 0.0, -0.08])
    poses = []
    for k in range(n):
        azimuth = np.pi + 2.0 * np.pi * k / n + rng.uniform(-0.1, 0.1)  # all around, from the robot first
        elevation = rng.uniform(-0.3, 0.6)
        eye = target + radius * np.array(
            [np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)]
        )
        poses.append(look_at(eye, target + rng.normal(0, 0.03, 3)))
    return poses


def test_same_log_odds_as_octomap_on_lab_clouds(lab):
    """Every cell OctoMap knows (occupied or free) has the same log-odds in the map, and no other cell is known.

    Same clouds (all points as obstacles, as OctoMap inserts them; coordinates rounded to
    float32 as pyoctomap passes them), full rays (stride 1), default probabilities. Catches
    any difference in the ray traversal (origin cell, end cell, stop rule), in the
    once-per-frame rule, in hits winning over misses, in the clamps or the constants.
    """
    import pyoctomap  # the test extra's OctoMap bindings
    robot, scene, cam = lab
    m = ObstacleMap(clear_stride=1, max_range=10.0)
    tree = pyoctomap.OcTree(RES)
    for pose in lab_views(scene, 3, seed=5):
        pose[:3, 3] = pose[:3, 3].astype(np.float32)
        c = cam.capture(robot.data, pose, 0.0)
        near = np.linalg.norm(c.points - pose[:3, 3], axis=1) < 1.0  # fewer leaves to compare
        pts = c.points[near].astype(np.float32).astype(np.float64)
        cloud = PointCloud(pts, np.full(len(pts), OBSTACLE, np.int8), c.colors[near], pose, 0.0, c.depth[near],
                           c.pixels[near], c.image_size)  # fmt: skip
        m.update(cloud)
        tree.insertPointCloud(pts, pose[:3, 3].copy())
    coords, values = [], []
    for leaf in tree.begin_leafs():
        size = leaf.getSize()
        n = int(round(size / RES))
        offs = (np.arange(n) - (n - 1) / 2) * RES
        grid = np.stack(np.meshgrid(offs, offs, offs, indexing="ij"), -1).reshape(-1, 3)
        coords.append(np.asarray(leaf.getCoordinate()) + grid)
        values.append(np.full(grid.shape[0], leaf.current_node.getLogOdds(), np.float32))
    coords, values = np.vstack(coords), np.concatenate(values)
    inside = np.all((coords > m.lower_corner) & (coords < m.upper_corner), axis=1)
    assert inside.sum() > 20000  # OctoMap also maps what lies outside the grid (floor, far canopy)
    ours = m.log_odds_at(coords[inside])
    assert np.array_equal(ours, values[inside])
    assert np.count_nonzero(m.log_odds) == int(inside.sum())  # and nothing else is known
    assert m.num_occupied == int((values[inside] > 0).sum()) > 1000


def _vine_shapes(robot, scene):
    """coal shapes and placements of the geoms the camera labels OBSTACLE (the vine), from MuJoCo's state."""
    import coal
    import mujoco

    model, data = robot.model, robot.data
    shapes = []
    for g in range(model.ngeom):
        if scene.geom_labels[g] != OBSTACLE or model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        size = model.geom_size[g]
        kind = model.geom_type[g]
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            shape = coal.Sphere(size[0])
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            shape = coal.Capsule(size[0], 2.0 * size[1])
        elif kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
            shape = coal.Ellipsoid(size[0], size[1], size[2])
        else:
            raise AssertionError(f"geom type {kind} not handled by the oracle")
        T = coal.Transform3s(data.geom_xmat[g].reshape(3, 3).copy(), data.geom_xpos[g].copy())
        shapes.append((shape, T))
    return shapes


def test_map_distances_match_the_lab_geometry_within_one_cell(lab):
    """Capsule-to-map distances against coal's exact capsule-to-vine distances, over random capsules near the vine.

    The map is built from 16 lab frames around the region of interest (default stride).
    Each occupied cell holds a seen surface point and counts as the sphere covering the
    cell, so the map distance can only be below the truth, by at most one cell diagonal
    (sqrt(3) res), when the closest surface was seen. Catches a wrong cell radius, cells
    off by one (a key or centre error), lost surface cells (over-clearing at grazing
    rays) and stem or robot points in the map.
    """
    import coal

    robot, scene, cam = lab
    m = ObstacleMap()
    for pose in lab_views(scene, 16, seed=1):
        m.update(cam.capture(robot.data, pose, 0.0))
    shapes = _vine_shapes(robot, scene)
    rng = np.random.default_rng(7)
    centre = scene.stem_base + np.array([0.0, 0.0, -0.08])
    req = coal.DistanceRequest()  # a fresh DistanceResult per call: coal keeps a past penetration in it
    errors, n_checked = [], 0
    while n_checked < 150:
        mid = centre + rng.uniform(-0.15, 0.15, 3)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        half, radius = rng.uniform(0.02, 0.1), rng.uniform(0.02, 0.06)
        p0, p1 = mid - half * axis, mid + half * axis
        z = axis
        x = np.cross(z, [1.0, 0, 0] if abs(z[0]) < 0.9 else [0, 1.0, 0])
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(z, x), z])
        capsule, T = coal.Capsule(radius, 2 * half), coal.Transform3s(R, mid)
        true = min(coal.distance(capsule, T, s, Ts, req, coal.DistanceResult()) for s, Ts in shapes)
        if not 0.005 < true < 0.1:
            continue
        n_checked += 1
        got = m.closest_cells(p0[None], p1[None], radius, max_distance=0.2, per_capsule=1).distances[0, 0]
        errors.append(got - true)
    errors = np.array(errors)
    assert errors.max() <= 1e-9 + 0.0, errors.max()  # never farther than the seen surface
    assert errors.min() >= -math.sqrt(3) * RES - 1e-9, errors.min()
    assert np.median(errors) < -0.002  # conservative by about half a cell diagonal, as designed


def test_distances_against_coals_octree_of_the_same_cells(lab):
    """coal's exact capsule-to-octree distance (the cells as boxes, as MoveIt/FCL check them)
    bounds the map's: between the box distance minus (sqrt(3) - 1)/2 res and the box distance.
    Catches cells at the wrong place (an off-by-half-cell centre) and a wrong sphere radius."""
    import coal

    robot, scene, cam = lab
    m = ObstacleMap()
    for pose in lab_views(scene, 4, seed=4):
        m.update(cam.capture(robot.data, pose, 0.0))
    tree = coal.makeOctree(m.occupied_centres(), RES)
    rng = np.random.default_rng(11)
    req = coal.DistanceRequest()  # a fresh DistanceResult per call: coal keeps a past penetration in it
    centre = scene.stem_base + np.array([0.0, 0.0, -0.08])
    gaps = []
    for _ in range(60):  # about 40 % of random capsules near the vine touch an occupied cell
        mid = centre + rng.uniform(-0.2, 0.2, 3)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        half, radius = rng.uniform(0.02, 0.1), rng.uniform(0.02, 0.06)
        x = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
        x /= np.linalg.norm(x)
        R = np.column_stack([x, np.cross(axis, x), axis])
        capsule = coal.Capsule(radius, 2 * half)
        box = coal.distance(capsule, coal.Transform3s(R, mid), tree, coal.Transform3s(), req, coal.DistanceResult())
        got = m.closest_cells((mid - half * axis)[None], (mid + half * axis)[None], radius, max_distance=1.0,
                              per_capsule=1).distances[0, 0]  # fmt: skip
        if box <= 0:
            continue  # coal reports penetration depth differently; compare separated capsules only
        gaps.append(box - got)
    gaps = np.array(gaps)
    assert gaps.shape[0] >= 25
    assert gaps.min() >= -1e-9
    assert gaps.max() <= 0.5 * (math.sqrt(3) - 1) * RES + 1e-9


def test_stem_never_enters_the_map_in_the_lab(lab):
    """Lab frames within the stem range: no cell on the stem is occupied, except where the
    branch or the cluster also passes through that cell (their surfaces are obstacles).

    Catches STEM points inserted as obstacles, and a stem seen from farther (labelled
    OBSTACLE beyond the stem range) that is not erased once recognised.
    """
    import coal

    robot, scene, cam = lab
    m = ObstacleMap()
    stem_pts = []
    for g in scene.stem_geoms:
        axis = robot.data.geom_xmat[g].reshape(3, 3)[:, 2] * robot.model.geom_size[g, 1]
        s = np.linspace(-1, 1, 30)[:, None]
        stem_pts.append(robot.data.geom_xpos[g] + s * axis)
    stem_pts = np.vstack(stem_pts)
    keys = np.unique(m.keys(stem_pts), axis=0)
    centres = (keys + 0.5) * RES
    shapes = _vine_shapes(robot, scene)
    req = coal.DistanceRequest()  # a fresh DistanceResult per call: coal keeps a past penetration in it
    probe = coal.Sphere(1e-9)
    pure = []
    for c in centres:
        T = coal.Transform3s(np.eye(3), c)
        gap = min(coal.distance(probe, T, s, Ts, req, coal.DistanceResult()) for s, Ts in shapes)
        pure.append(gap > 0.5 * math.sqrt(3) * RES)
    pure = np.array(pure)
    assert pure.sum() >= 3
    # From 0.9 m the camera labels the stem OBSTACLE (past its 0.7 m stem range): it is mapped ...
    for pose in lab_views(scene, 3, radius=0.9, seed=3):
        m.update(cam.capture(robot.data, pose, 0.0))
    assert m.is_occupied(centres[pure]).any()
    # ... and forgotten once seen from within the stem range (from all around).
    for pose in lab_views(scene, 8, radius=0.35, seed=2):
        m.update(cam.capture(robot.data, pose, 0.0))
    assert not m.is_occupied(centres[pure]).any()


# --------------------------------------------------------------------------- feeding the QP


def _controller(with_map: bool, *, ahead: float = 0.105, speed: float = 0.1):
    """Gripper driven at ``speed`` [m/s] towards a wall ``ahead`` [m] of it (default 10.5 cm: its
    capsule 6 cm from it), the wall known only from a cloud."""
    from harvest_qp import Configuration, TaskController
    from harvest_qp.limits import CollisionAvoidance
    from harvest_qp.robot import description as desc
    from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

    config = Configuration.dual_ur5e(desc.HOME_Q)
    gripper = FrameTwistTask("gripper", weight=1.0)
    gripper.set_reference(np.array([speed, 0.0, 0.0, 0.0, 0.0, 0.0]))
    limit = CollisionAvoidance.dual_ur5e(config)
    tasks = [gripper, PostureTask(desc.HOME_Q, weight=1e-3), DampingTask(config.nv)]
    controller = TaskController(config, tasks, [limit], dt=0.002)
    m = ObstacleMap()
    g = config.frame_position("gripper")
    wall = ([g[0] + ahead, g[1], g[2]], [0.0, 0.25, 0.0], [0.0, 0.0, 0.2], OBSTACLE)
    pose = look_at(g + [-0.25, 0.02, 0.15], g + [0.2, 0.0, 0.0])
    for _ in range(3):
        m.update(cast(pose, [wall], size=(160, 220)))
    feed = MapCollisionFeed(limit, m, config) if with_map else None
    return config, controller, limit, m, feed


def test_feed_gives_the_limit_the_closest_cells_named_by_key_with_the_maps_distances():
    """After update(), the limit's obstacle pairs are the capsules' closest cells, named cell[kx,ky,kz],
    and the limit's own distance for each (capsule, cell) pair equals the map's query distance."""
    config, controller, limit, m, feed = _controller(True)
    config.update(config.q)
    # The gripper point is 10.5 cm from the wall, its capsule (tip 5 mm short, r 45 mm) 6 cm: within d_i.
    assert feed.update() > 0
    assert feed.cells.shape[0] > 0
    w0, w1 = feed.capsule_world()
    query = m.closest_cells(w0, w1, feed.radii, max_distance=limit.influence_distance + feed.margin,
                            per_capsule=feed.per_capsule, min_separation=feed.min_separation)  # fmt: skip
    expected_keys = {tuple(k) for c in range(len(w0)) for k in query.keys[c, : query.counts[c]]}
    names = limit.pair_names()
    cell_names = {b for a, b in names if b.startswith("cell[")}
    assert cell_names == {f"cell[{kx},{ky},{kz}]" for kx, ky, kz in expected_keys}
    dist = limit.distances(config)
    for c, cap in enumerate(feed.capsule_names):
        for j in range(query.counts[c]):
            kx, ky, kz = query.keys[c, j]
            k = names.index((cap, f"cell[{kx},{ky},{kz}]"))
            assert abs(dist[k] - query.distances[c, j]) < 1e-9


def test_map_rows_keep_the_gripper_off_a_wall_seen_only_by_the_camera():
    """Closed loop on the kinematic model: with the map's rows the gripper stops at d_s from the
    wall's cells; without them it drives through. Catches a feed that does not reach the QP
    (names, distances or rows), or rows built from stale cells."""
    results = {}
    for with_map in (False, True):
        config, controller, limit, m, feed = _controller(with_map)
        q = config.q.copy()
        caps = feed if feed is not None else MapCollisionFeed(limit, m, config)
        closest = np.inf
        for _ in range(1000):  # 2 s at 0.1 m/s: 20 cm, past the wall
            if feed is not None:
                feed.update(q)
            step = controller.step(q)
            assert step.ok, step.status
            q = q + step.qdot * 0.002
            config.update(q)
            w0, w1 = caps.capsule_world()
            assert np.all(np.isfinite(step.qdot))
            d = m.closest_cells(w0, w1, caps.radii, max_distance=0.2, per_capsule=1).distances[:, 0]
            closest = min(closest, float(d.min()))
        results[with_map] = closest
    assert results[False] < 0.0
    assert results[True] >= 0.01 - 1e-3  # d_s of the limit, within the damper's discretisation (0.1 mm)


def test_approach_only_map_rows_stop_the_gripper_inside_d_s_but_never_push_it():
    """The gripper starts inside d_s of a mapped wall (the map's distance, as on seed 1 of the
    paper scenes); its capsules' rows are approach-only (``set_approach_only``, as the closed
    loop sets them for the grasping arm). Driven into the wall its map distance never decreases;
    left still, the rows alone do not move it; without the option the rows push it off.
    Oracle: the map's own ``closest_cells`` distance (checked against brute force above), not the
    limit's. Catches the grasping arm's map rows asking for separation (the seed-1 false success:
    the stem pre-stretched before the tare) or no longer stopping the approach."""
    runs = {}
    for approach_only, speed in ((True, 0.1), (True, 0.0), (False, 0.0)):
        config, controller, limit, m, feed = _controller(True, ahead=0.0095, speed=speed)
        if approach_only:
            limit.set_approach_only([name for name in feed.capsule_names if name.startswith("grasp_")])
        q = config.q.copy()
        distances = []
        for _ in range(60):
            feed.update(q)
            w0, w1 = feed.capsule_world(q)
            query = m.closest_cells(w0, w1, feed.radii, max_distance=0.2, per_capsule=1)
            distances.append(float(query.distances.min()))
            step = controller.step(q)
            assert step.ok, step.status
            q = q + step.qdot * 0.002
        runs[approach_only, speed] = np.array(distances)
    start = runs[True, 0.1][0]
    assert 0.0 < start < 0.01, f"the set-up must start inside d_s on the map, got {start:.4f} m"
    assert np.all(np.diff(runs[True, 0.1]) >= -1e-6), "approach-only rows let the gripper closer"
    assert np.ptp(runs[True, 0.0]) < 1e-5, "approach-only rows moved the gripper"
    assert runs[False, 0.0][-1] > start + 1e-3, "separation rows should push it off (the option's reason)"


def test_feed_gives_no_cells_to_capsules_switched_off():
    """``feed.active[c] = False`` takes capsule c's cells out (the controller switches the gripper's
    rows off while it holds the crop still); switched on again they come back, identical.
    Oracle: the map's own query of the capsules left on. Catches a mask that is ignored, or
    that drops the other capsules' cells too."""
    config, controller, limit, m, feed = _controller(True)
    config.update(config.q)
    feed.update()
    all_cells = set(feed.cells.tolist())
    gripper = [i for i, name in enumerate(feed.capsule_names) if name.startswith("grasp_")]
    assert all_cells and gripper
    feed.active[gripper] = False
    feed.update()
    w0, w1 = feed.capsule_world()
    keep = feed.active
    query = m.closest_cells(w0[keep], w1[keep], feed.radii[keep], max_distance=limit.influence_distance + feed.margin,
                            per_capsule=feed.per_capsule, min_separation=feed.min_separation)  # fmt: skip
    expected = {int(i) for c in range(int(keep.sum())) for i in query.indices[c, : query.counts[c]]}
    assert set(feed.cells.tolist()) == expected and expected != all_cells  # the wall is ahead of the gripper
    feed.active[:] = True
    feed.update()
    assert set(feed.cells.tolist()) == all_cells


def test_feed_keeps_the_closest_cells_when_they_exceed_its_slots():
    """With fewer slots than cells, the fed cells are the closest ones (each at its closest capsule)."""
    from harvest_qp.limits import CollisionAvoidance

    config, controller, limit, m, feed = _controller(True)
    config.update(config.q)
    feed.update()
    w0, w1 = feed.capsule_world()
    query = m.closest_cells(w0, w1, feed.radii, max_distance=limit.influence_distance + feed.margin,
                            per_capsule=feed.per_capsule, min_separation=feed.min_separation)  # fmt: skip
    best: dict[int, float] = {}
    for c in range(len(w0)):
        for j in range(query.counts[c]):
            i = int(query.indices[c, j])
            best[i] = min(best.get(i, np.inf), float(query.distances[c, j]))
    assert len(best) >= 3
    small = MapCollisionFeed(CollisionAvoidance.dual_ur5e(config), m, config, max_cells=2)
    assert small.update() == 2
    assert set(small.cells.tolist()) == set(sorted(best, key=best.get)[:2])


def _lab_approach(scene, with_map: bool, duration: float = 3.6) -> tuple[float, int]:
    """The camera arm driven at 0.15 m/s at the nearest obstacle point of its first frame,
    in the MuJoCo lab with its camera, the gripper holding the cluster (excluded from the map).

    Returns the smallest true distance [m] (MuJoCo) between a camera-arm geom and a vine geom
    other than the held cluster and stem, and the most map rows active at once.
    """
    import mujoco

    from harvest_qp import Configuration, TaskController
    from harvest_qp.limits import CollisionAvoidance
    from harvest_qp.runtime.task_episode import environment_capsules
    from harvest_qp.sim import SimRobot
    from harvest_qp.tasks import DampingTask, FrameTwistTask, PostureTask

    robot = SimRobot(scene)
    q = robot.joint_positions()
    config = Configuration.dual_ur5e(q)
    first = robot.capture_cloud()
    obstacles = first.points[first.labels == OBSTACLE]
    ranges = np.linalg.norm(obstacles - first.camera_position, axis=1)
    direction = (obstacles[np.argmin(ranges)] - first.camera_position) / ranges.min()
    camera = FrameTwistTask("camera", weight=1.0)
    camera.set_reference(np.concatenate([0.15 * direction, np.zeros(3)]))
    gripper = FrameTwistTask("gripper", weight=1.0)
    gripper.set_reference(np.zeros(6))
    # The scene's rigid branch and cane as environment capsules, as the CLI's configs do.
    limit = CollisionAvoidance.dual_ur5e(
        config, environment=environment_capsules(robot.model, robot.data, ["branch", "cane"])
    )
    tasks = [camera, gripper, PostureTask(q, weight=1e-3), DampingTask(config.nv)]
    controller = TaskController(config, tasks, [limit], dt=robot.control_period)
    m = ObstacleMap()
    feed = MapCollisionFeed(limit, m, config) if with_map else None
    model, data = robot.model, robot.data
    arm = [g for g in range(model.ngeom) if scene.geom_labels[g] == ROBOT
           and model.body(model.geom_bodyid[g]).name.startswith("cam_")]  # fmt: skip
    vine = [g for g in range(model.ngeom) if scene.geom_labels[g] == OBSTACLE
            and model.geom_type[g] != mujoco.mjtGeom.mjGEOM_PLANE and model.geom_bodyid[g] != scene.ids["cluster"]]
    closest, rows = np.inf, 0
    for k in range(int(round(duration / robot.control_period))):
        q = robot.joint_positions()
        cloud = robot.camera_cloud()
        if cloud is not None and with_map:
            G = config.frame_pose("gripper")
            y, p = G.rotation[:, 1], G.translation
            m.update(cloud, exclude=[ExclusionRegion(tuple(p - 0.03 * y), tuple(p + 0.22 * y), 0.08)])
        if feed is not None:
            feed.update(q)
        step = controller.step(q)
        assert step.ok, step.status
        assert np.all(np.isfinite(step.qdot))
        if feed is not None:
            names = limit.pair_names()
            rows = max(rows, sum(names[i][1].startswith("cell[") for i in limit.active_pairs))
        robot.send_joint_velocities(step.qdot)
        robot.step()
        if k % 5 == 0:
            for a in arm:
                for b in vine:
                    closest = min(closest, mujoco.mj_geomDistance(model, data, a, b, 0.1, None))
    return closest, rows


def test_lab_camera_arm_driven_at_a_leaf_stops_short_of_it_with_the_map(lab):
    """In the lab, with the camera's frames mapped and fed before each QP step, the camera arm
    driven at the nearest leaf it sees keeps the collision limit's d_s (1 cm) from every true
    vine geom; without the map it reaches the leaf (5.7 cm into it while leaves do not collide
    in MuJoCo; touching it once they do). Catches a map that does not reach the QP from real
    frames (labels, exclusion of the held cluster, feed, timing)."""
    _, scene, _ = lab
    without, _ = _lab_approach(scene, with_map=False)
    closest, rows = _lab_approach(scene, with_map=True)
    assert without < 0.002
    assert closest >= 0.01 - 1e-3
    assert rows >= 3


def test_held_cluster_is_kept_out_of_the_map_in_the_lab(lab):
    """Lab frames that see the held cluster: with the exclusion capsule along the gripper's y
    axis, no occupied cell touches a berry; without it, berries fill cells. Catches an
    exclusion test in the wrong frame or a capsule that does not cover the cluster."""
    import mujoco

    robot, scene, cam = lab
    G = robot.site_pose("gripper")
    y, p = G[:3, 1], G[:3, 3]
    params = scene.params
    held = ExclusionRegion(tuple(p - 0.03 * y), tuple(p + (params.cluster_length + 0.05) * y),
                           params.cluster_radius + 0.02)  # fmt: skip
    model, data = robot.model, robot.data
    berries = [g for g in range(model.ngeom) if model.geom_bodyid[g] == scene.ids["cluster"]
               and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE]  # fmt: skip
    touching = {}
    for name, exclude in (("with", [held]), ("without", None)):
        m = ObstacleMap()
        for pose in lab_views(scene, 6, seed=8):
            m.update(cam.capture(data, pose, 0.0), exclude=exclude)
        centres = m.occupied_centres()
        gaps = [np.linalg.norm(centres - data.geom_xpos[g], axis=1) - model.geom_size[g, 0] for g in berries]
        touching[name] = int((np.min(gaps, axis=0) < 0.5 * math.sqrt(3) * RES).sum())
    assert touching["without"] > 50
    assert touching["with"] == 0


def test_float_labels_and_a_short_q_are_refused_not_reinterpreted():
    """Catches labels cast to int8 without a check (NaN floats became STEM and emptied the map,
    1.9 became OBSTACLE) and a MapCollisionFeed whose compiled kinematics read past a short q
    (found by an independent audit: capsule ends changed with whatever followed q in memory)."""
    clean = cast(CAM, [WALL])
    floats = PointCloud(clean.points, clean.labels.astype(float), clean.colors, CAM, 0.0, clean.depth,
                        clean.pixels, clean.image_size)  # fmt: skip
    m = ObstacleMap(bounds=SMALL)
    with pytest.raises(InvalidInputError, match="labels must be integers"):
        m.update(floats)
    assert m.occupied_keys().shape[0] == 0
    config, _, _, _, feed = _controller(True)
    for bad in (np.zeros(6), np.zeros(13), "abc"):
        with pytest.raises(InvalidInputError, match="q must"):
            feed.update(bad)


def test_feed_between_map_changes_gives_exactly_the_full_querys_cells():
    """The feed keeps each capsule's candidate cells between map changes (a speed-up); every tick
    its cells and distances must still be those of ``ObstacleMap.closest_cells`` (the full block
    search, checked against brute force above) to rounding, while the arm moves farther than the
    kept lists' slack and a wall moving towards it changes the map every 10 ticks.
    Catches a candidate list kept after the map changed near a capsule (a new or cleared cell
    missed) or after a capsule moved past the slack."""
    config, controller, limit, m, feed = _controller(True, ahead=0.09)
    q0 = config.q.copy()
    g = config.frame_position("gripper")
    pose = look_at(g + [-0.25, 0.02, 0.15], g + [0.2, 0.0, 0.0])
    rebuilds_before = feed.rebuilds
    kept_ticks = 0
    for tick in range(160):
        # All joints of both arms swing (capsule ends move up to ~3 mm a tick); in the last 100
        # ticks the map stays as it is, so only the motion can invalidate the kept lists.
        q = q0 + 0.2 * np.sin(0.02 * tick + np.arange(q0.size))
        if tick % 10 == 5 and tick < 60:  # the wall comes 3 mm closer each time, and tilts: cells appear and clear
            x = g[0] + 0.09 - 0.0003 * tick
            wall = ([x, g[1], g[2]], [0.02 * np.sin(0.1 * tick), 0.25, 0.0], [0.0, 0.0, 0.2], OBSTACLE)
            m.update(cast(pose, [wall], size=(160, 220)))
        rebuilds = feed.rebuilds
        n = feed.update(q)
        kept_ticks += feed.rebuilds == rebuilds
        w0, w1 = feed.capsule_world(q)
        query = m.closest_cells(w0, w1, feed.radii, max_distance=limit.influence_distance + feed.margin,
                                per_capsule=feed.per_capsule, min_separation=feed.min_separation)  # fmt: skip
        counts, indices, distances = feed.capsule_cells()
        assert np.array_equal(counts, query.counts), tick
        valid = query.indices >= 0
        assert np.array_equal(indices[valid], query.indices[valid]), tick
        np.testing.assert_allclose(distances[valid], query.distances[valid], rtol=0, atol=1e-12, err_msg=str(tick))
        best: dict[int, float] = {}
        for c in range(len(w0)):
            for j in range(query.counts[c]):
                i = int(query.indices[c, j])
                best[i] = min(best.get(i, np.inf), float(query.distances[c, j]))
        expected = sorted(sorted(best, key=best.get)[: feed.slots])
        assert n == len(expected) and feed.cells.tolist() == expected, tick
        centre_of = {int(i): c for i, c in zip(query.indices[valid], query.centres[valid])}
        expected_centres = np.array([centre_of[i] for i in expected]).reshape(-1, 3)
        assert np.array_equal(limit.cap_p0[feed.limit_slots][:n], expected_centres), tick
    # The test must exercise both paths: lists kept, and rebuilt (map changes, motion).
    assert kept_ticks > 100
    assert feed.rebuilds - rebuilds_before > 12


def test_feed_drops_its_kept_cells_when_the_map_or_the_radii_are_replaced():
    """Oracle: the uncached ``ObstacleMap.closest_cells`` on the new map / with the new radii.

    Catches: candidate cells kept across ``feed.map = other`` (cells of the old map fed from
    an empty one) or across new radii (3 pairs fed where 6 are in reach), as an audit of the
    cached feed found; in-place changes of the radii are refused (read-only array)."""
    config, _controller_, limit, m, feed = _controller(True, ahead=0.07)
    q = config.q.copy()

    def uncached(feed):
        w0, w1 = (a.copy() for a in feed.capsule_world(q))
        query = feed.map.closest_cells(w0, w1, feed.radii, max_distance=feed.limit.influence_distance + feed.margin,
                                       per_capsule=feed.per_capsule, min_separation=feed.min_separation)
        return int(query.counts.sum())

    assert feed.update(q) > 0 and int(feed.capsule_cells()[0].sum()) == uncached(feed)
    with pytest.raises(ValueError, match="read-only"):
        feed.radii *= 3.0
    feed.radii = 3.0 * feed.radii
    feed.update(q)
    assert int(feed.capsule_cells()[0].sum()) == uncached(feed) > 0
    with pytest.raises(InvalidInputError, match="radii"):
        feed.radii = np.ones(3)
    feed.map = ObstacleMap()  # empty, at the same version count as a fresh map
    assert feed.update(q) == 0 and uncached(feed) == 0
    with pytest.raises(InvalidInputError, match="ObstacleMap"):
        feed.map = "not a map"


def test_feed_follows_an_edited_cell_radius():
    """Oracle: the uncached ``ObstacleMap.closest_cells``, which reads ``cell_radius`` live.

    Catches (audit auditb5, F3): the feed's copy of ``ObstacleMap.cell_radius`` kept
    after the attribute is edited (distances from the old radius, limit spheres of the new
    one); the limit's sphere radii left at the old value when the fed cells stay the same."""
    config, _controller_, limit, m, feed = _controller(True, ahead=0.07)
    q = config.q.copy()
    assert feed.update(q) > 0
    old_radius = m.cell_radius
    for radius in (1.5 * old_radius, 0.5 * old_radius):
        m.cell_radius = radius
        n = feed.update(q)
        w0, w1 = feed.capsule_world(q)
        query = m.closest_cells(w0, w1, feed.radii, max_distance=limit.influence_distance + feed.margin,
                                per_capsule=feed.per_capsule, min_separation=feed.min_separation)  # fmt: skip
        counts, indices, distances = feed.capsule_cells()
        assert np.array_equal(counts, query.counts)
        valid = query.indices >= 0
        assert valid.any()
        assert np.array_equal(indices[valid], query.indices[valid])
        np.testing.assert_allclose(distances[valid], query.distances[valid], rtol=0, atol=1e-12)
        assert np.all(limit.cap_radius[feed.limit_slots][:n] == radius)


def test_at_the_default_ray_budget_moved_leaves_clear_within_eleven_frames():
    """The default budget (DEFAULT_CLEAR_RAYS = 6000: stride 3 on this 192x256 image). A leaf
    0.25 m away (in the near-camera zone, only the coarser grid clears) leaves the map in 9 frames
    (a fully occupied cell needs 9 misses); one 0.95 m away, where the stride-3 rays are 1.2 cells
    apart, by frame 11 (measured: 9 with stride 2, 18 with stride 4).

    Catches a default budget too small to cross the far leaf's cells within a few frames (planted
    with clear_rays=3000, stride 4: the far leaf is still there at frame 11)."""
    size = (192, 256)
    near, far = leaf_at(0.25, y=-0.05), leaf_at(0.95, y=0.15)
    back = ([1.3, 0.0, 1.0], [0.0, 0.6, 0.0], [0.0, 0.0, 0.5], OBSTACLE)
    m = ObstacleMap(bounds=SMALL)
    assert m.clear_rays == DEFAULT_CLEAR_RAYS
    for _ in range(20):
        m.update(cast(CAM, [back, near, far], size=size))
    assert m.is_occupied(np.vstack([cells_of(near), cells_of(far)])).all()
    for frame in range(1, 12):
        m.update(cast(CAM, [back], size=size))
        if frame == 8:
            assert m.is_occupied(cells_of(near)).any()
        if frame == 9:
            assert not m.is_occupied(cells_of(near)).any()
    assert not m.is_occupied(np.vstack([cells_of(near), cells_of(far)])).any()
