"""The robot interface: one abstract class that every robot backend implements.

The agent talks to a robot only through this interface, from its control loop. ``send_twist`` returns what
was actually sent (after the backend's own clipping), as LeRobot's ``send_action`` does, so the supervisor
can publish the command that really reached the robot.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Vector = NDArray[np.float64]


class RobotFault(RuntimeError):
    """The robot cannot be commanded (link lost, protective stop, driver dead). The message says why."""


@dataclass
class RobotReading:
    """One state sample, SI units. ``tcp_pose`` is ``[x, y, z, rx, ry, rz]`` in the base frame."""

    tcp_pose: Vector
    tcp_speed: Vector
    q: Vector
    timestamp_ns: int  # when this sample was taken, on the agent's wall clock (what messages carry)
    robot_time: float = 0.0  # the controller's own clock, s
    mode: str = "running"
    connected: bool = True
    fault: str = ""  # empty while healthy; otherwise the reason motion is impossible
    tcp_force: Vector = field(default_factory=lambda: np.zeros(6))
    # Non-empty: somebody at the robot took it over (a program stopped on its teach pendant, local control), and why.
    # The agent disarms with this reason; the backend stays down until the edge is armed again (allow_restart).
    takeover: str = ""
    # When this sample was taken, on the monotonic clock: its age is judged on this one, as the wall clock can step.
    monotonic_ns: int = field(default_factory=time.monotonic_ns)


class Robot(ABC):
    """A robot arm commanded by Cartesian tool velocity."""

    @abstractmethod
    def connect(self) -> None:
        """Connect; raise RobotFault with the reason when the robot cannot be reached."""

    @abstractmethod
    def read_state(self) -> RobotReading:
        """The newest state. Never blocks for long: a dead link shows as ``connected=False`` / ``fault``."""

    @abstractmethod
    def send_twist(self, twist: Sequence[float], acceleration: float) -> Vector:
        """Command tool velocity ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s, base frame) with the given
        acceleration (m/s²). Returns the twist actually sent. Raises RobotFault if it cannot be sent."""

    @abstractmethod
    def stop(self, deceleration: float) -> None:
        """Bring the tool to rest with the given deceleration (m/s²). Must not raise on a dead link."""

    @abstractmethod
    def disconnect(self) -> None:
        """Stop motion and release the connection."""

    def allow_restart(self) -> None:
        """The edge was armed again: the on-site confirmation that whoever took the robot over at its side
        (``RobotReading.takeover``) is done. A backend that held back since then may connect again. Called by the
        agent holding its lock; returns at once."""
        return  # a backend that never holds back (the simulator) has nothing to do

    @property
    def control_period(self) -> float:
        """The period (s) at which the agent should run its control loop for this robot."""
        return 1.0 / 125.0

    @property
    def measures_joints(self) -> bool:
        """Whether ``RobotReading.q`` is measured. A robot that has no joint angles of its own (the simulator)
        reports a placeholder there, and the agent publishes the angles the kinematic guard tracks from the pose."""
        return True
