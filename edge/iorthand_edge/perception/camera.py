"""Camera sources behind one interface: a device through cv2.VideoCapture, a video file, a synthetic camera.

Every :class:`Frame` carries its capture timestamp (``time.time_ns()`` when the frame was grabbed), which is
what the robot pose is interpolated at.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

import cv2
import numpy as np

from .config import (
    CameraConfig,
    DeviceCameraConfig,
    PerceptionConfig,
    SyntheticCameraConfig,
    VideoFileCameraConfig,
)


class CameraError(RuntimeError):
    """A camera that cannot be opened or read; the message says which camera and why."""


class CameraFinished(CameraError):
    """A source that has nothing more to give (the end of a video file): reopening it would not help."""


@dataclass
class Frame:
    image: np.ndarray  # BGR (H×W×3) or grey (H×W), uint8
    t_ns: int  # capture time, ns since the epoch
    index: int  # frames delivered by this source so far, from 0

    @property
    def size(self) -> tuple[int, int]:
        return (self.image.shape[1], self.image.shape[0])


class CameraSource(ABC):
    """Open, read frames, close. ``read`` blocks until the next frame and raises :class:`CameraError` on failure."""

    description: str = "camera"

    @abstractmethod
    def open(self) -> None: ...

    @abstractmethod
    def read(self) -> Frame: ...

    @abstractmethod
    def close(self) -> None: ...

    def interrupt(self) -> None:  # noqa: B027 (optional)
        """From another thread: make a ``read`` that is waiting return soon (it raises :class:`CameraError`).
        Sources whose ``read`` returns within a frame period by itself need nothing."""

    def __enter__(self) -> CameraSource:
        self.open()
        return self

    def __exit__(self, *_: type[BaseException] | BaseException | TracebackType | None) -> None:
        self.close()


class _CaptureSource(CameraSource):
    """What device and file sources share: a cv2.VideoCapture, grabbed then stamped then decoded."""

    def __init__(self) -> None:
        self._capture: cv2.VideoCapture | None = None
        self._count = 0

    def _grab(self) -> Frame | None:
        if self._capture is None:
            raise CameraError(f"{self.description} is not open")
        # Stamp between grab and retrieve: grab returns when the frame has arrived, retrieve only decodes it.
        if not self._capture.grab():
            return None
        t_ns = time.time_ns()
        ok, image = self._capture.retrieve()
        if not ok or image is None:
            return None
        frame = Frame(image, t_ns, self._count)
        self._count += 1
        return frame

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None


class DeviceCamera(_CaptureSource):
    def __init__(self, config: DeviceCameraConfig) -> None:
        super().__init__()
        self.config = config
        target = config.path or f"index {config.index}"
        self.description = f"camera {target} ({config.width}×{config.height} @ {config.fps:g} fps)"

    def open(self) -> None:
        c = self.config
        capture = cv2.VideoCapture(c.path) if c.path else cv2.VideoCapture(c.index)
        if not capture.isOpened():
            capture.release()
            raise CameraError(f"cannot open {self.description}: no such device, or it is busy or not readable")
        capture.set(cv2.CAP_PROP_FRAME_WIDTH, c.width)
        capture.set(cv2.CAP_PROP_FRAME_HEIGHT, c.height)
        capture.set(cv2.CAP_PROP_FPS, c.fps)
        self._capture = capture
        deadline = time.monotonic() + c.open_timeout
        while (frame := self._grab()) is None:
            if time.monotonic() > deadline:
                self.close()
                raise CameraError(f"{self.description} opened but gave no frame within {c.open_timeout:g} s")
            time.sleep(0.05)
        if frame.size != (c.width, c.height):
            self.close()
            raise CameraError(
                f"{self.description} delivers {frame.size[0]}×{frame.size[1]}, not the requested size; "
                "set camera.width/height to a mode the camera supports (and calibrate at that size)"
            )

    def read(self) -> Frame:
        frame = self._grab()
        if frame is None:
            raise CameraError(f"{self.description} stopped delivering frames (unplugged or failed)")
        return frame


class VideoFileCamera(_CaptureSource):
    def __init__(self, config: VideoFileCameraConfig) -> None:
        super().__init__()
        self.config = config
        self.description = f"video file {config.path}"
        self._period_s = 0.0
        self._next_due = 0.0

    def open(self) -> None:
        if not self.config.path.is_file():
            raise CameraError(f"cannot open {self.description}: no such file")
        capture = cv2.VideoCapture(str(self.config.path))
        if not capture.isOpened():
            capture.release()
            raise CameraError(f"cannot open {self.description}: not a video OpenCV can decode")
        fps = capture.get(cv2.CAP_PROP_FPS)
        self._period_s = 1.0 / fps if self.config.realtime and fps > 0 else 0.0
        self._capture = capture
        self._next_due = time.monotonic()

    def read(self) -> Frame:
        if self._period_s:
            self._next_due = _sleep_until(self._next_due, self._period_s)
        frame = self._grab()
        if frame is None and self.config.loop and self._capture is not None and self._count > 0:
            self._capture.set(cv2.CAP_PROP_POS_FRAMES, 0)
            frame = self._grab()
        if frame is None:
            raise CameraFinished(f"{self.description}: no more frames (end of file or unreadable)")
        return frame


def _sleep_until(due: float, period_s: float) -> float:
    """Sleep until ``due`` (monotonic s); return the next due time, re-synchronised if we fell behind."""
    now = time.monotonic()
    if due > now:
        time.sleep(due - now)
        return due + period_s
    return now + period_s


def make_camera(
    config: PerceptionConfig,
    robot_pose_at: Callable[[int], np.ndarray | None],
    servo_angles_at: Callable[[int], tuple[float, float] | None],
) -> CameraSource:
    """The source ``config.camera`` describes. The synthetic one renders from the pose callables."""
    camera: CameraConfig = config.camera
    if isinstance(camera, DeviceCameraConfig):
        return DeviceCamera(camera)
    if isinstance(camera, VideoFileCameraConfig):
        return VideoFileCamera(camera)
    if isinstance(camera, SyntheticCameraConfig):
        # Imported here: synthetic.py builds on this module's Frame and CameraSource.
        from .synthetic import SyntheticCamera

        return SyntheticCamera.from_config(config, robot_pose_at, servo_angles_at)
    raise CameraError(f"unsupported camera kind {type(camera).__name__}")
