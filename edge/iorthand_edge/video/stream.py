"""Video streams: capture at a fixed rate, encode (H.264 or JPEG), publish on the video session (DATA_LOW, BLOCK).

Two named threads per stream. The capture thread grabs frames on schedule (or, from a source that paces itself,
the perception camera's images, each as it arrives) and stamps each with its capture time and a sequence number;
it hands them over through a one-frame slot. The sender takes the newest frame, encodes it and ``put()``s it. When
encoding or the network is slower than the camera, the frame waiting in the slot is replaced — dropped before it
costs any encoding — so nothing queues and latency stays one frame. ``seq`` numbers the frames *sent*: a gap at a
receiver is a frame lost on the way (an H.264 decoder then waits for a keyframe, a recorder counts it missing); a
frame skipped at the source was never encoded, so the stream stays whole, and the stream counts it (``dropped``).

H.264 (:mod:`iorthand_edge.video.h264`) follows the link: video is published with ``CongestionControl.BLOCK`` so
that a full uplink shows as a slow ``put`` (and frames the slot replaced) rather than as frames lost in transit —
a lost H.264 frame spoils the ones after it until the next keyframe — and the bitrate follows those signals and
the viewers' reports (:mod:`iorthand_edge.video.bitrate`). JPEG frames are independent pictures: the fallback.

A source that cannot be opened, fails, or gives no frame for ``stall_timeout`` s is closed and reopened every
``retry_interval`` s (a USB camera that enumerates after the edge starts, or is unplugged and plugged back).
Every attempt sends a ``VideoFrame`` with no image and ``failure`` set, through the same slot so that it
never overtakes a frame captured before it: the twin shows why the picture stopped instead of a frozen one.
A source that delivers frames of another size than an H.264 stream is configured for counts as failed (the
notice names both sizes): x264 takes only the size it was opened with.

Neither thread ends on an error. A frame the sender cannot encode or ``put()`` (an FFmpeg or Zenoh error, a bug)
is lost, and a failure notice saying why is sent in its place; the next frame is tried afresh. A silent stream
would leave every viewer with its last picture, frozen, as if live. ``error`` is the capture side's problem or
the sender's, each cleared only by the side that set it, once it works again.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import zenoh

from iorthand import keys
from iorthand.protocol import VideoFeedback, VideoFrame
from iorthand.transport import Worker, publisher
from iorthand_edge.video.bitrate import BitrateController, BitrateSettings
from iorthand_edge.video.config import StreamConfig
from iorthand_edge.video.h264 import H264Encoder
from iorthand_edge.video.sources import FrameSource, Image, VideoError

log = logging.getLogger("iorthand.edge.video")


@dataclass(frozen=True)
class Captured:
    seq: int
    t_ns: int  # capture time, wall clock
    image: Image | None  # None: no frame, ``failure`` says why
    failure: str = ""


class LatestSlot:
    """A one-item hand-over that keeps the newest item; replaced items are counted as dropped."""

    def __init__(self) -> None:
        self._item: Captured | None = None
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, item: Captured) -> None:
        with self._cond:
            if self._item is not None:
                self.dropped += 1
            self._item = item
            self._cond.notify()

    def take(self, timeout: float) -> Captured | None:
        with self._cond:
            if self._item is None:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return item


def encode_jpeg(image: Image, quality: int) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise VideoError(f"JPEG encoding failed for a {image.shape} image")
    return buf.tobytes()


def encode_frame(source: str, item: Captured, config: StreamConfig, h264: H264Encoder | None = None) -> VideoFrame | None:
    """The frame to publish for ``item``: a failure notice, a JPEG, or an H.264 access unit (None while the
    encoder holds it back, which ``zerolatency`` never does)."""
    if item.image is None:
        frame = VideoFrame(source=source, width=config.width, height=config.height, encoding=config.codec,
                           failure=item.failure[:256])
        if h264 is not None:
            h264.request_keyframe()  # whoever watches starts again when the source is back
        return frame.stamp(item.seq, item.t_ns)
    h, w = item.image.shape[:2]
    if h264 is None:
        frame = VideoFrame(source=source, width=w, height=h, data=encode_jpeg(item.image, config.quality))
        return frame.stamp(item.seq, item.t_ns)
    units = h264.encode(item.image, item.t_ns // 1_000_000)
    if not units:
        return None
    frame = VideoFrame(source=source, width=w, height=h, encoding="h264", data=b"".join(d for d, _ in units),
                       keyframe=any(k for _, k in units))
    return frame.stamp(item.seq, item.t_ns)


def decode_frame(frame: VideoFrame) -> Image:
    """The image of a JPEG frame (receivers, tests; H.264 needs the stream: :class:`H264Decoder`)."""
    if frame.encoding == "h264":
        raise VideoError(f"frame {frame.seq} from {frame.source} is H.264: decode the stream with H264Decoder")
    image = cv2.imdecode(np.frombuffer(frame.data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise VideoError(f"frame {frame.seq} from {frame.source} is not a valid JPEG")
    return image


class VideoStream:
    def __init__(self, name: str, key_suffix: str, config: StreamConfig, source: FrameSource) -> None:
        self.name = name
        self.key_suffix = key_suffix
        self.config = config
        self.source = source
        self.slot = LatestSlot()
        self.captured = 0  # frames
        self.failures = 0  # failed attempts to open or read the source
        self._seq = 0  # every item handed to the sender: frames and failure notices
        self.sent = 0
        self.bytes_sent = 0
        self.send_failures = 0  # frames the sender could not encode or put()
        self._capture_error = ""  # why the source gives no frames; cleared by the capture thread
        self._send_error = ""  # why the last frame could not be sent; cleared by the sender
        self._pub: Any = None
        self.before_send: Callable[[], None] | None = None  # run before each frame is encoded (the media process's
        # drain of the viewers' reports)
        self._workers: list[Worker] = []
        self.h264: H264Encoder | None = None
        self.bitrate: BitrateController | None = None
        if config.codec == "h264":
            self.h264 = H264Encoder(config.width, config.height, config.fps, 1000 * config.bitrate_kbps,
                                    config.keyframe_interval)
            if config.adaptive:
                self.bitrate = BitrateController(BitrateSettings(
                    1000 * config.bitrate_kbps, 1000 * config.min_bitrate_kbps, 1000 * config.max_bitrate_kbps,
                ), 1.0 / config.fps)

    def on_feedback(self, feedback: VideoFeedback, sets_bitrate: bool = True) -> None:
        """A viewer's report (the media process's subscription): a keyframe it waits for, and how the frames
        reach it (the bitrate follows the worst viewer among those that ``sets_bitrate``: see
        iorthand_edge.media.sets_bitrate)."""
        if self.h264 is not None and feedback.keyframe:
            self.h264.viewer_asks_keyframe()
        if self.bitrate is not None and sets_bitrate:
            self.bitrate.on_feedback(feedback.received, feedback.lost, feedback.delay_p90)

    @property
    def error(self) -> str:
        """Why the stream delivers no pictures now ("" while it does): the source's problem or the sender's."""
        return self._send_error or self._capture_error

    @property
    def dropped(self) -> int:
        return self.slot.dropped

    def start(self, session: zenoh.Session, robot_keys: keys.RobotKeys, stop: threading.Event) -> None:
        self.start_with(publisher(session, robot_keys.key(self.key_suffix)), stop)

    def start_with(self, pub: zenoh.Publisher | Any, stop: threading.Event) -> None:
        """Start the threads publishing through ``pub`` (anything with ``put(bytes)``)."""
        self._pub = pub
        for part, fn in (("capture", self._capture_loop), ("send", self._send_loop)):
            w = Worker(f"edge-video-{self.name}-{part}", self._guarded(fn), stop)
            w.start()
            self._workers.append(w)

    def _guarded(self, fn: Callable[[threading.Event], None]) -> Callable[[threading.Event], None]:
        """A bug in a stream's code ends this stream only (logged, kept in ``error``), never the others."""

        def run(stop: threading.Event) -> None:
            # (The streams run in the edge's media process, whose threads all run at a lower priority than the
            # control process's: iorthand_edge.media.MEDIA_NICE.)
            try:
                fn(stop)
            except Exception as exc:
                self._capture_error = f"{type(exc).__name__}: {exc}"
                log.exception("video %s stopped", self.name)

        return run

    def join(self, timeout: float = 2.0) -> None:
        for w in self._workers:
            w.join(timeout)
        if problem := self._close_source():  # the media process still closes the other streams and its session
            log.error("video %s: %s", self.name, problem)

    def _capture_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            reason = self._capture_until_failure(stop)
            # A source whose close() raises (a driver that fails to release a device that vanished) is reported and
            # reopened like any other failure: the exception must not end this thread, leaving the stream dead.
            closing = self._close_source()
            if reason or closing:
                self._failed("; ".join(r for r in (reason, closing) if r))
            stop.wait(self.config.retry_interval)

    def _capture_until_failure(self, stop: threading.Event) -> str:
        """Open the source and capture until stopped ("") or until it fails (why)."""
        try:
            self.source.open()
            self._capture(stop)
        except (VideoError, cv2.error) as exc:
            # A missing or failed camera must not take the robot down: report, and try again.
            return str(exc)
        except Exception as exc:  # a bug in a source: as visible as a failed camera, and retried the same way
            if f"internal error: {exc!r}" != self._capture_error:
                log.exception("video %s: internal error in %s", self.name, self.source.description)
            return f"internal error: {exc!r}"
        return ""

    def _close_source(self) -> str:
        """Close the source; why that failed, or ""."""
        try:
            self.source.close()
        except Exception as exc:
            return f"closing {self.source.description} failed: {type(exc).__name__}: {exc}"
        return ""

    def _capture(self, stop: threading.Event) -> None:
        """Grab frames on schedule until stopped; raise VideoError when the source stalls."""
        period = 1.0 / self.config.fps
        next_tick = last_frame = time.monotonic()
        while not stop.is_set():
            image = self.source.grab()
            t_ns = self.source.frame_time_ns(time.time_ns())
            if image is not None:
                self._check_size(image)
                last_frame = time.monotonic()
                self.captured += 1
                skipped = self.slot.dropped
                self.slot.put(Captured(self._next_seq(), t_ns, image))
                if self.bitrate is not None:
                    self.bitrate.on_capture(self.slot.dropped - skipped)
                if self._capture_error:
                    log.info("video %s: %s delivers frames again", self.name, self.source.description)
                    self._capture_error = ""
            elif time.monotonic() - last_frame > self.config.stall_timeout:
                raise VideoError(f"no frame from {self.source.description} for {self.config.stall_timeout:g} s")
            if self.source.paced:
                continue  # its grab() waited for the frame
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                stop.wait(delay)
            else:
                next_tick = time.monotonic()  # a slow source: never burst to catch up

    def _check_size(self, image: Image) -> None:
        """Raise VideoError for a frame an H.264 stream cannot take (another size than configured)."""
        if self.h264 is None:
            return  # JPEG frames carry their own size
        h, w = image.shape[:2]
        if (w, h) != (self.h264.width, self.h264.height):
            raise VideoError(
                f"{self.source.description} delivers {w}×{h} frames, the H.264 stream is configured for "
                f"{self.h264.width}×{self.h264.height}: set video.{self.name}.width/height to the source's size"
            )

    def _failed(self, reason: str) -> None:
        self.failures += 1
        if reason != self._capture_error:  # once per change, not at every retry
            log.error("video %s: %s (retrying every %g s)", self.name, reason, self.config.retry_interval)
        self._capture_error = reason
        self.slot.put(Captured(self._next_seq(), time.time_ns(), None, failure=reason))

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _send_loop(self, stop: threading.Event) -> None:
        while not stop.is_set():
            item = self.slot.take(timeout=0.2)
            if item is None or self._pub is None:
                continue
            try:
                self._send(item)
            except Exception as exc:  # this frame is lost; the next is tried afresh (see the module's docstring)
                self._send_failed(item, exc)

    def _send(self, item: Captured) -> None:
        if self.before_send is not None:
            self.before_send()
        if self.h264 is not None and self.bitrate is not None:
            self.h264.set_bitrate(self.bitrate.decide(time.monotonic()))
            if self.bitrate.reason:
                log.info("video %s: %s", self.name, self.bitrate.reason)
                self.bitrate.reason = ""
        frame = encode_frame(self.name, item, self.config, self.h264)
        if frame is None:
            return
        frame.seq = self.sent + 1  # frames sent, not captured: see the module's docstring
        payload = frame.encode()
        t0 = time.perf_counter()
        self._pub.put(payload)  # BLOCK: a full uplink shows here
        if self.bitrate is not None:
            self.bitrate.on_put(time.perf_counter() - t0)
        self.sent += 1
        self.bytes_sent += len(payload)
        if self._send_error and item.image is not None:
            log.info("video %s: frames are sent again", self.name)
            self._send_error = ""

    def _send_failed(self, item: Captured, exc: Exception) -> None:
        """A frame that could not be encoded or put(): say why, in a failure notice in its place (which may not
        get through either, when the put failed), and keep the stream going."""
        self.send_failures += 1
        detail = str(exc) if isinstance(exc, VideoError) else f"{type(exc).__name__}: {exc}"
        reason = f"frame not sent: {detail}"
        if reason != self._send_error:  # once per change, not at every frame
            if isinstance(exc, VideoError | zenoh.ZError):
                log.error("video %s: %s", self.name, reason)
            else:
                log.exception("video %s: %s", self.name, reason)
        self._send_error = reason
        try:
            # A notice as the capture side's (its keyframe request included: the viewers lost a frame).
            notice = encode_frame(self.name, Captured(self.sent + 1, item.t_ns, None, failure=reason), self.config,
                                  self.h264)
            assert notice is not None  # (a notice always is one)
            self._pub.put(notice.encode())
            self.sent += 1
        except Exception as notice_exc:  # the link itself: nothing more can be said through it now
            log.debug("video %s: the failure notice was not sent either: %s", self.name, notice_exc)
