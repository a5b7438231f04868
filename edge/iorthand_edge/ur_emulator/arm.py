"""The emulated arm with joints: the TCP and the six joints of a UR3e/UR5e moving together, as on a controller.

Two kinds of motion, as the real controller has them:

* Cartesian commands (speedl, movel, stopl, jog) drive the TCP through :class:`.kinematics.ToolModel`; every
  control cycle the joints follow by inverse kinematics (:func:`iorthand.kinematics.inverse`), taking the
  solution nearest the joints of the previous cycle, so that they move continuously.
* Joint commands (movej, servoj, speedj, stopj, and servol, which the control script turns into a servoj to the
  inverse kinematics of its pose) drive the joints; the TCP follows by forward kinematics.

Every cycle's step is checked before it is taken. A step that fails is refused: the arm stays where it was,
stopped, and :attr:`ArmModel.fault` says why (the controller turns it into a protective stop, as a real one
does when an arm runs into these during a motion):

* the TCP pose has no inverse kinematics solution (out of reach);
* a joint would pass its limit ("position close to joint limits"): the e-Series' ±360°, with the UR3e's wrist 3
  turning without limit, or tighter limits from the configuration. A joint motion is not refused whole there: it
  goes as far as the limit within that step and stops at it, as a controller stops a joint motion at its limit
  whatever its cycle (a step refused whole left the arm short by up to a step's travel, which grows with the
  emulator's step on a loaded machine: 0.05 rad at 0.1 s);
* in a Cartesian motion, a joint would turn faster than its maximum speed: the arm is at a singularity, where
  the inverse kinematics jumps from one branch to another.

A target that is checked when its command starts (movel's pose, movej_ik, servol, get_inverse_kin) and has no
solution raises :class:`Unreachable` instead: URScript's interpreter fails there, the program stops with a
runtime error and the arm does not move.

Force mode (:meth:`ArmModel.force_mode`) is a simple admittance on top of either kind of motion, see
:class:`ForceMode`. The model is pure (no threads, no I/O); the controller calls it under its lock.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from iorthand import geometry
from iorthand import kinematics as ur_kinematics

from .kinematics import HOME_POSE, MotionMode, ToolModel, Trapezoid

Vector = NDArray[np.float64]
#: The measured wrench (base frame, at the TCP: what ``actual_TCP_force`` reports) at a pose and a TCP speed.
WrenchFn = Callable[[Sequence[float], Sequence[float]], Sequence[float]]

JOINT_NAMES = ("base", "shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3")

#: Maximum joint speeds (rad/s) from UR's data sheets: UR3e 180°/s for the big joints and 360°/s for the wrists,
#: UR5e 180°/s everywhere.
MAX_JOINT_SPEED: dict[str, tuple[float, ...]] = {
    "ur3e": (math.pi, math.pi, math.pi, 2 * math.pi, 2 * math.pi, 2 * math.pi),
    "ur5e": (math.pi,) * 6,
}

#: Longest step of the force-mode admittance (s): a controller cycle late by a loaded machine is integrated in
#: pieces this long, so that a stiff phantom cannot make the force loop diverge.
FORCE_SUBSTEP = 0.001


def default_joint_limits(arm: str) -> tuple[tuple[float, float], ...]:
    """The e-Series' joint ranges (rad): ±360° each; the UR3e's wrist 3 turns without limit."""
    full = (-ur_kinematics.JOINT_LIMIT, ur_kinematics.JOINT_LIMIT)
    return (full,) * 5 + (((-math.inf, math.inf),) if arm == "ur3e" else (full,))


class Unreachable(ValueError):
    """A command's target has no inverse kinematics solution: the program fails with a runtime error."""


@dataclass
class ForceMode:
    """URScript's ``force_mode(task_frame, selection_vector, wrench, type, limits)``, simplified.

    Along (about) each compliant axis of the task frame the TCP moves at ``gain × (wrench_i − applied_i)``, where
    ``applied`` is the wrench the robot applies to its environment (the opposite of the measured one), clipped
    to ``limits_i``: a first-order admittance that settles where the measured force equals the target. The other
    axes follow the commanded motion (speedl, servol, movel, ...) exactly. Simplified: only type 2 (the task
    frame as given, in the base frame; types 1 and 3 are treated as 2), one fixed gain (no
    ``force_mode_set_damping`` / ``_gain_scaling``), no limit on the deviation of the non-compliant axes.
    """

    task_frame: list[float]
    selection: list[bool]
    wrench: list[float]
    limits: list[float]
    gain: float = 0.005  # m/s per N of force error
    gain_rot: float = 0.05  # rad/s per N·m of torque error
    rotation: Vector = field(init=False)

    def __post_init__(self) -> None:
        self.rotation = geometry.rotvec_to_matrix(self.task_frame[3:6])


