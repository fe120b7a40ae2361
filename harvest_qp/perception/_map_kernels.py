"""Compiled (numba) kernels of :class:`harvest_qp.perception.obstacle_map.ObstacleMap`.

The map is a dense voxel grid over a bounded workspace, stored block by block: 8x8x8
cells per block, the 512 cells of a block contiguous, so a ray's consecutive cells share
cache lines and the capsule query can skip whole empty blocks. Each cell holds an
OctoMap log-odds value (float32, so the same arithmetic as OctoMap's ``OcTreeNode``) and
the id of the last frame that updated it (at most one update per cell per frame, hits
before misses, as OctoMap's ``insertPointCloud``).

Cell keys are OctoMap's without the 2^15 offset: ``key = floor(x / resolution)``, cell
centre ``(key + 0.5) * resolution``; ``ix = key - lo_key`` indexes the grid.
"""

from __future__ import annotations

import numpy as np
from numba import njit

BLOCK_SHIFT = 3
BLOCK = 1 << BLOCK_SHIFT  # cells per block edge
BLOCK_CELLS = BLOCK**3
_MASK = BLOCK - 1

# Point labels (same values as harvest_qp.runtime.interface).
STEM = 0
OBSTACLE = 1
ROBOT = 2

# Counters returned by integrate_frame.
N_INVALID = 0  # non-finite point or label outside the known ones
N_OUT_OF_RANGE = 1  # farther than max_range (or closer than min_range) from the camera
N_INSERTED = 2  # obstacle points that updated a cell as a hit
N_EXCLUDED = 3  # obstacle points inside an exclusion region
N_OUTSIDE = 4  # obstacle points outside the grid
N_STEM_ERASED = 5  # occupied cells forgotten because a stem point fell in them
N_RAYS = 6  # clearing rays traced
N_CELLS_CLEARED = 7  # cells that got a miss
N_NO_RETURN_RAYS = 8  # clearing rays traced for pixels without a return
N_COUNTERS = 9


@njit(cache=True, inline="always")
def cell_index(ix, iy, iz, nby, nbz):
    """Linear index of grid cell (ix, iy, iz) in the block layout."""
    block = ((ix >> BLOCK_SHIFT) * nby + (iy >> BLOCK_SHIFT)) * nbz + (iz >> BLOCK_SHIFT)
    return (block << 9) | ((ix & _MASK) << 6) | ((iy & _MASK) << 3) | (iz & _MASK)


@njit(cache=True)
def index_to_cell(idx, nby, nbz):
    """Grid cell (ix, iy, iz) of a linear index (inverse of :func:`cell_index`)."""
    block = idx >> 9
    local = idx & (BLOCK_CELLS - 1)
    bz = block % nbz
    rest = block // nbz
    by = rest % nby
    bx = rest // nby
    return (bx << 3) | (local >> 6), (by << 3) | ((local >> 3) & _MASK), (bz << 3) | (local & _MASK)


@njit(cache=True, inline="always")
def _squared_axis_distance(px, py, pz, regions, k):
    """Squared distance [m^2] from the point to the axis segment of capsule ``regions[k]``."""
    ax, ay, az = regions[k, 0], regions[k, 1], regions[k, 2]
    dx, dy, dz = regions[k, 3] - ax, regions[k, 4] - ay, regions[k, 5] - az
    wx, wy, wz = px - ax, py - ay, pz - az
    dd = dx * dx + dy * dy + dz * dz
    t = 0.0
    if dd > 0.0:
        t = (wx * dx + wy * dy + wz * dz) / dd
        t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    ex, ey, ez = wx - t * dx, wy - t * dy, wz - t * dz
    return ex * ex + ey * ey + ez * ez


@njit(cache=True, inline="always")
def _point_in_region(px, py, pz, regions, k):
    """True if the point lies in the capsule ``regions[k] = (x0, y0, z0, x1, y1, z1, r)``."""
    return _squared_axis_distance(px, py, pz, regions, k) <= regions[k, 6] * regions[k, 6]


@njit(cache=True, inline="always")
def _point_in_regions(px, py, pz, regions):
    """True if the point lies in one of the capsules ``regions[k] = (x0, y0, z0, x1, y1, z1, r)``."""
    for k in range(regions.shape[0]):
        if _point_in_region(px, py, pz, regions, k):
            return True
    return False


@njit(cache=True)
def _region_boxes(regions):
    """``(n, 6)`` axis-aligned boxes ``(lo, hi)`` around the capsule ``regions``, 1 nm wider than
    the capsules: a point outside all of them is outside every region whatever the rounding of
    :func:`_point_in_regions` (errors ~1e-16 m), so the exact test runs only inside."""
    boxes = np.empty((regions.shape[0], 6))
    for k in range(regions.shape[0]):
        r = regions[k, 6] + 1e-9
        for a in range(3):
            boxes[k, a] = min(regions[k, a], regions[k, 3 + a]) - r
            boxes[k, 3 + a] = max(regions[k, a], regions[k, 3 + a]) + r
    return boxes


