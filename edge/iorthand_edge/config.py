"""The edge agent's configuration (YAML → dataclasses, validated at start-up)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from iorthand import keys
from iorthand.config import load, setting
from iorthand.protocol import MAX_PAYLOAD
from iorthand.transport import RX_MAX_MESSAGE_KEY, ZenohConfig
from iorthand_edge.actuators.config import ServosConfig, TorchConfig
from iorthand_edge.force.config import ForceConfig, RobotForceSensorConfig, SimForceSensorConfig
from iorthand_edge.force.contact import PhantomConfig
from iorthand_edge.goto import GotoConfig
from iorthand_edge.perception.config import PerceptionConfig
from iorthand_edge.robots.config import RobotConfig, SimRobotConfig
from iorthand_edge.supervisor import SafetyConfig
from iorthand_edge.video.config import VideoConfig

# The largest message the edge's sessions take from the network. The edge receives commands and control
# queries only, each under MAX_PAYLOAD (its video frames go out, and a session's limit is on what it receives),
# so Zenoh drops anything larger before reassembling it: a flood of 10 MB payloads then costs the edge no
# memory (before this and the other fixes of issue 20, benchmarks/bench_flood_memory.py's flood of malformed
# messages and twenty 10 MB payloads left the edge 106 MB larger, for good). Twice the payload
# limit leaves room for the key and Zenoh's headers; a larger command still reaches the subscriber's own size
# check, which names its size. ``zenoh.extra`` in the YAML may set another value.
EDGE_RX_MAX_MESSAGE = 2 * MAX_PAYLOAD


@dataclass
class EdgeConfig:
    robot_id: str
    zenoh: ZenohConfig
    robot: RobotConfig = field(default_factory=SimRobotConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    safety_rate_hz: float = setting(20.0, lo=1.0, hi=200.0)
    local_socket: Path | None = setting(None, help="Unix socket for local commands (arming confirmation)")
    # Optional end-effector components: absent (null) = not fitted.
    phantom: PhantomConfig | None = setting(None, help="simulated patient phantom (simulated robot only)")
    force: ForceConfig | None = setting(None, help="force/torque sensor, warning levels, supervisor reaction")
    servos: ServosConfig | None = setting(None, help="camera pan/tilt servos")
    torch: TorchConfig | None = setting(None, help="the torch (LED) next to the camera")
    video: VideoConfig | None = setting(None, help="camera and ultrasound JPEG streams")
    perception: PerceptionConfig | None = setting(None, help="ArUco markers → poses in the base frame")
    goto: GotoConfig = field(default_factory=GotoConfig)
    require_operator_alive: bool = setting(
        True, help="acquire only for an operator whose liveliness token is present (ACL-bound to its certificate)"
    )
    realtime: bool = setting(True, help="SCHED_FIFO for the control loop thread, and the UR driver's command "
                             "thread, when allowed")
    cpu_latency_us: int | None = setting(
        None, lo=0, help="while an operator holds control, no CPU of this host enters an idle state slower than this "
        "to leave (PM QoS, root; 0: idle cores poll, which costs power): every thread wake-up on the command path is "
        "faster. Null: the host's own idle states"
    )
    bind_operator_keys: bool = setting(
        False, help="commands and control queries only on keys that carry the operator id (with the generated ACL)"
    )

    def __post_init__(self) -> None:
        self.zenoh.extra.setdefault(RX_MAX_MESSAGE_KEY, EDGE_RX_MAX_MESSAGE)

    def check(self) -> None:
        keys.check_edge_robot_id(self.robot_id)
        if self.safety.auto_arm and not isinstance(self.robot, SimRobotConfig):
            raise ValueError("safety.auto_arm is allowed only for the simulated robot: a real arm needs local confirmation")
        simulated = isinstance(self.robot, SimRobotConfig)
        if self.force is not None and isinstance(self.force.sensor, SimForceSensorConfig) and not simulated:
            raise ValueError("force.sensor.kind sim measures the simulated robot: use a real sensor (netft, or robot: the arm's own) with a real arm")
        if self.force is not None and isinstance(self.force.sensor, RobotForceSensorConfig) and simulated:
            raise ValueError("force.sensor.kind robot reads the arm's own sensor over RTDE: the simulated robot has"
                             " none (use kind sim with a phantom)")
        if self.phantom is not None and not simulated:
            raise ValueError("phantom: a simulated phantom only makes sense with the simulated robot (robot.kind sim)")
        if self.force is not None and self.safety.contact.target >= self.force.levels.caution:
            raise ValueError(f"safety.contact.target {self.safety.contact.target:g} N must lie below "
                             f"force.levels.caution ({self.force.levels.caution:g} N): contact mode would always be "
                             "refused")
        stream = self.video.camera if self.video is not None else None
        # (A video file as the perception camera has no rate of its own to compare.)
        camera_fps = getattr(self.perception.camera, "fps", None) if self.perception is not None else None
        if stream is not None and stream.source == "perception" and camera_fps is not None \
                and not math.isclose(stream.fps, camera_fps):
            # The stream sends each image that camera captures: its encoder and bitrate must plan for that rate.
            raise ValueError(f"video.camera.fps {stream.fps:g} must be perception.camera.fps {camera_fps:g}: the "
                             "camera video sends each image the perception camera captures (set both alike)")

    def warnings(self) -> list[tuple[str, str]]:
        """Settings that load but that leave the agent unable to do its job: (setting, why). ``iorthand check``
        shows them and the agent logs them at start."""
        out = []
        if not self.safety.auto_arm and self.local_socket is None:
            out.append(("local_socket", "not set while safety.auto_arm is false: nothing can confirm arming "
                                        "(iorthand arm), so the robot never moves"))
        box = self.safety.workspace
        named = {f"goto.poses.{name}": pose for name, pose in self.goto.poses.items()}
        if isinstance(self.robot, SimRobotConfig):
            named["robot.initial_pose"] = self.robot.initial_pose
        for where, pose in named.items():
            if not box.contains(pose[:3]):
                out.append((where, f"{[round(v, 4) for v in pose[:3]]} lies outside safety.workspace "
                                   f"{box.min} .. {box.max}: every move there is refused"))
        return out


def load_edge_config(path: str | Path) -> EdgeConfig:
    return load(path, EdgeConfig)
