"""Compiled (numba) per-tick kernels of :class:`harvest_qp.perception.map_feed.MapCollisionFeed`.

The feed answers the query of :func:`harvest_qp.perception._map_kernels.closest_cells` then
:func:`~harvest_qp.perception._map_kernels.gather_cells` every control tick over candidate
cells kept between map changes (tested against that query in ``tests/perception``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from harvest_qp.collision import kernels as _collision
from harvest_qp.perception._map_kernels import (
    BLOCK,
    _insert_sorted,
    _point_segment_distance,
    blocks_in_reach,
    capsule_segment,
    cell_centre,
    gather_cells,
    keep_separated,
)

# --------------------------------------------------------------------------- per-tick feed
# MapCollisionFeed queries the map every control tick (500 Hz) but the map changes only when
# a camera frame is integrated (30 Hz) and the capsules move ~1 mm per tick. The feed keeps,
# per capsule, the occupied cells within ``reach + slack`` of the capsule where it was when the
# list was built (the candidates, in the full query's visiting order), and the blocks that
# can hold such cells. While every capsule end point stays within ``slack`` of where it was,
# no cell outside the list can come within ``reach`` (a segment's distance to a point moves
# by at most the larger of its end points' displacements), so the query over the list
# admits the same cells in the same order as the full query: the same result.
# The list is rebuilt when a capsule moved farther, when the query distance changed, or when
# one of its blocks changed occupancy since (the map stamps each rebuilt block with its
# version).

# Slots of the feed's integer state array.
FEED_VALID = 0  # 1 when the candidate lists hold
FEED_VERSION = 1  # map version the lists were checked against
FEED_N_BLOCKS = 2  # blocks the lists depend on
FEED_CHANGED = 3  # output: 1 when the fed cells differ from the last update's
FEED_N_LAST = 4  # cells fed at the last update
FEED_REBUILDS = 5  # lists rebuilt (diagnostics)
FEED_STATE = 6


@njit(cache=True)
def _feed_candidates(
    w0, w1, radii, max_distance, cell_radius, slack, res, lo_key, dims, nby, nbz, block_cells, block_count,
    cand_start, cand_index, cand_xyz, rel_blocks,
):
    """Candidate cells of each capsule (see above) in the visiting order of :func:`closest_cells`.

    Returns the number of dependent blocks written to ``rel_blocks``, or -1 when
    ``cand_index`` or ``rel_blocks`` is too small (nothing usable is written then). The empty
    blocks of each capsule's box are listed as dependent without their distance test (half the
    time of a rebuild, measured on the episode's maps); a longer list can only make the lists
    be rebuilt sooner, never kept when a block within reach changed."""
    block_half_diag = 0.5 * BLOCK * res * np.sqrt(3.0)
    half = 0.5 * BLOCK * res
    blocks = np.empty(block_count.shape[0], np.int64)
    corners = np.empty((block_count.shape[0], 3))
    cap_c = cand_index.shape[0]
    cap_b = rel_blocks.shape[0]
    n_cand = 0
    n_rel = 0
    for c in range(w0.shape[0]):
        cand_start[c] = n_cand
        ax, ay, az, dx, dy, dz, dd = capsule_segment(w0, w1, c)
        reach = radii[c] + max_distance + cell_radius + slack
        for i in range(blocks_in_reach(w0, w1, c, reach, res, lo_key, dims, nby, nbz, blocks, corners)):
            b = blocks[i]
            nc = block_count[b]
            cx0, cy0, cz0 = corners[i, 0], corners[i, 1], corners[i, 2]
            if nc > 0:
                db = _point_segment_distance(cx0 + half, cy0 + half, cz0 + half, ax, ay, az, dx, dy, dz, dd)
                if db - block_half_diag > reach:
                    continue
            if n_rel == cap_b:
                return -1
            rel_blocks[n_rel] = b
            n_rel += 1
            for j in range(nc):
                local = block_cells[b, j]
                px, py, pz = cell_centre(cx0, cy0, cz0, local, res)
                d = _point_segment_distance(px, py, pz, ax, ay, az, dx, dy, dz, dd)
                if d > reach:
                    continue
                if n_cand == cap_c:
                    return -1
                cand_index[n_cand] = (b << 9) | local
                cand_xyz[n_cand, 0] = px
                cand_xyz[n_cand, 1] = py
                cand_xyz[n_cand, 2] = pz
                n_cand += 1
    cand_start[w0.shape[0]] = n_cand
    return n_rel


# A bound that skips most kept candidates without their distance (exact, argued here). Let M be
# the length of the sorted list (scratch) and, for a capsule, D(e) its distance to candidate e
# when the lists were built (kept in cand_xyz[:, 3]), B the M-th smallest D (cand_bound; inf
# with fewer than M candidates) and s the larger displacement of its end points since then. A
# segment's distance to a point moves by at most s when its end points move by at most s, so M
# candidates are now within B + s (up to rounding, ~1e-16 m; the margin is 1e-9 m): when that is
# within reach they are all admitted, the list ends full and its last distance W <= B + s.
# A candidate with D(e) - s > B + s (+ margins) is then farther than W now. Such a candidate
# never changes the final list: it sorts after every candidate within W, so while it is in the
# list it is the one evicted (or skipped), and the candidates within W are admitted, evicted
# and ordered exactly as without it (the list of those is never full while it holds it). When
# B + s is beyond reach, it is farther than reach and skipped by the reach test anyway.
_BOUND_MARGIN = 1e-9  # [m]


@njit(cache=True)
def _candidate_bounds(w0, w1, n, m_max, cand_start, cand_xyz, cand_bound, scratch_distance):
    """Each candidate's distance to its capsule as the lists are built (into ``cand_xyz[:, 3]``) and
    each capsule's M-th smallest of them (``cand_bound``; inf with fewer than ``m_max`` candidates)."""
    for c in range(n):
        ax, ay, az, dx, dy, dz, dd = capsule_segment(w0, w1, c)
        count = 0
        for i in range(cand_start[c], cand_start[c + 1]):
            d = _point_segment_distance(cand_xyz[i, 0], cand_xyz[i, 1], cand_xyz[i, 2], ax, ay, az, dx, dy, dz, dd)
            cand_xyz[i, 3] = d
            if count == m_max and d >= scratch_distance[m_max - 1]:
                continue
            pos = count if count < m_max else m_max - 1
            while pos > 0 and scratch_distance[pos - 1] > d:
                scratch_distance[pos] = scratch_distance[pos - 1]
                pos -= 1
            scratch_distance[pos] = d
            if count < m_max:
                count += 1
        cand_bound[c] = scratch_distance[m_max - 1] if count == m_max else np.inf


