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
  the deadman is held); in contact mode at DANGER the operator's motion stops and only the admittance's back-off
  moves the probe. A sensor that goes stale stops the robot as a stop command does (latched, contact mode
  ended); with no fresh sample (or none yet) motion toward contact is refused. Motion away from contact is
  allowed whenever the robot may move. Each intervention is recorded in ``interventions`` (drained and logged by
  the agent) and shows in the status and reason.
- After a stop command or a silent force sensor the robot stays stopped until the deadman is released and
  pressed again; after a fault
  or the owner's loss, until an operator acquires control again *and then* releases and presses the deadman (a
  lease renewal alone never moves the robot). Nothing resumes by itself.
- Ownership belongs to the session that acquired it, never to a name: each grant draws a fresh key that only
  the acquirer receives, and only commands signed with it act (:mod:`iorthand.security.auth`). A command in the
  owner's name without the owner's signature is a forgery: refused, counted, never answered. Every grant starts
  a new sequence; a command whose sequence jumps further than ``max_sequence_jump`` is refused.
- After a gap in the commands longer than ``resume_gap`` while the deadman was held, motion resumes only after
  the deadman is released and pressed again (shorter gaps resume). A new grant of control starts the same way:
  its first motion needs a release and a press under it (the operator's client sends the release itself when the
  press came after the grant). A command names the robot state on the operator's screen (its stamp, on this
  edge's clock: the state's age is measured here, both trips over the link included); motion from a picture
  older than ``max_view_age`` is refused and the robot stops; a spell of such refusals longer than ``resume_gap``
  needs a fresh press, as a gap does.
- Clocks. A command's age is this edge's wall clock at receipt minus the operator's at sending: wall clocks
  that disagree (NTP stepped one, an edge booted without a real-time clock) make every command too old or from
  the future. The refusal says by how much the clocks differ, and whether this edge's own clock stepped (its
  wall clock against its monotonic one); the safety status says it once the robot has stopped. A new grant of
  control is refused with both clocks' readings when they differ by more than ``max_command_age``: the operator
  reads what to fix at connect, not in a flood of refusals afterwards.

Every event (a command, a control cycle, a stop, arming, ownership, a fault, a force level) goes through one
method with its time; each answer is a :class:`Decision` whose ``action`` says what the driver must do (move,
decelerate to a stop, or nothing). The agent around it only carries events in and actions out.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from iorthand import keys
from iorthand.config import setting
from iorthand.geometry import rotate
from iorthand.protocol import (
    RESUME_ON_PRESS,
    TWIST_FRAMES,
    ControlRequest,
    ForceLevel,
    Message,
    Status,
    TwistCommand,
)
from iorthand.security import auth
from iorthand_edge.kinematic_guard import KinematicGuard, KinematicLimits
from iorthand_edge.robots.base import Vector


@dataclass
class SpeedProfile:
    linear: float = setting(0.008, lo=0.0, hi=0.25, help="m/s")
    angular: float = setting(0.1, lo=0.0, hi=1.0, help="rad/s")


MAX_REACH = 2.0  # m from the base: no arm iorthand drives reaches further (a UR20: 1.75 m)


@dataclass
class WorkspaceBox:
    """Allowed tool positions in the base frame (m)."""

    min: list[float] = setting(default_factory=lambda: [0.10, -0.30, 0.02], length=3)
    max: list[float] = setting(default_factory=lambda: [0.45, 0.30, 0.45], length=3)

    def check(self) -> None:
        if any(lo >= hi for lo, hi in zip(self.min, self.max, strict=True)):
            raise ValueError(f"workspace min {self.min} must be below max {self.max} on every axis")
        far = [v for v in (*self.min, *self.max) if abs(v) > MAX_REACH]
        if far:
            # A box written in millimetres loads as metres: none of its faces would ever be met.
            raise ValueError(f"workspace {self.min} .. {self.max}: {far[0]:g} m is beyond any arm's reach "
                             f"({MAX_REACH:g} m); the box is in metres (millimetres?)")

    def contains(self, position: list[float]) -> bool:
        return all(lo <= v <= hi for lo, v, hi in zip(self.min, position, self.max, strict=False))


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
        # Normalised where it is used: a near-zero axis would amplify noise into a direction.
        if math.hypot(*self.contact_axis) < 0.1:
            raise ValueError(f"contact_axis {self.contact_axis} must be a direction (length 1: the probe's axis)")
        if self.retract_distance > 0 and self.retract_speed <= 0:
            raise ValueError(f"retract_distance {self.retract_distance:g} m needs a retract_speed above 0: at DANGER "
                             "the retreat would never run")

    def approach_speed_cap(self, deceleration: float) -> float:
        """The fastest approach (m/s) that still stops within ``overshoot_margin``: v·T + v²/(2a) ≤ margin."""
        a, t, m = deceleration, self.reaction_time, self.overshoot_margin
        return a * (math.sqrt(t * t + 2.0 * m / a) - t)


