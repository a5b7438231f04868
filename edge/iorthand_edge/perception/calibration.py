"""Camera intrinsics (ChArUco or chessboard) and eye-in-hand hand-eye calibration; their YAML files.

The solvers take plain arrays and return results with their quality figures; the CLI (``cli.py``) does the
file and camera I/O. Results are saved as YAML with metadata (image size, error, method, number of views,
date, units) and loaded back with :func:`load_intrinsics` / :func:`load_handeye`, which refuse a file made
for another image size.
"""

from __future__ import annotations

import datetime
import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from iorthand.config import ConfigError, load, setting, to_dict
from iorthand.geometry import (
    Matrix,
    compose,
    invert,
    make_transform,
    matrix_to_pose,
    matrix_to_rotvec,
    orthonormalize,
    pose_to_matrix,
    rotation_angle,
)

from .config import check_aruco_dictionary

MIN_INTRINSICS_VIEWS = 10
MIN_HANDEYE_POSES = 5
RECOMMENDED_HANDEYE_POSES = 15
_MIN_VIEW_SPREAD = math.radians(10.0)  # smaller spreads of target orientation leave the focal length unobservable
_MIN_CHARUCO_CORNERS = 6

HANDEYE_METHODS = {
    "tsai": cv2.CALIB_HAND_EYE_TSAI,
    "park": cv2.CALIB_HAND_EYE_PARK,
    "horaud": cv2.CALIB_HAND_EYE_HORAUD,
    "daniilidis": cv2.CALIB_HAND_EYE_DANIILIDIS,
}  # ANDREFF is left out: it disagrees with the other four by far more than their spread.


class CalibrationError(ValueError):
    """A calibration that cannot be made or used; the message says why and what to do."""


# The ``units`` each file is written with (and documented with): a file that says anything else (say, "mm and
# degrees") was written by another tool or edited by hand, and its numbers mean something else. Refused: read
# as metres and radians, a hand-eye in millimetres puts the camera tens of metres from the TCP.
INTRINSICS_UNITS = "camera_matrix and rms in px; target sizes in m"
HANDEYE_UNITS = "m and rad; poses are [x, y, z, rx, ry, rz] with a rotation vector"
# The camera rides on the TCP: a hand-eye translation this long is a file in other units (or a failed solve).
MAX_HANDEYE_TRANSLATION_M = 0.5
# Servo angles of a pan/tilt mount, in rad: a half turn either way (a value beyond is degrees, or another mount).
MAX_SERVO_ANGLE_RAD = math.pi
# A rotation vector's length is its angle, at most a half turn (more is written as the opposite rotation).
_MAX_ROTVEC = math.pi + 1e-6


def _check_units(units: str, expected: str) -> None:
    if units != expected:
        raise ValueError(f"units: the file says {units!r}; iorthand reads only {expected!r} (convert the values and "
                         "write that units string, or recalibrate with `iorthand calibrate`)")


def _check_pose(name: str, pose: list[float]) -> None:
    distance = math.dist(pose[:3], (0.0, 0.0, 0.0))
    if distance >= MAX_HANDEYE_TRANSLATION_M:
        raise ValueError(f"{name}: the camera would be {distance:.3g} m from the TCP (at most "
                         f"{MAX_HANDEYE_TRANSLATION_M:g} m): the translation must be in metres (millimetres?)")
    angle = math.dist(pose[3:], (0.0, 0.0, 0.0))
    if angle > _MAX_ROTVEC:
        raise ValueError(f"{name}: the rotation vector's angle is {angle:.3g}, more than π rad: the rotation must be "
                         "a rotation vector in radians (degrees?)")


# ---------------------------------------------------------------------------------------------------------
# Files


