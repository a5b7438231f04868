"""Closed loop: a moving robot, servos at non-zero angles, the synthetic camera, the full pipeline.

The robot state is sampled into a PoseHistory at 125 Hz while frames are captured at other instants; the
camera renders the true pose at its capture time and the pipeline must find it by interpolation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from iorthand.config import from_dict
from iorthand.geometry import (
    compose,
    invert,
    pose_to_matrix,
    rotation_angle,
    translation_distance,
    unflatten,
)
from iorthand.protocol import Markers
from iorthand_edge.perception.chain import CameraChain
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.perception.history import PoseHistory, ServoHistory
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.perception.synthetic import SyntheticCamera, look_at

T0 = 1_800_000_000_000_000_000  # ns: an arbitrary epoch time for the simulated clock
ROBOT_PERIOD_NS = 8_000_000  # 125 Hz robot state
FRAME_PERIOD_NS = 33_333_333  # ~30 fps, not a multiple of the robot period
CENTRE = np.array([0.40, 0.05, 0.02])

SCENE = {
    "markers": [
        {"id": 3, "size": 0.045, "pose": [0.40, 0.05, 0.02, 0.0, 0.0, 0.4]},
        {"id": 7, "size": 0.040, "pose": [0.465, 0.045, 0.03, 0.2, -0.1, 0.6]},
        {"id": 11, "size": 0.050, "pose": [0.335, 0.055, 0.015, -0.15, 0.2, 0.2]},
    ]
}


def make_config(noise: float = 2.0) -> PerceptionConfig:
    data = {
        "camera": {
            "kind": "synthetic",
            "width": 640,
            "height": 480,
            "fx": 600.0,
            "fy": 600.0,
            "cx": 319.5,
            "cy": 239.5,
            "noise_sigma": noise,
            "blur_sigma": 0.6,
            "seed": 4,
        },
        "markers": {"sizes": {m["id"]: m["size"] for m in SCENE["markers"]}},
        "geometry": {"tcp_mount": [0.0, 0.045, 0.03, 0.0, 0.0, 0.0], "tilt_camera": [0.0, 0.015, 0.035, 0.0, 0.0, 0.0]},
        "scene": SCENE,
    }
    return from_dict(data, PerceptionConfig)


class MovingRig:
    """A robot that keeps the camera aimed at the markers while it moves along an arc at ``distance``.

    The true pose is a function of time; the pipeline only sees 125 Hz samples of it through a history.
    """

    def __init__(
        self, config: PerceptionConfig, distance: float, servo: tuple[float, float], speed: float = 0.4
    ) -> None:
        self.chain = CameraChain(config.geometry)
        self.distance = distance
        self.servo = servo
        self.speed = speed  # rad/s around the vertical axis through the markers
        self.history = PoseHistory(span_s=2.0, max_extrapolation_s=0.02)
        self.servos = ServoHistory()

    def true_pose(self, t_ns: int) -> np.ndarray:
        phase = self.speed * (t_ns - T0) / 1e9
        slant = math.radians(20.0)
        eye = CENTRE + self.distance * np.array(
            [math.sin(slant) * math.cos(phase), math.sin(slant) * math.sin(phase), math.cos(slant)]
        )
        t_base_camera = look_at(eye, CENTRE, roll=0.3 * math.sin(phase))
        return compose(t_base_camera, invert(self.chain.tcp_camera(*self.servo)))

    def feed(self, until_ns: int) -> None:
        """Robot states up to ``until_ns`` (what the agent's control loop would have added)."""
        start = T0 - 2 * ROBOT_PERIOD_NS if len(self.history) == 0 else self._fed_until + ROBOT_PERIOD_NS
        for t in range(start, until_ns + 1, ROBOT_PERIOD_NS):
            self.history.add(t, self.true_pose(t))
            self.servos.add(t, *self.servo)
            self._fed_until = t


def run(config: PerceptionConfig, rig: MovingRig, frames: int, start_ns: int = T0) -> list[Markers]:
    published: list[Markers] = []
    pipeline = PerceptionPipeline(config, rig.history.at, rig.servos.at, published.append)
    camera = SyntheticCamera.from_config(config, rig.true_pose, lambda _t: rig.servo)
    for i in range(frames):
        t = start_ns + i * FRAME_PERIOD_NS + 1_234_567  # captured between two robot samples
        rig.feed(t + ROBOT_PERIOD_NS)  # the robot state after the frame has arrived by the time it is processed
        frame = camera.capture(t)
        message = pipeline.process(frame)
        assert message.t == t
        published.append(message)
    return published


def errors(message: Markers, which: str = "pose") -> dict[int, tuple[float, float]]:
    """Per marker: (translation error mm, rotation error deg) against the scene's ground truth."""
    truth = {m["id"]: pose_to_matrix(m["pose"]) for m in SCENE["markers"]}
    out = {}
    for marker in message.markers:
        estimate = unflatten(getattr(marker, which))
        out[marker.id] = (
            translation_distance(estimate, truth[marker.id]) * 1000,
            math.degrees(rotation_angle(estimate, truth[marker.id])),
        )
    return out


@pytest.mark.parametrize(
    ("distance", "max_mm", "max_deg"), [(0.2, 3.0, 1.0), (0.3, 3.0, 1.0), (0.35, 3.0, 1.0), (0.5, 6.0, 2.0)]
)
def test_markers_published_at_ground_truth_while_robot_moves(distance: float, max_mm: float, max_deg: float) -> None:
    config = make_config()
    rig = MovingRig(config, distance, servo=(0.35, -0.25))
    published = run(config, rig, frames=10)
    # The robot really moved during the run (so a "latest pose" shortcut would show).
    first, last = rig.true_pose(published[0].t), rig.true_pose(published[-1].t)
    assert translation_distance(first, last) > 0.01
    final = errors(published[-1])
    assert sorted(final) == [3, 7, 11], f"markers missing at {distance} m: saw {sorted(final)}"
    for marker_id, (mm, deg) in final.items():
        assert mm <= max_mm and deg <= max_deg, f"marker {marker_id} at {distance} m: {mm:.2f} mm, {deg:.2f}°"
    # Every frame's raw estimate is sane too (no mirror flips slipped through as published raw poses).
    for message in published:
        for marker_id, (_, deg) in errors(message, "raw").items():
            assert deg < 10.0, f"raw pose of {marker_id} off by {deg:.1f}°"


def test_servo_angles_do_not_move_reported_markers() -> None:
    config = make_config()
    results = []
    for servo in [(0.0, 0.0), (0.4, -0.3), (-0.35, 0.3)]:
        rig = MovingRig(config, 0.3, servo=servo, speed=0.0)
        results.append({m.id: unflatten(m.pose) for m in run(config, rig, frames=6)[-1].markers})
    for other in results[1:]:
        assert sorted(other) == sorted(results[0])
        for marker_id, pose in other.items():
            assert translation_distance(pose, results[0][marker_id]) < 0.002
            assert math.degrees(rotation_angle(pose, results[0][marker_id])) < 0.7


def test_servo_move_with_robot_still_keeps_markers_in_place() -> None:
    """The robot holds still and only the servos turn: the camera swings, the markers must not."""
    config = make_config()
    rig = MovingRig(config, 0.3, servo=(0.2, -0.1), speed=0.0)
    fixed_tcp = rig.true_pose(T0)
    history = PoseHistory()
    servos = ServoHistory()
    for t in range(T0 - 10 * ROBOT_PERIOD_NS, T0 + 10**9, ROBOT_PERIOD_NS):
        history.add(t, fixed_tcp)
        servos.add(t, 0.2 + 0.1 * (t - T0) / 1e9 * 3, -0.1 - 0.05 * (t - T0) / 1e9 * 3)
    published: list[Markers] = []
    pipeline = PerceptionPipeline(config, history.at, servos.at, published.append)
    camera = SyntheticCamera.from_config(config, history.at, lambda t: servos.at(t) or (0.0, 0.0))
    for i in range(8):
        frame = camera.capture(T0 + i * FRAME_PERIOD_NS * 3 + 777_777)
        published.append(pipeline.process(frame))
    for marker_id, (mm, deg) in errors(published[-1]).items():
        assert mm <= 3.0 and deg <= 1.0, f"marker {marker_id}: {mm:.2f} mm, {deg:.2f}°"
