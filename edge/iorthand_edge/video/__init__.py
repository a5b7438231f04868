"""Camera and ultrasound video: sources, JPEG streams on their own Zenoh session."""

from iorthand_edge.video.config import StreamConfig, VideoConfig
from iorthand_edge.video.sources import FrameSource, VideoError, make_source, render_ultrasound
from iorthand_edge.video.stream import LatestSlot, VideoStream, decode_frame, encode_frame

__all__ = [
    "FrameSource",
    "LatestSlot",
    "StreamConfig",
    "VideoConfig",
    "VideoError",
    "VideoStream",
    "decode_frame",
    "encode_frame",
    "make_source",
    "render_ultrasound",
]