@dataclass
class IntrinsicsCalibration:
    image_width: int = setting(lo=1, hi=8192)
    image_height: int = setting(lo=1, hi=8192)
    camera_matrix: list[list[float]] = setting(length=3)
    dist_coeffs: list[float] = setting(default_factory=lambda: [0.0] * 5)
    rms_px: float = setting(0.0, lo=0.0)
    method: str = ""
    views: int = setting(0, lo=0)
    target: str = ""
    date: str = ""
    units: str = INTRINSICS_UNITS

    def check(self) -> None:
        _check_units(self.units, INTRINSICS_UNITS)
        if any(len(row) != 3 for row in self.camera_matrix):
            raise ValueError("camera_matrix must be 3×3")
        k = np.asarray(self.camera_matrix)
        if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]):
            raise ValueError("camera_matrix must be [[fx,0,cx],[0,fy,cy],[0,0,1]] with positive focal lengths")
        cx, cy = float(k[0, 2]), float(k[1, 2])
        if not (0 < cx < self.image_width and 0 < cy < self.image_height):
            raise ValueError(f"camera_matrix: the principal point ({cx:g}, {cy:g}) px lies outside the "
                             f"{self.image_width}×{self.image_height} image (a matrix for another image size or "
                             "other units)")
        if len(self.dist_coeffs) not in (4, 5, 8, 12, 14):
            raise ValueError(f"dist_coeffs must have 4, 5, 8, 12 or 14 values, got {len(self.dist_coeffs)}")

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.image_width, self.image_height)

    def matrix(self) -> NDArray[np.float64]:
        return np.asarray(self.camera_matrix, dtype=float)

    def distortion(self) -> NDArray[np.float64]:
        return np.asarray(self.dist_coeffs, dtype=float)


@dataclass
class HandEyeCalibration:
    """Eye-in-hand result: T_tcp_camera at the servo angles held during calibration (UR pose vectors)."""

    tcp_camera: list[float] = setting(length=6)
    image_width: int = setting(lo=1, hi=8192)
    image_height: int = setting(lo=1, hi=8192)
    pan: float = setting(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    tilt: float = setting(0.0, lo=-2 * math.pi, hi=2 * math.pi)
    # For people reading the file: the pipeline recomputes it from tcp_camera with the configured mount.
    tilt_camera: list[float] = setting(default_factory=lambda: [0.0] * 6, length=6)
    method: str = ""
    poses: int = setting(0, lo=0)
    residual_translation: float = setting(0.0, lo=0.0)  # m, RMS spread of the target's pose in the base frame
    residual_rotation: float = setting(0.0, lo=0.0)  # rad, likewise
    date: str = ""
    units: str = HANDEYE_UNITS

    def check(self) -> None:
        _check_units(self.units, HANDEYE_UNITS)
        _check_pose("tcp_camera", self.tcp_camera)
        _check_pose("tilt_camera", self.tilt_camera)
        for name, angle in (("pan", self.pan), ("tilt", self.tilt)):
            if abs(angle) > MAX_SERVO_ANGLE_RAD:
                raise ValueError(f"{name}: {angle:g} is beyond ±π: the servo angles must be in radians (degrees?)")

    @property
    def image_size(self) -> tuple[int, int]:
        return (self.image_width, self.image_height)


C = TypeVar("C", IntrinsicsCalibration, HandEyeCalibration)


def _load_for_size(path: Path, cls: type[C], image_size: tuple[int, int] | None) -> C:
    try:
        calibration = load(path, cls)
    except ConfigError as exc:
        raise CalibrationError(f"unusable calibration file: {exc}") from None
    if image_size is not None and calibration.image_size != tuple(image_size):
        w, h = calibration.image_size
        raise CalibrationError(
            f"{path}: made for {w}×{h} images but the camera delivers {image_size[0]}×{image_size[1]}; "
            "recalibrate at this size or set the camera to the calibrated size"
        )
    return calibration


def load_intrinsics(path: Path, image_size: tuple[int, int] | None = None) -> IntrinsicsCalibration:
    """Read an intrinsics file; refuse it if it was made for another image size than ``image_size``."""
    return _load_for_size(path, IntrinsicsCalibration, image_size)


def load_handeye(path: Path, image_size: tuple[int, int] | None = None) -> HandEyeCalibration:
    return _load_for_size(path, HandEyeCalibration, image_size)


def save_calibration(path: Path, calibration: IntrinsicsCalibration | HandEyeCalibration) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    header = f"# iorthand {type(calibration).__name__}, written by `iorthand calibrate`\n"
    path.write_text(
        header + yaml.safe_dump(to_dict(calibration), sort_keys=False, allow_unicode=True), encoding="utf-8"
    )


def _today() -> str:
    return datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")


# ---------------------------------------------------------------------------------------------------------
# Targets


@dataclass
class TargetSpec:
    """A calibration target: a ChArUco board or a plain chessboard (counted in squares; sizes in m)."""

    kind: str = setting("charuco", choices=("charuco", "chessboard"))
    squares_x: int = setting(7, lo=3, hi=100)
    squares_y: int = setting(5, lo=3, hi=100)
    square: float = setting(0.03, lo=0.001, hi=1.0)
    marker: float = setting(0.022, lo=0.001, hi=1.0)  # ChArUco only
    dictionary: str = "DICT_4X4_50"

    def check(self) -> None:
        check_aruco_dictionary(self.dictionary)
        if self.kind == "charuco" and self.marker >= self.square:
            raise ValueError(f"marker ({self.marker:g} m) must be smaller than square ({self.square:g} m)")

    def describe(self) -> str:
        size = f"{self.squares_x}×{self.squares_y} squares of {self.square * 1000:g} mm"
        if self.kind == "chessboard":
            return f"chessboard, {size}"
        return f"ChArUco {self.dictionary}, {size}, markers {self.marker * 1000:g} mm"

    def charuco_board(self) -> cv2.aruco.CharucoBoard:
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square, self.marker, dictionary)


