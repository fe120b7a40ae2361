"""The UR5e meshes as MuJoCo visual-only geoms: drawn in renders, invisible to physics and to the lab.

The robot file carries Universal Robots' meshes (group 2, no contact, no mass); the lab strips
them, so its model, depth camera and contact checks are the capsule robot geom for geom.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from harvest_qp.exceptions import InvalidInputError, ModelError
from harvest_qp.robot import description as desc
from harvest_qp.robot import generate, meshes, paths
from harvest_qp.runtime.interface import ROBOT
from harvest_qp.sim import VineSceneParams, build_vine_scene
from harvest_qp.viewer.geometry import read_stl, robot_link_meshes

ROOT = Path(__file__).resolve().parents[2]


def _capsule_scene(tmp_path: Path) -> mujoco.MjModel:
    """The shipped scene with the robot file generated without visual geoms (the former robot file)."""
    (tmp_path / "dual_ur5e.xml").write_text(generate.build_mjcf(visual=False))
    (tmp_path / "scene.xml").write_text(generate.SCENE_XML)
    return mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))


def _model_arrays(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    prefixes = ("geom_", "body_", "jnt_", "dof_", "pair_", "site_", "actuator_")
    out = {}
    for name in dir(model):
        if name.startswith(prefixes) and not name.endswith("_user"):
            value = getattr(model, name)
            if isinstance(value, np.ndarray):
                out[name] = value
    return out


def test_stripped_robot_file_is_the_capsule_robot_array_for_array(tmp_path):
    """What the lab compiles (the shipped scene with strip_visual_meshes) equals the scene built
    from a robot file that never had meshes, in every geom/body/joint/dof/pair/site array
    (masses, inertias, contact filters, geom ids, sizes).

    Catches: a visual geom left in (ngeom and geom ids shift, the ray-cast camera would see it),
    a mesh that adds mass or inertia, a strip that removes a collision capsule.
    Oracle: MuJoCo compiling ``build_mjcf(visual=False)``, which is byte for byte the robot file
    before the meshes were added (checked when they were: ``git show d804e26:robots/dual_ur5e/dual_ur5e.xml``).
    """
    reference = _capsule_scene(tmp_path)
    spec = mujoco.MjSpec.from_file(str(paths.scene_path()))
    assert meshes.strip_visual_meshes(spec) == len(meshes.visual_geoms())
    stripped = spec.compile()
    assert (stripped.ngeom, stripped.nmesh, stripped.nbody, stripped.nq) == (
        reference.ngeom, 0, reference.nbody, reference.nq)  # fmt: skip
    a, b = _model_arrays(stripped), _model_arrays(reference)
    assert a.keys() == b.keys() and len(a) > 40
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)


def test_lab_scene_has_no_visual_geom_and_labels_only_capsules_as_robot():
    """The lab's model has no mesh and no group-2 geom; its ROBOT-labelled geoms are exactly the
    description's collision capsules (what the depth camera labels as the robot's own points).

    Catches: build_vine_scene no longer stripping the meshes (the camera would see them and
    label their points ROBOT; the contact checks would treat meshes as capsules).
    """
    scene = build_vine_scene(VineSceneParams(seed=3))
    model = scene.model
    assert model.nmesh == 0 and not np.any(model.geom_group == meshes.VISUAL_GROUP)
    robot = {model.geom(g).name for g in np.flatnonzero(scene.geom_labels == ROBOT)}
    capsules = {(b.arm + b.capsule.name) if b.arm else b.capsule.name for b in desc.collision_bodies()}
    assert robot == capsules


def test_visual_geoms_are_visual_only():
    """Every visual geom of the shipped scene: no contact (contype = conaffinity = 0), group 2,
    and the body masses and inertias are those of the explicit <inertial> elements.

    Oracle: the robot description's link masses (UR datasheet) and MuJoCo's own geom flags.
    """
    model = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    names = [g.name for g in meshes.visual_geoms()]
    ids = np.array([model.geom(n).id for n in names])
    assert np.all(model.geom_contype[ids] == 0) and np.all(model.geom_conaffinity[ids] == 0)
    assert np.all(model.geom_group[ids] == meshes.VISUAL_GROUP)
    assert np.all(model.geom_group[model.geom_group != meshes.VISUAL_GROUP] != meshes.VISUAL_GROUP)
    assert np.sum(model.geom_type[ids] == mujoco.mjtGeom.mjGEOM_MESH) == 14
    from harvest_qp.robot import ur5e

    for prefix in desc.ARM_PREFIXES:
        for link, mass in zip(ur5e.LINK_NAMES, ur5e.LINK_MASSES, strict=True):
            assert model.body(prefix + link).mass[0] == pytest.approx(mass)


def test_mujoco_meshes_sit_where_the_viewer_places_them(rng):
    """The MuJoCo mesh geoms' world vertices coincide with the STL vertices placed by pinocchio
    forward kinematics and the viewer's mesh origins (which tests/viewer/test_geometry.py
    checks against Universal Robots' joint table and the capsules), at random configurations.

    Catches: a wrong quaternion convention or mesh pose in the generated MJCF, a mesh on the
    wrong body, MuJoCo's mesh re-centring not accounted for. Checked by hand: writing the
    quaternion as (x, y, z, w) moves vertices by centimetres and fails.
    """
    model = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    data = mujoco.MjData(model)
    pmodel = pin.buildModelFromUrdf(str(paths.urdf_path()))
    pdata = pmodel.createData()
    stl = {m.path: read_stl(m.path)[0].reshape(-1, 3).astype(float) for m in robot_link_meshes()}
    for _ in range(3):
        q = rng.uniform(-2.5, 2.5, 12)
        data.qpos[:12] = q
        mujoco.mj_kinematics(model, data)
        pin.framesForwardKinematics(pmodel, pdata, q)
        for mesh in robot_link_meshes():
            g = model.geom(mesh.frame + "_visual").id
            m = int(model.geom_dataid[g])
            start, count = model.mesh_vertadr[m], model.mesh_vertnum[m]
            local = model.mesh_vert[start : start + count].astype(float)
            world_mj = local @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g]
            T = pdata.oMf[pmodel.getFrameId(mesh.frame)].homogeneous @ mesh.origin
            world_pin = stl[mesh.path] @ T[:3, :3].T + T[:3, 3]
            # every MuJoCo vertex is one of the placed STL vertices (MuJoCo merges duplicates)
            nearest = np.min(np.linalg.norm(world_mj[::7, None, :] - world_pin[None, ::1, :], axis=2), axis=1)
            assert nearest.max() < 1e-5, f"{mesh.frame}: {nearest.max():.2e} m"


def test_spec_api_adds_the_same_geoms_as_the_robot_file():
    """add_visual_meshes (used to draw a lab scene) puts every visual geom where the generated
    robot file does. Catches the two code paths drifting apart."""
    from_file = mujoco.MjModel.from_xml_path(str(paths.scene_path()))
    spec = mujoco.MjSpec.from_file(str(paths.scene_path()))
    meshes.strip_visual_meshes(spec)
    with pytest.raises(ModelError, match="no body"):
        meshes.add_visual_meshes(mujoco.MjSpec())
    assert meshes.add_visual_meshes(spec) == len(meshes.visual_geoms())
    with pytest.raises(ModelError, match="already"):
        meshes.add_visual_meshes(spec)
    rebuilt = spec.compile()
    a, b = mujoco.MjData(from_file), mujoco.MjData(rebuilt)
    a.qpos[:12] = b.qpos[:12] = desc.HOME_Q + 0.3
    mujoco.mj_kinematics(from_file, a)
    mujoco.mj_kinematics(rebuilt, b)
    for geom in meshes.visual_geoms():
        i, j = from_file.geom(geom.name).id, rebuilt.geom(geom.name).id
        np.testing.assert_allclose(a.geom_xpos[i], b.geom_xpos[j], atol=1e-9, err_msg=geom.name)
        np.testing.assert_allclose(a.geom_xmat[i], b.geom_xmat[j], atol=1e-9, err_msg=geom.name)
        assert from_file.geom_type[i] == rebuilt.geom_type[j]
        assert rebuilt.geom_contype[j] == rebuilt.geom_conaffinity[j] == 0


def render_check() -> dict[str, int]:
    """Segmentation renders of the default lab scene: pixels of mesh and capsule geoms per toggle.

    Needs ``MUJOCO_GL`` (egl or osmesa) set before mujoco is imported; run by
    :func:`test_renders_show_meshes_and_the_capsule_toggle` here or in a child process.
    """
    from harvest_qp.sim import SimRobot
    from harvest_qp.sim.render import SceneRenderer

    robot = SimRobot(camera=None)
    renderer = SceneRenderer.for_spec(robot.scene.spec, width=240, height=160)
    model = renderer.model
    mesh_ids = {model.geom(g.name).id for g in meshes.visual_geoms() if g.mesh is not None}
    capsule_ids = {i for i in range(model.ngeom) if model.geom_group[i] == 3}
    out = {}
    for key, flags in (("default", {}), ("capsules", {"show_meshes": False, "show_capsules": True})):
        renderer.set_visible(**flags)
        seg = renderer.render(robot.data, lookat=(0.3, 0.0, 1.0), distance=2.0, azimuth=180, elevation=-15,
                              segmentation=True)  # fmt: skip
        geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
        out[f"{key}_mesh"] = int(np.isin(geom, list(mesh_ids)).sum())
        out[f"{key}_capsule"] = int(np.isin(geom, list(capsule_ids)).sum())
    renderer.set_visible()
    rgb = renderer.render(robot.data, lookat=(0.3, 0.0, 1.0), distance=2.0, azimuth=180, elevation=-15)
    out["rgb_mean"] = int(rgb.mean())
    try:
        renderer.render(np.zeros(3))
    except InvalidInputError:
        out["bad_state_raises"] = 1
    renderer.close()
    return out


def test_renders_show_meshes_and_the_capsule_toggle():
    """A render of the lab scene draws the UR5e meshes and no capsule by default; the toggle
    draws the capsules (and, with meshes off, no mesh). Oracle: MuJoCo's segmentation image.

    Catches: meshes missing from renders (wrong group, not added), capsules drawn over the
    meshes by default, a toggle that does nothing. Runs in CI (EGL); when MUJOCO_GL is unset
    here it runs in a child process with MUJOCO_GL=egl.
    """
    if os.environ.get("MUJOCO_GL") in ("egl", "osmesa"):
        counts = render_check()
    else:
        code = "import json; from tests.core.test_visual_meshes import render_check; print(json.dumps(render_check()))"
        done = subprocess.run(
            [sys.executable, "-c", code], cwd=ROOT, env={**os.environ, "MUJOCO_GL": "egl"},
            capture_output=True, text=True, timeout=300,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        counts = json.loads(done.stdout.strip().splitlines()[-1])
    assert counts["default_mesh"] > 500 and counts["default_capsule"] == 0, counts
    assert counts["capsules_mesh"] == 0 and counts["capsules_capsule"] > 500, counts
    assert counts["rgb_mean"] > 20 and counts.get("bad_state_raises") == 1, counts
