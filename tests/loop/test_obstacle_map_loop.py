"""The obstacle map in the closed loop (issue 11), from the CLI's own code path (``harvest-qp run``).

A scene whose straight approach crosses a leaf (the lab's occluding leaf moved to 0.4 m in
front of the stem middle, across the camera's way: without the map its cutter enters the
leaf ~1.5 s into the approach), run for the approach only at low resolution, with and
without ``obstacle_map.enabled``. Every oracle is the simulator's ground truth or the
scene's geometry, never the map: which geoms touch (MuJoCo's contacts at the logged joint
positions), where the leaf, the stem and the berries are (the scene), the true stem base.
"""

from __future__ import annotations

import json
import re

import mujoco
import numpy as np
import pytest

from harvest_qp.cli import main
from harvest_qp.configuration import Configuration
from harvest_qp.robot.paths import tasks_dir
from harvest_qp.sim import SimRobot, VineSceneParams
from tests.helpers import ResetRobot

PAPER = tasks_dir() / "paper.yaml"
OCCLUDER = {"occluder_distance": 0.32, "occluder_coverage": 1.0}
# [s] with the map the camera arm goes round the leaf and switches to the bimanual phase
# (within 1.05 r of the ROI centre, at rest) at ~8.6 s; without it the cutter enters the
# leaf at ~2.2 s.
DURATION = {True: 14.0, False: 3.0}
# The camera task's turn weighted like its travel: on this scene that path goes round the leaf. With the
# default's turn weight 0.3 the camera stays behind the leaf, the stem hidden, for 30 s (docs/limitations.md,
# "A leaf across the approach"); what this file tests, the map's rows, is the same on both paths.
APPROACH = ["--no-figures", "--set", "camera.downsample=6",
            "--set", "perception.min_stem_points=6",
            "--set", "scene.params={occluder_distance: 0.32, occluder_coverage: 1.0}",
            "--set", "qp.camera_task.weight=[1, 1, 1, 1, 1, 0]"]
CELL = re.compile(r"cell\[(-?\d+),(-?\d+),(-?\d+)\]")


def _run(out, enabled: bool):
    # Map rows on both arms (the default gives them to the camera arm only), so that the
    # held-cluster check below has gripper rows to look at.
    main(["run", str(PAPER), "--seed", "0", "--out", str(out), "--duration", str(DURATION[enabled]), *APPROACH,
          "--set", f"obstacle_map.enabled={'true' if enabled else 'false'}", "--set", "obstacle_map.arms=both"])
    return json.loads((out / "metrics.json").read_text()), dict(np.load(out / "episode.npz"))


@pytest.fixture(scope="module")
def episodes(tmp_path_factory):
    with_map = _run(tmp_path_factory.mktemp("with-map"), True)
    without_map = _run(tmp_path_factory.mktemp("without-map"), False)
    return with_map, without_map


@pytest.fixture(scope="module")
def robot():
    return SimRobot(VineSceneParams(**OCCLUDER), camera=None)


def _touched_geoms(robot, q_log, ticks) -> set[str]:
    """Names of the vine geoms touching a robot geom at the logged joint positions (MuJoCo)."""
    m, d = robot.model, robot.data
    names = set()
    vine = set(int(g) for g in robot.scene.vine_geoms)
    for k in ticks:
        d.qpos[robot._qpos_ids] = q_log[k]
        mujoco.mj_forward(m, d)
        for c in d.contact[: d.ncon]:
            for a, b in ((c.geom1, c.geom2), (c.geom2, c.geom1)):
                if a in vine and m.geom(b).name.startswith(("cam_", "grasp_")):
                    names.add(m.geom(a).name)
    return names


def _active_cells(log, capsule_prefix: str = "") -> dict[tuple[int, int, int], set[str]]:
    """Cells of the map that were active collision rows, with the capsules they acted on."""
    names = log["collision/pair_names"]
    active = np.unique(log["collision/active_pair"])
    out: dict[tuple[int, int, int], set[str]] = {}
    for index in active[active >= 0]:
        a, b = str(names[index]).split("|")
        for capsule, other in ((a, b), (b, a)):
            match = CELL.fullmatch(other)
            if match and capsule.startswith(capsule_prefix):
                out.setdefault(tuple(int(x) for x in match.groups()), set()).add(capsule)
    return out


def _leaf_frame(robot, name: str):
    m, d = robot.model, robot.data
    mujoco.mj_forward(m, d)
    g = m.geom(name).id
    return d.geom_xpos[g].copy(), d.geom_xmat[g].reshape(3, 3).copy(), m.geom_size[g].copy()