class TargetFinder:
    """Finds the target's corners in an image: (object points N×3 in the target frame, image points N×2)."""

    def __init__(self, spec: TargetSpec) -> None:
        self.spec = spec
        if spec.kind == "charuco":
            self._charuco = cv2.aruco.CharucoDetector(spec.charuco_board())

    def find(self, gray: NDArray[np.uint8]) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        if self.spec.kind == "charuco":
            corners, ids, _, _ = self._charuco.detectBoard(gray)
            if ids is None or len(ids) < _MIN_CHARUCO_CORNERS:
                return None
            obj, img = self._charuco.getBoard().matchImagePoints(corners, ids)
        else:
            pattern = (self.spec.squares_x - 1, self.spec.squares_y - 1)
            found, corners = cv2.findChessboardCorners(gray, pattern, flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
            if not found:
                return None
            criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 1e-3)
            img = cv2.cornerSubPix(gray, corners, (5, 5), (-1, -1), criteria)
            grid = np.mgrid[0 : pattern[0], 0 : pattern[1]].T.reshape(-1, 2) * self.spec.square
            obj = np.hstack([grid, np.zeros((len(grid), 1))])
        # OpenCV 5 drops the middle dimension of these arrays; 4.x keeps it: normalise both to N×3 / N×2.
        return np.asarray(obj, dtype=np.float64).reshape(-1, 3), np.asarray(img, dtype=np.float64).reshape(-1, 2)


# ---------------------------------------------------------------------------------------------------------
# Intrinsics


@dataclass
class IntrinsicsResult:
    calibration: IntrinsicsCalibration
    view_errors: list[float]  # RMS reprojection error per view, px


