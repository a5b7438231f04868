"""Video: the simulated ultrasound responds to contact, JPEG and H.264 frames carry capture time and sequence, the
sender drops frames instead of queueing, the H.264 bitrate follows the link, and both streams flow through a
router on the video session."""

from __future__ import annotations

import contextlib
import os
import random
import re
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from iorthand import keys
from iorthand.config import from_dict
from iorthand.protocol import VideoFrame
from iorthand.transport import VIDEO
from iorthand_edge.perception.camera import CameraError, CameraSource, Frame
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.perception.pipeline import PerceptionPipeline
from iorthand_edge.video import (
    FrameSource,
    LatestSlot,
    StreamConfig,
    VideoError,
    VideoStream,
    decode_frame,
    make_source,
    render_ultrasound,
)
from iorthand_edge.video.bitrate import BitrateController, BitrateSettings
from iorthand_edge.video.h264 import H264Decoder, H264Encoder
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
    config = StreamConfig(width=160, height=120, quality=70, codec="jpeg")
    image = make_source(config, lambda: 0.0).grab()
    frame = encode_frame("camera", Captured(7, 1_700_000_000_123_456_789, image), config)
    back = VideoFrame.decode(frame.encode())
    assert (back.seq, back.t, back.width, back.height, back.source) == (7, 1_700_000_000_123_456_789, 160, 120, "camera")
    assert decode_frame(back).shape == (120, 160, 3) and back.failure == ""
    notice = VideoFrame.decode(encode_frame("camera", Captured(8, 1_700_000_000_2, None, failure="unplugged"), config).encode())
    assert (notice.seq, notice.width, notice.height, notice.data, notice.failure) == (8, 160, 120, b"", "unplugged")


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
    # The frames skipped at the source were never encoded: the stream a receiver gets is whole (seq counts the
    # frames sent, so a gap would be a loss on the way), and the stream counts what it skipped.
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))
    assert stream.dropped > 0 and stream.captured > stream.sent
    # No backlog: every frame sent was captured at most ~one put + one frame period before it was sent.
    ages = [(sent - captured) / 1e9 for _, captured, sent in pub.frames[2:]]
    assert max(ages) < 0.1 + 0.1 + 1 / 30 + 0.3  # 0.3 s of slack for a loaded machine; a queue would grow without bound


class Recorder:
    """A publisher that keeps what it was given (decoded)."""

    def __init__(self) -> None:
        self.frames: list[VideoFrame] = []

    def put(self, payload: bytes) -> None:
        self.frames.append(VideoFrame.decode(payload))


class FlakySource(FrameSource):
    """A camera that cannot be opened ``fail_opens`` times, then gives ``frames_per_open`` frames per opening
    and nothing after them (a stalled capture device). Stands in for a USB camera, which this machine has not."""

    description = "the flaky camera"

    def __init__(self, fail_opens: int, frames_per_open: int) -> None:
        self.fail_opens, self.frames_per_open = fail_opens, frames_per_open
        self.opens = self.closes = 0
        self._left = 0

    def open(self) -> None:
        self.opens += 1
        if self.opens <= self.fail_opens:
            raise VideoError(f"cannot open the flaky camera (attempt {self.opens})")
        self._left = self.frames_per_open

    def grab(self) -> np.ndarray | None:
        if self._left == 0:
            return None
        self._left -= 1
        return np.full((24, 32, 3), 100, np.uint8)

    def close(self) -> None:
        self.closes += 1


def _run_stream(source: FrameSource, config: StreamConfig, until) -> tuple[VideoStream, Recorder]:
    stream = VideoStream("camera", keys.VIDEO_CAMERA, config, source)
    pub = Recorder()
    stop = threading.Event()
    stream.start_with(pub, stop)
    try:
        wait_until(lambda: until(pub.frames), timeout=10.0, message="video messages")
    finally:
        stop.set()
        stream.join()
    return stream, pub


