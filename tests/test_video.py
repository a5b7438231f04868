"""Video: the simulated ultrasound responds to contact, JPEG frames carry capture time and sequence, the
sender drops frames instead of queueing, and both streams flow through a router on the video session."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from iorthand import keys
from iorthand.protocol import VideoFrame
from iorthand.transport import VIDEO
from iorthand_edge.video import LatestSlot, StreamConfig, VideoStream, decode_frame, make_source, render_ultrasound
from iorthand_edge.video.stream import Captured, encode_frame
from tests.conftest import wait_until


def test_ultrasound_image_changes_with_contact() -> None:
    rng = np.random.default_rng(0)
    air = render_ultrasound(320, 240, 0.0, rng).astype(float)
    light = render_ultrasound(320, 240, 1.0, rng).astype(float)
    firm = render_ultrasound(320, 240, 6.0, rng).astype(float)
    deep = slice(60, 200)  # below the probe's own ring-down
    assert air[deep].mean() < 10  # no coupling: nothing below the ring-down
    assert light[deep].mean() > air[deep].mean() + 10
    assert firm[deep].mean() > light[deep].mean()
    # Speckle: consecutive frames at the same force differ pixel by pixel.
    again = render_ultrasound(320, 240, 6.0, rng).astype(float)
    assert np.abs(again - firm)[deep].mean() > 5


def test_frames_round_trip_with_capture_time_and_sequence() -> None:
    image = make_source(StreamConfig(width=160, height=120), lambda: 0.0).grab()
    frame = encode_frame("camera", Captured(7, 1_700_000_000_123_456_789, image), quality=70)
    back = VideoFrame.decode(frame.encode())
    assert (back.seq, back.t, back.width, back.height, back.source) == (7, 1_700_000_000_123_456_789, 160, 120, "camera")
    assert decode_frame(back).shape == (120, 160, 3)


def test_slot_keeps_only_the_newest_frame() -> None:
    slot = LatestSlot()
    img = np.zeros((2, 2), np.uint8)
    for i in range(1, 6):
        slot.put(Captured(i, i, img))
    item = slot.take(0.0)
    assert item is not None and item.seq == 5 and slot.dropped == 4
    assert slot.take(0.0) is None


class SlowPublisher:
    """A congested network: each put takes 100 ms."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, int, int]] = []  # (seq, capture t, sent t)

    def put(self, payload: bytes) -> None:
        frame = VideoFrame.decode(payload)
        time.sleep(0.1)
        self.frames.append((frame.seq, frame.t, time.time_ns()))


def test_slow_network_drops_frames_instead_of_queueing() -> None:
    stream = VideoStream("camera", keys.VIDEO_CAMERA, StreamConfig(width=160, height=120, fps=30), make_source(StreamConfig(width=160, height=120), lambda: 0.0))
    pub = SlowPublisher()
    stop = threading.Event()
    stream.start_with(pub, stop)
    try:
        wait_until(lambda: len(pub.frames) >= 6, timeout=10.0, message="frames through the slow link")
    finally:
        stop.set()
        stream.join()
    seqs = [s for s, _, _ in pub.frames]
    assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
    assert stream.dropped > 0 and seqs[-1] - seqs[0] > len(seqs) - 1  # gaps in seq = dropped frames
    # No backlog: every frame sent was captured at most ~one put + one frame period before it was sent.
    ages = [(sent - captured) / 1e9 for _, captured, sent in pub.frames[2:]]
    assert max(ages) < 0.1 + 0.1 + 1 / 30 + 0.3  # 0.3 s of slack for a loaded machine; a queue would grow without bound


def test_video_qos_is_low_priority_and_dropping() -> None:
    import zenoh

    assert VIDEO.priority == zenoh.Priority.DATA_LOW and VIDEO.congestion == zenoh.CongestionControl.DROP


def test_streams_through_the_router_on_their_own_session(edge_factory, session_factory) -> None:
    video = {
        "camera": {"source": "pattern", "width": 160, "height": 120, "fps": 10, "quality": 60},
        "ultrasound": {"source": "ultrasound_sim", "width": 128, "height": 96, "fps": 10},
    }
    agent = edge_factory(video=video, phantom={"surface_z": 0.199})
    received: dict[str, list[tuple[VideoFrame, int]]] = {"camera": [], "ultrasound": []}
    s = session_factory()
    k = keys.RobotKeys("sim1")
    for name, suffix in (("camera", keys.VIDEO_CAMERA), ("ultrasound", keys.VIDEO_ULTRASOUND)):
        s.declare_subscriber(
            k.key(suffix), lambda x, n=name: received[n].append((VideoFrame.decode(x.payload.to_bytes()), time.time_ns()))
        )
    wait_until(lambda: len(received["camera"]) >= 3 and len(received["ultrasound"]) >= 3, timeout=10.0, message="frames")
    assert agent.video_session is not None and agent.video_session is not agent.session
    for name, (w, h) in (("camera", (160, 120)), ("ultrasound", (128, 96))):
        frames = received[name]
        assert [f.seq for f, _ in frames] == sorted(f.seq for f, _ in frames)
        for f, recv_ns in frames:
            assert f.source == name and (f.width, f.height) == (w, h) and f.t <= recv_ns
            assert decode_frame(f).shape[:2] == (h, w)


def test_missing_camera_does_not_take_the_agent_down(edge_factory, operator_factory, caplog) -> None:
    agent = edge_factory(video={"camera": {"source": "opencv", "device": "/dev/does-not-exist"}})
    stream = agent.video[0]
    wait_until(lambda: stream.error != "", message="camera error")
    assert "cannot open video device '/dev/does-not-exist'" in stream.error
    op = operator_factory()
    assert op.wait_for_state() is not None  # the control plane is alive


@pytest.mark.parametrize("bad", [{"camera": {"fps": 0}}, {"ultrasound": {"source": "pattern"}}, {"camera": {"quality": 101}}])
def test_bad_video_config_fails_with_the_key(bad: dict) -> None:
    from iorthand.config import ConfigError
    from tests.conftest import edge_config

    with pytest.raises(ConfigError, match="video"):
        edge_config("tcp/127.0.0.1:1", video=bad)