def calibrate_intrinsics(
    views: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    image_size: tuple[int, int],
    target: TargetSpec,
    images_total: int | None = None,
) -> IntrinsicsResult:
    """Calibrate from the target's corners in each view; refuse sets that cannot constrain the camera."""
    total = len(views) if images_total is None else images_total
    if len(views) < MIN_INTRINSICS_VIEWS:
        raise CalibrationError(
            f"the target was found in {len(views)} of {total} images; at least {MIN_INTRINSICS_VIEWS} views are "
            "needed (show the whole board, from different angles and across the image)"
        )
    object_points = [o.astype(np.float32).reshape(-1, 1, 3) for o, _ in views]
    image_points = [i.astype(np.float32).reshape(-1, 1, 2) for _, i in views]
    try:
        rms, k, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, image_size, None, None)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV could not calibrate from these views: {exc.err}") from None
    normals = [cv2.Rodrigues(r)[0][:, 2] for r in rvecs]
    spread = max(math.acos(float(np.clip(a @ b, -1.0, 1.0))) for a, b in itertools.combinations(normals, 2))
    if spread < _MIN_VIEW_SPREAD:
        raise CalibrationError(
            f"degenerate views: the target's orientation varies by only {math.degrees(spread):.1f}° across them "
            f"(need at least {math.degrees(_MIN_VIEW_SPREAD):.0f}°); tilt the board by 20–40° in different directions"
        )
    view_errors = []
    for obj, img, r, t in zip(object_points, image_points, rvecs, tvecs, strict=True):
        projected, _ = cv2.projectPoints(obj, r, t, k, dist)
        view_errors.append(float(np.sqrt(np.mean(np.sum((projected - img) ** 2, axis=-1)))))
    calibration = IntrinsicsCalibration(
        image_width=image_size[0],
        image_height=image_size[1],
        camera_matrix=k.tolist(),
        dist_coeffs=np.asarray(dist).reshape(-1).tolist(),
        rms_px=float(rms),
        method="cv2.calibrateCamera (pinhole, k1 k2 p1 p2 k3)",
        views=len(views),
        target=target.describe(),
        date=_today(),
    )
    return IntrinsicsResult(calibration, view_errors)


# ---------------------------------------------------------------------------------------------------------
# Hand-eye (eye-in-hand): the camera rides on the TCP, the target is fixed in the base frame.


def target_pose(
    obj: NDArray[np.float64], img: NDArray[np.float64], k: NDArray[np.float64], dist: NDArray[np.float64]
) -> Matrix:
    """T_camera_target from the target's corners in one image."""
    ok, rvec, tvec = cv2.solvePnP(obj.reshape(-1, 1, 3), img.reshape(-1, 1, 2), k, dist)
    if not ok:
        raise CalibrationError("solvePnP found no pose for the target")
    return make_transform(cv2.Rodrigues(rvec)[0], np.asarray(tvec).reshape(3))


def _park_martin(t_base_tcp: list[Matrix], t_camera_target: list[Matrix]) -> Matrix:
    """AX = XB by Park & Martin (1994), for OpenCV builds without calibrateHandEye (5.0)."""
    a_list, b_list = [], []
    for i, j in itertools.combinations(range(len(t_base_tcp)), 2):
        a_list.append(compose(invert(t_base_tcp[i]), t_base_tcp[j]))
        b_list.append(compose(t_camera_target[i], invert(t_camera_target[j])))
    m = sum(
        np.outer(matrix_to_rotvec(b[:3, :3]), matrix_to_rotvec(a[:3, :3])) for a, b in zip(a_list, b_list, strict=True)
    )
    eigenvalues, eigenvectors = np.linalg.eigh(m.T @ m)
    rotation = orthonormalize(eigenvectors @ np.diag(eigenvalues**-0.5) @ eigenvectors.T @ m.T)
    lhs = np.vstack([a[:3, :3] - np.eye(3) for a in a_list])
    rhs = np.concatenate([rotation @ b[:3, 3] - a[:3, 3] for a, b in zip(a_list, b_list, strict=True)])
    translation, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
    return make_transform(rotation, translation)


@dataclass
class HandEyeResult:
    t_tcp_camera: Matrix
    method: str
    residual_translation: float  # m
    residual_rotation: float  # rad