class _MoveJ:
    """movej: all joints start and stop together; the one that travels furthest follows the profile."""

    mode = MotionMode.MOVE_JOINT

    def __init__(self, q0: Vector, q1: Vector, v: float, a: float) -> None:
        self.q0, self.delta = q0.copy(), q1 - q0
        self.profile = Trapezoid(max(float(np.max(np.abs(self.delta))), 1e-12), v, a)
        self.elapsed = 0.0
        self.done = False

    def step(self, q: Vector, dt: float, vmax: Vector) -> Vector:
        self.elapsed += dt
        s, _ = self.profile.s_at(self.elapsed)
        self.done = self.elapsed >= self.profile.t_total
        return self.q0 + self.delta * (s / self.profile.length)


class _Servo:
    """servoj: the joints follow a target that the client updates every cycle, with a first-order lag of the
    lookahead time and at most each joint's maximum speed. (A real servoj's gain is accepted, not modelled.)"""

    mode = MotionMode.SERVO
    done = False

    def __init__(self, target: Vector, lookahead: float) -> None:
        self.target = target
        self.lookahead = lookahead

    def step(self, q: Vector, dt: float, vmax: Vector) -> Vector:
        # The exact discretisation of the lag: stable at any dt.
        delta = (self.target - q) * (1.0 - math.exp(-dt / max(self.lookahead, 1e-3)))
        return q + np.clip(delta, -vmax * dt, vmax * dt)


class _SpeedJ:
    """speedj (and stopj, toward zero): joint speeds ramp to a target at ``a`` rad/s², vector-wise."""

    def __init__(self, qd: Vector, target: Vector, a: float, stopping: bool) -> None:
        self.qd, self.target, self.a = qd.copy(), target, a
        self.mode = MotionMode.STOPPING if stopping else MotionMode.SPEED
        self.done = False

    def step(self, q: Vector, dt: float, vmax: Vector) -> Vector:
        delta = self.target - self.qd
        n = float(np.linalg.norm(delta))
        new = self.target.copy() if n <= self.a * dt else self.qd + delta * (self.a * dt / n)
        q_next = q + (self.qd + new) / 2 * dt
        self.qd = new
        self.done = self.mode is MotionMode.STOPPING and not np.any(new)
        return q_next


_JointMotion = _MoveJ | _Servo | _SpeedJ


