"""Perception configuration: camera source, detector, markers, filter, mount geometry, calibration files.

Everything here loads with :func:`iorthand.config.load` / :func:`iorthand.config.from_dict`. Units are SI
(m, s, rad); poses are UR pose vectors ``[x, y, z, rx, ry, rz]`` (metres and a rotation vector).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import cv2

from iorthand.config import setting


def _identity_pose() -> list[float]:
    return [0.0] * 6


def _check_axis(name: str, axis: list[float]) -> None:
    if math.hypot(*axis) < 1e-9:
        raise ValueError(f"{name} must be a non-zero vector, got {axis}")


# ---------------------------------------------------------------------------------------------------------
# Camera sources: a tagged union chosen by ``kind``.


@dataclass
class CameraConfig:
    """Base of the camera source settings; ``kind`` selects one of :attr:`VARIANTS`."""

    VARIANTS: ClassVar[dict[str, type]] = {}
    KIND: ClassVar[str] = ""

    def image_size(self) -> tuple[int, int] | None:
        """(width, height) the source will deliver, if known before opening it."""
        return None


@dataclass
class DeviceCameraConfig(CameraConfig):
    """A camera through cv2.VideoCapture: a device index, or a device path / stream URL when ``path`` is set."""

    KIND: ClassVar[str] = "device"
    index: int = setting(0, lo=0, hi=63)
    path: str = setting("", help="device path or URL; overrides index when set")
    width: int = setting(640, lo=16, hi=8192)
    height: int = setting(480, lo=16, hi=8192)
    fps: float = setting(30.0, lo=1.0, hi=1000.0)
    open_timeout: float = setting(5.0, lo=0.1, hi=60.0, help="s to wait for the first frame")

    def image_size(self) -> tuple[int, int] | None:
        return (self.width, self.height)


@dataclass
class VideoFileCameraConfig(CameraConfig):
    """Frames from a video file, stamped with the wall-clock time they are read (as a live camera would be)."""

    KIND: ClassVar[str] = "video"
    path: Path = setting()
    loop: bool = True
    realtime: bool = setting(True, help="deliver frames at the file's frame rate rather than as fast as possible")


@dataclass
class SyntheticCameraConfig(CameraConfig):
    """A pinhole camera with known intrinsics (no distortion) rendering the scene's markers."""

    KIND: ClassVar[str] = "synthetic"
    width: int = setting(640, lo=16, hi=8192)
    height: int = setting(480, lo=16, hi=8192)
    fx: float = setting(600.0, lo=1.0)
    fy: float = setting(600.0, lo=1.0)
    cx: float = setting(319.5)
    cy: float = setting(239.5)
    fps: float = setting(30.0, lo=1.0, hi=1000.0)
    noise_sigma: float = setting(2.0, lo=0.0, hi=64.0, help="Gaussian pixel noise, grey levels")
    blur_sigma: float = setting(0.6, lo=0.0, hi=10.0, help="Gaussian blur, px (0 = none)")
    background: int = setting(150, lo=0, hi=255)
    supersample: int = setting(3, lo=1, hi=8, help="render at this many times the size, then area-downsample")
    seed: int = setting(0, lo=0)
    pose_timeout: float = setting(
        5.0, lo=0.1, hi=60.0, help="s without a robot pose to render from before the camera fails"
    )

    def image_size(self) -> tuple[int, int] | None:
        return (self.width, self.height)


CameraConfig.VARIANTS = {c.KIND: c for c in (DeviceCameraConfig, VideoFileCameraConfig, SyntheticCameraConfig)}


# ---------------------------------------------------------------------------------------------------------
# Detection, markers, filter, geometry, scene.


CORNER_REFINEMENTS = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}


def check_aruco_dictionary(name: str) -> None:
    """One of OpenCV's predefined ArUco dictionaries, or ValueError naming it."""
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise ValueError(f"unknown ArUco dictionary {name!r} (e.g. DICT_4X4_50, DICT_5X5_100)")


