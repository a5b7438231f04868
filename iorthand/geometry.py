"""Rigid transforms: 4×4 homogeneous matrices, rotation vectors, UR pose vectors.

A UR pose is ``[x, y, z, rx, ry, rz]``: metres and a rotation vector (axis × angle, rad). It is never a set of
Euler angles. All functions are pure numpy and accept any array-like input.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

Matrix = NDArray[np.float64]
_SMALL = 1e-12


def _rotation_rows(rx: float, ry: float, rz: float) -> tuple[tuple[float, float, float], ...]:
    """Rodrigues' formula on plain floats (a few numpy calls on 3-vectors cost more than the maths; the edge's
    kinematic guard converts a pose every control cycle)."""
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    if theta < _SMALL:  # first order: I + [rv]×
        return (1.0, -rz, ry), (rz, 1.0, -rx), (-ry, rx, 1.0)
    kx, ky, kz = rx / theta, ry / theta, rz / theta
    c, s = math.cos(theta), math.sin(theta)
    v = 1.0 - c  # R = I + s·K + (1 − c)·K², K² = k·kᵀ − I
    return ((c + kx * kx * v, kx * ky * v - kz * s, kx * kz * v + ky * s),
            (ky * kx * v + kz * s, c + ky * ky * v, ky * kz * v - kx * s),
            (kz * kx * v - ky * s, kz * ky * v + kx * s, c + kz * kz * v))


def rotvec_to_matrix(rv: ArrayLike) -> Matrix:
    """Rodrigues' formula: rotation vector (rad) → 3×3 rotation matrix."""
    rx, ry, rz = np.asarray(rv, dtype=float).tolist()
    return np.array(_rotation_rows(rx, ry, rz))


def rotate(rv: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    """Rotate the 3-vector ``v`` by the rotation vector ``rv`` (Rodrigues' formula on plain floats: the
    supervisor calls it for every command, where a few numpy calls on 3-vectors cost more than the maths)."""
    rx, ry, rz = (float(c) for c in rv)
    vx, vy, vz = (float(c) for c in v)
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    if theta < _SMALL:  # first order, as rotvec_to_matrix: v + rv × v
        return vx + ry * vz - rz * vy, vy + rz * vx - rx * vz, vz + rx * vy - ry * vx
    kx, ky, kz = rx / theta, ry / theta, rz / theta
    c, s = math.cos(theta), math.sin(theta)
    kv = (kx * vx + ky * vy + kz * vz) * (1.0 - c)
    return (
        vx * c + (ky * vz - kz * vy) * s + kx * kv,
        vy * c + (kz * vx - kx * vz) * s + ky * kv,
        vz * c + (kx * vy - ky * vx) * s + kz * kv,
    )


def matrix_to_rotvec(r: ArrayLike) -> NDArray[np.float64]:
    """3×3 rotation matrix → rotation vector with angle in [0, π]; stable near 0 and π."""
    r = np.asarray(r, dtype=float)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r.tolist()
    theta = math.acos(min(1.0, max(-1.0, (r00 + r11 + r22 - 1.0) / 2.0)))
    wx, wy, wz = r21 - r12, r02 - r20, r10 - r01  # 2·sin θ · axis
    if theta < 1e-6:
        return np.array([wx / 2.0, wy / 2.0, wz / 2.0])
    if math.pi - theta < 1e-4:
        # Near π the antisymmetric part vanishes: take the axis from the symmetric part instead.
        b = (r + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(b)))
        axis = b[:, i] / math.sqrt(max(b[i, i], _SMALL))
        axis /= np.linalg.norm(axis)
        # Resolve the sign with what little antisymmetric part remains.
        if wx * axis[0] + wy * axis[1] + wz * axis[2] < 0:
            axis = -axis
        return axis * theta
    k = theta / (2.0 * math.sin(theta))
    return np.array([wx * k, wy * k, wz * k])


