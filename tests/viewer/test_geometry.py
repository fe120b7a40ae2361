"""Where the UR5e meshes sit, the STL reader, and the vine geoms read from the MuJoCo scene."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from harvest_qp import Configuration
from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.sim import VineSceneParams, build_vine_scene
from harvest_qp.viewer.geometry import (
    UR_LINK_OFFSETS,
    meshes_dir,
    read_stl,
    robot_link_meshes,
    rpy_matrix,
    vine_body_poses,
    vine_geoms,
)

PI = np.pi
#: Universal Robots' joint origins (ur_description 2.4.5),
#: from base_link_inertia: (xyz, rpy) of shoulder_pan ... wrist_3, all about local z.
UR_JOINTS = [
    ((0, 0, 0.1625), (0, 0, 0)),
    ((0, 0, 0), (PI / 2, 0, 0)),
    ((-0.425, 0, 0), (0, 0, 0)),
    ((-0.3922, 0, 0.1333), (0, 0, 0)),
    ((0, -0.0997, 0), (PI / 2, 0, 0)),
    ((0, 0.0996, 0), (PI / 2, PI, PI)),
]
LINKS = ["shoulder_link", "upper_arm_link", "forearm_link", "wrist_1_link", "wrist_2_link", "wrist_3_link"]


def pose(xyz, rpy) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_matrix(*rpy)
    T[:3, 3] = xyz
    return T


def rot_z(angle: float) -> np.ndarray:
    T = np.eye(4)
    c, s = np.cos(angle), np.sin(angle)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def test_rpy_matches_pinocchio():
    import pinocchio as pin

    for rpy in [(0.3, -0.2, 1.1), (PI / 2, PI, PI), (-1.0, 0.5, -2.0)]:
        np.testing.assert_allclose(rpy_matrix(*rpy), pin.rpy.rpyToMatrix(*rpy), atol=1e-12)


def test_ur_link_frames_differ_by_the_offset_table(rng):
    """Universal Robots' link frames (their joint table, chained here) equal this project's link
    frames (pinocchio on the project URDF) times UR_LINK_OFFSETS, at random configurations.

    Catches: a wrong or missing offset (each is 0.1 m or more), a base frame turned by pi.
    """
    conf = Configuration.dual_ur5e()
    for _ in range(5):
        q = rng.uniform(-3, 3, 12)
        conf.update(q)
        for arm, q_arm in ((desc.CAMERA_ARM, q[:6]), (desc.GRASP_ARM, q[6:])):
            T = conf.frame_pose(arm + "base_link").homogeneous
            for i, (xyz, rpy) in enumerate(UR_JOINTS):
                T = T @ pose(xyz, rpy) @ rot_z(q_arm[i])
                ours = conf.frame_pose(arm + LINKS[i]).homogeneous
                expected = ours @ pose((0, 0, UR_LINK_OFFSETS[LINKS[i]]), (0, 0, 0))
                np.testing.assert_allclose(T, expected, atol=1e-9, err_msg=arm + LINKS[i])


def segment_distance(points, a, b):
    ab = b - a
    t = np.clip((points - a) @ ab / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def test_meshes_lie_within_the_collision_capsules(rng):
    """Every vertex of every placed mesh is within 3.5 cm of the robot's collision capsules
    (stand and same arm), and its centroid is inside them, at random configurations.

    Catches: a mesh in the wrong link, a missing z offset, a wrong mesh rotation (checked by
    hand: a zero wrist 1 offset puts vertices 3.9 cm outside; a zero shoulder offset stays
    inside the tall shoulder capsule and only the test above catches it).
    The 3.5 cm margin is measured: the UR5e's joint housings stick out of the project's
    capsules by up to 2.9 cm (upper arm and forearm), a note for the capsule sizes.
    """
    conf = Configuration.dual_ur5e()
    meshes = robot_link_meshes()
    assert len(meshes) == 14
    vertices = {m.path: read_stl(m.path)[0].reshape(-1, 3).astype(float) for m in meshes}
    bodies = desc.collision_bodies()
    for _ in range(3):
        conf.update(rng.uniform(-2.5, 2.5, 12))
        for mesh in meshes:
            T = conf.frame_pose(mesh.frame).homogeneous @ mesh.origin
            world = vertices[mesh.path] @ T[:3, :3].T + T[:3, 3]
            arm = desc.CAMERA_ARM if mesh.frame.startswith(desc.CAMERA_ARM) else desc.GRASP_ARM
            points = np.vstack([world, world.mean(0)])
            outside = np.full(len(points), np.inf)
            for body in bodies:
                if body.arm not in (arm, ""):
                    continue
                L = conf.frame_pose(body.link).homogeneous
                a = L[:3, :3] @ body.capsule.p0 + L[:3, 3]
                b = L[:3, :3] @ body.capsule.p1 + L[:3, 3]
                outside = np.minimum(outside, segment_distance(points, a, b) - body.capsule.radius)
            assert outside[:-1].max() < 0.035, f"{mesh.frame}: a vertex {outside.max():.3f} m outside the capsules"
            assert outside[-1] < 0.0, f"{mesh.frame}: the mesh's centroid is outside the capsules"


def test_shipped_meshes_are_small_and_licensed():
    folder = meshes_dir()
    total = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())
    assert total < 1_000_000, f"the shipped meshes weigh {total / 1e6:.2f} MB"
    assert "Redistribution and use" in (folder / "LICENSE").read_text()
    assert "Universal Robots" in (folder / "README.md").read_text()


def test_read_stl(tmp_path):
    triangles, normals = read_stl(meshes_dir() / "collision" / "wrist3.stl")
    assert triangles.shape[1:] == (3, 3) and len(normals) == len(triangles) > 10
    extent = triangles.reshape(-1, 3).max(0) - triangles.reshape(-1, 3).min(0)
    assert np.all(extent < 0.2) and np.all(extent > 0.02), f"wrist 3 is not metres-sized: {extent}"
    bad = tmp_path / "bad.stl"
    bad.write_bytes(b"solid ascii\n" * 10)
    with pytest.raises(ModelError, match="binary STL"):
        read_stl(bad)


@pytest.fixture(scope="module")
def scene():
    return build_vine_scene(VineSceneParams(seed=2))


def test_vine_geoms_match_mujoco(scene):
    """The vine geoms, placed by their body poses, are where MuJoCo puts them (geom_xpos/xmat).

    Catches: a geom pose composed in the wrong order, a capsule size read as (half-length,
    radius), missing parts.
    """
    geoms = vine_geoms(scene.model)
    parts = {g.part for g in geoms}
    assert parts == {"branch", "cane", "leaf", "petiole", "stem", "cluster"}
    assert sum(g.part == "stem" for g in geoms) == len(scene.stem_geoms)
    assert sum(g.name.startswith("berry_") for g in geoms) == len(scene.berry_geoms)
    data = mujoco.MjData(scene.model)
    mujoco.mj_kinematics(scene.model, data)
    poses = vine_body_poses(scene.model, data)
    for g in geoms:
        gid = scene.model.geom(g.name).id
        world = poses[g.body] @ g.local
        np.testing.assert_allclose(world[:3, 3], data.geom_xpos[gid], atol=1e-9, err_msg=g.name)
        np.testing.assert_allclose(world[:3, :3], data.geom_xmat[gid].reshape(3, 3), atol=1e-9, err_msg=g.name)
        if g.kind == "capsule":
            assert g.size == pytest.approx(tuple(scene.model.geom_size[gid][:2]))
    stem = [g for g in geoms if g.part == "stem"]
    assert all(g.size[0] == pytest.approx(scene.params.stem_radius) for g in stem)


def test_vine_geoms_bad_input():
    with pytest.raises(InvalidInputError, match="mujoco.MjModel"):
        vine_geoms("scene.xml")