@njit(cache=True, inline="always")
def _point_in_boxed_regions(px, py, pz, regions, boxes):
    """:func:`_point_in_regions`, the exact test only for the regions whose box holds the point."""
    for k in range(regions.shape[0]):
        if (
            boxes[k, 0] <= px and px <= boxes[k, 3] and boxes[k, 1] <= py and py <= boxes[k, 4]
            and boxes[k, 2] <= pz and pz <= boxes[k, 5] and _point_in_region(px, py, pz, regions, k)
        ):  # fmt: skip
            return True
    return False


@njit(cache=True)
def _cell_region_class(fx, fy, fz, res, regions, boxes):
    """Whether every point whose cell key is ``(fx, fy, fz)`` (floats) lies in a region (1), every
    one outside all of them (0), or it depends on the point (2), as :func:`_point_in_boxed_regions`
    decides it.

    The points of a cell lie in its box [key res, (key + 1) res] up to the rounding of
    ``p / res`` (~1e-16 m), so in the box widened by 1 nm, and that box in the ball of its
    centre with radius half its diagonal plus 1 nm. A region whose segment is farther than its
    radius plus that ball's from the centre (or whose 1 nm-wider bounding box misses the box)
    holds none of them; one nearer than its radius minus the ball's radius holds them all, 1 nm
    or more inside, far beyond the rounding of the exact test (the same 1 nm margin as
    :func:`_region_boxes`).
    """
    margin = 1e-9
    lo_x, lo_y, lo_z = fx * res - margin, fy * res - margin, fz * res - margin
    hi_x, hi_y, hi_z = (fx + 1.0) * res + margin, (fy + 1.0) * res + margin, (fz + 1.0) * res + margin
    cx, cy, cz = 0.5 * (lo_x + hi_x), 0.5 * (lo_y + hi_y), 0.5 * (lo_z + hi_z)
    ball = 0.5 * np.sqrt(3.0) * (res + 2.0 * margin) + margin
    undecided = False
    for k in range(regions.shape[0]):
        if (
            hi_x < boxes[k, 0] or lo_x > boxes[k, 3] or hi_y < boxes[k, 1] or lo_y > boxes[k, 4]
            or hi_z < boxes[k, 2] or lo_z > boxes[k, 5]
        ):  # fmt: skip
            continue
        distance = np.sqrt(_squared_axis_distance(cx, cy, cz, regions, k))
        radius = regions[k, 6]
        if distance + ball + margin <= radius:
            return 1
        if distance - ball - margin <= radius:
            undecided = True
    return 2 if undecided else 0


@njit(cache=True)
def _grid_classes(size, phase, stride):
    """Per pixel row (or column) index: 2 on the ``2 * stride`` grid of ``phase``, 1 on the
    ``stride`` grid only, 0 off it (the same tests as ``(i - phase) % stride == 0``)."""
    out = np.zeros(size, np.int8)
    for i in range(size):
        d = i - phase
        if stride <= 1 or d % stride == 0:
            out[i] = 2 if d % (2 * stride) == 0 else 1
    return out


@njit(cache=True, inline="always")
def _mark_dirty(block, dirty, dirty_list, n_dirty):
    if not dirty[block]:
        dirty[block] = True
        dirty_list[n_dirty[0]] = block
        n_dirty[0] += 1


