"""The twin's configuration (``iorthand twin --config configs/twin.yaml``), validated at start-up."""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import yaml

from iorthand import keys
from iorthand.config import ConfigError, load, setting
from iorthand.transport import ZenohConfig


def _zero_pose() -> list[float]:
    return [0.0] * 6


@dataclass
class CameraView:
    """Camera intrinsics and the mount chain (same keys as the edge's ``perception.mount``), to draw the
    camera frustum: ``T_tcp_camera = T_tcp_mount · R(pan_axis, pan) · R(tilt_axis, tilt) · T_tilt_camera``."""

    width: int = setting(640, lo=1, hi=8192)
    height: int = setting(480, lo=1, hi=8192)
    fx: float = setting(600.0, lo=1.0)
    fy: float = setting(600.0, lo=1.0)
    cx: float = setting(319.5)
    cy: float = setting(239.5)
    intrinsics_file: Path | None = setting(None, help="an intrinsics calibration YAML; overrides fx..height")
    tcp_mount: list[float] = setting(default_factory=lambda: [0.0, 0.05, -0.02, 0.0, 0.0, 0.0], length=6)
    pan_axis: list[float] = setting(default_factory=lambda: [0.0, 0.0, 1.0], length=3)
    tilt_axis: list[float] = setting(default_factory=lambda: [1.0, 0.0, 0.0], length=3)
    tilt_camera: list[float] = setting(default_factory=_zero_pose, length=6)
    pan_zero: float = setting(0.0, lo=-7.0, hi=7.0, help="servo angle (rad) at which the pan rotation is zero")
    tilt_zero: float = setting(0.0, lo=-7.0, hi=7.0, help="servo angle (rad) at which the tilt rotation is zero")
    frustum_depth: float = setting(0.08, lo=0.005, hi=2.0, help="m: drawn depth of the image plane")

    def check(self) -> None:
        for name in ("pan_axis", "tilt_axis"):
            if np.linalg.norm(getattr(self, name)) < 1e-9:
                raise ValueError(f"{name} must not be zero")
        if self.intrinsics_file is not None:
            try:
                data = yaml.safe_load(Path(self.intrinsics_file).read_text(encoding="utf-8"))
                k = data["camera_matrix"]
                self.width, self.height = int(data["image_width"]), int(data["image_height"])
                self.fx, self.fy, self.cx, self.cy = float(k[0][0]), float(k[1][1]), float(k[0][2]), float(k[1][2])
            except (OSError, KeyError, TypeError, IndexError, ValueError, yaml.YAMLError) as exc:
                raise ValueError(f"intrinsics_file {self.intrinsics_file}: cannot read image size and camera_matrix ({exc})") from None


@dataclass
class SceneObject:
    """A box in the robot's base frame (bed, phantom, table): centre and full size in metres."""

    name: str
    center: list[float] = setting(length=3)
    size: list[float] = setting(length=3, lo=0.0)
    color: list[int] = setting(default_factory=lambda: [160, 160, 160, 255], length=4, lo=0, hi=255)


def _default_scene() -> list[SceneObject]:
    # The phantom of the demo's simulated edge (configs/edge-sim.yaml, phantom: x 0.20–0.40, y ±0.10, its top at
    # z 0.15, where its markers lie): keep the two in step, or the probe is drawn pressing on air.
    return [
        SceneObject("table", [0.0, 0.0, -0.01], [0.6, 0.6, 0.02], [110, 90, 70, 255]),
        SceneObject("bed", [0.32, 0.0, -0.05], [0.35, 0.55, 0.10], [200, 200, 215, 255]),
        SceneObject("phantom", [0.30, 0.0, 0.075], [0.20, 0.20, 0.15], [230, 180, 160, 255]),
    ]


