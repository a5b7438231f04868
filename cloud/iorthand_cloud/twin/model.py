"""Geometry of the twin's drawing: pure numpy, no rerun (so it is tested without a viewer).

- The arm: joint angles from the TCP pose (:class:`iorthand.kinematics.ArmTracker`), then capsules between the
  points of :func:`iorthand.kinematics.link_points`.
- The camera: ``T_tcp_camera`` from the mount chain and the servo angles, and its intrinsic matrix.
- Force arrows: the colour of the level, grey when stale.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand import geometry, kinematics
from iorthand.protocol import FORCE_LEVEL_COLOURS, ForceLevel

from .config import CameraView, RobotView

Vector = NDArray[np.float64]

RGBA = tuple[int, int, int, int]
COLOURS: dict[str, RGBA] = {
    "green": (40, 190, 60, 255),
    "yellow": (240, 200, 20, 255),
    "red": (230, 40, 40, 255),
    "grey": (140, 140, 140, 255),
}
ARM_COLOUR: RGBA = (120, 160, 210, 255)
JOINT_COLOUR: RGBA = (60, 80, 110, 255)
GHOST_OK: RGBA = (60, 200, 90, 110)
GHOST_REFUSED: RGBA = (230, 60, 60, 110)


def force_colour(level: int, stale: bool) -> RGBA:
    """Green / yellow / red by level; grey when stale (no colour for data we do not trust)."""
    if stale:
        return COLOURS["grey"]
    return COLOURS[FORCE_LEVEL_COLOURS[ForceLevel(level)]]


@dataclass
class Capsules:
    """A batch of capsules in rerun's convention: each from ``translation`` along its own z for ``length``."""

    lengths: Vector
    radii: Vector
    translations: Vector  # N×3
    quaternions: Vector  # N×4, xyzw


def quaternion_z_to(direction: ArrayLike) -> Vector:
    """Unit quaternion (x, y, z, w) rotating +z onto ``direction``."""
    d = np.asarray(direction, dtype=float)
    n = float(np.linalg.norm(d))
    if n < 1e-12:
        return np.array([0.0, 0.0, 0.0, 1.0])
    d = d / n
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, d))
    if c < -1.0 + 1e-12:  # opposite: any perpendicular axis, 180°
        return np.array([1.0, 0.0, 0.0, 0.0])
    axis = np.cross(z, d)
    q = np.array([axis[0], axis[1], axis[2], 1.0 + c])
    return q / np.linalg.norm(q)


def segments_to_capsules(points: ArrayLike, radius: float) -> Capsules:
    p = np.asarray(points, dtype=float)
    starts, ends = p[:-1], p[1:]
    vec = ends - starts
    lengths = np.linalg.norm(vec, axis=1)
    keep = lengths > 1e-6  # zero-length segments (coincident DH origins) draw nothing useful
    d = vec[keep] / lengths[keep, None]
    # Vectorised quaternion_z_to: axis z × d = (-d_y, d_x, 0), w = 1 + d_z, normalised (runs 120 times a second).
    quats = np.column_stack([-d[:, 1], d[:, 0], np.zeros(len(d)), 1.0 + d[:, 2]])
    flipped = quats[:, 3] < 1e-9  # pointing straight down: 180° about x
    quats[flipped] = [1.0, 0.0, 0.0, 0.0]
    quats /= np.linalg.norm(quats, axis=1)[:, None]
    radii = np.full(int(np.sum(keep)), radius)
    return Capsules(lengths[keep], radii, starts[keep], quats)


class ArmModel(kinematics.ArmTracker):
    """The twin's arm: joint angles from the TCP pose (:class:`iorthand.kinematics.ArmTracker`), drawn as capsules."""

    def __init__(self, view: RobotView) -> None:
        super().__init__(view.model, view.tcp_offset)
        self.view = view

    def capsules(self, q: ArrayLike) -> Capsules:
        return segments_to_capsules(kinematics.link_points(self.model, q), self.model.link_radius)

    def joint_points(self, q: ArrayLike) -> Vector:
        return np.array([f[:3, 3] for f in kinematics.joint_frames(self.model, q)])


def tcp_camera(cam: CameraView, pan: float, tilt: float) -> Vector:
    """``T_tcp_camera`` at the servo angles (as published on state/servo), the edge's perception chain."""
    return geometry.pan_tilt_chain(
        geometry.pose_to_matrix(cam.tcp_mount), cam.pan_axis, pan - cam.pan_zero, cam.tilt_axis, tilt - cam.tilt_zero,
        geometry.pose_to_matrix(cam.tilt_camera),
    )


def intrinsics(cam: CameraView) -> Vector:
    return np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])


def world_from_base(view: RobotView) -> Vector:
    return geometry.pose_to_matrix(view.base if view.base is not None else [0.0] * 6)


def transform_parts(t: ArrayLike) -> tuple[Vector, Vector]:
    """A 4×4 as (translation, quaternion xyzw) for rerun."""
    t = np.asarray(t, dtype=float)
    return t[:3, 3].copy(), np.array(geometry.matrix_to_quaternion(t))


__all__ = [
    "ArmModel",
    "Capsules",
    "force_colour",
    "intrinsics",
    "quaternion_z_to",
    "segments_to_capsules",
    "tcp_camera",
    "transform_parts",
    "world_from_base",
]
