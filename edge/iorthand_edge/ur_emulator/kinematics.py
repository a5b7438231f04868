"""Cartesian tool model of the emulated arm: where the TCP is and how it moves in Cartesian commands.

This model is purely Cartesian: a TCP pose ``[x, y, z, rx, ry, rz]`` (metres, rotation vector in the base
frame, UR's convention) and a TCP twist ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s, base frame). It reproduces
what the UR controller does with the motion commands the ur_rtde control script issues:

* ``speedl(xd, a)`` ramps the twist towards ``xd`` with acceleration ``a`` (linear and angular parts limited
  separately, like UR's ``a``/``aRot``) and then keeps that twist *forever*, because the control script calls
  ``speedl`` again in a loop — the "speedL persists" behaviour of a real robot.
* ``stopl(a)`` ramps the twist down to zero with deceleration ``a``.
* ``movel(pose, a, v)`` follows a straight line with a trapezoidal speed profile; the orientation is
  interpolated along the geodesic in the same proportion.

The joints are :mod:`.arm`'s: it runs this model for the Cartesian commands and makes the joints follow by
inverse kinematics, and moves the joints itself for the joint commands (movej, servoj, speedj).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum

from iorthand import kinematics as ur_kinematics

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

#: Initial TCP pose: 30 cm in front of a UR3e base, 20 cm up, tool pointing down (rotation of pi about x).
HOME_POSE: tuple[float, ...] = (0.30, -0.10, 0.20, math.pi, 0.0, 0.0)


def _home_q() -> tuple[float, ...]:
    q = ur_kinematics.solve_near(ur_kinematics.UR3E, HOME_POSE)
    assert q is not None  # well within a UR3e's reach
    return tuple(float(v) for v in q)


#: The UR3e's joints (rad) at :data:`HOME_POSE`, where the emulated arm starts: the inverse kinematics solution
#: that looks like the usual "elbow up, tool down" posture turned toward the pose.
HOME_Q: tuple[float, ...] = _home_q()


def _norm(v: Vec3) -> float:
    return math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])


def rotvec_to_matrix(r: Vec3) -> Mat3:
    """Rodrigues' formula."""
    theta = _norm(r)
    if theta < 1e-12:
        return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    kx, ky, kz = r[0] / theta, r[1] / theta, r[2] / theta
    c, s = math.cos(theta), math.sin(theta)
    v = 1.0 - c
    return (
        (kx * kx * v + c, kx * ky * v - kz * s, kx * kz * v + ky * s),
        (ky * kx * v + kz * s, ky * ky * v + c, ky * kz * v - kx * s),
        (kz * kx * v - ky * s, kz * ky * v + kx * s, kz * kz * v + c),
    )


def matrix_to_rotvec(m: Mat3) -> Vec3:
    """Inverse of :func:`rotvec_to_matrix`, robust near 0 and near pi."""
    trace = m[0][0] + m[1][1] + m[2][2]
    cos_t = max(-1.0, min(1.0, (trace - 1.0) / 2.0))
    theta = math.acos(cos_t)
    if theta < 1e-9:
        return (0.0, 0.0, 0.0)
    if math.pi - theta < 1e-6:
        # Near pi the antisymmetric part vanishes: take the axis from the diagonal of (R + I) / 2 = k k^T.
        xx = max(0.0, (m[0][0] + 1.0) / 2.0)
        yy = max(0.0, (m[1][1] + 1.0) / 2.0)
        zz = max(0.0, (m[2][2] + 1.0) / 2.0)
        if xx >= yy and xx >= zz:
            kx = math.sqrt(xx)
            ky, kz = m[0][1] / (2 * kx), m[0][2] / (2 * kx)
        elif yy >= zz:
            ky = math.sqrt(yy)
            kx, kz = m[0][1] / (2 * ky), m[1][2] / (2 * ky)
        else:
            kz = math.sqrt(zz)
            kx, ky = m[0][2] / (2 * kz), m[1][2] / (2 * kz)
        n = _norm((kx, ky, kz))
        return (kx / n * theta, ky / n * theta, kz / n * theta)
    s = 2.0 * math.sin(theta)
    return (
        (m[2][1] - m[1][2]) / s * theta,
        (m[0][2] - m[2][0]) / s * theta,
        (m[1][0] - m[0][1]) / s * theta,
    )


def _row(m: Mat3, i: int) -> Vec3:
    return m[i]


def _col(m: Mat3, j: int) -> Vec3:
    return (m[0][j], m[1][j], m[2][j])


def _dot(u: Sequence[float], v: Sequence[float]) -> float:
    return u[0] * v[0] + u[1] * v[1] + u[2] * v[2]


