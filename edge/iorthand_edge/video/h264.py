"""H.264 for the camera and the ultrasound: a few hundred kbit/s where JPEG needs several Mbit/s (issue 24).

libx264 through PyAV, tuned for latency: ``ultrafast`` + ``zerolatency`` (no lookahead, no B-frames: each frame
is encoded and sent as it is captured), a bounded VBV buffer (no frame much bigger than the rate allows, so the
uplink never queues seconds of video), SPS/PPS repeated at every keyframe (a viewer can start at any of them), a
keyframe every ``keyframe_interval`` s (a viewer that joins or lost a frame waits at most that) and on request
(:meth:`H264Encoder.viewer_asks_keyframe`: a viewer's feedback). One encoder thread: x264's default of 1.5 threads per
core spread the encoding over every core and delayed the control process (command path p99 with video 5.7 → 4.3
ms in one run, benchmarks/bench_command_path.py); one thread encodes 640×480 at 30 fps with room to spare. Each access unit travels in one ``VideoFrame``
(Annex B, ``encoding: h264``, ``keyframe`` set on IDR frames).

The bitrate is a target that :mod:`iorthand_edge.video.bitrate` moves with the link; libx264 cannot change it
on the fly through PyAV, so a new target opens a new encoder, whose first frame is a keyframe.
"""

from __future__ import annotations

import fractions
import logging
import time

import av
import cv2
import numpy as np

from iorthand_edge.video.sources import Image, VideoError

log = logging.getLogger("iorthand.edge.video")

# The part of a second of video the decoder's buffer holds (VBV): smaller bounds each frame's size (and so the
# delay a keyframe adds on a thin link) at some cost in quality. 0.3 s: a keyframe crosses a link of twice the
# bitrate in about a frame period more than a plain frame.
VBV_SECONDS = 0.3
# A viewer asks for a keyframe at every frame it cannot decode until one arrives, and several viewers may ask about
# the same lost frame. Requests within this long after a keyframe went out are about frames before it (it is on
# its way) and get no other (each is several times a plain frame: on a lossy datagram link, answering them all
# made more loss). A viewer that lost that keyframe too asks again after it. 0.2 s: a 4G round trip (~100 ms)
# and a few frame periods.
KEYFRAME_REQUEST_HOLD_S = 0.2


