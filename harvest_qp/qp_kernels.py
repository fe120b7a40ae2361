"""Compiled helpers for assembling the task QP (small dense loops beat numpy's per-call overhead)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def accumulate_task(H, f, J, w, v):
    """``H += J^T diag(w) J`` and ``f -= J^T diag(w) v`` for one task.

    Returns False, writing nothing, when the sizes do not fit (``J`` m x n with ``H`` n x n,
    ``f``, ``w`` and ``v`` of m): the loops below index without bounds checks.
    """
    m, n = J.shape
    if H.shape[0] != n or H.shape[1] != n or f.shape[0] != n or w.shape[0] != m or v.shape[0] != m:
        return False
    for r in range(m):
        wr = w[r]
        if wr == 0.0:
            continue
        wv = wr * v[r]
        for i in range(n):
            wji = wr * J[r, i]
            if wji == 0.0:
                continue
            f[i] -= J[r, i] * wv
            for k in range(n):
                H[i, k] += wji * J[r, k]
    return True


@njit(cache=True)
def accumulate_diagonal(H, f, w, v, floor):
    """``H += diag(w)``, ``f -= w * v`` and ``floor += w`` for a joint-space task (``J = I``);
    ``floor`` sums the diagonal weight joint-space tasks put on each joint.

    Returns False, writing nothing, unless ``w`` and ``v`` have one entry per row of ``H`` (n x n).
    """
    n = H.shape[0]
    if H.shape[1] != n or f.shape[0] != n or floor.shape[0] != n or w.shape[0] != n or v.shape[0] != n:
        return False
    for i in range(n):
        H[i, i] += w[i]
        f[i] -= w[i] * v[i]
        floor[i] += w[i]
    return True


@njit(cache=True)
def rotate_twist_rows(R, J, v, J_out, v_out):
    """Rows of a world-aligned twist task expressed in the frame's axes: ``blkdiag(R^T, R^T)``."""
    rotate_twist(R, v, v_out)
    n = J.shape[1]
    for b in range(2):
        o = 3 * b
        for i in range(3):
            for c in range(n):
                acc = 0.0
                for k in range(3):
                    acc += R[k, i] * J[o + k, c]
                J_out[o + i, c] = acc


@njit(cache=True)
def rotate_twist(R, v, v_out):
    """The ``v`` part of :func:`rotate_twist_rows` alone: ``blkdiag(R^T, R^T) v``."""
    for b in range(2):
        o = 3 * b
        for i in range(3):
            acc = 0.0
            for k in range(3):
                acc += R[k, i] * v[o + k]
            v_out[o + i] = acc


@njit(cache=True)
def clip_inplace(x, lower, upper):
    """Clip ``x`` to ``[lower, upper]`` in place; returns ``x``."""
    for i in range(x.shape[0]):
        if x[i] < lower[i]:
            x[i] = lower[i]
        elif x[i] > upper[i]:
            x[i] = upper[i]
    return x


@njit(cache=True)
def intersect_boxes(lowers, uppers, lower, upper, conflict):
    """Intersect boxes row by row (rows in priority order); a later row that does not
    overlap the running box is moved onto the running box's nearest point.

    ``conflict[j]`` is set to the index of the first yielding row for joint ``j`` (-1: none);
    returns the number of joints with a conflict.
    """
    k, n = lowers.shape
    n_conflicts = 0
    for j in range(n):
        lo = -1e30
        hi = 1e30
        conflict[j] = -1
        for r in range(k):
            new_lo = max(lo, lowers[r, j])
            new_hi = min(hi, uppers[r, j])
            if new_lo > new_hi:
                if conflict[j] < 0:
                    conflict[j] = r
                    n_conflicts += 1
                # The yielding box lies entirely above or below: keep the nearest point.
                target = hi if lowers[r, j] > hi else lo
                new_lo = target
                new_hi = target
            lo = new_lo
            hi = new_hi
        lower[j] = lo
        upper[j] = hi
    return n_conflicts


@njit(cache=True)
def acceleration_bounds(previous, max_acceleration, dt, lower, upper):
    """``previous -+ max_acceleration * dt``: the velocities reachable in one step [rad/s]."""
    for i in range(previous.shape[0]):
        step = max_acceleration[i] * dt
        lower[i] = previous[i] - step
        upper[i] = previous[i] + step


@njit(cache=True)
def all_finite(x):
    """True when no entry of the 1-D array ``x`` is NaN or infinite."""
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return False
    return True