def calibrate_handeye(t_base_tcp: list[Matrix], t_camera_target: list[Matrix], method: str = "tsai") -> HandEyeResult:
    """T_tcp_camera from robot poses and target observations taken at the same instants.

    The residuals are the RMS spread of T_base_target = T_base_tcp · T_tcp_camera · T_camera_target over the
    poses: the target did not move, so a good calibration makes them agree.
    """
    n = len(t_base_tcp)
    if n != len(t_camera_target):
        raise CalibrationError(f"{n} robot poses but {len(t_camera_target)} target observations")
    if n < MIN_HANDEYE_POSES:
        raise CalibrationError(
            f"{n} poses are too few for hand-eye calibration (need at least {MIN_HANDEYE_POSES}, "
            f"{RECOMMENDED_HANDEYE_POSES} recommended, with ≥ 30° rotations between them)"
        )
    spread = max(rotation_angle(a, b) for a, b in itertools.combinations(t_base_tcp, 2))
    if spread < math.radians(10.0):
        raise CalibrationError(
            f"degenerate poses: the tool rotates by only {math.degrees(spread):.1f}° between them; hand-eye needs "
            "rotations about different axes (≥ 30° between poses)"
        )
    if method not in HANDEYE_METHODS:
        raise CalibrationError(f"unknown hand-eye method {method!r} (use one of {sorted(HANDEYE_METHODS)})")
    if hasattr(cv2, "calibrateHandEye"):
        r, t = cv2.calibrateHandEye(
            [p[:3, :3] for p in t_base_tcp],
            [p[:3, 3] for p in t_base_tcp],
            [p[:3, :3] for p in t_camera_target],
            [p[:3, 3] for p in t_camera_target],
            method=HANDEYE_METHODS[method],
        )
        x = make_transform(orthonormalize(r), np.asarray(t).reshape(3))
        used = f"cv2.calibrateHandEye {method.upper()}"
    else:
        x = _park_martin(t_base_tcp, t_camera_target)
        used = "Park-Martin (numpy; this OpenCV has no calibrateHandEye)"
    targets = [compose(a, x, b) for a, b in zip(t_base_tcp, t_camera_target, strict=True)]
    positions = np.stack([t[:3, 3] for t in targets])
    mean_rotation = orthonormalize(np.sum([t[:3, :3] for t in targets], axis=0))
    residual_t = float(np.sqrt(np.mean(np.sum((positions - positions.mean(axis=0)) ** 2, axis=1))))
    residual_r = float(np.sqrt(np.mean([rotation_angle(t, mean_rotation) ** 2 for t in targets])))
    return HandEyeResult(x, used, residual_t, residual_r)


def handeye_calibration(
    result: HandEyeResult, pan: float, tilt: float, t_tilt_camera: Matrix, image_size: tuple[int, int], poses: int
) -> HandEyeCalibration:
    return HandEyeCalibration(
        tcp_camera=matrix_to_pose(result.t_tcp_camera).tolist(),
        pan=pan,
        tilt=tilt,
        tilt_camera=matrix_to_pose(t_tilt_camera).tolist(),
        image_width=image_size[0],
        image_height=image_size[1],
        method=result.method,
        poses=poses,
        residual_translation=result.residual_translation,
        residual_rotation=result.residual_rotation,
        date=_today(),
    )


def poses_file_entry(image: str, t_base_tcp: Matrix) -> dict[str, Any]:
    return {"image": image, "tcp_pose": [round(float(v), 9) for v in matrix_to_pose(t_base_tcp)]}


def read_poses_file(path: Path) -> tuple[list[tuple[Path, Matrix]], float, float]:
    """A hand-eye dataset's ``poses.yaml``: ``pan``, ``tilt`` (rad) and a list of {image, tcp_pose} where
    tcp_pose is the UR pose [x, y, z, rx, ry, rz] (rotation vector) at the moment the image was taken."""
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise CalibrationError(f"{path}: cannot read the poses file ({exc})") from None
    if not isinstance(data, dict) or not isinstance(data.get("views"), list):
        raise CalibrationError(f"{path}: expected a mapping with 'pan', 'tilt' and a 'views' list")
    views = []
    for i, entry in enumerate(data["views"]):
        try:
            views.append((path.parent / str(entry["image"]), pose_to_matrix(entry["tcp_pose"])))
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(
                f"{path}: views[{i}]: expected image and tcp_pose [x,y,z,rx,ry,rz] ({exc})"
            ) from None
    try:
        return views, float(data.get("pan", 0.0)), float(data.get("tilt", 0.0))
    except (TypeError, ValueError):
        raise CalibrationError(f"{path}: pan and tilt must be numbers (rad)") from None
