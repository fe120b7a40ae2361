"""3-vectors as tuples of Python floats, for the reference laws that run every 2 ms tick.

numpy spends ~1 us per call on a 3-vector (dispatch and a new array), most of a law's cost at
one call per tick; an operation on Python floats costs ~0.1 us. The per-tick laws read their
arrays once (``tolist()``), compute on these tuples and return a numpy array.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]

__all__ = ["Vec3", "add", "cross", "dot", "norm", "rotation_between", "scale", "sub"]

# Below this |z x e| / |e| (sin theta ~ 1e-12) the axis k of eq:ktheta_world is undefined;
# theta is then 0 (V_cr's angular part is 0) or pi (any axis normal to z works).
_PARALLEL_SINE = 1e-12


def add(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def sub(a: Vec3, b: Vec3) -> Vec3:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def scale(k: float, a: Vec3) -> Vec3:
    return (k * a[0], k * a[1], k * a[2])


def dot(a: Vec3, b: Vec3) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a: Vec3, b: Vec3) -> Vec3:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def norm(a: Vec3) -> float:
    return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])


def rotation_between(z: Vec3, e: Vec3) -> tuple[float, Vec3]:
    """The least rotation (angle [rad], unit axis) taking direction ``z`` onto ``e``
    (:func:`harvest_qp.references.reaching.minimum_rotation` on Python floats)."""
    normal = cross(z, e)
    sine = norm(normal)
    norm_e = norm(e)
    if norm_e == 0.0:
        return 0.0, (0.0, 0.0, 0.0)
    cosine = dot(z, e)
    if sine > _PARALLEL_SINE * norm_e:
        return math.atan2(sine, cosine), scale(1.0 / sine, normal)
    if cosine > 0.0:
        return 0.0, (0.0, 0.0, 0.0)
    axis = cross(z, (1.0, 0.0, 0.0) if abs(z[0]) < 0.9 else (0.0, 1.0, 0.0))
    return math.pi, scale(1.0 / norm(axis), axis)
