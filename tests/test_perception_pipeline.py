"""The pipeline as the agent uses it: config files, the worker thread, and bad input."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from iorthand.config import ConfigError, from_dict, load
from iorthand.geometry import compose, invert
from iorthand.protocol import Markers
from iorthand_edge.perception.camera import Frame
from iorthand_edge.perception.chain import CameraChain
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.perception.pipeline import PerceptionError, PerceptionPipeline
from iorthand_edge.perception.synthetic import SyntheticCamera, look_at

ROOT = Path(__file__).resolve().parents[1]
PHANTOM = ROOT / "configs" / "scene-phantom.yaml"
INTRINSICS = ROOT / "configs" / "calibration" / "intrinsics-640x480.yaml"
HANDEYE = ROOT / "configs" / "calibration" / "handeye.yaml"
SERVO = (0.2, -0.1)


def robot_over_phantom(config: PerceptionConfig) -> np.ndarray:
    """T_base_tcp that puts the camera 0.3 m above the phantom's markers, looking at them."""
    t_base_camera = look_at(np.array([0.45, 0.1, 0.3]), np.array([0.40, 0.05, 0.02]), roll=0.0)
    return compose(t_base_camera, invert(CameraChain(config.geometry).tcp_camera(*SERVO)))


def test_example_config_runs_in_its_own_thread_and_publishes() -> None:
    config = load(PHANTOM, PerceptionConfig)
    config.intrinsics_file, config.handeye_file = INTRINSICS, HANDEYE  # the example calibration files
    tcp = robot_over_phantom(config)
    received: list[Markers] = []
    got_three = threading.Event()

    def publish(message: Markers) -> None:
        assert threading.current_thread().name == "perception"
        received.append(message)
        if len(received) >= 3:
            got_three.set()

    pipeline = PerceptionPipeline(config, lambda _t: tcp, lambda _t: SERVO, publish)
    started = time.monotonic()
    pipeline.start()
    assert time.monotonic() - started < 0.1  # start never blocks the caller
    try:
        assert got_three.wait(10.0), f"no messages: {pipeline.failure}"
    finally:
        pipeline.stop()
    assert not pipeline.running and pipeline.failure is None
    last = received[-1]
    assert sorted(m.id for m in last.markers) == [3, 7, 11]
    assert [m.seq for m in received[:3]] == [1, 2, 3]
    assert received[0].t < received[1].t < received[2].t
    assert last.frames >= 3 and last.fps > 0 and last.processing_ms > 0
    Markers.decode(last.encode())  # valid on the wire


def test_synthetic_camera_waits_for_the_first_robot_pose() -> None:
    # At start-up the perception worker can run before the control loop has stored a robot state: the
    # synthetic camera then has nothing to render from and must wait, not end perception.
    config = load(PHANTOM, PerceptionConfig)
    config.intrinsics_file, config.handeye_file = INTRINSICS, HANDEYE
    tcp = robot_over_phantom(config)
    pose_known = threading.Event()
    received: list[Markers] = []
    pipeline = PerceptionPipeline(
        config, lambda _t: tcp if pose_known.is_set() else None, lambda _t: SERVO, received.append
    )
    pipeline.start()
    try:
        time.sleep(0.3)  # ~9 frame periods without a pose
        assert pipeline.running and pipeline.failure is None and received == []
        pose_known.set()
        deadline = time.monotonic() + 10.0
        while not received and time.monotonic() < deadline:
            time.sleep(0.01)
        assert received, f"no markers after the pose arrived: {pipeline.failure}"
        assert sorted(m.id for m in received[-1].markers) == [3, 7, 11]
    finally:
        pipeline.stop()



def test_a_failed_camera_is_published_with_its_reason_and_perception_resumes_when_it_delivers_again() -> None:
    # The synthetic camera fails when it has had no robot pose to render from for pose_timeout: the same
    # CameraError a real camera gives when it stops delivering, and it recovers the same way.
    config = load(PHANTOM, PerceptionConfig)
    config.intrinsics_file, config.handeye_file = INTRINSICS, HANDEYE
    config.camera.pose_timeout = 0.2  # type: ignore[union-attr]
    config.retry_interval = 0.2
    tcp = robot_over_phantom(config)
    pose_known = threading.Event()
    pose_known.set()
    received: list[Markers] = []
    pipeline = PerceptionPipeline(
        config, lambda _t: tcp if pose_known.is_set() else None, lambda _t: SERVO, received.append
    )

    def wait_for(predicate, what: str) -> None:
        deadline = time.monotonic() + 10.0
        while not predicate() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert predicate(), f"timed out waiting for {what}; failure: {pipeline.failure}"

    pipeline.start()
    try:
        wait_for(lambda: any(m.markers for m in received), "markers")
        pose_known.clear()  # the camera stops delivering
        wait_for(lambda: sum(bool(m.failure) for m in received) >= 2, "two failure messages")
        assert pipeline.running, "a camera failure must not end the perception worker"
        failed = [m for m in received if m.failure]
        assert all(m.markers == [] for m in failed)
        assert "no robot pose to render from for 0.2 s" in failed[0].failure and pipeline.failure == failed[0].failure
        assert pipeline.stats.camera_failures >= 2
        assert [m.seq for m in received] == list(range(1, len(received) + 1))  # one sequence for both kinds
        pose_known.set()  # delivering again: reopened at the next retry
        count = len(received)
        wait_for(lambda: any(m.markers for m in received[count:]), "markers again")
        assert pipeline.failure is None and not received[-1].failure
    finally:
        pipeline.stop()