class ArmModel:
    """TCP pose and joints of the emulated arm. Not thread-safe: the controller calls it under its own lock."""

    def __init__(self, arm: str = "ur3e", joint_limits: Sequence[Sequence[float]] | None = None,
                 pose: Sequence[float] = HOME_POSE, wrench: WrenchFn | None = None) -> None:
        self.arm = ur_kinematics.model(arm)
        limits = default_joint_limits(arm) if joint_limits is None else joint_limits
        if len(limits) != 6 or any(len(pair) != 2 or not pair[0] < pair[1] for pair in limits):
            raise ValueError(f"joint limits must be 6 pairs [min, max] with min < max (rad), got {limits!r}")
        self.lower = np.array([float(pair[0]) for pair in limits])
        self.upper = np.array([float(pair[1]) for pair in limits])
        self.vmax = np.array(MAX_JOINT_SPEED[self.arm.name])
        self.wrench = wrench  # the controller's sensor, read by force mode
        self.tcp_offset = [0.0] * 6
        self.tool = ToolModel(pose=[float(v) for v in pose])
        # The usual posture for the pose (iorthand's choice), else the solution nearest it within the limits.
        usual = ur_kinematics.solve_near(self.arm, self.tool.pose)
        if usual is None:
            raise ValueError(f"the initial pose {list(pose)} is out of reach of a {self.arm.name}")
        allowed = [q for q in ur_kinematics.inverse(self.arm, self.tool.pose) if self.within_limits(q)]
        if self.within_limits(usual):
            allowed = [usual]
        if not allowed:
            raise ValueError(f"no joints within the joint limits put a {self.arm.name} at the initial pose {list(pose)}")
        self.q: Vector = min(allowed, key=lambda q: float(np.linalg.norm(q - usual)))
        self.qd: Vector = np.zeros(6)
        self.twist = [0.0] * 6  # reported TCP speed (base frame)
        self.joint: _JointMotion | None = None
        self.force: ForceMode | None = None
        self.fault: str | None = None  # why the last step was refused; the controller takes it
        # The pendant's speed slider (RTDE target_speed_fraction): a controller runs every motion on a clock slowed
        # by it, so a speedl of 8 mm/s moves at 2.4 mm/s with the slider at 30 %.
        self.speed_fraction = 1.0

    # -- state ------------------------------------------------------------------------------------------

    @property
    def pose(self) -> list[float]:
        return self.tool.pose

    @property
    def mode(self) -> MotionMode:
        return self.joint.mode if self.joint is not None else self.tool.mode

    @property
    def steady(self) -> bool:
        return all(abs(v) < 1e-6 for v in self.twist)

    # -- kinematics ------------------------------------------------------------------------------------

    def fk(self, q: Sequence[float], tcp_offset: Sequence[float] | None = None) -> list[float]:
        """TCP pose at joints ``q`` (with this TCP offset, or the current one)."""
        offset = self.tcp_offset if tcp_offset is None else tcp_offset
        return geometry.matrix_to_pose(ur_kinematics.forward(self.arm, q, offset)).tolist()

    def flange_pose(self) -> list[float]:
        return geometry.matrix_to_pose(ur_kinematics.forward(self.arm, self.q)).tolist()

    def within_limits(self, q: Sequence[float]) -> bool:
        qa = np.asarray(q, dtype=float)
        return bool(np.all(qa >= self.lower) and np.all(qa <= self.upper))

    def ik(self, pose: Sequence[float], qnear: Sequence[float] | None = None) -> tuple[Vector | None, str]:
        """The joints nearest ``qnear`` (default: the current ones) that put the TCP at ``pose``, or None and why."""
        solutions = ur_kinematics.inverse(self.arm, np.asarray(pose, dtype=float), self.tcp_offset)
        if not solutions:
            return None, f"no inverse kinematics solution for p{_fmt(pose)} (out of reach of a {self.arm.name})"
        ref = np.array(self.q if qnear is None else qnear, dtype=float)
        # kinematics.nearest drops solutions beyond ±360°, which would hide the nearest one behind another branch
        # (and a joint without limit, the UR3e's wrist 3, may have wound further): solve around the angles modulo
        # 2π, add the turns back, then check this arm's own limits.
        turns = np.round(ref / (2 * math.pi)) * 2 * math.pi
        q = ur_kinematics.nearest(solutions, ref - turns)
        assert q is not None  # within ±π of ±π: never beyond ±2π
        q = q + turns
        if not self.within_limits(q):
            return None, self._limit_reason(q)
        return q, ""

    def _up_to_limits(self, target: Vector) -> Vector:
        """The joints on the way from the current ones to ``target`` where the first joint reaches its limit."""
        delta = target - self.q
        fraction = 1.0
        for i in range(6):
            if target[i] > self.upper[i] and delta[i] > 0:
                fraction = min(fraction, (self.upper[i] - self.q[i]) / delta[i])
            elif target[i] < self.lower[i] and delta[i] < 0:
                fraction = min(fraction, (self.lower[i] - self.q[i]) / delta[i])
        return np.clip(self.q + max(fraction, 0.0) * delta, self.lower, self.upper)

    def _limit_reason(self, q: Vector) -> str:
        bad = [i for i in range(6) if not self.lower[i] <= q[i] <= self.upper[i]]
        i = bad[0]
        return (f"position close to joint limits: {JOINT_NAMES[i]} at {math.degrees(q[i]):.1f}° would pass its "
                f"limits [{math.degrees(self.lower[i]):.1f}°, {math.degrees(self.upper[i]):.1f}°]")

    # -- commands ---------------------------------------------------------------------------------------

    def _slider_twist(self) -> list[float]:
        """The arm's twist on the speed slider's clock, where the tool model runs (its own, with the slider at 0)."""
        fraction = min(max(self.speed_fraction, 0.0), 1.0)
        return list(self.tool.twist) if fraction <= 0 else [v / fraction for v in self.twist]

    def _to_cartesian(self) -> None:
        """Hand a running joint motion over to the tool model, which continues from the arm's current speed."""
        if self.joint is not None:
            self.joint = None
            self.tool.twist = self._slider_twist()
            self.tool.mode = MotionMode.SPEED if any(self.twist) else MotionMode.IDLE
            self.tool.target_twist = list(self.tool.twist)

    def _to_joint(self, motion: _JointMotion) -> None:
        self.tool.halt()  # the tool model's own motion ends; the pose stays
        self.joint = motion

    def speedl(self, xd: Sequence[float], a: float) -> None:
        self._to_cartesian()
        self.tool.speedl(list(xd), a)

    def stopl(self, a: float) -> None:
        self._to_cartesian()
        self.tool.twist = self._slider_twist()  # force mode may have moved the TCP faster than the tool model did
        self.tool.stopl(a)

    def halt(self) -> None:
        """Stop at once, where the arm is (emergency stop, a refused step)."""
        self.joint = None
        self.tool.halt()
        self.twist = [0.0] * 6
        self.qd = np.zeros(6)

    def movel(self, target: Sequence[float], v: float, a: float) -> None:
        if not ur_kinematics.inverse(self.arm, np.asarray(target, dtype=float), self.tcp_offset):
            raise Unreachable(f"movel: no inverse kinematics solution for p{_fmt(target)} "
                              f"(out of reach of a {self.arm.name})")
        self._to_cartesian()
        self.tool.twist = self._slider_twist()
        self.tool.movel(list(target), v, a)

    def movel_fk(self, q: Sequence[float], v: float, a: float) -> None:
        self.movel(self.fk(q), v, a)

    def movej(self, q: Sequence[float], v: float, a: float) -> None:
        target = np.asarray(q, dtype=float)
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise Unreachable(f"movej: not a joint vector: {list(q)!r}")
        v = abs(v) if v > 0 else 1.05
        a = abs(a) if a > 0 else 1.4
        if float(np.max(np.abs(target - self.q))) < 1e-9:
            self.halt()
            return
        self._to_joint(_MoveJ(self.q, target, v, a))

    def movej_ik(self, pose: Sequence[float], v: float, a: float) -> None:
        q, why = self.ik(pose)
        if q is None:
            raise Unreachable(f"movej: {why}")
        self.movej(q, v, a)

    def servoj(self, q: Sequence[float], lookahead: float) -> None:
        target = np.asarray(q, dtype=float)
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise Unreachable(f"servoj: not a joint vector: {list(q)!r}")
        if isinstance(self.joint, _Servo):
            self.joint.target, self.joint.lookahead = target, lookahead
        else:
            self._to_joint(_Servo(target, lookahead))

    def servol(self, pose: Sequence[float], lookahead: float) -> None:
        # The control script does q = get_inverse_kin(pose) (nearest the current joints), then servoj(q).
        q, why = self.ik(pose)
        if q is None:
            raise Unreachable(f"get_inverse_kin: {why}")
        self.servoj(q, lookahead)

    def speedj(self, qd: Sequence[float], a: float) -> None:
        target = np.asarray(qd, dtype=float)
        a = abs(a) if a > 0 else 1.4
        if isinstance(self.joint, _SpeedJ) and self.joint.mode is MotionMode.SPEED:
            self.joint.target, self.joint.a = target, a
        else:
            self._to_joint(_SpeedJ(self.qd, target, a, stopping=False))

    def stopj(self, a: float) -> None:
        a = abs(a) if a > 0 else 10.0
        if not np.any(self.qd):
            self.halt()
            return
        self._to_joint(_SpeedJ(self.qd, np.zeros(6), a, stopping=True))

    def set_tcp(self, offset: Sequence[float]) -> None:
        """set_tcp: the joints stay, the TCP (and so the reported pose) moves with its new offset."""
        self.tcp_offset = [float(v) for v in offset]
        self.tool.pose = self.fk(self.q)

    def place(self, pose: Sequence[float]) -> None:
        """Put the arm at rest at ``pose`` (fault injection); ValueError when it cannot be reached."""
        q, why = self.ik(pose)
        if q is None:
            raise ValueError(why)
        self.halt()
        self.q = q
        self.tool.pose = [float(v) for v in pose]

    def place_joints(self, q: Sequence[float]) -> None:
        """Put the arm at rest at joints ``q`` (fault injection); ValueError outside the joint limits."""
        qa = np.asarray(q, dtype=float)
        if qa.shape != (6,) or not self.within_limits(qa):
            raise ValueError(f"joints {list(q)!r} are not 6 values within the joint limits")
        self.halt()
        self.q = qa
        self.tool.pose = self.fk(qa)

    def force_mode(self, mode: ForceMode) -> None:
        self.force = mode

    def end_force_mode(self) -> None:
        self.force = None

    # -- the control cycle ------------------------------------------------------------------------------

    def step(self, dt: float) -> None:
        if dt <= 0 or (self.joint is None and self.force is None and self.tool.mode is MotionMode.IDLE):
            return
        before = list(self.tool.pose)
        joint = self.joint
        # Motions advance on the slider's clock; speeds measured below (joint speeds, the TCP twist) on the real one.
        fraction = min(max(self.speed_fraction, 0.0), 1.0)
        scaled = dt * fraction
        q_nominal: Vector | None = None  # where a joint motion takes the joints
        if joint is not None:
            q_nominal = joint.step(self.q, scaled, self.vmax)
            pose = self.fk(q_nominal)
        else:
            self.tool.step(scaled)
            pose = list(self.tool.pose)
            if pose == before and self.force is None:  # e.g. a speedl of zero: nothing to solve
                self.qd = np.zeros(6)
                self.twist = [v * fraction for v in self.tool.twist]
                return
        if self.force is not None:
            pose = self._comply(before, pose, dt)
        why = ""
        if q_nominal is not None and self.force is None:
            q: Vector | None = q_nominal
            if not self.within_limits(q_nominal):
                why = self._limit_reason(q_nominal)
                q = self._up_to_limits(q_nominal)
                pose = self.fk(q)
        else:
            q, why = self.ik(pose, self.q if q_nominal is None else q_nominal)
            if q is not None and joint is None:
                speed = np.abs(q - self.q) / dt
                if np.any(speed > self.vmax):
                    i = int(np.argmax(speed / self.vmax))
                    q, why = None, (f"{JOINT_NAMES[i]} would turn at {math.degrees(speed[i]):.0f}°/s, over its "
                                    f"maximum {math.degrees(self.vmax[i]):.0f}°/s (a singularity)")
        if q is None:
            # Refuse the step: the arm stays where it was, stopped.
            self.tool.pose = before
            self.halt()
            self.fault = why
            return
        self.qd = (q - self.q) / dt
        self.q = q
        self.tool.pose = pose
        if joint is None and self.force is None:
            self.twist = [v * fraction for v in self.tool.twist]  # the tool model's exact twist, on the real clock
        else:
            self.twist = _pose_rate(before, pose, dt)
        if why:  # a joint motion that reached a joint limit: stopped there
            self.halt()
            self.fault = why
            return
        if joint is not None and joint.done:
            self.joint = None
            self.twist = [0.0] * 6
            self.qd = np.zeros(6)

    def _comply(self, before: list[float], nominal: list[float], dt: float) -> list[float]:
        """Force mode: the nominal step with its compliant components replaced by the admittance's."""
        fm = self.force
        assert fm is not None
        rt = fm.rotation
        p0 = np.array(before[:3])
        r0 = geometry.rotvec_to_matrix(before[3:])
        lin = rt.T @ (np.array(nominal[:3]) - p0)  # the nominal step in the task frame
        ang = rt.T @ geometry.matrix_to_rotvec(geometry.rotvec_to_matrix(nominal[3:]) @ r0.T)
        sel = np.array(fm.selection[:6], dtype=bool)
        lin[sel[:3]] = 0.0
        ang[sel[3:]] = 0.0
        n = max(1, math.ceil(dt / FORCE_SUBSTEP - 1e-9))
        h = dt / n
        target = np.array(fm.wrench[:6], dtype=float)
        limit = np.abs(np.array(fm.limits[:6], dtype=float))
        gain = np.array([fm.gain] * 3 + [fm.gain_rot] * 3)
        offset, velocity = np.zeros(6), np.zeros(6)  # compliant displacement and speed, task frame
        for k in range(n):
            p = p0 + rt @ (lin * (k / n) + offset[:3])
            v = rt @ (lin / dt + velocity[:3])
            measured = np.zeros(6) if self.wrench is None else np.asarray(self.wrench([*p, *before[3:]], [*v, 0, 0, 0]),
                                                                              dtype=float)
            # The wrench the robot applies to its environment is the opposite of the one it measures.
            applied = -np.concatenate([rt.T @ measured[:3], rt.T @ measured[3:]])
            velocity = np.where(sel, np.clip(gain * (target - applied), -limit, limit), 0.0)
            offset += velocity * h
        lin += offset[:3]
        ang += offset[3:]
        position = p0 + rt @ lin
        rotation = geometry.rotvec_to_matrix(rt @ ang) @ r0
        return [*position.tolist(), *geometry.matrix_to_rotvec(rotation).tolist()]


def _pose_rate(a: Sequence[float], b: Sequence[float], dt: float) -> list[float]:
    """The TCP twist (base frame) that takes pose ``a`` to ``b`` in ``dt``."""
    w = geometry.matrix_to_rotvec(geometry.rotvec_to_matrix(b[3:6]) @ geometry.rotvec_to_matrix(a[3:6]).T)
    return [(b[i] - a[i]) / dt for i in range(3)] + (w / dt).tolist()


def _fmt(values: Sequence[float]) -> str:
    return "[" + ", ".join(f"{float(v):.4f}" for v in values) + "]"
