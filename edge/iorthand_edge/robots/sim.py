"""A simulated robot: a kinematic model of the tool driven by Cartesian velocity.

The tool velocity follows the commanded twist with the commanded acceleration (a ramp), and the pose is
integrated from it, in the base frame. Time comes from the monotonic clock at each call, so the model needs no
thread of its own and is exact whatever the caller's rate. Joint angles are not computed here: ``q`` is the UR3e
home posture, a placeholder (:attr:`measures_joints` is False); the agent publishes the angles its kinematic
guard tracks from the pose instead.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence

import numpy as np

from iorthand import geometry
from iorthand_edge.robots.base import Robot, RobotFault, RobotReading, Vector
from iorthand_edge.robots.config import UR3E_HOME_Q, SimRobotConfig


class SimRobot(Robot):
    # State in plain floats, numpy only for the orientation while it turns: send_twist runs on every command,
    # and a handful of numpy calls on 6-vectors cost more than the arithmetic they do.
    def __init__(self, config: SimRobotConfig, clock=time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self._lock = threading.Lock()
        self._set_pose(config.initial_pose)
        self._velocity = [0.0] * 6
        self._target = [0.0] * 6
        self._acceleration = 1.0
        self._last = clock()
        self._t0 = self._last
        self.connected = False

    @property
    def control_period(self) -> float:
        return 1.0 / self.config.control_rate_hz

    @property
    def measures_joints(self) -> bool:
        return False

    def connect(self) -> None:
        with self._lock:
            self.connected = True
            self._last = self._clock()

    def _set_pose(self, pose: Vector | list[float]) -> None:
        matrix = geometry.pose_to_matrix(pose)
        self._position = matrix[:3, 3].tolist()
        self._rotation = matrix[:3, :3]
        self._rotvec = geometry.matrix_to_rotvec(self._rotation).tolist()

    def _advance(self) -> None:
        now = self._clock()
        dt = max(0.0, now - self._last)
        self._last = now
        if dt == 0.0:
            return
        # Ramp the velocity toward the target at the commanded acceleration (vector-wise, so the direction of
        # an accelerating move is preserved), integrating with the mean velocity over the step.
        velocity, target = self._velocity, self._target
        delta = [t - v for t, v in zip(target, velocity, strict=True)]
        step = self._acceleration * dt
        norm = math.sqrt(sum(d * d for d in delta))
        new_velocity = list(target) if norm <= step else [v + d * (step / norm) for v, d in zip(velocity, delta, strict=True)]
        mean = [(v + w) / 2.0 for v, w in zip(velocity, new_velocity, strict=True)]
        self._velocity = new_velocity
        self._position = [p + m * dt for p, m in zip(self._position, mean[:3], strict=True)]
        if any(mean[3:]):
            self._rotation = geometry.rotvec_to_matrix([m * dt for m in mean[3:]]) @ self._rotation
            self._rotvec = geometry.matrix_to_rotvec(self._rotation).tolist()

    def read_state(self) -> RobotReading:
        with self._lock:
            self._advance()
            return RobotReading(
                tcp_pose=np.array(self._position + self._rotvec),
                tcp_speed=np.array(self._velocity),
                q=np.array(UR3E_HOME_Q),
                timestamp_ns=time.time_ns(),
                robot_time=self._last - self._t0,
                mode="running" if self.connected else "disconnected",
                connected=self.connected,
            )

    def send_twist(self, twist: Sequence[float], acceleration: float) -> Vector:
        values = [float(v) for v in twist]
        if len(values) != 6 or not all(map(math.isfinite, values)):
            raise ValueError(f"a twist has 6 finite numbers, got {twist!r}")
        with self._lock:
            if not self.connected:
                raise RobotFault("simulated robot is not connected")
            self._advance()
            self._target = values
            self._acceleration = max(float(acceleration), 1e-6)
            return np.array(values)

    def stop(self, deceleration: float) -> None:
        with self._lock:
            self._advance()
            self._target = [0.0] * 6
            self._acceleration = max(float(deceleration), 1e-6)

    def disconnect(self) -> None:
        with self._lock:
            self._advance()
            self._target = [0.0] * 6
            self._velocity = [0.0] * 6
            self.connected = False

    def teleport(self, pose: Vector) -> None:
        """Place the tool (tests and demos only)."""
        with self._lock:
            self._set_pose(pose)
            self._velocity = [0.0] * 6
            self._target = [0.0] * 6