@njit(cache=True)
def position_limit_bounds(q, q_min, q_max, gain, dt, max_acceleration, lower, upper):
    """Velocity bounds [rad/s] keeping ``q + qdot dt`` in ``[q_min, q_max]``.

    ``gain * (q_min - q) / dt <= qdot <= gain * (q_max - q) / dt``; with a non-empty
    ``max_acceleration`` the bounds are also capped at the braking speed
    ``sqrt(2 a margin)`` (only inside the range: outside, the plain bound returns the joint).
    """
    braking = max_acceleration.shape[0] > 0
    for i in range(q.shape[0]):
        below = q_min[i] - q[i]
        above = q_max[i] - q[i]
        lo = gain * below / dt
        hi = gain * above / dt
        if braking:
            hi = min(hi, np.sqrt(2.0 * max_acceleration[i] * max(above, 0.0)))
            lo = max(lo, -np.sqrt(2.0 * max_acceleration[i] * max(-below, 0.0)))
        lower[i] = lo
        upper[i] = hi


@njit(cache=True)
def max_violation(x, lower, upper, A, b, G, h):
    """Largest violation of ``lower <= x <= upper``, ``A x = b`` and ``G x <= h`` (0 if feasible).

    A non-finite ``x`` counts as an infinite violation.
    """
    worst = 0.0
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return np.inf
        worst = max(worst, lower[i] - x[i], x[i] - upper[i])
    for r in range(A.shape[0]):
        acc = -b[r]
        for i in range(x.shape[0]):
            acc += A[r, i] * x[i]
        worst = max(worst, abs(acc))
    for r in range(G.shape[0]):
        if h[r] >= 1e29:
            continue
        acc = -h[r]
        for i in range(x.shape[0]):
            acc += G[r, i] * x[i]
        worst = max(worst, acc)
    return worst


@njit(cache=True)
def max_scaled_violation(x, lower, upper, A, b, G, h):
    """Largest violation of the constraints, each row relative to its own scale.

    A row ``g x <= h`` counts ``(g x - h) / (1 + |h| + sum_i |g_i x_i|)``, a bound
    ``x_i <= u_i`` counts ``(x_i - u_i) / (1 + |u_i|)``: a rounding error on terms of
    size ~1 is ~1e-16 whatever the row's units. A non-finite ``x`` is infinite.
    """
    worst = 0.0
    for i in range(x.shape[0]):
        if not np.isfinite(x[i]):
            return np.inf
        if lower[i] > -1e29:
            worst = max(worst, (lower[i] - x[i]) / (1.0 + abs(lower[i])))
        if upper[i] < 1e29:
            worst = max(worst, (x[i] - upper[i]) / (1.0 + abs(upper[i])))
    for r in range(A.shape[0]):
        acc = -b[r]
        size = 1.0 + abs(b[r])
        for i in range(x.shape[0]):
            term = A[r, i] * x[i]
            acc += term
            size += abs(term)
        worst = max(worst, abs(acc) / size)
    for r in range(G.shape[0]):
        if h[r] >= 1e29:
            continue
        acc = -h[r]
        size = 1.0 + abs(h[r])
        for i in range(x.shape[0]):
            term = G[r, i] * x[i]
            acc += term
            size += abs(term)
        worst = max(worst, acc / size)
    return worst


@njit(cache=True)
def top_up_diagonal(H, floor, value):
    """``H[i, i] += max(value - floor[i], 0)``: a diagonal of at least ``value`` where tasks left less."""
    for i in range(H.shape[0]):
        if floor[i] < value:
            H[i, i] += value - floor[i]


@njit(cache=True)
def weighted_rows(J, w, out, start):
    """Rows ``sqrt(w_r) J_r`` of the rows with ``w_r > 0`` (``(np.sqrt(w)[:, None] * J)[w > 0]``),
    written from row ``start`` of ``out``; returns the row after the last one written."""
    r_out = start
    for r in range(J.shape[0]):
        if w[r] > 0.0:
            scale = np.sqrt(w[r])
            for c in range(J.shape[1]):
                out[r_out, c] = scale * J[r, c]
            r_out += 1
    return r_out


