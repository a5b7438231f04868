"""A video stream never goes silent on an error: a frame of the wrong size, an encoder or a network error in the
sender each become failure notices that say why (and the stream carries on when the cause is gone), never a
stream that stops while its viewers keep their last picture as if it were live."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
import zenoh

from iorthand import keys
from iorthand.protocol import VideoFrame
from iorthand_edge import media
from iorthand_edge.video import FrameSource, StreamConfig, VideoError, VideoStream
from iorthand_edge.video.h264 import H264Decoder, H264Encoder
from tests.conftest import edge_config, wait_until


class SizedSource(FrameSource):
    """A camera that delivers ``size`` (w, h) whatever the stream asked for (cameras often do)."""

    description = "a camera that ignores the requested size"

    def __init__(self, size: tuple[int, int]) -> None:
        self.size = size
        self.n = 0

    def open(self) -> None:
        pass

    def grab(self) -> np.ndarray:
        self.n += 1
        image = np.full((self.size[1], self.size[0], 3), 128, np.uint8)
        image[:, : (self.n * 3) % self.size[0]] = 40  # a moving edge: every frame differs
        return image


class Recorder:
    """A publisher: keeps what it is given; ``fail`` (a callable of the call number) makes put() raise."""

    def __init__(self, fail=lambda _n: False) -> None:
        self.frames: list[VideoFrame] = []
        self.calls = 0
        self.fail = fail
        self.lock = threading.Lock()

    def put(self, payload: bytes) -> None:
        with self.lock:
            self.calls += 1
            if self.fail(self.calls):
                raise zenoh.ZError("the session is closed")
            self.frames.append(VideoFrame.decode(payload))

    def snapshot(self) -> list[VideoFrame]:
        with self.lock:
            return list(self.frames)


def run(source: FrameSource, config: StreamConfig, pub: Recorder, until, timeout: float = 10.0) -> VideoStream:
    stream = VideoStream("camera", keys.VIDEO_CAMERA, config, source)
    stop = threading.Event()
    stream.start_with(pub, stop)
    try:
        wait_until(lambda: until(stream, pub.snapshot()), timeout=timeout,
                   message=f"the stream's outcome (sent {stream.sent}, error {stream.error!r})")
        assert all(w.is_alive() for w in stream._workers), "a stream thread ended"
    finally:
        stop.set()
        stream.join()
    return stream


def test_frames_of_another_size_on_h264_give_failure_notices_naming_both_sizes() -> None:
    """The red team's scenario (scaled down): a stream configured 64×48 whose camera delivers 128×96. The old
    sender died on the first frame and the capture thread cleared its error: captured 40, sent 0, silence."""
    config = StreamConfig(width=64, height=48, fps=20, codec="h264", stall_timeout=0.5, retry_interval=0.3)
    pub = Recorder()
    stream = run(SizedSource((128, 96)), config, pub, lambda _s, frames: sum(bool(f.failure) for f in frames) >= 3)
    frames = pub.snapshot()
    assert frames and all(f.failure and not f.data for f in frames)  # no picture, and never silence
    for f in frames:
        assert "128×96" in f.failure and "64×48" in f.failure, f.failure
        assert (f.width, f.height, f.source) == (64, 48, "camera")
    assert "128×96" in stream.error and "64×48" in stream.error
    assert [f.seq for f in frames] == list(range(1, len(frames) + 1))


def test_an_encoder_error_is_a_failure_notice_and_the_stream_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = {"n": 0}
    real = H264Encoder.encode

    def flaky(self: H264Encoder, image: np.ndarray, t_ms: int) -> list[tuple[bytes, bool]]:
        calls["n"] += 1
        if calls["n"] in (3, 4):
            raise VideoError("H.264 encoding failed: [Errno 12] Cannot allocate memory")
        return real(self, image, t_ms)

    monkeypatch.setattr(H264Encoder, "encode", flaky)
    config = StreamConfig(width=64, height=48, fps=30, codec="h264", adaptive=False)
    pub = Recorder()
    run(SizedSource((64, 48)), config, pub,
        lambda _s, frames: sum(bool(f.data) for f in frames) >= 8 and any(f.failure for f in frames))
    frames = pub.snapshot()
    notices = [f for f in frames if f.failure]
    assert notices and all("Cannot allocate memory" in f.failure for f in notices)
    first = frames.index(notices[0])
    after = [f for f in frames[first:] if f.data]
    assert after and after[0].keyframe  # the viewers lost a frame: they can start again at once
    decoder = H264Decoder()
    assert decoder.decode(after[0].data, after[0].keyframe, gap=True)  # a picture again
    assert [f.seq for f in frames] == list(range(1, len(frames) + 1))


def test_a_failing_put_does_not_end_the_sender_and_its_error_is_kept() -> None:
    """While put() fails the stream says why (stream.error, not cleared by the capture thread, which still gets
    frames); once the link is back the frames flow again."""
    config = StreamConfig(width=64, height=48, fps=30, codec="jpeg")
    broken = threading.Event()
    broken.set()
    pub = Recorder(fail=lambda _n: broken.is_set())
    stream = VideoStream("camera", keys.VIDEO_CAMERA, config, SizedSource((64, 48)))
    stop = threading.Event()
    stream.start_with(pub, stop)
    try:
        wait_until(lambda: pub.calls >= 6, timeout=10.0, message="several attempts to put")
        captured = stream.captured
        time.sleep(0.3)
        assert stream.captured > captured  # the capture thread runs on ...
        assert "ZError" in stream.error and "session is closed" in stream.error  # ... and the sender's error stays
        assert stream.send_failures >= 3
        broken.clear()
        wait_until(lambda: len(pub.snapshot()) >= 5, timeout=10.0, message="frames again once put() works")
        wait_until(lambda: stream.error == "", timeout=5.0, message="the error cleared by the sender")
        assert all(w.is_alive() for w in stream._workers)
    finally:
        stop.set()
        stream.join()
    assert all(f.data and not f.failure for f in pub.snapshot()[-3:])


def test_a_source_bug_is_reported_and_retried_not_silence() -> None:
    class Buggy(SizedSource):
        description = "a buggy camera"

        def grab(self) -> np.ndarray:
            raise KeyError("frame")

    config = StreamConfig(width=64, height=48, fps=30, codec="jpeg", retry_interval=0.2)
    pub = Recorder()
    stream = run(Buggy((64, 48)), config, pub, lambda _s, frames: sum(bool(f.failure) for f in frames) >= 2)
    assert all("internal error" in f.failure and "KeyError" in f.failure for f in pub.snapshot())
    assert stream.failures >= 2


def test_a_source_whose_close_raises_is_reported_and_reopened_not_a_dead_stream() -> None:
    """A driver that fails to release a device that vanished: the notices say so and the stream keeps retrying
    (the close() error used to end the capture thread after one notice, and join() raised it)."""

    class BadRelease(SizedSource):
        description = "a camera whose release fails"

        def __init__(self, size: tuple[int, int]) -> None:
            super().__init__(size)
            self.opened = 0

        def open(self) -> None:
            self.opened += 1

        def grab(self) -> np.ndarray:
            raise VideoError("the camera was unplugged")

        def close(self) -> None:
            raise OSError("release failed")

    config = StreamConfig(width=64, height=48, fps=30, codec="jpeg", retry_interval=0.05)
    pub = Recorder()
    source = BadRelease((64, 48))
    stream = run(source, config, pub, lambda _s, frames: sum(bool(f.failure) for f in frames) >= 3)
    notices = pub.snapshot()
    assert source.opened >= 3
    assert all(
        "the camera was unplugged" in f.failure
        and "closing a camera whose release fails failed: OSError: release failed" in f.failure
        for f in notices
    )
    assert "release failed" in stream.error


def test_a_perception_fed_video_of_another_size_refuses_to_start() -> None:
    perception = {"camera": {"kind": "synthetic", "width": 640, "height": 480, "fps": 15}}
    bad = edge_config("tcp/127.0.0.1:1", perception=perception,
                      video={"camera": {"source": "perception", "width": 1280, "height": 720, "fps": 15}})
    with pytest.raises(VideoError, match=r"1280×720.*640×480"):
        media.check_config(bad)
    good = edge_config("tcp/127.0.0.1:1", perception=perception,
                       video={"camera": {"source": "perception", "width": 640, "height": 480, "fps": 15}})
    media.check_config(good)
