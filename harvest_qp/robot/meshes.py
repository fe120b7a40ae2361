"""The UR5e's real shape: Universal Robots' meshes, where each sits, and MuJoCo visual-only geoms.

Meshes: Universal Robots' UR5e collision shells (``robots/ur5e_meshes/collision/*.stl``,
BSD-3-Clause, licence beside them, ~380 KB in all). They are used for drawing only: by the
meshcat viewer and, as *visual-only* geoms, by MuJoCo renders. The controller, the
collision rows and the lab's physics and depth camera use the capsules of
:mod:`harvest_qp.robot.description`.

Universal Robots' link frames differ from this project's link frames by a constant
translation along the link's z axis (:data:`UR_LINK_OFFSETS`); inside a link each mesh has
the origin of :data:`MESH_ORIGINS` (ur_description 2.4.5). ``tests/viewer/test_geometry.py``
checks both against pinocchio and the capsules.

MuJoCo (Menagerie's convention): the robot file ``robots/dual_ur5e/dual_ur5e.xml`` carries the
meshes as geoms of class ``robot_visual`` in geom group :data:`VISUAL_GROUP` (2, shown by
default) with ``contype = conaffinity = 0`` (no contact) and ``density = 0`` (no mass; every
body has an explicit ``<inertial>`` anyway); the collision capsules are in group 3 (hidden
by default; key ``3`` in MuJoCo's viewer, ``show_capsules`` in
:class:`harvest_qp.sim.render.SceneRenderer`). The lab (:func:`harvest_qp.sim.build_vine_scene`)
removes them with :func:`strip_visual_meshes` before compiling, so its model, its depth
camera, its contacts and its metrics are those of the capsule robot, geom for geom.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.robot import paths
from harvest_qp.robot.ur5e import Capsule

__all__ = [
    "UR_LINK_OFFSETS",
    "MESH_ORIGINS",
    "VISUAL_GROUP",
    "VISUAL_CLASS",
    "VISUAL_RGBA",
    "meshes_dir",
    "rpy_matrix",
    "mesh_pose",
    "VisualGeom",
    "visual_geoms",
    "add_visual_meshes",
    "strip_visual_meshes",
]

#: MuJoCo geom group of the visual-only UR5e meshes (groups 0-2 are drawn by default).
VISUAL_GROUP = 2
#: MuJoCo default class of the visual-only UR5e meshes.
VISUAL_CLASS = "robot_visual"
#: Colour of the UR5e meshes in MuJoCo renders (the viewer's robot colour, 0x8FA9D8).
VISUAL_RGBA = (0x8F / 255, 0xA9 / 255, 0xD8 / 255, 1.0)
#: Prefix of the mesh asset names in MuJoCo (``ur5e_base``, ``ur5e_shoulder``, ...).
MESH_ASSET_PREFIX = "ur5e_"


def rpy_matrix(roll: float, pitch: float, yaw: float) -> NDArray[np.float64]:
    """URDF roll-pitch-yaw [rad] to a rotation matrix, ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def _pose(xyz: tuple[float, float, float], rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(*rpy)
    T[:3, 3] = xyz
    return T


#: Universal Robots' link frame in this project's link frame: a translation along z [m]
#: (the URDF here puts each joint's offset d_i in the child's joint origin instead).
UR_LINK_OFFSETS: dict[str, float] = {
    "base_link": 0.0,
    "shoulder_link": 0.1625,
    "upper_arm_link": 0.0,
    "forearm_link": 0.0,
    "wrist_1_link": 0.1333,
    "wrist_2_link": 0.0997,
    "wrist_3_link": 0.0996,
}

_PI = np.pi
#: Mesh file and mesh origin (xyz [m], rpy [rad]) in Universal Robots' link frame
#: (ur_description 2.4.5; the base mesh sits in ``base_link_inertia``, which is this
#: project's arm base frame).
MESH_ORIGINS: dict[str, tuple[str, tuple[float, float, float], tuple[float, float, float]]] = {
    "base_link": ("base", (0.0, 0.0, 0.0), (0.0, 0.0, _PI)),
    "shoulder_link": ("shoulder", (0.0, 0.0, 0.0), (0.0, 0.0, _PI)),
    "upper_arm_link": ("upperarm", (0.0, 0.0, 0.138), (_PI / 2, 0.0, -_PI / 2)),
    "forearm_link": ("forearm", (0.0, 0.0, 0.007), (_PI / 2, 0.0, -_PI / 2)),
    "wrist_1_link": ("wrist1", (0.0, 0.0, -0.127), (_PI / 2, 0.0, 0.0)),
    "wrist_2_link": ("wrist2", (0.0, 0.0, -0.0997), (0.0, 0.0, 0.0)),
    "wrist_3_link": ("wrist3", (0.0, 0.0, -0.0989), (_PI / 2, 0.0, 0.0)),
}


def meshes_dir() -> Path:
    """Folder of the shipped UR5e meshes (``robots/ur5e_meshes``)."""
    try:
        root = paths.robots_root()
    except ModelError:
        root = Path(__file__).resolve().parents[2] / "robots"
    folder = root / "ur5e_meshes"
    if not (folder / "collision").is_dir():
        raise ModelError(f"cannot find the UR5e meshes in {folder}/collision (shipped under robots/ur5e_meshes)")
    return folder


def mesh_pose(link: str) -> NDArray[np.float64]:
    """(4, 4) pose of the mesh of UR5e ``link`` (e.g. ``"forearm_link"``) in this project's link frame."""
    if link not in MESH_ORIGINS:
        raise InvalidInputError(f"link must be one of {sorted(MESH_ORIGINS)}, got {link!r}")
    _, xyz, rpy = MESH_ORIGINS[link]
    return _pose((0.0, 0.0, UR_LINK_OFFSETS[link])) @ _pose(xyz, rpy)


#: Colours of the parts drawn as capsules in renders (no Universal Robots mesh for them).
STAND_RGBA = (0.38, 0.38, 0.42, 1.0)
TOOL_RGBA = (0.22, 0.22, 0.25, 1.0)


@dataclass(frozen=True)
class VisualGeom:
    """A visual-only geom of the robot file: a UR5e mesh, or a capsule of a part without one.

    Attributes:
        name: geom name (``cam_forearm_link_visual``, ``stand_visual``, ``cutter_visual``, ...).
        body: MuJoCo body that carries it.
        mesh: UR5e mesh name (``forearm``) or None for a capsule.
        pose: (4, 4) mesh pose in the body frame (identity for a capsule).
        capsule: the capsule (body frame) drawn for the stand and the tools, else None.
        rgba: colour.
    """

    name: str
    body: str
    mesh: str | None
    pose: NDArray[np.float64]
    capsule: Capsule | None
    rgba: tuple[float, float, float, float]


def visual_geoms() -> list[VisualGeom]:
    """Every visual-only geom of the dual UR5e: 14 UR5e meshes, and the stand and tools as capsules.

    The stand and the tools have no Universal Robots mesh: their collision capsules are
    drawn (as visual-only copies), so a render without the capsule toggle shows the whole robot.
    """
    out = [VisualGeom(f"{cap.name}_visual", "base", None, np.eye(4), cap, STAND_RGBA)
           for cap in (desc.STAND_CAPSULE, desc.STAND_PLATE_CAPSULE)]  # fmt: skip
    for prefix in desc.ARM_PREFIXES:
        for link, (mesh, _, _) in MESH_ORIGINS.items():
            out.append(VisualGeom(f"{prefix}{link}_visual", prefix + link, mesh, mesh_pose(link), None, VISUAL_RGBA))
        tool = desc.TOOLS[prefix]
        for cap in tool.capsules:
            out.append(VisualGeom(f"{prefix}{cap.name}_visual", tool.name, None, np.eye(4), cap, TOOL_RGBA))
    return out


def _quat(R: NDArray[np.float64]) -> NDArray[np.float64]:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=float).ravel())
    return q