def matmul(a: Mat3, b: Mat3) -> Mat3:
    c0, c1, c2 = _col(b, 0), _col(b, 1), _col(b, 2)
    r0, r1, r2 = _row(a, 0), _row(a, 1), _row(a, 2)
    return (
        (_dot(r0, c0), _dot(r0, c1), _dot(r0, c2)),
        (_dot(r1, c0), _dot(r1, c1), _dot(r1, c2)),
        (_dot(r2, c0), _dot(r2, c1), _dot(r2, c2)),
    )


def transpose(a: Mat3) -> Mat3:
    return (_col(a, 0), _col(a, 1), _col(a, 2))


def matvec(a: Mat3, v: Vec3) -> Vec3:
    return (
        a[0][0] * v[0] + a[0][1] * v[1] + a[0][2] * v[2],
        a[1][0] * v[0] + a[1][1] * v[1] + a[1][2] * v[2],
        a[2][0] * v[0] + a[2][1] * v[1] + a[2][2] * v[2],
    )


def pose_trans(p_from: list[float], p_from_to: list[float]) -> list[float]:
    """URScript ``pose_trans``: compose two poses (``p_from`` * ``p_from_to``)."""
    ra = rotvec_to_matrix((p_from[3], p_from[4], p_from[5]))
    rb = rotvec_to_matrix((p_from_to[3], p_from_to[4], p_from_to[5]))
    t = matvec(ra, (p_from_to[0], p_from_to[1], p_from_to[2]))
    r = matrix_to_rotvec(matmul(ra, rb))
    return [p_from[0] + t[0], p_from[1] + t[1], p_from[2] + t[2], r[0], r[1], r[2]]


def _ramp(current: Sequence[float], target: Sequence[float], max_step: float) -> Vec3:
    """Move ``current`` towards ``target`` by at most ``max_step`` (vector norm)."""
    d = (target[0] - current[0], target[1] - current[1], target[2] - current[2])
    n = _norm(d)
    if n <= max_step or n < 1e-15:
        return (target[0], target[1], target[2])
    k = max_step / n
    return (current[0] + d[0] * k, current[1] + d[1] * k, current[2] + d[2] * k)


class MotionMode(Enum):
    IDLE = "idle"
    SPEED = "speed"  # speedl / speedj: track a commanded twist or joint speed
    STOPPING = "stopping"  # stopl / stopj / program stop: decelerate to zero
    MOVE = "move"  # movel: trapezoidal profile to a target pose
    MOVE_JOINT = "movej"  # movej: trapezoidal profile to target joints
    SERVO = "servo"  # servoj / servol: follow a target that the client updates every cycle


@dataclass
class Trapezoid:
    """A trapezoidal (or triangular, when ``v`` is never reached) speed profile over a path of ``length``."""

    length: float
    v: float
    a: float
    t_acc: float = field(init=False, default=0.0)
    t_total: float = field(init=False, default=0.0)

    def __post_init__(self) -> None:
        self.t_acc = self.v / self.a
        if self.a * self.t_acc * self.t_acc >= self.length:  # triangular profile: never reaches v
            self.t_acc = math.sqrt(self.length / self.a)
            self.t_total = 2 * self.t_acc
        else:
            self.t_total = 2 * self.t_acc + (self.length - self.a * self.t_acc * self.t_acc) / self.v

    def s_at(self, t: float) -> tuple[float, float]:
        """Distance along the path and speed at time ``t``."""
        if t >= self.t_total:
            return self.length, 0.0
        t_dec_start = self.t_total - self.t_acc
        if t < self.t_acc:
            return 0.5 * self.a * t * t, self.a * t
        v_peak = self.a * self.t_acc
        s_acc = 0.5 * self.a * self.t_acc * self.t_acc
        if t < t_dec_start:
            return s_acc + v_peak * (t - self.t_acc), v_peak
        td = self.t_total - t
        return self.length - 0.5 * self.a * td * td, self.a * td


@dataclass
class _LinearMove:
    start_p: Vec3
    start_r: Mat3
    direction: Vec3  # unit vector of the translation (zero when only rotating)
    axis_angle: Vec3  # rotation vector from start to target orientation, in the base frame
    profile: Trapezoid  # over the path length (m, or rad for a pure rotation)
    elapsed: float = 0.0


