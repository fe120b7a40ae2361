"""Small helpers shared by test modules of different packages."""

from __future__ import annotations

import functools
from fractions import Fraction

import numpy as np


def random_pose(rng: np.random.Generator, scale: float = 0.5) -> np.ndarray:
    """A C-ordered homogeneous pose with a uniformly random rotation (QR of a Gaussian matrix)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    pose = np.eye(4)
    pose[:3, :3] = q
    pose[:3, 3] = scale * rng.normal(size=3)
    return pose


@functools.cache
def numpy_dot_is_fused() -> bool:
    """Whether numpy's dot of two float64 3-vectors is, on this machine, the fused chain
    ``fma(a2, b2, fma(a1, b1, fma(a0, b0, 0.0)))`` that the compiled per-tick kernels compute
    (``harvest_qp.references._kernels.dot3``). True with OpenBLAS's Haswell-and-later ddot
    kernels (this project's machines); False with its older ones, e.g. under
    ``OPENBLAS_CORETYPE=Sandybridge`` (measured: a third of the dot products then differ in
    the last bit). Oracle: exact rational arithmetic on 64 random pairs."""

    def fused(x: float, y: float, c: float) -> float:
        return float(Fraction(x) * Fraction(y) + Fraction(c))

    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(64, 3)), rng.normal(size=(64, 3))
    return all(
        float(a[i].dot(b[i])) == fused(a[i, 2], b[i, 2], fused(a[i, 1], b[i, 1], fused(a[i, 0], b[i, 0], 0.0)))
        for i in range(64)
    )


def assert_as_numpy(got, expected, *, exact_zeros: bool = False, rtol: float = 1e-9, atol: float = 1e-12) -> None:
    """A compiled kernel's floats against the numpy path it replaces.

    Where numpy's dot is the kernels' fused chain (:func:`numpy_dot_is_fused`), the same bits
    (-0.0 and NaN included): the closed loop's results must not move. Elsewhere the kernels (the
    same arithmetic on every machine) and numpy differ in the last bits by design, so the values
    must agree to round-off (NaN where NaN), and with ``exact_zeros`` the zeros keep their sign.
    """
    g = np.asarray(got, dtype=np.float64).reshape(-1)
    e = np.asarray(expected, dtype=np.float64).reshape(-1)
    assert g.shape == e.shape, (g.shape, e.shape)
    if numpy_dot_is_fused():
        assert g.view(np.int64).tolist() == e.view(np.int64).tolist(), (g.tolist(), e.tolist())
        return
    np.testing.assert_allclose(g, e, rtol=rtol, atol=atol)
    if exact_zeros:
        zero = e == 0.0
        assert g[zero].view(np.int64).tolist() == e[zero].view(np.int64).tolist(), (g.tolist(), e.tolist())


class ResetRobot:
    """Just what ``HarvestController.reset`` reads of a robot: the joints [rad] and the control period [s]."""

    control_period = 0.002

    def __init__(self, q: np.ndarray) -> None:
        self.q = np.asarray(q, float)

    def joint_positions(self) -> np.ndarray:
        return self.q.copy()
