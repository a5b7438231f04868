"""Named safety poses and straight-line Cartesian paths, checked before anything moves. Pure.

The edge (the safety authority) plans a preview with :func:`plan_to`: a straight line in Cartesian space from
the current TCP pose to a named pose, the orientation along the geodesic, timed by a trapezoidal profile at
the active speed limits. :func:`check_plan` then tells whether every point stays inside the workspace box and
within the arm's reach (an inverse-kinematics solution exists at every sample, and consecutive solutions are
close, so the arm does not flip through a singularity half-way). The same functions run on the twin only to
draw what the edge answered; the verdict always comes from the edge.

Named poses: the absolute poses of the edge configuration (``home``, …), ``retract`` (straight up from the
current pose when the configuration does not define it) and ``above_marker:<id>`` (a stand-off above a marker
seen by the camera, tool pointing at it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand import geometry, kinematics

Vector = NDArray[np.float64]
ABOVE_MARKER = "above_marker:"
RETRACT = "retract"


class PoseError(ValueError):
    """A named pose that cannot be resolved (unknown name, marker not seen)."""


@dataclass
class Limits:
    """What a plan must respect: speeds (the active profile), acceleration, workspace box, arm model."""

    linear_speed: float  # m/s
    angular_speed: float  # rad/s
    acceleration: float = 0.25  # m/s²
    workspace_min: Sequence[float] = (0.10, -0.30, 0.02)
    workspace_max: Sequence[float] = (0.45, 0.30, 0.45)
    model: str = "ur3e"
    tcp_offset: Sequence[float] | None = None  # UR pose of the TCP in the flange frame
    max_joint_step: float = 0.35  # rad between IK solutions of consecutive samples: more = flipping


@dataclass
class Plan:
    """A straight-line path and its verdict. ``ok`` only when inside the workspace and reachable."""

    name: str
    start: Vector
    goal: Vector
    poses: Vector  # N×6 samples along the path (UR poses)
    times: Vector  # N seconds from the start
    duration: float
    length: float  # m
    rotation: float  # rad
    inside_workspace: bool = True
    reachable: bool = True
    reason: str = ""
    joints: Vector | None = None  # N×6 IK solutions, when reachable

    @property
    def ok(self) -> bool:
        return self.inside_workspace and self.reachable

    def summary(self, max_points: int = 60, token: str = "", ttl: float = 0.0) -> dict[str, Any]:
        """The plan as plain data for a reply (positions rounded to 0.1 mm, at most ``max_points``)."""
        idx = np.unique(np.linspace(0, len(self.poses) - 1, min(max_points, len(self.poses))).round().astype(int))
        return {
            "name": self.name,
            "ok": self.ok,
            "reason": self.reason,
            "token": token,
            "ttl": ttl,
            "duration": round(self.duration, 3),
            "length": round(self.length, 5),
            "rotation": round(self.rotation, 4),
            "inside_workspace": self.inside_workspace,
            "reachable": self.reachable,
            "start": [round(float(v), 5) for v in self.start],
            "goal": [round(float(v), 5) for v in self.goal],
            "path": [[round(float(v), 4) for v in self.poses[i, :3]] for i in idx],
        }


# ---------------------------------------------------------------------------------------------------------
# Named poses


def above_marker(marker: ArrayLike, standoff: float, current: ArrayLike | None = None) -> Vector:
    """A TCP pose ``standoff`` metres above a marker (4×4 ``T_base_marker``), the tool's z axis pointing at
    the marker, its x axis kept as close as possible to the current tool x (no needless wrist spin)."""
    t = np.asarray(marker, dtype=float).reshape(4, 4)
    normal = t[:3, 2] / np.linalg.norm(t[:3, 2])
    z = -normal
    ref_x = geometry.pose_to_matrix(current)[:3, 0] if current is not None else t[:3, 0]
    x = ref_x - np.dot(ref_x, z) * z
    if np.linalg.norm(x) < 1e-6:  # current x along the normal: fall back to the marker's x
        x = t[:3, 0] - np.dot(t[:3, 0], z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = geometry.make_transform(np.column_stack([x, y, z]), t[:3, 3] + normal * standoff)
    return geometry.matrix_to_pose(pose)


def resolve_pose(
    name: str,
    current: ArrayLike,
    poses: Mapping[str, Sequence[float]],
    markers: Mapping[int, ArrayLike] | None = None,
    retract_distance: float = 0.05,
    marker_standoff: float = 0.10,
) -> Vector:
    """The goal pose of a named pose. Raises :class:`PoseError` with the reason when it cannot."""
    if name in poses:
        return np.asarray(poses[name], dtype=float)
    if name == RETRACT:
        goal = np.asarray(current, dtype=float).copy()
        goal[2] += retract_distance  # straight up in the base frame: away from the patient lying below
        return goal
    if name.startswith(ABOVE_MARKER):
        text = name[len(ABOVE_MARKER):]
        if not text.isdigit():
            raise PoseError(f"{name!r}: expected above_marker:<id> with a numeric marker id")
        marker_id = int(text)
        if not markers or marker_id not in markers:
            raise PoseError(f"marker {marker_id} is not in view: no pose above it")
        return above_marker(markers[marker_id], marker_standoff, current)
    known = sorted([*poses, RETRACT, f"{ABOVE_MARKER}<id>"])
    raise PoseError(f"unknown pose {name!r} (known: {', '.join(known)})")


# ---------------------------------------------------------------------------------------------------------
# Planning


def trapezoid_duration(distance: float, speed: float, acceleration: float) -> float:
    """Time to cover ``distance`` from rest to rest at ``speed`` with ``acceleration`` (triangle if short)."""
    if distance <= 0.0:
        return 0.0
    if speed <= 0.0:
        return math.inf
    if acceleration <= 0.0:
        return distance / speed
    if distance <= speed * speed / acceleration:  # never reaches full speed
        return 2.0 * math.sqrt(distance / acceleration)
    return distance / speed + speed / acceleration


def trapezoid_progress(t: float, duration: float, distance: float, speed: float, acceleration: float) -> float:
    """Fraction (0–1) of the path covered at time ``t`` of the profile of :func:`trapezoid_duration`."""
    if duration <= 0.0 or distance <= 0.0 or t >= duration:
        return 1.0
    if t <= 0.0:
        return 0.0
    if acceleration <= 0.0:
        return t / duration
    v_peak = min(speed, math.sqrt(distance * acceleration))
    t_acc = v_peak / acceleration
    # The profile is scaled to ``duration``, which may be longer than distance/speed would need (rotation).
    s_full = distance
    scale = trapezoid_duration(distance, v_peak, acceleration) / duration
    tt = t * scale
    t_total = duration * scale
    if tt < t_acc:
        s = 0.5 * acceleration * tt * tt
    elif tt < t_total - t_acc:
        s = 0.5 * acceleration * t_acc * t_acc + v_peak * (tt - t_acc)
    else:
        dt = t_total - tt
        s = s_full - 0.5 * acceleration * dt * dt
    return float(min(1.0, max(0.0, s / s_full)))


def plan_line(name: str, start: ArrayLike, goal: ArrayLike, limits: Limits, step: float = 0.002) -> Plan:
    """A straight-line path from ``start`` to ``goal`` sampled every ``step`` metres (and ≤ 2° of rotation),
    timed at the speed limits. The slower of the linear and angular motions sets the duration."""
    a = geometry.pose_to_matrix(start)
    b = geometry.pose_to_matrix(goal)
    length = geometry.translation_distance(a, b)
    rotation = geometry.rotation_angle(a, b)
    t_lin = trapezoid_duration(length, limits.linear_speed, limits.acceleration)
    ang_accel = limits.acceleration / max(limits.linear_speed, 1e-9) * limits.angular_speed
    t_rot = trapezoid_duration(rotation, limits.angular_speed, ang_accel)
    duration = max(t_lin, t_rot)
    n = max(2, math.ceil(max(length / step, rotation / math.radians(2.0))) + 1)
    fractions = np.linspace(0.0, 1.0, n)
    poses = np.array([geometry.matrix_to_pose(geometry.interpolate_pose(a, b, float(s))) for s in fractions])
    # Sample times: invert the progress profile numerically (monotonic, so a lookup table is exact enough).
    if math.isfinite(duration) and duration > 0:
        grid = np.linspace(0.0, duration, 512)
        prog = np.array([_progress(t, duration, length, rotation, limits) for t in grid])
        times = np.interp(fractions, prog, grid)
    else:
        times = np.zeros(n)
    return Plan(name, np.asarray(start, dtype=float), np.asarray(goal, dtype=float), poses, times,
                duration, length, rotation)


def _progress(t: float, duration: float, length: float, rotation: float, limits: Limits) -> float:
    """Path fraction at ``t``: the linear profile, or the angular one for a pure rotation."""
    if length > 1e-9:
        return trapezoid_progress(t, duration, length, limits.linear_speed, limits.acceleration)
    ang_accel = limits.acceleration / max(limits.linear_speed, 1e-9) * limits.angular_speed
    return trapezoid_progress(t, duration, rotation, limits.angular_speed, ang_accel)


def reference_at(plan: Plan, t: float, limits: Limits) -> tuple[Vector, float]:
    """The pose the path prescribes at time ``t`` and the path fraction (1 at and after the end)."""
    s = _progress(t, plan.duration, plan.length, plan.rotation, limits)
    a = geometry.pose_to_matrix(plan.start)
    b = geometry.pose_to_matrix(plan.goal)
    return geometry.matrix_to_pose(geometry.interpolate_pose(a, b, s)), s


def check_plan(plan: Plan, limits: Limits, reference_q: ArrayLike | None = None) -> Plan:
    """Fill in the verdict: every sample inside the workspace box, every sample reachable without a flip."""
    lo = np.asarray(limits.workspace_min, dtype=float)
    hi = np.asarray(limits.workspace_max, dtype=float)
    reasons: list[str] = []
    if not math.isfinite(plan.duration):
        plan.inside_workspace = plan.reachable = False
        plan.reason = "the speed limit is zero: nothing can move"
        return plan
    pos = plan.poses[:, :3]
    outside = np.any((pos < lo - 1e-9) | (pos > hi + 1e-9), axis=1)
    if np.any(outside):
        i = int(np.argmax(outside))
        plan.inside_workspace = False
        if outside[0]:
            where = "the start (current pose)"
        elif i == len(pos) - 1:
            where = "the goal"
        else:
            where = f"{1000 * plan.length * i / (len(pos) - 1):.0f} mm along the path"
        p = pos[i]
        axes = [f"{'xyz'[k]}={p[k]:.3f} m outside [{lo[k]:.3f}, {hi[k]:.3f}]"
                for k in range(3) if not lo[k] - 1e-9 <= p[k] <= hi[k] + 1e-9]
        reasons.append(f"leaves the workspace box at {where}: {'; '.join(axes)}")
    m = kinematics.model(limits.model)
    q_prev = None if reference_q is None else np.asarray(reference_q, dtype=float)
    joints: list[Vector] = []
    for i, pose in enumerate(plan.poses):
        q = kinematics.solve_near(m, pose, q_prev, limits.tcp_offset)
        if q is None:
            plan.reachable = False
            p = pose[:3]
            reasons.append(f"out of the {m.name}'s reach at ({p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}) m"
                           f" ({'the goal' if i == len(plan.poses) - 1 else f'sample {i} of {len(plan.poses)}'})")
            break
        if q_prev is not None and joints and float(np.max(np.abs(q - q_prev))) > limits.max_joint_step:
            plan.reachable = False
            reasons.append(f"the arm would flip through a singularity at sample {i} of {len(plan.poses)}"
                           f" (joint jump {math.degrees(float(np.max(np.abs(q - q_prev)))):.0f}°)")
            break
        joints.append(q)
        q_prev = q
    if plan.reachable:
        plan.joints = np.array(joints)
    plan.reason = "; ".join(reasons) if reasons else "ok"
    return plan


def plan_to(
    name: str,
    current: ArrayLike,
    limits: Limits,
    poses: Mapping[str, Sequence[float]],
    markers: Mapping[int, ArrayLike] | None = None,
    retract_distance: float = 0.05,
    marker_standoff: float = 0.10,
    reference_q: ArrayLike | None = None,
) -> Plan:
    """Resolve a named pose, plan the line to it and check it. An unresolvable name gives a refused plan."""
    current = np.asarray(current, dtype=float)
    try:
        goal = resolve_pose(name, current, poses, markers, retract_distance, marker_standoff)
    except PoseError as exc:
        empty = np.array([current])
        return Plan(name, current, current, empty, np.zeros(1), 0.0, 0.0, 0.0, False, False, str(exc))
    return check_plan(plan_line(name, current, goal, limits), limits, reference_q)


__all__ = [
    "ABOVE_MARKER",
    "RETRACT",
    "Limits",
    "Plan",
    "PoseError",
    "above_marker",
    "check_plan",
    "plan_line",
    "plan_to",
    "reference_at",
    "resolve_pose",
    "trapezoid_duration",
    "trapezoid_progress",
]