@njit(cache=True)
def feed_update(
    w0, w1, active, park, radii, max_distance, cell_radius, min_separation, slack, res, lo_key, dims, nby, nbz,
    block_cells, block_count, block_stamp, map_version, state, cache_w0, cache_w1, cache_distance,
    cand_start, cand_index, cand_xyz, rel_blocks, scratch_index, scratch_distance, out_index, out_distance,
    out_count, out_cells, out_centres, cand_bound, displacement, kept_cells,
):
    """One tick of ``MapCollisionFeed.update`` after the capsules' world end points ``w0``, ``w1``.

    Returns -1 (nothing done) when an end point is not finite, -2 when the candidate
    arrays are too small (grow them and call again), else the number of cells written to
    ``out_cells`` / ``out_centres`` (the other slots of ``out_centres`` at ``park``), with
    ``state[FEED_CHANGED]`` telling whether they differ from the previous call's.
    Switched-off capsules (``active`` False) are moved to ``park`` first, in place.
    The result equals :func:`closest_cells` then :func:`gather_cells` (see above).
    ``cand_xyz`` has a 4th column for the candidates' distances; ``cand_bound``,
    ``displacement``: per-capsule scratch kept with the lists; ``kept_cells``: ``(k, 3)`` int
    scratch of :func:`keep_separated`."""
    n = w0.shape[0]
    for c in range(n):
        for a in range(3):
            if not (np.isfinite(w0[c, a]) and np.isfinite(w1[c, a])):
                return -1
    for c in range(n):
        if not active[c]:
            for a in range(3):
                w0[c, a] = park[a]
                w1[c, a] = park[a]
    valid = state[FEED_VALID] == 1 and cache_distance[0] == max_distance
    if valid:
        slack2 = slack * slack
        for c in range(n):
            e0 = (w0[c, 0] - cache_w0[c, 0]) ** 2 + (w0[c, 1] - cache_w0[c, 1]) ** 2 + (w0[c, 2] - cache_w0[c, 2]) ** 2
            e1 = (w1[c, 0] - cache_w1[c, 0]) ** 2 + (w1[c, 1] - cache_w1[c, 1]) ** 2 + (w1[c, 2] - cache_w1[c, 2]) ** 2
            if e0 > slack2 or e1 > slack2:
                valid = False
                break
            displacement[c] = np.sqrt(max(e0, e1))
    if valid and state[FEED_VERSION] != map_version:
        version = state[FEED_VERSION]
        for j in range(state[FEED_N_BLOCKS]):
            if block_stamp[rel_blocks[j]] > version:
                valid = False
                break
        if valid:
            state[FEED_VERSION] = map_version
    m_max = scratch_index.shape[0]
    if not valid:
        state[FEED_VALID] = 0
        # A hair more than slack, so that rounding never drops a cell the query would admit.
        n_rel = _feed_candidates(
            w0, w1, radii, max_distance, cell_radius, slack * (1.0 + 1e-9) + 1e-12, res, lo_key, dims,
            nby, nbz, block_cells, block_count, cand_start, cand_index, cand_xyz, rel_blocks,
        )  # fmt: skip
        if n_rel < 0:
            return -2
        _candidate_bounds(w0, w1, n, m_max, cand_start, cand_xyz, cand_bound, scratch_distance)
        displacement[:] = 0.0
        state[FEED_VALID] = 1
        state[FEED_VERSION] = map_version
        state[FEED_N_BLOCKS] = n_rel
        state[FEED_REBUILDS] += 1
        cache_distance[0] = max_distance
        cache_w0[:, :] = w0
        cache_w1[:, :] = w1
    k_max = out_index.shape[1]
    sep2 = min_separation * min_separation
    for c in range(n):
        ax, ay, az, dx, dy, dz, dd = capsule_segment(w0, w1, c)
        worst = radii[c] + max_distance + cell_radius
        far = cand_bound[c] + 2.0 * displacement[c] + 3.0 * _BOUND_MARGIN  # see above
        count = 0
        for i in range(cand_start[c], cand_start[c + 1]):
            if cand_xyz[i, 3] > far:
                continue
            d = _point_segment_distance(cand_xyz[i, 0], cand_xyz[i, 1], cand_xyz[i, 2], ax, ay, az, dx, dy, dz, dd)
            if d > worst:
                continue
            count = _insert_sorted(scratch_distance, scratch_index, count, m_max, d, cand_index[i])
            if count == m_max:
                worst = scratch_distance[m_max - 1]
        kept = keep_separated(c, count, k_max, sep2, res, nby, nbz, radii[c], cell_radius, scratch_index,
                              scratch_distance, out_index, out_distance, kept_cells)
        for j in range(kept, k_max):
            out_index[c, j] = -1
        out_count[c] = kept
    n_last = state[FEED_N_LAST]
    previous = out_cells[:n_last].copy()
    for i in range(out_centres.shape[0]):
        for a in range(3):
            out_centres[i, a] = park[a]
    m = gather_cells(out_index, out_distance, out_cells.shape[0], res, lo_key, nby, nbz, out_cells, out_centres)
    changed = m != n_last
    if not changed:
        for i in range(m):
            if out_cells[i] != previous[i]:
                changed = True
                break
    state[FEED_CHANGED] = 1 if changed else 0
    state[FEED_N_LAST] = m
    return m


