"""Preview and goto of named poses on the edge: the safety authority plans, issues tokens and drives. Pure.

Flow (DESIGN.md "Safety model", issue 6 §5):

1. ``plan/preview`` (name) → :meth:`GotoController.preview` plans a straight line from the *current* pose
   to the named pose at the *active* speed limits, checks the workspace box and the arm's reach, and — only
   if the plan is acceptable — issues a single-use token valid for ``token_ttl`` seconds. The reply carries
   the verdict and the path (the twin draws it as a ghost trajectory).
2. ``control/goto`` (name, token) → :meth:`GotoController.start` refuses unless the token is known, unused,
   fresh, for the same pose, issued to the same operator, and the robot is still where the preview started
   (the approved path begins there). Then the move is active.
3. While active, the operator keeps sending ``cmd/twist`` with the deadman held (hold-to-run): the agent
   gives :meth:`GotoController.twist` to the supervisor with the command (``Supervisor.on_command``'s
   ``goto_twist``), which judges it as any command — the owner's signature, sequence, age, deadman, speed and
   workspace limits and the force reaction all apply — and moves with the goto's velocity instead. Releasing the deadman, a refused command, a stop, a fault or a tracking error
   cancels the move (:meth:`GotoController.cancel`); nothing resumes by itself.

Tracking: the twist is the path's feed-forward velocity plus a proportional correction toward the path's
reference pose at the current time; at the end it converges on the goal and reports done within
``position_tolerance`` (0.5 mm by default) and ``angle_tolerance``.
"""

from __future__ import annotations

import math
import secrets
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iorthand import geometry, motion
from iorthand.config import setting
from iorthand.protocol import ControlReply

Vector = NDArray[np.float64]


@dataclass
class GotoConfig:
    """The ``goto`` section of the edge configuration."""

    enabled: bool = setting(True, help="serve plan/preview and control/goto")
    poses: dict[str, list[float]] = setting(
        default_factory=lambda: {"home": [0.30, 0.0, 0.25, math.pi, 0.0, 0.0]},
        help="named safety poses [x,y,z,rx,ry,rz] in the base frame (m, rotation vector)",
    )
    token_ttl: float = setting(10.0, lo=0.5, hi=300.0, help="s a preview token stays valid")
    retract_distance: float = setting(0.05, lo=0.0, hi=0.3, help="m straight up for 'retract' if not in poses")
    marker_standoff: float = setting(0.10, lo=0.01, hi=0.5, help="m above a marker for above_marker:<id>")
    marker_max_age: float = setting(
        0.5, lo=0.05, hi=5.0, help="s a marker pose stays usable for above_marker:<id> after its camera frame"
    )
    marker_tolerance: float = setting(
        0.005, lo=0.0005, hi=0.05, help="m a move's marker may have moved since the preview (the patient moved)",
    )
    marker_angle_tolerance: float = setting(0.1, lo=0.005, hi=0.5, help="rad, idem for its orientation")
    tcp_offset: list[float] = setting(default_factory=lambda: [0.0] * 6, length=6, help="TCP in the flange frame")
    start_tolerance: float = setting(0.005, lo=0.0, hi=0.1, help="m the robot may have moved since the preview")
    start_angle_tolerance: float = setting(0.05, lo=0.0, hi=1.0, help="rad, idem for orientation")
    position_tolerance: float = setting(0.0005, lo=1e-5, hi=0.01, help="m: goal reached")
    angle_tolerance: float = setting(0.005, lo=1e-4, hi=0.1, help="rad: goal reached")
    max_tracking_error: float = setting(0.01, lo=0.001, hi=0.1, help="m off the path → cancel")
    gain: float = setting(3.0, lo=0.1, hi=20.0, help="1/s proportional correction toward the path")
    settle_timeout: float = setting(3.0, lo=0.1, hi=30.0, help="s after the path's end to reach the tolerance")

    def check(self) -> None:
        for name, pose in self.poses.items():
            if len(pose) != 6:
                raise ValueError(f"poses.{name}: expected 6 numbers [x,y,z,rx,ry,rz], got {len(pose)}")
            if name in (motion.SWEEP, motion.RETREAT):
                raise ValueError(f"poses.{name}: the name of a primitive, which it would hide: name it otherwise")
            if ":" in name:  # a pose named above_marker:<id> would hide the live marker's
                raise ValueError(f"poses.{name}: ':' is reserved for above_marker:<id> and approach:<id>")


