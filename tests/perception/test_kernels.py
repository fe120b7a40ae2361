"""The compiled kernels of perception against independent references.

Each kernel is tested against a plain computation that does not share its code: the
ray/obstacle pairs of ``ray_obstacle_pairs`` against a dense evaluation of ``eq:nearest`` over
every (ray, obstacle), the block-list erase of the obstacle map against a brute force over the
occupied cells, the clearing-grid tables against the modulo rule, the stem kernels against
scipy (``kmeans2``, ``cKDTree``) and numpy (``np.unique``, ``np.median``).
"""

from __future__ import annotations

import numpy as np
import pytest

from harvest_qp.perception import _map_kernels as K
from harvest_qp.perception.obstacle_map import ExclusionRegion, ObstacleMap
from harvest_qp.perception.unveiling import ray_obstacle_pairs
from harvest_qp.runtime.interface import OBSTACLE, STEM, PointCloud

SMALL = ((-0.2, -0.4, 0.6), (1.0, 0.4, 1.4))


# --------------------------------------------------------------------------- unveiling cull


def _scene(rng, n_stem, n_obstacles):
    """A stem 0.25-0.45 m from the camera, obstacles around its rays, near the camera and behind it."""
    camera = rng.normal(scale=0.2, size=3)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    side = np.cross(direction, rng.normal(size=3))
    side /= np.linalg.norm(side)
    base = camera + rng.uniform(0.25, 0.45) * direction
    stem = base + np.outer(rng.uniform(0.0, 0.06, n_stem), side) + rng.normal(scale=0.002, size=(n_stem, 3))
    fractions = rng.uniform(-0.2, 1.3, n_obstacles)[:, None]
    targets = stem[rng.integers(0, n_stem, n_obstacles)]
    obstacles = camera + fractions * (targets - camera) + rng.normal(scale=0.02, size=(n_obstacles, 3))
    near = camera + rng.normal(scale=0.01, size=(20, 3))  # within reach of the rays' camera ends
    far = camera + rng.normal(scale=1.0, size=(200, 3))  # all around, behind the camera too
    return stem, np.vstack([obstacles, near, far]), camera


def _dense_pairs(stem, obstacles, camera, d_a, d_o):
    """eq:nearest over every (ray, obstacle): s, the pair mask, p_hat - p_o and its norm."""
    rays = stem - camera
    s = np.einsum("ij,kj->ik", rays, obstacles - camera) / np.einsum("ij,ij->i", rays, rays)[:, None]
    t = np.clip(s, 0.0, 1.0)
    gap = camera + t[..., None] * rays[:, None, :] - obstacles[None]
    distance = np.linalg.norm(gap, axis=-1)
    return s, distance - d_o < d_a, gap, distance


def _assert_pairs_are_the_dense_pairs(pairs, stem, obstacles, camera, d_a, d_o):
    s, inside, gap, distance = _dense_pairs(stem, obstacles, camera, d_a, d_o)
    j, k = pairs.stem_index, pairs.obstacle_index
    assert len(pairs) == int(inside.sum()) > 0 and np.all(inside[j, k])
    assert len(set(zip(j.tolist(), k.tolist()))) == len(pairs)  # each pair once
    np.testing.assert_allclose(pairs.segment_parameter, np.clip(s[j, k], 0.0, 1.0), rtol=0, atol=1e-12)
    np.testing.assert_allclose(pairs.surface_distance, distance[j, k] - d_o, rtol=0, atol=1e-12)
    expected_case = (s[j, k] > 0.0).astype(np.int8) + (s[j, k] >= 1.0)
    assert np.array_equal(pairs.case, expected_case)
    away = gap[j, k] / np.where(distance[j, k] > 0, distance[j, k], 1.0)[:, None]
    np.testing.assert_allclose(pairs.away_directions, away, rtol=0, atol=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_pairs_are_every_pair_of_the_dense_evaluation(seed):
    """The compiled cull and pair kernels find exactly the pairs of eq:nearest evaluated over every
    (ray, obstacle) with numpy, with their s, r_hat, branch and away direction. Obstacles next to
    the camera and behind it, rays in every direction (bundles without a useful cone) on one seed
    in three. Catches a dropped clause of the cull (e.g. the "within reach of the camera" one,
    which the points next to the camera need), a wrong depth window, a bundle cone too narrow, or a
    wrong branch of eq:nearest."""
    rng = np.random.default_rng(seed)
    stem, obstacles, camera = _scene(rng, int(rng.integers(5, 300)), int(rng.integers(100, 5000)))
    if seed % 3 == 2:
        stem = camera + rng.normal(size=stem.shape)
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=0.02, d_o=0.002)
    assert 0 < pairs.n_candidate_obstacles <= obstacles.shape[0]
    _assert_pairs_are_the_dense_pairs(pairs, stem, obstacles, camera, 0.02, 0.002)


