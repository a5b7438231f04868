"""Camera sources behind one interface: a device through cv2.VideoCapture, a video file, a synthetic camera.

Every :class:`Frame` carries its capture timestamp, which is what the robot pose is interpolated at: for a device,
the time its driver stamped the frame when it is known (:func:`device_frame_time_ns`), else ``time.time_ns()``
when the frame was grabbed.
"""

from __future__ import annotations

import math
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

# A device's frames wait in the driver's buffers until grabbed: OpenCV's V4L2 backend queues 4, so a reader slower
# than the camera got a frame up to 4 periods old, stamped "now". 2 keeps one buffer filling while the reader holds
# the other; 1 would halve the frame rate of a UVC camera (it drops every frame that starts while no buffer is
# queued, i.e. the one after each grab).
DEVICE_BUFFERS = 2
DRIVER_STAMP_MAX_AGE_NS = 2_000_000_000  # an older driver stamp is not read as this frame's capture time
DRIVER_STAMP_AHEAD_NS = 2_000_000  # a stamp this much ahead of "now" still counts (clocks read one after the other)


def device_frame_time_ns(pos_msec: float, wall_ns: int, mono_ns: int) -> int:
    """The capture time (wall clock, ns) of the frame a device capture has just grabbed.

    ``pos_msec``: CAP_PROP_POS_MSEC read after the grab; ``wall_ns``/``mono_ns``: ``time.time_ns()`` and
    ``time.monotonic_ns()`` read right after the grab. OpenCV's V4L2 backend answers with the timestamp the driver
    put on the buffer when the frame was captured: CLOCK_MONOTONIC on current drivers (UVC), CLOCK_REALTIME on
    some old ones; 0 before the first frame. Other backends answer a stream position or -1. The stamp is taken
    when it reads as a time in either clock that is not ahead of now and at most
    :data:`DRIVER_STAMP_MAX_AGE_NS` old (the clocks are decades apart, a stream position is the device's uptime
    away from both); otherwise ``wall_ns``, when the frame was grabbed: late by however long it waited in the
    driver's buffers."""
    if not math.isfinite(pos_msec) or pos_msec <= 0:
        return wall_ns
    stamp_ns = round(pos_msec * 1e6)
    for now_ns in (mono_ns, wall_ns):
        age_ns = now_ns - stamp_ns
        if -DRIVER_STAMP_AHEAD_NS <= age_ns <= DRIVER_STAMP_MAX_AGE_NS:
            return wall_ns - max(age_ns, 0)
    return wall_ns


def open_device_capture(device: int | str) -> cv2.VideoCapture:
    """A cv2.VideoCapture on a device (index or path) holding at most :data:`DEVICE_BUFFERS` frames where the
    backend lets that be set (V4L2 does; others ignore it, and their frames' stamps say how old they are)."""
    capture = cv2.VideoCapture(device)
    if capture.isOpened():
        capture.set(cv2.CAP_PROP_BUFFERSIZE, DEVICE_BUFFERS)
    return capture


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
        t_ns = self._stamp(time.time_ns(), time.monotonic_ns())
        ok, image = self._capture.retrieve()
        if not ok or image is None:
            return None
        frame = Frame(image, t_ns, self._count)
        self._count += 1
        return frame

    def _stamp(self, wall_ns: int, mono_ns: int) -> int:
        """The capture time of the frame just grabbed, read at ``wall_ns``: that (a file's frames are stamped as
        they are read, as a live camera's would be)."""
        return wall_ns

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
        capture = open_device_capture(c.path or c.index)
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

    def _stamp(self, wall_ns: int, mono_ns: int) -> int:
        assert self._capture is not None
        return device_frame_time_ns(self._capture.get(cv2.CAP_PROP_POS_MSEC), wall_ns, mono_ns)

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