@dataclass
class Preview:
    """A preview's outcome: the route with its verdict, and the token when accepted."""

    plan: motion.Route
    token: str = ""
    ttl: float = 0.0

    @property
    def ok(self) -> bool:
        return self.plan.ok and bool(self.token)

    def detail(self) -> dict[str, Any]:
        """The plan for the preview's reply (``ControlReply.detail``): its reason cut to what a reply carries."""
        out = self.plan.summary(token=self.token, ttl=self.ttl)
        out["reason"] = ControlReply.fit("reason", out["reason"])
        return out


def _refused(name: str, current_pose: ArrayLike, limits: motion.Limits, reason: str) -> Preview:
    """A preview refused before any plan: an empty path from where the robot is."""
    plan = motion.plan_to(name, current_pose, limits, {}, None)
    plan.inside_workspace = plan.reachable = False
    plan.reason = reason
    return Preview(motion.Route(name, [plan]))


@dataclass(frozen=True)
class _Aim:
    """The marker a move aims at, as the preview saw it (T_base_marker)."""

    marker_id: int
    pose: Vector


def _aim(name: str, markers: Mapping[int, ArrayLike] | None) -> _Aim | None:
    """The marker ``name`` aims at (above_marker:<id>, approach:<id>) with its pose now; None for other moves."""
    for prefix in (motion.ABOVE_MARKER, motion.APPROACH):
        text = name[len(prefix):] if name.startswith(prefix) else ""
        if text.isdigit() and markers and int(text) in markers:
            return _Aim(int(text), np.asarray(markers[int(text)], dtype=float))
    return None


@dataclass
class _Issued:
    name: str
    operator: str
    plan: motion.Route
    issued_at: float
    limits: motion.Limits
    aim: _Aim | None = None


@dataclass
class _Active:
    plan: motion.Route
    operator: str
    started_at: float
    limits: motion.Limits
    aim: _Aim | None = None


