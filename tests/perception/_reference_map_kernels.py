"""The obstacle map's frame kernel as it was on main ce2c8f7 (before the live bits): the oracle of
``test_map_live_bits.py``. Copied verbatim (``_trace_ray`` and ``integrate_frame``); the helpers
it calls are the package's, unchanged by the live bits.

Every clearing-ray step tests the frame stamp first and stamps every cell it crosses, including
cells already at clamp_min; ``N_CELLS_CLEARED`` counts those too.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from harvest_qp.perception._map_kernels import (  # noqa: F401  (names the copied code uses)
    _MASK,
    N_CELLS_CLEARED,
    N_EXCLUDED,
    N_INSERTED,
    N_INVALID,
    N_NO_RETURN_RAYS,
    N_OUT_OF_RANGE,
    N_OUTSIDE,
    N_RAYS,
    N_STEM_ERASED,
    OBSTACLE,
    STEM,
    _cell_region_class,
    _clip_to_box,
    _grid_classes,
    _mark_dirty,
    _point_in_boxed_regions,
    _region_boxes,
    cell_index,
)


@njit(cache=False)
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
        if tmx < tmy:
            if tmx < tmz:
                if sx > 0:
                    idx += cross_x if (ix & _MASK) == _MASK else 64
                else:
                    idx -= cross_x if (ix & _MASK) == 0 else 64
                ix += sx
                tmx += tdx
                if ix < 0 or ix >= nx:
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
        else:
            if tmy < tmz:
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


@njit(cache=False)
def integrate_frame(
    points, labels, pixels, image_size, origin, rotation, regions, stride, phase_row, phase_col, near_skip, min_range, max_range,
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
