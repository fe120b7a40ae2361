"""Camera hand-eye and base-to-base calibration from views of a ChArUco board (OpenCV), in YAML.

Two transforms are estimated (docs/real_robots.md gives the procedure):

* ``hand_eye``: the camera optical frame {C} in the camera arm's flange frame (``cam_flange``),
  from views of a board fixed in the cell while the camera arm moves: ``cv2.calibrateHandEye``
  (eye-in-hand, ``AX = XB``);
* ``grasp_base_in_camera_base``: the grasping arm's base frame in the camera arm's base frame,
  from views of a board clamped to the grasping arm's flange: ``cv2.calibrateRobotWorldHandEye``
  (``AX = ZB``, with the hand-eye transform of the first step).

Both are written to one YAML file (:func:`save_calibration`) that the cell file names; the
real robot reads it with :func:`load_calibration`. All transforms are 4x4, lengths in [m].

The views live in a folder: ``views.yaml`` (the board, the colour intrinsics and one entry per
view: image file, kind ``hand_eye`` or ``bases``, the 12 measured joint positions [rad]) next to
the images (``harvest-qp calibrate capture`` writes it; anything else that writes the same file
will do).
"""

from __future__ import annotations

import datetime
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike, NDArray

from harvest_qp.exceptions import InvalidInputError
from harvest_qp.real.errors import CalibrationError, missing_package
from harvest_qp.validation import as_rigid_transform

__all__ = [
    "Board",
    "Calibration",
    "HandEyeView",
    "load_calibration",
    "save_calibration",
    "detect_board",
    "solve_hand_eye",
    "solve_bases",
    "calibrate_folder",
    "flange_poses",
    "pose_error",
    "check_hand_eye",
    "MAX_HAND_EYE_DISTANCE",
]

FORMAT = "harvest_qp calibration 1"


def _cv2():
    try:
        import cv2
    except ImportError:
        raise missing_package("opencv-python-headless", "calibration") from None
    return cv2


def _transform(R: NDArray, t: NDArray) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, float).reshape(3, 3)
    T[:3, 3] = np.asarray(t, float).ravel()
    return T


def _inverse(T: NDArray) -> NDArray[np.float64]:
    R, t = T[:3, :3], T[:3, 3]
    return _transform(R.T, -R.T @ t)


def pose_error(A: NDArray, B: NDArray) -> tuple[float, float]:
    """(position difference [m], rotation angle between them [deg]) of two 4x4 poses."""
    dR = A[:3, :3].T @ B[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3])), float(angle)


#: Farthest a camera on the camera arm's flange can sit from it [m] (the description's is 0.08 m away).
MAX_HAND_EYE_DISTANCE = 0.5


def check_hand_eye(hand_eye: ArrayLike) -> NDArray[np.float64]:
    """``hand_eye`` as a rigid 4x4 transform within :data:`MAX_HAND_EYE_DISTANCE` of the flange.

    Raises:
        CalibrationError: not a finite rigid transform, or a camera farther from the flange than
            any mount could put it (e.g. millimetres written as metres).
    """
    try:
        T = as_rigid_transform(hand_eye, "hand_eye")
    except InvalidInputError as err:
        raise CalibrationError(str(err)) from None
    distance = float(np.linalg.norm(T[:3, 3]))
    if distance > MAX_HAND_EYE_DISTANCE:
        raise CalibrationError(
            f"hand_eye puts the camera {distance:.6g} m from the flange (translation {T[:3, 3].tolist()}); a camera "
            f"on the flange is within {MAX_HAND_EYE_DISTANCE} m: check the calibration's units [m]")
    return T


@dataclass(frozen=True)
class Board:
    """A ChArUco board: ``squares`` (columns, rows), square and marker edge [m], ArUco dictionary."""

    squares: tuple[int, int] = (7, 5)
    square: float = 0.04
    marker: float = 0.03
    dictionary: str = "DICT_5X5_100"

    def __post_init__(self) -> None:
        if len(self.squares) != 2 or min(self.squares) < 3:
            raise CalibrationError(f"board.squares must be (columns, rows) >= 3 each, got {self.squares!r}")
        if not 0 < self.marker < self.square:
            raise CalibrationError(f"board.marker ({self.marker} m) must be > 0 and below board.square "
                                   f"({self.square} m)")

    def opencv(self):
        """The ``cv2.aruco.CharucoBoard``."""
        cv2 = _cv2()
        try:
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        except AttributeError:
            raise CalibrationError(f"board.dictionary {self.dictionary!r} is not an OpenCV ArUco dictionary") from None
        return cv2.aruco.CharucoBoard(tuple(int(n) for n in self.squares), float(self.square), float(self.marker),
                                      dictionary)

    def image(self, pixels_per_square: int = 200, margin: int = 100) -> NDArray[np.uint8]:
        """The board to print (grey image): print it at the configured square size."""
        cols, rows = self.squares
        return self.opencv().generateImage((cols * pixels_per_square + 2 * margin,
                                            rows * pixels_per_square + 2 * margin), marginSize=margin)

    def as_dict(self) -> dict[str, Any]:
        return {"squares": list(self.squares), "square": self.square, "marker": self.marker,
                "dictionary": self.dictionary}


