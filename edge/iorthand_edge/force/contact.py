"""The simulated phantom: a flat, springy surface in the robot's workspace. Pure maths, no I/O.

The phantom is the plane ``z = surface_z`` (base frame) over an x/y box; the tool tip is the TCP. Pressing
``d`` metres below the surface at speed ``v`` into it gives a normal force ``k·d + c·v`` (never pulling: a
surface cannot hold the probe), along +z of the base frame. The sensor measures the reaction in its own
frame (the tool frame), which is what a real wrist sensor reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand.config import setting
from iorthand.geometry import rotvec_to_matrix


@dataclass
class PhantomConfig:
    surface_z: float = setting(0.15, lo=-2.0, hi=2.0, help="m: height of the phantom's surface, base frame")
    x_range: list[float] = setting(default_factory=lambda: [0.20, 0.40], length=2, help="m: extent along x")
    y_range: list[float] = setting(default_factory=lambda: [-0.10, 0.10], length=2, help="m: extent along y")
    stiffness: float = setting(2000.0, lo=1.0, hi=1e6, help="N/m (soft tissue phantom: ~1–5 kN/m)")
    damping: float = setting(20.0, lo=0.0, hi=1e4, help="N·s/m, acts only while pressing in")

    def check(self) -> None:
        for name, r in (("x_range", self.x_range), ("y_range", self.y_range)):
            if r[0] >= r[1]:
                raise ValueError(f"{name} {r} must be [min, max] with min < max")

    def depth(self, tcp_pose: ArrayLike) -> float:
        """How far (m) the tool tip is below the surface; 0 when above it or outside the box."""
        p = np.asarray(tcp_pose, dtype=float)
        inside = self.x_range[0] <= p[0] <= self.x_range[1] and self.y_range[0] <= p[1] <= self.y_range[1]
        return max(0.0, self.surface_z - float(p[2])) if inside else 0.0

    def depth_for_force(self, force: float) -> float:
        """Static penetration (m) at which the spring alone gives ``force`` N."""
        return force / self.stiffness


def contact_wrench(phantom: PhantomConfig, tcp_pose: ArrayLike, tcp_speed: ArrayLike) -> NDArray[np.float64]:
    """The wrench ``[Fx, Fy, Fz, Tx, Ty, Tz]`` the phantom exerts on the tool, in the tool (sensor) frame."""
    pose = np.asarray(tcp_pose, dtype=float)
    depth = phantom.depth(pose)
    if depth <= 0.0:
        return np.zeros(6)
    vz = float(np.asarray(tcp_speed, dtype=float)[2])
    normal = max(0.0, phantom.stiffness * depth - phantom.damping * vz)  # vz < 0 is pressing in
    force_base = np.array([0.0, 0.0, normal])
    force_tool = rotvec_to_matrix(pose[3:]).T @ force_base
    # The contact is at the TCP, so it exerts no torque about it.
    return np.concatenate([force_tool, np.zeros(3)])