@dataclass
class ContactConfig:
    """Contact mode: the operator steers along the surface and orients the probe; the edge holds the force along
    the probe's axis at a target by an admittance at the control rate (the force levels stay the outer envelope)."""

    target: float = setting(4.0, lo=0.5, hi=50.0, help="N along the probe axis, held (below the caution level)")
    gain: float = setting(0.0025, lo=1e-5, hi=0.05, help="m/s of axial speed per N of force error (admittance)")
    integral_gain: float = setting(
        0.003, lo=0.0, hi=0.1, help="m/s per N·s of accumulated error: follows a rising or falling surface without"
        " a standing error (0: proportional only)",
    )
    max_speed: float = setting(0.005, lo=0.0005, hi=0.05, help="m/s along the probe axis at most")
    deadband: float = setting(0.1, lo=0.0, hi=5.0, help="N: a smaller error moves nothing along the axis")
    max_force_age: float = setting(0.05, lo=0.005, hi=1.0, help="s: an older force reading moves nothing along the axis")


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
    contact: ContactConfig = field(default_factory=ContactConfig)
    kinematics: KinematicLimits = field(default_factory=KinematicLimits)
    resume_gap: float = setting(
        0.5, lo=0.05, hi=10.0, help="s; after a longer gap in the commands motion needs a fresh deadman press",
    )
    max_view_age: float = setting(
        0.5, lo=0.05, hi=10.0, help="s; motion from an operator whose robot state is older is refused",
    )
    max_sequence_jump: int = setting(1000, lo=1, hi=1_000_000, help="a larger jump in a command's sequence is refused")

    def check(self) -> None:
        if self.profile not in self.profiles:
            raise ValueError(f"profile {self.profile!r} is not one of the profiles {sorted(self.profiles)}")


class Action(StrEnum):
    """What the driver must do with a decision."""

    MOVE = "move"  # send the twist
    STOP = "stop"  # decelerate to zero at the stop deceleration (the robot was commanded to move)
    HOLD = "hold"  # nothing to send: the robot was already commanded to stand still


@dataclass
class Decision:
    """What the supervisor decided for one command or one control cycle."""

    twist: list[float]  # what to send to the robot, [vx, vy, vz, wx, wy, wz] (m/s, rad/s)
    accepted: bool
    status: Status
    reason: str = ""
    limits_hit: list[str] = field(default_factory=list)
    action: Action = Action.HOLD
    answer: bool = True  # False: a forgery, counted but not answered on state/applied (no echo to amplify)
    cancel_goto: str = ""  # why a previewed move under way ends with this command ("" = it goes on, if any)


NOT_ARMED = "not armed: confirm arming on the robot side"
# s: a change of this edge's wall clock against its monotonic clock beyond this (plus what NTP may slew in the
# time between, 500 ppm) is a step of the wall clock, not the jitter of reading two clocks.
WALL_STEP_TOLERANCE = 0.05
MAX_SLEW = 500e-6
GRANT_NEEDS_PRESS = "control granted: release the deadman and press it to move"
DANGER_HELD = "danger-level force: motion pressing harder removed"
RETRACTING = "retracting from danger-level force"


@dataclass
class Grant:
    """The answer to an acquire: ``key`` is set when a new grant starts (the acquirer alone receives it)."""

    ok: bool
    reason: str
    key: bytes = b""


@dataclass
class Counters:
    received: int = 0
    applied: int = 0
    rejected: int = 0
    stops: int = 0
    forged: int = 0


def _not_signed(operator: str) -> str:
    """Why a message in the name of the operator holding control is refused without its grant's signature."""
    return f"not signed by the session that holds control for {operator!r}"