@dataclass
class Calibration:
    """What the real cell needs beyond the robot description.

    Attributes:
        hand_eye: (4, 4) camera optical frame {C} (z forward, x right, y down) in the camera
            arm's flange frame ``cam_flange`` [m].
        grasp_base_in_camera_base: (4, 4) measured grasping-arm base in the camera-arm base, or
            None when not calibrated; the robot description's value is used by the controller,
            this one checks it (:meth:`base_discrepancy`).
        info: free-form provenance (date, number of views, residuals).
    """

    hand_eye: NDArray[np.float64]
    grasp_base_in_camera_base: NDArray[np.float64] | None = None
    info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("hand_eye", "grasp_base_in_camera_base"):
            value = getattr(self, name)
            if value is None and name != "hand_eye":
                continue
            T = np.asarray(value, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise CalibrationError(f"calibration {name} must be a finite 4x4 transform, got {value!r}")
            R = T[:3, :3]
            if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0.0 or not np.allclose(
                T[3], [0, 0, 0, 1]
            ):
                raise CalibrationError(f"calibration {name} is not a rigid transform (rotation not orthonormal "
                                       f"or last row not 0 0 0 1): {T.tolist()}")
            setattr(self, name, check_hand_eye(T) if name == "hand_eye" else T)

    def base_discrepancy(self) -> tuple[float, float] | None:
        """(position [m], angle [deg]) between the calibrated and the described grasping-arm base
        (in the camera-arm base), or None when not calibrated."""
        if self.grasp_base_in_camera_base is None:
            return None
        from harvest_qp.robot.description import CAMERA_ARM, GRASP_ARM, mount_transform

        described = _inverse(mount_transform(CAMERA_ARM)) @ mount_transform(GRASP_ARM)
        return pose_error(described, self.grasp_base_in_camera_base)


def save_calibration(path: str | Path, calibration: Calibration) -> Path:
    """Write ``calibration`` as YAML (``yaml.safe_dump``)."""
    path = Path(path)
    data: dict[str, Any] = {
        "format": FORMAT,
        "hand_eye": np.round(calibration.hand_eye, 12).tolist(),
        "grasp_base_in_camera_base": (None if calibration.grasp_base_in_camera_base is None
                                      else np.round(calibration.grasp_base_in_camera_base, 12).tolist()),
        "info": calibration.info,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# harvest_qp calibration (harvest-qp calibrate solve): transforms 4x4, lengths [m]\n"
              "# hand_eye: camera optical frame (z forward, x right, y down) in the camera arm's flange frame\n"
              "# grasp_base_in_camera_base: grasping arm base in the camera arm base (a check of the description)\n")
    path.write_text(header + yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration file (``yaml.safe_load``).

    Raises:
        CalibrationError: missing file, not a calibration, malformed transform (one line, the path named).
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except OSError as err:
        raise CalibrationError(f"cannot read the calibration file {path}: {err.strerror}") from None
    except yaml.YAMLError as err:
        raise CalibrationError(f"{path}: not valid YAML: {' '.join(str(err).split())}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT or "hand_eye" not in data:
        raise CalibrationError(f"{path}: not a harvest_qp calibration file (expected format: {FORMAT!r} and hand_eye)")
    try:
        return Calibration(np.asarray(data["hand_eye"], float),
                           None if data.get("grasp_base_in_camera_base") is None
                           else np.asarray(data["grasp_base_in_camera_base"], float),
                           dict(data.get("info") or {}))
    except (ValueError, TypeError) as err:
        raise CalibrationError(f"{path}: {err}") from None
    except CalibrationError as err:
        raise CalibrationError(f"{path}: {err}") from None


def detect_board(image: NDArray[np.uint8], board: Board, K: NDArray, dist: NDArray | None = None,
                 min_corners: int = 6, max_rms: float = 1.0) -> NDArray[np.float64] | None:
    """The board's pose (4x4) in the camera optical frame from one image, or None if not found.

    ChArUco corners (``cv2.aruco.CharucoDetector``), then ``cv2.solvePnP`` (IPPE, planar) refined
    by ``cv2.solvePnPRefineLM`` with the intrinsics ``K`` (3x3) and distortion ``dist`` (OpenCV
    order; None: none). Views whose corners lie on one line, or whose reprojection error exceeds
    ``max_rms`` [px], give None.
    """
    cv2 = _cv2()
    grey = image if image.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    cv_board = board.opencv()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board).detectBoard(grey)
    if corners is None or ids is None or len(ids) < min_corners:
        return None
    obj, img = cv_board.matchImagePoints(corners, ids)
    obj, img = obj.reshape(-1, 3).astype(np.float64), img.reshape(-1, 2).astype(np.float64)
    # Corners along one line (a single visible row) leave the pose undetermined.
    if np.linalg.svd(obj[:, :2] - obj[:, :2].mean(axis=0), compute_uv=False)[1] < 0.5 * board.square:
        return None
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    K = np.asarray(K, float)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)  # planar target
    if not ok or not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    if np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1))) > max_rms:
        return None
    return _transform(cv2.Rodrigues(rvec)[0], tvec)


