"""A look around at the start of the approach: the optical axis sweeps a cone (beyond the paper).

The paper's camera only looks at the ROI, so space beside it is never seen, and "unknown" counts
as free (``docs/limitations.md``): on sweep scenes the camera arm's wrist and cutter met leaves
that had never been inside the field of view (one lay 29-31 deg off the optical axis at the start,
9-11 deg outside the D415's 20 deg vertical half field of view, then beside the camera as it moved
sideways to unveil the stem). During the first ``period`` of the approach the camera's optical
axis z_c turns once around a cone of half-angle ``alpha`` about the direction a from the camera's
start to the ROI centre; the composition keeps the translation of V_cr + V_cu meanwhile::

    d(phi)  = cos(alpha) a + sin(alpha) (cos(phi) e_1 + sin(phi) e_2),   phi = phi_0 + 2 pi s / T
    w_look  = (2 pi / T) (a - (a^T z_c) z_c) + k theta k_d

with (e_1, e_2) an orthonormal pair normal to a, phi_0 the cone direction nearest to z_c at the
start, s the time since the start, T the ``period``, and theta, k_d the angle and axis of the
minimum rotation taking z_c onto d (:func:`~harvest_qp.references.minimum_rotation`). The first
term turns z_c with the cone (the feed-forward (2 pi / T) a without its roll about z_c, which does
not move z_c: the QP's camera task leaves that roll free, but the pseudo-inverse mapper follows
all six components and rolled the camera by 293 deg over the sweep with it), the second pulls z_c
onto the cone. With the D415's 40 x 65 deg field of view a 25 deg cone sees
up to ~45 deg off a. The obstacle map keeps what the sweep saw, so the collision rows know those
leaves later in the approach (on the scene above: 35 cells within 5 cm of the leaf after 6 s,
none without the sweep; the map held 4,065 cells against 2,919).

Opt-in (``look_around.enabled``): on 200 never-run sweep scenes it lost 4 to the camera arm's wrist
singularity (the sweep takes wrist 2 to -2.84 rad) and gave one new contact elsewhere
(``docs/references.md`` deviation 9). Measured on 20 development scenes (median time to pre-cut
13.77 s without a sweep): this one +0.6 s; the same cone with the camera held in place +2.2 s (the
arm cannot turn the camera about its own centre at the start pose; it lost its place by 27-32 cm
anyway); a circle of the two wrist joints added to V_c +2.2 s, and the leaf above still touched.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.references._checks import as_pose, as_position, as_positive_scalar
from harvest_qp.references._vec3 import Vec3, add, cross, dot, norm, rotation_between, scale, sub

__all__ = ["LookAround"]


class LookAround:
    """The optical axis' sweep of a cone about the ROI direction (an angular velocity [rad/s]).

    Args:
        cone: the cone's half-angle alpha [rad], in (0, pi/2).
        period: T, the time of one turn around the cone [s].
        gain: k, the gain that pulls z_c onto the cone [1/s].

    Call :meth:`start` once (the time, the camera pose and the ROI centre at the start), then
    :meth:`angular_velocity` every tick until :meth:`done`.
    """

    def __init__(self, *, cone: float = math.radians(25.0), period: float = 2.5, gain: float = 3.0) -> None:
        cone = as_positive_scalar(cone, "cone")
        if not cone < math.pi / 2:
            raise InvalidInputError(f"LookAround cone must be below pi/2 rad (a half-angle), got {cone!r}")
        self.cone = cone
        self.period = as_positive_scalar(period, "period")
        self.gain = as_positive_scalar(gain, "gain")
        self._start: tuple[float, Vec3, Vec3, Vec3, float] | None = None

    def reset(self) -> None:
        """Forget the sweep (a new episode sweeps again after :meth:`start`)."""
        self._start = None

    def start(self, time: float, camera_pose: ArrayLike, roi_centre: ArrayLike) -> None:
        """Begin the sweep at ``time`` [s] from ``camera_pose`` (4, 4) about the direction to ``roi_centre`` [m]."""
        if not math.isfinite(time):
            raise InvalidInputError(f"LookAround.start: time must be finite [s], got {time!r}")
        pose = as_pose(camera_pose, "camera_pose")
        a = sub(as_position(roi_centre, "roi_centre").tolist(), pose[:3, 3].tolist())
        if norm(a) < 1e-9:
            raise InvalidInputError("LookAround.start: the ROI centre must not be at the camera")
        a = scale(1.0 / norm(a), a)
        # e_1 horizontal where a is not vertical, so phi = 0 looks sideways at the ROI's height
        e1 = cross(a, (0.0, 0.0, 1.0) if abs(a[2]) < 0.9 else (1.0, 0.0, 0.0))
        e1 = scale(1.0 / norm(e1), e1)
        e2 = cross(a, e1)
        z = tuple(pose[:3, 2].tolist())
        phi0 = math.atan2(dot(z, e2), dot(z, e1))  # the cone direction nearest to z_c
        self._start = (float(time), a, e1, e2, phi0)

    @property
    def started(self) -> bool:
        """Whether :meth:`start` was called."""
        return self._start is not None

    def done(self, time: float) -> bool:
        """Whether the sweep is over at ``time`` [s] (one period after the start)."""
        if not math.isfinite(time):
            raise InvalidInputError(f"LookAround.done: time must be finite [s], got {time!r}")
        return self._start is not None and time - self._start[0] >= self.period

    def direction(self, time: float) -> NDArray[np.float64]:
        """d(phi), the cone direction z_c is driven to at ``time`` [s] (unit, world)."""
        t0, a, e1, e2, phi0 = self._started()
        return np.array(self._direction(time - t0, a, e1, e2, phi0))

    def angular_velocity(self, time: float, camera_pose: ArrayLike) -> NDArray[np.float64]:
        """w_look ``(3,)`` [rad/s], world frame, at ``time`` [s]; zero after the period (before the
        start: the pull onto the first cone direction alone)."""
        t0, a, e1, e2, phi0 = self._started()
        if not math.isfinite(time):
            raise InvalidInputError(f"LookAround.angular_velocity: time must be finite [s], got {time!r}")
        if time - t0 >= self.period:
            return np.zeros(3)
        pose = as_pose(camera_pose, "camera_pose")
        z = tuple(pose[:3, 2].tolist())
        d = self._direction(time - t0, a, e1, e2, phi0)
        theta, axis = rotation_between(z, d)
        rate = 2.0 * math.pi / self.period if time >= t0 else 0.0
        feed_forward = scale(rate, sub(a, scale(dot(a, z), z)))  # no roll about z_c
        return np.array(add(feed_forward, scale(self.gain * theta, axis)))

    def _direction(self, elapsed: float, a: Vec3, e1: Vec3, e2: Vec3, phi0: float) -> Vec3:
        phi = phi0 + 2.0 * math.pi * min(max(elapsed, 0.0), self.period) / self.period
        ring = add(scale(math.cos(phi), e1), scale(math.sin(phi), e2))
        return add(scale(math.cos(self.cone), a), scale(math.sin(self.cone), ring))

    def _started(self) -> tuple[float, Vec3, Vec3, Vec3, float]:
        if self._start is None:
            raise InvalidInputError("LookAround: call start(time, camera_pose, roi_centre) first")
        return self._start
