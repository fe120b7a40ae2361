"""What the viewer draws of the paper episode besides the robot and the cloud.

:class:`~harvest_qp.harvest.harvest_controller.HarvestController` returns a ``Command`` whose ``values``
(logged as ``value/*``) hold the phase, theta, p_r, p_sb, p_gd, V_c and V_g; this turns them
into :class:`~harvest_qp.viewer.ViewerFrame` fields for :class:`~harvest_qp.viewer.ViewedController`.
Used by ``harvest-qp run --viewer meshcat`` and ``examples/03_paper_episode.py``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

__all__ = ["paper_episode_extras"]

_VECTORS = (("p_r", "p_r"), ("p_sb", "p_sb"), ("p_gd", "p_gd"), ("p_c", "p_c"), ("v_c", "V_c"), ("v_g", "V_g"))


def paper_episode_extras(
    roi_radius: float, *, cell_resolution: float = 0.01, controller: Any = None
) -> Callable[[Any, Any], Mapping[str, Any]]:
    """``(obs, command) -> ViewerFrame fields`` for the paper episode's controller.

    Besides the controller's values, the closest of the QP's active collision rows
    (``Command.collision_pairs``) is drawn as a line between its witness points, recomputed
    from ``obs.q`` by :class:`~harvest_qp.viewer.closest.ClosestPairLocator`.

    Args:
        roi_radius: r, the ROI sphere's radius drawn around p_r [m] (``reaching.radius``).
        cell_resolution: the obstacle map's cell edge [m] (``obstacle_map.resolution``).
        controller: the :class:`~harvest_qp.harvest.harvest_controller.HarvestController`; once it has
            switched, what perception found at the switch (``switch_snapshot``: both stem
            segments, the Fibonacci samples kept, i.e. free space F, and removed) is drawn too.
    """
    from harvest_qp.harvest.harvest_controller import Phase  # the viewer observes the loop, never the reverse
    from harvest_qp.viewer.closest import ClosestPairLocator

    radius = float(roi_radius)
    locator = ClosestPairLocator(cell_resolution=cell_resolution)
    switch_fields: dict[str, Any] = {}

    def at_switch() -> Mapping[str, Any]:
        snapshot = getattr(controller, "switch_snapshot", None)
        if snapshot is not None and not switch_fields:  # taken once, at the switch
            stem = snapshot.stem
            switch_fields["stem_segments"] = np.array(
                [[stem.top.start, stem.top.end], [stem.bottom.start, stem.bottom.end]], dtype=float
            )
            switch_fields["samples_kept"] = np.array(snapshot.free_space.kept_samples, dtype=float)
            switch_fields["samples_removed"] = np.array(snapshot.free_space.removed_samples, dtype=float)
        return switch_fields

    def extras(obs: Any, command: Any) -> Mapping[str, Any]:
        values = command.values
        out: dict[str, Any] = {"phase": Phase(int(values["phase"])).name.lower(), "theta": float(values["theta"])}
        for field, key in _VECTORS:
            if field == "p_c" and key not in values:  # a controller that does not log its camera position
                continue
            value = np.array(values[key], dtype=float)  # a copy: the viewer draws it later, on its thread
            if np.all(np.isfinite(value)):  # NaN: not known yet (p_gd before the switch)
                out[field] = value
        if "p_r" in out:
            out["roi_center"], out["roi_radius"] = out["p_r"], radius
        pairs = getattr(command, "collision_pairs", ())
        if pairs:
            name_a, name_b, distance = min(pairs, key=lambda pair: pair[2])
            out["closest_pair"] = locator.points(obs.q, name_a, name_b)
            out["closest_distance"] = float(distance)
        out.update(at_switch())
        return out

    return extras