@njit(cache=True)
def _trace_ray(
    ox, oy, oz, ex, ey, ez, res, lo_key, dims, nby, nbz, log_odds, stamp, frame, miss, clamp_min,
    dirty, dirty_list, n_dirty,
):
    """Apply a miss to every cell the segment origin -> end crosses, the end's own cell excluded.

    The traversal is OctoMap's ``computeRayKeys`` (Amanatides & Woo): the origin's cell,
    then each cell entered before the end's cell or before the segment ends. The origin
    must lie in the grid; the walk stops when it leaves the grid. The linear index is
    stepped incrementally (within a block or across to the next block) rather than
    recomputed: this loop is the map update's main cost. Returns the number of cells that
    got a miss.
    """
    inv = 1.0 / res
    kox = int(np.floor(ox * inv))
    koy = int(np.floor(oy * inv))
    koz = int(np.floor(oz * inv))
    kex = int(np.floor(ex * inv))
    key_ey = int(np.floor(ey * inv))
    kez = int(np.floor(ez * inv))
    if kox == kex and koy == key_ey and koz == kez:
        return 0
    dx, dy, dz = ex - ox, ey - oy, ez - oz
    length = np.sqrt(dx * dx + dy * dy + dz * dz)
    dx /= length
    dy /= length
    dz /= length
    big = 1e300
    sx = 1 if dx > 0.0 else (-1 if dx < 0.0 else 0)
    sy = 1 if dy > 0.0 else (-1 if dy < 0.0 else 0)
    sz = 1 if dz > 0.0 else (-1 if dz < 0.0 else 0)
    tmx = ((kox + 0.5) * res + sx * res * 0.5 - ox) / dx if sx != 0 else big
    tmy = ((koy + 0.5) * res + sy * res * 0.5 - oy) / dy if sy != 0 else big
    tmz = ((koz + 0.5) * res + sz * res * 0.5 - oz) / dz if sz != 0 else big
    tdx = res / abs(dx) if sx != 0 else big
    tdy = res / abs(dy) if sy != 0 else big
    tdz = res / abs(dz) if sz != 0 else big
    nx, ny, nz = dims[0], dims[1], dims[2]
    # Grid cell and its end-cell offsets; the end key in grid coordinates.
    ix, iy, iz = kox - lo_key[0], koy - lo_key[1], koz - lo_key[2]
    jx, jy, jz = kex - lo_key[0], key_ey - lo_key[1], kez - lo_key[2]
    if not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz):
        return 0
    # Index steps: inside a block, and when crossing into the next block (+1 direction).
    bsx = (nby * nbz) << 9
    bsy = nbz << 9
    bsz = 1 << 9
    cross_x = bsx - (_MASK << 6)
    cross_y = bsy - (_MASK << 3)
    cross_z = bsz - _MASK
    idx = cell_index(ix, iy, iz, nby, nbz)
    count = 0
    while True:
        if stamp[idx] != frame:
            stamp[idx] = frame
            old = log_odds[idx]
            if old > clamp_min:
                new = old + miss
                if new < clamp_min:
                    new = clamp_min
                log_odds[idx] = new
                if old > 0.0 and new <= 0.0:
                    _mark_dirty(idx >> 9, dirty, dirty_list, n_dirty)
            count += 1
        # Step into the next cell along the axis whose boundary is nearest (ties: z, then y).
        if tmx < tmy and tmx < tmz:
            if sx > 0:
                idx += cross_x if (ix & _MASK) == _MASK else 64
            else:
                idx -= cross_x if (ix & _MASK) == 0 else 64
            ix += sx
            tmx += tdx
            if ix < 0 or ix >= nx:
                return count
        elif tmx >= tmy and tmy < tmz:
            if sy > 0:
                idx += cross_y if (iy & _MASK) == _MASK else 8
            else:
                idx -= cross_y if (iy & _MASK) == 0 else 8
            iy += sy
            tmy += tdy
            if iy < 0 or iy >= ny:
                return count
        else:
            if sz > 0:
                idx += cross_z if (iz & _MASK) == _MASK else 1
            else:
                idx -= cross_z if (iz & _MASK) == 0 else 1
            iz += sz
            tmz += tdz
            if iz < 0 or iz >= nz:
                return count
        if ix == jx and iy == jy and iz == jz:
            return count
        if min(tmx, min(tmy, tmz)) > length:
            return count


@njit(cache=True)
def _clip_to_box(ox, oy, oz, px, py, pz, lo, hi):
    """Segment o -> p clipped to the box [lo, hi]: (t0, t1) in [0, 1], t0 > t1 when it misses."""
    t0, t1 = 0.0, 1.0
    o = (ox, oy, oz)
    d = (px - ox, py - oy, pz - oz)
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                return 1.0, 0.0
        else:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            t0 = max(t0, ta)
            t1 = min(t1, tb)
    return t0, t1