def test_a_camera_that_cannot_be_opened_is_retried_and_every_attempt_says_why() -> None:
    config = StreamConfig(width=32, height=24, fps=50, retry_interval=0.3, codec="jpeg")
    source = FlakySource(fail_opens=2, frames_per_open=1_000_000)
    stream, pub = _run_stream(source, config, lambda frames: sum(f.failure == "" for f in frames) >= 3)
    failures = [f for f in pub.frames if f.failure]
    texts = [f.failure for f in failures]
    # Both attempts, in order. (The sender keeps only the newest item: a notice not sent within retry_interval
    # is replaced by the next one, as the stream's design intends, so a starved machine may show one.)
    expected = [f"cannot open the flaky camera (attempt {n})" for n in (1, 2)]
    assert texts and texts == [e for e in expected if e in texts], texts
    assert all((f.data, f.width, f.height, f.source) == (b"", 32, 24, "camera") for f in failures)
    assert pub.frames[: len(failures)] == failures  # the notices came first, then pictures
    assert all(decode_frame(f).shape == (24, 32, 3) for f in pub.frames[len(failures):])
    seqs = [f.seq for f in pub.frames]
    assert seqs == sorted(set(seqs))  # one sequence for notices and pictures: the recorder's loss count holds
    assert (stream.failures, stream.error) == (2, "")


def test_a_camera_that_stops_giving_frames_is_reopened() -> None:
    config = StreamConfig(width=32, height=24, fps=50, retry_interval=0.3, stall_timeout=0.2, codec="jpeg")
    source = FlakySource(fail_opens=0, frames_per_open=5)
    _, pub = _run_stream(source, config, lambda frames: sum(bool(f.failure) for f in frames) >= 2
                         and frames[-1].failure == "")
    kinds = "".join("x" if f.failure else "." for f in pub.frames)
    # Frames, a stall, reopened: frames again. At most 5 in a row (fewer if the sender had to drop one).
    assert re.fullmatch(r"(\.{1,5}x)+\.{1,5}x?", kinds), kinds  # (x?: a stall just as the test stopped)
    first = kinds.index("x")
    assert pub.frames[first].failure == "no frame from the flaky camera for 0.2 s"
    assert source.opens >= 3 and source.closes >= 2
    # The stall is noticed after stall_timeout, not sooner: the notice is stamped ≥ 0.2 s after the last frame.
    assert pub.frames[first].t - pub.frames[first - 1].t >= 0.2e9


def test_video_qos_is_low_priority_blocks_at_the_sender_and_may_go_as_datagrams() -> None:
    """BLOCK: a full uplink shows as a slow put at the edge (which then skips frames at the source and lowers the
    bitrate), not as frames dropped from its queue (a lost H.264 frame spoils the ones after it). Best effort: where
    a datagram link exists, a packet lost on the radio costs frames, not a stall of the stream
    (tests/test_datagram_links.py)."""
    import zenoh

    assert VIDEO.priority == zenoh.Priority.DATA_LOW and VIDEO.congestion == zenoh.CongestionControl.BLOCK
    assert VIDEO.reliability == zenoh.Reliability.BEST_EFFORT


