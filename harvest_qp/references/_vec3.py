"""3-vectors as tuples of Python floats, for the reference laws that run every 2 ms tick.

numpy spends ~1 us per call on a 3-vector (dispatch and a new array), most of a law's cost at
one call per tick; an operation on Python floats costs ~0.1 us. The per-tick laws read their
arrays once (``tolist()``), compute on these tuples and return a numpy array.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]

__all__ = ["Vec3", "add", "cross", "dot", "norm", "scale", "sub"]


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
