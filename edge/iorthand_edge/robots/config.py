"""One configuration dataclass per kind of robot, chosen by ``robot.kind`` in the edge YAML."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from iorthand.config import setting

# UR3e "home" joint angles (rad): the simulated robot's placeholder for the joint angles it does not measure.
UR3E_HOME_Q = [0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0]


@dataclass
class RobotConfig:
    """Base of the robot configurations; ``VARIANTS`` maps ``kind`` to the dataclass for it."""

    VARIANTS: ClassVar[dict[str, type[RobotConfig]]] = {}
    KIND: ClassVar[str] = ""

    control_rate_hz: float = setting(125.0, lo=10.0, hi=1000.0, help="control loop and state/robot rate")
    model: str = setting("ur3e", choices=("ur3e", "ur5e"), help="the arm (its kinematics: reach, singularities)")


@dataclass
class SimRobotConfig(RobotConfig):
    """A kinematic Cartesian-velocity model of the tool (no dynamics, no joint limits)."""

    KIND: ClassVar[str] = "sim"
    initial_pose: list[float] = setting(
        default_factory=lambda: [0.30, 0.0, 0.25, 3.14159, 0.0, 0.0], length=6,
        help="start pose [x,y,z,rx,ry,rz], m and rotation vector; default: tool pointing down",
    )


@dataclass
class URRobotConfig(RobotConfig):
    """A real Universal Robots arm (or the emulator) through ur_rtde, driven from a child process."""

    KIND: ClassVar[str] = "ur"
    host: str = "127.0.0.1"
    rtde_frequency: float = setting(125.0, lo=10.0, hi=500.0)
    watchdog_hz: float = setting(10.0, lo=1.0, hi=500.0, help="controller stops the program after 1/f s silent")
    connect_timeout: float = setting(5.0, lo=0.5, hi=60.0)
    reconnect_max_s: float = setting(5.0, lo=0.1, hi=60.0, help="longest back-off between reconnects")
    link_timeout: float = setting(0.1, lo=0.01, hi=2.0, help="controller timestamp frozen this long = link lost")
    # The workspace box, the kinematics and the force levels hold for one tool point and one payload: the
    # controller's installation must have them, or the box guards another point and the force readings carry the
    # weight difference. The tool point is goto.tcp_offset (the kinematics' too), checked at connect.
    tcp_tolerance_m: float = setting(0.001, lo=0.0, hi=0.05, help="allowed TCP position difference from goto.tcp_offset")
    tcp_tolerance_rad: float = setting(0.01, lo=0.0, hi=0.5, help="allowed TCP orientation difference")
    payload_kg: float | None = setting(
        None, lo=0.0, hi=20.0, help="the payload the controller must have (end-effector mass); another one is "
        "refused at connect. None: not checked (warned)",
    )
    payload_tolerance_kg: float = setting(0.05, lo=0.0, hi=5.0, help="allowed payload difference")


RobotConfig.VARIANTS = {c.KIND: c for c in (SimRobotConfig, URRobotConfig)}
