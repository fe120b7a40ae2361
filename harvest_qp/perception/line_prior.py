"""A long straight structure seen in part goes on beyond the view: the map's line prior.

Beyond the paper. The obstacle map knows only what the camera has seen, and unknown space is
free. A cane, a cordon or a trellis wire is seen in part (the camera looks at the crop below
it) while the camera arm's wrist, behind the camera, moves along it: on a never-run scene the
camera arm's wrist-2 link rested on the cane 5.5 cm past the last cell the camera had mapped
(dev seed 16148, 20 s of contact). :class:`LinePrior` finds such structures among the map's
seen cells (:func:`find_lines`: the longest tube of cells along the row) and marks the never-seen cells
along their continuation occupied with one hit's belief
(:meth:`~harvest_qp.perception.obstacle_map.ObstacleMap.set_prior`): the arms' collision rows
then keep clear of them, and the frames that see the space free clear them like any cell.

Typical use, after the map's update on a new frame::

    prior = LinePrior((0.0, 1.0, 0.0), extend=0.3)  # the row along y
    prior.update(obstacle_map, keep_clear=[p_sb])
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.perception._validation import as_finite_points, positive_int
from harvest_qp.validation import as_positive_scalar, as_vector

__all__ = ["LinePrior", "LineStructure", "find_lines"]


@dataclass(frozen=True)
class LineStructure:
    """A straight structure among the map's cells.

    Attributes:
        start, end: ``(3,)`` ends [m] of its seen part, on the fitted axis.
        radius: median distance [m] of its cells from the axis.
        support: number of cells on it.
    """

    start: NDArray[np.float64]
    end: NDArray[np.float64]
    radius: float
    support: int

    @property
    def length(self) -> float:
        """Length [m] of the seen part."""
        return float(np.linalg.norm(self.end - self.start))

    @property
    def direction(self) -> NDArray[np.float64]:
        """Unit vector from ``start`` to ``end``."""
        return (self.end - self.start) / max(self.length, 1e-12)


def _longest_run(t: NDArray[np.float64], max_gap: float) -> tuple[int, int]:
    """Indices ``[i, j)`` into sorted ``t`` of the longest run whose consecutive gaps are <= max_gap."""
    if t.shape[0] == 0:
        return 0, 0
    breaks = np.flatnonzero(np.diff(t) > max_gap) + 1
    starts = np.concatenate(([0], breaks))
    ends = np.concatenate((breaks, [t.shape[0]]))
    spans = t[ends - 1] - t[starts]
    k = int(np.argmax(spans))
    return int(starts[k]), int(ends[k])


def find_lines(
    cells: ArrayLike,
    direction: ArrayLike = (0.0, 1.0, 0.0),
    *,
    bin_size: float = 0.02,
    min_length: float = 0.25,
    max_gap: float = 0.08,
    max_tilt_deg: float = 20.0,
    max_lines: int = 1,
) -> list[LineStructure]:
    """Straight structures along ``direction`` (the row) among ``(n, 3)`` cell centres [m], longest first.

    The cells are binned across ``direction`` (square bins of ``bin_size`` [m]); each bin with
    its eight neighbours is a tube along the row, and its cells' longest run with no gap over
    ``max_gap`` [m] along the row is a candidate seen part. The longest one (the one with
    more cells among equally long ones), at least ``min_length`` [m], is refitted to its cells
    (their principal axis, then the cells near that axis, twice) and kept when that
    axis lies within ``max_tilt_deg`` [deg] of ``direction``; its cells are removed and the
    search repeats, up to ``max_lines`` lines. Deterministic. A leaf (10-15 cm across) is
    never a line at the default ``min_length``.
    """
    pts = as_finite_points("cells", cells)
    u = as_vector(direction, 3, "direction")
    norm = float(np.linalg.norm(u))
    if norm < 1e-9:
        raise InvalidInputError(f"direction must be a non-zero vector, got {direction!r}")
    u = u / norm
    bin_size = as_positive_scalar(bin_size, "bin_size")
    min_length = as_positive_scalar(min_length, "min_length")
    max_gap = as_positive_scalar(max_gap, "max_gap")
    max_tilt_deg = as_positive_scalar(max_tilt_deg, "max_tilt_deg")
    max_lines = positive_int("max_lines", max_lines, minimum=0)
    a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    lines: list[LineStructure] = []
    while len(lines) < max_lines and pts.shape[0] >= 3:
        along = pts @ u
        keys = np.floor(np.column_stack((pts @ a, pts @ b)) / bin_size).astype(np.int64)
        bins, inverse = np.unique(keys, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        # The cells of each bin, grouped: by_bin[bounds[i]:bounds[i + 1]] are bin i's.
        by_bin = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[by_bin], np.arange(bins.shape[0] + 1))
        index = {(int(k0), int(k1)): i for i, (k0, k1) in enumerate(bins)}
        first, last = np.minimum.reduceat(along[by_bin], bounds[:-1]), np.maximum.reduceat(along[by_bin], bounds[:-1])
        best, best_score = None, (0.0, 0)
        for k0, k1 in bins:
            near = [i for i in (index.get((int(k0) + d0, int(k1) + d1)) for d0 in (-1, 0, 1) for d1 in (-1, 0, 1))
                    if i is not None]  # fmt: skip
            if last[near].max() - first[near].min() < max(min_length, best_score[0]):
                continue  # no run in this tube can be long enough
            tube = np.concatenate([by_bin[bounds[i] : bounds[i + 1]] for i in near])
            order = np.argsort(along[tube])
            ts = along[tube][order]
            lo, hi = _longest_run(ts, max_gap)
            score = (round(float(ts[hi - 1] - ts[lo]), 6), hi - lo)  # span, then cells
            if score > best_score:
                best_score, best = score, tube[order[lo:hi]]
        if best is None or best_score[0] < min_length:
            break
        # Refit to the structure's own axis: the principal axis of the run's cells, then the
        # cells within 1.5 bins of that axis and a gap of the run's ends (a tube along the row
        # clips a structure a little off the row), twice.
        for _ in range(3):
            run = pts[best]
            centre = run.mean(axis=0)
            _, _, vt = np.linalg.svd(run - centre, full_matrices=False)
            axis = vt[0] if vt[0] @ u >= 0 else -vt[0]
            rel = pts - centre
            t = rel @ axis
            near = np.einsum("ij,ij->i", rel, rel) - t * t <= (1.5 * bin_size) ** 2
            near &= (t >= t[best].min() - max_gap) & (t <= t[best].max() + max_gap)
            candidates = np.flatnonzero(near)
            order = np.argsort(t[candidates])
            lo, hi = _longest_run(t[candidates][order], max_gap)
            if hi - lo < 3:
                break
            best = candidates[order[lo:hi]]
        run = pts[best]
        centre = run.mean(axis=0)
        if axis @ u < cos_tilt:
            break
        t = (run - centre) @ axis
        perp = run - centre - np.outer(t, axis)
        lines.append(LineStructure(
            start=centre + t.min() * axis, end=centre + t.max() * axis,
            radius=float(np.median(np.linalg.norm(perp, axis=1))), support=int(best.shape[0]),
        ))  # fmt: skip
        keep = np.ones(pts.shape[0], dtype=bool)
        keep[best] = False
        pts = pts[keep]
    return lines


class LinePrior:
    """Marks the never-seen continuation of long structures along the row occupied in an obstacle map.

    Args:
        direction: the row's direction in the world frame (the platform drives along it;
            canes, cordons and trellis wires run along it).
        extend: how far [m] past each end of a line's seen part the prior goes.
        min_length: shortest seen part [m] that counts as a line (:func:`find_lines`).
        bin_size: the tubes' cross bins [m] (:func:`find_lines`).
        max_tilt_deg: only lines within this angle [deg] of ``direction`` count (a shoot or a
            stem hangs or climbs).
        keep_clear: no prior cell within this distance [m] of the ``keep_clear`` points of
            :meth:`update` (the stem base, where the grasping arm must go).
        max_lines: lines extended at most (the longest first).
        voxel: the search runs on one cell per ``voxel`` [m] cube (the first), a quarter of
            the map's cells at most.
        period: shortest time [s] between two searches (:meth:`due`).
    """

    def __init__(
        self,
        direction: ArrayLike = (0.0, 1.0, 0.0),
        *,
        extend: float = 0.3,
        min_length: float = 0.25,
        bin_size: float = 0.02,
        max_tilt_deg: float = 20.0,
        keep_clear: float = 0.12,
        max_lines: int = 1,
        voxel: float = 0.02,
        period: float = 0.5,
    ) -> None:
        u = as_vector(direction, 3, "direction")
        if float(np.linalg.norm(u)) < 1e-9:
            raise InvalidInputError(f"direction must be a non-zero vector, got {direction!r}")
        self.direction = u / np.linalg.norm(u)
        self.extend = as_positive_scalar(extend, "extend")
        self.min_length = as_positive_scalar(min_length, "min_length")
        self.bin_size = as_positive_scalar(bin_size, "bin_size")
        self.max_tilt_deg = as_positive_scalar(max_tilt_deg, "max_tilt_deg")
        if self.max_tilt_deg > 90.0:
            raise InvalidInputError(f"max_tilt_deg must be in (0, 90] [deg], got {max_tilt_deg!r}")
        self.keep_clear = as_positive_scalar(keep_clear, "keep_clear", allow_zero=True)
        self.max_lines = positive_int("max_lines", max_lines, minimum=0)
        self.voxel = as_positive_scalar(voxel, "voxel")
        self.period = as_positive_scalar(period, "period", allow_zero=True)
        #: The lines extended by the last search.
        self.lines: list[LineStructure] = []
        self._last = -math.inf

    def reset(self) -> None:
        """Forget the lines and the time of the last search."""
        self.lines = []
        self._last = -math.inf

    def due(self, t: float) -> bool:
        """Whether ``period`` [s] has passed since the last search at time ``t`` [s]."""
        return t - self._last >= self.period

    def update(self, obstacle_map, *, keep_clear: Sequence[ArrayLike] = (), t: float | None = None) -> int:
        """Search the map's seen cells for lines and set the prior on their continuation.

        Args:
            obstacle_map: an :class:`~harvest_qp.perception.obstacle_map.ObstacleMap`.
            keep_clear: points [m] (e.g. p_sb) near which no prior cell is set.
            t: time [s] of this search, for :meth:`due`.

        Returns:
            the number of cells the prior marks.
        """
        if t is not None:
            self._last = float(t)
        cells = obstacle_map.occupied_centres(observed_only=True)
        _, first = np.unique(np.floor(cells / self.voxel).astype(np.int64), axis=0, return_index=True)
        self.lines = find_lines(
            cells[np.sort(first)],
            self.direction,
            bin_size=self.bin_size,
            min_length=self.min_length,
            max_tilt_deg=self.max_tilt_deg,
            max_lines=self.max_lines,
        )
        points = [self.continuation(line, obstacle_map.resolution) for line in self.lines]
        pts = np.concatenate(points) if points else np.zeros((0, 3))
        clear = as_finite_points("keep_clear", [np.asarray(p, float).reshape(3) for p in keep_clear])
        if pts.shape[0] and clear.shape[0] and self.keep_clear > 0.0:
            d2 = ((pts[:, None, :] - clear[None, :, :]) ** 2).sum(axis=2).min(axis=1)
            pts = pts[d2 > self.keep_clear**2]
        return obstacle_map.set_prior(pts)

    def continuation(self, line: LineStructure, resolution: float) -> NDArray[np.float64]:
        """Points [m] past both ends of ``line`` over ``extend``: on its axis and at its radius
        on four sides, every half cell along it."""
        u = line.direction
        a = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        r = line.radius
        offsets = np.array([[0.0, 0.0, 0.0], r * a, -r * a, r * b, -r * b])
        s = np.arange(0.5 * resolution, self.extend + 1e-12, 0.5 * resolution)
        axis = np.concatenate((line.end + np.outer(s, u), line.start - np.outer(s, u)))
        return (axis[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
