"""Bad arguments to the lab's and the obstacle map's public constructors: the package's own error.

Each case passes one bad value (text, None, NaN, a list, a wrong type) and checks that a
:class:`~harvest_qp.exceptions.HarvestQPError` is raised whose message names the argument and
shows the value received. Bug caught: a constructor that lets the value reach numpy or MuJoCo,
which then raise a foreign ``TypeError``/``ValueError``/``AttributeError`` (or accept it), e.g.
``SimRobot(settle_time='a')`` raised numpy's "ufunc 'isfinite' not supported" before this file.
"""

import math

import pytest

from harvest_qp.exceptions import HarvestQPError, InvalidInputError
from harvest_qp.perception.obstacle_map import ExclusionRegion, ObstacleMap, _as_regions
from harvest_qp.sim import (
    ActuationConfig,
    CameraConfig,
    ForceSensorConfig,
    RayCastCamera,
    SensorFaults,
    SimRobot,
    VineSceneParams,
    build_vine_scene,
    make_camera,
)

NAN = math.nan


@pytest.fixture(scope="module")
def scene():
    return build_vine_scene()


# (constructor, keyword arguments, text the message must contain: the argument and the value)
DATACLASS_CASES = [
    (VineSceneParams, {"stem_bend": "abc"}, ["VineSceneParams.stem_bend", "'abc'"]),
    (VineSceneParams, {"stem_bend": None}, ["VineSceneParams.stem_bend", "None"]),
    (VineSceneParams, {"branch_yaw": [1.0, 2.0]}, ["VineSceneParams.branch_yaw", "[1.0, 2.0]"]),
    (VineSceneParams, {"branch_pitch": {"a": 1}}, ["VineSceneParams.branch_pitch", "{'a': 1}"]),
    (VineSceneParams, {"grasp_offset": None}, ["VineSceneParams.grasp_offset", "None"]),
    (VineSceneParams, {"stem_bend_stiffness": "abc"}, ["VineSceneParams.stem_bend_stiffness", "'abc'"]),
    (VineSceneParams, {"stem_length": NAN}, ["VineSceneParams.stem_length", "nan"]),
    (VineSceneParams, {"stem_segments": 2.5}, ["VineSceneParams.stem_segments", "2.5"]),
    (VineSceneParams, {"occlude_stem": "abc"}, ["VineSceneParams.occlude_stem", "'abc'", "True or False"]),
    (VineSceneParams, {"occlude_stem": None}, ["VineSceneParams.occlude_stem", "None"]),
    (VineSceneParams, {"camera_start": "abc"}, ["camera_start", "'abc'"]),
    (VineSceneParams, {"camera_start": {"a": 1}}, ["camera_start", "{'a': 1}"]),
    (VineSceneParams, {"seed": "abc"}, ["VineSceneParams.seed", "'abc'"]),
    (CameraConfig, {"vertical_fov": "abc"}, ["CameraConfig.vertical_fov", "'abc'"]),
    (CameraConfig, {"rate": None}, ["CameraConfig.rate", "None"]),
    (CameraConfig, {"max_depth": [1.0, 2.0]}, ["CameraConfig.max_depth", "[1.0, 2.0]"]),
    (CameraConfig, {"dropout": {"a": 1}}, ["CameraConfig.dropout", "{'a': 1}"]),
    (CameraConfig, {"latency": NAN}, ["CameraConfig.latency", "nan"]),
    (CameraConfig, {"rendered_rgb": "abc"}, ["CameraConfig.rendered_rgb", "'abc'"]),
    (ForceSensorConfig, {"noise_std": "abc"}, ["ForceSensorConfig.noise_std", "'abc'"]),
    (ForceSensorConfig, {"filter_time_constant": None}, ["ForceSensorConfig.filter_time_constant", "None"]),
    (SensorFaults, {"frame_latency": "abc"}, ["SensorFaults.frame_latency", "'abc'"]),
    (SensorFaults, {"frame_loss": None}, ["SensorFaults.frame_loss", "None"]),
    (ActuationConfig, {"bandwidth": "abc"}, ["ActuationConfig.bandwidth", "'abc'"]),
    (ActuationConfig, {"damping_ratio": [1.0, 2.0]}, ["ActuationConfig.damping_ratio", "[1.0, 2.0]"]),
    (ActuationConfig, {"max_acceleration": "abc"}, ["ActuationConfig.max_acceleration", "'abc'"]),
    (ActuationConfig, {"max_acceleration": True}, ["ActuationConfig.max_acceleration", "True"]),
    (ActuationConfig, {"position_margin": None}, ["ActuationConfig.position_margin", "None"]),
    (ExclusionRegion, {"p0": "abc", "p1": (0, 0, 1), "radius": 0.1}, ["ExclusionRegion.p0", "'abc'"]),
    (ExclusionRegion, {"p0": (0, 0, 0), "p1": (0, NAN, 1), "radius": 0.1}, ["ExclusionRegion.p1", "nan"]),
    (ExclusionRegion, {"p0": (0, 0, 0), "p1": (0, 0, 1), "radius": -1.0}, ["ExclusionRegion.radius", "-1.0"]),
    (ExclusionRegion, {"p0": (0, 0, 0), "p1": (0, 0, 1), "radius": "abc"}, ["ExclusionRegion.radius", "'abc'"]),
    (ObstacleMap, {"bounds": {"a": 1}}, ["bounds"]),
    (ObstacleMap, {"erase_excluded": "abc"}, ["erase_excluded", "'abc'"]),
    (ObstacleMap, {"resolution": "abc"}, ["resolution", "'abc'"]),
    (ObstacleMap, {"prob_hit": None}, ["prob_hit", "None"]),
    (ObstacleMap, {"no_return_range": "ab"}, ["no_return_range", "'ab'"]),
]


