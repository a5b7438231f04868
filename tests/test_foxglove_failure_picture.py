"""The twin's live Foxglove view replaces the picture when the video fails: an image panel keeps the last image
it was given, so a failure notice (which has no picture) left viewers a frozen picture that looked live."""

from __future__ import annotations

import io
import time

import av
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from PIL import Image

from iorthand import keys
from iorthand.protocol import VideoFrame
from iorthand_cloud.foxglove_channels import NOTICE_INTERVAL_NS, FoxgloveChannel, FoxgloveConverter
from iorthand_cloud.twin.config import FoxgloveLiveConfig
from iorthand_cloud.twin.foxglove import FoxgloveLive

KEY = keys.RobotKeys("r1").key(keys.VIDEO_CAMERA)


class Logged:
    """Stands in for a foxglove.Channel: keeps what the live view logs into it (no server, no client)."""

    def __init__(self, ch: FoxgloveChannel, into: list[tuple[str, str, bytes]]) -> None:
        self.ch, self.into = ch, into

    def log(self, data: bytes, log_time: int) -> None:
        self.into.append((self.ch.topic, self.ch.schema_name, data))


def live_view() -> tuple[FoxgloveLive, FoxgloveConverter, list[tuple[str, str, bytes]]]:
    live = FoxgloveLive(FoxgloveLiveConfig())
    logged: list[tuple[str, str, bytes]] = []
    live._channel = lambda ch: Logged(ch, logged)  # type: ignore[method-assign]
    return live, FoxgloveConverter(video=True), logged  # as the live view makes it


def jpeg(value: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.full((48, 64, 3), value, np.uint8)).save(buf, format="JPEG")
    return buf.getvalue()


def test_a_failure_notice_replaces_the_last_jpeg_with_a_picture_that_says_so() -> None:
    live, conv, logged = live_view()
    picture = VideoFrame(source="camera", width=64, height=48, data=jpeg(200)).stamp(1)
    live._forward(conv, KEY, picture.encode(), time.time_ns())
    notice = VideoFrame(source="camera", width=640, height=480, failure="cannot open video device '0'").stamp(2)
    live._forward(conv, KEY, notice.encode(), time.time_ns())
    images = [(s, d) for t, s, d in logged if t == "/r1/camera"]
    assert len(images) == 2, "the notice put no picture on the image topic: the last frame stays, as if live"
    schema, data = images[-1]
    assert schema == "foxglove.CompressedImage"
    shown = CompressedImage.FromString(data)
    assert shown.format == "jpeg" and shown.frame_id == "r1/camera"
    image = np.asarray(Image.open(io.BytesIO(shown.data)).convert("RGB"))
    assert image.shape == (480, 640, 3)  # the stream's size, as the notice gives it
    assert image.mean() < 60  # a dark notice, not the bright picture before it
    assert any(t == "/r1/events" for t, _, _ in logged)  # the events log says it too
    # The source retrying: one notice picture per half second, not one per notice.
    live._forward(conv, KEY, notice.stamp(3).encode(), time.time_ns())
    assert len([1 for t, _, _ in logged if t == "/r1/camera"]) == 2


def test_on_an_h264_stream_the_notice_is_a_keyframe_of_the_streams_size() -> None:
    live, conv, logged = live_view()
    notice = VideoFrame(source="camera", width=320, height=240, encoding="h264", failure="frame not sent").stamp(1)
    live._forward(conv, KEY, notice.encode(), time.time_ns())
    ((schema, data),) = [(s, d) for t, s, d in logged if t == "/r1/camera"]
    assert schema == "foxglove.CompressedVideo"
    shown = CompressedVideo.FromString(data)
    assert shown.format == "h264"
    decoder = av.CodecContext.create("h264", "r")
    packets = [*decoder.parse(shown.data), *decoder.parse(None)]  # the parser holds the last unit until flushed
    frames = [f for p in packets for f in decoder.decode(p)]
    frames += list(decoder.decode(None))
    assert len(frames) == 1 and frames[0].key_frame and (frames[0].width, frames[0].height) == (320, 240)


def test_live_failure_pictures_are_timed_by_the_twins_clock_not_the_edges() -> None:
    """Found by a review: the pictures were limited to one per NOTICE_INTERVAL_NS of the notices' source time, the
    edge's to set: a clock stepping back drew one for every notice, one standing still drew no more. Live, the
    converter times them by its own monotonic clock."""
    live, conv, logged = live_view()

    def pictures() -> int:
        return len([1 for t, _, _ in logged if t == "/r1/camera"])

    notice = VideoFrame(source="camera", width=64, height=48, failure="cannot open video device '0'")
    t0 = time.time_ns()
    started = time.monotonic()
    for i in range(20):  # an edge clock stepping back a second at every notice
        live._forward(conv, KEY, notice.stamp(1 + i, t=t0 - i * 1_000_000_000).encode(), time.time_ns())
    elapsed = time.monotonic() - started
    assert 1 <= pictures() <= 1 + elapsed / (NOTICE_INTERVAL_NS / 1e9), (pictures(), elapsed)
    # Standing still: a notice of the same source time, NOTICE_INTERVAL_NS later on the twin's clock, is drawn.
    before = pictures()
    time.sleep(NOTICE_INTERVAL_NS / 1e9)
    live._forward(conv, KEY, notice.stamp(21, t=t0 - 19 * 1_000_000_000).encode(), time.time_ns())
    assert pictures() == before + 1, "a notice with a standing clock drew no picture"
