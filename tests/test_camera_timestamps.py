"""Frames from a device camera carry the time the driver captured them, not the time they were grabbed.

A V4L2 camera queues frames in the driver's buffers; OpenCV's CAP_PROP_POS_MSEC then gives the buffer's timestamp
(CLOCK_MONOTONIC on current drivers, CLOCK_REALTIME on some old ones, a stream position on other backends). No
camera exists on this machine: the decision is tested as plain code, and the two device sources (the perception
camera, the video stream's) are tested against a stand-in for cv2.VideoCapture that plays a camera whose frames
waited 80 ms in the driver's buffers.
"""

from __future__ import annotations

import math
import threading
import time
from typing import ClassVar

import numpy as np
import pytest

from iorthand import keys
from iorthand_edge.perception import camera as perception_camera
from iorthand_edge.perception.camera import (
    DEVICE_BUFFERS,
    DRIVER_STAMP_MAX_AGE_NS,
    DeviceCamera,
    device_frame_time_ns,
)
from iorthand_edge.perception.config import DeviceCameraConfig
from iorthand_edge.video import StreamConfig, VideoStream
from iorthand_edge.video.sources import OpenCVSource
from tests.test_video_errors import Recorder

WALL = 1_790_000_000_000_000_000  # ns since the epoch
MONO = 86_400_000_000_000  # a day of uptime, ns
MS = 1_000_000


def test_a_monotonic_driver_stamp_dates_the_frame_back_by_its_age() -> None:
    assert device_frame_time_ns((MONO - 80 * MS) / 1e6, WALL, MONO) == WALL - 80 * MS


def test_a_wall_clock_driver_stamp_is_taken_as_it_is() -> None:
    assert device_frame_time_ns((WALL - 30 * MS) / 1e6, WALL, MONO) == pytest.approx(WALL - 30 * MS, abs=1000)


@pytest.mark.parametrize(
    "pos_msec",
    [
        0.0,  # before the first frame
        -1.0,  # a backend without the property
        math.nan,
        5_000.0,  # a stream position (5 s into a network stream): neither clock
        (MONO + 50 * MS) / 1e6,  # ahead of now
        (MONO - DRIVER_STAMP_MAX_AGE_NS - MS) / 1e6,  # too old to be this frame's
    ],
)
def test_an_implausible_driver_stamp_keeps_the_grab_time(pos_msec: float) -> None:
    assert device_frame_time_ns(pos_msec, WALL, MONO) == WALL


class BufferedCamera:
    """Stands in for cv2.VideoCapture on a V4L2 camera (none exists here): each frame it hands over was captured
    ``age_ns`` before, and POS_MSEC says so on the monotonic clock."""

    instances: ClassVar[list[BufferedCamera]] = []

    def __init__(self, _device: int | str, age_ns: int = 80 * MS) -> None:
        self.age_ns = age_ns
        self.props: dict[int, float] = {}
        self.grabbed_at = 0
        self.grab_walls: list[int] = []  # time.time_ns() at each grab
        BufferedCamera.instances.append(self)

    def isOpened(self) -> bool:  # (OpenCV's name)
        return True

    def set(self, prop: int, value: float) -> bool:
        self.props[prop] = value
        return True

    def get(self, prop: int) -> float:
        if prop == perception_camera.cv2.CAP_PROP_POS_MSEC:
            return (self.grabbed_at - self.age_ns) / 1e6
        return self.props.get(prop, 0.0)

    def grab(self) -> bool:
        self.grabbed_at = time.monotonic_ns()
        self.grab_walls.append(time.time_ns())
        return True

    def retrieve(self) -> tuple[bool, np.ndarray]:
        w, h = (
            int(self.props[perception_camera.cv2.CAP_PROP_FRAME_WIDTH]),
            int(self.props[perception_camera.cv2.CAP_PROP_FRAME_HEIGHT]),
        )
        return True, np.full((h, w, 3), 100, np.uint8)

    def read(self) -> tuple[bool, np.ndarray]:
        self.grab()
        return self.retrieve()

    def release(self) -> None:
        pass


@pytest.fixture
def buffered_camera(monkeypatch: pytest.MonkeyPatch) -> type[BufferedCamera]:
    BufferedCamera.instances.clear()
    monkeypatch.setattr(perception_camera.cv2, "VideoCapture", BufferedCamera)
    return BufferedCamera


def test_the_perception_camera_stamps_frames_with_the_driver_time(buffered_camera: type[BufferedCamera]) -> None:
    with DeviceCamera(DeviceCameraConfig(index=0, width=64, height=48)) as camera:
        before = time.time_ns()
        frame = camera.read()
        after = time.time_ns()
    assert before - 80 * MS - 5 * MS <= frame.t_ns <= after - 80 * MS
    assert buffered_camera.instances[0].props[perception_camera.cv2.CAP_PROP_BUFFERSIZE] == DEVICE_BUFFERS


def test_the_video_stream_stamps_device_frames_with_the_driver_time(buffered_camera: type[BufferedCamera]) -> None:
    config = StreamConfig(source="opencv", device="0", width=64, height=48, fps=30, codec="jpeg")
    pub = Recorder()
    stream = VideoStream("camera", keys.VIDEO_CAMERA, config, OpenCVSource(config))
    stop = threading.Event()
    stream.start_with(pub, stop)
    deadline = time.monotonic() + 10
    while not pub.snapshot() and time.monotonic() < deadline:
        time.sleep(0.01)
    stop.set()
    stream.join()
    frame = pub.snapshot()[0]
    assert not frame.failure and frame.data
    # The first frame says it was captured 80 ms before its grab (it waited in the driver's buffers), not at it.
    assert frame.t <= buffered_camera.instances[0].grab_walls[0] - 75 * MS
    assert buffered_camera.instances[0].props[perception_camera.cv2.CAP_PROP_BUFFERSIZE] == DEVICE_BUFFERS