def add_visual_meshes(spec, *, mesh_folder: str | Path | None = None) -> int:
    """Add the visual-only geoms (:func:`visual_geoms`) to a MuJoCo spec of the dual UR5e that lacks them.

    Args:
        spec: a ``mujoco.MjSpec`` holding the robot's bodies (``base``, ``cam_shoulder_link``,
            ...), e.g. a lab scene's ``VineScene.spec`` (which :func:`strip_visual_meshes`
            left without them).
        mesh_folder: folder of the STL files (default ``robots/ur5e_meshes/collision``).

    Returns:
        The number of geoms added.
    """
    import mujoco

    folder = Path(mesh_folder) if mesh_folder is not None else meshes_dir() / "collision"
    if any(g.classname.name == VISUAL_CLASS for g in spec.geoms):
        raise ModelError(f"the spec already has {VISUAL_CLASS} geoms")
    for mesh in sorted({m for m, _, _ in MESH_ORIGINS.values()}):
        spec.add_mesh(name=MESH_ASSET_PREFIX + mesh, file=str((folder / f"{mesh}.stl").resolve()))
    # The class survives strip_visual_meshes (a spec read from the robot file keeps it).
    cls = spec.find_default(VISUAL_CLASS) or spec.add_default(VISUAL_CLASS, spec.default)
    cls.geom.type = mujoco.mjtGeom.mjGEOM_MESH
    cls.geom.contype = 0
    cls.geom.conaffinity = 0
    cls.geom.group = VISUAL_GROUP
    cls.geom.density = 0.0
    geoms = visual_geoms()
    for g in geoms:
        body = spec.body(g.body)
        if body is None:
            raise ModelError(f"the spec has no body {g.body!r} to carry the visual geom {g.name!r}")
        if g.mesh is not None:
            body.add_geom(cls, name=g.name, meshname=MESH_ASSET_PREFIX + g.mesh, pos=g.pose[:3, 3].tolist(),
                          quat=_quat(g.pose[:3, :3]).tolist(), rgba=list(g.rgba))  # fmt: skip
        else:
            body.add_geom(cls, name=g.name, type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[g.capsule.radius, 0, 0],
                          fromto=[*g.capsule.p0, *g.capsule.p1], rgba=list(g.rgba))  # fmt: skip
    return len(geoms)


def strip_visual_meshes(spec) -> int:
    """Remove the visual-only geoms (class ``robot_visual``) and the UR5e mesh assets from a MuJoCo spec.

    Used by the lab before compiling, so that its model (geom ids, ray-cast camera, contact
    checks) is the capsule robot alone. Returns the number of geoms removed.
    """
    removed = 0
    for geom in list(spec.geoms):
        if geom.classname.name == VISUAL_CLASS:
            spec.delete(geom)
            removed += 1
    for mesh in list(spec.meshes):
        if mesh.name.startswith(MESH_ASSET_PREFIX):
            spec.delete(mesh)
    return removed
