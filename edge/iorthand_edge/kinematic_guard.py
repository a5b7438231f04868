"""Kinematic awareness in live teleoperation: singularities, joint limits and the edge of reach. Pure code.

The arm's joint angles follow its TCP pose (the robot's reported ``q`` where it agrees with the pose, else a
Newton step from the previous angles: continuous, never a flip between IK branches). Once per control cycle
:meth:`KinematicGuard.update` measures, at those angles:

- **manipulability**: the inverse condition number ``σmin/σmax`` of the Jacobian, its angular rows scaled by the
  arm's reach so that metres and radians weigh alike (0 at a singularity; a UR3e at home: 0.09). Which way is
  *toward* the singularity is the least singular direction, signed by a small step along it;
- **joint limits**: each joint's distance to its configured range (the ±360° of the e-Series, or tighter: the
  end-effector's cables);
- **reach**: what is left before the elbow is straight, ``|a2| + |a3|`` minus the shoulder–wrist span.

:meth:`KinematicGuard.limit` then scales each operator twist, as MoveIt Servo does: a twist that moves toward one
of them inside its *slow* margin is slowed with what is left of the margin (see :func:`_fraction`), and halted (zero) at
the *halt* margin; motion away from it is never slowed. Each case has its own status and a reason that names the
joint or the singularity. The per-command work is a few dozen multiplications on lists (the command path);
the numpy work happens in :meth:`~KinematicGuard.update`, in the control cycle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from iorthand import geometry, kinematics
from iorthand.config import setting
from iorthand.protocol import Status

JOINT_NAMES = ("base", "shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3")
_DAMPING = 1e-3  # of the pseudo-inverse: joint speeds stay finite at a singularity (only their sign is used there)
# An assessment stands while the pose (m, and its rotation vector, rad) and the reported joint angles (rad) stay this
# close to where it was made: what it measures is millimetres and hundredths of a radian from a limit, and it is
# never further than this from the arm's true place (it is remade once the arm moves this far from where it was
# made, not from the previous cycle). Recomputing at 125 Hz for an arm at rest cost 5-8 % of a core of the edge.
SAME_POSE = 1e-5


_Reading = tuple[tuple[float, ...], tuple[float, ...] | None]  # a TCP pose and the reported joint angles, if any


def _within(a: _Reading, b: _Reading) -> bool:
    """Whether two (pose, reported angles) are within SAME_POSE of each other, in plain floats (numpy's per-call
    cost was most of an arm at rest's cycle here). A NaN is never within: the arm is assessed again."""
    (pose_a, q_a), (pose_b, q_b) = a, b
    if not all(abs(x - y) <= SAME_POSE for x, y in zip(pose_a, pose_b, strict=True)):
        return False
    if q_a is None or q_b is None:
        return q_a is None and q_b is None
    return all(abs(x - y) <= SAME_POSE for x, y in zip(q_a, q_b, strict=True))


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """How far apart two poses (4×4) are: metres, plus a tenth of a metre per radian."""
    return geometry.translation_distance(a, b) + 0.1 * geometry.rotation_angle(a, b)


@dataclass
class KinematicLimits:
    """The ``safety.kinematics`` section: where live motion slows and halts."""

    enabled: bool = setting(True, help="slow and halt near singularities, joint limits and the edge of reach")
    slow_manipulability: float = setting(0.03, lo=0.001, hi=0.5, help="below this, motion toward a singularity slows")
    halt_manipulability: float = setting(0.01, lo=0.0, hi=0.5, help="at this, motion toward a singularity halts")
    joint_min: list[float] = setting(default_factory=lambda: [-2 * math.pi] * 6, length=6,
                                     help="rad per joint (base … wrist 3); tighter than ±2π for cabled tools")
    joint_max: list[float] = setting(default_factory=lambda: [2 * math.pi] * 6, length=6, help="rad per joint")
    joint_slow_margin: float = setting(0.26, lo=0.01, hi=1.0, help="rad from a joint limit where motion slows")
    joint_halt_margin: float = setting(0.035, lo=0.0, hi=0.5, help="rad from a joint limit where motion halts")
    reach_slow_margin: float = setting(0.03, lo=0.001, hi=0.3, help="m of elbow reach left where motion slows")
    reach_halt_margin: float = setting(0.005, lo=0.0, hi=0.1, help="m of elbow reach left where motion halts")

    def check(self) -> None:
        if self.halt_manipulability >= self.slow_manipulability:
            raise ValueError("halt_manipulability must be below slow_manipulability")
        if self.joint_halt_margin >= self.joint_slow_margin:
            raise ValueError("joint_halt_margin must be below joint_slow_margin")
        if self.reach_halt_margin >= self.reach_slow_margin:
            raise ValueError("reach_halt_margin must be below reach_slow_margin")
        for i, (lo, hi) in enumerate(zip(self.joint_min, self.joint_max, strict=True)):
            if lo >= hi:
                raise ValueError(f"joint_min[{i}] ({lo}) must be below joint_max[{i}] ({hi})")


@dataclass
class Assessment:
    """What :meth:`KinematicGuard.update` found at the current joint angles, and what :meth:`KinematicGuard.limit`
    needs of it (lists, not numpy: see the module doc). Replaced whole by each update, so a command on another
    thread sees one consistent assessment."""

    q: list[float] | None = None  # None: no joint solution for the pose (beyond reach)
    # σmin/σmax; outside the slow margin it may be a lower bound of it, one that is still outside (see _bounded).
    manipulability: float = 0.0
    reach_left: float = 0.0  # m of elbow span left
    nearest_joint: int = -1  # the joint closest to its limit
    joint_margin: float = math.inf  # rad from that limit
    # Rows: joint speed per scaled twist component. Only near a joint limit or the edge of reach (empty elsewhere):
    # nothing else reads it.
    pinv: list[list[float]] = field(default_factory=list)
    toward: list[float] | None = None  # the scaled twist direction into the singularity (when near one)
    near_joints: list[tuple[int, int, float]] = field(default_factory=list)  # (joint, +1 max / -1 min, margin)
    reach_near: bool = False


def _manipulability(singular_values: np.ndarray) -> float:
    """The inverse condition number σmin/σmax (singular values in decreasing order, as numpy gives them)."""
    return float(singular_values[-1] / singular_values[0])


def _fraction(left: float, halt: float, slow: float) -> float:
    """How much speed is allowed with ``left`` of a margin: 1 at ``slow`` and beyond, 0 at ``halt`` and within, the
    square root in between: a constant deceleration, which reaches the halt in finite time (a speed in proportion
    to the distance left would only approach it, exponentially)."""
    return math.sqrt(min(1.0, max(0.0, (left - halt) / (slow - halt))))


class KinematicGuard:
    def __init__(self, limits: KinematicLimits, model: str, tcp_offset: ArrayLike | None = None) -> None:
        limits.check()
        self.limits = limits
        self.model = kinematics.model(model)
        offset = np.asarray(tcp_offset, dtype=float) if tcp_offset is not None else None
        self.tcp_offset = offset if offset is not None and np.any(offset) else None
        self.scale = self.model.reach  # m per rad: weighs rotations like the motion of the arm's far end
        self.state = Assessment()
        self._q: np.ndarray | None = None
        self._assessed_at: _Reading | None = None  # where self.state was made
        self._disagreed: np.ndarray | None = None  # reported angles that did not give the pose
        # The Jacobian and TCP pose at self._q, where the last assessment computed them: the next Newton step starts
        # from them (one forward kinematics and Jacobian fewer per cycle of a moving arm).
        self._at_q: tuple[np.ndarray, np.ndarray] | None = None
        # The scaled Jacobian of the last singular value decomposition, with its largest and smallest singular value.
        self._svd_at: tuple[np.ndarray, float, float] | None = None

    # ------------------------------------------------------------------ per control cycle

    def update(self, tcp_pose: ArrayLike, reported_q: ArrayLike | None = None) -> Assessment:
        """The joint angles for ``tcp_pose`` and what is near at them. An arm at rest costs nothing: while the pose
        and the reported angles stay within :data:`SAME_POSE` of those of the last assessment, it stands."""
        # Copies: what is kept here must not change with the caller's arrays.
        at = (tuple(map(float, tcp_pose)), None if reported_q is None else tuple(map(float, reported_q)))
        if self._assessed_at is not None and _within(self._assessed_at, at):
            return self.state
        if not all(map(math.isfinite, at[0] + (at[1] or ()))):  # a broken reading: no angles, every motion halts
            self._assessed_at, self._q, self._at_q, self._svd_at, self.state = None, None, None, None, Assessment()
            return self.state
        self._assessed_at = at
        q, jac = self._track(np.array(at[0]), None if at[1] is None else np.array(at[1]))
        self._q = q
        if q is None:
            self.state = Assessment()
            return self.state
        lim = self.limits
        margins = [(float(q[i] - lim.joint_min[i]), float(lim.joint_max[i] - q[i])) for i in range(6)]
        near_joints = [(i, side, margin) for i, pair in enumerate(margins)
                       for side, margin in zip((-1, 1), pair, strict=True) if margin < lim.joint_slow_margin]
        nearest = min(range(6), key=lambda i: min(margins[i]))
        full = abs(self.model.a[1]) + abs(self.model.a[2])
        reach_left = full - kinematics.elbow_span(self.model, float(q[2]))
        reach_near = reach_left < lim.reach_slow_margin
        scaled = self._scaled_jacobian(q, jac)
        m = self._bounded(scaled)
        if m is None:
            m = self._decomposed(scaled, np.linalg.svd(scaled, compute_uv=False))
        pinv: list[list[float]] = []
        toward = None
        # The singular vectors only where they are used (a third of a driven cycle's cost otherwise): the joint
        # speeds a twist asks for near a joint limit or the edge of reach, the direction into a singularity near one.
        if near_joints or reach_near or m < lim.slow_manipulability:
            u, s, vt = np.linalg.svd(scaled)
            m = self._decomposed(scaled, s)
            inverse = vt.T @ np.diag(s / (s * s + _DAMPING**2)) @ u.T
            if near_joints or reach_near:
                pinv = inverse.tolist()
            if m < lim.slow_manipulability:
                direction = u[:, -1]
                step = inverse @ direction
                probe = q + 1e-3 * step / max(float(np.linalg.norm(step)), 1e-12)  # 1 mrad along it
                probed = _manipulability(np.linalg.svd(self._scaled_jacobian(probe), compute_uv=False))
                toward = (direction if probed < m else -direction).tolist()
        self.state = Assessment([float(v) for v in q], m, reach_left, nearest, min(margins[nearest]), pinv,
                                toward, near_joints, reach_near)
        return self.state

    def _bounded(self, scaled: np.ndarray) -> float | None:
        """A lower bound of the manipulability at ``scaled`` (a scaled Jacobian) from the last decomposition, if it
        proves the arm outside the slow margin; else None (decompose). By Weyl's inequality no singular value moves
        by more than the matrix does (its 2-norm, at most its Frobenius norm), so σmin/σmax is at least
        (σmin₀ − ε)/(σmax₀ + ε). What the guard decides is the same as with the exact value: above the slow margin
        nothing reads it but that comparison. The decomposition, a sixth of a moving arm's assessment, is then made
        about once a centimetre of motion instead of at every cycle."""
        if self._svd_at is None:
            return None
        at, largest, smallest = self._svd_at
        change = scaled - at
        eps = math.sqrt(float(np.vdot(change, change)))
        bound = (smallest - eps) / (largest + eps)
        return bound if bound >= self.limits.slow_manipulability else None

    def _decomposed(self, scaled: np.ndarray, singular_values: np.ndarray) -> float:
        """The manipulability from a decomposition of ``scaled``, kept for :meth:`_bounded`."""
        self._svd_at = (scaled, float(singular_values[0]), float(singular_values[-1]))
        return _manipulability(singular_values)

    def _scaled_jacobian(self, q: np.ndarray, jac: np.ndarray | None = None) -> np.ndarray:
        """The Jacobian at ``q`` (``jac``: already computed there) with its angular rows scaled by the reach."""
        scaled = kinematics.jacobian(self.model, q, self.tcp_offset)[0] if jac is None else jac.copy()
        scaled[3:] *= self.scale
        return scaled

    def _track(self, pose: np.ndarray, reported: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Joint angles at ``pose``, and the Jacobian there when it came with them: the reported angles if they
        agree, else Newton from the last (else IK). Reported angles that disagreed are not checked again while
        they stay the same (the simulator reports its home angles whatever its pose)."""
        target = geometry.pose_to_matrix(pose)
        if reported is not None and not (self._disagreed is not None and np.array_equal(reported, self._disagreed)):
            jac, tcp = kinematics.jacobian(self.model, reported, self.tcp_offset)
            if _distance(tcp, target) < 1e-4:
                self._disagreed, self._at_q = None, (jac, tcp)
                return reported, jac
            self._disagreed = reported
        q, at_q, self._at_q = self._q, self._at_q, None
        if q is not None:
            # Far from a singularity (the last assessment's manipulability, of a Jacobian scaled within a factor
            # of 2 of this one, is above the slow margin: a condition number under ~70) the least-squares step
            # equals the exact one, and an LU solve costs a fraction of lstsq's SVD (a third of a driven cycle's
            # guard). Near a singularity the least-squares step keeps the joint speeds bounded.
            exact = self.state.q is not None and self.state.manipulability >= self.limits.slow_manipulability
            for _ in range(4):
                jac, tcp = at_q or kinematics.jacobian(self.model, q, self.tcp_offset)
                at_q = None
                ex, ey, ez = (target[:3, 3] - tcp[:3, 3]).tolist()
                wx, wy, wz = geometry.matrix_to_rotvec(target[:3, :3] @ tcp[:3, :3].T).tolist()
                if math.sqrt(ex * ex + ey * ey + ez * ez) + 0.1 * math.sqrt(wx * wx + wy * wy + wz * wz) < 1e-7:
                    self._at_q = (jac, tcp)
                    return q, jac
                error = np.array([ex, ey, ez, wx, wy, wz])
                q = q + (np.linalg.solve(jac, error) if exact else np.linalg.lstsq(jac, error, rcond=1e-6)[0])
            if _distance(kinematics.forward(self.model, q, self.tcp_offset), target) < 1e-5:
                return q, None
        return kinematics.solve_near(self.model, pose, self._q, self.tcp_offset), None

    # ------------------------------------------------------------------ per command

    def limit(self, twist: list[float]) -> tuple[Status, str] | None:
        """Scale ``twist`` (base frame, in place) for whatever it moves toward; (status, reason) if it did."""
        snap = self.state
        if snap.q is None:
            if any(twist):
                twist[:] = [0.0] * 6
                return Status.REACH_LIMIT, "no joint solution for this pose (beyond the arm's reach): motion halted"
            return None
        lim = self.limits
        k = self.scale
        scaled = [*twist[:3], k * twist[3], k * twist[4], k * twist[5]]
        worst, status, reason = 1.0, Status.OK, ""
        if snap.toward is not None and sum(a * b for a, b in zip(scaled, snap.toward, strict=True)) > 0:
            m = snap.manipulability
            worst = _fraction(m, lim.halt_manipulability, lim.slow_manipulability)
            status, reason = Status.NEAR_SINGULARITY, f"{_singularity_name(snap.q)} (manipulability {m:.3f})"
        if snap.near_joints or snap.reach_near:
            qdot = [sum(a * b for a, b in zip(row, scaled, strict=True)) for row in snap.pinv]
            for joint, side, margin in snap.near_joints:
                if side * qdot[joint] > 0:
                    f = _fraction(margin, lim.joint_halt_margin, lim.joint_slow_margin)
                    if f < worst:
                        worst, status = f, Status.NEAR_JOINT_LIMIT
                        reason = (f"{JOINT_NAMES[joint]} {math.degrees(margin):.1f}° from its "
                                  f"{'upper' if side > 0 else 'lower'} limit")
            # The span grows as the elbow straightens: |q3| falling.
            if snap.reach_near and snap.q[2] * qdot[2] < 0:
                left = snap.reach_left
                f = _fraction(left, lim.reach_halt_margin, lim.reach_slow_margin)
                if f < worst:
                    worst, status = f, Status.NEAR_REACH
                    reason = f"the edge of reach: {1000 * left:.1f} mm of the elbow's span left"
        if worst >= 1.0:
            return None
        twist[:] = [v * worst for v in twist]
        if worst <= 0.0:
            return _HALTED[status], f"{reason}: motion toward it halted (move away from it)"
        return status, f"{reason}: slowed to {math.floor(100 * worst)} %"



def _singularity_name(q: list[float]) -> str:
    """Which of the UR's singularities is nearest (for the operator): wrist 2 straight, the elbow straight, or the
    wrist over the base's axis (the shoulder's)."""
    wrist = abs(math.sin(q[4]))
    elbow = abs(math.sin(q[2]))
    if wrist <= elbow and wrist < 0.5:
        return f"near the wrist singularity (wrist 2 at {math.degrees(math.asin(wrist)):.0f}° from straight)"
    if elbow < 0.5:
        return f"near the elbow singularity (elbow {math.degrees(math.asin(elbow)):.0f}° from straight)"
    return "near the shoulder singularity (the wrist close to the base's axis)"


_HALTED = {Status.NEAR_SINGULARITY: Status.SINGULARITY, Status.NEAR_JOINT_LIMIT: Status.JOINT_LIMIT,
           Status.NEAR_REACH: Status.REACH_LIMIT}

__all__ = ["JOINT_NAMES", "Assessment", "KinematicGuard", "KinematicLimits"]
