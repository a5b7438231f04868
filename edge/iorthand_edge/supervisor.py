"""The safety supervisor: every rule that decides whether and how the robot may move. No I/O.

The agent feeds it commands, ownership events, the robot's pose and the force level, with explicit times; it
answers with the twist to send and a status code (see :class:`iorthand.protocol.Status`) and a reason for
every refusal and every halt. Being pure, it is tested in milliseconds.

Rules (DESIGN.md, "Safety model"):
- Disarmed at start. Remote clients can only *request* arming; ``arm()`` is the local confirmation.
- One owner at a time, by lease. Others are refused with the owner's name.
- A command moves the robot only with its deadman flag set, while fresh: nothing accepted for
  ``command_timeout`` → the commanded twist is zero at once and the robot decelerates. Commands older than
  ``max_command_age``, or not newer than the last one, are dropped.
- Limits on every command: speed by profile, acceleration (passed to the robot), a workspace box.
- Force (only with a force sensor, ``force_required``): at CAUTION the speed toward contact is capped so that
  the tool stops within ``overshoot_margin`` of where DANGER is detected; at DANGER velocity pressing harder is
  removed and, if configured, the tool backs off ``retract_distance`` along the contact normal (whether or not
  the deadman is held); a stale sensor (or none yet) stops the robot once and then refuses motion toward
  contact. Motion away from contact is always allowed. Each intervention is recorded in ``interventions``
  (drained and logged by the agent) and shows in the status and reason.
- After a stop command the robot stays stopped until the deadman is released and pressed again; after a fault
  or the owner's loss, until an operator acquires control again *and then* releases and presses the deadman (a
  lease renewal alone never moves the robot). Nothing resumes by itself.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from iorthand.config import setting
from iorthand.geometry import rotate
from iorthand.protocol import ForceLevel, Status, TwistCommand
from iorthand_edge.robots.base import Vector


@dataclass
class SpeedProfile:
    linear: float = setting(0.008, lo=0.0, hi=0.25, help="m/s")
    angular: float = setting(0.1, lo=0.0, hi=1.0, help="rad/s")


@dataclass
class WorkspaceBox:
    """Allowed tool positions in the base frame (m)."""

    min: list[float] = setting(default_factory=lambda: [0.10, -0.30, 0.02], length=3)
    max: list[float] = setting(default_factory=lambda: [0.45, 0.30, 0.45], length=3)

    def check(self) -> None:
        if any(lo >= hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"workspace min {self.min} must be below max {self.max} on every axis")


@dataclass
class ForceReaction:
    enabled: bool = setting(True, help="react to force levels (needs a force sensor)")
    retract_distance: float = setting(0.0, lo=0.0, hi=0.02, help="m to back off along the contact normal at DANGER")
    retract_speed: float = setting(0.005, lo=0.0, hi=0.05, help="m/s of that retreat")
    contact_axis: list[float] = setting(
        default_factory=lambda: [0.0, 0.0, 1.0], length=3,
        help="direction of pressing in the tool frame (the probe's axis)",
    )
    overshoot_margin: float = setting(
        0.002, lo=0.0002, hi=0.02, help="m the tool may travel into contact after DANGER is detected",
    )
    reaction_time: float = setting(
        0.04, lo=0.0, hi=0.5, help="s from crossing a threshold to the robot starting to brake (sensor + loop)",
    )

    def check(self) -> None:
        if not any(self.contact_axis):
            raise ValueError("contact_axis must not be the zero vector")

    def approach_speed_cap(self, deceleration: float) -> float:
        """The fastest approach (m/s) that still stops within ``overshoot_margin``: v·T + v²/(2a) ≤ margin."""
        a, t, m = deceleration, self.reaction_time, self.overshoot_margin
        return a * (math.sqrt(t * t + 2.0 * m / a) - t)


@dataclass
class SafetyConfig:
    auto_arm: bool = setting(False, help="arm at start without local confirmation (simulated robots only)")
    command_timeout: float = setting(0.15, lo=0.01, hi=2.0, help="s without a fresh command → stop")
    max_command_age: float = setting(0.5, lo=0.01, hi=10.0, help="s; older commands are dropped")
    lease: float = setting(3.0, lo=0.5, hi=60.0, help="s an ownership lasts without renewal")
    profile: str = "remote"
    profiles: dict[str, SpeedProfile] = setting(
        default_factory=lambda: {
            "local": SpeedProfile(linear=0.030, angular=0.2),
            "remote": SpeedProfile(linear=0.008, angular=0.1),
        }
    )
    max_linear_acceleration: float = setting(0.25, lo=0.01, hi=2.0, help="m/s²")
    stop_deceleration: float = setting(0.5, lo=0.01, hi=5.0, help="m/s² when stopping")
    workspace: WorkspaceBox = field(default_factory=WorkspaceBox)
    allowed_operators: list[str] = setting(default_factory=list, help="empty: any operator may acquire")
    force: ForceReaction = field(default_factory=ForceReaction)

    def check(self) -> None:
        if self.profile not in self.profiles:
            raise ValueError(f"profile {self.profile!r} is not one of the profiles {sorted(self.profiles)}")


@dataclass
class Decision:
    """What the supervisor decided for one command or one control cycle."""

    twist: list[float]  # what to send to the robot, [vx, vy, vz, wx, wy, wz] (m/s, rad/s)
    accepted: bool
    status: str
    reason: str = ""
    limits_hit: list[str] = field(default_factory=list)


@dataclass
class Counters:
    received: int = 0
    applied: int = 0
    rejected: int = 0
    stops: int = 0


class Supervisor:
    def __init__(self, config: SafetyConfig, period: float = 1.0 / 125.0, force_required: bool = False) -> None:
        self.config = config
        self.period = period
        self.armed = config.auto_arm
        self.arm_requested = False
        self.owner = ""
        self.profile = config.profile
        self.counters = Counters()
        self.force_required = force_required
        self.force_level = ForceLevel.SAFE
        self.force_stale = force_required
        self.fault = ""
        self._lease_until = 0.0
        self._last_seq = 0
        self._last_accepted = -math.inf  # monotonic time of the last accepted command
        self._deadman = False
        self._target = [0.0] * 6  # the last accepted command, already limited
        self._latched = ""  # status that keeps the robot stopped until cleared (see module doc)
        self._latch_reason = ""
        self._now = 0.0  # the latest monotonic time given to on_command/step
        self._retreat_until = -math.inf  # monotonic time until which the tool backs off from contact
        self._force_active = ""  # the force intervention in effect (edge-triggers ``interventions``)
        self.interventions: list[tuple[str, str]] = []  # (status, reason), drained by the agent to log
        self.status = Status.DISARMED if not self.armed else Status.IDLE
        self.reason = "" if self.armed else "not armed: confirm arming on the robot side"
        self.limits_hit: list[str] = []
        self.moving = False

    # ---------------------------------------------------------------- arming and ownership

    @property
    def deadman(self) -> bool:
        """The owner holds the deadman (its last fresh command had the flag set)."""
        return self._deadman

    def timeout_at(self) -> float:
        """Monotonic time at which the held deadman times out (inf when it is not held): the control loop wakes
        then, not only at its next tick, so a dead link stops the robot at the timeout itself."""
        return self._last_accepted + self.config.command_timeout if self._deadman else math.inf

    def command_age(self, now: float) -> float:
        """Seconds since the last accepted command (monotonic ``now``); -1 before the first."""
        return -1.0 if math.isinf(self._last_accepted) else max(0.0, now - self._last_accepted)

    @property
    def limits(self) -> SpeedProfile:
        return self.config.profiles[self.profile]

    def request_arm(self, operator: str) -> tuple[bool, str]:
        if self.armed:
            return True, "already armed"
        self.arm_requested = True
        return False, f"arming requested by {operator}: waiting for confirmation on the robot side"

    def arm(self) -> None:
        """Local confirmation (a button or local command on the robot side)."""
        self.armed = True
        self.arm_requested = False
        self._set(Status.IDLE, "armed")

    def disarm(self, reason: str) -> None:
        self.armed = False
        self._halt(Status.DISARMED, reason)

    def acquire(self, operator: str, now: float, profile: str = "") -> tuple[bool, str]:
        allowed = self.config.allowed_operators
        if allowed and operator not in allowed:
            return False, f"operator {operator!r} is not on this robot's allow-list"
        if self.owner and self.owner != operator and now < self._lease_until:
            return False, f"robot is controlled by {self.owner!r}"
        if profile and profile not in self.config.profiles:
            return False, f"unknown speed profile {profile!r} (this robot has {sorted(self.config.profiles)})"
        if self.owner != operator:
            self._last_seq = 0  # a new owner starts its own sequence
            self._deadman = False
        self.owner = operator
        self._lease_until = now + self.config.lease
        if profile:
            self.profile = profile
        if self._latched in (Status.FAULT, Status.OWNER_LOST) and not self.fault:
            # Acquiring again acknowledges the fault, but never moves the robot by itself: the client renews
            # its lease with acquire while the operator may still hold the deadman. Motion needs a fresh press.
            self._latched = Status.STOPPED
            self._latch_reason = f"{self._latch_reason} — acknowledged: release the deadman and press it again"
            self._set(Status.STOPPED, self._latch_reason)
        return True, f"control granted to {operator!r} for {self.config.lease:g} s, profile {self.profile}"

    def release(self, operator: str, reason: str = "released by its owner") -> tuple[bool, str]:
        if operator != self.owner:
            return False, f"{operator!r} does not hold control"
        self.owner = ""
        self._halt(Status.IDLE, reason)
        return True, reason

    def owner_lost(self, operator: str, reason: str) -> bool:
        """The owner's liveliness token vanished (or its lease ran out): stop and release."""
        if not self.owner or operator != self.owner:
            return False
        self.owner = ""
        self._halt(Status.OWNER_LOST, reason, latch=True)
        return True

    # ---------------------------------------------------------------- faults, stops, force

    def stop(self, reason: str) -> None:
        """A stop command: controlled stop, latched until the deadman is released and pressed again."""
        self._halt(Status.STOPPED, reason, latch=True)

    def set_fault(self, reason: str) -> None:
        if reason and reason != self.fault:
            self.fault = reason
            self._halt(Status.FAULT, reason, latch=True)
        elif not reason:
            self.fault = ""

    def update_force(self, level: int, stale: bool, now: float | None = None) -> None:
        """A change of the force level or staleness. ``now`` (monotonic) times the retreat; by default the
        latest time the supervisor was given."""
        level = ForceLevel(level)
        now = self._now if now is None else now
        was_danger = self.force_level == ForceLevel.DANGER and not self.force_stale
        became_stale = stale and not self.force_stale
        self.force_level, self.force_stale = level, stale
        reaction = self.config.force
        if not (reaction.enabled and self.force_required):
            return
        if became_stale:
            # A silent sensor: the robot does not know how hard it presses. Stop once (not latched); then only
            # motion away from contact is allowed until samples come back.
            self._retreat_until = -math.inf
            reason = "force sensor stale: robot stopped, motion toward contact refused"
            self._halt(Status.FORCE_STALE, reason)
            self._intervene(Status.FORCE_STALE, reason)
        elif level == ForceLevel.DANGER and not stale and not was_danger:
            reason = "danger-level force: motion pressing harder removed"
            if reaction.retract_distance > 0 and reaction.retract_speed > 0:
                self._retreat_until = now + reaction.retract_distance / reaction.retract_speed
                reason += f", retracting {1000 * reaction.retract_distance:.1f} mm"
            self._set(Status.FORCE_DANGER, reason)
            self._intervene(Status.FORCE_DANGER, reason)

    # ---------------------------------------------------------------- commands and control cycles

    def on_command(self, cmd: TwistCommand, recv_wall: float, now: float, tcp_pose: Vector) -> Decision:
        """A decoded twist command. ``recv_wall`` is the receive time (s since the epoch, to compare with
        ``cmd.t``); ``now`` is the monotonic time; ``tcp_pose`` the latest ``[x,y,z,rx,ry,rz]``."""
        self.counters.received += 1
        self._now = now
        refusal = self._refuse(cmd, recv_wall)
        if refusal is not None:
            self.counters.rejected += 1
            status, reason = refusal
            return Decision(self._current(), False, status, reason)
        self._last_seq = cmd.seq
        self._last_accepted = now
        self._lease_until = now + self.config.lease
        if not cmd.deadman:
            self._deadman = False
            if self._latched == Status.STOPPED:
                self._latched = ""  # deadman released after a stop: the next press may move again
            self._target = [0.0] * 6
            self.counters.applied += 1
            self._set(Status.NO_DEADMAN, "deadman released")
            return Decision([0.0] * 6, True, Status.NO_DEADMAN, "deadman released")
        self._deadman = True
        if self._latched:
            self.counters.rejected += 1
            return Decision([0.0] * 6, False, self._latched, self._latch_reason)
        self._target = [float(v) for v in (*cmd.linear, *cmd.angular)]
        decision = self._limit(self._target, tcp_pose, now)
        self.counters.applied += 1
        decision.accepted = True
        return decision

    def step(self, now: float, tcp_pose: Vector) -> Decision:
        """One control cycle: apply the timeout and the limits to the current target."""
        self._now = now
        if self.owner and now >= self._lease_until and now - self._last_accepted > self.config.lease:
            self.owner_lost(self.owner, f"lease of {self.owner!r} expired")
        if self._latched or not self.armed:
            return Decision([0.0] * 6, False, self.status, self.reason)
        if self._deadman and now - self._last_accepted > self.config.command_timeout:
            self._deadman = False
            self._target = [0.0] * 6
            self._halt(
                Status.COMMAND_TIMEOUT,
                f"no command for {1000 * (now - self._last_accepted):.0f} ms "
                f"(timeout {1000 * self.config.command_timeout:.0f} ms)",
            )
        if not self._deadman:
            return self._retreat_only(tcp_pose, now)
        return self._limit(self._target, tcp_pose, now)

    # ---------------------------------------------------------------- internals

    def _refuse(self, cmd: TwistCommand, recv_wall: float) -> tuple[str, str] | None:
        if self.fault:
            return Status.FAULT, self.fault
        if not self.armed:
            return Status.DISARMED, "not armed: confirm arming on the robot side"
        if not self.owner:
            return Status.NOT_OWNER, "no operator holds control: acquire it first"
        if cmd.operator != self.owner:
            return Status.NOT_OWNER, f"robot is controlled by {self.owner!r}, not {cmd.operator!r}"
        if cmd.seq <= self._last_seq:
            return Status.OUT_OF_ORDER, f"sequence {cmd.seq} is not after {self._last_seq}"
        age = recv_wall - cmd.t / 1e9
        if age > self.config.max_command_age:
            return Status.STALE_COMMAND, f"command is {1000 * age:.0f} ms old (max {1000 * self.config.max_command_age:.0f})"
        if age < -self.config.max_command_age:
            return Status.STALE_COMMAND, f"command time is {-1000 * age:.0f} ms in the future: check clock sync"
        return None

    def _current(self) -> list[float]:
        return list(self._target) if self._deadman and not self._latched else [0.0] * 6

    def _set(self, status: str, reason: str) -> None:
        self.status, self.reason = status, reason

    def _halt(self, status: str, reason: str, latch: bool = False) -> None:
        was_moving = self.moving or any(self._target)
        self._deadman = False
        self._target = [0.0] * 6
        self.moving = False
        if was_moving or latch:
            self.counters.stops += 1
        if latch:
            self._latched, self._latch_reason = status, reason
        self._set(status, reason)

    def _contact_direction(self, pose: list[float]) -> tuple[float, float, float]:
        x, y, z = rotate(pose[3:], self.config.force.contact_axis)
        norm = max(math.sqrt(x * x + y * y + z * z), 1e-9)
        return x / norm, y / norm, z / norm

    def _retreat_only(self, tcp_pose: Vector, now: float) -> Decision:
        """No operator motion: only the retreat from danger, if one is under way."""
        if now < self._retreat_until:
            twist = [0.0] * 6
            pose = _floats(tcp_pose)
            self._clip_force(twist, pose, now)
            self._clip_workspace(twist, pose)
            self.moving = any(twist)
            self._set(Status.FORCE_DANGER, "retracting from danger-level force")
            return Decision(twist, True, Status.FORCE_DANGER, "retracting from danger-level force", ["force"])
        self.moving = False
        return Decision([0.0] * 6, False, self.status, self.reason)

    def _intervene(self, status: str, reason: str) -> None:
        if status != self._force_active:
            self._force_active = status
            self.interventions.append((status, reason))
            del self.interventions[:-64]  # bounded if nobody drains it

    def _limit(self, target: list[float], tcp_pose: Vector, now: float) -> Decision:
        """Speed, force and workspace limits on ``target`` (6 floats). Plain float arithmetic, not numpy: this
        runs for every command and every control cycle, where numpy's per-call overhead on 3-vectors is most
        of the cost."""
        limits = self.limits
        twist = list(target)
        hit: list[str] = []
        status, reason = Status.OK, ""
        lin_speed = math.hypot(*twist[:3])
        if lin_speed > limits.linear:
            scale = limits.linear / lin_speed
            twist[:3] = [v * scale for v in twist[:3]]
            hit.append("linear_speed")
            status, reason = Status.SPEED_LIMITED, f"linear speed {1000 * lin_speed:.1f} mm/s clipped to {1000 * limits.linear:.1f} mm/s ({self.profile})"
        ang_speed = math.hypot(*twist[3:])
        if ang_speed > limits.angular:
            scale = limits.angular / ang_speed
            twist[3:] = [v * scale for v in twist[3:]]
            hit.append("angular_speed")
            status, reason = Status.SPEED_LIMITED, f"angular speed {ang_speed:.2f} rad/s clipped to {limits.angular:.2f} rad/s ({self.profile})"
        pose = _floats(tcp_pose)
        # Force before workspace: a retreat adds velocity, and the box must still bound it.
        force_status = self._clip_force(twist, pose, now)
        if force_status is not None:
            hit.append("force")
            status, reason = force_status
            self._intervene(status, reason)
        else:
            self._force_active = ""
        if self._clip_workspace(twist, pose):
            hit.append("workspace")
            status, reason = Status.WORKSPACE, "velocity leaving the workspace box removed"
        self.limits_hit = hit
        self.moving = any(abs(v) > 1e-9 for v in twist)
        self._set(status, reason)
        return Decision(twist, True, status, reason, hit)

    def _clip_workspace(self, twist: list[float], pose: list[float]) -> bool:
        """Remove velocity components that would carry the tool out of the box: the allowed speed toward a
        face is what still stops in time at the stop deceleration, ``v ≤ √(2·a·d)`` and ``v·T ≤ d``."""
        box = self.config.workspace
        # A reduced target is reached at the command acceleration, a stop at the stop deceleration: assume the
        # slower of the two, halved as a margin for the one-cycle lag of a sampled loop.
        decel = 0.5 * min(self.config.max_linear_acceleration, self.config.stop_deceleration)
        horizon = 2.0 * self.period  # two control periods of reaction
        clipped = False
        for i in range(3):
            p, v = pose[i], twist[i]
            if v > 0:
                d = box.max[i] - p
            elif v < 0:
                d = p - box.min[i]
            else:
                continue
            allowed = 0.0 if d <= 0 else min(math.sqrt(2 * decel * d), d / horizon)
            if abs(v) > allowed:
                twist[i] = math.copysign(allowed, v)
                clipped = True
        return clipped

    def _clip_force(self, twist: list[float], pose: list[float], now: float) -> tuple[str, str] | None:
        """Shape ``twist`` (in place) by the force state; return (status, reason) if it intervened."""
        reaction = self.config.force
        if not reaction.enabled or not self.force_required:
            return None
        n = self._contact_direction(pose)  # pressing direction in the base frame
        toward = twist[0] * n[0] + twist[1] * n[1] + twist[2] * n[2]
        if self.force_stale:
            if toward <= 0:
                return None
            _add_along(twist, -toward, n)
            return Status.FORCE_STALE, "force sensor stale: motion toward contact refused"
        result: tuple[str, str] | None = None
        if self.force_level == ForceLevel.DANGER and toward > 0:
            _add_along(twist, -toward, n)
            toward = 0.0
            result = Status.FORCE_DANGER, "danger-level force: motion pressing harder removed"
        elif self.force_level == ForceLevel.CAUTION:
            decel = min(self.config.max_linear_acceleration, self.config.stop_deceleration)
            cap = reaction.approach_speed_cap(decel)
            if toward > cap:
                _add_along(twist, cap - toward, n)
                toward = cap
                result = Status.FORCE_CAUTION, f"caution-level force: approach slowed to {1000 * cap:.1f} mm/s"
        # The retreat runs its full distance even once the level has dropped (it drops within a fraction of
        # a millimetre, by the hysteresis): a retreat cut short would leave the probe at the red threshold.
        if now < self._retreat_until and toward > -reaction.retract_speed:
            _add_along(twist, -reaction.retract_speed - toward, n)
            result = Status.FORCE_DANGER, "danger-level force: retracting along the contact normal"
        return result


def _floats(v: Vector | list[float]) -> list[float]:
    return v.tolist() if isinstance(v, np.ndarray) else [float(x) for x in v]


def _add_along(twist: list[float], amount: float, n: tuple[float, float, float]) -> None:
    """Add ``amount`` times the unit vector ``n`` to the linear part of ``twist`` (in place)."""
    twist[0] += amount * n[0]
    twist[1] += amount * n[1]
    twist[2] += amount * n[2]
