"""The operator's configuration."""

from __future__ import annotations

from dataclasses import dataclass, field

from iorthand import keys
from iorthand.config import setting
from iorthand.transport import ZenohConfig
from iorthand_operator.console.settings import ConsoleSettings


@dataclass
class OperatorConfig:
    operator_id: str
    robot: str
    zenoh: ZenohConfig = field(default_factory=lambda: ZenohConfig(connect=["tcp/127.0.0.1:7447"]))
    rate_hz: float = setting(60.0, lo=10.0, hi=500.0, help="command stream rate")
    release_tail: float = setting(0.3, lo=0.0, hi=5.0, help="s of zero twists sent after the deadman is released")
    profile: str = setting("", help="speed profile to ask for (empty: the edge's default)")
    console: ConsoleSettings = field(default_factory=ConsoleSettings)  # the terminal UI and its inputs
    bind_operator_keys: bool = setting(False, help="command on keys carrying this operator's id (the edge's setting)")

    def check(self) -> None:
        keys.check_robot_id(self.robot)
        keys.check_operator_id(self.operator_id)
