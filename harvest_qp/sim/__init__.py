"""MuJoCo simulation of the paper's lab: vine scene, UR5e-like actuation, RGB-D camera, F/T sensor.

Typical use::

    from harvest_qp.sim import SimRobot, VineSceneParams
    from harvest_qp.runtime.runner import run_episode

    robot = SimRobot(VineSceneParams.sample(seed=3), seed=3)  # or SimRobot() for the paper's setup
    result = run_episode(robot, controller, duration=10.0, log_path="episode.npz")
"""

from harvest_qp.sim.actuation import ActuationConfig, SpeedjServo
from harvest_qp.sim.camera import CameraConfig, DepthCamera, OpenGLCamera, RayCastCamera, make_camera
from harvest_qp.sim.force import ForceSensorConfig, WristForceSensor
from harvest_qp.sim.robot import SensorFaults, SimRobot, SimulationError
from harvest_qp.sim.scene import LEAF_LAYOUT, PARAM_RANGES, VineScene, VineSceneParams, build_vine_scene

__all__ = [
    "ActuationConfig",
    "CameraConfig",
    "DepthCamera",
    "ForceSensorConfig",
    "LEAF_LAYOUT",
    "OpenGLCamera",
    "PARAM_RANGES",
    "RayCastCamera",
    "SensorFaults",
    "SimRobot",
    "SimulationError",
    "SpeedjServo",
    "VineScene",
    "VineSceneParams",
    "WristForceSensor",
    "build_vine_scene",
    "make_camera",
]
