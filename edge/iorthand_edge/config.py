"""The edge agent's configuration (YAML → dataclasses, validated at start-up)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from iorthand import keys
from iorthand.config import load, setting
from iorthand.transport import ZenohConfig
from iorthand_edge.robots.config import RobotConfig, SimRobotConfig
from iorthand_edge.supervisor import SafetyConfig


@dataclass
class EdgeConfig:
    robot_id: str
    zenoh: ZenohConfig
    robot: RobotConfig = field(default_factory=SimRobotConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    safety_rate_hz: float = setting(20.0, lo=1.0, hi=200.0)
    local_socket: Path | None = setting(None, help="Unix socket for local commands (arming confirmation)")

    def check(self) -> None:
        keys.check_robot_id(self.robot_id)
        if self.safety.auto_arm and not isinstance(self.robot, SimRobotConfig):
            raise ValueError("safety.auto_arm is allowed only for the simulated robot: a real arm needs local confirmation")


def load_edge_config(path: str | Path) -> EdgeConfig:
    return load(path, EdgeConfig)
