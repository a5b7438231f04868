"""Robot backends and the factory that builds one from its configuration."""

from __future__ import annotations

from iorthand_edge.robots.base import Robot, RobotFault, RobotReading
from iorthand_edge.robots.config import RobotConfig, SimRobotConfig, URRobotConfig


def make_robot(config: RobotConfig, stop_deceleration: float, realtime: bool = True,
               tcp_offset: list[float] | None = None) -> Robot:
    """The robot backend of ``config``. ``stop_deceleration`` (m/s², the safety config's) is what a driver uses
    for the stops it makes on its own (at connect, at shutdown, when the agent falls silent); ``realtime`` (the
    edge's setting): a driver's time-critical thread may run at real-time priority; ``tcp_offset`` (the edge's
    ``goto.tcp_offset``, None when not set): the tool point a real controller's installation must have."""
    if isinstance(config, SimRobotConfig):
        from iorthand_edge.robots.sim import SimRobot

        return SimRobot(config)
    if isinstance(config, URRobotConfig):
        from iorthand_edge.robots.ur import URRobot  # imports ur_rtde only when a UR is configured

        return URRobot(config, stop_deceleration, realtime, tcp_offset)
    raise ValueError(f"no robot backend for {type(config).__name__}")


__all__ = ["Robot", "RobotConfig", "RobotFault", "RobotReading", "make_robot"]
