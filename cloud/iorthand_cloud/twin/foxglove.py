"""The twin's live view in the Foxglove app: the recorder's Foxglove channels, served over the Foxglove
WebSocket protocol by foxglove-sdk's server (``foxglove: {enabled: true}`` in the twin's config).

The channels, topics and frames are those of :mod:`iorthand_cloud.foxglove_channels` (the same conversion the
recorder writes into ``<session>/foxglove/``), so a live view and a recording open with the same Foxglove
layout. Each channel is advertised when its first message arrives (a robot that never spoke has none).

Threads, as in the rest of the twin: the Zenoh callbacks only queue (state on a drop-oldest inbox, video on a
small one of its own so big frames never delay poses and safety logs); ``twin-foxglove`` and
``twin-foxglove-video`` decode, convert and hand the bytes to the server, whose own threads (in Rust) send them.
The server queues per client and drops for a client that reads too slowly (foxglove-sdk sends lossily); logging
into it never blocks on a client.

The server is read-only: it advertises no capability, so clients can subscribe, not publish, call services or
set parameters. It declares Zenoh subscribers of its own: the rerun side's rate gates and lazy decoding stay as
they are, and neither view waits for the other.

A video failure notice (the edge's camera failed, or its media process is down) has no picture, and an image
panel keeps the last one it was given: frozen, as if live. So each notice also puts a picture on the image topic:
a dark one that says "VIDEO FAILED" with the reason and the time (:func:`failure_picture`), as a JPEG, or for an
H.264 stream as one H.264 keyframe of the stream's size. The ``events`` log says it too (the converter's).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import io
import logging
import textwrap
import threading
import time
from fractions import Fraction
from typing import Any

import foxglove
import zenoh
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
from PIL import Image, ImageDraw, ImageFont

from iorthand import keys
from iorthand.protocol import DecodeError, Message, VideoFrame, message_type_for
from iorthand.transport import Inbox, Worker
from iorthand_cloud.foxglove_channels import (
    VIDEO_TOPICS,
    FoxgloveChannel,
    FoxgloveConverter,
    FoxgloveMessage,
    frame_id,
)

from .config import FoxgloveLiveConfig

log = logging.getLogger("iorthand.twin.foxglove")

SERVER_NAME = "iorthand twin"
NOTICE_MAX_SIDE = 4096  # px: a notice claiming a bigger frame is drawn at most this big (it is only text)
NOTICE_INTERVAL_NS = 500_000_000  # at most one notice picture per stream this often (viewers that join see one)


def notice_image(text: str, width: int, height: int) -> Image.Image:
    """A dark picture of ``width``×``height`` saying ``VIDEO FAILED`` and ``text`` (wrapped to fit)."""
    width, height = max(16, min(width, NOTICE_MAX_SIDE)), max(16, min(height, NOTICE_MAX_SIDE))
    image = Image.new("RGB", (width, height), (40, 0, 0))
    draw = ImageDraw.Draw(image)
    size = max(8, min(width // 24, height // 12))
    font = ImageFont.load_default(size=size)
    lines = ["VIDEO FAILED", *textwrap.wrap(text, max(8, int(width / (0.6 * size)) - 2))]
    y = size
    for i, line in enumerate(lines):
        draw.text((size, y), line, fill=(255, 80, 80) if i == 0 else (235, 235, 235), font=font)
        y += int(1.4 * size)
    return image


@functools.lru_cache(maxsize=16)
def _notice_data(text: str, width: int, height: int, encoding: str) -> bytes:
    """The notice encoded as the stream's frames are (cached: notices repeat at every retry of the source)."""
    image = notice_image(text, width, height)
    if encoding != "h264":
        buf = io.BytesIO()
        image.save(buf, format="JPEG", quality=80)
        return buf.getvalue()
    import av  # only for H.264 streams (PyAV is what their edge encodes with)

    codec = av.CodecContext.create("libx264", "w")
    codec.width, codec.height = image.width // 2 * 2, image.height // 2 * 2  # 4:2:0 wants even sides
    codec.pix_fmt, codec.time_base = "yuv420p", Fraction(1, 1000)
    codec.options = {"preset": "ultrafast", "tune": "zerolatency"}
    frame = av.VideoFrame.from_image(image.crop((0, 0, codec.width, codec.height))).reformat(format="yuv420p")
    frame.pts = 0
    return b"".join(bytes(p) for p in [*codec.encode(frame), *codec.encode(None)])