@njit(cache=True)
def load_daqp_rows(A_buf, upper, lower, sense, A, b, G, h, box_lower, box_upper, n_eq_before, inf):
    """Write one QP into DAQP's fixed layout: ``n`` bounds, ``n`` equality slots, the inequality rows.

    Equality slots past ``A``'s rows are cleared (free rows) when this QP or the one before
    had equalities; returns the number of equality rows now loaded.
    """
    n = A_buf.shape[1]
    n_eq = A.shape[0]
    if n_eq > 0 or n_eq_before > 0:
        for r in range(n):
            if r < n_eq:
                for c in range(n):
                    A_buf[r, c] = A[r, c]
                upper[n + r] = b[r]
                lower[n + r] = b[r]
                sense[n + r] = 5
            else:
                for c in range(n):
                    A_buf[r, c] = 0.0
                upper[n + r] = inf
                lower[n + r] = -inf
                sense[n + r] = 0
    for r in range(G.shape[0]):
        for c in range(n):
            A_buf[n + r, c] = G[r, c]
        upper[2 * n + r] = h[r]
    for i in range(n):
        upper[i] = box_upper[i]
        lower[i] = box_lower[i]
    return n_eq


@njit(cache=True)
def orthonormal_rows_qr(A, x, tol, rows_out, rhs_out):
    """Orthonormal rows spanning the rows of ``A`` (m x n) and the right-hand side that holds
    ``A x`` fixed: Householder QR of ``A^T`` with column pivoting (``A^T P = Q R``).

    Writes the ``rank`` rows of ``Q^T`` into ``rows_out[:rank]`` and ``rows_out[:rank] @ x`` into
    ``rhs_out[:rank]``; returns ``rank``, the number of pivots with ``|R_kk| > tol * max(1, |R_00|)``
    (``|R_00|``: the largest row norm of ``A``). The rows span ``A``'s rows (up to the rank
    tolerance), so ``{y : rows y = rows x}`` is ``{y : A y = A x}``.
    """
    m, n = A.shape
    M = np.empty((n, m))  # A^T, overwritten by R above the diagonal and the reflectors below
    for i in range(m):
        for j in range(n):
            M[j, i] = A[i, j]
    beta = np.zeros(n)
    diag = np.zeros(min(m, n))
    steps = min(m, n)
    rank = 0
    threshold = 0.0
    for k in range(steps):
        # Pivot: the remaining column (row of A) with the largest norm below row k (recomputed,
        # not downdated: exact on these small sizes).
        best = -1.0
        p = k
        for col in range(k, m):
            acc = 0.0
            for r in range(k, n):
                acc += M[r, col] * M[r, col]
            if acc > best:
                best = acc
                p = col
        if p != k:
            for r in range(n):
                tmp = M[r, k]
                M[r, k] = M[r, p]
                M[r, p] = tmp
        norm = np.sqrt(best)
        if k == 0:
            threshold = tol * max(1.0, norm)
        if not norm > threshold:
            break
        # Householder reflector H = I - beta v v^T with v[k] = 1 mapping M[k:, k] to alpha e_k.
        x0 = M[k, k]
        alpha = -norm if x0 >= 0.0 else norm
        v0 = x0 - alpha
        for r in range(k + 1, n):
            M[r, k] /= v0
        beta[k] = -v0 / alpha
        M[k, k] = alpha
        diag[k] = alpha
        for col in range(k + 1, m):
            acc = M[k, col]
            for r in range(k + 1, n):
                acc += M[r, k] * M[r, col]
            acc *= beta[k]
            M[k, col] -= acc
            for r in range(k + 1, n):
                M[r, col] -= acc * M[r, k]
        rank += 1
    # Q[:, :rank] = H_0 H_1 ... H_{rank-1} [e_0 .. e_{rank-1}], built backwards; rows_out = Q^T.
    Q = np.zeros((n, rank))
    for j in range(rank):
        Q[j, j] = 1.0
    for k in range(rank - 1, -1, -1):
        for j in range(rank):
            acc = Q[k, j]
            for r in range(k + 1, n):
                acc += M[r, k] * Q[r, j]
            acc *= beta[k]
            Q[k, j] -= acc
            for r in range(k + 1, n):
                Q[r, j] -= acc * M[r, k]
    for j in range(rank):
        acc = 0.0
        for r in range(n):
            rows_out[j, r] = Q[r, j]
            acc += Q[r, j] * x[r]
        rhs_out[j] = acc
    return rank


@njit(cache=True)
def scaled_difference(gain, target, q):
    """A new array ``gain * (target - q)`` (the posture task's velocity), the same products as numpy's."""
    out = np.empty(target.shape[0])
    for i in range(target.shape[0]):
        out[i] = gain * (target[i] - q[i])
    return out
