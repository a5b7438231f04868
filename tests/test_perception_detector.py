"""Detection and IPPE pose on rendered images; the mirror-solution choice as pure maths."""

from __future__ import annotations

import math

import cv2
import numpy as np

from iorthand.geometry import compose, rot_x, rot_y, rotation_angle, translation, translation_distance
from iorthand_edge.perception.config import DetectorConfig, SyntheticCameraConfig
from iorthand_edge.perception.detector import (
    choose_ippe_solution,
    detect_markers,
    estimate_marker_pose,
    make_aruco_detector,
)
from iorthand_edge.perception.synthetic import camera_matrix, degrade, marker_texture, render

K = camera_matrix(SyntheticCameraConfig())
DICTIONARY = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)


def rendered(t_camera_marker: np.ndarray, marker_id: int = 5, size: float = 0.045, seed: int = 0) -> np.ndarray:
    image = render([(marker_texture(DICTIONARY, marker_id, size), t_camera_marker)], K, (640, 480), 150, 3)
    return degrade(image, 0.6, 2.0, np.random.default_rng(seed))


def test_detects_and_estimates_pose_within_a_millimetre_at_30_cm() -> None:
    truth = compose(translation(0.02, -0.01, 0.3), rot_x(math.pi + 0.3), rot_y(0.2))
    detections = detect_markers(make_aruco_detector(DetectorConfig()), rendered(truth))
    assert [d.id for d in detections] == [5]
    assert detections[0].corners.shape == (4, 2)
    estimate = estimate_marker_pose(detections[0].corners, 0.045, K, np.zeros(5), None, corner_sigma=0.25, normal_sigma=0.35)
    assert estimate is not None
    assert translation_distance(estimate.t_camera_marker, truth) < 0.0015
    assert math.degrees(rotation_angle(estimate.t_camera_marker, truth)) < 1.0
    assert 60 < estimate.pixel_size < 120
    assert estimate.reprojection_error < 0.5


class _DetectorReturning:
    """Stands in for ArucoDetector to return ids in OpenCV 5's (N,) shape or 4.x's (N, 1)."""

    def __init__(self, ids: np.ndarray | None) -> None:
        self.ids = ids

    def detectMarkers(self, _image: np.ndarray) -> tuple:
        count = 0 if self.ids is None else len(self.ids)
        corners = tuple(np.full((1, 4, 2), float(i), dtype=np.float32) for i in range(count))
        return corners, self.ids, ()


def test_ids_shape_agnostic() -> None:
    for ids in (np.array([4, 9], dtype=np.int32), np.array([[4], [9]], dtype=np.int32)):
        found = detect_markers(_DetectorReturning(ids), np.zeros((4, 4), np.uint8))  # type: ignore[arg-type]
        assert [(d.id, d.corners.shape) for d in found] == [(4, (4, 2)), (9, (4, 2))]
    assert detect_markers(_DetectorReturning(None), np.zeros((4, 4), np.uint8)) == []  # type: ignore[arg-type]


def test_ippe_choice_uses_error_when_clear_and_normal_when_ambiguous() -> None:
    facing = rot_x(math.pi)[:3, :3]  # marker +z towards the camera (camera −z)
    mirror = rot_x(math.pi + 0.6)[:3, :3]
    expected = np.array([0.0, 0.0, -1.0])
    # Residuals 0.1 vs 0.5 px² with 0.05 px corner noise: the corners decide, against the prior.
    best, ambiguous, other = choose_ippe_solution([mirror, facing], [0.1, 0.5], 0.05, expected, 0.35)
    assert (best, ambiguous) == (0, False) and other < 1e-6
    # Residuals 0.1 vs 0.15 px² with 0.3 px noise: the corners cannot tell, the expected normal decides.
    best, ambiguous, other = choose_ippe_solution([mirror, facing], [0.1, 0.15], 0.3, expected, 0.35)
    assert (best, ambiguous) == (1, True) and other < 0.5
    assert choose_ippe_solution([facing], [0.3], 0.05, expected, 0.35) == (0, False, 0.0)


def test_far_small_marker_resolved_by_expected_normal() -> None:
    """A small marker far away: IPPE's two mirror solutions fit almost equally well and the lower-error one is
    often the wrong one; the expected normal picks the right one."""
    truth = compose(translation(0.0, 0.0, 0.9), rot_x(math.pi + 0.2))
    detector = make_aruco_detector(DetectorConfig())
    by_normal, by_error = [], []
    for seed in range(4):
        detections = detect_markers(detector, rendered(truth, size=0.025, seed=seed))
        assert detections
        corners = detections[0].corners
        chosen = estimate_marker_pose(corners, 0.025, K, np.zeros(5), truth[:3, 2], corner_sigma=0.25, normal_sigma=0.35)
        # A prior so wide that it says nothing: the reprojection error alone chooses.
        error_only = estimate_marker_pose(corners, 0.025, K, np.zeros(5), truth[:3, 2], corner_sigma=0.25, normal_sigma=1e6)
        assert chosen is not None and error_only is not None and chosen.ambiguous
        by_normal.append(math.degrees(rotation_angle(chosen.t_camera_marker, truth)))
        by_error.append(math.degrees(rotation_angle(error_only.t_camera_marker, truth)))
    assert max(by_error) > 14.0, "the test did not reach a case where the error alone picks the mirror"
    assert max(by_normal) < 10.0