@njit(cache=True)
def integrate_frame(
    points, labels, pixels, image_size, origin, rotation, regions, stride, phase_row, phase_col, near_skip, min_range,
    max_range,
    no_return, nr_stride, nr_phase_row, nr_phase_col, intrinsics, returned, res, lo_key, dims, nby, nbz,
    log_odds, stamp, frame, hit, miss,
    clamp_min, clamp_max, dirty, dirty_list, n_dirty, counters,
):
    """One camera frame into the map (see ``ObstacleMap.update`` for the rules); ``image_size``: (h, w).

    Pass 1 inserts the obstacle points (one hit per cell), pass 2 erases the cells the stem
    points fall in, pass 3 traces the clearing rays of the pixels on the ``stride`` grid
    (one miss per cell, none where pass 1 or 2 acted this frame; those off the twice coarser
    grid start ``near_skip`` [m] from the camera when it is > 0); pass 4, when
    ``no_return[1] > no_return[0]``, traces the pixels of the ``nr_stride`` grid without any point from
    ``no_return[0]`` to ``no_return[1]`` [m] along the pinhole rays of ``intrinsics``
    ``(f, cx, cy)`` [pixels] (camera rotation ``rotation``; ``returned`` is an (h, w) scratch).
    """
    n = points.shape[0]
    ox, oy, oz = origin[0], origin[1], origin[2]
    inv = 1.0 / res
    nx, ny, nz = dims[0], dims[1], dims[2]
    lo = (lo_key[0] * res, lo_key[1] * res, lo_key[2] * res)
    hi = ((lo_key[0] + nx) * res, (lo_key[1] + ny) * res, (lo_key[2] + nz) * res)
    # Slightly inside the box, so the clipped end points fall in edge cells.
    eps = 1e-9 * res
    lo_in = (lo[0] + eps, lo[1] + eps, lo[2] + eps)
    hi_in = (hi[0] - eps, hi[1] - eps, hi[2] - eps)
    min2, max2 = min_range * min_range, max_range * max_range
    boxes = _region_boxes(regions)
    # The box around all of them, in locals: most points are outside it (one test, not one per region).
    ulx = uly = ulz = np.inf
    uhx = uhy = uhz = -np.inf
    for k in range(boxes.shape[0]):
        ulx, uly, ulz = min(ulx, boxes[k, 0]), min(uly, boxes[k, 1]), min(ulz, boxes[k, 2])
        uhx, uhy, uhz = max(uhx, boxes[k, 3]), max(uhy, boxes[k, 4]), max(uhz, boxes[k, 5])
    # Pixel grid membership from per-row and per-column tables (an integer modulo per point
    # was a fifth of the update at 848x480); pixels outside the image take the modulo path.
    h_img, w_img = min(image_size[0], 1 << 16), min(image_size[1], 1 << 16)
    row_class = _grid_classes(h_img, phase_row, stride)
    col_class = _grid_classes(w_img, phase_col, stride)
    # One pass over the cloud: it inserts the obstacle points and lists the valid stem points
    # (pass 2) and the valid points on the clearing grid (pass 3, with 2 for the coarser grid),
    # in cloud order, so the later passes do not read the whole cloud again.
    stem_list = np.empty(n, np.int64)
    ray_list = np.empty(n, np.int64)
    ray_class = np.empty(n, np.int8)
    n_stem = 0
    n_ray = 0
    # Cell key of the last obstacle point that reached the stamp test (stamped this frame
    # either way): a point in the same cell would find it stamped, so it is skipped before
    # the key is computed (neighbouring pixels mostly fall in one cell).
    fx0 = fy0 = fz0 = np.nan
    # Cell key of the last point tested against the exclusion regions, and its region class.
    gx0 = gy0 = gz0 = np.nan
    region_class = 2
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        lab = labels[i]
        # Finite exactly when x * 0 + y * 0 + z * 0 == 0 (inf * 0 and NaN give NaN): one test,
        # not three (~0.1 ms of the pass over 190,000 points, measured).
        if not (px * 0.0 + py * 0.0 + pz * 0.0 == 0.0) or lab < 0 or lab > 2:
            counters[N_INVALID] += 1
            continue
        r2 = (px - ox) ** 2 + (py - oy) ** 2 + (pz - oz) ** 2
        if r2 > max2 or r2 < min2:
            counters[N_OUT_OF_RANGE] += 1
            continue
        r, c = pixels[i, 0], pixels[i, 1]
        if 0 <= r < h_img and 0 <= c < w_img:
            rc = row_class[r]
            cc = col_class[c] if rc != 0 else 0
        else:
            dr, dc = r - phase_row, c - phase_col
            rc = 0 if stride > 1 and dr % stride != 0 else (2 if dr % (2 * stride) == 0 else 1)
            cc = 0 if stride > 1 and dc % stride != 0 else (2 if dc % (2 * stride) == 0 else 1)
        if rc != 0 and cc != 0:
            ray_list[n_ray] = i
            ray_class[n_ray] = 2 if rc == 2 and cc == 2 else 1
            n_ray += 1
        if lab != OBSTACLE:
            if lab == STEM:
                stem_list[n_stem] = i
                n_stem += 1
            continue
        vx, vy, vz = px * inv, py * inv, pz * inv
        if ulx <= px and px <= uhx and uly <= py and py <= uhy and ulz <= pz and pz <= uhz:
            # Most points in the regions' box lie in a cell wholly inside a region (the held
            # cluster) or wholly outside all: decided once per cell (_cell_region_class), the
            # exact test only in the cells the regions' surfaces cross.
            if not (gx0 <= vx and vx < gx0 + 1.0 and gy0 <= vy and vy < gy0 + 1.0 and gz0 <= vz and vz < gz0 + 1.0):
                gx0, gy0, gz0 = np.floor(vx), np.floor(vy), np.floor(vz)
                region_class = _cell_region_class(gx0, gy0, gz0, res, regions, boxes)
            if region_class == 1 or (region_class == 2 and _point_in_boxed_regions(px, py, pz, regions, boxes)):
                counters[N_EXCLUDED] += 1
                continue
        # floor(v) == f exactly when f <= v < f + 1 (NaN at the start: never).
        if fx0 <= vx and vx < fx0 + 1.0 and fy0 <= vy and vy < fy0 + 1.0 and fz0 <= vz and vz < fz0 + 1.0:
            continue
        fx, fy, fz = np.floor(vx), np.floor(vy), np.floor(vz)
        ix = int(fx) - lo_key[0]
        iy = int(fy) - lo_key[1]
        iz = int(fz) - lo_key[2]
        if not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz):
            counters[N_OUTSIDE] += 1
            continue
        fx0, fy0, fz0 = fx, fy, fz
        idx = cell_index(ix, iy, iz, nby, nbz)
        if stamp[idx] == frame:
            continue
        stamp[idx] = frame
        old = log_odds[idx]
        new = old + hit
        if new > clamp_max:
            new = clamp_max
        log_odds[idx] = new
        counters[N_INSERTED] += 1
        if old <= 0.0 and new > 0.0:
            _mark_dirty(idx >> 9, dirty, dirty_list, n_dirty)
    # The stem is what the arms must reach: an occupied cell a stem point falls in is
    # forgotten (unless an obstacle point hit it in this frame), so a stem seen earlier as
    # an obstacle (beyond the camera's stem range) leaves the map once it is recognised.
    for j in range(n_stem):
        i = stem_list[j]
        ix = int(np.floor(points[i, 0] * inv)) - lo_key[0]
        iy = int(np.floor(points[i, 1] * inv)) - lo_key[1]
        iz = int(np.floor(points[i, 2] * inv)) - lo_key[2]
        if not (0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz):
            continue
        idx = cell_index(ix, iy, iz, nby, nbz)
        if stamp[idx] == frame:
            continue
        stamp[idx] = frame
        if log_odds[idx] > 0.0:
            log_odds[idx] = 0.0
            counters[N_STEM_ERASED] += 1
            _mark_dirty(idx >> 9, dirty, dirty_list, n_dirty)
    for j in range(n_ray):
        i = ray_list[j]
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        sx, sy, sz = ox, oy, oz
        t0, t1 = _clip_to_box(ox, oy, oz, px, py, pz, lo_in, hi_in)
        if near_skip > 0.0 and ray_class[j] != 2:
            # Within near_skip of the camera the rays of the twice coarser grid are close
            # enough to cross every cell: the others start there (half the ray steps).
            rng = np.sqrt((px - ox) ** 2 + (py - oy) ** 2 + (pz - oz) ** 2)
            if rng <= near_skip:
                continue
            t0 = max(t0, near_skip / rng)
        if t0 > t1:
            continue
        if t0 > 0.0:
            sx, sy, sz = ox + t0 * (px - ox), oy + t0 * (py - oy), oz + t0 * (pz - oz)
        counters[N_RAYS] += 1
        counters[N_CELLS_CLEARED] += _trace_ray(
            sx, sy, sz, px, py, pz, res, lo_key, dims, nby, nbz, log_odds, stamp, frame, miss, clamp_min,
            dirty, dirty_list, n_dirty,
        )
    if no_return[1] <= no_return[0]:
        return
    # Pixels without a return (nothing within the camera's range, as the empty space behind
    # a leaf that moved away): clear along their rays from no_return[0] to no_return[1].
    h, w = returned.shape
    returned[:, :] = False
    for i in range(n):
        r, c = pixels[i, 0], pixels[i, 1]
        if 0 <= r < h and 0 <= c < w:
            returned[r, c] = True  # any point, valid or not: that pixel saw something
    for r in range(h):
        if nr_stride > 1 and (r - nr_phase_row) % nr_stride != 0:
            continue
        for c in range(w):
            if returned[r, c] or (nr_stride > 1 and (c - nr_phase_col) % nr_stride != 0):
                continue
            xc = (c + 0.5 - intrinsics[1]) / intrinsics[0]
            yc = (r + 0.5 - intrinsics[2]) / intrinsics[0]
            norm = np.sqrt(xc * xc + yc * yc + 1.0)
            dx = (rotation[0, 0] * xc + rotation[0, 1] * yc + rotation[0, 2]) / norm
            dy = (rotation[1, 0] * xc + rotation[1, 1] * yc + rotation[1, 2]) / norm
            dz = (rotation[2, 0] * xc + rotation[2, 1] * yc + rotation[2, 2]) / norm
            ax, ay, az = ox + no_return[0] * dx, oy + no_return[0] * dy, oz + no_return[0] * dz
            bx, by, bz = ox + no_return[1] * dx, oy + no_return[1] * dy, oz + no_return[1] * dz
            t0, t1 = _clip_to_box(ax, ay, az, bx, by, bz, lo_in, hi_in)
            if t0 > t1:
                continue
            if t0 > 0.0:
                ax, ay, az = ax + t0 * (bx - ax), ay + t0 * (by - ay), az + t0 * (bz - az)
            counters[N_NO_RETURN_RAYS] += 1
            counters[N_CELLS_CLEARED] += _trace_ray(
                ax, ay, az, bx, by, bz, res, lo_key, dims, nby, nbz, log_odds, stamp, frame, miss, clamp_min,
                dirty, dirty_list, n_dirty,
            )


