"""Force sensing configuration: one dataclass per kind of sensor (``force.sensor.kind``), plus the levels."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from iorthand.config import setting
from iorthand_edge.force.levels import LevelConfig


@dataclass
class ForceSensorConfig:
    VARIANTS: ClassVar[dict[str, type[ForceSensorConfig]]] = {}
    KIND: ClassVar[str] = ""


@dataclass
class SimForceSensorConfig(ForceSensorConfig):
    """A sensor that measures the simulated robot's contact with the phantom (``phantom`` in the edge config)."""

    KIND: ClassVar[str] = "sim"
    noise: float = setting(0.05, lo=0.0, hi=10.0, help="N (and N·m /10): standard deviation of white noise")
    bias: list[float] = setting(
        default_factory=lambda: [0.3, -0.2, 0.5, 0.01, -0.01, 0.0], length=6,
        help="offset of the raw reading until zeroed, N and N·m (a real sensor drifts like this)",
    )
    seed: int | None = setting(None, help="noise seed (tests); none: random")


@dataclass
class NetFTSensorConfig(ForceSensorConfig):
    """ATI Net F/T (or Axia) over the Raw Data Transfer protocol: UDP, port 49152."""

    KIND: ClassVar[str] = "netft"
    host: str = "192.168.1.1"
    port: int = setting(49152, lo=1, hi=65535)
    counts_per_force: float = setting(1_000_000.0, lo=1.0, help="from the sensor's calibration page")
    counts_per_torque: float = setting(1_000_000.0, lo=1.0, help="from the sensor's calibration page")
    bias_on_start: bool = setting(False, help="zero the sensor when the agent starts (tool in free space!)")


@dataclass
class RobotForceSensorConfig(ForceSensorConfig):
    """The arm's own wrist sensor (a UR e-Series: getActualTCPForce over RTDE), as the robot driver reports it."""

    KIND: ClassVar[str] = "robot"
    max_age: float = setting(0.05, lo=0.005, hi=1.0, help="s: an older robot state gives no sample (stale)")


ForceSensorConfig.VARIANTS = {c.KIND: c for c in (SimForceSensorConfig, NetFTSensorConfig, RobotForceSensorConfig)}


@dataclass
class ForceConfig:
    sensor: ForceSensorConfig = field(default_factory=SimForceSensorConfig)
    levels: LevelConfig = field(default_factory=LevelConfig)
    rate_hz: float = setting(100.0, lo=10.0, hi=1000.0, help="sampling and state/force rate of a sensor with a "
                             "stream of its own (netft); sim and robot: one sample per robot state")
    level_rate_hz: float = setting(10.0, lo=1.0, hi=100.0, help="state/force_level heartbeat (also sent on change)")
