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
from dataclasses import dataclass, field
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


# ---------------------------------------------------------------------------------------------------------
# Routes: several legs run one after the other (the motion primitives)

SWEEP = "sweep"
APPROACH = "approach:"
RETREAT = "retreat"
HOME = "home"
SWEEP_DEFAULTS = {"width": 0.06, "pitch": 0.01, "lanes": 4, "speed": 0.005}  # m, m, count, m/s


@dataclass
class Route:
    """Legs (straight-line plans) run one after the other. ``planar``: only x and y are tracked (contact mode
    holds the height along the probe: a sweep over a curved surface)."""

    name: str
    legs: list[Plan]
    planar: bool = False
    labels: list[str] = field(default_factory=list)  # what each leg is, for progress ("lane 3 of 8")

    @property
    def start(self) -> Vector:
        return self.legs[0].start

    @property
    def goal(self) -> Vector:
        return self.legs[-1].goal

    @property
    def duration(self) -> float:
        return float(sum(leg.duration for leg in self.legs))

    @property
    def length(self) -> float:
        return float(sum(leg.length for leg in self.legs))

    @property
    def inside_workspace(self) -> bool:
        return all(leg.inside_workspace for leg in self.legs)

    @property
    def reachable(self) -> bool:
        return all(leg.reachable for leg in self.legs)

    @property
    def ok(self) -> bool:
        return self.inside_workspace and self.reachable

    @property
    def reason(self) -> str:
        bad = [f"{self.labels[i] if i < len(self.labels) else f'leg {i + 1}'}: {leg.reason}"
               for i, leg in enumerate(self.legs) if not leg.ok]
        if len(self.legs) == 1:
            return self.legs[0].reason
        return "; ".join(bad) if bad else "ok"

    def leg_at(self, t: float) -> tuple[int, float]:
        """The leg running at ``t`` s from the start, and the time into it (the last leg after the end)."""
        for i, leg in enumerate(self.legs):
            if t < leg.duration or i == len(self.legs) - 1:
                return i, t
            t -= leg.duration
        return len(self.legs) - 1, t

    def _path(self, max_points: int) -> list[list[float]]:
        """At most ``max_points`` points along the legs: each leg's own while they have two or more each, else
        the corners (the legs are straight), evenly thinned: a 50-lane sweep in ~1 KB, not 5 (a reply's limit)."""
        if max_points // len(self.legs) >= 2:
            return [p for leg in self.legs for p in leg.summary(max_points // len(self.legs))["path"]]
        corners = [leg.start for leg in self.legs] + [self.legs[-1].goal]
        idx = np.unique(np.linspace(0, len(corners) - 1, max_points).round().astype(int))
        return [[round(float(v), 4) for v in corners[i][:3]] for i in idx]

    def summary(self, max_points: int = 60, token: str = "", ttl: float = 0.0) -> dict[str, Any]:
        out = self.legs[0].summary(max_points, token, ttl) if len(self.legs) == 1 else {
            "name": self.name, "ok": self.ok, "reason": self.reason, "token": token, "ttl": ttl,
            "duration": round(self.duration, 3), "length": round(self.length, 5),
            "rotation": round(sum(leg.rotation for leg in self.legs), 4),
            "inside_workspace": self.inside_workspace, "reachable": self.reachable,
            "start": [round(float(v), 5) for v in self.start], "goal": [round(float(v), 5) for v in self.goal],
            "path": self._path(max_points),
        }
        out["name"], out["planar"], out["legs"] = self.name, self.planar, len(self.legs)
        return out


def _param(params: Mapping[str, Any], name: str, default: float, lo: float, hi: float) -> float:
    value = params.get(name, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or not lo <= value <= hi:
        raise PoseError(f"{name}: expected a number within [{lo:g}, {hi:g}], got {value!r:.30}")
    return float(value)


def _end_joints(plan: Plan) -> Vector | None:
    """Where a leg leaves the arm's joints: the next leg is solved near them, so that a flip between two legs
    (one arm configuration at the end of one, another at the start of the next) is seen, not planned over."""
    return None if plan.joints is None or not len(plan.joints) else plan.joints[-1]


def plan_sweep(current: ArrayLike, limits: Limits, params: Mapping[str, Any],
               reference_q: ArrayLike | None = None) -> Route:
    """A zig-zag over the surface from ``current``: ``lanes`` lanes ``width`` m long along the base x axis,
    ``pitch`` m apart along y, at ``speed`` m/s (at most the profile's); the height and the contact are contact
    mode's, the orientation kept. Checked at the current height (workspace, reach), each leg from the joints
    the one before left (the first from ``reference_q``, the arm's now)."""
    width = _param(params, "width", SWEEP_DEFAULTS["width"], 0.005, 0.5)
    pitch = _param(params, "pitch", SWEEP_DEFAULTS["pitch"], 0.001, 0.1)
    lanes = int(_param(params, "lanes", SWEEP_DEFAULTS["lanes"], 1, 50))
    speed = min(_param(params, "speed", SWEEP_DEFAULTS["speed"], 0.0005, 0.25), limits.linear_speed)
    lim = Limits(speed, limits.angular_speed, limits.acceleration, limits.workspace_min, limits.workspace_max,
                 limits.model, limits.tcp_offset, limits.max_joint_step)
    here = np.asarray(current, dtype=float)
    legs: list[Plan] = []
    labels: list[str] = []
    direction = 1.0
    q = reference_q
    for lane in range(lanes):
        there = here.copy()
        there[0] += direction * width
        legs.append(check_plan(plan_line(SWEEP, here, there, lim), lim, q))
        labels.append(f"lane {lane + 1} of {lanes}")
        q = _end_joints(legs[-1])
        here = there
        if lane < lanes - 1:
            there = here.copy()
            there[1] += pitch
            legs.append(check_plan(plan_line(SWEEP, here, there, lim), lim, q))
            labels.append(f"step to lane {lane + 2} of {lanes}")
            q = _end_joints(legs[-1])
            here = there
        direction = -direction
    return Route(SWEEP, legs, planar=True, labels=labels)


def primitives(markers: Sequence[int], standoff: float) -> list[dict[str, Any]]:
    """The motion primitives an operator can preview (``control/poses``), each with its parameters' defaults."""
    sweep = ", ".join(f"{k} {v:g}" for k, v in SWEEP_DEFAULTS.items())
    out = [
        {"name": SWEEP, "description": f"zig-zag over the surface in contact mode ({sweep})", "params": SWEEP_DEFAULTS},
        {"name": RETREAT, "description": "straight up, away from the patient, then to the home pose"},
    ]
    out += [{"name": f"{APPROACH}{i}", "description": f"to stand off above marker {i}", "params": {"standoff": standoff}}
            for i in markers]
    return out


def plan_route(
    name: str,
    current: ArrayLike,
    limits: Limits,
    poses: Mapping[str, Sequence[float]],
    markers: Mapping[int, ArrayLike] | None = None,
    retract_distance: float = 0.05,
    marker_standoff: float = 0.10,
    reference_q: ArrayLike | None = None,
    params: Mapping[str, Any] | None = None,
) -> Route:
    """A named pose (one leg) or a primitive: ``sweep`` (params width, pitch, lanes, speed), ``approach:<id>``
    (params standoff: above marker <id>), ``retreat`` (straight up, then to the ``home`` pose when there is one)."""
    params = params or {}
    current = np.asarray(current, dtype=float)
    try:
        known = list(SWEEP_DEFAULTS) if name == SWEEP else ["standoff"] if name.startswith(APPROACH) else []
        unknown = sorted(set(params) - set(known))
        if unknown:
            raise PoseError(f"{name}: unknown parameter(s) {', '.join(map(str, unknown))}"
                            f" (known: {', '.join(known) or 'none'})")
        if name == SWEEP:
            return plan_sweep(current, limits, params, reference_q)
        if name.startswith(APPROACH):
            standoff = _param(params, "standoff", marker_standoff, 0.01, 0.5)
            marker = f"{ABOVE_MARKER}{name[len(APPROACH):]}"
            plan = plan_to(marker, current, limits, poses, markers, retract_distance, standoff, reference_q)
            plan.name = name
            return Route(name, [plan])
        if name == RETREAT:
            up = plan_to(RETRACT, current, limits, poses, markers, retract_distance, marker_standoff, reference_q)
            legs, labels = [up], ["up, away from the patient"]
            if HOME in poses:
                home = plan_line(HOME, up.goal, np.asarray(poses[HOME], dtype=float), limits)
                legs.append(check_plan(home, limits, _end_joints(up)))
                labels.append("to the safe pose")
            return Route(RETREAT, legs, labels=labels)
    except PoseError as exc:
        empty = np.array([current])
        return Route(name, [Plan(name, current, current, empty, np.zeros(1), 0.0, 0.0, 0.0, False, False, str(exc))])
    return Route(name, [plan_to(name, current, limits, poses, markers, retract_distance, marker_standoff,
                                reference_q)])


__all__ = [
    "ABOVE_MARKER",
    "APPROACH",
    "HOME",
    "RETRACT",
    "RETREAT",
    "SWEEP",
    "SWEEP_DEFAULTS",
    "Limits",
    "Plan",
    "PoseError",
    "Route",
    "above_marker",
    "check_plan",
    "plan_line",
    "plan_route",
    "plan_sweep",
    "plan_to",
    "primitives",
    "reference_at",
    "resolve_pose",
    "trapezoid_duration",
    "trapezoid_progress",
]