def make_transform(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> Matrix:
    t = np.eye(4)
    if rotation is not None:
        t[:3, :3] = np.asarray(rotation, dtype=float)
    if translation is not None:
        t[:3, 3] = np.asarray(translation, dtype=float)
    return t


def pose_to_matrix(pose: ArrayLike) -> Matrix:
    """UR pose ``[x, y, z, rx, ry, rz]`` → 4×4."""
    p = np.asarray(pose, dtype=float)
    if p.shape != (6,):
        raise ValueError(f"a UR pose has 6 numbers [x,y,z,rx,ry,rz], got shape {p.shape}")
    x, y, z, rx, ry, rz = p.tolist()
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = _rotation_rows(rx, ry, rz)
    return np.array([[r00, r01, r02, x], [r10, r11, r12, y], [r20, r21, r22, z], [0.0, 0.0, 0.0, 1.0]])


def matrix_to_pose(t: ArrayLike) -> NDArray[np.float64]:
    """4×4 → UR pose ``[x, y, z, rx, ry, rz]``."""
    t = np.asarray(t, dtype=float)
    return np.concatenate([t[:3, 3], matrix_to_rotvec(t[:3, :3])])


def invert(t: ArrayLike) -> Matrix:
    """Inverse of a rigid transform (uses Rᵀ, not a general matrix inverse)."""
    t = np.asarray(t, dtype=float)
    r = t[:3, :3]
    return make_transform(r.T, -r.T @ t[:3, 3])


def compose(*transforms: ArrayLike) -> Matrix:
    """Left-to-right product ``T1 · T2 · …``."""
    out = np.eye(4)
    for t in transforms:
        out = out @ np.asarray(t, dtype=float)
    return out


def rot_x(angle: float) -> Matrix:
    c, s = math.cos(angle), math.sin(angle)
    return make_transform([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(angle: float) -> Matrix:
    c, s = math.cos(angle), math.sin(angle)
    return make_transform([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(angle: float) -> Matrix:
    c, s = math.cos(angle), math.sin(angle)
    return make_transform([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def axis_rotation(axis: ArrayLike, angle: float) -> Matrix:
    """Rotation by ``angle`` (rad) about ``axis`` (any non-zero length), as a 4×4."""
    a = np.asarray(axis, dtype=float)
    return make_transform(rotvec_to_matrix(a / np.linalg.norm(a) * angle))


def pan_tilt_chain(
    t_tcp_mount: ArrayLike, pan_axis: ArrayLike, pan: float, tilt_axis: ArrayLike, tilt: float, t_tilt_camera: ArrayLike
) -> Matrix:
    """``T_tcp_camera = T_tcp_mount · R(pan_axis, pan) · R(tilt_axis, tilt) · T_tilt_camera``: the camera on
    its pan/tilt servos. ``pan``/``tilt`` are the chain's rotation angles (servo angle minus its zero)."""
    return compose(t_tcp_mount, axis_rotation(pan_axis, pan), axis_rotation(tilt_axis, tilt), t_tilt_camera)


def translation(x: float, y: float, z: float) -> Matrix:
    return make_transform(None, [x, y, z])


def rotation_angle(r_a: ArrayLike, r_b: ArrayLike) -> float:
    """Angle (rad) of the rotation between two rotation matrices (or the rotation parts of two 4×4)."""
    a = np.asarray(r_a, dtype=float)[:3, :3]
    b = np.asarray(r_b, dtype=float)[:3, :3]
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.acos(float(np.clip(c, -1.0, 1.0)))


def translation_distance(t_a: ArrayLike, t_b: ArrayLike) -> float:
    return float(np.linalg.norm(np.asarray(t_a, dtype=float)[:3, 3] - np.asarray(t_b, dtype=float)[:3, 3]))


def is_rigid(t: ArrayLike, tol: float = 1e-6) -> bool:
    """True for a proper rigid transform: orthonormal rotation with det +1 and a [0,0,0,1] last row, each within
    ``tol`` (as ``np.allclose`` with ``atol=tol`` compares). In plain floats: the perception pipeline checks every
    marker sample and every robot pose it keeps, and numpy's calls on a 4×4 cost ~10× more."""
    t = np.asarray(t, dtype=float)
    if t.shape != (4, 4):
        return False
    rows = t.tolist()
    if not all(map(math.isfinite, rows[0] + rows[1] + rows[2] + rows[3])):
        return False

    def close(value: float, expected: float) -> bool:  # np.allclose's test: atol=tol, rtol=1e-5
        return abs(value - expected) <= tol + 1e-5 * abs(expected)

    r = [row[:3] for row in rows[:3]]
    for i in range(3):  # RᵀR = I: the columns are unit vectors at right angles
        for j in range(i, 3):
            if not close(r[0][i] * r[0][j] + r[1][i] * r[1][j] + r[2][i] * r[2][j], 1.0 if i == j else 0.0):
                return False
    det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
           + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    return abs(det - 1.0) < tol and all(map(close, rows[3], (0.0, 0.0, 0.0, 1.0)))


def orthonormalize(r: ArrayLike) -> Matrix:
    """The nearest rotation matrix (SVD projection), det +1."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def interpolate_pose(t_a: ArrayLike, t_b: ArrayLike, s: float) -> Matrix:
    """Interpolate between two transforms: linear in translation, along the geodesic in rotation."""
    a = np.asarray(t_a, dtype=float)
    b = np.asarray(t_b, dtype=float)
    r_rel = a[:3, :3].T @ b[:3, :3]
    r = a[:3, :3] @ rotvec_to_matrix(matrix_to_rotvec(r_rel) * s)
    return make_transform(r, a[:3, 3] + (b[:3, 3] - a[:3, 3]) * s)


def flatten(t: ArrayLike) -> list[float]:
    """4×4 → 16 numbers, row-major (the wire form of a matrix)."""
    return [float(v) for v in np.asarray(t, dtype=float).reshape(16)]


def unflatten(values: Sequence[float]) -> Matrix:
    return np.asarray(values, dtype=float).reshape(4, 4)

def rotvec_to_quaternion(rv: Sequence[float]) -> tuple[float, float, float, float]:
    """A rotation vector (axis × angle, rad: UR's rx, ry, rz) → unit quaternion (x, y, z, w), as ROS and Foxglove
    order it. Plain floats: exporters and the Foxglove channels call this for every message."""
    rx, ry, rz = (float(c) for c in rv)
    theta = math.sqrt(rx * rx + ry * ry + rz * rz)
    if theta < 1e-12:
        return (0.0, 0.0, 0.0, 1.0)
    s = math.sin(theta / 2.0) / theta
    return (rx * s, ry * s, rz * s, math.cos(theta / 2.0))


def matrix_to_quaternion(m: ArrayLike) -> tuple[float, float, float, float]:
    """The rotation of a matrix → unit quaternion (x, y, z, w) with w ≥ 0 (q and −q are the same rotation: one
    canonical sign). ``m``: a 3×3 or 4×4 array, or its 9 or 16 numbers row-major. Shepperd's method: the largest
    of w, x, y, z is computed first, so no division by a small number, stable for every angle."""
    if isinstance(m, np.ndarray) and m.ndim == 2:
        m = m[:3, :3].ravel().tolist()
    elif not isinstance(m, (list, tuple)):
        m = np.asarray(m, dtype=float).ravel().tolist()
    n = 4 if len(m) == 16 else 3
    r00, r01, r02 = m[0], m[1], m[2]
    r10, r11, r12 = m[n], m[n + 1], m[n + 2]
    r20, r21, r22 = m[2 * n], m[2 * n + 1], m[2 * n + 2]
    trace = r00 + r11 + r22
    if trace > 0.0:
        s = 2.0 * math.sqrt(trace + 1.0)
        q = ((r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s)
    elif r00 > r11 and r00 > r22:
        s = 2.0 * math.sqrt(max(1.0 + r00 - r11 - r22, 1e-300))
        q = (0.25 * s, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s)
    elif r11 > r22:
        s = 2.0 * math.sqrt(max(1.0 + r11 - r00 - r22, 1e-300))
        q = ((r01 + r10) / s, 0.25 * s, (r12 + r21) / s, (r02 - r20) / s)
    else:
        s = 2.0 * math.sqrt(max(1.0 + r22 - r00 - r11, 1e-300))
        q = ((r02 + r20) / s, (r12 + r21) / s, 0.25 * s, (r10 - r01) / s)
    norm = math.sqrt(sum(c * c for c in q))
    x, y, z, w = (c / norm for c in q)
    return (x, y, z, w) if w >= 0.0 else (-x, -y, -z, -w)
