"""ArUco detection and per-marker pose (IPPE_SQUARE), with the choice between IPPE's two mirror solutions.

The maths (:func:`choose_ippe_solution`, :func:`marker_object_points`) is free of I/O. The code is written
for both OpenCV 4.x (ids of shape (N, 1)) and 5.x (ids of shape (N,)).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand.geometry import Matrix, make_transform

from .config import CORNER_REFINEMENTS, DetectorConfig


@dataclass
class Detection:
    id: int
    corners: NDArray[np.float64]  # 4×2 px: top-left, top-right, bottom-right, bottom-left of the marker


@dataclass
class MarkerPoseEstimate:
    t_camera_marker: Matrix
    reprojection_error: float  # RMS, px
    pixel_size: float  # mean side length, px
    ambiguous: bool  # the expected normal, not the reprojection error, chose the solution


def make_aruco_detector(config: DetectorConfig) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = CORNER_REFINEMENTS[config.corner_refinement]
    params.cornerRefinementWinSize = config.corner_refinement_window
    params.adaptiveThreshWinSizeMin = config.adaptive_window_min
    params.adaptiveThreshWinSizeMax = config.adaptive_window_max
    params.adaptiveThreshWinSizeStep = config.adaptive_window_step
    params.minMarkerPerimeterRate = config.min_marker_perimeter_rate
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.dictionary))
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_markers(detector: cv2.aruco.ArucoDetector, gray: np.ndarray) -> list[Detection]:
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return []
    # reshape(-1) accepts (N,) from OpenCV 5 as well as (N, 1) from 4.x; corners likewise (1, 4, 2) or (4, 2).
    return [
        Detection(int(i), np.asarray(c, dtype=np.float64).reshape(4, 2))
        for i, c in zip(np.asarray(ids).reshape(-1), corners, strict=True)
    ]


def marker_object_points(size: float) -> NDArray[np.float64]:
    """The marker's corners in its own frame (x right, y up, z out of the printed face), detector order."""
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def choose_ippe_solution(
    rotations: list[Matrix], errors: list[float], expected_normal: ArrayLike, ambiguity_ratio: float
) -> tuple[int, bool]:
    """Index of the IPPE solution to keep, and whether the choice was ambiguous.

    ``expected_normal`` is where the marker's +z should point, in the camera frame. When the reprojection
    errors differ by more than ``ambiguity_ratio`` the smaller one wins; otherwise (small or far markers,
    where the two mirror poses fit the corners equally well) the one whose normal is closest to the
    expected normal wins. "Closest to the previous output" is deliberately not used: it locks onto a wrong
    solution once it has been chosen.
    """
    best = int(np.argmin(errors))
    if len(rotations) < 2:
        return best, False
    other = 1 - best
    if errors[other] > ambiguity_ratio * max(errors[best], 1e-9):
        return best, False
    normal = np.asarray(expected_normal, dtype=float)
    alignment = [float(r[:, 2] @ normal) for r in rotations[:2]]
    return int(np.argmax(alignment)), True


def estimate_marker_pose(
    corners: NDArray[np.float64],
    size: float,
    camera_matrix: NDArray[np.float64],
    dist_coeffs: NDArray[np.float64],
    expected_normal_camera: NDArray[np.float64] | None,
    ambiguity_ratio: float,
) -> MarkerPoseEstimate | None:
    """T_camera_marker from the four corners; None when PnP finds no solution.

    ``expected_normal_camera`` None means "facing the camera" (the normal points from the marker towards it).
    """
    image_points = corners.reshape(4, 1, 2)
    n, rvecs, tvecs, errors = cv2.solvePnPGeneric(
        marker_object_points(size), image_points, camera_matrix, dist_coeffs, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    if n == 0:
        return None
    rotations = [cv2.Rodrigues(r)[0] for r in rvecs]
    error_list = [float(e) for e in np.asarray(errors).reshape(-1)]
    if expected_normal_camera is None:
        towards_camera = -np.asarray(tvecs[0], dtype=float).reshape(3)
        expected_normal_camera = towards_camera / np.linalg.norm(towards_camera)
    chosen, ambiguous = choose_ippe_solution(rotations, error_list, expected_normal_camera, ambiguity_ratio)
    t_camera_marker = make_transform(rotations[chosen], np.asarray(tvecs[chosen], dtype=float).reshape(3))
    sides = np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)
    return MarkerPoseEstimate(t_camera_marker, error_list[chosen], float(sides.mean()), ambiguous)
