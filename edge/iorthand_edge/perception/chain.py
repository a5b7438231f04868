"""The kinematic chain from the robot base to a marker, through the pan/tilt servos. Pure maths, no I/O.

``T_base_marker = T_base_tcp(t_frame) · T_tcp_mount · R_pan(θ) · R_tilt(φ) · T_tilt_camera · T_camera_marker``
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from iorthand.geometry import Matrix, axis_rotation, compose, pan_tilt_chain, pose_to_matrix

from .config import MountGeometry


class CameraChain:
    """T_base_camera from the robot pose and the servo angles, for one mount geometry."""

    def __init__(self, geometry: MountGeometry, t_tilt_camera: Matrix | None = None) -> None:
        self.t_tcp_mount = pose_to_matrix(geometry.tcp_mount)
        self.pan_axis = np.asarray(geometry.pan_axis, dtype=float)
        self.tilt_axis = np.asarray(geometry.tilt_axis, dtype=float)
        self.t_tilt_camera = pose_to_matrix(geometry.tilt_camera) if t_tilt_camera is None else t_tilt_camera
        self.pan_zero, self.tilt_zero = geometry.pan_zero, geometry.tilt_zero

    def tcp_camera(self, pan: float, tilt: float) -> Matrix:
        """T_tcp_camera at the given servo angles (rad, as the servos report them)."""
        return pan_tilt_chain(
            self.t_tcp_mount, self.pan_axis, pan - self.pan_zero, self.tilt_axis, tilt - self.tilt_zero, self.t_tilt_camera
        )

    def base_camera(self, t_base_tcp: ArrayLike, pan: float, tilt: float) -> Matrix:
        return compose(t_base_tcp, self.tcp_camera(pan, tilt))

    def base_marker(self, t_base_tcp: ArrayLike, pan: float, tilt: float, t_camera_marker: ArrayLike) -> Matrix:
        return compose(self.base_camera(t_base_tcp, pan, tilt), t_camera_marker)

    def tilt_camera_from_tcp_camera(self, t_tcp_camera: ArrayLike, pan: float, tilt: float) -> Matrix:
        """T_tilt_camera from a hand-eye result T_tcp_camera measured at servo angles (pan, tilt)."""
        to_tilt = compose(
            self.t_tcp_mount, axis_rotation(self.pan_axis, pan - self.pan_zero), axis_rotation(self.tilt_axis, tilt - self.tilt_zero)
        )
        return np.linalg.solve(to_tilt, np.asarray(t_tcp_camera, dtype=float))