def _split(transforms: Sequence[NDArray]) -> tuple[list[NDArray], list[NDArray]]:
    return [np.ascontiguousarray(T[:3, :3]) for T in transforms], [np.ascontiguousarray(T[:3, 3:4]) for T in transforms]


def solve_hand_eye(flange_in_base: Sequence[NDArray], board_in_camera: Sequence[NDArray]) -> NDArray[np.float64]:
    """The camera frame in the flange frame (4x4) from paired views (eye-in-hand, ``cv2.calibrateHandEye``).

    Args:
        flange_in_base: the camera arm's flange pose in its base for each view (forward kinematics).
        board_in_camera: the (fixed) board's pose in the camera frame for each view (:func:`detect_board`).
    """
    cv2 = _cv2()
    if len(flange_in_base) != len(board_in_camera) or len(flange_in_base) < 3:
        raise CalibrationError(f"hand-eye calibration needs >= 3 paired views; got {len(flange_in_base)} robot "
                               f"poses and {len(board_in_camera)} board poses")
    R_g, t_g = _split(flange_in_base)
    R_t, t_t = _split(board_in_camera)
    R, t = cv2.calibrateHandEye(R_g, t_g, R_t, t_t, method=cv2.CALIB_HAND_EYE_PARK)
    if not np.all(np.isfinite(R)) or not np.all(np.isfinite(t)):
        raise CalibrationError("cv2.calibrateHandEye returned no solution: the views need rotations about "
                               "at least two different axes")
    return _transform(R, t)