def test_streams_through_the_router_on_their_own_session(edge_factory, session_factory) -> None:
    video = {
        "camera": {"source": "pattern", "width": 160, "height": 120, "fps": 10, "codec": "h264"},
        "ultrasound": {"source": "ultrasound_sim", "width": 128, "height": 96, "fps": 10, "codec": "jpeg"},
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
    # Published by the media process, on its own session: not one video thread in the agent's process.
    assert agent.media is not None and agent.media.pid not in (None, os.getpid())
    assert not [t.name for t in threading.enumerate() if "video" in t.name]
    decoder = H264Decoder()
    for name, (w, h) in (("camera", (160, 120)), ("ultrasound", (128, 96))):
        frames = received[name]
        assert [f.seq for f, _ in frames] == sorted(f.seq for f, _ in frames)
        for f, recv_ns in frames:
            assert f.source == name and (f.width, f.height) == (w, h) and f.t <= recv_ns
            if name == "camera":  # H.264: the first keyframe starts the picture, then every frame decodes
                assert f.encoding == "h264"
                images = decoder.decode(f.data, f.keyframe)
                assert all(i.shape[:2] == (h, w) for i in images)
            else:
                assert decode_frame(f).shape[:2] == (h, w)
    assert received["camera"][0][0].keyframe  # a stream starts with one


def test_missing_camera_does_not_take_the_agent_down_and_its_failure_reaches_the_subscribers(
    edge_factory, operator_factory, session_factory
) -> None:
    """Real OpenCV on a device path that does not exist, through a real router: every attempt to reopen it
    reaches a video subscriber with the reason, and the robot's control plane is unaffected."""
    notices: list[VideoFrame] = []
    s = session_factory()
    s.declare_subscriber(keys.RobotKeys("sim1").key(keys.VIDEO_CAMERA),
                         lambda x: notices.append(VideoFrame.decode(x.payload.to_bytes())))
    edge_factory(video={"camera": {"source": "opencv", "device": "/dev/does-not-exist", "retry_interval": 0.2}})
    wait_until(lambda: len(notices) >= 2, timeout=10.0, message="two failure notices")
    assert "cannot open video device '/dev/does-not-exist'" in notices[0].failure
    assert all(n.failure == notices[0].failure and n.data == b"" for n in notices)
    op = operator_factory()
    assert op.wait_for_state() is not None  # the control plane is alive


@pytest.mark.parametrize("bad", [{"camera": {"fps": 0}}, {"ultrasound": {"source": "pattern"}}, {"camera": {"quality": 101}},
                                 {"camera": {"fps": 5, "stall_timeout": 0.3}}])
def test_bad_video_config_fails_with_the_key(bad: dict) -> None:
    from iorthand.config import ConfigError
    from tests.conftest import edge_config

    with pytest.raises(ConfigError, match="video"):
        edge_config("tcp/127.0.0.1:1", video=bad)


def test_h264_frames_decode_in_order_and_start_at_a_keyframe() -> None:
    config = StreamConfig(width=160, height=120, fps=30, codec="h264", bitrate_kbps=300, min_bitrate_kbps=100)
    enc = H264Encoder(160, 120, 30, 300_000, keyframe_interval=1.0)
    source = make_source(config, lambda: 0.0)
    frames = [encode_frame("camera", Captured(i, 1_700_000_000_000_000_000 + i * 33_000_000, source.grab()), config, enc)
              for i in range(1, 46)]
    assert all(f is not None and f.encoding == "h264" for f in frames)
    keys_at = [f.seq for f in frames if f.keyframe]
    assert keys_at[:2] == [1, 31]  # the first frame, then one a second (30 frames at 30 fps)
    back = [VideoFrame.decode(f.encode()) for f in frames]
    dec = H264Decoder()
    assert all(dec.decode(f.data, f.keyframe)[0].shape == (120, 160, 3) for f in back)
    # A viewer that joins in the middle decodes nothing until a keyframe, then everything.
    late = H264Decoder()
    got = [bool(late.decode(f.data, f.keyframe)) for f in back[10:]]
    assert not any(got[:20]) and all(got[20:])  # seq 11…30 wait; the keyframe at seq 31 starts the picture
    # On request (a viewer's feedback), the next frame is a keyframe; so is the first at a new bitrate. Requests
    # while the keyframe is on its way (other viewers, or the same viewer's next undecodable frames) get no other.
    now = time.monotonic()
    assert enc.viewer_asks_keyframe(now + 1.0)
    assert encode_frame("camera", Captured(99, 1, source.grab()), config, enc).keyframe
    assert not enc.viewer_asks_keyframe() and not enc.viewer_asks_keyframe(time.monotonic() + 0.1)
    assert not encode_frame("camera", Captured(100, 2, source.grab()), config, enc).keyframe
    assert enc.viewer_asks_keyframe(time.monotonic() + 0.25)  # that keyframe was lost too: asked again later
    assert encode_frame("camera", Captured(101, 3, source.grab()), config, enc).keyframe
    assert not encode_frame("camera", Captured(102, 4, source.grab()), config, enc).keyframe
    enc.set_bitrate(150_000)
    assert encode_frame("camera", Captured(103, 5, source.grab()), config, enc).keyframe


def test_a_grey_picture_reaches_x264_as_pyav_would_have_converted_it_and_decodes_back() -> None:
    """The encoder converts a grey picture (the ultrasound) to x264's planes itself, not through PyAV's swscale: the
    planes must be swscale's for every grey level, and the picture must survive x264 and the decoder."""
    import av
    import cv2

    from iorthand_edge.video.h264 import grey_to_yuv420p

    grey = np.tile(np.arange(256, dtype=np.uint8), (4, 1))  # every level, 4 × 256
    swscale = av.VideoFrame.from_ndarray(grey, format="gray").reformat(format="yuv420p").to_ndarray()
    assert np.array_equal(grey_to_yuv420p(grey), swscale)
    image = render_ultrasound(160, 120, 5.0, np.random.default_rng(3))
    enc, dec = H264Encoder(160, 120, 30, 2_000_000, keyframe_interval=1.0), H264Decoder()
    (data, key), = enc.encode(image, 0)
    (back,) = dec.decode(data, key)
    assert key and np.abs(back.astype(int) - cv2.cvtColor(image, cv2.COLOR_GRAY2BGR).astype(int)).mean() < 3
    assert np.abs(back[..., 0].astype(int) - back[..., 2].astype(int)).max() <= 2  # still grey: no colour cast


def _exact_yuv420p(image: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """BT.601 limited range in floats, each chroma sample its 2×2 block's mean: what yuv420p means."""
    f = image.astype(np.float64)
    b, g, r = f[..., 0], f[..., 1], f[..., 2]
    h, w = image.shape[:2]
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = (128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255).reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    v = (128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255).reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
    return y, u, v


def _planes(flat: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    flat, q = flat.reshape(-1).astype(np.float64), (h // 2) * (w // 2)
    return flat[:h * w].reshape(h, w), flat[h * w:h * w + q].reshape(h // 2, w // 2), flat[h * w + q:].reshape(h // 2, w // 2)


@pytest.mark.parametrize("size", [(480, 640), (242, 322)])  # the camera's; a half height that is odd
def test_a_colour_picture_reaches_x264_at_least_as_exact_as_pyavs_own_conversion(size: tuple[int, int]) -> None:
    """The encoder converts BGR to x264's planes itself (half of swscale's time): luma and each block's mean colour
    must be as close to BT.601's as swscale's (OpenCV's own I420 takes one pixel's colour per block: 1.9 levels off
    on average)."""
    import av
    import cv2

    from iorthand_edge.video.h264 import bgr_to_yuv420p

    h, w = size
    rng = np.random.default_rng(7)
    for image in (rng.integers(0, 256, (h, w, 3), dtype=np.uint8),
                  cv2.GaussianBlur(rng.integers(0, 256, (h, w, 3), dtype=np.uint8), (9, 9), 3)):
        exact = _exact_yuv420p(image)
        ours = _planes(bgr_to_yuv420p(image), h, w)
        pyav = _planes(av.VideoFrame.from_ndarray(image, format="bgr24").reformat(format="yuv420p").to_ndarray(), h, w)
        for mine, theirs, truth in zip(ours, pyav, exact, strict=True):
            assert np.abs(mine - truth).mean() <= np.abs(theirs - truth).mean() + 0.05
            assert np.abs(mine - truth).max() <= 1.6  # (swscale's own: 1.35)


def test_the_bitrate_falls_at_once_on_congestion_and_climbs_back_slowly() -> None:
    s = BitrateSettings(start=1_000_000, min=200_000, max=2_000_000, hold=2.0)
    c = BitrateController(s, frame_period=1 / 30)
    assert c.decide(0.0) == pytest.approx(1_100_000)  # no congestion: +10 % per hold
    c.on_put(0.030)  # a put of 30 ms at 30 fps: the uplink queue was full
    assert c.decide(1.0) == pytest.approx(1_100_000)  # within the hold: one cut per burst, not per frame
    assert c.decide(2.0) == pytest.approx(770_000) and "a put took 30 ms" in c.reason
    for _ in range(30):
        c.on_capture(skipped=1)  # the slot replaced every frame: the sender is behind
    assert c.decide(4.0) == pytest.approx(539_000)
    c.on_feedback(received=90, lost=10, delay_p90=0.05)  # a viewer lost 10 %
    assert c.decide(6.0) == pytest.approx(377_300)
    c.on_feedback(received=30, lost=0, delay_p90=0.8)  # frames arriving late: queueing on the way
    for t in (8.0, 10.0, 12.0):
        c.decide(t)
        c.on_feedback(received=30, lost=0, delay_p90=0.8)
    assert c.target == s.min  # never below the floor
    for t in range(14, 80, 2):  # ×1.1 every 2 s: the floor to the ceiling (×10) in about 50 s
        c.decide(float(t))
    assert c.target == s.max  # climbs back, never past the ceiling


class IrregularCamera(CameraSource):
    """A perception camera whose clock is not the stream's: ``count`` images, each numbered by its grey level (5
    per number: JPEG keeps that), 5 to 45 ms apart, then nothing until interrupted."""

    description = "the irregular test camera"

    def __init__(self, count: int) -> None:
        self.count, self.index = count, 0
        self._gaps = random.Random(5)
        self._interrupted = threading.Event()

    def open(self) -> None:
        pass

    def read(self) -> Frame:
        if self.index >= self.count:
            self._interrupted.wait()
            raise CameraError("interrupted")
        time.sleep(self._gaps.uniform(0.005, 0.045))
        image = np.full((48, 64, 3), 5 * self.index, np.uint8)
        self.index += 1
        return Frame(image, time.time_ns(), self.index - 1)

    def close(self) -> None:
        pass

    def interrupt(self) -> None:
        self._interrupted.set()


class DriverStampedCamera(IrregularCamera):
    """As IrregularCamera, but each frame carries a driver's capture stamp 80 ms before it is read (frames that
    waited in the device's buffers), as a V4L2 camera's can; ``stamps`` keeps each image number's."""

    def __init__(self, count: int) -> None:
        super().__init__(count)
        self.stamps: dict[int, int] = {}

    def read(self) -> Frame:
        frame = super().read()
        frame.t_ns -= 80_000_000
        self.stamps[frame.index] = frame.t_ns
        return frame


@contextlib.contextmanager
def perception_video(camera: object) -> Iterator[tuple[VideoStream, Recorder]]:
    """A JPEG camera stream fed by a perception pipeline reading ``camera``, both running; stopped on exit."""
    perception = from_dict({"camera": {"kind": "synthetic", "width": 64, "height": 48, "fps": 30.0}}, PerceptionConfig)
    pipeline = PerceptionPipeline(perception, lambda _t: None, lambda _t: None, lambda _m: None, camera=camera)
    config = StreamConfig(width=64, height=48, fps=30, codec="jpeg", source="perception")
    stream = VideoStream("camera", keys.VIDEO_CAMERA, config, make_source(config, lambda: 0.0, pipeline.next_image))
    pub = Recorder()
    stop = threading.Event()
    stream.start_with(pub, stop)
    pipeline.start()
    try:
        yield stream, pub
    finally:
        pipeline.stop()
        stop.set()
        stream.join()


def test_the_camera_video_carries_each_perception_frames_capture_time() -> None:
    """A video frame fed by the perception camera is stamped with that frame's capture time (its markers carry
    the same), not with the time the video thread received it (which was 80 ms late here)."""
    camera = DriverStampedCamera(10)
    with perception_video(camera) as (stream, pub):
        wait_until(lambda: len(pub.frames) + stream.dropped == 10, timeout=10.0, message="the camera's 10 images")
    assert pub.frames
    for f in pub.frames:
        number = round(float(decode_frame(f).mean()) / 5)
        assert f.t == camera.stamps[number], (number, (f.t - camera.stamps[number]) / 1e6)


def test_the_camera_video_sends_each_perception_image_once_whatever_its_rate() -> None:
    """The stream takes the perception camera's images as they arrive: none twice, none skipped, in order, even
    when the camera's rate is irregular and above the stream's. (Polling at the stream's own rate sent some twice
    or dropped some, and each up to a period late.)"""
    with perception_video(IrregularCamera(40)) as (stream, pub):
        wait_until(lambda: stream.captured == 40 and len(pub.frames) + stream.dropped == 40, timeout=10.0,
                   message="the camera's 40 images through the stream")
        time.sleep(0.1)  # nothing more comes
    assert stream.captured == 40
    numbers = [round(float(decode_frame(f).mean()) / 5) for f in pub.frames]
    assert numbers == sorted(set(numbers)), numbers  # never one twice, never out of order
    assert len(numbers) + stream.dropped == 40  # what was not sent, the sender dropped and counted (a slow encode)
    assert not stream.error