def test_the_end_of_a_video_file_ends_perception_once(tmp_path: Path) -> None:
    video = tmp_path / "three-frames.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (640, 480))
    for i in range(3):
        writer.write(np.full((480, 640, 3), 60 * i, np.uint8))
    writer.release()
    config = from_dict(
        {"camera": {"kind": "video", "path": str(video), "loop": False, "realtime": False},
         "intrinsics_file": str(INTRINSICS), "retry_interval": 0.1},
        PerceptionConfig,
    )
    received: list[Markers] = []
    pipeline = PerceptionPipeline(config, lambda _t: np.eye(4), lambda _t: (0.0, 0.0), received.append)
    pipeline.start()
    deadline = time.monotonic() + 5.0
    while pipeline.running and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)  # three retry intervals: none may come
    assert not pipeline.running
    assert [bool(m.failure) for m in received] == [False, False, False, True]
    assert "no more frames" in received[-1].failure and pipeline.failure == received[-1].failure


def test_publish_failure_does_not_stop_perception() -> None:
    config = load(PHANTOM, PerceptionConfig)
    tcp = robot_over_phantom(config)
    calls = threading.Semaphore(0)

    def publish(_message: Markers) -> None:
        calls.release()
        raise ConnectionError("zenoh session closed")

    pipeline = PerceptionPipeline(config, lambda _t: tcp, lambda _t: SERVO, publish)
    pipeline.start()
    try:
        assert all(calls.acquire(timeout=5.0) for _ in range(3))
        assert pipeline.running
    finally:
        pipeline.stop()
    assert pipeline.stats.publish_errors >= 3


def test_unreadable_camera_is_retried_and_every_attempt_says_why() -> None:
    config = from_dict(
        {"camera": {"kind": "device", "path": "/nonexistent/video9"}, "intrinsics_file": str(INTRINSICS),
         "retry_interval": 0.1},
        PerceptionConfig,
    )
    received: list[Markers] = []
    pipeline = PerceptionPipeline(config, lambda _t: np.eye(4), lambda _t: (0.0, 0.0), received.append)
    pipeline.start()
    try:
        deadline = time.monotonic() + 5.0
        while len(received) < 3 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert pipeline.running
        assert len(received) >= 3 and all("cannot open camera /nonexistent/video9" in m.failure for m in received)
        assert pipeline.failure == received[0].failure and pipeline.stats.camera_failures >= 3
    finally:
        pipeline.stop()
    assert not pipeline.running


def test_calibration_for_another_image_size_is_refused() -> None:
    config = from_dict(
        {"camera": {"kind": "device", "width": 1280, "height": 720}, "intrinsics_file": str(INTRINSICS)},
        PerceptionConfig,
    )
    with pytest.raises(PerceptionError, match="made for 640×480 images but the camera delivers 1280×720"):
        PerceptionPipeline(config, lambda _t: None, lambda _t: (0.0, 0.0), lambda _m: None)


def test_real_camera_without_intrinsics_is_refused() -> None:
    config = from_dict({"camera": {"kind": "device"}}, PerceptionConfig)
    with pytest.raises(PerceptionError, match="needs intrinsics_file"):
        PerceptionPipeline(config, lambda _t: None, lambda _t: (0.0, 0.0), lambda _m: None)


def test_corrupt_files_name_the_file_and_the_problem(tmp_path: Path) -> None:
    broken = tmp_path / "perception.yaml"
    broken.write_text("camera: {kind: synthetic, width: [640\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load(broken, PerceptionConfig)
    wrong = tmp_path / "wrong.yaml"
    wrong.write_text("detector: {dictionary: DICT_9X9_7}\n", encoding="utf-8")
    with pytest.raises(ConfigError, match="unknown ArUco dictionary"):
        load(wrong, PerceptionConfig)
    calibration = tmp_path / "intrinsics.yaml"
    calibration.write_text("image_width: 640\nimage_height: 480\ncamera_matrix: [[1, 2]]\n", encoding="utf-8")
    config = from_dict({"intrinsics_file": str(calibration)}, PerceptionConfig)
    with pytest.raises(PerceptionError, match=r"intrinsics.yaml: camera_matrix: expected 3 values"):
        PerceptionPipeline(config, lambda _t: None, lambda _t: (0.0, 0.0), lambda _m: None)


def test_frame_of_the_wrong_size_is_refused_and_no_pose_means_no_markers() -> None:
    config = load(PHANTOM, PerceptionConfig)
    pipeline = PerceptionPipeline(config, lambda _t: None, lambda _t: (0.0, 0.0), lambda _m: None)
    with pytest.raises(PerceptionError, match="frame is 1280×720"):
        pipeline.process(Frame(np.zeros((720, 1280), np.uint8), 1, 0))
    tcp = robot_over_phantom(config)
    frame = SyntheticCamera.from_config(config, lambda _t: tcp, lambda _t: SERVO).capture(10**18)
    message = pipeline.process(frame)  # the robot pose is unknown at that time: nothing is published as a pose
    assert message.markers == [] and pipeline.stats.frames_without_robot_pose == 1