@dataclass
class RobotView:
    """How one robot is drawn. ``base`` places its base frame in the world (several robots side by side)."""

    model: str = setting("ur3e", choices=("ur3e", "ur5e"))
    base: list[float] | None = setting(None, length=6, help="world pose of the base; default: a row along y")
    tcp_offset: list[float] = setting(default_factory=_zero_pose, length=6, help="TCP in the flange frame")
    probe_length: float = setting(0.10, lo=0.0, hi=0.5, help="m, drawn along -z of the TCP (back to the flange)")
    workspace_min: list[float] | None = setting(default_factory=lambda: [0.10, -0.30, 0.02], length=3)
    workspace_max: list[float] | None = setting(default_factory=lambda: [0.45, 0.30, 0.45], length=3)
    camera: CameraView = field(default_factory=CameraView)
    scene: list[SceneObject] = field(default_factory=_default_scene)


@dataclass
class ViewerConfig:
    """Where the rerun data goes and how much of it."""

    enabled: bool = setting(True, help="false: no rerun at all (snapshots and previews only)")
    serve: bool = setting(True, help="serve the web viewer (an operator opens a URL)")
    bind: str = setting("127.0.0.1", help="address the viewer's HTTP and gRPC ports listen on")
    unauthenticated_network: bool = setting(False, help="allow a bind reachable from other machines: the viewer has "
                                            "no log-in (it is read-only: nobody who reaches it writes into it)")
    public_host: str = setting("", help="host name put in the printed URL (default: the bind address)")
    grpc_port: int = setting(9876, lo=0, hi=65535)
    web_port: int = setting(9090, lo=0, hi=65535)
    memory_limit: str = setting("256MiB", help="the gRPC server's buffer; older data is dropped first")
    save: Path | None = setting(None, help=".rrd file written with the same data")
    save_max_mb: float = setting(500.0, lo=1.0, hi=1e6, help="the .rrd stops growing at this size (the recorder's "
                                 "files hold whole sessions; a twin is live for hours)")
    save_footer: bool = setting(False, help="end the .rrd with rerun's footer (an index of every chunk): rerun keeps "
                                "that index in the twin's memory while saving, ~0.3 MB per MB written (+200 MB "
                                "at a 500 MB file); without it the file is valid, read in order, and `rerun rrd "
                                "optimize` adds the footer afterwards")
    relay_start_timeout: float = setting(20.0, lo=1.0, hi=120.0)
    queue: int = setting(1024, lo=16, hi=100_000, help="items between the Zenoh side and rerun (oldest dropped)")
    pose_hz: float = setting(30.0, lo=0.1, hi=500.0, help="robot drawing rate per robot")
    arm_hz: float = setting(10.0, lo=0.1, hi=500.0, help="arm redraws (inverse kinematics) per robot; the tool at pose_hz")
    force_batch_s: float = setting(0.1, lo=0.01, hi=5.0, help="force samples are sent in batches this long")
    image_fps: float = setting(10.0, lo=0.1, hi=60.0, help="images per second and source at most")
    markers_hz: float = setting(10.0, lo=0.1, hi=100.0)
    stale_after: float = setting(0.5, lo=0.05, hi=10.0, help="s without force: arrow grey")
    media_stale_after: float = setting(2.0, lo=0.1, hi=60.0, help="s without a camera/ultrasound picture or a "
                                       "markers message: that image or those markers are cleared from the view "
                                       "(a frozen picture never passes for a live one). Default: the edge's video "
                                       "stall_timeout (2 s), after which the edge itself declares the source failed; "
                                       "at least two periods of image_fps and markers_hz")

    def check(self) -> None:
        try:
            address = ipaddress.ip_address(self.bind)
        except ValueError:
            raise ValueError(f"bind {self.bind!r} must be an IP address such as 127.0.0.1 or 0.0.0.0") from None
        if self.enabled and self.serve and not address.is_loopback and not self.unauthenticated_network:
            raise ValueError(f"bind {self.bind} is reachable from other machines, and the rerun viewer has no log-in: "
                             "anyone who reaches it would see the patient's images and poses. Keep 127.0.0.1 behind "
                             "an authenticating reverse proxy "
                             "(docs/DEPLOY.md), or set viewer.unauthenticated_network: true on a network where "
                             "everyone may")
        if self.serve and self.grpc_port != 0 and self.grpc_port == self.web_port:
            raise ValueError("grpc_port and web_port must differ")
        slowest = min(self.image_fps, self.markers_hz)
        if self.media_stale_after < 2.0 / slowest:
            raise ValueError(f"media_stale_after: {self.media_stale_after:g} s is shorter than two periods of "
                             f"image_fps/markers_hz ({slowest:g} Hz): live pictures would flicker off between frames")