@dataclass
class ToolModel:
    """Cartesian state of the TCP. Not thread-safe: the controller calls it under its own lock."""

    pose: list[float] = field(default_factory=lambda: list(HOME_POSE))
    twist: list[float] = field(default_factory=lambda: [0.0] * 6)
    mode: MotionMode = MotionMode.IDLE
    target_twist: list[float] = field(default_factory=lambda: [0.0] * 6)
    accel: float = 0.25  # linear acceleration/deceleration of the current speed or stop command (m/s^2)
    accel_rot: float = 0.25  # angular counterpart (rad/s^2)
    _move: _LinearMove | None = None

    # -- commands --------------------------------------------------------------------------------------

    def speedl(self, xd: list[float], a: float) -> None:
        self.mode = MotionMode.SPEED
        self.target_twist = [float(v) for v in xd[:6]]
        a = abs(a) if a > 0 else 0.25
        self.accel, self.accel_rot = a, a
        self._move = None

    def stopl(self, a: float) -> None:
        a = abs(a) if a > 0 else 10.0
        self.target_twist = [0.0] * 6
        self.accel, self.accel_rot = a, a
        self._move = None
        self.mode = MotionMode.STOPPING if any(abs(v) > 0 for v in self.twist) else MotionMode.IDLE

    def halt(self) -> None:
        """Immediate stop without ramp (emergency stop, power loss)."""
        self.twist = [0.0] * 6
        self.target_twist = [0.0] * 6
        self._move = None
        self.mode = MotionMode.IDLE

    def movel(self, target: list[float], v: float, a: float) -> None:
        p0 = (self.pose[0], self.pose[1], self.pose[2])
        r0 = rotvec_to_matrix((self.pose[3], self.pose[4], self.pose[5]))
        r1 = rotvec_to_matrix((target[3], target[4], target[5]))
        delta = (target[0] - p0[0], target[1] - p0[1], target[2] - p0[2])
        dist = _norm(delta)
        rel = matrix_to_rotvec(matmul(r1, transpose(r0)))  # base-frame rotation taking r0 to r1
        angle = _norm(rel)
        v = abs(v) if v > 0 else 0.25
        a = abs(a) if a > 0 else 1.2
        # UR's movel speed is a tool speed; a pure re-orientation uses v and a as rad/s and rad/s^2.
        length = dist if dist > 1e-6 else angle
        if length < 1e-9:
            self.halt()
            return
        direction = (delta[0] / dist, delta[1] / dist, delta[2] / dist) if dist > 1e-6 else (0.0, 0.0, 0.0)
        self._move = _LinearMove(p0, r0, direction, rel, Trapezoid(length, v, a))
        self.mode = MotionMode.MOVE

    # -- queries ----------------------------------------------------------------------------------------

    @property
    def steady(self) -> bool:
        return all(abs(v) < 1e-6 for v in self.twist)

    # -- integration -----------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        if dt <= 0:
            return
        if self.mode is MotionMode.MOVE and self._move is not None:
            self._step_move(dt)
            return
        if self.mode in (MotionMode.SPEED, MotionMode.STOPPING):
            lin = _ramp(self.twist[:3], self.target_twist[:3], self.accel * dt)
            ang = _ramp(self.twist[3:], self.target_twist[3:], self.accel_rot * dt)
            # Integrate with the mean of old and new twist (trapezoid rule) so distances during ramps are exact.
            old = self.twist
            new = [*lin, *ang]
            self._integrate([(o + n) / 2 for o, n in zip(old, new, strict=True)], dt)
            self.twist = new
            if self.mode is MotionMode.STOPPING and all(v == 0.0 for v in new):
                self.mode = MotionMode.IDLE

    def _integrate(self, twist: list[float], dt: float) -> None:
        self.pose[0] += twist[0] * dt
        self.pose[1] += twist[1] * dt
        self.pose[2] += twist[2] * dt
        w = (twist[3] * dt, twist[4] * dt, twist[5] * dt)
        if _norm(w) > 0:
            r = matmul(rotvec_to_matrix(w), rotvec_to_matrix((self.pose[3], self.pose[4], self.pose[5])))
            self.pose[3:] = list(matrix_to_rotvec(r))

    def _step_move(self, dt: float) -> None:
        m = self._move
        assert m is not None
        m.elapsed += dt
        s, speed = m.profile.s_at(m.elapsed)
        frac = s / m.profile.length
        # direction is zero for a pure re-orientation, so the position then stays put.
        p = [m.start_p[i] + m.direction[i] * s for i in range(3)]
        rot = (m.axis_angle[0] * frac, m.axis_angle[1] * frac, m.axis_angle[2] * frac)
        r = matrix_to_rotvec(matmul(rotvec_to_matrix(rot), m.start_r))
        self.pose = [*p, *r]
        k = speed / m.profile.length  # d(frac)/dt
        self.twist = [m.direction[0] * speed, m.direction[1] * speed, m.direction[2] * speed,
                      m.axis_angle[0] * k, m.axis_angle[1] * k, m.axis_angle[2] * k]
        if m.elapsed >= m.profile.t_total:
            self.twist = [0.0] * 6
            self._move = None
            self.mode = MotionMode.IDLE