def test_leaf_on_the_approach_is_avoided_with_the_map(episodes, robot):
    """Without the map the camera arm runs into the leaf; with it, no contact, ROI reached, leaf cells active.

    Oracles: MuJoCo's contacts at the logged joint positions (which geoms touch), the true
    stem base of the scene (ROI), the leaf's ellipsoid (which cells lie on it).
    Catches: a map never fed to the QP (the contact stays), a map fed but not updated from
    the frames (no cell rows), rows so conservative the camera never reaches the ROI.
    """
    (m_with, log_with), (m_without, log_without) = episodes
    # Without the map: arm-vine contacts, and the leaf is among the touched geoms.
    vine_without = np.flatnonzero(log_without["truth/contacts_arm_vine"] > 0)
    assert len(vine_without) > 0
    assert "leaf_0" in _touched_geoms(robot, log_without["q"], vine_without[:: max(1, len(vine_without) // 20)])
    assert m_without["min_vine_distance"] < 1e-3
    # With the map: never a contact with the vine, and a true clearance left.
    assert m_with["contacts_by_kind"]["arm_vine"] == 0
    assert np.all(log_with["truth/contacts_arm_vine"] == 0)
    assert m_with["min_vine_distance"] > 0.0
    # ... and the camera still reaches the ROI: within the switch distance (1.05 r) of the ROI
    # centre it aims at, which moves (filtered) from the true gripper point to the stem base
    # once one is found: it must stay within 1.5 cm of that true segment.
    p_r = log_with["value/p_r"]
    a, b = robot.scene.gripper_home[:3, 3], np.asarray(robot.scene.stem_base)
    along = np.clip((p_r - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    assert np.all(np.linalg.norm(p_r - (a + along[:, None] * (b - a)), axis=1) < 0.015)
    distance = np.linalg.norm(log_with["value/p_c"] - p_r, axis=1)
    assert distance.min() <= 1.05 * m_with["roi_radius"]
    # The camera reached the ROI and came to rest there: the switch to the bimanual phase
    # (within 1.05 r of the ROI centre, tip slower than 0.01 m/s and 0.025 rad/s) fired.
    assert m_with["t_bimanual_start"] is not None, "the camera never reached the ROI round the leaf"
    # ... with the true stem base (not only the filtered ROI centre) within 1.05 r of the camera
    k = int(np.searchsorted(log_with["t"], m_with["t_bimanual_start"]))
    assert np.linalg.norm(log_with["value/p_c"][k] - b) <= 1.05 * m_with["roi_radius"] + 0.015
    # The leaf's cells were active rows on the way, on the camera arm.
    centre, R, semi = _leaf_frame(robot, "leaf_0")
    res = 0.01
    on_leaf = []
    for key, capsules in _active_cells(log_with).items():
        local = R.T @ ((np.array(key) + 0.5) * res - centre)
        in_plane = np.hypot(local[0] / (semi[0] + res), local[1] / (semi[1] + res))
        if in_plane <= 1.0 and abs(local[2]) <= semi[2] + res:
            on_leaf.append(capsules)
    assert on_leaf, "no active map row from a cell on leaf_0"
    assert any(c.startswith("cam_") for capsules in on_leaf for c in capsules)


def test_min_vine_distance_is_the_ground_truth_minimum(episodes, robot):
    """``metrics.json``'s min_vine_distance is the smallest true robot-vine distance of the episode.

    Oracle: MuJoCo's exact distance (``SimRobot.min_vine_distance``, itself checked against
    brute force in tests/sim) recomputed at the logged joint positions of a few ticks; the
    metric must be no larger than any of them and equal to the per-tick minimum.
    Catches: a metric taken from the controller's own (map) distances, or the last value only.
    """
    for metrics, log in episodes:
        per_tick = log["truth/min_vine_distance"]
        assert metrics["min_vine_distance"] == pytest.approx(float(np.nanmin(per_tick)))
        for k in np.linspace(0, len(per_tick) - 1, 5).astype(int):
            robot.data.qpos[robot._qpos_ids] = log["q"][k]
            mujoco.mj_forward(robot.model, robot.data)
            assert metrics["min_vine_distance"] <= robot.min_vine_distance() + 2e-3


def test_stem_and_held_cluster_are_never_map_rows(episodes, robot):
    """No active map cell lies on the stem (any capsule) or on the held cluster (gripper arm).

    Oracles: the scene's stem polyline and berry spheres, carried with the gripper frame
    from the logged joint positions (the cluster is welded to the gripper; the gripper
    holds still during the approach). Catches: the held cluster or the stem (seen as an
    obstacle beyond the camera's stem range) mapped and damping the arm that holds it.
    """
    (_, log), _ = episodes
    res = 0.01
    cell_radius = 0.5 * np.sqrt(3) * res
    scene = robot.scene
    m, d = robot.model, robot.data
    mujoco.mj_forward(m, d)
    G0 = scene.gripper_home
    berries = (d.geom_xpos[scene.berry_geoms] - G0[:3, 3]) @ G0[:3, :3]  # in {G}
    berry_r = float(m.geom_size[scene.berry_geoms[0]][0])
    stem = np.asarray(scene.stem_polyline)
    base = np.asarray(scene.stem_base)
    configuration = Configuration.dual_ur5e()
    cells = _active_cells(log)
    assert cells, "no map row at all: the test would pass vacuously"
    # Stem: cells within a cell of the stem's axis, away from the branch at its base.
    for key in cells:
        c = (np.array(key) + 0.5) * res
        a, b = stem[:-1], stem[1:]
        t = np.clip(np.einsum("ij,ij->i", c - a, b - a) / np.einsum("ij,ij->i", b - a, b - a), 0, 1)
        axis = np.min(np.linalg.norm(a + t[:, None] * (b - a) - c, axis=1))
        on_stem = axis <= scene.params.stem_radius + cell_radius and np.linalg.norm(c - base) > 0.03
        assert not on_stem, f"cell {key} on the stem was an active row on {cells[key]}"
    # Held cluster: at each tick a gripper-arm cell row was active, no cell on a berry.
    names = log["collision/pair_names"]
    for k in np.flatnonzero(np.any(log["collision/active_pair"] >= 0, axis=1))[::25]:
        pairs = [str(names[i]).split("|") for i in log["collision/active_pair"][k] if i >= 0]
        keys = [tuple(int(x) for x in CELL.fullmatch(b).groups()) for a, b in pairs
                if a.startswith("grasp_") and CELL.fullmatch(b)]
        if not keys:
            continue
        configuration.update(log["q"][k])
        G = configuration.frame_pose("gripper")
        world = berries @ G.rotation.T + G.translation
        for key in keys:
            c = (np.array(key) + 0.5) * res
            assert np.min(np.linalg.norm(world - c, axis=1)) > berry_r + cell_radius, (
                f"cell {key} on the held cluster was a row on the gripper arm at t={log['t'][k]:.3f}"
            )


def test_map_and_cloud_spheres_together_are_rejected():
    """Both feed the same collision limit's obstacle spheres: a ConfigError naming both keys."""
    from harvest_qp.config.settings import check_settings
    from harvest_qp.exceptions import ConfigError
    from harvest_qp.harvest.harvest_controller import HarvestController

    with pytest.raises(ConfigError, match="obstacle_map.enabled and obstacles.enabled"):
        HarvestController(check_settings({"obstacles": {"enabled": True}}))
    settings = check_settings({"obstacle_map": {"enabled": False}, "obstacles": {"enabled": True}})
    assert HarvestController(settings).obstacle_map is None


def test_controller_exclusions_keep_the_held_cluster_and_the_stem_out_of_the_map():
    """Lab frames around the ROI (the lab's ray-cast camera), mapped with the controller's own
    ``map_exclusions`` at the true gripper pose: no occupied cell touches a berry of the held
    cluster or the stem (away from the branch at its base), before a stem base is known and
    with the true one; without the exclusions, berries fill cells (the frames do see them).

    Oracles: the berry spheres and the stem geoms of the MuJoCo scene. Catches an exclusion
    in the wrong frame or along the wrong axis, a capsule too small for the cluster, a stem
    capsule pointing down the cluster instead of up to the branch.
    """
    from harvest_qp.config.settings import check_settings
    from harvest_qp.harvest.harvest_controller import HarvestController
    from harvest_qp.perception.obstacle_map import ObstacleMap
    from harvest_qp.sim import CameraConfig, make_camera
    from tests.perception.test_obstacle_map import lab_views

    robot = SimRobot(camera=None)
    scene, model, data = robot.scene, robot.model, robot.data
    mujoco.mj_forward(model, data)
    cam = make_camera(model, CameraConfig(), geom_labels=scene.geom_labels, exclude_body=scene.ids["cam_tool"])
    near = [cam.capture(data, pose, 0.0) for pose in lab_views(scene, 6, seed=8)]
    # Beyond the camera's 0.7 m stem range the stem is labelled an obstacle: only the
    # exclusion keeps it out of the map there.
    far = [cam.capture(data, pose, 0.0) for pose in lab_views(scene, 6, radius=0.8, seed=8)]
    controller = HarvestController(check_settings({}))
    T_g = robot.site_pose("gripper")
    cell = 0.5 * np.sqrt(3) * 0.01

    polyline = np.asarray(scene.stem_polyline)

    def touching(part: str, exclude, clouds) -> int:
        m = ObstacleMap()
        for cloud in clouds:
            m.update(cloud, exclude=exclude)
        c = m.occupied_centres()
        if part == "berries":
            gaps = np.min([np.linalg.norm(c - data.geom_xpos[g], axis=1) - model.geom_size[g, 0]
                           for g in scene.berry_geoms], axis=0)
        else:  # distance to the stem's polyline minus its radius
            a, b = polyline[:-1], polyline[1:]
            gaps = np.full(len(c), np.inf)
            for a0, b0 in zip(a, b):
                t = np.clip((c - a0) @ (b0 - a0) / ((b0 - a0) @ (b0 - a0)), 0.0, 1.0)
                gaps = np.minimum(gaps, np.linalg.norm(a0 + t[:, None] * (b0 - a0) - c, axis=1))
            gaps -= scene.params.stem_radius
        near_base = np.linalg.norm(c - np.asarray(scene.stem_base), axis=1) < 0.03
        return int(((gaps < cell) & ~near_base).sum())

    assert touching("berries", None, near) > 50
    assert touching("stem", None, far) > 3
    controller.state.p_sb = None  # before a stem base is found: the stem along -y_g
    exclude = controller.map_exclusions(T_g)
    assert touching("berries", exclude, near) == 0
    assert touching("stem", exclude, far) == 0
    controller.state.p_sb = np.asarray(scene.stem_base, float)
    exclude = controller.map_exclusions(T_g)
    assert touching("berries", exclude, near) == 0
    assert touching("stem", exclude, far) == 0


def test_the_held_cluster_region_never_erases_the_wood_next_to_the_tool():
    """Wood mapped beside the gripper (6 cm along x_g, level with the gripper point: inside the held
    cluster's exclusion capsule, whose round top reaches 4 cm above the gripper point and 8 cm
    out, but 1-3 cm beyond the real crop) stays in the map through the controller's frames: the
    region keeps the crop's points out, it does not forget what is there. Oracle: the wood's own
    points, placed here. Catches the region erasing mapped cells (held-out scene: a petiole's
    cells 42 -> 16, the gripper then rested on the branch for ~28 s); planted once
    (``erase_excluded=True``): this test failed."""
    from harvest_qp.config.settings import check_settings
    from harvest_qp.harvest.harvest_controller import HarvestController
    from harvest_qp.runtime.interface import OBSTACLE, PointCloud
    from harvest_qp.runtime.runner import Observation

    controller = HarvestController(check_settings({}))
    q = controller.configuration.q.copy()
    controller.reset(ResetRobot(q))
    T_g = controller.configuration.frame_pose("gripper").homogeneous
    p_g, x_g, y_g = T_g[:3, 3], T_g[:3, 0], T_g[:3, 1]
    camera = p_g - 0.4 * T_g[:3, 2]

    def cloud(points):
        z = (points.mean(axis=0) - camera) / np.linalg.norm(points.mean(axis=0) - camera)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = np.column_stack([x, np.cross(z, x), z]), camera
        n = len(points)
        rows, cols = np.divmod(np.arange(n), n)
        return PointCloud(points, np.full(n, OBSTACLE, np.int8), np.zeros((n, 3), np.uint8), pose, 0.0,
                          (points - camera) @ z, np.column_stack([rows, cols]).astype(np.int32), (n, n))

    grid = np.linspace(-0.01, 0.01, 5)
    wood = (p_g + 0.06 * x_g + grid[:, None, None] * y_g + grid[None, :, None] * T_g[:3, 2]).reshape(-1, 3)
    for _ in range(3):  # mapped before the crop came next to it (as the camera saw it earlier)
        controller.obstacle_map.update(cloud(wood))
    assert controller.obstacle_map.is_occupied(wood).all()
    far = p_g + np.array([0.0, 0.0, 0.5]) + 0.01 * np.arange(5)[:, None]
    for k in range(3):
        controller.step(Observation(time=0.002 * k, q=q, qdot=np.zeros(12), force=np.zeros(3), cloud=cloud(far),
                                    new_cloud=True))
    assert controller.obstacle_map.is_occupied(wood).mean() > 0.9