def failure_picture(robot: str, name: str, msg: VideoFrame, since_ns: int) -> CompressedImage | CompressedVideo:
    """What the image topic ``name`` shows for a failure notice: the failure (failing since ``since_ns``) as a
    picture of the stream's size (a JPEG, or for an H.264 stream a keyframe, which a decoder takes without the
    frames before it)."""
    when = dt.datetime.fromtimestamp(since_ns / 1e9, dt.UTC).strftime("%H:%M:%S UTC")
    text = f"{msg.failure} (since {when}: this is not a live picture)"
    h264 = msg.encoding == "h264"
    out = CompressedVideo(format="h264") if h264 else CompressedImage(format="jpeg")
    out.data = _notice_data(text, msg.width, msg.height, "h264" if h264 else "jpeg")
    out.timestamp.seconds, out.timestamp.nanos = divmod(max(msg.t, 0), 1_000_000_000)
    out.frame_id = frame_id(robot, name)
    return out


def failure_messages(conv: FoxgloveConverter, key: str, msg: Message, since_ns: int) -> list[FoxgloveMessage]:
    """For a video failure notice on ``key`` (failing since ``since_ns``), the notice picture on its image
    topic; else nothing."""
    if not isinstance(msg, VideoFrame) or not msg.failure:
        return []
    try:
        robot, suffix = keys.split_key(key)
    except keys.KeyExprError:
        return []
    name = VIDEO_TOPICS.get(suffix)
    if name is None:
        return []
    picture = failure_picture(robot, name, msg, since_ns)
    schema = "CompressedVideo" if isinstance(picture, CompressedVideo) else "CompressedImage"
    return [FoxgloveMessage(conv.channel(robot, name, schema, key), picture.SerializeToString(), msg.t)]