@njit(cache=True)
def erase_regions(regions, res, lo_key, dims, nby, nbz, log_odds, dirty, dirty_list, n_dirty, block_cells, block_count):
    """Forget (log-odds 0) every occupied cell whose centre lies in one of the capsule ``regions``; returns how many.

    Visits only the occupied cells of the blocks the regions' boxes overlap: the block lists
    must be up to date (no dirty block on entry: ``ObstacleMap`` rebuilds them after every change).
    """
    if n_dirty[0] > 0:
        raise ValueError("erase_regions: the block lists are out of date (dirty blocks)")
    erased = 0
    lo_i = np.empty(3, np.int64)
    hi_i = np.empty(3, np.int64)
    for k in range(regions.shape[0]):
        r = regions[k, 6]
        empty = False
        for a in range(3):
            lo_c = min(regions[k, a], regions[k, 3 + a]) - r
            hi_c = max(regions[k, a], regions[k, 3 + a]) + r
            lo_i[a] = max(int(np.floor(lo_c / res)) - lo_key[a], 0)
            hi_i[a] = min(int(np.floor(hi_c / res)) - lo_key[a], dims[a] - 1)
            empty = empty or lo_i[a] > hi_i[a]
        if empty:
            continue
        for bx in range(lo_i[0] >> BLOCK_SHIFT, (hi_i[0] >> BLOCK_SHIFT) + 1):
            for by in range(lo_i[1] >> BLOCK_SHIFT, (hi_i[1] >> BLOCK_SHIFT) + 1):
                for bz in range(lo_i[2] >> BLOCK_SHIFT, (hi_i[2] >> BLOCK_SHIFT) + 1):
                    b = (bx * nby + by) * nbz + bz
                    for j in range(block_count[b]):
                        local = block_cells[b, j]
                        ix = (bx << BLOCK_SHIFT) | (local >> 6)
                        iy = (by << BLOCK_SHIFT) | ((local >> 3) & _MASK)
                        iz = (bz << BLOCK_SHIFT) | (local & _MASK)
                        if not (lo_i[0] <= ix <= hi_i[0] and lo_i[1] <= iy <= hi_i[1] and lo_i[2] <= iz <= hi_i[2]):
                            continue
                        cx = (ix + lo_key[0] + 0.5) * res
                        cy = (iy + lo_key[1] + 0.5) * res
                        cz = (iz + lo_key[2] + 0.5) * res
                        if not _point_in_region(cx, cy, cz, regions, k):
                            continue
                        idx = (b << 9) | local
                        if log_odds[idx] > 0.0:
                            log_odds[idx] = 0.0
                            erased += 1
                            _mark_dirty(b, dirty, dirty_list, n_dirty)
    return erased


