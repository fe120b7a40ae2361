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
from harvest_qp.perception._validation import as_finite_points, as_grid_points, as_unit_vector, positive_int
from harvest_qp.validation import as_positive_scalar

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


def _across(u: NDArray[np.float64], hint, fallback) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unit vectors ``a = u x hint`` (``u x fallback`` when ``u`` lies near ``hint``) and ``b = u x a``."""
    a = np.cross(u, hint if abs(u @ hint) < 0.9 else fallback)
    a /= np.linalg.norm(a)
    return a, np.cross(u, a)


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


def _longest_tube_run(
    pts: NDArray[np.float64], along: NDArray[np.float64], cross: NDArray[np.float64], bin_size: float, max_gap: float
) -> tuple[NDArray[np.int64], float]:
    """Cells of the longest run (then the one with more cells) over all tubes, and its span [m].

    A tube is an occupied cross bin with its eight neighbours; a cell is in the tubes of the
    occupied bins around its own. All tubes at once: (tube, along) pairs sorted, runs split
    where the tube changes or the gap along exceeds ``max_gap``.
    """
    keys = np.floor(cross / bin_size).astype(np.int64)
    keys -= keys.min(axis=0) - 1  # >= 1, so the neighbours' keys are >= 0
    width = int(keys[:, 1].max()) + 2
    codes = keys[:, 0] * width + keys[:, 1]
    bins = np.unique(codes)
    tube_of, cell_of = [], []
    for d0 in (-1, 0, 1):
        for d1 in (-1, 0, 1):
            neighbour = codes + d0 * width + d1
            at = np.searchsorted(bins, neighbour)
            found = (at < bins.shape[0]) & (bins[np.minimum(at, bins.shape[0] - 1)] == neighbour)
            tube_of.append(at[found])
            cell_of.append(np.flatnonzero(found))
    tube = np.concatenate(tube_of)
    cell = np.concatenate(cell_of)
    order = np.lexsort((along[cell], tube))
    tube, cell = tube[order], cell[order]
    t = along[cell]
    new_run = np.ones(t.shape[0], dtype=bool)
    new_run[1:] = (tube[1:] != tube[:-1]) | (np.diff(t) > max_gap)
    starts = np.flatnonzero(new_run)
    ends = np.append(starts[1:], t.shape[0])
    spans = np.round(t[ends - 1] - t[starts], 9)
    best = np.lexsort((-(ends - starts), -spans))[0]  # longest, then most cells
    return cell[starts[best] : ends[best]], float(spans[best])


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
    ``max_gap`` [m] along the row is a candidate seen part. The longest one (the one with more
    cells among equally long ones) is refitted: the principal axis of its cells, then the cells
    within 1.5 bins of that axis and a gap of the run's ends, until the run stops growing (a
    tube along the row clips a structure a little off the row). It is kept when, refitted, it
    is at least ``min_length`` [m] long and its axis lies within ``max_tilt_deg`` [deg] of
    ``direction``; its cells are removed and the search repeats, up to ``max_lines`` lines.
    Deterministic. A single leaf (10-15 cm across) is never a line at the default
    ``min_length``; leaves in a row with gaps under ``max_gap`` can be (docs/obstacle_map.md).
    """
    pts = as_grid_points("cells", cells)
    u = as_unit_vector("direction", direction)
    bin_size = as_positive_scalar(bin_size, "bin_size")
    min_length = as_positive_scalar(min_length, "min_length")
    max_gap = as_positive_scalar(max_gap, "max_gap")
    max_tilt_deg = as_positive_scalar(max_tilt_deg, "max_tilt_deg")
    max_lines = positive_int("max_lines", max_lines, minimum=0)
    a, b = _across(u, (1.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    cos_tilt = math.cos(math.radians(max_tilt_deg))
    reach2 = (1.5 * bin_size) ** 2
    lines: list[LineStructure] = []
    while len(lines) < max_lines and pts.shape[0] >= 3:
        best, span = _longest_tube_run(pts, pts @ u, np.column_stack((pts @ a, pts @ b)), bin_size, max_gap)
        if span < min_length:
            break
        for _ in range(20):
            run = pts[best]
            centre = run.mean(axis=0)
            _, _, vt = np.linalg.svd(run - centre, full_matrices=False)
            axis = vt[0] if vt[0] @ u >= 0 else -vt[0]
            rel = pts - centre
            t = rel @ axis
            near = np.einsum("ij,ij->i", rel, rel) - t * t <= reach2
            near &= (t >= t[best].min() - max_gap) & (t <= t[best].max() + max_gap)
            candidates = np.flatnonzero(near)
            order = np.argsort(t[candidates], kind="stable")
            lo, hi = _longest_run(t[candidates][order], max_gap)
            grown = np.sort(candidates[order[lo:hi]])
            if hi - lo < 3 or np.array_equal(grown, np.sort(best)):
                break
            best = grown
        run = pts[best]
        centre = run.mean(axis=0)
        t = (run - centre) @ axis
        perp = run - centre - np.outer(t, axis)
        line = LineStructure(
            start=centre + t.min() * axis,
            end=centre + t.max() * axis,
            radius=float(np.median(np.linalg.norm(perp, axis=1))),
            support=int(best.shape[0]),
        )
        if axis @ u < cos_tilt or line.length < min_length:
            break
        lines.append(line)
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
        voxel: the search runs on one cell per ``voxel`` [m] cube (the first): a surface's
            cells to about a quarter.
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
        self.direction = as_unit_vector("direction", direction)
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
            keep_clear: ``(n, 3)`` points [m] (e.g. p_sb), or one point: no prior cell (the sphere
                covering it) reaches within ``keep_clear`` [m] of them.
            t: time [s] of this search, for :meth:`due`.

        Returns:
            the number of cells the prior marks.
        """
        if t is not None:
            if not math.isfinite(t):
                raise InvalidInputError(f"t must be a finite time [s], got {t!r}")
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
        try:
            clear = np.asarray(keep_clear, dtype=float)
        except (TypeError, ValueError):
            raise InvalidInputError(f"keep_clear must be (n, 3) points or one point [m], got {keep_clear!r}") from None
        clear = as_finite_points("keep_clear", clear.reshape(1, 3) if clear.shape == (3,) else clear)
        if pts.shape[0] and clear.shape[0] and self.keep_clear > 0.0:
            # On the cells the points fall in: no cell reaches into the sphere.
            res = obstacle_map.resolution
            centres = (np.floor(pts / res) + 0.5) * res  # as the map's kernels key a point
            d2 = ((centres[:, None, :] - clear[None, :, :]) ** 2).sum(axis=2).min(axis=1)
            pts = pts[d2 > (self.keep_clear + obstacle_map.cell_radius) ** 2]
        return obstacle_map.set_prior(pts)

    def continuation(self, line: LineStructure, resolution: float) -> NDArray[np.float64]:
        """Points [m] past both ends of ``line`` over ``extend``: on its axis and at its radius
        on four sides, every half cell along it."""
        u = line.direction
        a, b = _across(u, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0))
        r = line.radius
        offsets = np.array([[0.0, 0.0, 0.0], r * a, -r * a, r * b, -r * b])
        s = np.arange(0.5 * resolution, self.extend + 1e-12, 0.5 * resolution)
        axis = np.concatenate((line.end + np.outer(s, u), line.start - np.outer(s, u)))
        return (axis[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