class Supervisor:
    def __init__(self, config: SafetyConfig, period: float = 1.0 / 125.0, force_required: bool = False,
                 robot: str = "robot", keygen: Callable[[], bytes] = auth.new_key,
                 wall_clock: Callable[[], float] = time.time) -> None:
        self.config = config
        self.period = period
        self.robot = keys.check_robot_id(robot)
        self._keygen = keygen
        self._wall_clock = wall_clock  # this edge's wall clock (s since the epoch), read when control is asked for
        self.armed = config.auto_arm
        self.arm_requested = False
        self.owner = ""
        self.profile = config.profile
        self.counters = Counters()
        self.force_required = force_required
        self.force_level = ForceLevel.SAFE
        self.force_stale = force_required
        self.fault = ""
        self._key = b""  # the owner's secret (see iorthand.security.auth); empty while nobody holds control
        self._lease_until = 0.0
        self._last_seq: dict[str, int] = {}  # per key suffix, within the current grant
        self._last_accepted = -math.inf  # monotonic time of the last accepted command
        # Monotonic time of the last command that could move the robot as far as its time and view go (accepted,
        # its picture fresh) or released the deadman: a longer spell without one, the deadman held, needs a press.
        self._last_live = -math.inf
        # This edge's wall clock minus its monotonic clock at the last command (None before the first), and the
        # steps of the wall clock seen since the clocks last agreed (s): which clock moved, for the refusals.
        self._wall_offset: float | None = None
        self._wall_offset_at = 0.0
        self._wall_step = 0.0
        self._time_refusal = ""  # why the owner's commands have been refused for their time since the last accepted
        self._time_refused_at = -math.inf  # monotonic time of the latest such refusal
        self._shown_age: float | None = None  # the command age those refusals give (s), kept through jitter
        self._last_deadman = False  # the deadman flag of the last accepted command
        self._deadman = False
        self._target = [0.0] * 6  # the last accepted command, already limited
        self._target_is_move = False  # _target is a previewed move's velocity, not the operator's own twist
        self._sent_motion = False  # the driver was last told to move (a zero then means: stop)
        self._latched: Status | None = None  # keeps the robot stopped until cleared (see module doc)
        self._latch_reason = ""
        self._now = 0.0  # the latest monotonic time given to on_command/step
        self._retreat_until = -math.inf  # monotonic time until which the tool backs off from contact
        self._force_active: Status | None = None  # the force intervention in effect (edge-triggers ``interventions``)
        # Contact mode (set_contact): the force held along the probe's axis (None: off), the newest reading of that
        # force (N, pressing positive) and the monotonic time it was taken. ``contact_ceiling``: the caution level
        # (a target at or above it is refused); set by the agent from the force configuration.
        self.contact_target: float | None = None
        self.contact_off_reason = "contact mode not entered"  # why it is off ("" while on)
        self.contact_ceiling = math.inf
        self._contact_force = 0.0
        self._contact_force_at = -math.inf
        self._contact_integral = 0.0  # m/s: the admittance's integral term (see _hold_contact)
        self._contact_at = -math.inf  # monotonic time _hold_contact last integrated
        # Singularities, joint limits, reach (set by the agent, which knows the arm's model; None: not guarded).
        self.kinematics: KinematicGuard | None = None
        self.interventions: list[tuple[Status, str]] = []  # (status, reason), drained by the agent to log
        self.status = Status.DISARMED if not self.armed else Status.IDLE
        self.reason = "" if self.armed else NOT_ARMED
        self.disarmed_because = ""  # why the edge was disarmed (a takeover at the robot, a local command), for refusals
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
        self.disarmed_because = ""
        self.arm_requested = False
        self._set(Status.IDLE, "armed")

    def disarm(self, reason: str) -> None:
        self.armed = False
        self.disarmed_because = reason
        self._halt(Status.DISARMED, reason)

    def owner_refusal(self, msg: Message, suffix: str) -> str:
        """"" if ``msg`` (a command or control request on ``suffix``) comes from the session holding control —
        the owner's name, a valid signature with this grant's key, and a sequence after the last one on that
        suffix (a replayed message fails), which is then recorded — else why not."""
        operator = getattr(msg, "operator", "")
        if not self.owner:
            return f"{operator!r} does not hold control (nobody does)"
        if operator != self.owner:
            return f"{operator!r} does not hold control ({self.owner!r} does)"
        if not self.signed_by_owner(msg, suffix):
            return _not_signed(operator)
        return self._sequence_refusal(msg.seq, suffix)

    def signed_by_owner(self, msg: Message, suffix: str) -> bool:
        """Whether ``msg`` carries the signature of the grant that holds control (the sequence is not checked)."""
        return bool(self._key) and auth.verify(self._key, self._context(suffix), msg)

    def impersonation(self, msg: Message, suffix: str) -> str:
        """"" unless ``msg`` (a request anyone may make, as a preview) is in the name of the operator holding
        control without its grant's signature: then why it is refused. A preview's token is kept for its operator,
        the owner's last (GotoController); previews claiming the owner's name could push its own out."""
        operator = getattr(msg, "operator", "")
        if not self.owner or operator != self.owner or self.signed_by_owner(msg, suffix):
            return ""
        return _not_signed(operator)

    def _sequence_refusal(self, seq: int, suffix: str) -> str:
        """"" and ``seq`` recorded if it follows the last one on ``suffix`` within the jump bound, else why not."""
        last = self._last_seq.get(suffix, 0)
        if seq <= last:
            return f"sequence {seq} is not after {last} (a replay, or out of order)"
        if seq - last > self.config.max_sequence_jump:
            return (f"sequence {seq} jumps {seq - last} past {last} (max {self.config.max_sequence_jump}): "
                    "acquire control again")
        self._last_seq[suffix] = seq
        return ""

    def acquire(self, req: ControlRequest, now: float) -> Grant:
        """A request for control. The holder renews its lease (and may switch profile) with a signed request;
        anyone else is refused while the lease runs. A new grant draws a new key and starts a new sequence."""
        operator, profile = req.operator, req.profile
        allowed = self.config.allowed_operators
        if allowed and operator not in allowed:
            return Grant(False, f"operator {operator!r} is not on this robot's allow-list")
        if profile and profile not in self.config.profiles:
            return Grant(False, f"unknown speed profile {profile!r} (this robot has {sorted(self.config.profiles)})")
        held = bool(self.owner) and now < self._lease_until
        renewal = held and not self.owner_refusal(req, keys.CONTROL_ACQUIRE)
        if held and not renewal:
            why = " (from a session that does not hold its key)" if operator == self.owner else ""
            return Grant(False, f"robot is controlled by {self.owner!r}{why}")
        if not renewal:
            # A renewal goes through whatever the clocks say: a step during a session refuses commands, not control.
            clocks = self._clock_refusal(req)
            if clocks:
                return Grant(False, clocks)
            self.owner = operator
            self._key = self._keygen()
            self._last_seq = {}
            self._deadman = self._last_deadman = False
            if not self._latched:
                # A grant moves nothing until the deadman is released and pressed under it: a press held from
                # before (a client that re-acquired by itself after this edge restarted) is no fresh intent.
                self._latched, self._latch_reason = Status.NO_DEADMAN, GRANT_NEEDS_PRESS
        self._lease_until = now + self.config.lease
        if profile:
            self.profile = profile
        if self._latched in (Status.FAULT, Status.OWNER_LOST) and not self.fault:
            # Acquiring (or renewing) acknowledges the fault, but never moves the robot by itself: motion needs
            # a fresh press of the deadman.
            self._latched = Status.STOPPED
            self._latch_reason = f"{self._latch_reason} — acknowledged: release the deadman and press it again"
            self._set(Status.STOPPED, self._latch_reason)
        if renewal:
            return Grant(True, f"lease of {operator!r} renewed for {self.config.lease:g} s, profile {self.profile}")
        return Grant(True, f"control granted to {operator!r} for {self.config.lease:g} s, profile {self.profile}",
                     key=self._key)

    def _clock_refusal(self, req: ControlRequest) -> str:
        """"" if the request's time (the operator's clock) agrees with this edge's wall clock within the age a
        command may have, else what to fix: both readings, so that the operator sees which one is wrong."""
        here = self._wall_clock()
        there = req.t / 1e9
        if abs(here - there) <= self.config.max_command_age:
            return ""
        return (f"clocks disagree: this robot's reads {_utc(here)}, the operator's {_utc(there)} "
                f"({_duration(here - there)} apart; a command may be {_duration(self.config.max_command_age)} old): "
                "set the wrong one right (NTP)")

    def release(self, req: ControlRequest) -> tuple[bool, str]:
        """The owner gives control back (a signed request)."""
        refusal = self.owner_refusal(req, keys.CONTROL_RELEASE)
        if refusal:
            return False, refusal
        self._drop_owner()
        self._halt(Status.IDLE, "released by its owner")
        return True, "released by its owner"

    def owner_lost(self, operator: str, reason: str) -> bool:
        """The owner's liveliness token vanished (or its lease ran out): stop and release."""
        if not self.owner or operator != self.owner:
            return False
        self._drop_owner()
        self._halt(Status.OWNER_LOST, reason, latch=True)
        return True

    def _drop_owner(self) -> None:
        self.owner = ""
        self._key = b""
        self._last_seq = {}

    def _context(self, suffix: str) -> bytes:
        return auth.context(self.robot, suffix)

    def for_owner(self, suffix: str, msg: Message) -> bytes:
        """``msg``'s payload, signed with the owner's key while someone holds control: the owner's client then
        believes only what this edge said (the robot's state, command echoes, safety state, force levels), not a
        third session that publishes on the same key (a fresh-looking robot state would get its commands past
        the stale-view check, a level 0 would show green)."""
        return auth.seal(self._key, self._context(suffix), msg) if self._key else msg.encode()

    @property
    def grant_key(self) -> bytes:
        """The current grant's key (empty while nobody holds control): what :meth:`answer` signs with."""
        return self._key

    def answer(self, suffix: str, reply: Message, key: bytes | None = None) -> bytes:
        """A reply to a ``suffix`` query, stamped with the request's sequence, as its payload: signed with ``key``
        (default: the current grant's) so that the owner's client can tell this edge's answer from another
        session's. Unsigned while nobody holds control."""
        key = self._key if key is None else key
        return auth.seal(key, auth.reply_context(self.robot, suffix), reply) if key else reply.encode()

    # ---------------------------------------------------------------- faults, stops, force

    def stop(self, reason: str) -> None:
        """A stop command: controlled stop, latched until the deadman is released and pressed again."""
        self._halt(Status.STOPPED, reason, latch=True)

    @property
    def stop_in_force(self) -> bool:
        """A stop holds the robot still, and nothing has released it yet: another stop would change nothing."""
        return self._latched is Status.STOPPED and not self.moving and not any(self._target)

    def set_fault(self, reason: str) -> None:
        if reason and reason != self.fault:
            self.fault = reason
            self._halt(Status.FAULT, reason, latch=True)
        elif not reason:
            self.fault = ""

    def on_reading(self, fault: str, connected: bool, tcp_pose: Vector, takeover: str = "") -> str:
        """The robot driver's health from one reading: a fault it reports, a lost link, or a pose that is not a
        number (every limit compares with it, and a comparison with NaN never holds) is a fault here. A
        ``takeover`` (somebody at the robot has it: a program stopped on its pendant, local control) disarms with
        that reason: no remote operator moves the arm again until the edge is armed on site. Returns the fault in
        effect ("" when healthy). The takeover is said last: it is what the operator must read."""
        if not fault and connected and not all(math.isfinite(v) for v in _floats(tcp_pose)):
            fault = "the robot reported a pose that is not a number: no limit can hold"
        self.set_fault(fault or ("" if connected else "robot link lost"))
        if takeover and self.armed:
            self.disarm(takeover)
        return self.fault

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
            # A silent sensor: the robot does not know how hard it presses. A stop like any other, latched: a
            # deadman held through it moves nothing (the probe on a patient must not slide on blind), contact mode
            # ends, and after a release and a press only motion that does not press harder is allowed until
            # samples come back.
            self._retreat_until = -math.inf
            reason = ("force sensor stale: robot stopped, motion toward contact refused; release the deadman and "
                      "press it again to move")
            self._halt(Status.FORCE_STALE, reason, latch=True)
            self._intervene(Status.FORCE_STALE, reason)
        elif level == ForceLevel.DANGER and not stale and not was_danger:
            reason = DANGER_HELD
            if reaction.retract_distance > 0 and reaction.retract_speed > 0:
                self._retreat_until = now + reaction.retract_distance / reaction.retract_speed
                reason += f", retracting {1000 * reaction.retract_distance:.1f} mm"
            self._set(Status.FORCE_DANGER, reason)
            self._intervene(Status.FORCE_DANGER, reason)

    def set_contact(self, req: ControlRequest, on: bool, target: float | None = None) -> tuple[bool, str]:
        """Contact mode on (holding ``target`` N, default the configured one) or off, by the owner (a signed
        request). Entering is refused without a fresh force sensor, or at a target at or above the caution level."""
        refusal = self.owner_refusal(req, keys.CONTROL_CONTACT)
        if refusal:
            return False, refusal
        if not on:
            self.contact_off("left by the operator")
            return True, "contact mode off"
        if not (self.force_required and self.config.force.enabled):
            return False, "contact mode needs a force sensor and the force reaction on"
        if self.force_stale:
            return False, "contact mode refused: the force sensor is stale"
        force = self.config.contact.target if target is None else float(target)
        if not 0.0 < force < self.contact_ceiling:
            return False, f"contact force {force:g} N refused: it must lie above 0 and below the caution level " \
                          f"({self.contact_ceiling:g} N)"
        self.contact_target, self.contact_off_reason = force, ""
        self._contact_integral, self._contact_at = 0.0, -math.inf
        self._note(Status.CONTACT, f"contact mode on: holding {force:g} N along the probe")
        return True, f"contact mode on: holding {force:g} N along the probe"

    def contact_off(self, why: str) -> None:
        """Leave contact mode (if on), with the reason logged and recorded."""
        if self.contact_target is not None:
            self.contact_target, self.contact_off_reason = None, why
            self._note(Status.CONTACT, f"contact mode off: {why}")

    def update_contact_force(self, force: float, at: float) -> None:
        """The newest force along the probe's axis (N, pressing positive), read at monotonic ``at``."""
        self._contact_force, self._contact_force_at = float(force), at

    def force_zero_refusal(self) -> str:
        """Why the force sensor may not be zeroed now ("" if it may): zeroing in contact would hide the contact
        force from every threshold afterwards."""
        if not self.force_required:
            return "this robot has no force sensor"
        if self.force_stale or self.force_level != ForceLevel.SAFE:
            stale = ", stale" if self.force_stale else ""
            return f"force sensor not zeroed: level {int(self.force_level)}{stale}; lift the tool out of contact first"
        return ""

    # ---------------------------------------------------------------- commands and control cycles

    def on_command(self, cmd: TwistCommand, recv_wall: float, now: float, tcp_pose: Vector,
                   goto_twist: list[float] | None = None) -> Decision:
        """A decoded twist command. ``recv_wall`` is the receive time (s since the epoch, to compare with
        ``cmd.t``); ``now`` is the monotonic time; ``tcp_pose`` the latest ``[x,y,z,rx,ry,rz]``.

        ``goto_twist``: a previewed move is under way and this is its velocity now. The owner holds the deadman
        with zero twists while it runs (hold-to-run); a released deadman, a manual twist (the operator takes
        over) or any refusal of the owner's command ends it (``Decision.cancel_goto``)."""
        decision = self._on_command(cmd, recv_wall, now, tcp_pose, goto_twist)
        if goto_twist is not None and not decision.cancel_goto and decision.status != Status.NOT_OWNER:
            if not cmd.deadman:
                decision.cancel_goto = "deadman released"
            elif not decision.accepted or decision.status.halts:
                decision.cancel_goto = decision.reason or decision.status.message
        return decision

    def _on_command(self, cmd: TwistCommand, recv_wall: float, now: float, tcp_pose: Vector,
                    goto_twist: list[float] | None) -> Decision:
        self.counters.received += 1
        self._now = now
        self._track_wall_clock(recv_wall, now)
        refusal = self._refuse(cmd, recv_wall)
        if refusal is not None:
            self.counters.rejected += 1
            status, reason = refusal
            forged = cmd.operator == self.owner and bool(self.owner) and status == Status.NOT_OWNER
            if forged:
                self.counters.forged += 1
            if status == Status.STALE_COMMAND:  # the owner's (the age is checked last): its clock, or a late link
                self._time_refusal, self._time_refused_at = reason, now
                if not self._deadman and not self._latched:
                    self._set(status, reason)  # the robot stands still for this reason: the safety status says it
            return self._decide(self._current(), False, status, reason, answer=not forged)
        self._time_refusal = ""
        gap = now - self._last_live
        resumed_after_gap = cmd.deadman and self._last_deadman and gap > self.config.resume_gap
        silence = now - self._last_accepted
        self._last_accepted = now
        self._last_deadman = cmd.deadman
        self._lease_until = now + self.config.lease
        if not cmd.deadman:
            self._last_live = now
            self._deadman = False
            if self._latched in RESUME_ON_PRESS:
                self._latched = None  # deadman released after a stop, a gap or a silent sensor: the next press may
                # move (a grant's latch is cleared by any authentic release, in _refuse)
            self._target = [0.0] * 6
            self.counters.applied += 1
            self._set(Status.NO_DEADMAN, "deadman released")
            return self._decide([0.0] * 6, True, Status.NO_DEADMAN, "deadman released")
        if resumed_after_gap and not self._latched:
            # A gap in the commands, or commands that kept coming but could move nothing (an old picture on the
            # operator's screen): either way the operator has not driven for a while, and a press resumes.
            spell = (f"commands resumed after a gap of {1000 * gap:.0f} ms" if silence > self.config.resume_gap else
                     f"motion was refused for {1000 * gap:.0f} ms")
            self._halt(Status.LINK_GAP, f"{spell} (more than {1000 * self.config.resume_gap:.0f}): release the "
                       "deadman and press it again", latch=True)
        view_age = _view_age(cmd, recv_wall)
        if view_age < 0 or view_age > self.config.max_view_age:
            # Acting on an old picture: the robot stops, and moves again once the operator sees it live.
            seen = "no robot state" if view_age < 0 else f"a robot state {1000 * view_age:.0f} ms old"
            self.counters.rejected += 1
            self._halt(Status.STALE_VIEW, f"motion refused: the operator's screen shows {seen} "
                       f"(max {1000 * self.config.max_view_age:.0f} ms)")
            return self._decide([0.0] * 6, False, self.status, self.reason)
        self._last_live = now
        self._deadman = True
        if self._latched:
            self.counters.rejected += 1
            # What holds the robot is the latch: a halt since (a stale view, now cleared) may have taken the status.
            self._set(self._latched, self._latch_reason)
            return self._decide([0.0] * 6, False, self._latched, self._latch_reason)
        manual = [float(v) for v in (*cmd.linear, *cmd.angular)]
        if cmd.frame == "tool":  # the probe's frame about its tip → the base frame, where every limit applies
            manual = [*rotate(tcp_pose[3:], manual[:3]), *rotate(tcp_pose[3:], manual[3:])]
        took_over = goto_twist is not None and any(manual)
        self._target_is_move = goto_twist is not None and not took_over
        self._target = [float(v) for v in goto_twist] if self._target_is_move else manual
        decision = self._limit(self._target, tcp_pose, now)
        if took_over:
            decision.cancel_goto = "the operator took over with a manual twist"
        self.counters.applied += 1
        return decision

    def step(self, now: float, tcp_pose: Vector) -> Decision:
        """One control cycle: apply the timeout and the limits to the current target."""
        self._now = now
        if self.owner and now >= self._lease_until and now - self._last_accepted > self.config.lease:
            reason = f"lease of {self.owner!r} expired: robot stopped, control released"
            self.owner_lost(self.owner, reason)
            self._note(Status.OWNER_LOST, reason)
        # The deadman times out also while a latch holds the robot: a deadman left held under a latch made
        # timeout_at() a time already past, and the control loop woke for it again and again (~20 000 cycles a
        # second, a core, for as long as the lease was renewed).
        if now >= self.timeout_at():  # the instant itself (the control loop wakes for it)
            self._deadman = False
            self._target = [0.0] * 6
            if not self._latched and self.armed:
                # Commands that keep coming refused for their time are no silence: their reason is the stop's (a
                # refusal from before a silence is not).
                refusing = self._time_refusal and now - self._time_refused_at <= self.config.command_timeout
                status, reason = (Status.STALE_COMMAND, self._time_refusal) if refusing else (
                    Status.COMMAND_TIMEOUT, f"no command for {1000 * (now - self._last_accepted):.0f} ms "
                                            f"(timeout {1000 * self.config.command_timeout:.0f} ms)")
                self._halt(status, reason)
                self._note(status, reason)
        if self._latched or not self.armed:
            return self._decide([0.0] * 6, False, self.status, self.reason)
        if not self._deadman:
            return self._retreat_only(tcp_pose, now)
        return self._limit(self._target, tcp_pose, now)

    def driver_failed(self, reason: str) -> Decision:
        """The driver refused or failed a command: a fault, and the robot is told to stop."""
        self.set_fault(reason)
        self._sent_motion = True  # whatever it did with the last command, stop it
        return self._decide([0.0] * 6, False, self.status, self.reason)

    # ---------------------------------------------------------------- internals

    def _decide(self, twist: list[float], accepted: bool, status: Status, reason: str,
                hit: list[str] | None = None, answer: bool = True) -> Decision:
        """Every decision leaves through here: the driver's action follows from the twist and what the driver
        was last told (a zero after motion is a stop at the stop deceleration; a zero after a zero is nothing)."""
        if any(twist):
            action, self._sent_motion = Action.MOVE, True
        elif self._sent_motion:
            action, self._sent_motion = Action.STOP, False
        else:
            action = Action.HOLD
        return Decision(twist, accepted, status, reason, hit or [], action, answer)

    def _refuse(self, cmd: TwistCommand, recv_wall: float) -> tuple[Status, str] | None:
        # The owner's authentic commands count in its sequence whatever happens to them next (a fault, disarmed):
        # an operator holding the deadman through a protective stop must not run into the jump bound afterwards.
        if self.owner and cmd.operator == self.owner:
            if not auth.verify(self._key, self._context(keys.CMD_TWIST), cmd):
                return Status.NOT_OWNER, f"command in the name of {cmd.operator!r} not signed by its session"
            out_of_order = self._sequence_refusal(cmd.seq, keys.CMD_TWIST)
            if out_of_order:
                return Status.OUT_OF_ORDER, out_of_order
            if not cmd.deadman and self._latched == Status.NO_DEADMAN:
                self._latched = None  # the grant's release: counts even while disarmed or in a fault
        if cmd.frame not in TWIST_FRAMES:
            return Status.BAD_COMMAND, f"unknown twist frame {cmd.frame!r} (known: {', '.join(TWIST_FRAMES)})"
        if self.fault:
            return Status.FAULT, self.fault
        if not self.armed:
            return Status.DISARMED, f"{self.disarmed_because}; {NOT_ARMED}" if self.disarmed_because else NOT_ARMED
        if not self.owner:
            return Status.NOT_OWNER, "no operator holds control: acquire it first"
        if cmd.operator != self.owner:
            return Status.NOT_OWNER, f"robot is controlled by {self.owner!r}, not {cmd.operator!r}"
        age = recv_wall - cmd.t / 1e9
        if abs(age) <= self.config.max_command_age:
            self._wall_step, self._shown_age = 0.0, None  # the clocks agree: a step seen before is settled
            return None
        # The operator's client logs each distinct refusal once, and a reason that changed with every command's
        # jitter was a new line 60 times a second: the age given stays until it is off by more than the jitter of
        # a loaded link, and it is rounded (_duration).
        shown = self._shown_age
        if shown is None or abs(age - shown) > max(0.2, 0.05 * abs(shown)):
            self._shown_age = shown = age
        age = shown
        stepped = (f" (this robot's clock stepped {_duration(self._wall_step)} "
                   f"{'forward' if self._wall_step > 0 else 'back'})" if self._wall_step else "")
        loop = _named_state_age(cmd, recv_wall)
        if loop is not None and loop <= self.config.max_view_age:
            # It names a robot state this edge stamped a moment ago: the command is not old, the clocks differ.
            side = "behind" if age > 0 else "ahead of"
            return Status.STALE_COMMAND, (f"the operator's clock is {_duration(age)} {side} this robot's{stepped}: "
                                          "synchronise the clocks (NTP)")
        if age > 0:
            return Status.STALE_COMMAND, (f"command is {_duration(age)} old "
                                          f"(max {_duration(self.config.max_command_age)}){stepped}")
        return Status.STALE_COMMAND, f"command time is {_duration(age)} in the future{stepped}: check clock sync"

    def _track_wall_clock(self, recv_wall: float, now: float) -> None:
        """Follow this edge's wall clock against its monotonic one (``recv_wall`` and ``now`` name one instant): a
        jump between two commands is a step of the wall clock (NTP, ``date -s``), added to ``_wall_step``."""
        offset = recv_wall - now
        if self._wall_offset is not None:
            jump = offset - self._wall_offset
            if abs(jump) > WALL_STEP_TOLERANCE + MAX_SLEW * abs(now - self._wall_offset_at):
                self._wall_step += jump
        self._wall_offset, self._wall_offset_at = offset, now

    def _current(self) -> list[float]:
        return list(self._target) if self._deadman and not self._latched else [0.0] * 6

    def _set(self, status: Status, reason: str) -> None:
        self.status, self.reason = status, reason

    def _halt(self, status: Status, reason: str, latch: bool = False) -> None:
        if latch:  # a stop, a fault, a lost owner, a long gap: contact mode is entered again on purpose only
            self.contact_off(reason)
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
            self._set(Status.FORCE_DANGER, RETRACTING)
            return self._decide(twist, True, Status.FORCE_DANGER, RETRACTING, ["force"])
        self.moving = False
        if self.status == Status.FORCE_DANGER and self.reason == RETRACTING:
            # The retreat is over: say what holds now (the status said "retracting" until the next event, seconds).
            if self.force_level == ForceLevel.DANGER and not self.force_stale:
                self._set(Status.FORCE_DANGER, DANGER_HELD)
            else:
                self._set(Status.NO_DEADMAN, "deadman released")
        return self._decide([0.0] * 6, False, self.status, self.reason)

    def _intervene(self, status: Status, reason: str) -> None:
        if status != self._force_active:
            self._force_active = status
            self._note(status, reason)

    def _note(self, status: Status, reason: str) -> None:
        """An intervention the agent logs (every stop the supervisor decides on its own has a line of its own)."""
        self.interventions.append((status, reason))
        del self.interventions[:-64]  # bounded if nobody drains it

    def _limit(self, target: list[float], tcp_pose: Vector, now: float) -> Decision:
        """Speed, force and workspace limits on ``target`` (6 floats). Plain float arithmetic, not numpy: this
        runs for every command and every control cycle, where numpy's per-call overhead on 3-vectors is most
        of the cost."""
        limits = self.limits
        twist = list(target)
        hit: list[str] = []
        status: Status = Status.OK
        reason = ""
        if self.contact_target is not None:  # the axial motion is the admittance's, then every limit applies
            status, reason = Status.CONTACT, self._hold_contact(twist, _floats(tcp_pose), now)
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
        if self.kinematics is not None:
            slowed = self.kinematics.limit(twist)
            if slowed is not None:
                hit.append("kinematics")
                status, reason = slowed
        pose = _floats(tcp_pose)
        # Force before workspace: a retreat adds velocity, and the box must still bound it.
        force_status = self._clip_force(twist, pose, now)
        if force_status is not None:
            hit.append("force")
            status, reason = force_status
            self._intervene(status, reason)
        else:
            self._force_active = None
        if self._clip_workspace(twist, pose):
            hit.append("workspace")
            status, reason = Status.WORKSPACE, "velocity leaving the workspace box removed"
        self.limits_hit = hit
        self.moving = any(abs(v) > 1e-9 for v in twist)
        self._set(status, reason)
        return self._decide(twist, True, status, reason, hit)

    def _hold_contact(self, twist: list[float], pose: list[float], now: float) -> str:
        """Contact mode: replace the twist's component along the probe's axis (in place) by the admittance toward
        the target force; the operator keeps the tangential motion and the rotation. Returns the status line."""
        c = self.config.contact
        n = self._contact_direction(pose)  # pressing direction in the base frame
        along = twist[0] * n[0] + twist[1] * n[1] + twist[2] * n[2]
        assert self.contact_target is not None
        error = self.contact_target - self._contact_force
        fresh = now - self._contact_force_at <= c.max_force_age
        dt = 0.0 if math.isinf(self._contact_at) else min(max(0.0, now - self._contact_at), 2 * self.period)
        self._contact_at = now
        speed = 0.0
        if fresh and abs(error) > c.deadband:
            # PI: the integral follows a surface that rises or falls under a sweep (a proportional admittance
            # would lag it by a standing error of slope·speed/gain). It integrates only while the output is not
            # at its bound (no wind-up during the approach from free space, when the error is the whole target).
            integral = self._contact_integral + c.integral_gain * error * dt
            if abs(c.gain * error + integral) < c.max_speed:
                self._contact_integral = integral
            speed = max(-c.max_speed, min(c.max_speed, c.gain * error + self._contact_integral))
        _add_along(twist, speed - along, n)
        if not fresh:
            if math.isinf(self._contact_force_at):
                return "contact mode: no force reading along the probe yet: holding"
            return f"contact mode: no fresh force reading for {1000 * (now - self._contact_force_at):.0f} ms: holding"
        return f"contact mode: {self._contact_force:.1f} N of {self.contact_target:g} N"

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

    def _clip_force(self, twist: list[float], pose: list[float], now: float) -> tuple[Status, str] | None:
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
        result: tuple[Status, str] | None = None
        in_contact = self.contact_target is not None
        if self.force_level == ForceLevel.DANGER and (in_contact or (self._target_is_move and toward >= 0)):
            # Red while the admittance holds a force below yellow: it is not keeping up (a surface rising under the
            # sweep, the patient moving); red during a previewed move that does not lift off: it met what its
            # preview did not show. Going on would press harder sideways, so the operator's steering and the move
            # stop; only motion away from contact (the admittance backing off to the held force) goes on.
            away = min(0.0, toward)
            twist[:] = [away * n[0], away * n[1], away * n[2], 0.0, 0.0, 0.0]
            toward = away
            result = Status.FORCE_DANGER, ("danger-level force in contact mode: steering stopped, the probe backs off"
                                           if in_contact else
                                           "danger-level force: the previewed move stopped")
        elif self.force_level == ForceLevel.DANGER and toward > 0:
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