class FoxgloveLive:
    """Start with :meth:`start` on the twin's Zenoh session; :meth:`stop` ends the server and the threads."""

    def __init__(self, config: FoxgloveLiveConfig) -> None:
        self.config = config
        self.context = foxglove.Context()  # its own: nothing else of this process logs into these channels
        self.server: foxglove.WebSocketServer | None = None
        self._stop = threading.Event()
        self._state = Inbox(config.queue, keep="newest")
        self._video = Inbox(8, keep="newest")
        self._channels: dict[FoxgloveChannel, foxglove.Channel] = {}
        self._lock = threading.Lock()  # two worker threads create channels
        # video key → (its failure, receive time of its first notice, of the last one drawn)
        self._failures: dict[str, tuple[str, int, int]] = {}
        self._declared: list[Any] = []
        self._workers: list[Worker] = []
        self.sent = 0  # messages handed to the server
        self.rejected = 0  # payloads that failed to decode (never converted)
        self.errors = 0  # conversions that failed

    @property
    def port(self) -> int:
        return self.server.port if self.server is not None else 0

    @property
    def url(self) -> str:
        """The address the Foxglove app opens ("Open connection" → Foxglove WebSocket)."""
        scheme = "wss" if self.config.tls_cert else "ws"
        return f"{scheme}://{self.config.host}:{self.port}" if self.server is not None else ""

    def start(self, session: zenoh.Session) -> None:
        cfg = self.config
        tls: dict[str, bytes] = {}
        if cfg.tls_cert is not None and cfg.tls_key is not None:
            tls = {"tls_cert": cfg.tls_cert.read_bytes(), "tls_key": cfg.tls_key.read_bytes()}
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=cfg.host, port=cfg.port, context=self.context,
                                                **tls)
        except Exception as exc:  # the SDK raises its own error types: say where it failed to listen
            raise RuntimeError(f"Foxglove server cannot listen on {cfg.host}:{cfg.port}: {exc}") from exc
        state, video = self._state, self._video

        def on_state(sample: zenoh.Sample) -> None:
            state.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        def on_video(sample: zenoh.Sample) -> None:
            video.put((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

        for suffix in FoxgloveConverter.SUFFIXES:
            if suffix in VIDEO_TOPICS and not cfg.video:
                continue
            self._declared.append(session.declare_subscriber(
                keys.all_robots(suffix), on_video if suffix in VIDEO_TOPICS else on_state))
        for name, inbox in (("twin-foxglove", state), ("twin-foxglove-video", video)):
            w = Worker(name, lambda stop, inbox=inbox: self._loop(stop, inbox), self._stop)
            w.start()
            self._workers.append(w)
        log.info("Foxglove live view on %s", self.url)

    def stop(self) -> None:
        self._stop.set()
        for inbox in (self._state, self._video):
            inbox.close()
        for w in self._workers:
            w.join(timeout=3.0)
        for d in self._declared:
            with contextlib.suppress(zenoh.ZError):
                d.undeclare()
        self._declared.clear()
        if self.server is not None:
            self.server.stop()
            self.server = None

    # ------------------------------------------------------------------ the worker threads

    def _loop(self, stop: threading.Event, inbox: Inbox) -> None:
        conv = FoxgloveConverter(video=self.config.video)  # one per thread: its state is per key
        while not stop.is_set():
            item = inbox.get(timeout=0.2)
            if item is None:
                continue
            for key, payload, recv_ns in [item, *inbox.drain()]:
                self._forward(conv, key, payload, recv_ns)

    def _forward(self, conv: FoxgloveConverter, key: str, payload: bytes, recv_ns: int) -> None:
        cls = message_type_for(key)
        if cls is None or not conv.handles(key):
            return
        try:
            msg = cls.decode(payload)
        except DecodeError as exc:
            self.rejected += 1
            if self.rejected == 1 or self.rejected % 1000 == 0:
                log.warning("%d malformed payloads not served (latest on %s: %s)", self.rejected, key, exc)
            return
        try:
            out = conv.convert(key, msg)
            if conv.video and isinstance(msg, VideoFrame) and (since := self._notice_due(key, msg, recv_ns)):
                out = [*failure_messages(conv, key, msg, since), *out]
        except Exception as exc:  # a conversion bug costs that message, never the live view (or the twin)
            self.errors += 1
            if self.errors == 1 or self.errors % 1000 == 0:
                log.error("Foxglove conversion of %s failed (%d so far): %r", key, self.errors, exc)
            return
        for m in out:
            self._channel(m.channel).log(m.data, log_time=recv_ns)
            self.sent += 1

    def _notice_due(self, key: str, msg: VideoFrame, recv_ns: int) -> int | None:
        """For a failure notice whose picture is due, when the failure began (its first notice's receive time);
        None for a frame, or a notice within NOTICE_INTERVAL_NS of the last picture drawn for the same failure
        (the source retries every second or so; a flood of notices must not keep this thread drawing). Only the
        video thread calls it."""
        if not msg.failure:
            self._failures.pop(key, None)
            return None
        reason, since, drawn = self._failures.get(key, ("", recv_ns, 0))
        if msg.failure != reason:
            since, drawn = recv_ns, 0
        elif recv_ns - drawn < NOTICE_INTERVAL_NS:
            return None
        if len(self._failures) >= 1000:  # keys come from the network: never an unbounded table
            self._failures.clear()
        self._failures[key] = (msg.failure, since, recv_ns)
        return since

    def _channel(self, ch: FoxgloveChannel) -> foxglove.Channel:
        channel = self._channels.get(ch)
        if channel is None:
            with self._lock:
                channel = self._channels.get(ch)
                if channel is None:
                    schema = foxglove.Schema(name=ch.schema_name, encoding=ch.schema_encoding, data=ch.schema)
                    channel = self._channels[ch] = foxglove.Channel(
                        ch.topic, schema=schema, message_encoding=ch.message_encoding, context=self.context,
                        metadata=ch.metadata)
        return channel


__all__ = ["SERVER_NAME", "FoxgloveLive"]
