"""Compiled (numba) arithmetic of the reference laws' control-loop paths.

numpy's ``a.dot(b)`` of two float64 3-vectors is OpenBLAS's ``ddot``, which on x86-64 with FMA
(every machine this project measured, contiguous and strided operands alike) computes the
fused chain ``fma(a2, b2, fma(a1, b1, fma(a0, b0, 0.0)))``: a Python sum of products differs
from it in the last bit on ~1/3 of vectors, which is why the laws' float paths still call
numpy for every dot product (~0.8 us each: an array built, then ``dot``). :func:`dot3` is that
chain with LLVM's correctly rounded ``fma``, callable from Python (~0.35 us) and from other
kernels; tests/references/test_kernels.py checks it against numpy's ``dot`` and against exact
rational arithmetic. On a machine whose BLAS sums without FMA numpy's dot products could differ
from these in the last bit; these are the same on every machine.

Element-wise steps are written as the numpy expressions they replace, in the same order (numba,
without ``fastmath``, neither reassociates nor contracts them into fused multiply-adds), and
``math.atan2`` / ``math.sqrt`` are libm's, as in Python.
"""

from __future__ import annotations

import math

from numba import njit

from harvest_qp._fma import fma as _fma

__all__: list[str] = []

# _NO_NRT: the per-tick kernels allocate nothing, so they are compiled without numba's reference-
# counted runtime (``_nrt=False``): an array argument is then unboxed without a MemInfo allocated
# and freed per call (measured: 8 array arguments 0.82 -> 0.55 us per call, hot).

# stretching_terms' out slots.
FORCE_ALONG, Q0, W0, POSITION_ERROR, ALIGNMENT, STRETCH_SIZE = 0, 1, 4, 7, 8, 9


@njit(cache=True)
def dot3(a0, a1, a2, b0, b1, b2):  # pragma: no cover (compiled)
    """numpy's ``np.array((a0, a1, a2)).dot(np.array((b0, b1, b2)))``, bit for bit (float64)."""
    return _fma(a2, b2, _fma(a1, b1, _fma(a0, b0, 0.0)))


@njit(cache=True, _nrt=False)  # see _NO_NRT
def stretching_terms(pose, n, target, f, k_og, out):  # pragma: no cover (compiled)
    """What :meth:`StemStretching.update` computes before its force command (which is stateful
    Python): into ``out`` n_c^T f [N], the projected position error (I - n n^T)(p_g - p_gd) [m],
    v_gw [rad/s], its norm and the alignment angle [rad] (slots named in this module); returns
    whether ``f`` is finite.

    ``pose``: the gripper pose, float64 ``(4, 4)``; ``n``, ``target``, ``f``: float64 ``(3,)``
    (n_c, p_gd [m], the wrist force [N]); ``k_og`` > 0.
    """
    n0, n1, n2 = n[0], n[1], n[2]
    y0, y1, y2 = pose[0, 1], pose[1, 1], pose[2, 1]
    e0, e1, e2 = pose[0, 3] - target[0], pose[1, 3] - target[1], pose[2, 3] - target[2]
    along = dot3(n0, n1, n2, e0, e1, e2)  # n @ e_pg
    q0, q1, q2 = e0 - along * n0, e1 - along * n1, e2 - along * n2
    out[FORCE_ALONG] = dot3(n0, n1, n2, f[0], f[1], f[2])  # n @ f
    k = -k_og
    w0, w1, w2 = k * (n1 * y2 - n2 * y1), k * (n2 * y0 - n0 * y2), k * (n0 * y1 - n1 * y0)  # -k_og n x y_g
    out[Q0], out[Q0 + 1], out[Q0 + 2] = q0, q1, q2
    out[W0], out[W0 + 1], out[W0 + 2] = w0, w1, w2
    out[POSITION_ERROR] = math.sqrt(dot3(q0, q1, q2, q0, q1, q2))  # np.linalg.norm(projected)
    out[ALIGNMENT] = math.atan2(math.sqrt(dot3(w0, w1, w2, w0, w1, w2)) / k_og, dot3(y0, y1, y2, n0, n1, n2))
    return math.isfinite(f[0]) and math.isfinite(f[1]) and math.isfinite(f[2])
