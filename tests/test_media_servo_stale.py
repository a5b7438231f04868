"""Servo angles go stale: the media process holds the newest servo state for a frame only for a few of the servo
unit's heartbeats (servos.publish_hz); after that the camera's angle is unknown and the markers seen are not
published, with the reason in the log, as for a missing robot pose."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import yaml

from iorthand.config import load
from iorthand.geometry import compose, invert
from iorthand_edge.media import MediaService
from iorthand_edge.perception.chain import CameraChain
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.perception.history import ServoHistory
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.perception.synthetic import SyntheticCamera, look_at
from tests.conftest import ROOT, edge_config

PHANTOM = ROOT / "configs" / "scene-phantom.yaml"
SERVO = (0.2, -0.1)
S = 1_000_000_000


def _servos(publish_hz: float) -> dict:
    servos = yaml.safe_load((ROOT / "configs" / "edge-sim.yaml").read_text())["servos"]
    return {**servos, "publish_hz": publish_hz}


@pytest.mark.parametrize("publish_hz", [2.0, 0.5])
def test_the_media_process_forgets_servo_angles_after_a_few_heartbeats(publish_hz: float) -> None:
    config = edge_config("tcp/127.0.0.1:1", servos=_servos(publish_hz),
                         perception={"camera": {"kind": "synthetic", "width": 320, "height": 240}})
    service = MediaService(config)
    assert service.servos is not None
    now = time.time_ns()
    heartbeat = S / publish_hz
    service.servos.add(now - 600 * S, 0.30, -0.10)  # the servo unit went quiet ten minutes ago
    assert service.servo_angles_at(now) is None
    service.servos.add(now - int(2 * heartbeat), 0.31, -0.11)  # two heartbeats ago: still its angle
    assert service.servo_angles_at(now) == pytest.approx((0.31, -0.11))
    assert service.servo_angles_at(now + int(1.5 * heartbeat)) is None  # three and a half: unknown


def test_markers_are_not_published_with_a_stale_camera_angle(caplog: pytest.LogCaptureFixture) -> None:
    config = load(PHANTOM, PerceptionConfig)
    t_base_camera = look_at(np.array([0.45, 0.1, 0.3]), np.array([0.40, 0.05, 0.02]), roll=0.0)
    tcp = compose(t_base_camera, invert(CameraChain(config.geometry).tcp_camera(*SERVO)))
    camera = SyntheticCamera.from_config(config, lambda _t: tcp, lambda _t: SERVO)
    now = time.time_ns()
    servos = ServoHistory(config.history_span)
    servos.add(now - 600 * S, *SERVO)  # the right angles, but from ten minutes ago
    stale = PerceptionPipeline(config, lambda _t: tcp, servos.at, lambda _m: None, camera=camera)
    with caplog.at_level(logging.WARNING, logger="iorthand"):
        markers = stale.process(camera.capture(now))
    assert markers.markers == [] and stale.stats.frames_without_robot_pose == 1
    assert any("no servo angles at the frame's capture time" in r.getMessage() for r in caplog.records)
    servos.add(now - S // 10, *SERVO)  # a heartbeat 100 ms ago: the markers are back
    fresh = PerceptionPipeline(config, lambda _t: tcp, servos.at, lambda _m: None, camera=camera)
    assert sorted(m.id for m in fresh.process(camera.capture(now + 1)).markers) == [3, 7, 11]
