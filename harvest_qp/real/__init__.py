"""The field side: two UR5e (``ur-rtde``) and a RealSense D415 behind :class:`~harvest_qp.runtime.RobotInterface`.

* :mod:`harvest_qp.real.ur_rtde_robot` -- :class:`DualUR5eRobot`, the dual arm through ur-rtde;
* :mod:`harvest_qp.real.watchdog` -- the checks run before every command;
* :mod:`harvest_qp.real.realsense` -- :class:`RealSenseSource`, D415 frames as the lab's ``PointCloud``;
* :mod:`harvest_qp.real.stem_detector` -- pluggable stem detectors (default: the red threshold);
* :mod:`harvest_qp.real.calibration` -- hand-eye and base-to-base calibration (OpenCV), YAML files;
* :mod:`harvest_qp.real.cell` -- the cell file (``tasks/real/ur5e.yaml``);
* :mod:`harvest_qp.real.episode` -- ``harvest-qp run CONFIG --robot ur`` and its ``--dry-run``.

The hardware packages (``pip install -e ".[robot]"``: ur-rtde, pyrealsense2, opencv-python-headless)
are imported only where they are used, so the lab never needs them. See docs/real_robots.md.
"""

from harvest_qp.real.errors import CalibrationError, CameraError, RobotConnectionError, WatchdogError

__all__ = ["CalibrationError", "CameraError", "RobotConnectionError", "WatchdogError"]
