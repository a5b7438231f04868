"""Universal Robots e-Series kinematics from the standard DH parameters. Pure numpy.

The DH table is UR's published one (standard convention, ``T_i = Rz(θ_i)·Tz(d_i)·Tx(a_i)·Rx(α_i)``); its base
frame is the controller's ``base`` frame, the one in which ``getActualTCPPose`` reports the TCP (ROS's
``base_link`` is this frame turned by 180° about z). The last frame is the tool flange; a tool centre point
offset (``tcp_offset``, a UR pose in the flange frame) is applied on top, as the controller does.

:func:`inverse` is the closed-form solution of Hawkins ("Analytic inverse kinematics for the Universal Robots
UR-5/UR-10 arms", 2013): up to 8 joint vectors per pose. The twin uses it to draw the arm from the TCP pose
(the simulated robot reports no joint angles) and the motion planner to check that every point of a path is
reachable.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand import geometry

Matrix = NDArray[np.float64]

HOME_Q = np.array([0.0, -math.pi / 2, math.pi / 2, -math.pi / 2, -math.pi / 2, 0.0])
JOINT_LIMIT = 2 * math.pi  # every e-Series joint turns ±360°


@dataclass(frozen=True)
class URModel:
    """DH parameters (m, rad) of one arm model and the radii used to draw its links."""

    name: str
    d: tuple[float, ...]
    a: tuple[float, ...]
    alpha: tuple[float, ...]
    link_radius: float  # drawing only

    @property
    def reach(self) -> float:
        """Upper bound of the distance from the shoulder axis to the flange (m)."""
        return abs(self.a[1]) + abs(self.a[2]) + math.hypot(self.d[3], self.d[4]) + self.d[5]


_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)
UR3E = URModel("ur3e", d=(0.15185, 0.0, 0.0, 0.13105, 0.08535, 0.0921), a=(0.0, -0.24355, -0.2132, 0.0, 0.0, 0.0),
               alpha=_ALPHA, link_radius=0.032)
UR5E = URModel("ur5e", d=(0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996), a=(0.0, -0.425, -0.3922, 0.0, 0.0, 0.0),
               alpha=_ALPHA, link_radius=0.045)
MODELS: dict[str, URModel] = {m.name: m for m in (UR3E, UR5E)}


def model(name: str) -> URModel:
    try:
        return MODELS[name]
    except KeyError:
        raise ValueError(f"unknown arm model {name!r} (known: {sorted(MODELS)})") from None


def dh_transform(theta: float, d: float, a: float, alpha: float) -> Matrix:
    ct, st = math.cos(theta), math.sin(theta)
    ca, sa = math.cos(alpha), math.sin(alpha)
    return np.array([
        [ct, -st * ca, st * sa, a * ct],
        [st, ct * ca, -ct * sa, a * st],
        [0.0, sa, ca, d],
        [0.0, 0.0, 0.0, 1.0],
    ])


def _chain(m: URModel, q: ArrayLike) -> list[tuple[float, ...]]:
    """The frames after each joint, as rows ``(r00, r01, r02, x, r10, r11, r12, y, r20, r21, r22, z)`` in plain
    floats: the kinematic guard needs them twice per control cycle, and on 6 joints numpy's per-call overhead was
    most of the cost (a Jacobian took ~100 µs that way, ~25 µs this way)."""
    frames: list[tuple[float, ...]] = []
    r00, r01, r02, x, r10, r11, r12, y, r20, r21, r22, z = 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0
    for theta, d, a, alpha in zip(np.asarray(q, dtype=float).tolist(), m.d, m.a, m.alpha, strict=True):
        ct, st = math.cos(theta), math.sin(theta)
        ca, sa = math.cos(alpha), math.sin(alpha)
        # The DH step's columns: (ct, st, 0), (-st·ca, ct·ca, sa), (st·sa, -ct·sa, ca); its origin (a·ct, a·st, d).
        c1x, c1y, c2x, c2y = -st * ca, ct * ca, st * sa, -ct * sa
        x, y, z = (x + r00 * a * ct + r01 * a * st + r02 * d, y + r10 * a * ct + r11 * a * st + r12 * d,
                   z + r20 * a * ct + r21 * a * st + r22 * d)
        r00, r01, r02 = r00 * ct + r01 * st, r00 * c1x + r01 * c1y + r02 * sa, r00 * c2x + r01 * c2y + r02 * ca
        r10, r11, r12 = r10 * ct + r11 * st, r10 * c1x + r11 * c1y + r12 * sa, r10 * c2x + r11 * c2y + r12 * ca
        r20, r21, r22 = r20 * ct + r21 * st, r20 * c1x + r21 * c1y + r22 * sa, r20 * c2x + r21 * c2y + r22 * ca
        frames.append((r00, r01, r02, x, r10, r11, r12, y, r20, r21, r22, z))
    return frames


def _matrix(rows: tuple[float, ...]) -> Matrix:
    return np.array([rows[0:4], rows[4:8], rows[8:12], (0.0, 0.0, 0.0, 1.0)])


def joint_frames(m: URModel, q: ArrayLike) -> list[Matrix]:
    """The base frame and the frames after each joint (7 transforms in the base frame; the last is the flange)."""
    return [np.eye(4), *(_matrix(f) for f in _chain(m, q))]


def jacobian(m: URModel, q: ArrayLike, tcp_offset: ArrayLike | None = None) -> tuple[Matrix, Matrix]:
    """The geometric Jacobian at ``q`` (6×6: rows vx, vy, vz of the TCP and wx, wy, wz, in the base frame, per
    joint speed) and the TCP pose (4×4)."""
    chain = _chain(m, q)
    tcp = _matrix(chain[-1])
    if tcp_offset is not None:
        tcp = tcp @ geometry.pose_to_matrix(tcp_offset)
    px, py, pz = float(tcp[0, 3]), float(tcp[1, 3]), float(tcp[2, 3])
    # Joint i turns about the z axis of the frame before it (the base's for the first), through that frame's origin.
    frames = [(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)] + [(f[2], f[6], f[10], f[3], f[7], f[11]) for f in chain[:5]]
    cols = []
    for ax, ay, az, ox, oy, oz in frames:
        rx, ry, rz = px - ox, py - oy, pz - oz
        cols.append((ay * rz - az * ry, az * rx - ax * rz, ax * ry - ay * rx, ax, ay, az))
    return np.array(cols).T, tcp


def elbow_span(m: URModel, q3: float) -> float:
    """Distance from the shoulder to the wrist's first joint (m), a function of the elbow angle alone: the arm's
    reach is used up when it equals ``|a2| + |a3|`` (the elbow straight, a singularity)."""
    a2, a3 = m.a[1], m.a[2]
    return math.sqrt(max(0.0, a2 * a2 + a3 * a3 + 2 * a2 * a3 * math.cos(q3)))


def forward(m: URModel, q: ArrayLike, tcp_offset: ArrayLike | None = None) -> Matrix:
    """Flange pose (or TCP pose with ``tcp_offset``, a UR pose in the flange frame) as a 4×4 in the base frame."""
    flange = joint_frames(m, q)[-1]
    return flange if tcp_offset is None else flange @ geometry.pose_to_matrix(tcp_offset)


def link_points(m: URModel, q: ArrayLike) -> Matrix:
    """Points of a drawing of the arm (N×3, base frame): base, shoulder, elbow, wrists, flange, with the
    offsets along the joint axes that make the UR's characteristic zig-zag (the DH frames alone would draw
    the upper arm and forearm through the shoulder and elbow axes)."""
    f = joint_frames(m, q)
    shoulder_off = 0.12 if m.name == "ur3e" else 0.138  # lateral offset of the upper arm from the shoulder
    elbow_off = shoulder_off - m.d[3] * 0.9
    p = [
        f[0][:3, 3],  # base
        f[1][:3, 3],  # shoulder pan/lift axis crossing
        f[1][:3, 3] + f[1][:3, 2] * shoulder_off,  # out along the shoulder-lift axis
        f[2][:3, 3] + f[1][:3, 2] * shoulder_off,  # upper arm to the elbow
        f[2][:3, 3] + f[1][:3, 2] * elbow_off,  # back along the elbow axis
        f[3][:3, 3] + f[1][:3, 2] * elbow_off,  # forearm to wrist 1
        f[4][:3, 3],  # wrist 2
        f[5][:3, 3],  # wrist 3
        f[6][:3, 3],  # flange
    ]
    return np.array(p)


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def inverse(m: URModel, pose: ArrayLike, tcp_offset: ArrayLike | None = None) -> list[Matrix]:
    """All joint solutions (each in (-π, π]) that put the flange (or the TCP) at ``pose`` (a 4×4 or a UR pose).

    Returns an empty list when the pose is out of reach. Near the wrist singularity (θ5 ≈ 0) θ6 is not
    determined: the solver then picks θ6 = 0, and the other joints still place the flange exactly.
    """
    t = np.asarray(pose, dtype=float)
    if t.shape == (6,):
        t = geometry.pose_to_matrix(t)
    if tcp_offset is not None:
        t = t @ geometry.invert(geometry.pose_to_matrix(tcp_offset))
    d1, d4, d5, d6 = m.d[0], m.d[3], m.d[4], m.d[5]
    a2, a3 = m.a[1], m.a[2]
    solutions: list[Matrix] = []
    clipped = False  # an acos/asin argument was clipped: the pose may be just out of reach, verify by FK
    p05 = t @ np.array([0.0, 0.0, -d6, 1.0])
    r = math.hypot(p05[0], p05[1])
    if r < abs(d4) - 1e-12:
        return []  # the wrist centre is inside the cylinder the shoulder offset cannot reach
    psi = math.atan2(p05[1], p05[0])
    phi = math.acos(max(-1.0, min(1.0, d4 / r)))
    for th1 in (psi + phi + math.pi / 2, psi - phi + math.pi / 2):
        s1, c1 = math.sin(th1), math.cos(th1)
        c5 = (t[0, 3] * s1 - t[1, 3] * c1 - d4) / d6
        if abs(c5) > 1.0 + 1e-9:
            continue
        clipped |= abs(c5) > 1.0
        acos5 = math.acos(max(-1.0, min(1.0, c5)))
        for th5 in (acos5, -acos5):
            s5 = math.sin(th5)
            if abs(s5) < 1e-9:
                th6 = 0.0
            else:
                # θ6 from the x and y axes of the base as seen from the flange (rows of R06).
                th6 = math.atan2((-t[0, 1] * s1 + t[1, 1] * c1) / s5, (t[0, 0] * s1 - t[1, 0] * c1) / s5)
            t01 = dh_transform(th1, d1, 0.0, m.alpha[0])
            t45 = dh_transform(th5, d5, 0.0, m.alpha[4])
            t56 = dh_transform(th6, d6, 0.0, m.alpha[5])
            t14 = geometry.invert(t01) @ t @ geometry.invert(t45 @ t56)
            p13 = t14 @ np.array([0.0, -d4, 0.0, 1.0])
            p13 = p13[:3]
            n13 = float(np.linalg.norm(p13))
            c3 = (n13 * n13 - a2 * a2 - a3 * a3) / (2 * a2 * a3)
            if abs(c3) > 1.0 + 1e-9:
                continue
            clipped |= abs(c3) > 1.0
            acos3 = math.acos(max(-1.0, min(1.0, c3)))
            for th3 in (acos3, -acos3):
                th2 = -math.atan2(p13[1], -p13[0]) + math.asin(max(-1.0, min(1.0, a3 * math.sin(th3) / n13)))
                t12 = dh_transform(th2, 0.0, a2, m.alpha[1])
                t23 = dh_transform(th3, 0.0, a3, m.alpha[2])
                t34 = geometry.invert(t12 @ t23) @ t14
                th4 = math.atan2(t34[1, 0], t34[0, 0])
                q = np.array([_wrap(v) for v in (th1, th2, th3, th4, th5, th6)])
                solutions.append(q)
    if not clipped:
        return solutions
    # Keep only exact solutions: the clipping of acos arguments above admits poses just out of reach.
    return [q for q in solutions if _pose_error(forward(m, q), t) < 1e-6]


def _pose_error(a: Matrix, b: Matrix) -> float:
    return geometry.translation_distance(a, b) + geometry.rotation_angle(a, b) * 0.1


def nearest(solutions: list[Matrix], reference: ArrayLike) -> Matrix | None:
    """The solution closest to ``reference`` (Euclidean joint-space distance, each joint taken modulo 2π)."""
    if not solutions:
        return None
    ref = np.asarray(reference, dtype=float)
    best, best_d = None, math.inf
    for q in solutions:
        # Choose each joint's 2π-equivalent nearest the reference (the joints turn ±360°).
        q_adj = ref + (q - ref + math.pi) % (2 * math.pi) - math.pi
        d = float(np.linalg.norm(q_adj - ref))
        if d < best_d and np.all(np.abs(q_adj) <= JOINT_LIMIT):
            best, best_d = q_adj, d
    return best


def solve_near(m: URModel, pose: ArrayLike, reference: ArrayLike | None = None,
               tcp_offset: ArrayLike | None = None) -> Matrix | None:
    """The IK solution nearest ``reference``, or None when out of reach.

    Without a reference: the home posture (elbow up, tool down) turned about the base axis toward the target,
    so a first solution looks like the arm an operator expects rather than an elbow-down mirror image."""
    solutions = inverse(m, pose, tcp_offset)
    if reference is None:
        t = np.asarray(pose, dtype=float)
        target = geometry.pose_to_matrix(t)[:3, 3] if t.shape == (6,) else t[:3, 3]
        home = forward(m, HOME_Q)[:3, 3]
        reference = HOME_Q.copy()
        reference[0] = _wrap(math.atan2(target[1], target[0]) - math.atan2(home[1], home[0]))
    return nearest(solutions, reference)


__all__ = [
    "HOME_Q",
    "MODELS",
    "UR3E",
    "UR5E",
    "ArmTracker",
    "URModel",
    "elbow_span",
    "forward",
    "inverse",
    "jacobian",
    "joint_frames",
    "link_points",
    "model",
    "nearest",
    "solve_near",
]


class ArmTracker:
    """Joint angles of one robot from its TCP pose, continuous from call to call: what a drawing of the arm needs
    (the twin, the web console). The simulated robot and many drivers report no usable ``q``; the TCP pose is the
    truth, so ``q`` is the reported one only where it agrees with the pose (a real UR), else the inverse kinematics
    solution nearest the previous one, so the drawing never flips."""

    def __init__(self, model_name: str, tcp_offset: ArrayLike | None = None) -> None:
        self.model = model(model_name)
        offset = np.asarray(tcp_offset, dtype=float) if tcp_offset is not None else None
        self.tcp_offset = offset if offset is not None and np.any(offset) else None
        self.q: Matrix | None = None
        self.reachable = True
        self._last_pose: Matrix | None = None
        self._q_ignored: Matrix | None = None

    def solve(self, tcp_pose: ArrayLike, reported_q: ArrayLike | None = None) -> Matrix | None:
        """Joint angles that put the TCP at ``tcp_pose``; None (and ``reachable`` False) if there is no solution."""
        pose = np.asarray(tcp_pose, dtype=float)
        if self._last_pose is not None and self.q is not None and np.array_equal(pose, self._last_pose):
            return self.q
        if reported_q is not None:
            q = np.asarray(reported_q, dtype=float)
            # A driver that reports a fixed q (the simulator) fails this check every time: remember that q.
            if self._q_ignored is None or not np.array_equal(q, self._q_ignored):
                fk = forward(self.model, q, self.tcp_offset)
                if geometry.translation_distance(fk, geometry.pose_to_matrix(pose)) < 1e-3:
                    self.q, self._last_pose, self.reachable = q, pose, True
                    return q
                self._q_ignored = q
        q = solve_near(self.model, pose, self.q, self.tcp_offset)
        self._last_pose = pose
        self.reachable = q is not None
        if q is not None:
            self.q = q
        return q