@pytest.mark.parametrize(("make", "kwargs", "expected"), DATACLASS_CASES)
def test_bad_constructor_argument_raises_the_package_error(make, kwargs, expected):
    with pytest.raises(HarvestQPError) as info:
        make(**kwargs)
    assert isinstance(info.value, InvalidInputError)
    for text in expected:
        assert text in str(info.value), (str(info.value), text)


OTHER_CASES = [
    ("exclude", lambda scene: _as_regions("abc"), ["exclude", "'abc'"]),
    ("exclude", lambda scene: _as_regions([["a"] * 7]), ["exclude", "'a'"]),
    ("center", lambda scene: ExclusionRegion.sphere("abc", 0.1), ["center", "'abc'"]),
    ("radius", lambda scene: ExclusionRegion.sphere((0, 0, 0), NAN), ["radius", "nan"]),
    ("distance", lambda scene: scene.approach_pose("a"), ["distance", "'a'"]),
    ("distance", lambda scene: scene.approach_pose(NAN), ["distance", "nan"]),
    ("target", lambda scene: scene.approach_pose(0.3, target="abc"), ["target", "'abc'"]),
    ("target", lambda scene: scene.approach_pose(0.3, target=[NAN, 0, 0]), ["target", "nan"]),
    ("home_q", lambda scene: build_vine_scene(home_q="abc"), ["home_q", "'abc'"]),
    ("actuation", lambda scene: build_vine_scene(actuation="abc"), ["actuation", "'abc'"]),
    ("settle_time", lambda scene: SimRobot(scene, settle_time="a"), ["settle_time", "'a'"]),
    ("settle_time", lambda scene: SimRobot(scene, settle_time=None), ["settle_time", "None"]),
    ("control_period", lambda scene: SimRobot(scene, control_period="a"), ["control_period", "'a'"]),
    ("payload_compensation", lambda scene: SimRobot(scene, payload_compensation="yes"),
     ["payload_compensation", "'yes'"]),
    ("force", lambda scene: SimRobot(scene, force=[1.0, 2.0]), ["force", "[1.0, 2.0]", "ForceSensorConfig"]),
    ("actuation", lambda scene: SimRobot(scene, actuation=3), ["actuation", "3", "ActuationConfig"]),
    ("seed", lambda scene: SimRobot(scene, seed="x"), ["seed", "'x'"]),
    ("camera config", lambda scene: RayCastCamera(scene.model, "abc"), ["config", "'abc'"]),
    ("camera seed", lambda scene: RayCastCamera(scene.model, CameraConfig(), seed=None), ["seed", "None"]),
    ("camera model", lambda scene: make_camera("abc", CameraConfig()), ["model", "'abc'"]),
]


@pytest.mark.parametrize(("argument", "call", "expected"), OTHER_CASES, ids=[c[0] for c in OTHER_CASES])
def test_bad_argument_of_the_lab_and_the_map_raises_the_package_error(scene, argument, call, expected):
    with pytest.raises(HarvestQPError) as info:
        call(scene)
    for text in expected:
        assert text in str(info.value), (str(info.value), text)
