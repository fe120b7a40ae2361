"""Where the shipped robot and scene descriptions live."""

from __future__ import annotations

import os
from pathlib import Path

from harvest_qp.exceptions import ModelError

_PACKAGE_DIR = Path(__file__).resolve().parent.parent


def robots_root() -> Path:
    """The ``robots/`` folder: ``$HARVEST_QP_ROBOTS``, the repository's, or the installed copy."""
    candidates = []
    if os.environ.get("HARVEST_QP_ROBOTS"):
        candidates.append(Path(os.environ["HARVEST_QP_ROBOTS"]))
    candidates += [_PACKAGE_DIR.parent / "robots", _PACKAGE_DIR / "_data" / "robots"]
    for path in candidates:
        if (path / "dual_ur5e").is_dir():
            return path
    raise ModelError(
        "cannot find the robots/ folder with dual_ur5e/; looked in "
        + ", ".join(str(p) for p in candidates)
        + ". Install the package from its repository (pip install -e .) or set HARVEST_QP_ROBOTS."
    )


def robot_dir() -> Path:
    """Folder of the dual-UR5e description (URDF, MJCF, scene)."""
    try:
        return robots_root() / "dual_ur5e"
    except ModelError:
        return _PACKAGE_DIR.parent / "robots" / "dual_ur5e"


def urdf_path() -> Path:
    """Path of the dual-UR5e URDF (read by pinocchio and placo)."""
    return robot_dir() / "dual_ur5e.urdf"


def mjcf_path() -> Path:
    """Path of the dual-UR5e MJCF robot file (read by MuJoCo)."""
    return robot_dir() / "dual_ur5e.xml"


def scene_path() -> Path:
    """Path of the bare MuJoCo scene (floor, light, robot)."""
    return robot_dir() / "scene.xml"


def tasks_dir() -> Path:
    """The ``tasks/`` folder of YAML task configurations (repository or installed copy)."""
    for path in (_PACKAGE_DIR.parent / "tasks", _PACKAGE_DIR / "_data" / "tasks"):
        if path.is_dir():
            return path
    raise ModelError("cannot find the tasks/ folder of YAML task configurations")
