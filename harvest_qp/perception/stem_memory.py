"""The stem's top as seen over the approach: p_sb from every close frame, not the last one alone.

Beyond the paper. ``stem_basend`` places p_sb at the branch end of the top cluster of one
frame, and the controller refits it on every frame of the approach, then freezes it at the
switch (:mod:`harvest_qp.harvest.harvest_controller`). The unveiling law (``eq:v_c2``)
maximises the *number* of stem points seen, not the top end: on never-run scenes it lifted the
camera from 6 to 17 deg above the stem base while the stem's lower part came into view, and the
branch (with a petiole) came to hide the stem's top 12 mm (dev 16291: 11 -> 140 stem points, the
frame's p_sb 4.4 -> 12.5 mm down the stem). The p_sb frozen at the switch was then 13 mm off and
the camera ended 2.2 deg off the true base. Across 613 sweep episodes, the six whose p_sb was more
than 8 mm off at the switch (12-51 mm, along the stem) held five failures.

The stem hangs still during the approach (the grasping arm holds the crop, ``eq:hold``; the
paper's p_sb is static too), so a stem point seen from close range in one frame is still there
in the next. :class:`StemTopMemory` keeps those points (in ``voxel`` cells) and
:meth:`~StemTopMemory.extension` says how far up the frame's top axis they reach past its p_sb:
the controller moves p_sb up by that much (at most ``max_extension``). Points off the axis by
more than ``axis_radius`` (another stem, a far noisy view) do not count, nor do points past a gap
of more than ``max_gap`` along the axis (a stem is one piece; a patch of stem labels on the branch,
a segmenter's mistake kept from one frame, must not lift p_sb for the rest of the approach), and
the ``rank``-th highest point is used, not the highest, so that one or two stray points move nothing. Measured on the
approach frames of fourteen sweep scenes (``docs/perception.md``): p_sb's error along the stem
12.3 -> 4.4 mm and 12.2 -> 2.7 mm (16291, 17287), 27.6 -> 1.3 mm (16102), 23.8 -> 1.1 mm
(15467); on eight scenes whose base was seen the points reached 0.0-0.6 mm past it (no change).

The memory assumes what the paper assumes, a static stem. On a real cell the frames' poses
come from the arm's kinematics and the hand-eye calibration, and their error between views
biases the extension *upwards* (it keeps the highest points of all frames), more with more
frames: an independent review measured p_sb 3-5 mm above the true base after 40 views with 2 mm
of random pose error per view, 6-12 mm with 3 mm (against -1 to +6 mm from the last frame
alone). Turn it off (``perception.stem_memory: false``) where the views' pose error is that large.

Typical use, on each frame of the approach::

    memory = StemTopMemory()
    fit = fit_stem(stem_points, gripper_position)
    memory.add(stem_points, camera_position=p_c, stem_base=fit.base)
    p_sb = fit.base - memory.extension(fit.base, fit.top.direction) * fit.top.direction
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_grid_points, as_point, as_unit_vector, positive_int
from harvest_qp.validation import as_positive_scalar

__all__ = ["StemTopMemory"]


class StemTopMemory:
    """Stem points seen from close range during the approach (module docstring).

    Args:
        voxel: edge of the cells the points are kept in [m] (one point per cell, its centre).
        max_range: a frame's points are kept only when its camera is within this distance [m]
            of the frame's stem base (far views are coarse: the first fits at 0.57 m were
            22-41 mm off).
        axis_radius: points farther than this from the top axis [m] do not count.
        max_extension: the extension never exceeds this [m].
        min_extension: a smaller reach counts as 0 [m]: it is the fit's own scatter (the extent
            of the top cluster moves by 0-0.6 mm between frames of a base in view), and p_sb then
            stays the frame's.
        rank: the extension reaches the ``rank``-th highest point (0: the highest).
        max_gap: only the points that run on from p_sb up the axis with no gap longer than this
            [m] count: a stem is one piece, and a patch of stem labels past a gap (a segmenter's
            mistake on the branch or a leaf, kept from one frame) must not lift p_sb for the rest
            of the approach.
    """

    def __init__(
        self,
        *,
        voxel: float = 0.001,
        max_range: float = 0.45,
        axis_radius: float = 0.008,
        max_extension: float = 0.03,
        min_extension: float = 0.003,
        rank: int = 2,
        max_gap: float = 0.003,
    ) -> None:
        self.voxel = as_positive_scalar(voxel, "voxel")
        if self.voxel < 1e-6:
            raise InvalidInputError(f"voxel must be at least 1e-6 m (cell keys are int64), got {voxel!r}")
        self.max_range = as_positive_scalar(max_range, "max_range")
        self.axis_radius = as_positive_scalar(axis_radius, "axis_radius")
        self.max_extension = as_positive_scalar(max_extension, "max_extension", allow_zero=True)
        self.min_extension = as_positive_scalar(min_extension, "min_extension", allow_zero=True)
        if self.min_extension > self.max_extension:
            raise InvalidInputError(f"min_extension must not exceed max_extension, got {min_extension!r} > "
                                    f"{max_extension!r}")
        self.rank = positive_int("rank", rank, minimum=0)
        self.max_gap = as_positive_scalar(max_gap, "max_gap")
        self.reset()

    def reset(self) -> None:
        """Forget every point (a new episode, a new stem)."""
        self._cells: set[tuple[int, int, int]] = set()
        self._points = np.empty((0, 3))

    @property
    def points(self) -> NDArray[np.float64]:
        """``(n, 3)`` the kept points [m] (cell centres)."""
        if self._points.shape[0] != len(self._cells):
            self._points = (np.array(sorted(self._cells), dtype=np.float64).reshape(-1, 3) + 0.5) * self.voxel
        return self._points

    def add(self, stem_points: ArrayLike, *, camera_position: ArrayLike, stem_base: ArrayLike) -> bool:
        """Keep a frame's stem points ``(n, 3)`` [m] if its camera p_c [m] lies within ``max_range`` of
        its stem base p_sb [m]; returns whether they were kept."""
        points = as_grid_points("stem_points", stem_points)
        camera = as_point("camera_position", camera_position)
        base = as_point("stem_base", stem_base)
        if float(np.linalg.norm(camera - base)) > self.max_range:
            return False
        keys = np.unique(np.floor(points / self.voxel).astype(np.int64), axis=0)
        self._cells.update(map(tuple, keys.tolist()))
        return True

    def extension(self, stem_base: ArrayLike, direction: ArrayLike) -> float:
        """How far [m] the kept points reach up the top axis past ``stem_base``.

        Args:
            stem_base: a frame's p_sb [m].
            direction: n_st, the top segment's axis from the branch towards the crop (any length).

        Returns:
            e in [0, ``max_extension``]: p_sb - e n_st is the ``rank``-th highest of the points within
            ``axis_radius`` of the axis that run on from p_sb with no gap over ``max_gap``; 0 when there
            are no more than ``rank`` of them or that point lies less than ``min_extension`` above p_sb.
        """
        base = as_point("stem_base", stem_base)
        axis = as_unit_vector("direction", direction, min_norm=1e-12)
        offsets = self.points - base
        along = offsets @ axis
        across = offsets - np.outer(along, axis)
        heights = np.sort(-along[np.einsum("ij,ij->i", across, across) <= self.axis_radius**2])
        # The run up from p_sb: the first gap over max_gap (p_sb itself at height 0) ends it.
        heights = heights[heights > -self.max_gap]
        gaps = np.diff(heights, prepend=min(0.0, heights[0]) if heights.shape[0] else 0.0)
        ends = np.flatnonzero(gaps > self.max_gap)
        run = heights[: ends[0]] if ends.shape[0] else heights
        if run.shape[0] <= self.rank:
            return 0.0
        reach = float(run[run.shape[0] - 1 - self.rank])
        return min(reach, self.max_extension) if reach > self.min_extension else 0.0