@dataclass
class GotoController:
    """Preview tokens and the execution of one named-pose move at a time. Times are monotonic seconds."""

    config: GotoConfig
    workspace_min: Sequence[float]
    workspace_max: Sequence[float]
    model: str = "ur3e"  # the arm's (robot.model): reach and singularities along a path
    max_tokens: int = 16
    # Plans a route (motion.plan_route's arguments and answer): the edge plans in a process of its own
    # (iorthand_edge.planner); a TimeoutError or any failure of it refuses the preview.
    planner: Callable[..., motion.Route] = motion.plan_route
    status: str = "idle"  # idle | moving | done | cancelled
    reason: str = ""
    _tokens: OrderedDict[str, _Issued] = field(default_factory=OrderedDict)
    _active: _Active | None = None

    # ------------------------------------------------------------------ preview

    def limits(self, linear_speed: float, angular_speed: float, acceleration: float) -> motion.Limits:
        return motion.Limits(
            linear_speed=linear_speed, angular_speed=angular_speed, acceleration=acceleration,
            workspace_min=tuple(self.workspace_min), workspace_max=tuple(self.workspace_max),
            model=self.model, tcp_offset=tuple(self.config.tcp_offset) if any(self.config.tcp_offset) else None,
        )

    def preview(
        self,
        name: str,
        operator: str,
        current_pose: ArrayLike,
        now: float,
        limits: motion.Limits,
        markers: Mapping[int, ArrayLike] | None = None,
        current_q: ArrayLike | None = None,
        params: Mapping[str, Any] | None = None,
        owner: str = "",
    ) -> Preview:
        """Plan ``name`` (a named pose or a primitive with its ``params``: :func:`iorthand.motion.plan_route`)
        from ``current_pose`` at ``limits``; a token only for an acceptable plan. Beyond ``max_tokens`` the
        oldest token goes, the ``owner``'s (who holds control) last: previews from others do not void his."""
        if not self.config.enabled:
            return _refused(name, current_pose, limits, "preview/goto is disabled in this edge's configuration")
        try:
            plan = self.planner(
                name, current_pose, limits, self.config.poses, markers,
                self.config.retract_distance, self.config.marker_standoff, current_q, params,
            )
        except TimeoutError as exc:
            return _refused(name, current_pose, limits, f"{exc}: refused")
        except Exception as exc:  # the planner's child died (killed, out of memory) or planning has a bug
            # The preview is refused with why; the next one starts a new child. Raised, it ended the edge's
            # planner thread, and with it the whole edge (a worker's crash stops the agent). The agent logs why.
            return _refused(name, current_pose, limits, f"planning failed: {type(exc).__name__}: {exc}")
        if not plan.ok:
            return Preview(plan)
        self._expire(now)
        token = secrets.token_hex(12)
        self._tokens[token] = _Issued(name, operator, plan, now, limits, _aim(name, markers))
        while len(self._tokens) > self.max_tokens:
            others = [t for t, issued in self._tokens.items() if issued.operator != owner]
            del self._tokens[others[0] if others else next(iter(self._tokens))]
        return Preview(plan, token, self.config.token_ttl)

    def _expire(self, now: float) -> None:
        for token in [t for t, v in self._tokens.items() if now - v.issued_at > self.config.token_ttl]:
            del self._tokens[token]

    # ------------------------------------------------------------------ goto

    def start(self, name: str, token: str, operator: str, current_pose: ArrayLike, now: float,
              limits: motion.Limits, contact: bool = False,
              markers: Mapping[int, ArrayLike] | None = None) -> tuple[bool, str]:
        """Validate a goto. Tokens are single-use: a refused goto for a known token also consumes it. A valid
        goto while another move runs preempts it (a new goal). ``contact``: contact mode is on (a planar route,
        a sweep, runs only in it: its height is the force's). ``markers``: those in view now (fresh); a move
        aimed at a marker starts only while it is seen where the preview saw it."""
        if not self.config.enabled:
            return False, "preview/goto is disabled in this edge's configuration"
        if not token:
            return False, f"no preview token: preview {name!r} first"
        issued = self._tokens.get(token)
        if issued is None:
            return False, "unknown or already used preview token: preview again"
        age = now - issued.issued_at
        del self._tokens[token]
        if age > self.config.token_ttl:
            return False, f"preview token expired ({age:.1f} s old, valid {self.config.token_ttl:g} s): preview again"
        if issued.name != name:
            return False, f"the token was issued for {issued.name!r}, not {name!r}"
        if issued.operator != operator:
            return False, f"the token was issued to {issued.operator!r}, not {operator!r}"
        here = geometry.pose_to_matrix(current_pose)
        there = geometry.pose_to_matrix(issued.plan.start)
        moved = geometry.translation_distance(here, there)
        turned = geometry.rotation_angle(here, there)
        if moved > self.config.start_tolerance or turned > self.config.start_angle_tolerance:
            return False, (f"the robot moved {1000 * moved:.1f} mm / {math.degrees(turned):.1f}° since the preview:"
                           " preview again")
        if (limits.linear_speed < issued.limits.linear_speed - 1e-12
                or limits.angular_speed < issued.limits.angular_speed - 1e-12):
            return False, "the speed limits are lower than at the preview (profile changed): preview again"
        if issued.plan.planar and not contact:
            return False, f"{name!r} runs in contact mode (its height is the held force): turn contact mode on first"
        if issued.aim is not None:
            if not markers or issued.aim.marker_id not in markers:
                return False, f"marker {issued.aim.marker_id} is not in view now: preview again once it is"
            moved = self._marker_moved(issued.aim, markers[issued.aim.marker_id])
            if moved:
                return False, f"{moved}: preview again"
        if self._active is not None:
            self.cancel(f"preempted by a new goal: {name!r}")
        # Run the path exactly as previewed (its timing was approved), never faster.
        self._active = _Active(issued.plan, operator, now, issued.limits, issued.aim)
        self.status, self.reason = "moving", f"{name}: started ({issued.plan.duration:.1f} s)"
        return True, self.reason

    def _marker_moved(self, aim: _Aim, seen: ArrayLike) -> str:
        """Why the marker seen now is not where the preview saw it ("" when it is, within the tolerances)."""
        moved = geometry.translation_distance(aim.pose, seen)
        turned = geometry.rotation_angle(aim.pose, seen)
        if moved > self.config.marker_tolerance or turned > self.config.marker_angle_tolerance:
            return f"marker {aim.marker_id} moved {1000 * moved:.1f} mm / {math.degrees(turned):.1f}° since the preview"
        return ""

    @property
    def aims_at_marker(self) -> bool:
        """The move under way aims at a marker (its twist wants the markers in view)."""
        return self._active is not None and self._active.aim is not None

    @property
    def planar(self) -> bool:
        """The move under way tracks x and y only (a sweep: contact mode holds its height)."""
        return self._active is not None and self._active.plan.planar

    @property
    def active(self) -> bool:
        return self._active is not None

    @property
    def operator(self) -> str:
        return self._active.operator if self._active else ""

    @property
    def target(self) -> str:
        return self._active.plan.name if self._active else ""

    def cancel(self, reason: str) -> bool:
        """Abort the move (deadman released, stop, refusal, fault). Returns True if one was active."""
        if self._active is None:
            return False
        self._active = None
        self.status, self.reason = "cancelled", reason
        return True

    def twist(self, current_pose: ArrayLike, now: float, *, contact_off: str,
              markers: Mapping[int, ArrayLike] | None = None) -> Vector:
        """The tool twist for this cycle (base frame). Zero, and the move ends, when done, off the path, when a
        planar route (a sweep) finds contact mode off (``contact_off``: why; "" while it is on): nothing holds
        its height any more, or when the marker it aims at is seen (in ``markers``, those in view) away from
        where the preview saw it: the patient moved. A marker out of view goes on (the probe itself hides it
        close up)."""
        act = self._active
        if act is None:
            return np.zeros(6)
        if act.aim is not None and markers and act.aim.marker_id in markers:
            moved = self._marker_moved(act.aim, markers[act.aim.marker_id])
            if moved:
                self.cancel(f"{moved}: move cancelled, preview again")
                return np.zeros(6)
        if act.plan.planar and contact_off:
            self.cancel(f"contact mode ended ({contact_off}): {act.plan.name!r} runs only in it (its height is the "
                        "held force)")
            return np.zeros(6)
        t = now - act.started_at
        route, limits = act.plan, act.limits
        index, t_leg = route.leg_at(t)
        leg = route.legs[index]
        last = index == len(route.legs) - 1
        ref, s = motion.reference_at(leg, t_leg, limits)
        ahead, _ = motion.reference_at(leg, t_leg + 0.02, limits)
        cur = geometry.pose_to_matrix(current_pose)
        ref_m = geometry.pose_to_matrix(ref)
        goal_m = geometry.pose_to_matrix(route.goal)
        # A planar route (a sweep in contact mode) tracks x and y only: its height is the held force's.
        mask = np.array([1.0, 1.0, 0.0]) if route.planar else np.ones(3)
        # Off the path (blocked by a limit, a force reaction or a collision): stop rather than push on.
        err = float(np.linalg.norm((cur[:3, 3] - ref_m[:3, 3]) * mask))
        if err > self.config.max_tracking_error:
            self.cancel(f"{1000 * err:.1f} mm off the planned path (max {1000 * self.config.max_tracking_error:.0f} mm):"
                        " move cancelled")
            return np.zeros(6)
        if last and s >= 1.0:
            pos_err = float(np.linalg.norm((cur[:3, 3] - goal_m[:3, 3]) * mask))
            ang_err = geometry.rotation_angle(cur, goal_m)
            if pos_err <= self.config.position_tolerance and ang_err <= self.config.angle_tolerance:
                self._active = None
                self.status, self.reason = "done", f"{route.name}: done ({1000 * pos_err:.2f} mm from its end)"
                return np.zeros(6)
            if t > route.duration + self.config.settle_timeout:
                self.cancel(f"did not settle on {route.name!r} within {self.config.settle_timeout:g} s"
                            f" ({1000 * pos_err:.1f} mm off)")
                return np.zeros(6)
        label = route.labels[index] if index < len(route.labels) else ""
        done = min(1.0, t / route.duration) if route.duration > 0 else 1.0
        self.reason = f"{route.name}: {100 * done:.0f} %" + (f" ({label})" if label else "")
        # Feed-forward: the path's velocity over the next 20 ms; feedback: toward the reference now.
        ahead_m = geometry.pose_to_matrix(ahead)
        v_ff = (ahead_m[:3, 3] - ref_m[:3, 3]) / 0.02
        w_ff = geometry.matrix_to_rotvec(ahead_m[:3, :3] @ ref_m[:3, :3].T) / 0.02
        v = (v_ff + self.config.gain * (ref_m[:3, 3] - cur[:3, 3])) * mask
        w = w_ff + self.config.gain * geometry.matrix_to_rotvec(ref_m[:3, :3] @ cur[:3, :3].T)
        # Stay within the limits here already, so the supervisor's clipping never bends the path.
        v = _clip_norm(v, limits.linear_speed)
        w = _clip_norm(w, limits.angular_speed)
        return np.concatenate([v, w])


def _clip_norm(v: Vector, limit: float) -> Vector:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit > 0 else (v if limit > 0 else np.zeros_like(v))


__all__ = ["GotoConfig", "GotoController", "Preview"]