@njit(cache=True)
def replace_prior(points, value, clamp_min, old, res, lo_key, dims, nby, nbz, log_odds, dirty, dirty_list, n_dirty,
                  out):  # fmt: skip
    """Replace the prior cells ``old`` by the unknown cells holding ``points`` (indices to ``out``); returns how many.

    The old prior's ``value`` is taken out of its cells (what frames added since stays; exactly
    0 when none did; an erased cell stays 0); then an unknown cell (0) holding a point gets ``value``.
    """
    for j in range(old.shape[0]):
        idx = old[j]
        x = log_odds[idx]
        if x != 0.0:  # 0: erased since (a region or a stem point made it unknown)
            log_odds[idx] = 0.0 if x == value else max(x - value, clamp_min)
            _mark_dirty(idx >> 9, dirty, dirty_list, n_dirty)
    n = 0
    for j in range(points.shape[0]):
        idx = point_cell(points, j, res, lo_key, dims, nby, nbz)
        if idx >= 0 and log_odds[idx] == 0.0:
            log_odds[idx] = value
            _mark_dirty(idx >> 9, dirty, dirty_list, n_dirty)
            out[n] = idx
            n += 1
    return n


@njit(cache=True)
def rebuild_blocks(dirty_list, n_dirty, dirty, log_odds, block_cells, block_count, block_stamp, version):
    """Refresh the list of occupied cells (log-odds > 0) of every dirty block, stamp it with
    ``version`` (the map's version after this change), then clear the flags."""
    for j in range(n_dirty):
        b = dirty_list[j]
        block_stamp[b] = version
        base = b << 9
        c = 0
        for local in range(BLOCK_CELLS):
            if log_odds[base + local] > 0.0:
                block_cells[b, c] = local
                c += 1
        block_count[b] = c
        dirty[b] = False


@njit(cache=True, inline="always")
def _point_segment_distance(px, py, pz, ax, ay, az, dx, dy, dz, dd):
    wx, wy, wz = px - ax, py - ay, pz - az
    t = 0.0
    if dd > 0.0:
        t = (wx * dx + wy * dy + wz * dz) / dd
        t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
    ex, ey, ez = wx - t * dx, wy - t * dy, wz - t * dz
    return np.sqrt(ex * ex + ey * ey + ez * ez)