def _named_state_age(cmd: TwistCommand, recv_wall: float) -> float | None:
    """The age (s), on this edge's clock, of the robot state the command names (``view_t``), both trips over the
    link included; None when it names none, or one from this edge's future (not one of its states)."""
    age = recv_wall - cmd.view_t / 1e9
    return age if cmd.view_t and age >= 0.0 else None


def _view_age(cmd: TwistCommand, recv_wall: float) -> float:
    """The age (s) of the robot state the operator acted on; -1: none. The named state's age measured here: no
    operator's clock comes into it, so one that is behind cannot make an old picture look fresh, nor one ahead a
    fresh one old. Otherwise (an older client) what the operator says: its clock minus this edge's."""
    if cmd.state_age < 0:
        return -1.0
    age = _named_state_age(cmd, recv_wall)
    return cmd.state_age if age is None else age


def _duration(seconds: float) -> str:
    """The size of a clock difference or an age (its sign dropped), to 100 ms below 10 s, then coarser: stable
    from one command to the next, readable from milliseconds to an edge that booted in 1970."""
    s = abs(seconds)
    if s < 10.0:
        return f"{100 * round(10 * s)} ms"
    for unit, size, limit in (("s", 1.0, 120.0), ("min", 60.0, 7200.0), ("h", 3600.0, 2 * 86400.0),
                              ("days", 86400.0, 2 * 365.25 * 86400.0)):
        if s < limit:
            return f"{s / size:.0f} {unit}"
    return f"{s / (365.25 * 86400.0):.0f} years"


def _utc(wall: float) -> str:
    """A wall clock reading (s since the epoch) to the minute, UTC (the seconds themselves if out of a date's range)."""
    try:
        return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(wall))
    except (OverflowError, OSError, ValueError):
        return f"{wall:.0f} s after 1970"


def _floats(v: Vector | list[float]) -> list[float]:
    return v.tolist() if isinstance(v, np.ndarray) else [float(x) for x in v]


def _add_along(twist: list[float], amount: float, n: tuple[float, float, float]) -> None:
    """Add ``amount`` times the unit vector ``n`` to the linear part of ``twist`` (in place)."""
    twist[0] += amount * n[0]
    twist[1] += amount * n[1]
    twist[2] += amount * n[2]
