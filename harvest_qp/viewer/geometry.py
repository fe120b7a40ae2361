"""What the viewer draws, as plain data: UR5e meshes and where they sit, capsules, vine geoms.

Nothing here talks to meshcat; :mod:`harvest_qp.viewer.viewer` turns these into scene objects.

UR5e meshes: Universal Robots' collision shells (BSD-3-Clause, ``robots/ur5e_meshes/``,
licence beside them). Universal Robots' link frames differ from this project's link
frames (the URDF in ``robots/dual_ur5e/``) by a constant translation along the link's z
axis (:data:`UR_LINK_OFFSETS`, found by forward kinematics of both chains at random
configurations; ``tests/viewer/test_geometry.py`` checks it against pinocchio and checks
that the placed meshes lie inside the project's collision capsules).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.robot import ur5e
from harvest_qp.robot.meshes import MESH_ORIGINS, UR_LINK_OFFSETS, mesh_pose, meshes_dir, rpy_matrix

__all__ = [
    "UR_LINK_OFFSETS",
    "MESH_ORIGINS",
    "LinkMesh",
    "robot_link_meshes",
    "meshes_dir",
    "read_stl",
    "rpy_matrix",
    "VineGeom",
    "vine_geoms",
    "vine_body_poses",
]


# Where each UR5e mesh sits is defined once, in harvest_qp.robot.meshes (also used for
# MuJoCo's visual-only geoms); re-exported here for the viewer's users.
@dataclass(frozen=True)
class LinkMesh:
    """One UR5e mesh: the model frame that carries it, its STL file and its pose in that frame."""

    frame: str  # pinocchio frame name, e.g. "cam_forearm_link" or "cam_base_link"
    path: Path
    origin: NDArray[np.float64]  # (4, 4) mesh pose in ``frame``


def robot_link_meshes() -> list[LinkMesh]:
    """The 14 UR5e meshes of the two arms (7 per arm) with their frames and mesh origins."""
    folder = meshes_dir() / "collision"
    out = []
    for prefix in desc.ARM_PREFIXES:
        for link, (mesh, _, _) in MESH_ORIGINS.items():
            out.append(LinkMesh(prefix + link, folder / f"{mesh}.stl", mesh_pose(link)))
    return out


def read_stl(path: str | Path) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Triangles of a binary STL file: vertices (n, 3, 3) [m] and normals (n, 3)."""
    data = Path(path).read_bytes()
    if len(data) < 84:
        raise ModelError(f"{path} is not a binary STL file ({len(data)} bytes)")
    n = int(np.frombuffer(data, np.uint32, 1, 80)[0])
    if len(data) != 84 + 50 * n:
        raise ModelError(f"{path} is not a binary STL file: {n} triangles need {84 + 50 * n} bytes, got {len(data)}")
    record = np.dtype([("normal", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    tri = np.frombuffer(data, record, n, 84)
    return tri["v"].copy(), tri["normal"].copy()


# ---------------------------------------------------------------------------- vine


@dataclass(frozen=True)
class VineGeom:
    """A vine geom of the MuJoCo scene.

    Attributes:
        name: geom name (``branch``, ``cane``, ``leaf_3``, ``stem_seg_0``, ``berry_12``, ...).
        part: ``branch``, ``cane``, ``leaf``, ``petiole``, ``stem``, ``cluster`` (rachis and berries).
        body: name of the MuJoCo body that carries it (``vine``, ``stem_0``, ``cluster``, ...).
        kind: ``capsule``, ``sphere`` or ``ellipsoid``.
        size: radius and half-length (capsule), radius (sphere) or the 3 radii (ellipsoid) [m].
        local: (4, 4) pose in its body frame (capsules along local z).
        rgba: colour from the scene model.
    """

    name: str
    part: str
    body: str
    kind: str
    size: tuple[float, ...]
    local: NDArray[np.float64]
    rgba: tuple[float, float, float, float]


_PARTS = (("stem_seg_", "stem"), ("berry_", "cluster"), ("rachis", "cluster"), ("leaf_", "leaf"),
          ("petiole_", "petiole"), ("branch", "branch"), ("cane", "cane"))  # fmt: skip


def vine_geoms(model) -> list[VineGeom]:
    """The vine geoms (branch, cane, leaves, petioles, stem, cluster) of a MuJoCo vine scene model.

    Args:
        model: ``mujoco.MjModel`` of :func:`harvest_qp.sim.build_vine_scene` (e.g. ``SimRobot.model``).
    """
    import mujoco

    if not isinstance(model, mujoco.MjModel):
        raise InvalidInputError(f"model must be a mujoco.MjModel, got {type(model).__name__}")
    kinds = {
        int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
        int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
        int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): "ellipsoid",
    }
    out = []
    for g in range(model.ngeom):
        name = model.geom(g).name
        part = next((p for prefix, p in _PARTS if name.startswith(prefix)), None)
        kind = kinds.get(int(model.geom_type[g]))
        if part is None or kind is None:
            continue
        size = model.geom_size[g]
        size_t = (float(size[0]), float(size[1])) if kind == "capsule" else (
            (float(size[0]),) if kind == "sphere" else tuple(float(s) for s in size))  # fmt: skip
        local = np.eye(4)
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.geom_quat[g])
        local[:3, :3] = R.reshape(3, 3)
        local[:3, 3] = model.geom_pos[g]
        body = model.body(int(model.geom_bodyid[g])).name
        out.append(VineGeom(name, part, body, kind, size_t, local, tuple(float(c) for c in model.geom_rgba[g])))
    if not out:
        raise ModelError("the MuJoCo model has no vine geoms (branch, cane, leaf_*, stem_seg_*, berry_*)")
    return out


def vine_body_poses(model, data=None) -> dict[str, NDArray[np.float64]]:
    """World poses (4, 4) of the bodies that carry vine geoms.

    Args:
        model: the MuJoCo vine scene model.
        data: its ``mujoco.MjData`` after a forward pass (e.g. ``SimRobot.data``); None: the
            rest pose (``qpos0``).
    """
    import mujoco

    if data is None:
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
    bodies = {geom.body for geom in vine_geoms(model)}
    out = {}
    for name in bodies:
        b = model.body(name).id
        T = np.eye(4)
        T[:3, :3] = data.xmat[b].reshape(3, 3)
        T[:3, 3] = data.xpos[b]
        out[name] = T
    return out


def capsule_bodies() -> list[desc.CollisionBody]:
    """The robot's collision capsules (stand, arms, tools) from the robot description."""
    return desc.collision_bodies()


def link_capsules(link: str) -> tuple[ur5e.Capsule, ...]:
    """Capsules carried by a model frame (``cam_forearm_link``, ``grasp_tool``, ``base``)."""
    return tuple(b.capsule for b in desc.collision_bodies() if b.link == link)
