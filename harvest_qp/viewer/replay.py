"""Replay a saved episode: a meshcat animation with a time slider, or one offline HTML file.

Typical use::

    from harvest_qp.viewer import replay, export_episode_html

    viewer = replay("runs/paper")           # serves http://127.0.0.1:7000/static/
    export_episode_html("runs/paper", "paper_episode.html")   # self-contained, plays offline

The vine is rebuilt from the log's metadata: ``meta/scene_params`` (a JSON object of
:class:`~harvest_qp.sim.VineSceneParams` fields) or ``meta/scene_sample_seed`` (the seed of
``VineSceneParams.sample``); without them, the paper's default scene.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.viewer.frame import frames_from_log
from harvest_qp.viewer.server import ViewerServer
from harvest_qp.viewer.viewer import MeshcatViewer

__all__ = ["load_log", "vine_params_from_log", "replay", "export_episode_html", "free_port"]


def load_log(run: str | Path | Mapping[str, Any]) -> dict[str, np.ndarray]:
    """An episode log from a ``.npz`` file, a run directory holding one, or a mapping.

    In a directory, ``episode.npz`` is used if present, else the only ``*.npz`` file.
    """
    if isinstance(run, Mapping):
        return dict(run)
    path = Path(run)
    if path.is_dir():
        candidates = sorted(path.glob("*.npz"))
        named = path / "episode.npz"
        if named.is_file():
            path = named
        elif len(candidates) == 1:
            path = candidates[0]
        else:
            raise InvalidInputError(
                f"run directory {str(path)!r} must hold episode.npz or exactly one .npz log, found "
                f"{[c.name for c in candidates]}"
            )
    if not path.is_file():
        raise InvalidInputError(f"episode log {str(path)!r} does not exist (expected a .npz file or a run directory)")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except (OSError, ValueError) as error:
        raise InvalidInputError(f"cannot read the episode log {str(path)!r}: {error}") from None


def vine_params_from_log(log: Mapping[str, Any]):
    """The :class:`~harvest_qp.sim.VineSceneParams` of a logged episode (see the module docstring)."""
    from harvest_qp.sim.scene import VineSceneParams

    if "meta/scene_params" in log:
        text = str(np.asarray(log["meta/scene_params"]))
        try:
            fields = json.loads(text)
            if isinstance(fields.get("camera_start"), list):
                fields["camera_start"] = tuple(fields["camera_start"])
            return VineSceneParams(**fields)
        except (ValueError, TypeError) as error:
            raise InvalidInputError(
                f"meta/scene_params is not a JSON object of VineSceneParams fields: {error}"
            ) from None
    if "meta/scene_sample_seed" in log:
        return VineSceneParams.sample(int(np.asarray(log["meta/scene_sample_seed"])))
    return VineSceneParams()


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def replay(
    run: str | Path | Mapping[str, Any],
    *,
    viewer: MeshcatViewer | None = None,
    fps: float = 30.0,
    play: bool = True,
    host: str = "127.0.0.1",
    port: int = 7000,
    vine: Any = "log",
    verbose: bool = True,
    **viewer_kwargs: Any,
) -> MeshcatViewer:
    """Load a saved episode into a viewer as an animation; returns the viewer (close it when done).

    Args:
        run: ``.npz`` log, run directory or log mapping.
        viewer: draw into this viewer; None starts one on ``host``:``port``.
        fps: animation frames per second of episode time.
        play: start playing when a browser connects.
        vine: ``"log"`` (from the log's metadata), or anything :class:`MeshcatViewer` accepts.
        verbose: print the URL.
        **viewer_kwargs: more :class:`MeshcatViewer` arguments for a new viewer.
    """
    log = load_log(run)
    frames = frames_from_log(log, fps=fps)
    if viewer is None:
        vine_arg = vine_params_from_log(log) if isinstance(vine, str) and vine == "log" else vine
        viewer = MeshcatViewer(vine_arg, host=host, port=port, verbose=verbose, **viewer_kwargs)
    try:
        viewer.load_animation(frames, play=play)
    except BaseException:
        viewer.close()
        raise
    return viewer


def export_episode_html(
    run: str | Path | Mapping[str, Any],
    html_path: str | Path,
    *,
    fps: float = 30.0,
    play: bool = True,
    vine: Any = "log",
    **viewer_kwargs: Any,
) -> Path:
    """Write a saved episode as one self-contained HTML file that plays offline.

    A private server on a free 127.0.0.1 port builds the scene and is stopped afterwards.

    Args:
        run: ``.npz`` log, run directory or log mapping.
        html_path: output ``.html`` file.
        fps: animation frames per second of episode time.
        play: start playing when the page opens.
        vine: ``"log"`` or anything :class:`MeshcatViewer` accepts.
        **viewer_kwargs: more :class:`MeshcatViewer` arguments (``view_center``, ``camera_offset``,
            ``point_size``, ``show_capsules``, ...).
    """
    html_path = Path(html_path)
    if html_path.suffix.lower() not in (".html", ".htm"):
        raise InvalidInputError(f"html_path must end in .html, got {str(html_path)!r}")
    log = load_log(run)
    vine_arg = vine_params_from_log(log) if isinstance(vine, str) and vine == "log" else vine
    with ViewerServer("127.0.0.1", free_port(), verbose=False) as server:
        viewer = MeshcatViewer(vine_arg, server=server, **viewer_kwargs)
        try:
            viewer.load_animation(frames_from_log(log, fps=fps), play=play)
            return viewer.export_html(html_path)
        finally:
            viewer.close()
