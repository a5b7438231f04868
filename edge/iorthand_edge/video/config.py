"""Video configuration: one stream per source (camera, ultrasound), on a Zenoh session of its own."""

from __future__ import annotations

from dataclasses import dataclass

from iorthand.config import setting
from iorthand.transport import ZenohConfig

SOURCES = ("pattern", "opencv", "ultrasound_sim", "perception")


@dataclass
class StreamConfig:
    source: str = setting("pattern", choices=SOURCES, help="pattern: synthetic test image; opencv: a capture "
                          "device; ultrasound_sim: speckle that responds to the contact force")
    device: str = setting("0", help="opencv: device index or path/URL (the ultrasound grabber is one too)")
    width: int = setting(640, lo=16, hi=4096)
    height: int = setting(480, lo=16, hi=4096)
    fps: float = setting(30.0, lo=0.5, hi=120.0)
    codec: str = setting("h264", choices=("h264", "jpeg"), help="h264: a few hundred kbit/s, adapted to the link; "
                         "jpeg: independent pictures, several Mbit/s (the fallback)")
    quality: int = setting(80, lo=10, hi=100, help="JPEG quality")
    bitrate_kbps: float = setting(1200.0, lo=50.0, hi=50_000.0, help="h264: the bitrate to start with")
    min_bitrate_kbps: float = setting(200.0, lo=20.0, hi=50_000.0, help="h264: the link's congestion never takes it lower")
    max_bitrate_kbps: float = setting(2000.0, lo=50.0, hi=100_000.0, help="h264: nor higher than this (640×480 at "
                                      "30 fps looks clean at 1–2 Mbit/s; more only queues on a thin uplink)")
    adaptive: bool = setting(True, help="h264: follow the link (congestion at the sender, the viewers' reports)")
    keyframe_interval: float = setting(1.0, lo=0.1, hi=10.0, help="h264: s between keyframes (a viewer that joins or "
                                       "lost a frame starts again at the next one)")
    retry_interval: float = setting(2.0, lo=0.1, hi=60.0, help="s between attempts to reopen a source that failed "
                                    "(each one sends why to the twin and the recorder)")
    stall_timeout: float = setting(2.0, lo=0.1, hi=60.0, help="s without a frame after which an open source counts "
                                   "as failed and is reopened (at least two frame periods)")


@dataclass
class VideoConfig:
    camera: StreamConfig | None = setting(default_factory=StreamConfig)
    ultrasound: StreamConfig | None = None
    zenoh: ZenohConfig | None = setting(None, help="the media process's session (video, markers, and the robot, "
                                        "servo and force state they need); default: the edge's own zenoh settings")

    def check(self) -> None:
        if self.ultrasound is not None and self.ultrasound.source == "pattern":
            raise ValueError("ultrasound.source: use ultrasound_sim or opencv (a capture device)")
        for name, stream in (("camera", self.camera), ("ultrasound", self.ultrasound)):
            if stream is not None and not stream.min_bitrate_kbps <= stream.bitrate_kbps <= stream.max_bitrate_kbps:
                raise ValueError(f"{name}: bitrate_kbps {stream.bitrate_kbps:g} must lie within min_bitrate_kbps "
                                 f"{stream.min_bitrate_kbps:g} and max_bitrate_kbps {stream.max_bitrate_kbps:g}")
            if stream is not None and stream.codec == "h264" and (stream.width % 2 or stream.height % 2):
                raise ValueError(f"{name}: H.264 needs an even width and height, got {stream.width}×{stream.height}")
            if stream is not None and stream.stall_timeout < 2.0 / stream.fps:
                raise ValueError(f"{name}.stall_timeout: {stream.stall_timeout:g} s is shorter than two frame periods "
                                 f"at {stream.fps:g} fps")