# 8-bit grey to the limited-range luma (16..235) of x264's yuv420p, as swscale maps it (all 256 values checked
# against PyAV's own conversion in the tests): a table for cv2.LUT.
_GREY_TO_LUMA = ((np.arange(256) * 219 + 127) // 255 + 16).astype(np.uint8)


def grey_to_yuv420p(image: Image) -> np.ndarray:
    """A grey image as the planes x264 takes (Y, then U and V at half size, stacked: h·3/2 × w), exactly as PyAV's
    conversion (swscale) makes them, at a sixth of its cost (480×360, the ultrasound: ~0.5 → ~0.08 ms here)."""
    h, w = image.shape
    planes = np.empty((h * 3 // 2, w), dtype=np.uint8)
    cv2.LUT(image, _GREY_TO_LUMA, dst=planes[:h])
    planes[h:] = 128  # no colour
    return planes


# OpenCV's full-range chroma (YCrCb: 128 ± 127.5 over the colour range) to the limited range of yuv420p (128 ± 112).
_FULL_TO_LIMITED_CHROMA = np.clip(np.round(128 + (np.arange(256) - 128) * 224 / 255), 0, 255).astype(np.uint8)


def bgr_to_yuv420p(image: Image) -> np.ndarray:
    """A BGR image as the planes x264 takes (BT.601, limited range, as PyAV's conversion), each chroma sample the
    average colour of its 2×2 block. OpenCV's own I420 conversion takes one pixel's colour per block (chroma 1.9
    levels off the block's average on average, 9 at most): its luma is kept, its chroma replaced by that of the
    blocks' mean colours. Closer to the exact conversion than swscale on average (luma 0.25 against 0.5 levels,
    chroma 0.35 against 0.5; at most 1.5 against 1.35) at ~0.5 of its time (640×480: 0.53 against 0.88 ms here)."""
    h, w = image.shape[:2]
    planes = cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420)  # h·3/2 × w: Y, then U and V at half size
    blocks = cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA)  # each 2×2 block's mean colour
    ycrcb = cv2.cvtColor(blocks, cv2.COLOR_BGR2YCrCb)
    flat, luma, quarter = planes.reshape(-1), h * w, (h // 2) * (w // 2)
    flat[luma:luma + quarter] = cv2.LUT(ycrcb[:, :, 2], _FULL_TO_LIMITED_CHROMA).reshape(-1)  # U (Cb)
    flat[luma + quarter:] = cv2.LUT(ycrcb[:, :, 1], _FULL_TO_LIMITED_CHROMA).reshape(-1)  # V (Cr)
    return planes


class H264Encoder:
    """Encodes images of one stream (fixed size) into H.264 access units."""

    def __init__(self, width: int, height: int, fps: float, bitrate: float, keyframe_interval: float) -> None:
        # x264 wants even dimensions in 4:2:0.
        if width % 2 or height % 2:
            raise VideoError(f"H.264 needs an even width and height, got {width}×{height}")
        self.width, self.height, self.fps = width, height, fps
        self.keyframe_interval = keyframe_interval
        self.bitrate = bitrate
        self._codec: av.VideoCodecContext | None = None
        self._pts = 0
        self._want_key = True
        self._key_sent_at = -1e9  # monotonic s
        self.reopened = 0

    def _open(self) -> av.VideoCodecContext:
        kbps = max(16, int(self.bitrate / 1000))
        keyint = max(1, round(self.fps * self.keyframe_interval))
        codec = av.CodecContext.create("libx264", "w")
        codec.width, codec.height, codec.pix_fmt = self.width, self.height, "yuv420p"
        codec.time_base = fractions.Fraction(1, 1000)
        codec.framerate = fractions.Fraction(round(self.fps * 1000), 1000)
        codec.bit_rate = int(self.bitrate)
        codec.options = {
            "preset": "ultrafast", "tune": "zerolatency", "forced-idr": "1", "threads": "1",
            "x264-params": (f"keyint={keyint}:min-keyint={keyint}:scenecut=0:bframes=0:repeat-headers=1:"
                            f"vbv-maxrate={kbps}:vbv-bufsize={max(8, int(kbps * VBV_SECONDS))}:nal-hrd=none"),
        }
        codec.open()
        self.reopened += 1
        return codec

    def set_bitrate(self, bitrate: float) -> None:
        """A new target (bit/s): the next frame starts a new encoder with it (a keyframe)."""
        if abs(bitrate - self.bitrate) > 1.0:
            self.bitrate = bitrate
            self._codec = None

    def request_keyframe(self) -> None:
        """The next frame is a keyframe (the source is back: whoever watches starts again)."""
        self._want_key = True

    def viewer_asks_keyframe(self, now: float | None = None) -> bool:
        """A viewer's request (``now``: monotonic s): the next frame is a keyframe, unless one went out less than
        KEYFRAME_REQUEST_HOLD_S ago. Returns whether the request was taken."""
        now = time.monotonic() if now is None else now
        if now - self._key_sent_at < KEYFRAME_REQUEST_HOLD_S:
            return False
        self._want_key = True
        return True

    def encode(self, image: Image, t_ms: int) -> list[tuple[bytes, bool]]:
        """The access units for ``image`` (usually one; none while the encoder fills up), with keyframe flags."""
        if image.shape[0] != self.height or image.shape[1] != self.width:
            raise VideoError(f"frame of {image.shape[1]}×{image.shape[0]} for a {self.width}×{self.height} H.264 stream")
        if self._codec is None:
            self._codec = self._open()
            self._want_key = True
        planes = grey_to_yuv420p(image) if image.ndim == 2 else bgr_to_yuv420p(image)
        frame = av.VideoFrame.from_ndarray(planes, format="yuv420p")
        frame.pts = max(self._pts + 1, t_ms)  # strictly increasing, in ms
        self._pts = frame.pts
        if self._want_key:
            frame.pict_type = av.video.frame.PictureType.I
            self._want_key = False
        try:
            packets = self._codec.encode(frame)
        except av.error.FFmpegError as exc:
            self._codec = None
            raise VideoError(f"H.264 encoding failed: {exc}") from exc
        out = [(bytes(p), bool(p.is_keyframe)) for p in packets]
        if any(key for _, key in out):
            self._key_sent_at = time.monotonic()
        return out


class H264Decoder:
    """Access units back to images (receivers that draw them, tests). Waits for a keyframe after a gap."""

    def __init__(self) -> None:
        self._codec = av.CodecContext.create("h264", "r")
        self._synced = False

    def decode(self, data: bytes, keyframe: bool, gap: bool = False) -> list[np.ndarray]:
        """BGR images of one access unit; none before the first keyframe, or after a lost frame until the next."""
        if gap:
            self._synced = False
        if not self._synced and not keyframe:
            return []
        self._synced = True
        try:
            frames = self._codec.decode(av.Packet(data))
        except av.error.FFmpegError:
            self._synced = False
            return []
        return [f.to_ndarray(format="bgr24") for f in frames]


__all__ = ["H264Decoder", "H264Encoder"]