@njit(cache=True, inline="always")
def capsule_segment(w0, w1, c):
    """Capsule ``c``'s axis: its start (ax, ay, az), its vector (dx, dy, dz) and squared length dd."""
    ax, ay, az = w0[c, 0], w0[c, 1], w0[c, 2]
    dx, dy, dz = w1[c, 0] - ax, w1[c, 1] - ay, w1[c, 2] - az
    return ax, ay, az, dx, dy, dz, dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def cell_centre(cx0, cy0, cz0, local, res):
    """World centre [m] of cell ``local`` of the block whose lower corner is (cx0, cy0, cz0)."""
    x = cx0 + ((local >> 6) + 0.5) * res
    y = cy0 + (((local >> 3) & _MASK) + 0.5) * res
    return x, y, cz0 + ((local & _MASK) + 0.5) * res


@njit(cache=True)
def blocks_in_reach(w0, w1, c, reach, res, lo_key, dims, nby, nbz, blocks, corners):
    """The map blocks that capsule ``c``'s segment box, grown by ``reach`` [m], overlaps, in
    (x, y, z) order: their ids into ``blocks``, their lower corners [m] into ``corners``
    (both sized for every block of the map); returns how many."""
    nb = (dims[0] >> BLOCK_SHIFT, nby, nbz)
    lo = np.empty(3, np.int64)
    hi = np.empty(3, np.int64)
    for a in range(3):
        lo_c = min(w0[c, a], w1[c, a]) - reach
        hi_c = max(w0[c, a], w1[c, a]) + reach
        lo[a] = max((int(np.floor(lo_c / res)) - lo_key[a]) >> BLOCK_SHIFT, 0)
        hi[a] = min((int(np.floor(hi_c / res)) - lo_key[a]) >> BLOCK_SHIFT, nb[a] - 1)
    n = 0
    for bx in range(lo[0], hi[0] + 1):
        for by in range(lo[1], hi[1] + 1):
            for bz in range(lo[2], hi[2] + 1):
                blocks[n] = (bx * nby + by) * nbz + bz
                corners[n, 0] = (lo_key[0] + bx * BLOCK) * res
                corners[n, 1] = (lo_key[1] + by * BLOCK) * res
                corners[n, 2] = (lo_key[2] + bz * BLOCK) * res
                n += 1
    return n


@njit(cache=True)
def _insert_sorted(scratch_distance, scratch_index, count, m_max, d, idx):
    """Insert ``(d, idx)`` into the ascending top-``m_max`` list; returns the new count."""
    pos = count if count < m_max else m_max - 1
    while pos > 0 and scratch_distance[pos - 1] > d:
        scratch_distance[pos] = scratch_distance[pos - 1]
        scratch_index[pos] = scratch_index[pos - 1]
        pos -= 1
    scratch_distance[pos] = d
    scratch_index[pos] = idx
    return count + 1 if count < m_max else count


@njit(cache=True)
def keep_separated(c, count, k_max, sep2, res, nby, nbz, radius, cell_radius, scratch_index, scratch_distance,
                   out_index, out_distance, kept_cells):
    """Capsule ``c``'s first ``k_max`` cells of the sorted list, each at least ``sqrt(sep2)``
    from those kept before it; their surface distances into ``out_*[c]``. Returns how many.
    ``kept_cells``: ``(k_max, 3)`` int scratch for the kept cells' grid coordinates."""
    kept = 0
    for j in range(count):
        if kept == k_max:
            break
        idx = scratch_index[j]
        if sep2 > 0.0:
            ix, iy, iz = index_to_cell(idx, nby, nbz)
            far = True
            for i in range(kept):
                jx, jy, jz = kept_cells[i, 0], kept_cells[i, 1], kept_cells[i, 2]
                if ((ix - jx) ** 2 + (iy - jy) ** 2 + (iz - jz) ** 2) * res * res < sep2:
                    far = False
                    break
            if not far:
                continue
            kept_cells[kept, 0] = ix
            kept_cells[kept, 1] = iy
            kept_cells[kept, 2] = iz
        out_index[c, kept] = idx
        out_distance[c, kept] = scratch_distance[j] - radius - cell_radius
        kept += 1
    return kept