def solve_bases(camera_flange_in_base: Sequence[NDArray], hand_eye: NDArray, board_in_camera: Sequence[NDArray],
                grasp_flange_in_base: Sequence[NDArray]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The grasping-arm base in the camera-arm base, and the board in the grasping flange (both 4x4).

    The board is clamped to the grasping arm's flange; each view gives it in the camera-arm base
    (camera arm's forward kinematics, ``hand_eye``, detection) and the grasping flange in its own
    base: ``cv2.calibrateRobotWorldHandEye`` solves ``AX = ZB`` for both unknowns.
    """
    cv2 = _cv2()
    n = len(board_in_camera)
    if not (len(camera_flange_in_base) == n == len(grasp_flange_in_base)) or n < 3:
        raise CalibrationError(f"base-to-base calibration needs >= 3 views with both arms' poses; got {n} board "
                               f"poses, {len(camera_flange_in_base)} and {len(grasp_flange_in_base)} arm poses")
    # OpenCV's frames: "world" = camera-arm base, "camera" = board, "gripper" = grasp flange, "base" = grasp base.
    world2board = [_inverse(Tc @ hand_eye @ Tb) for Tc, Tb in zip(camera_flange_in_base, board_in_camera)]
    base2flange = [_inverse(T) for T in grasp_flange_in_base]
    R_w, t_w = _split(world2board)
    R_b, t_b = _split(base2flange)
    R_bw, t_bw, R_gc, t_gc = cv2.calibrateRobotWorldHandEye(R_w, t_w, R_b, t_b)
    base_in_world = _transform(R_bw, t_bw)
    board_in_flange = _inverse(_transform(R_gc, t_gc))
    return base_in_world, board_in_flange


@dataclass(frozen=True)
class HandEyeView:
    """One captured view: the image file, its kind (``hand_eye`` or ``bases``), the 12 joint positions [rad]."""

    image: str
    kind: str
    q: tuple[float, ...]


def flange_poses(q: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each arm's flange pose in its own base (4x4) at the 12 joint positions ``q``, from the robot description."""
    from harvest_qp.configuration import Configuration
    from harvest_qp.robot.description import CAMERA_ARM, GRASP_ARM, mount_transform

    configuration = Configuration.dual_ur5e(np.asarray(q, float))
    out = []
    for prefix in (CAMERA_ARM, GRASP_ARM):
        pose = configuration.frame_pose(prefix + "flange")
        out.append(_inverse(mount_transform(prefix)) @ _transform(pose.rotation, pose.translation))
    return out[0], out[1]


def calibrate_folder(folder: str | Path) -> Calibration:
    """Detect the board in every view of ``folder/views.yaml`` and solve both transforms.

    Raises:
        CalibrationError: unreadable folder, too few views with a detected board.
    """
    cv2 = _cv2()
    folder = Path(folder)
    index = folder / "views.yaml"
    try:
        data = yaml.safe_load(index.read_text(encoding="utf-8"))
        board = Board(**{k: tuple(v) if k == "squares" else v for k, v in data["board"].items()})
        K = np.asarray(data["intrinsics"]["K"], float).reshape(3, 3)
        dist = np.asarray(data["intrinsics"].get("dist") or np.zeros(5), float)
        views = [HandEyeView(str(v["image"]), str(v["kind"]), tuple(float(x) for x in v["q"])) for v in data["views"]]
    except OSError as err:
        raise CalibrationError(f"cannot read {index}: {err.strerror}") from None
    except (KeyError, TypeError, ValueError, AttributeError, yaml.YAMLError) as err:
        raise CalibrationError(f"{index}: expected board, intrinsics {{K, dist}} and views [{{image, kind, q}}]: "
                               f"{' '.join(str(err).split())}") from None
    found: dict[str, list[tuple[NDArray, NDArray, NDArray]]] = {"hand_eye": [], "bases": []}
    missed = []
    for view in views:
        if view.kind not in found or len(view.q) != 12:
            raise CalibrationError(f"{index}: view {view.image}: kind must be hand_eye or bases and q 12 joint "
                                   f"positions [rad]; got {view.kind!r} and {len(view.q)} values")
        image = cv2.imread(str(folder / view.image), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise CalibrationError(f"cannot read the image {folder / view.image}")
        pose = detect_board(image, board, K, dist)
        if pose is None:
            missed.append(view.image)
            continue
        camera_flange, grasp_flange = flange_poses(np.array(view.q))
        found[view.kind].append((camera_flange, pose, grasp_flange))
    hand = found["hand_eye"]
    if len(hand) < 3:
        raise CalibrationError(f"{index}: the board was found in {len(hand)} hand_eye view(s), 3 or more are needed "
                               f"(board not found in: {', '.join(missed) or 'none'})")
    X = solve_hand_eye([v[0] for v in hand], [v[1] for v in hand])
    info: dict[str, Any] = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                            "hand_eye_views": len(hand), "views_without_board": missed, "board": board.as_dict()}
    # Consistency: the fixed board in the camera-arm base from each view; its spread is the residual.
    board_in_base = [v[0] @ X @ v[1] for v in hand]
    spread = [pose_error(board_in_base[0], T) for T in board_in_base[1:]]
    info["hand_eye_board_spread_mm"] = float(1e3 * max(s[0] for s in spread))
    info["hand_eye_board_spread_deg"] = float(max(s[1] for s in spread))
    bases = found["bases"]
    Y = None
    if len(bases) >= 3:
        Y, Z = solve_bases([v[0] for v in bases], X, [v[1] for v in bases], [v[2] for v in bases])
        info["bases_views"] = len(bases)
        info["board_in_grasp_flange"] = np.round(Z, 9).tolist()
    calibration = Calibration(X, Y, info)
    discrepancy = calibration.base_discrepancy()
    if discrepancy is not None:
        info["base_vs_description_mm"] = 1e3 * discrepancy[0]
        info["base_vs_description_deg"] = discrepancy[1]
    return calibration
