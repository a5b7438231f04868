"""Recorder configuration (``configs/recorder.yaml``), validated by :mod:`iorthand.config`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from iorthand.config import setting
from iorthand.transport import ZenohConfig


@dataclass
class ReportConfig:
    """How a session report turns recorded data into the tele-echography figures."""

    contact_threshold: float = setting(1.0, lo=0.0, help="N: force above it counts as body contact (τ)")
    force_quantity: str = setting("norm", choices=("norm", "fz", "abs_fz"), help="what is compared with thresholds")
    alpha: float = setting(230.0, help="weight of ψ in the performance index φ")
    beta: float = setting(0.25, help="weight of Ω/(1−ψ) in φ")
    caution: float = setting(6.0, lo=0.0, help="N: level 1, used only when no state/force_level was recorded")
    danger: float = setting(8.0, lo=0.0, help="N: level 2, idem")
    hysteresis: float = setting(0.5, lo=0.0, help="N: idem")
    max_sample_gap: float = setting(0.1, lo=0.001, help="s: a longer gap between force samples counts no contact")
    teleop_time: str = setting(
        "commands", choices=("commands", "session"),
        help="t_t: from the first to the last deadman-held command, or the whole session",
    )
    plots: bool = True


@dataclass
class FoxgloveRecording:
    """Channels with Foxglove's schemas written beside the raw ones (:mod:`iorthand_cloud.foxglove_channels`),
    so the Foxglove app opens a session as it is: ``<session>/foxglove/foxglove-NNNN.mcap``."""

    enabled: bool = setting(True, help="write the Foxglove channels (tf, markers, images, logs, force plots)")
    video: bool = setting(True, help="with the camera and ultrasound pictures (a second copy: twice the video's disk)")


@dataclass
class RecorderConfig:
    zenoh: ZenohConfig = field(default_factory=lambda: ZenohConfig(mode="peer"))
    output_dir: Path = Path("recordings")
    key_exprs: list[str] = setting(default_factory=lambda: ["iorthand/**"], help="subscribed at start-up")
    video_key_exprs: list[str] = setting(
        default_factory=lambda: ["iorthand/*/video/**"], help="keys stored in the uncompressed video files"
    )
    exclude_key_exprs: list[str] = setting(
        default_factory=lambda: ["iorthand/_recorder/**"], help="never recorded (the recorder's own status)"
    )
    segment_max_mb: float = setting(256.0, lo=0.001, help="telemetry segment size before a new file")
    video_segment_max_mb: float = setting(1024.0, lo=0.001)
    segment_max_s: float = setting(600.0, lo=1.0, help="segment duration before a new file")
    flush_interval: float = setting(0.5, lo=0.02, hi=1.0, help="s: data reaches the file at least this often")
    fsync: bool = setting(True, help="also fsync at each flush (power loss, not only a killed process)")
    chunk_kb: int = setting(1024, lo=4, hi=32 * 1024, help="MCAP chunk size; a flush also ends a chunk")
    inbox_max: int = setting(50_000, lo=100, help="samples queued between Zenoh and the writer thread")
    inbox_max_mb: float = setting(512.0, lo=1.0, help="and at most this many MB of them (video frames are large)")
    max_keys: int = setting(2000, lo=1, hi=1_000_000, help="distinct keys one recording keeps of the robots its "
                            "start request names, and as many of the others (each is a channel and a line of the "
                            "manifest); samples on more are not recorded, counted as dropped")
    status_interval: float = setting(1.0, lo=0.05, help="s between status publications while recording")
    manifest_interval: float = setting(2.0, lo=0.1, help="s between manifest rewrites while recording")
    calibration_files: list[Path] = setting(default_factory=list, help="stored as MCAP attachments")
    start_on_launch: bool = setting(False, help="start a recording as soon as the service is up")
    session_prefix: str = "session"
    report: ReportConfig = field(default_factory=ReportConfig)
    foxglove: FoxgloveRecording = field(default_factory=FoxgloveRecording)

    def check(self) -> None:
        for expr in [*self.key_exprs, *self.video_key_exprs, *self.exclude_key_exprs]:
            if not expr or expr.startswith("/") or expr.endswith("/"):
                raise ValueError(f"key expression {expr!r} is not valid (no leading or trailing '/')")
        if not self.key_exprs:
            raise ValueError("key_exprs: at least one key expression to record")