@njit(cache=True)
def closest_cells(
    w0, w1, radii, max_distance, cell_radius, min_separation, res, lo_key, dims, nby, nbz, block_cells,
    block_count, scratch_index, scratch_distance, out_index, out_distance, out_count,
):
    """For each capsule ``w0[c]-w1[c]`` (radius ``radii[c]``), its closest occupied cells.

    A cell counts as the sphere of radius ``cell_radius`` around its centre; its distance
    is the capsule-sphere surface distance. The ``m = scratch_index.shape[0]`` closest
    cells within ``max_distance`` are collected (blocks whose bounding sphere is farther
    are skipped whole), then kept closest first, skipping a cell closer than
    ``min_separation`` to one already kept (neighbouring cells of one surface give nearly
    the same damper row), up to ``out_index.shape[1]`` cells: ``out_index[c]`` (linear cell
    indices), ``out_distance[c]``, ``out_count[c]``.
    """
    m_max = scratch_index.shape[0]
    k_max = out_index.shape[1]
    block_half_diag = 0.5 * BLOCK * res * np.sqrt(3.0)
    half = 0.5 * BLOCK * res
    sep2 = min_separation * min_separation
    blocks = np.empty(block_count.shape[0], np.int64)
    corners = np.empty((block_count.shape[0], 3))
    kept_cells = np.empty((k_max, 3), np.int64)
    for c in range(w0.shape[0]):
        ax, ay, az, dx, dy, dz, dd = capsule_segment(w0, w1, c)
        reach = radii[c] + max_distance + cell_radius  # centre distance that still counts
        count = 0
        worst = reach  # current admission bound on the centre distance
        for i in range(blocks_in_reach(w0, w1, c, reach, res, lo_key, dims, nby, nbz, blocks, corners)):
            b = blocks[i]
            nc = block_count[b]
            if nc == 0:
                continue
            cx0, cy0, cz0 = corners[i, 0], corners[i, 1], corners[i, 2]
            db = _point_segment_distance(cx0 + half, cy0 + half, cz0 + half, ax, ay, az, dx, dy, dz, dd)
            if db - block_half_diag > worst:
                continue
            for j in range(nc):
                local = block_cells[b, j]
                px, py, pz = cell_centre(cx0, cy0, cz0, local, res)
                d = _point_segment_distance(px, py, pz, ax, ay, az, dx, dy, dz, dd)
                if d > worst:
                    continue
                count = _insert_sorted(scratch_distance, scratch_index, count, m_max, d, (b << 9) | local)
                if count == m_max:
                    worst = scratch_distance[m_max - 1]
        out_count[c] = keep_separated(c, count, k_max, sep2, res, nby, nbz, radii[c], cell_radius, scratch_index,
                                      scratch_distance, out_index, out_distance, kept_cells)


@njit(cache=True)
def cell_centres(indices, res, lo_key, nby, nbz, out):
    """World centres [m] of linear cell ``indices``."""
    for j in range(indices.shape[0]):
        ix, iy, iz = index_to_cell(indices[j], nby, nbz)
        out[j, 0] = (ix + lo_key[0] + 0.5) * res
        out[j, 1] = (iy + lo_key[1] + 0.5) * res
        out[j, 2] = (iz + lo_key[2] + 0.5) * res


@njit(cache=True, inline="always")
def point_cell(points, j, res, lo_key, dims, nby, nbz):
    """Linear index of the cell holding ``points[j]``; -1 outside the grid or for a non-finite point."""
    px, py, pz = points[j, 0], points[j, 1], points[j, 2]
    if not (np.isfinite(px) and np.isfinite(py) and np.isfinite(pz)):
        return -1
    ix = int(np.floor(px / res)) - lo_key[0]
    iy = int(np.floor(py / res)) - lo_key[1]
    iz = int(np.floor(pz / res)) - lo_key[2]
    if 0 <= ix < dims[0] and 0 <= iy < dims[1] and 0 <= iz < dims[2]:
        return cell_index(ix, iy, iz, nby, nbz)
    return -1


@njit(cache=True)
def log_odds_at(points, res, lo_key, dims, nby, nbz, log_odds, out):
    """Log-odds of the cells holding ``points`` (0 = unknown for points outside the grid or non-finite)."""
    for j in range(points.shape[0]):
        idx = point_cell(points, j, res, lo_key, dims, nby, nbz)
        out[j] = log_odds[idx] if idx >= 0 else 0.0


@njit(cache=True)
def occupied_indices(block_cells, block_count, out):
    """Linear indices of all occupied cells into ``out``; returns how many."""
    n = 0
    for b in range(block_count.shape[0]):
        for j in range(block_count[b]):
            out[n] = (b << 9) | block_cells[b, j]
            n += 1
    return n


@njit(cache=True)
def gather_cells(index, distance, max_cells, res, lo_key, nby, nbz, out_cells, out_centres):
    """Union of the capsules' cells (``index[c, j] >= 0``), at most ``max_cells`` of them.

    When there are more, the ones closest to any capsule are kept. The kept cells are
    written sorted into ``out_cells`` with their centres [m] in ``out_centres``; returns
    how many.
    """
    n_all = index.shape[0] * index.shape[1]
    cells = np.empty(n_all, np.int64)
    best = np.empty(n_all)
    n = 0
    for c in range(index.shape[0]):
        for j in range(index.shape[1]):
            idx = index[c, j]
            if idx < 0:
                continue
            found = -1
            for i in range(n):
                if cells[i] == idx:
                    found = i
                    break
            if found < 0:
                cells[n] = idx
                best[n] = distance[c, j]
                n += 1
            elif distance[c, j] < best[found]:
                best[found] = distance[c, j]
    if n > max_cells:
        order = np.argsort(best[:n], kind="mergesort")
        kept = np.sort(cells[:n][order[:max_cells]])
        n = max_cells
        cells[:n] = kept
    else:
        cells[:n] = np.sort(cells[:n])
    for i in range(n):
        out_cells[i] = cells[i]
    cell_centres(out_cells[:n], res, lo_key, nby, nbz, out_centres)
    return n