@dataclass
class DetectorConfig:
    dictionary: str = "DICT_4X4_50"
    # OpenCV's own corner refinement only seeds the edge fit below when that is on (then "none" would do too,
    # but the edge fit starts better and falls back to these corners when an edge cannot be measured).
    corner_refinement: str = setting("subpix", choices=CORNER_REFINEMENTS)
    # Two adaptive-threshold windows (5 and 13 px) instead of OpenCV's three (3, 13, 23): ~1.5× faster and
    # still finds 40–50 mm markers at 0.2–0.5 m on a 640×480 image (see benchmarks/bench_perception.py).
    adaptive_window_min: int = setting(5, lo=3, hi=99)
    adaptive_window_max: int = setting(13, lo=3, hi=99)
    adaptive_window_step: int = setting(8, lo=1, hi=99)
    min_marker_perimeter_rate: float = setting(0.03, lo=0.001, hi=4.0)
    corner_refinement_window: int = setting(5, lo=1, hi=20)
    # Corners from lines fitted to the marker's four outer edges (detector.refine_corners): removes the
    # ~0.2 px shrink of OpenCV's corners (a 0.3–0.7 % range over-estimate) and cuts their noise ~10×.
    edge_refinement: bool = True
    # The longest profile across an edge (each pass sizes them to the blur it measured, and to 0.6 cell).
    edge_band: float = setting(6.0, lo=1.0, hi=20.0, help="px either side of an edge that its profiles may span")
    edge_max_shift: float = setting(
        2.0, lo=0.1, hi=20.0, help="px an edge-fitted corner may move from OpenCV's before the fit is refused"
    )
    # Move the fitted edges by the edge shift measured on the marker's own border (detector._border_shift):
    # corrects an unknown tone curve (a gamma-encoded camera puts edges ~0.2 px towards their dark side,
    # +1.2 % of range at 0.33 m), sharpening or a lopsided blur, without calibrating the camera's response.
    border_calibration: bool = True
    # Corner noise assumed for corners that were not edge-refined (edge-refined ones carry their own): OpenCV's
    # subpix corners were off by 0.21–0.26 px RMS on benchmarks/bench_marker_accuracy.py's scenes.
    corner_sigma: float = setting(0.25, lo=0.001, hi=10.0, help="px, 1-σ per coordinate")

    def check(self) -> None:
        check_aruco_dictionary(self.dictionary)
        if self.adaptive_window_max < self.adaptive_window_min:
            raise ValueError("adaptive_window_max must be at least adaptive_window_min")


@dataclass
class MarkerConfig:
    """Marker side lengths (black square, m) and the normal each marker is expected to have in the base frame."""

    default_size: float = setting(0.05, lo=0.001, hi=2.0)
    sizes: dict[int, float] = setting(default_factory=dict)
    # Markers lie on the patient/table facing up by default. None = prefer the solution facing the camera.
    expected_normal: list[float] | None = setting(default_factory=lambda: [0.0, 0.0, 1.0], length=3)
    expected_normals: dict[int, list[float]] = setting(default_factory=dict)
    # How far a marker's normal may be from the expected one (a curved body, a tilted table): the σ of the
    # prior that chooses between IPPE's mirror solutions when the corners cannot.
    normal_sigma: float = setting(0.35, lo=0.01, hi=math.pi, help="rad")

    def size_of(self, marker_id: int) -> float:
        return self.sizes.get(marker_id, self.default_size)

    def check(self) -> None:
        for marker_id, size in self.sizes.items():
            if not 0.001 <= size <= 2.0:
                raise ValueError(f"sizes.{marker_id}: expected a side length in [0.001, 2] m, got {size}")
        if self.expected_normal is not None:
            _check_axis("expected_normal", self.expected_normal)
        for marker_id, normal in self.expected_normals.items():
            if len(normal) != 3:
                raise ValueError(f"expected_normals.{marker_id}: expected 3 values, got {len(normal)}")
            _check_axis(f"expected_normals.{marker_id}", normal)