# --------------------------------------------------------------------------- obstacle map


def _occupied_map(rng, n=3000):
    """A small map with ~n occupied cells at random (one hit each), and their points."""
    m = ObstacleMap(bounds=SMALL)
    points = rng.uniform(SMALL[0], SMALL[1], size=(n, 3))
    pose = np.eye(4)
    pose[:3, 3] = (0.4, 0.0, 1.0)
    cloud = PointCloud(
        points=points, labels=np.full(n, OBSTACLE, np.int8), colors=np.zeros((n, 3), np.uint8),
        camera_pose=pose, timestamp=0.0, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(1, 1),
    )  # fmt: skip
    m.update(cloud)
    return m


@pytest.mark.parametrize("seed", range(3))
def test_erase_over_the_block_lists_forgets_exactly_the_occupied_cells_in_the_regions(seed):
    """ObstacleMap.erase visits only the occupied cells (block lists) of the regions' boxes; it must
    forget exactly the occupied cells whose centres lie in a capsule (numpy brute force over all
    occupied cells) and change nothing else. Catches cells of a block only partly inside the
    box being skipped or the box test letting outside cells through."""
    rng = np.random.default_rng(seed)
    m = _occupied_map(rng)
    before = m.log_odds.copy()
    centres = m.occupied_centres()
    regions = []
    for _ in range(3):
        p0 = rng.uniform(SMALL[0], SMALL[1])
        p1 = p0 + rng.normal(scale=0.1, size=3)
        regions.append(ExclusionRegion(tuple(p0), tuple(p1), float(rng.uniform(0.02, 0.15))))
    inside = np.zeros(len(centres), dtype=bool)
    for r in regions:
        a, b = np.array(r.p0), np.array(r.p1)
        d = b - a
        t = np.clip((centres - a) @ d / max(d @ d, 1e-300), 0.0, 1.0) if d @ d > 0 else np.zeros(len(centres))
        inside |= np.linalg.norm(centres - a - t[:, None] * d, axis=1) <= r.radius
    assert 0 < inside.sum() < len(centres)
    erased = m.erase(regions)
    assert erased == int(inside.sum())
    assert np.array_equal(m.occupied_centres(), centres[~inside])
    changed = np.flatnonzero(m.log_odds != before)
    assert changed.size == erased and np.all(m.log_odds[changed] == 0.0)


@pytest.mark.parametrize("stride", [1, 2, 3, 6])
def test_clearing_grid_tables_follow_the_modulo_rule(stride):
    """The per-row / per-column tables of the clearing grid: 2 on the 2*stride grid, 1 on the
    stride grid only, 0 off it, for every phase."""
    for phase in range(stride):
        classes = K._grid_classes(40, phase, stride)
        for i in range(40):
            d = i - phase
            expected = 0 if stride > 1 and d % stride else (2 if d % (2 * stride) == 0 else 1)
            assert classes[i] == expected, (stride, phase, i)