@dataclass
class FoxgloveLiveConfig:
    """The live view in the Foxglove app (:mod:`iorthand_cloud.twin.foxglove`): the same channels the recorder
    writes for Foxglove, served over the Foxglove WebSocket protocol. Read-only: a client can subscribe, never
    publish or call anything. Served beyond this machine, it needs a certificate (patient images)."""

    enabled: bool = setting(False, help="serve the Foxglove WebSocket protocol (the app connects to ws://host:port)")
    host: str = setting("127.0.0.1", help="address to listen on; loopback by default (this machine only)")
    port: int = setting(8765, lo=0, hi=65535, help="0: any free port (printed at start)")
    video: bool = setting(True, help="serve the camera and ultrasound pictures too")
    tls_cert: Path | None = setting(None, help="PEM certificate (chain): wss://, required off loopback")
    tls_key: Path | None = setting(None, help="PEM private key of tls_cert")
    queue: int = setting(4096, lo=16, hi=100_000, help="state messages between Zenoh and the server (oldest dropped)")

    def check(self) -> None:
        try:
            address = ipaddress.ip_address(self.host)
        except ValueError:
            raise ValueError(f"host {self.host!r} must be an IP address such as 127.0.0.1 or 0.0.0.0") from None
        if (self.tls_cert is None) != (self.tls_key is None):
            raise ValueError("tls_cert and tls_key go together")
        if self.enabled and not address.is_loopback and self.tls_cert is None:
            raise ValueError(f"host {self.host} is reachable from other machines: serving patient images and poses "
                             "there in clear text is refused; set tls_cert and tls_key, or listen on 127.0.0.1")


@dataclass
class TwinConfig:
    zenoh: ZenohConfig
    viewer: ViewerConfig = field(default_factory=ViewerConfig)
    robots: dict[str, RobotView] = setting(default_factory=dict, help="per-robot drawing; others use default_robot")
    default_robot: RobotView = field(default_factory=RobotView)
    robot_spacing: float = setting(1.0, lo=0.0, hi=100.0, help="m along y between robots without a base pose")
    state_timeout: float = setting(1.0, lo=0.05, hi=60.0, help="s without state/robot: shown as stale")
    # Above the edge's own bound on a plan (planner.PLAN_TIMEOUT_S, 10 s), which it answers with its reason, and
    # below the operator client's wait (client.PLAN_QUERY_TIMEOUT_S, 12 s), which then reads this answer.
    preview_timeout: float = setting(11.0, lo=0.1, hi=60.0, help="s to wait for the edge's preview answer")
    snapshot_images: bool = setting(False, help="include the latest JPEGs in snapshots (also: ?images=1)")
    max_robots: int = setting(64, lo=1, hi=10_000, help="robots followed besides those under robots: (each costs "
                              "memory here and in the viewer); samples of more are refused, counted and logged")
    foxglove: FoxgloveLiveConfig = field(default_factory=FoxgloveLiveConfig)

    def check(self) -> None:
        for robot in self.robots:
            keys.check_robot_id(robot)

    def view(self, robot: str, index: int) -> RobotView:
        """The drawing settings of ``robot``; the ``index``-th robot without a base pose goes at y = index·spacing."""
        v = self.robots.get(robot, self.default_robot)
        if v.base is None:
            v = replace(v, base=[0.0, index * self.robot_spacing, 0.0, 0.0, 0.0, 0.0])
        return v


def load_twin_config(path: str | Path) -> TwinConfig:
    return load(path, TwinConfig)


__all__ = [
    "CameraView", "ConfigError", "FoxgloveLiveConfig", "RobotView", "SceneObject", "TwinConfig", "ViewerConfig",
    "load_twin_config",
]