@dataclass
class FilterConfig:
    """Per-marker robust temporal filter on SE(3): medoid of a sliding window, then the mean of the samples
    within gates scaled to the window's own scatter (see filter.py)."""

    window: int = setting(9, lo=1, hi=100)
    # Metres that count as much as one radian when comparing poses: 0.05 m ≈ 1 rad makes 1 mm ≈ 1.1°.
    translation_scale: float = setting(0.05, lo=1e-4, hi=10.0)
    reset_after: float = setting(0.5, lo=0.0, hi=60.0, help="s unseen before a marker's window is cleared")
    # A sample joins the mean within this many times the window's median distance from its anchor. Distances
    # of 3-D Gaussian noise follow a Maxwell law whose 99.7 % quantile is 2.45× its median.
    inlier_spread: float = setting(2.5, lo=1.0, hi=100.0, help="× the window's median distance from the anchor")
    inlier_rotation: float = setting(0.05, lo=0.0, hi=math.pi, help="rad: the widest rotation gate")
    inlier_translation: float = setting(0.006, lo=0.0, hi=1.0, help="m: the widest translation gate")
    # The narrowest gates: a window of near-identical samples (a still camera) must not gate out its own noise.
    min_inlier_rotation: float = setting(0.005, lo=0.0, hi=math.pi, help="rad")
    min_inlier_translation: float = setting(0.0005, lo=0.0, hi=1.0, help="m")

    def check(self) -> None:
        if self.min_inlier_rotation > self.inlier_rotation or self.min_inlier_translation > self.inlier_translation:
            raise ValueError("min_inlier_rotation/min_inlier_translation must not exceed inlier_rotation/inlier_translation")


@dataclass
class MountGeometry:
    """The camera's mechanical chain: TCP → mount → pan servo → tilt servo → camera optical frame.

    ``T_base_camera = T_base_tcp · T_tcp_mount · R(pan_axis, θ) · R(tilt_axis, φ) · T_tilt_camera``. The pan
    axis is expressed in the mount frame, the tilt axis in the frame after the pan rotation. The camera frame
    is OpenCV's: x right, y down, z along the optical axis.
    """

    tcp_mount: list[float] = setting(default_factory=_identity_pose, length=6, help="T_tcp_mount as a UR pose")
    pan_axis: list[float] = setting(default_factory=lambda: [0.0, 0.0, 1.0], length=3)
    tilt_axis: list[float] = setting(default_factory=lambda: [1.0, 0.0, 0.0], length=3)
    tilt_camera: list[float] = setting(
        default_factory=_identity_pose, length=6, help="T_tilt_camera as a UR pose (a hand-eye file overrides it)"
    )
    # The servo angle (rad) at which each rotation of the chain is zero. Servos report their own angle (home
    # 90° = π/2 on a 0–180° servo): set these to the home angles when the geometry is measured at home.
    pan_zero: float = setting(0.0, lo=-7.0, hi=7.0)
    tilt_zero: float = setting(0.0, lo=-7.0, hi=7.0)

    def check(self) -> None:
        _check_axis("pan_axis", self.pan_axis)
        _check_axis("tilt_axis", self.tilt_axis)


@dataclass
class SceneMarker:
    id: int = setting(lo=0, hi=10_000)
    size: float = setting(lo=0.001, hi=2.0)
    pose: list[float] = setting(default_factory=_identity_pose, length=6, help="T_base_marker as a UR pose")


@dataclass
class SceneConfig:
    """What the synthetic camera renders: markers at fixed poses in the robot base frame."""

    markers: list[SceneMarker] = setting(default_factory=list)

    def check(self) -> None:
        ids = [m.id for m in self.markers]
        duplicates = sorted({i for i in ids if ids.count(i) > 1})
        if duplicates:
            raise ValueError(f"marker ids appear more than once: {duplicates}")


@dataclass
class PerceptionConfig:
    camera: CameraConfig = setting(default_factory=SyntheticCameraConfig)
    detector: DetectorConfig = setting(default_factory=DetectorConfig)
    markers: MarkerConfig = setting(default_factory=MarkerConfig)
    filter: FilterConfig = setting(default_factory=FilterConfig)
    geometry: MountGeometry = setting(default_factory=MountGeometry)
    scene: SceneConfig = setting(default_factory=SceneConfig)
    intrinsics_file: Path | None = setting(None, help="required unless the camera is synthetic")
    handeye_file: Path | None = setting(None, help="overrides geometry.tilt_camera")
    history_span: float = setting(2.0, lo=0.1, hi=60.0, help="s of robot/servo states kept for interpolation")
    max_extrapolation: float = setting(
        0.05, lo=0.0, hi=1.0, help="s a frame may be newer than the newest robot state and still use it"
    )
    retry_interval: float = setting(
        2.0, lo=0.1, hi=60.0, help="s between attempts to reopen a camera that failed (each one publishes why)"
    )