def test_pixels_outside_the_image_clear_as_inside_it():
    """Pixels past the reported image size take the modulo path instead of the tables: the map
    and its statistics are the same as with the true image size."""
    rng = np.random.default_rng(3)
    h, w = 60, 80
    rows, cols = np.divmod(np.arange(h * w), w)
    pose = np.eye(4)
    pose[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]  # looking along +x
    pose[:3, 3] = (0.0, 0.0, 1.0)
    f = 70.0
    depth = rng.uniform(0.5, 0.9, h * w)
    pc = np.column_stack([(cols + 0.5 - w / 2) / f * depth, (rows + 0.5 - h / 2) / f * depth, depth])
    points = pc @ pose[:3, :3].T + pose[:3, 3]
    labels = np.where(rng.random(h * w) < 0.1, STEM, OBSTACLE).astype(np.int8)
    maps = []
    for size in ((h, w), (h // 2, w // 3)):
        m = ObstacleMap(bounds=SMALL, clear_stride=2)
        stats = []
        for _ in range(4):
            cloud = PointCloud(
                points=points, labels=labels, colors=np.zeros((h * w, 3), np.uint8), camera_pose=pose, timestamp=0.0,
                depth=depth, pixels=np.column_stack([rows, cols]).astype(np.int32), image_size=size,
            )  # fmt: skip
            stats.append(m.update(cloud))
        maps.append((m, stats))
    (a, sa), (b, sb) = maps
    assert sa == sb and sa[-1].rays > 0
    assert np.array_equal(a.log_odds, b.log_odds)


# --------------------------------------------------------------------------- stem model


def _stem_like_clouds(seed):
    """Stem-like point sets (bent lines with noise), random blobs, and coarse ones with ties."""
    rng = np.random.default_rng(seed)
    clouds = []
    for _ in range(40):
        n = int(rng.integers(3, 400))
        t = rng.uniform(0.0, 0.06, n)
        line = np.column_stack([0.02 * t, 0.3 * t * t, t]) + rng.normal(scale=0.002, size=(n, 3))
        clouds.append(line + rng.normal(size=3))
        clouds.append(rng.normal(size=(n, 3)) * rng.uniform(1e-3, 1.0, 3))
        clouds.append(np.round(rng.normal(size=(n, 3)), 1))  # duplicated points and equal distances
    for k in range(2, 12):  # symmetric about the centre: the middle points are equally far from both codes
        x = np.arange(-k, k + 1, dtype=float)
        clouds.append(np.column_stack([x, np.zeros_like(x), np.abs(x) % 2]))
    return clouds


@pytest.mark.parametrize("seed", range(2))
def test_compiled_kmeans_gives_scipys_kmeans2_labels(seed):
    """fit_stem's compiled 2-means gives the labels of scipy's kmeans2 (minit="matrix",
    missing="raise") from the same start, and an empty cluster where scipy raises. Catches
    ties going to the last code instead of the first, or means summed in another order."""
    from scipy.cluster.vq import ClusterError, kmeans2

    from harvest_qp.perception import _stem_kernels
    from harvest_qp.perception.stem import _principal_axes

    empty = 0
    for points in _stem_like_clouds(seed):
        eigenvalues, axes = _principal_axes(points)
        centre, offset = points.mean(axis=0), np.sqrt(eigenvalues[0]) * axes[:, 0]
        initial = np.stack((centre - offset, centre + offset))
        labels = np.empty(points.shape[0], dtype=np.int32)
        ok = _stem_kernels.kmeans_labels(np.ascontiguousarray(points), initial, 10, labels)
        try:
            _, expected = kmeans2(points, initial, iter=10, minit="matrix", missing="raise", check_finite=False)
        except ClusterError:
            assert not ok
            empty += 1
            continue
        assert ok and np.array_equal(labels, expected)
    assert empty < 40


@pytest.mark.parametrize("seed", range(2))
def test_compiled_nearest_neighbours_give_ckdtrees_distances(seed):
    """The point spacing's compiled nearest-neighbour sweep gives cKDTree's distances. Catches a
    sweep that stops too early (a closer point farther along x missed)."""
    from scipy.spatial import cKDTree

    from harvest_qp.perception import _stem_kernels

    for points in _stem_like_clouds(seed):
        distinct = np.unique(points, axis=0)
        if distinct.shape[0] < 2:
            continue
        expected = cKDTree(distinct).query(distinct, k=2)[0][:, 1]
        got = _stem_kernels.nearest_neighbour_distances(np.ascontiguousarray(distinct))
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=0)


def _rows_with_ties(rng, n):
    """Rows repeated, some changed by one ulp, by the sign of a zero, or sharing a coordinate."""
    base = rng.normal(size=(n, 3))
    base[::3, 0] = base[0, 0]  # runs of equal x, sorted by (y, z) within
    rows = base[rng.integers(0, n, 3 * n)].copy()
    rows[::5, 1] = np.nextafter(rows[::5, 1], np.inf)
    rows[::7, 2] = base[0, 2]
    rows[::11, 0] = 0.0
    rows[::13, 0] = -0.0
    rows[::4, 1] = 0.0
    rows[::6, 1] = -0.0
    rows[::9, 2] = -0.0
    rows[::10, 2] = 0.0
    return rows


@pytest.mark.parametrize("seed", range(3))
def test_compiled_distinct_rows_are_numpys_unique_rows(seed):
    """The compiled distinct rows are ``np.unique(axis=0)``'s, in the same lexicographic order
    (0.0 and -0.0 compare equal in both). Catches runs of equal x not sorted by (y, z), or
    runs sorted by z before y (rows out of order, duplicates not adjacent and kept)."""
    from harvest_qp.perception import _stem_kernels

    rng = np.random.default_rng(seed)
    for n in (2, 3, 7, 40, 300):
        rows = _rows_with_ties(rng, n)
        expected = np.unique(rows, axis=0)
        got = _stem_kernels.distinct_rows(np.ascontiguousarray(rows))
        assert got.shape == expected.shape
        np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize("seed", range(2))
def test_compiled_point_spacing_is_the_median_of_ckdtrees_distances_over_unique_rows(seed):
    """``_point_spacing`` (one compiled call: distinct rows, the nearest-neighbour sweep along the
    widest axis, the median) equals numpy's median of cKDTree's nearest-neighbour distances
    over ``np.unique(axis=0)``'s rows, for clouds elongated along x, y or z.
    Catches a sweep pruned on the wrong axis's gap, a median of an even count taken as one
    middle value, or duplicates counted."""
    from scipy.spatial import cKDTree

    from harvest_qp.perception.stem import _point_spacing

    rng = np.random.default_rng(seed)
    clouds = list(_stem_like_clouds(seed))
    for axis in range(3):
        scale = np.full(3, 0.004)
        scale[axis] = 0.05
        clouds.append(rng.uniform(-1.0, 1.0, (500, 3)) * scale)
        clouds.append(np.round(rng.uniform(-1.0, 1.0, (400, 3)) * scale, 3))  # a lattice: ties
    clouds += [_rows_with_ties(rng, n) for n in (2, 5, 60)]
    for points in clouds:
        unique = np.unique(points, axis=0)
        expected = 0.0 if unique.shape[0] < 2 else float(np.median(cKDTree(unique).query(unique, k=2)[0][:, 1]))
        assert _point_spacing(points) == pytest.approx(expected, rel=1e-12, abs=0.0)


def test_pair_kernel_keeps_every_pair_when_its_outputs_grow():
    """Many more pairs than the compiled kernel's first output size (1,024 or 8 per ray): 12 rays
    through a dense cloud of 3,000 obstacle points around them (~20,000 pairs), so the outputs
    are grown several times mid-bundle. The pairs must still be the dense evaluation's. Catches a
    growth that drops the pairs already found (outputs not copied) or overruns them."""
    rng = np.random.default_rng(7)
    camera = np.zeros(3)
    stem = np.column_stack([rng.uniform(-0.005, 0.005, 12), rng.uniform(-0.005, 0.005, 12), np.full(12, 0.4)])
    obstacles = np.column_stack([rng.uniform(-0.01, 0.01, 3000), rng.uniform(-0.01, 0.01, 3000),
                                 rng.uniform(0.0, 0.4, 3000)])
    pairs = ray_obstacle_pairs(stem, obstacles, camera, d_a=0.02, d_o=0.002)
    assert len(pairs) > 8 * 1024
    _assert_pairs_are_the_dense_pairs(pairs, stem, obstacles, camera, 0.02, 0.002)


def _random_capsules(rng, n):
    """``(n, 7)`` capsules around (0.4, 0, 1) [m]: some spheres, radii 5-90 mm, any axis."""
    a = rng.uniform((0.2, -0.2, 0.8), (0.6, 0.2, 1.2), size=(n, 3))
    b = a + rng.normal(scale=0.08, size=(n, 3)) * (rng.uniform(size=(n, 1)) < 0.8)
    return np.column_stack([a, b, rng.uniform(0.005, 0.09, n)])


@pytest.mark.parametrize("seed", range(3))
def test_cell_region_classes_agree_with_the_exact_point_test(seed):
    """The map update decides exclusion once per cell where a cell lies wholly inside a region or
    wholly outside all (``_cell_region_class``); the per-point exact test
    (``_point_in_boxed_regions``, the oracle) must agree on every point of such a cell,
    including points at its corners and one ulp inside its faces. Catches a class that ignores
    the cell's extent (its centre's distance alone) or the widened boxes."""
    rng = np.random.default_rng(seed)
    res = 0.01
    regions = _random_capsules(rng, 3)
    boxes = K._region_boxes(regions)
    classes = []
    for _ in range(600):
        # Cells near the capsules' surfaces, inside and outside.
        k = rng.integers(0, regions.shape[0])
        on_axis = regions[k, :3] + rng.uniform() * (regions[k, 3:6] - regions[k, :3])
        offset = rng.normal(size=3)
        near = on_axis + offset / np.linalg.norm(offset) * regions[k, 6] * rng.uniform(0.0, 1.6)
        key = np.floor(near / res)
        cls = K._cell_region_class(key[0], key[1], key[2], res, regions, boxes)
        classes.append(cls)
        if cls == 2:
            continue
        corners = np.array([[i, j, k] for i in (0.0, 1.0) for j in (0.0, 1.0) for k in (0.0, 1.0)])
        u = np.vstack([rng.uniform(size=(60, 3)), corners, np.nextafter(corners, 0.5)])
        points = (key + u) * res
        for p in points:
            if not np.array_equal(np.floor(p * (1.0 / res)), key):
                continue  # rounded into the next cell: not this cell's point
            assert K._point_in_boxed_regions(p[0], p[1], p[2], regions, boxes) == (cls == 1), (key, p, cls)
    assert classes.count(0) > 20 and classes.count(1) > 5 and classes.count(2) > 5


def test_exclusion_counts_every_obstacle_point_in_the_regions():
    """A cloud thick inside and around exclusion capsules: the update's ``excluded`` count is the
    number of obstacle points within a capsule by a numpy brute force (segment distance), and
    no cell is occupied by those points alone. Catches cells classed wholly inside a region
    whose corner sticks out of it (points outside counted as excluded)."""
    rng = np.random.default_rng(11)
    regions = _random_capsules(rng, 2)
    points = rng.uniform((0.1, -0.3, 0.7), (0.7, 0.3, 1.3), size=(40000, 3))
    a, d = regions[:, :3], regions[:, 3:6] - regions[:, :3]
    w = points[:, None, :] - a[None]
    dd = np.einsum("kj,kj->k", d, d)
    t = np.clip(np.einsum("nkj,kj->nk", w, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    gap = w - t[..., None] * d[None]
    inside = (np.einsum("nkj,nkj->nk", gap, gap) <= regions[:, 6] ** 2).any(axis=1)
    pose = np.eye(4)
    pose[:3, 3] = (-0.1, 0.0, 1.0)
    n = points.shape[0]
    cloud = PointCloud(
        points=points, labels=np.full(n, OBSTACLE, np.int8), colors=np.zeros((n, 3), np.uint8),
        camera_pose=pose, timestamp=0.0, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(1, 1),
    )  # fmt: skip
    m = ObstacleMap(bounds=((-0.2, -0.4, 0.6), (1.0, 0.4, 1.4)), erase_excluded=False)
    stats = m.update(cloud, exclude=regions)
    assert stats.excluded == int(inside.sum()) > 300
    only_inside = np.setdiff1d(
        np.unique(np.floor(points[inside] / 0.01), axis=0).view([("", float)] * 3),
        np.unique(np.floor(points[~inside] / 0.01), axis=0).view([("", float)] * 3),
    ).view(float).reshape(-1, 3)
    assert only_inside.shape[0] > 10
    assert not m.is_occupied((only_inside + 0.5) * 0.01).any()


def test_every_non_finite_coordinate_makes_a_point_invalid():
    """The update's finiteness test (one sum of the coordinates times zero) counts a point with
    NaN, +inf or -inf in any single coordinate as invalid, and no finite point (huge, tiny,
    negative zero) as invalid: ``stats.invalid`` equals numpy's count of non-finite rows.
    Catches a test that misses one coordinate or lets an infinity through."""
    rng = np.random.default_rng(3)
    n = 600
    points = rng.uniform((0.3, -0.2, 0.9), (0.8, 0.2, 1.1), size=(n, 3))
    points[::50] = (-0.0, 0.0, 1.0)
    points[1::50, 0] = 1e-300
    points[2::50, 1] = -1e-300
    for k, value in enumerate((np.nan, np.inf, -np.inf)):
        for axis in range(3):
            points[3 + 3 * k + axis :: 40, axis] = value
    bad = ~np.isfinite(points).all(axis=1)
    assert bad.sum() > 100
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 1.0)
    cloud = PointCloud(
        points=points, labels=np.full(n, OBSTACLE, np.int8), colors=np.zeros((n, 3), np.uint8),
        camera_pose=pose, timestamp=0.0, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(1, 1),
    )  # fmt: skip
    stats = ObstacleMap(bounds=((-0.2, -0.4, 0.6), (1.0, 0.4, 1.4)), min_range=0.0).update(cloud)
    assert stats.invalid == int(bad.sum())


# --------------------------------------------------------------------------- per-tick map feed


def _occupy(m: ObstacleMap, keys) -> None:
    """Make the cells with integer ``keys`` occupied: one frame of obstacle points at their centres."""
    centres = (np.asarray(keys, float).reshape(-1, 3) + 0.5) * m.resolution
    n = centres.shape[0]
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 1.0)
    m.update(PointCloud(
        points=centres, labels=np.full(n, OBSTACLE, np.int8), colors=np.zeros((n, 3), np.uint8), camera_pose=pose,
        timestamp=0.0, depth=np.ones(n), pixels=np.zeros((n, 2), np.int32), image_size=(1, 1),
    ))  # fmt: skip


def _feed_and_full_query(m: ObstacleMap, n: int):
    """One tick of the compiled feed (its lists kept between ticks) and the oracle: the full block search
    ``ObstacleMap.closest_cells`` then the union of the capsules' cells. The kernel reads the map's block
    lists, which only the map's own code may reach: this test is the kernel's."""
    from harvest_qp.perception import _feed_kernels as FK

    k, m_max, max_distance, separation = 4, 32, 0.11, 0.03
    s = dict(
        state=np.zeros(FK.FEED_STATE, np.int64), cache_w0=np.zeros((n, 3)), cache_w1=np.zeros((n, 3)),
        cache_distance=np.full(1, np.nan), cand_start=np.zeros(n + 1, np.int64), cand_index=np.zeros(4096, np.int64),
        cand_xyz=np.zeros((4096, 4)), rel_blocks=np.zeros(4096, np.int64), scratch_index=np.zeros(m_max, np.int64),
        scratch_distance=np.zeros(m_max), out_index=np.full((n, k), -1, np.int64), out_distance=np.full((n, k), np.inf),
        out_count=np.zeros(n, np.int64), out_cells=np.zeros(24, np.int64), out_centres=np.zeros((24, 3)),
        cand_bound=np.full(n, np.inf), displacement=np.zeros(n), kept_cells=np.zeros((k, 3), np.int64),
    )  # fmt: skip

    def tick(w0, w1, radii):
        fed = FK.feed_update(
            w0.copy(), w1.copy(), np.ones(n, bool), np.array([0.0, 0.0, -1e3]), radii, max_distance, m.cell_radius,
            separation, 0.02, m.resolution, m.lo_key, m.dims, m._nby, m._nbz, m._block_cells, m._block_count,
            m._block_stamp, m._version, s["state"], s["cache_w0"], s["cache_w1"], s["cache_distance"],
            s["cand_start"], s["cand_index"], s["cand_xyz"], s["rel_blocks"], s["scratch_index"],
            s["scratch_distance"], s["out_index"], s["out_distance"], s["out_count"], s["out_cells"],
            s["out_centres"], s["cand_bound"], s["displacement"], s["kept_cells"],
        )  # fmt: skip
        query = m.closest_cells(w0, w1, radii, max_distance=max_distance, per_capsule=k, min_separation=separation,
                                candidates=m_max)
        assert np.array_equal(s["out_count"], query.counts)
        valid = query.indices >= 0
        assert np.array_equal(s["out_index"][valid], query.indices[valid])
        np.testing.assert_allclose(s["out_distance"][valid], query.distances[valid], rtol=0, atol=1e-12)
        best: dict[int, float] = {}
        for i, d in zip(query.indices[valid], query.distances[valid]):
            best[int(i)] = min(best.get(int(i), np.inf), float(d))
        expected = sorted(sorted(best, key=best.get)[:24])
        assert fed == len(expected) and s["out_cells"][:fed].tolist() == expected
        return fed, s

    return tick


def test_feed_skips_only_kept_candidates_that_cannot_change_the_closest_cells():
    """The per-tick feed keeps each capsule's candidate cells between map changes and skips a kept
    candidate without its distance when, at the lists' capsule pose, it was farther than the M-th
    closest candidate by more than twice the capsule's displacement since. Oracle: the full block
    search (``ObstacleMap.closest_cells``, checked against brute force in test_obstacle_map.py)
    every tick. Scene 1 (hand-built): 40 cells on one side of a capsule, 8 cells 3 cm farther on
    the other, the capsule then moves 1.6 cm towards them (inside the 2 cm slack, no rebuild): the
    far cells become the closest; then a cell appears in a block that was empty. Catches (planted
    and checked) a bound without the displacement (the far cells are skipped), and empty blocks not
    listed as dependent (the new cell is never fed). Scene 2: random cells and capsules wandering in
    steps up to 6 mm (rebuilds when past the slack or when cells are added or erased)."""
    from harvest_qp.perception import _feed_kernels as FK

    m = ObstacleMap(bounds=((-0.4, -0.4, 0.6), (0.4, 0.4, 1.4)))
    near = [(kx, ky, kz) for kx in (-13, -14) for ky in (-1, 0) for kz in range(100, 110)]
    far = [(15, ky, kz) for ky in (-1, 0) for kz in range(100, 104)]
    _occupy(m, near + far)
    tick = _feed_and_full_query(m, 1)
    radii = np.array([0.05])
    fed_far = False
    for shift in (0.0, 0.008, 0.016):
        w0, w1 = np.array([[shift, 0.0, 1.0]]), np.array([[shift, 0.0, 1.1]])
        count, s = tick(w0, w1, radii)
        assert s["state"][FK.FEED_REBUILDS] == 1  # lists kept from the first tick
        fed_far = fed_far or bool((m.keys(s["out_centres"][:count])[:, 0] == 15).any())
    assert fed_far  # the far cells were reached through the kept lists
    # A cell appears in a block that was empty, next to the capsule, which holds still.
    _occupy(m, [(6, 0, 105)])
    count, s = tick(w0, w1, radii)
    assert s["state"][FK.FEED_REBUILDS] == 2
    assert (m.keys(s["out_centres"][:count]) == (6, 0, 105)).all(axis=1).any()
    # Scene 2.
    rng = np.random.default_rng(3)
    m = ObstacleMap(bounds=((-0.4, -0.4, 0.6), (0.4, 0.4, 1.4)))
    cells = rng.integers((-12, -12, 88), (12, 12, 112), size=(700, 3))
    _occupy(m, cells)
    n = 3
    tick = _feed_and_full_query(m, n)
    radii = np.array([0.04, 0.05, 0.03])
    centre = np.zeros((n, 3)) + [0.0, 0.0, 1.0]
    axis = rng.normal(size=(n, 3)) * 0.05
    for step in range(200):
        centre += rng.normal(size=(n, 3)) * (0.002 if step % 40 else 0.03)
        centre = np.clip(centre, [-0.1, -0.1, 0.9], [0.1, 0.1, 1.1])
        axis += rng.normal(size=(n, 3)) * 0.001
        if step % 25 == 12:
            gone = (cells[rng.integers(0, len(cells), 20)] + 0.5) * m.resolution
            m.erase([ExclusionRegion.sphere(p, 0.004) for p in gone])  # some cells forgotten
            _occupy(m, rng.integers((-12, -12, 88), (12, 12, 112), size=(15, 3)))  # some new ones
        tick(centre - axis, centre + axis, radii)