@njit(cache=True)
def feed_tick(
    q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p, cap_joint, cap_a, cap_b,
    w0, w1, active, park, radii, max_distance, cell_radius, min_separation, slack, res, lo_key, dims, nby, nbz,
    block_cells, block_count, block_stamp, map_version, state, cache_w0, cache_w1, cache_distance,
    cand_start, cand_index, cand_xyz, rel_blocks, scratch_index, scratch_distance, out_index, out_distance,
    out_count, out_cells, out_centres, cand_bound, displacement, kept_cells,
):
    """:func:`feed_update` after the capsules' world end points at joint positions ``q``: the
    collision package's forward kinematics and capsule placement (the kernels
    ``MapCollisionFeed.capsule_world`` calls), in the same compiled call."""
    _collision.forward_kinematics(q, parent, idx_v, joint_type, axis, place_R, place_p, joint_R, joint_p)
    _collision.capsule_world(cap_joint, cap_a, cap_b, joint_R, joint_p, w0, w1)
    return feed_update(
        w0, w1, active, park, radii, max_distance, cell_radius, min_separation, slack, res, lo_key, dims, nby, nbz,
        block_cells, block_count, block_stamp, map_version, state, cache_w0, cache_w1, cache_distance,
        cand_start, cand_index, cand_xyz, rel_blocks, scratch_index, scratch_distance, out_index, out_distance,
        out_count, out_cells, out_centres, cand_bound, displacement, kept_cells,
    )
