"""A simulated robot: a kinematic model of the tool driven by Cartesian velocity.

The tool velocity follows the commanded twist with the commanded acceleration (a ramp), and the pose is
integrated from it, in the base frame. Time comes from the monotonic clock at each call, so the model needs no
thread of its own and is exact whatever the caller's rate. Joint angles are not computed: ``q`` stays at the
UR3e home posture (documented in robots/config.py); the tool pose is what every consumer uses.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from iorthand import geometry
from iorthand_edge.robots.base import Robot, RobotFault, RobotReading, Vector
from iorthand_edge.robots.config import UR3E_HOME_Q, SimRobotConfig


class SimRobot(Robot):
    def __init__(self, config: SimRobotConfig, clock=time.monotonic) -> None:
        self.config = config
        self._clock = clock
        self._lock = threading.Lock()
        self._pose = geometry.pose_to_matrix(config.initial_pose)
        self._velocity = np.zeros(6)
        self._target = np.zeros(6)
        self._acceleration = 1.0
        self._last = clock()
        self._t0 = self._last
        self.connected = False

    @property
    def control_period(self) -> float:
        return 1.0 / self.config.control_rate_hz

    def connect(self) -> None:
        with self._lock:
            self.connected = True
            self._last = self._clock()

    def _advance(self) -> None:
        now = self._clock()
        dt = max(0.0, now - self._last)
        self._last = now
        if dt == 0.0:
            return
        # Ramp the velocity toward the target at the commanded acceleration (vector-wise, so the direction of
        # an accelerating move is preserved), integrating with the mean velocity over the step.
        delta = self._target - self._velocity
        step = self._acceleration * dt
        norm = float(np.linalg.norm(delta))
        new_velocity = self._target.copy() if norm <= step else self._velocity + delta * (step / norm)
        mean = (self._velocity + new_velocity) / 2.0
        self._velocity = new_velocity
        self._pose[:3, 3] += mean[:3] * dt
        self._pose[:3, :3] = geometry.rotvec_to_matrix(mean[3:] * dt) @ self._pose[:3, :3]

    def read_state(self) -> RobotReading:
        with self._lock:
            self._advance()
            return RobotReading(
                tcp_pose=geometry.matrix_to_pose(self._pose),
                tcp_speed=self._velocity.copy(),
                q=np.array(UR3E_HOME_Q),
                timestamp_ns=time.time_ns(),
                robot_time=self._last - self._t0,
                mode="running" if self.connected else "disconnected",
                connected=self.connected,
            )

    def send_twist(self, twist: Vector, acceleration: float) -> Vector:
        twist = np.asarray(twist, dtype=float)
        if twist.shape != (6,) or not np.all(np.isfinite(twist)):
            raise ValueError(f"a twist has 6 finite numbers, got {twist!r}")
        with self._lock:
            if not self.connected:
                raise RobotFault("simulated robot is not connected")
            self._advance()
            self._target = twist.copy()
            self._acceleration = max(float(acceleration), 1e-6)
            return self._target.copy()

    def stop(self, deceleration: float) -> None:
        with self._lock:
            self._advance()
            self._target = np.zeros(6)
            self._acceleration = max(float(deceleration), 1e-6)

    def disconnect(self) -> None:
        with self._lock:
            self._advance()
            self._target = np.zeros(6)
            self._velocity = np.zeros(6)
            self.connected = False

    def teleport(self, pose: Vector) -> None:
        """Place the tool (tests and demos only)."""
        with self._lock:
            self._pose = geometry.pose_to_matrix(pose)
            self._velocity = np.zeros(6)
            self._target = np.zeros(6)
