"""The operator's library client: acquire control, stream twists at a fixed rate, watch the robot.

The sender runs on an absolute schedule (``rate_hz``, default 60), independent of input
events: the reference system's irregular, event-driven publishing tripped safety stops. Given ``sender_config`` (the
console and the ``iorthand operator`` CLI), it runs in its own process with its own Zenoh session
(:mod:`iorthand_operator.sender`), out of reach of a busy UI's GIL; without it, in a thread of this process
(library users, tests). Each twist carries a
sequence number, its send time and the deadman flag. When the deadman is released the sender keeps sending
zero twists with ``deadman=False`` for ``release_tail`` seconds, then goes quiet. A liveliness token tells
the edge this operator is alive; the edge releases control when it disappears (a crash, a kill, Ctrl-C).

Besides the command stream the client watches what the console shows: the force level (``state/force_level``,
with its receive time so a silent sensor turns "stale" here even if the edge says nothing), the wrench, servo
and torch state, markers, the edge's liveliness, link quality (:class:`LinkWindow`) and a log of refusals and
stops with their reasons. Zenoh callbacks only decode small messages and store them.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import threading
import time
from collections import OrderedDict, defaultdict, deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from iorthand import keys
from iorthand.process import raise_priority
from iorthand.protocol import (
    CONSOLE_SENDS,
    NEWER_SENDER,
    REVISION,
    SAFETY_STATE,
    STOP_FROM,
    TWIST_FRAMES,
    AppliedCommand,
    ControlReply,
    ControlRequest,
    DecodeError,
    ForceLevelState,
    ForceSample,
    Markers,
    Message,
    RejectCounter,
    RobotState,
    SafetyStatus,
    SensorReading,
    Sequencer,
    ServoCommand,
    ServoState,
    Status,
    StopCommand,
    TorchCommand,
    TorchState,
    TwistCommand,
    revision_json,
    said_revision,
    source_news,
    superseded_news,
    unreadable_by,
    update_the_edge,
)
from iorthand.security import auth, identity
from iorthand.transport import QOS_BY_KEY, ZenohConfig, publisher, query
from iorthand_operator import recovery
from iorthand_operator.link import STATE_STALE_S, LinkQuality, LinkWindow
from iorthand_operator.sender import CommandStream, ProcessSender, run_fixed_rate

log = logging.getLogger("iorthand.operator")


class ControlRefused(RuntimeError):
    """The edge refused a control request; the message is the edge's reason."""


@dataclass(slots=True)  # 100 000 of them are kept: no per-object dict
class Echo:
    """One command's round trip: sent by us, applied (or refused) by the edge, echoed back. Its times are
    monotonic: a wall clock stepped by NTP between the send and the echo made round trips of -500 ms."""

    seq: int
    sent_ns: int  # the command's own time stamp (wall clock): with ``seq``, which command this echo answers
    echoed_ns: int  # wall clock when the echo arrived (to line echoes up with other records, not to time them)
    accepted: bool
    status: str
    sent_mono: float  # monotonic time the command was sent
    echoed_mono: float  # monotonic time the echo arrived: what "lately" is measured on

    @property
    def rtt_ms(self) -> float:
        return (self.echoed_mono - self.sent_mono) * 1e3


@dataclass
class Event:
    """A refusal, a stop or an input problem, with its reason: what the console's log shows."""

    t: float  # wall time, s
    kind: str  # "refused", "stop", "control", "input", "action", "warning", "info"
    status: str
    reason: str
    # Its number in the client's log (1, 2, ...): how a reader knows what it has shown, however alike two events
    # read (the same refusal twice in a second, around a stop).
    n: int = 0


# Safety statuses that mean the robot was stopped (worth a line in the log when the edge enters them).
STOP_STATUSES = frozenset(s for s in Status if s.halts)
MAX_VITALS = 16
# An acquire refused because the edge has not seen our liveliness token yet is asked again (identity.NO_TOKEN).
TOKEN_RETRIES = 4
TOKEN_RETRY_S = 0.25
RENEW_RETRY_S = 0.2  # s between attempts while a lease renewal fails (see OperatorClient._renew_lease)
# A safety status older than this is none (next_step) or shown as old (the console): the edge sends one at
# safety_rate_hz (20 Hz by default, 1 Hz at the least) and on every change.
SAFETY_STALE_S = 2.0
# A planning query (a preview, the list of poses) waits for the edge's planner, which refuses a plan that takes
# longer than 10 s (iorthand_edge.planner.PLAN_TIMEOUT_S: a planner stuck, not slow); that refusal comes a round
# trip (and the twin's hop) later. The generic query_timeout (2 s) ran out first: the operator read a bare "Timeout".
PLAN_QUERY_TIMEOUT_S = 12.0
# How a query that nobody answered in time ends (Zenoh's error reply, which iorthand.transport.query raises).
QUERY_TIMED_OUT = ": Timeout"
# Marker poses older than this are out of view on both consoles: the web console stops drawing them (its 3D view
# would put them where the patient was) and the terminal console stops listing them; both then say how old they are.
# The edge publishes them with every camera frame it processes, several a second.
MARKERS_SHOWN_S = 1.0
# A servo or torch state is shown as old (the console) once this many of its heartbeats went missing: the edge
# publishes each on change and every ``period`` s (servos/torch publish_hz, 0.1..50 Hz), and calls the servo angles
# unknown after as many (iorthand_edge.perception.history.SERVO_STALE_HEARTBEATS).
ACTUATOR_STALE_HEARTBEATS = 3
# The bound for a state that does not say its period (an older edge): three heartbeats at the default 2 Hz.
ACTUATOR_STALE_S = ACTUATOR_STALE_HEARTBEATS / 2.0


def actuator_stale_after(msg: ServoState | TorchState) -> float:
    """s after which ``msg`` is shown as old: three of its sender's heartbeat periods (ACTUATOR_STALE_S when it
    does not say its period), never less than a robot state's bound: at 50 Hz three periods are 60 ms, less than
    an Internet link's jitter, and the row would flicker."""
    if msg.period <= 0:
        return ACTUATOR_STALE_S
    return max(ACTUATOR_STALE_HEARTBEATS * msg.period, STATE_STALE_S)


# The deadman flag of the last command sent is what the stream sends only if that command went out within this
# long (a few periods, and the process sender's records arrive up to ~50 ms late): a quiet stream sends none.
SENT_LATELY_S = 0.25
# A sender process that dies is started again, unless it died this many times within this many seconds: then the
# client gives control up and says why (OperatorClient._restart_sender).
SENDER_LOSSES = 3
SENDER_LOSS_WINDOW_S = 60.0

class OperatorClient:
    def __init__(
        self,
        session: zenoh.Session,
        robot_id: str,
        operator_id: str,
        rate_hz: float = 60.0,
        release_tail: float = 0.3,
        query_timeout: float = 2.0,
        plan_timeout: float = PLAN_QUERY_TIMEOUT_S,
        link_window: float = 5.0,
        realtime: bool = True,
        spin: bool = True,
        gil_switch_interval: float | None = 0.0005,
        bind_keys: bool = False,
        sender_config: ZenohConfig | None = None,
        ui_timeout: float = 0.5,
        announce: bool = True,
        external_sender: bool = False,
    ) -> None:
        self.session = session
        self.keys = keys.RobotKeys(robot_id)
        # What the edge signs for the owner (Supervisor.for_owner), each key's signature context made once: they
        # are checked in Zenoh's callbacks, the robot state 125 times a second.
        self._edge_contexts = {suffix: auth.context(robot_id, suffix) for suffix in
                               (keys.STATE_ROBOT, keys.STATE_APPLIED, keys.STATE_SAFETY, keys.STATE_FORCE_LEVEL)}
        self.operator_id = keys.check_operator_id(operator_id)
        self.rate_hz = rate_hz
        self.release_tail = release_tail
        self.query_timeout = query_timeout
        self.plan_timeout = plan_timeout
        self.rejects = RejectCounter()
        self._lock = threading.Lock()
        self._twist = np.zeros(6)
        self._frame = "base"  # of the twist: "base" or "tool" (the probe's frame about its tip)
        self._deadman = False
        self._released_at = 0.0
        # The grant of control: the key the edge's acquire reply carried (signs every command of ours) and a
        # counter of grants (each restarts the command sequence). Empty while we do not hold control.
        self._key = b""
        self._key_gen = 0
        # Monotonic time the key arrived, or a sender process that died was started again: a deadman press from
        # before it starts nothing.
        self._press_from = 0.0
        self._pressed_at = 0.0  # monotonic time the deadman was last pressed
        # Monotonic time the edge entered its latest halt that waits for a fresh press or a new grant
        # (recovery.REPRESS, recovery.REACQUIRE): a press after it is fresh intent (CommandStream).
        self._halted_at = -math.inf
        # The latest stop command that somebody else sent (the nurse at the patient, another console): monotonic
        # time the edge said so, and its reason. A headless client's motion asked before it ends there
        # (scripted.drive_for). The stops this client sent itself: (monotonic time, reason).
        self.stopped_by_other_at = -math.inf
        self.stopped_by_other = ""
        self._own_stops: deque[tuple[float, str]] = deque(maxlen=8)
        self._acquire_lock = threading.Lock()
        self._heartbeat = time.monotonic()  # the UI is alive (see CommandStream): beaten by the heartbeat thread
        self._beats_itself = True
        self._state_t = 0  # source time (ns) of the newest robot state: each command states its age
        # One sequence per key suffix: the edge and the recorder count gaps per key, and the edge checks a signed
        # message's sequence per suffix (a counter shared between control verbs would jump on each of them).
        self._seq_other: defaultdict[str, Sequencer] = defaultdict(Sequencer)
        self.bind_keys = bind_keys  # commands and control queries on keys carrying our id (ACL-bound)
        # (seq, the command's time stamp) → monotonic send instant, bounded; an echo takes its entry. The sequence
        # alone restarts with every grant: an echo of an earlier grant's command matched a new one.
        self._sent: OrderedDict[tuple[int, int], float] = OrderedDict()
        self.echoes: deque[Echo] = deque(maxlen=100_000)  # the newest (~28 min at 60 Hz): bounded for long sessions
        self.echo_count = 0  # every echo ever appended: marks for echoes_since (the deque drops its oldest)
        self.sent_count = 0
        self.last_sent_ns = 0
        # The deadman flag of the last command sent and its monotonic send instant (sending_deadman).
        self.last_sent_deadman = False
        self.last_sent_at = -math.inf
        self.send_times: list[float] = []  # monotonic send instants, for jitter figures
        self.robot_state: RobotState | None = None
        self.safety: SafetyStatus | None = None
        self.safety_at = -math.inf  # monotonic time the newest safety status arrived
        self.last_refusal: AppliedCommand | None = None
        self.owner = False
        self.lease = 0.0
        self._renewed_at = -math.inf  # monotonic time our last granted or renewed acquire was sent
        self._muted = False
        self.link = LinkWindow(link_window)
        self.realtime = realtime
        # The thread sender sleeps most of each period and spins the last ~1.5 ms for sub-ms regularity; many
        # clients on one small machine (scale benchmarks) sleep only.
        self.spin = spin
        self.gil_switch_interval = gil_switch_interval
        self.sender_priority = "normal"  # what the sender thread got: "SCHED_FIFO", "normal (…)"
        self.events: deque[Event] = deque(maxlen=200)
        self.event_count = 0  # every event ever logged: marks for events_since
        self._events_lock = threading.Lock()
        self.force_level: ForceLevelState | None = None
        self.force_level_at = 0.0  # monotonic receive time of force_level
        self.peak_force_level = 0  # highest fresh level seen (scripts and the demo report it)
        self.force: ForceSample | None = None
        self.force_at = 0.0
        self.force_history: deque[float] = deque(maxlen=120)  # |F| N, for the sparkline
        # The patient's vital signs (sensor/vital, from iorthand bridge mqtt): the newest reading per name and its
        # receive time (monotonic), at most MAX_VITALS names (a flood of names cannot grow it).
        self.vitals: dict[str, tuple[SensorReading, float]] = {}
        self.servo: ServoState | None = None
        self.servo_at = -math.inf  # monotonic receive time of servo
        self.torch: TorchState | None = None
        self.torch_at = -math.inf  # monotonic receive time of torch
        self.markers: Markers | None = None
        self.markers_at = 0.0
        self.robot_state_at = 0.0
        self.edge_alive: bool | None = None  # None: not known yet
        # The protocol revision the edge's latest acquire answer said (None: not asked yet; 1: it said none).
        self.edge_revision: int | None = None
        # Safety state this console cannot read (refused as from a newer sender since the last one it could), by
        # message class: it asks for no control meanwhile. And the keys whose newer sender the log has shown.
        self.unreadable: dict[str, str] = {}
        self._newer_said: set[str] = set()
        self._servo_target = [0.0, 0.0]
        self._last_refusal_key: tuple[str, str] | None = None
        self._last_safety_status = ""
        self._last_forged: int | None = None  # likewise for SafetyStatus.forged
        self._last_superseded: int | None = None  # None until the first status: a count from before we joined is not news
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        twist_key = self._own_key(keys.CMD_TWIST)
        self.ui_timeout = ui_timeout
        # The process sender (own session; twists go out from the child) or, without a config, the thread one.
        self._proc_sender: ProcessSender | None = None
        if sender_config is not None:
            self._proc_sender = ProcessSender(
                sender_config, twist_key, robot_id, self.operator_id, rate_hz, release_tail, ui_timeout, realtime,
                self._lock, self._on_send_record, on_lost=self._on_sender_lost,
            )
        self.sender_down = ""  # why our commands cannot go out (the sender died); empty while they can
        self._sender_losses: deque[float] = deque(maxlen=SENDER_LOSSES)
        self._sender_start = threading.Lock()  # a restart of the sender and close() one at a time
        self._stream = CommandStream(robot_id, self.operator_id, release_tail, ui_timeout)  # the thread sender's
        # Twists leave from exactly one place: the child's own publisher, or this one for the thread sender.
        self._pub_twist = None if self._proc_sender is not None else publisher(session, twist_key, QOS_BY_KEY[keys.CMD_TWIST])
        # With bound keys every command goes on the key carrying our id, the one the router's ACL lets only our
        # certificate publish on (a stop there also tells the edge who sent it).
        self._pub_stop = publisher(session, self._own_key(keys.CMD_STOP), QOS_BY_KEY[keys.CMD_STOP])
        self._pub_servo = publisher(session, self._own_key(keys.CMD_SERVO), QOS_BY_KEY[keys.CMD_SERVO])
        self._pub_torch = publisher(session, self._own_key(keys.CMD_TORCH), QOS_BY_KEY[keys.CMD_TORCH])
        # The liveliness token tells the edge this operator is alive (its loss releases control); a client that
        # only watches (the web console's view of a robot) announces nothing.
        self._token = session.liveliness().declare_token(self.keys.alive_operator(operator_id)) if announce else None
        # external_sender: no loop of ours; the caller sends each command with send_now at its own fixed rate
        # (the web console forwards its page's 60 Hz stream, one page message one command).
        self.external_sender = external_sender
        # Called (on a Zenoh thread) with each of our commands' echoes as it arrives.
        self.echo_listener: Callable[[Echo, AppliedCommand], None] | None = None
        self._subs = [
            session.declare_subscriber(self.keys.key(keys.STATE_ROBOT), self._on_robot),
            session.declare_subscriber(self.keys.key(keys.STATE_SAFETY), self._on_safety),
            session.declare_subscriber(self.keys.key(keys.STATE_APPLIED), self._on_applied),
            session.declare_subscriber(self.keys.key(keys.STATE_FORCE_LEVEL), self._on_force_level),
            session.declare_subscriber(self.keys.key(keys.STATE_FORCE), self._on_force),
            session.declare_subscriber(self.keys.key(keys.STATE_SERVO), self._on_servo),
            session.declare_subscriber(self.keys.key(keys.STATE_TORCH), self._on_torch),
            session.declare_subscriber(self.keys.key(keys.MARKERS), self._on_markers),
            session.declare_subscriber(self.keys.key(keys.SENSOR_VITAL), self._on_vital),
            session.liveliness().declare_subscriber(self.keys.key(keys.ALIVE_EDGE), self._on_edge_alive, history=True),
        ]

    # ------------------------------------------------------------------ control

    def _control(self, suffix: str, profile: str = "", *, key: str | None = None, timeout: float | None = None,
                 **fields: str) -> ControlReply:
        """A control query; signed with our grant's key while we hold control (renewing, releasing, moving to
        a pose and zeroing the sensor are the owner's alone: the edge checks the signature, not the name).

        While we hold a key, the edge's answer is signed with it and carries our request's sequence
        (Supervisor.answer): that answer is taken as soon as it arrives, whoever else answers or holds the query
        open, and an answer that is not signed so is not believed (ControlRefused): the edge no longer holds us
        as its owner, or another session answered in its name. A new grant is the exception: it is signed with the
        new key it carries."""
        req = ControlRequest(operator=self.operator_id, profile=profile, **fields)
        req.stamp(self._next_seq(suffix))
        grant = self._sign(req, suffix)  # and what the edge's answer must be signed with
        payload = req.encode()
        to_edge = key is None  # (a preview goes through the twin: what it answers, the edge checks again)
        key = key or self._own_key(suffix)
        context = auth.reply_context(self.keys.robot, suffix)

        def signed_with(payload: bytes, secret: bytes) -> ControlReply | None:
            """The answer to this very request, signed with ``secret``; else None."""
            try:
                reply = ControlReply.decode(payload)
            except DecodeError:
                return None
            return reply if secret and reply.seq == req.seq and auth.verify(secret, context, reply) else None

        until = (lambda p: signed_with(p, grant) is not None) if to_edge and grant else None
        replies = query(self.session, key, payload, timeout=timeout or self.query_timeout, every_answer=to_edge,
                        until=until)
        if not replies:
            raise ControlRefused(f"no answer from robot {self.keys.robot!r} on {suffix} (is its edge agent online?)")
        if until is not None and (ours := signed_with(replies[-1], grant)) is not None:
            if len(replies) > 1:
                self.rejects.add(key, f"{len(replies) - 1} other answer(s) not signed by the edge for our grant")
            return ours
        if to_edge and len(replies) > 1:
            # Only the robot's edge answers here. On a router without access control any session can declare a
            # queryable on the key and answer first (a forged grant with a key of its own, to drive the robot
            # in our name while we believe we do): with more than one answer, none is to be believed.
            raise ControlRefused(f"{len(replies)} sessions answered {suffix} for robot {self.keys.robot!r}, where only "
                                 "its edge should: another session is answering in its name (a router without "
                                 "access control, docs/DEPLOY.md); no answer was taken")
        try:
            reply = ControlReply.decode(replies[0])
        except DecodeError as exc:
            raise ControlRefused(f"malformed reply on {suffix}: {exc}") from None
        if until is not None and signed_with(replies[0], reply.key) is None:
            self.rejects.add(key, "an answer not signed by the edge for our grant")
            raise ControlRefused(f"the answer on {suffix} is not signed for our grant of control: the edge no longer "
                                 f"holds us as its owner, or another session answered in its name ({reply.reason!r})")
        return reply

    def acquire(self, profile: str = "") -> ControlReply:
        """Acquire control, or renew it (a request signed with the key we hold). A new grant's key replaces
        ours; from then on every command is signed with it and the sequence starts again."""
        with self._acquire_lock:  # the lease thread and the user: one request at a time, in sequence order
            asked = time.monotonic()
            # Our protocol revision: the edge refuses a console that cannot read all it sends (protocol's docstring).
            reply = self._control(keys.CONTROL_ACQUIRE, profile, params=revision_json())
            for _ in range(TOKEN_RETRIES):
                if reply.ok or identity.NO_TOKEN not in reply.reason or self._token is None:
                    break
                time.sleep(TOKEN_RETRY_S)  # our token may still be on its way to the edge
                asked = time.monotonic()
                reply = self._control(keys.CONTROL_ACQUIRE, profile, params=revision_json())
        self._edge_speaks(said_revision(reply.detail))
        if reply.ok and (why := self._cannot_drive()):
            if reply.key:
                self._set_key(reply.key)  # what the release is signed with
            self.owner = True  # the grant is ours until released: give it back, as a console that must not drive
            self.release()
            reply.ok, reply.reason = False, why
        if not reply.ok:
            self.log_event("control", Status.NOT_OWNER, f"control refused: {reply.reason}")
            raise ControlRefused(reply.reason)
        if reply.key:
            self._set_key(reply.key)
            if self._deadman:  # a press from before this grant starts nothing (CommandStream): say so
                self.log_event("control", Status.NO_DEADMAN,
                               "control granted anew: release the deadman and press it again to move")
        elif not self._key:
            raise ControlRefused("the edge granted control without a key (an edge older than this client?)")
        self.owner, self.lease = True, reply.lease
        self._renewed_at = asked  # the edge's lease runs from no earlier than this
        return reply

    def _edge_speaks(self, revision: int) -> None:
        """Note the edge's protocol revision; a change from what we knew is said once in the log."""
        if revision == self.edge_revision:
            return
        self.edge_revision = revision
        if revision < REVISION:
            self.log_event("warning", "version", f"the edge speaks protocol revision {revision}, this console "
                                                 f"{REVISION}: update the edge")
        elif revision > REVISION:
            self.log_event("warning", "version", f"the edge speaks protocol revision {revision}, this console "
                                                 f"{REVISION}: what the edge added is not shown here: update this "
                                                 "console")

    def _cannot_drive(self) -> str:
        """Why this console must not drive the edge it was just granted: the edge cannot read a command it sends, or
        it cannot read the edge's safety state (an edge that granted anyway). Empty when it may."""
        edge = self.edge_revision or 1
        if fields := unreadable_by(edge, CONSOLE_SENDS):
            return update_the_edge(edge, fields)
        return self._cannot_read_safety()

    def _cannot_read_safety(self) -> str:
        """Why this console cannot read the edge's safety state (empty when it can): the instruction, both
        revisions (the edge's as its latest answer said, else unknown) and the refusals."""
        if not self.unreadable:
            return ""
        edge = f"the edge {self.edge_revision}" if self.edge_revision is not None else "the edge a newer one"
        return (f"update this console: it speaks protocol revision {REVISION}, {edge}, and it cannot read "
                f"{'; '.join(self.unreadable.values())}")

    def _own_key(self, suffix: str) -> str:
        """The key this client sends ``suffix`` on: with bound keys the one carrying its id, which the router's ACL
        lets only its certificate write (identity.bound_key), else the plain key."""
        return identity.bound_key(self.keys, suffix, self.operator_id) if self.bind_keys else self.keys.key(suffix)

    def _set_key(self, key: bytes) -> None:
        with self._lock:
            self._key = key
            self._key_gen += 1
            self._press_from = time.monotonic()
            stop = self._seq_other[keys.CMD_STOP]  # stops are not signed: one sequence for the session
            self._seq_other.clear()  # the edge counts each grant's signed messages afresh
            self._seq_other[keys.CMD_STOP] = stop
            if self._proc_sender is not None:
                self._proc_sender.write(key=key, key_gen=self._key_gen, press_from=self._press_from)
        self.link.new_grant()  # the loss counts this grant's commands

    def _next_seq(self, suffix: str) -> int:
        with self._lock:
            return self._seq_other[suffix].next()

    def _sign(self, msg: Any, suffix: str) -> bytes:
        """Sign ``msg`` (stamped) with our grant's key, if we hold one; returns the key (empty: unsigned)."""
        key = self._key
        if key:
            auth.sign(key, auth.context(self.keys.robot, suffix), msg)
        return key

    def switch_profile(self, profile: str) -> ControlReply:
        """Ask the edge for another speed profile (renewing the lease); the edge refuses unknown ones."""
        return self.acquire(profile)

    # ------------------------------------------------------------------ safety poses (edge + twin)

    def _plan(self, what: str, suffix: str, *, key: str | None = None, **fields: str) -> ControlReply:
        """A query that the edge's planner answers (its thread plans one at a time): waited for up to
        ``plan_timeout``, long enough for the edge's own refusal of a plan that overran; none by then is said so."""
        try:
            return self._control(suffix, key=key, timeout=self.plan_timeout, **fields)
        except ControlRefused:
            raise
        except RuntimeError as exc:
            if not str(exc).endswith(QUERY_TIMED_OUT):
                raise
            raise ControlRefused(f"the edge's planner did not answer {what} within {self.plan_timeout:g} s (stopped, "
                                 "or busy with earlier plans): try again, or check the edge's log") from None

    def list_poses(self) -> list[dict[str, Any]]:
        """The edge's named safety poses (``control/poses``; detail: a JSON list of {name, ...})."""
        reply = self._plan("the list of poses", keys.CONTROL_POSES)
        if not reply.ok:
            raise ControlRefused(reply.reason)
        return _json_list(reply.detail, "poses")

    def preview_pose(self, name: str, params: Mapping[str, float] | None = None) -> ControlReply:
        """Ask the twin to preview moving to ``name`` (a named pose, or a primitive with its ``params``: ``sweep``
        {width, pitch, lanes, speed}, ``approach:<marker>`` {standoff}, ``retreat``); the reply carries the
        verdict and a token."""
        key = keys.service_key(keys.TWIN, self.keys.robot, keys.TWIN_PREVIEW)
        # Signed for the edge's plan/preview, which the twin asks with our request as it is: the edge plans the
        # owner's previews first (EdgeAgent._signed_by_owner).
        return self._plan(f"the preview of {name!r}", keys.PLAN_PREVIEW, key=key, name=name,
                          params=json.dumps(dict(params)) if params else "")

    def goto_pose(self, name: str, token: str) -> ControlReply:
        """Execute a previewed move (``control/goto`` with the preview's token); the edge decides."""
        reply = self._control(keys.CONTROL_GOTO, name=name, token=token)
        if not reply.ok:
            self.log_event("refused", "goto", f"goto {name!r} refused: {reply.reason}")
        return reply

    # ------------------------------------------------------------------ camera and torch

    def send_servo(self, pan: float | None = None, tilt: float | None = None) -> None:
        """Absolute pan/tilt targets (rad); None keeps an axis."""
        if pan is not None:
            self._servo_target[0] = pan
        if tilt is not None:
            self._servo_target[1] = tilt
        cmd = ServoCommand(operator=self.operator_id, pan=pan, tilt=tilt).stamp(self._next_seq(keys.CMD_SERVO))
        self._sign(cmd, keys.CMD_SERVO)
        self._pub_servo.put(cmd.encode())

    def step_servo(self, dpan: float = 0.0, dtilt: float = 0.0, limit: float = math.pi / 2) -> tuple[float, float]:
        """Move the camera by a step from its current target (the edge clamps to its real range)."""
        if self.servo is not None and not any(self._servo_target):
            self._servo_target = [self.servo.pan_target, self.servo.tilt_target]
        pan = max(-limit, min(limit, self._servo_target[0] + dpan))
        tilt = max(-limit, min(limit, self._servo_target[1] + dtilt))
        self.send_servo(pan if dpan else None, tilt if dtilt else None)
        return pan, tilt

    def set_torch(self, on: bool, brightness: float = 1.0) -> None:
        cmd = TorchCommand(operator=self.operator_id, on=on, brightness=brightness).stamp(self._next_seq(keys.CMD_TORCH))
        self._sign(cmd, keys.CMD_TORCH)
        self._pub_torch.put(cmd.encode())

    def toggle_torch(self) -> bool:
        on = not (self.torch.on if self.torch is not None else False)
        self.set_torch(on)
        return on

    # ------------------------------------------------------------------ what the console shows

    def log_event(self, kind: str, status: str, reason: str) -> None:
        with self._events_lock:  # (Zenoh callbacks, the lease thread and the UI log events: numbers stay in order)
            self.event_count += 1
            self.events.append(Event(time.time(), kind, status, reason, self.event_count))

    def echoes_since(self, mark: int) -> list[Echo]:
        """The echoes that arrived after ``mark`` (an earlier ``echo_count``), as many as are still kept."""
        with self._lock:
            n = min(self.echo_count - mark, len(self.echoes))
            return list(self.echoes)[len(self.echoes) - n:] if n > 0 else []

    def events_since(self, mark: int) -> list[Event]:
        """The events logged after ``mark`` (an earlier ``event_count``), as many as are still kept."""
        n = min(self.event_count - mark, len(self.events))
        return list(self.events)[len(self.events) - n:] if n > 0 else []

    def link_quality(self, now_ns: int | None = None, state_stale_after: float = STATE_STALE_S) -> LinkQuality:
        """The link's figures at ``now_ns`` (monotonic; default now); no robot state for ``state_stale_after`` s
        is a dead downlink (LinkWindow.snapshot)."""
        return self.link.snapshot(time.monotonic_ns() if now_ns is None else now_ns, state_stale_after)

    def release(self) -> ControlReply | None:
        self.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        if not self.owner:
            return None
        self.owner = False
        try:
            return self._control(keys.CONTROL_RELEASE)
        except (ControlRefused, RuntimeError) as exc:
            log.warning("release: %s", exc)
            return None
        finally:
            self._set_key(b"")

    def set_contact(self, on: bool, force: float | None = None) -> ControlReply:
        """Contact mode on (holding ``force`` N along the probe, default the edge's) or off; the edge decides."""
        params = json.dumps({"force": force}) if on and force is not None else ""
        reply = self._control(keys.CONTROL_CONTACT, name="on" if on else "off", params=params)
        self.log_event("action" if reply.ok else "refused", "contact", reply.reason)
        return reply

    def request_arm(self) -> ControlReply:
        return self._control(keys.CONTROL_ARM)

    def emergency_stop(self, reason: str = "operator e-stop") -> None:
        self.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        self.log_event("stop", Status.STOPPED, f"e-stop sent: {reason}")
        self._own_stops.append((time.monotonic(), reason))
        self._pub_stop.put(StopCommand(operator=self.operator_id, reason=reason).stamp(self._next_seq(keys.CMD_STOP)).encode())

    # ------------------------------------------------------------------ the command stream

    @property
    def muted(self) -> bool:
        """True: the sender skips its sends (models a dead link; tests and demo)."""
        return self._muted

    @muted.setter
    def muted(self, value: bool) -> None:
        with self._lock:
            self._muted = bool(value)
            if self._proc_sender is not None:
                self._proc_sender.write(muted=self._muted)

    @property
    def sender_process(self):
        """The sender's ``multiprocessing.Process`` (None with the thread sender or before ``start``)."""
        return self._proc_sender.proc if self._proc_sender is not None else None

    def set_twist(self, linear, angular, deadman: bool, frame: str | None = None) -> None:
        """What the sender sends from its next tick on (linear m/s, angular rad/s) in ``frame`` ("base", "tool":
        the probe's frame about its tip; None keeps the current one)."""
        with self._lock:
            if frame is not None:
                if frame not in TWIST_FRAMES:
                    raise ValueError(f"frame {frame!r}: expected one of {TWIST_FRAMES}")
                self._frame = frame
                if self._proc_sender is not None:
                    self._proc_sender.write(frame=TWIST_FRAMES.index(frame))
            if self._deadman and not deadman:
                self._released_at = time.monotonic()
            elif deadman and not self._deadman:
                self._pressed_at = time.monotonic()
            self._twist = np.concatenate([np.asarray(linear, float), np.asarray(angular, float)])
            self._deadman = bool(deadman)
            if not deadman:
                self._twist[:] = 0.0
            self._heartbeat = time.monotonic()  # the operator's input is alive: it just said what it wants
            if self._proc_sender is not None:  # shared memory only: microseconds, never blocks on the child
                self._proc_sender.write(twist=self._twist, deadman=self._deadman, released_at=self._released_at,
                                        pressed_at=self._pressed_at, heartbeat=self._heartbeat)

    def start(self) -> None:
        """Start the fixed-rate sender, the heartbeat and, while we own the robot, the lease renewal."""
        # Being started is a sign of life: the heartbeat from construction may be older than ui_timeout by now, and
        # the heartbeat thread's first beat comes one period after the sender's first tick.
        self.beat()
        # The heartbeat and the lease renewal first: the sender process's start-up can take seconds on a loaded
        # machine, and the edge's lease runs out meanwhile if nobody renews it.
        fns: list[tuple[str, Any]] = [("heartbeat", self._beat), ("lease", self._renew_lease)]
        if self._proc_sender is None and not self.external_sender:
            fns.insert(0, ("sender", self._sender))
        for name, fn in fns:
            t = threading.Thread(target=fn, name=f"operator-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        if self._proc_sender is not None:
            if self.gil_switch_interval is not None and sys.getswitchinterval() > self.gil_switch_interval:
                sys.setswitchinterval(self.gil_switch_interval)  # keeps the heartbeat and echo matching prompt
            with self._lock:
                self._proc_sender.write(twist=self._twist, deadman=self._deadman, released_at=self._released_at,
                                        muted=self._muted, pressed_at=self._pressed_at, key=self._key,
                                        key_gen=self._key_gen, press_from=self._press_from, state_t=self._state_t,
                                        halted_at=self._halted_at, frame=TWIST_FRAMES.index(self._frame))
            self._proc_sender.start()
            self.sender_priority = f"{self._proc_sender.priority} (process {self._proc_sender.proc.pid})"

    def _on_sender_lost(self, reason: str) -> None:
        """The sender process died (its link thread tells us): no command goes out, so the edge stops the robot
        when its deadman times out. Say so, and start another in a thread of its own (a start takes a second)."""
        if self._stop.is_set():
            return
        self.sender_down = f"{reason}: no command goes out"
        self.log_event("sender", "stopped", f"{reason}: the robot stops")
        threading.Thread(target=self._restart_sender, name="operator-sender-restart", daemon=True).start()

    def _restart_sender(self) -> None:
        """Start the sender process again, going on with the grant's sequence. A press held through the gap is no
        intent to move: only a fresh one after the restart is (``_press_from``; the edge latches a gap over its
        resume bound too). A sender that keeps dying (SENDER_LOSSES times in SENDER_LOSS_WINDOW_S) is not started
        again: the client gives control up, so that a console that can command may take it."""
        assert self._proc_sender is not None
        now = time.monotonic()
        self._sender_losses.append(now)
        if len(self._sender_losses) == SENDER_LOSSES and now - self._sender_losses[0] < SENDER_LOSS_WINDOW_S:
            self._give_up_control(f"the command sender process failed {SENDER_LOSSES} times in "
                                  f"{now - self._sender_losses[0]:.0f} s")
            return
        with self._sender_start:
            if self._stop.is_set():
                return
            with self._lock:
                self._press_from = time.monotonic()
                self._proc_sender.write(press_from=self._press_from)
            try:
                self._proc_sender.start()
            except Exception as exc:  # whatever it is, this console cannot command: say it and let control go
                self._give_up_control(f"the command sender could not be started again ({exc})")
                return
        self.sender_down = ""
        self.log_event("sender", "restarted", "commands go out again: release the deadman and press it again to move")

    def _give_up_control(self, why: str) -> None:
        """This console cannot send commands: it says why and releases control, which another console may take."""
        self.sender_down = f"{why}: control given up; restart the console"
        self.log_event("sender", "failed", self.sender_down)
        self.release()

    def _on_send_record(self, seq: int, t_ns: int, mono: float, grant: int, deadman: bool) -> None:
        """One send by the sender process (called by its link thread, or by an echo arriving first)."""
        self._record_send(seq, t_ns, mono, grant, deadman)

    def _raise_priority(self) -> None:
        """Best effort: make the sender hard to delay. Two things delay a Python thread that wakes on time:
        the GIL, held by a busy UI thread for up to ``sys.getswitchinterval()`` (5 ms by default; lowered here,
        process-wide, to ``gil_switch_interval``), and other processes on a loaded CPU (a real-time policy for
        this thread only, when the OS allows it: root or CAP_SYS_NICE). Measured by benchmarks/bench_sender.py."""
        if self.gil_switch_interval is not None and sys.getswitchinterval() > self.gil_switch_interval:
            sys.setswitchinterval(self.gil_switch_interval)
        self.sender_priority = raise_priority(self.realtime)

    def _sender(self) -> None:
        self._raise_priority()

        def tick() -> bool:
            self._send()
            return not self._stop.is_set()

        try:
            run_fixed_rate(tick, self.rate_hz, self.spin, self._stop.wait)
        except Exception as exc:  # no command goes out any more: the operator must see why, not a silent console
            log.exception("the command sender thread failed")
            self.sender_down = f"the command sender failed ({type(exc).__name__}: {exc}): restart the console"
            self.log_event("sender", "failed", self.sender_down)

    def _send(self, state_t: int | None = None) -> TwistCommand | None:
        """What the command stream sends now (the thread sender's tick, or one send_now), sent."""
        with self._lock:
            out = self._stream.next(time.monotonic(), self._twist, self._deadman, self._released_at,
                                    self._muted, self._heartbeat, self._state_t if state_t is None else state_t,
                                    self._key_gen, self._key, self._pressed_at, self._press_from, self._halted_at,
                                    self._frame)
        if out is None:
            return None
        cmd, payload = out
        self._record_send(cmd.seq, cmd.t, time.monotonic(), int(self._stream.key_gen), cmd.deadman)
        assert self._pub_twist is not None, "the thread sender's publisher"
        self._pub_twist.put(payload)
        return cmd

    @property
    def frame(self) -> str:
        return self._frame

    def set_frame(self, frame: str) -> None:
        """The frame of the twists from now on ("base", or "tool": the probe's frame about its tip)."""
        with self._lock:
            deadman = self._deadman
            twist = self._twist.copy()
        self.set_twist(twist[:3], twist[3:], deadman, frame)

    def send_now(self, linear: Any, angular: Any, deadman: bool, state_t: int | None = None,
                 frame: str | None = None) -> TwistCommand | None:
        """Send one command at once (``external_sender``): the caller's own fixed-rate stream, one message one
        command, never repeated. ``state_t``: the source time (ns) of the newest robot state the operator's screen
        showed (default: the newest this client has). Returns what was sent: None when the stream is quiet (no
        grant, muted, released past the tail), and the deadman reads released under a new grant until a fresh press
        (:class:`CommandStream`)."""
        if not self.external_sender:
            raise RuntimeError("send_now is for a client made with external_sender=True")
        self.set_twist(linear, angular, deadman, frame)
        self.beat()  # the caller's message is the sign of life
        return self._send(state_t)

    def _record_send(self, seq: int, t_ns: int, mono: float, grant: int, deadman: bool) -> None:
        """One command sent: ``seq``, ``t_ns`` and ``deadman`` as on it, ``mono`` its monotonic send instant,
        under ``grant`` (a key_gen)."""
        with self._lock:
            self._sent[(seq, t_ns)] = mono
            while len(self._sent) > 4096:
                self._sent.popitem(last=False)
            self.sent_count += 1
            self.last_sent_ns = t_ns
            self.last_sent_deadman, self.last_sent_at = deadman, mono
            self.send_times.append(mono)
            if len(self.send_times) > 400_000:  # ~2 h at 60 Hz: keep memory bounded on long sessions
                del self.send_times[:100_000]
            current = grant == self._key_gen
        if current:  # (a record of the grant before, read after a new one, is none of the new grant's loss)
            self.link.sent((seq, t_ns), int(mono * 1e9))

    def _beat(self) -> None:
        """The client's heartbeat, every 50 ms: this process is alive and running Python (see CommandStream). A
        thread of its own that never waits on the network: a slow lease reply must not read as a frozen UI. Only
        while the client beats for itself (:attr:`beats_itself`)."""
        while not self._stop.wait(0.05):
            if self._beats_itself:
                self.beat()

    @property
    def beats_itself(self) -> bool:
        """True (a headless client): its process being alive is its sign of life. False (a console): only its
        input's :meth:`set_twist` and :meth:`beat` are, so an input thread that stalls with the deadman held (a
        device read that never returns) releases the deadman after ``ui_timeout``; the client's own threads no
        longer speak for the operator."""
        return self._beats_itself

    @beats_itself.setter
    def beats_itself(self, value: bool) -> None:
        self._beats_itself = bool(value)
        if self._proc_sender is not None:
            self._proc_sender.link_beats = self._beats_itself

    def _renew_lease(self) -> None:
        """While we own the robot, the lease renewal every lease/3 (a query: it may wait up to query_timeout).

        A renewal that fails is tried again every RENEW_RETRY_S for as long as the edge's lease may still run (it
        began no earlier than the sending of our last renewal, or of our last command whose signed echo says the
        edge applied it): a busy edge, a stalled link or another session's answer costs nothing unless it lasts a
        whole lease. Then we give control up: the edge has let it go too (it stops the robot when the lease runs
        out)."""
        failing = False
        while not self._stop.wait(RENEW_RETRY_S if failing else max(0.2, self.lease / 3.0) if self.lease else 0.5):
            if not self.owner:
                failing = False
                continue
            try:
                self.acquire()
                if failing:
                    self.log_event("control", Status.OK, "lease renewed again")
                failing = False
            except (ControlRefused, RuntimeError) as exc:
                left = self._renewed_at + self.lease - time.monotonic()
                if left > 0:
                    if not failing:
                        self.log_event("control", Status.NOT_OWNER, f"lease renewal failed ({exc}): trying again; "
                                       f"control lapses in {left:.1f} s unless a renewal gets through")
                        log.warning("lease renewal failed: %s", exc)
                    failing = True
                    continue
                failing = False
                self.owner = False
                self._set_key(b"")
                self.log_event("control", Status.NOT_OWNER, f"lost control: {exc}")
                log.warning("lost control: %s", exc)

    def beat(self) -> None:
        """The UI is alive: without a beat for ``ui_timeout`` the sender releases the deadman."""
        with self._lock:
            self._heartbeat = time.monotonic()
            if self._proc_sender is not None:
                self._proc_sender.write(heartbeat=self._heartbeat)

    def close(self) -> None:
        self._stop.set()
        if self._proc_sender is not None:
            with self._sender_start:  # (not while a restart starts another)
                self._proc_sender.stop()  # the child first: no orphan, and no twist after close
        for t in self._threads:
            t.join(timeout=1.0)
        try:
            self.release()
        finally:
            if self._token is not None:
                self._token.undeclare()
            for s in self._subs:
                s.undeclare()

    # ------------------------------------------------------------------ state (callbacks only store)

    def _decode(self, cls, sample: zenoh.Sample):
        key = str(sample.key_expr)
        try:
            msg = cls.decode(sample.payload.to_bytes())
        except DecodeError as exc:
            self.rejects.add(key, str(exc))
            if exc.newer:
                if cls in SAFETY_STATE:
                    self.unreadable[cls.__name__] = str(exc)
                self._say_newer(key, f"refused {cls.__name__}: {exc}")
            return None
        if msg.ignored and self.rejects.note_newer(key, f"{cls.__name__} shown without {', '.join(msg.ignored)}"):
            self._say_newer(key, f"{cls.__name__} shown without {', '.join(msg.ignored)}: {NEWER_SENDER}")
        if self.unreadable and cls in SAFETY_STATE:
            self.unreadable.pop(cls.__name__, None)
        return msg

    def _say_newer(self, key: str, what: str) -> None:
        """Tell the operator, once per key, that the edge is newer than this console and what that costs."""
        if key not in self._newer_said:
            self._newer_said.add(key)
            self.log_event("warning", "version", f"{key}: {what}")

    def _from_the_edge(self, msg: Message, suffix: str, key: str) -> bool:
        """While we hold control, the edge signs its robot state, command echoes, safety state and force levels
        with our key: one that does not verify came from another session (on an open router) and is ignored,
        counted in ``rejects``. A forged fresh robot state would have told the edge our screen was live while it
        showed a frozen picture, forged echoes faked the link's latency and "driving", and a forged level 0
        showed green while the real level was red. Without a key (watching, or between grants) nothing can be
        checked: everything is taken, as before."""
        own = self._key
        if not own or auth.verify(own, self._edge_contexts[suffix], msg):
            return True
        self.rejects.add(key, "not signed by the edge for the session that holds control")
        return False

    def _on_robot(self, sample: zenoh.Sample) -> None:
        msg = self._decode(RobotState, sample)
        if msg is not None and self._from_the_edge(msg, keys.STATE_ROBOT, str(sample.key_expr)):
            self.robot_state = msg
            self.robot_state_at = time.monotonic()
            self._state_t = msg.t
            if self._proc_sender is not None:
                with self._lock:
                    self._proc_sender.write(state_t=msg.t)
            self.link.state(msg.seq, time.monotonic_ns())

    def _on_safety(self, sample: zenoh.Sample) -> None:
        msg = self._decode(SafetyStatus, sample)
        if msg is not None and self._from_the_edge(msg, keys.STATE_SAFETY, str(sample.key_expr)):
            self.safety, self.safety_at = msg, time.monotonic()
            if msg.status != self._last_safety_status and msg.status in recovery.REPRESS | recovery.REACQUIRE:
                with self._lock:
                    self._halted_at = time.monotonic()
                    if self._proc_sender is not None:
                        self._proc_sender.write(halted_at=self._halted_at)
            if msg.status != self._last_safety_status:
                self._last_safety_status = msg.status
                if msg.status == Status.STOPPED and msg.reason.startswith(STOP_FROM) and not self._own_stop(msg.reason):
                    self.stopped_by_other_at, self.stopped_by_other = time.monotonic(), msg.reason
                if msg.status in STOP_STATUSES:
                    self.log_event("stop", msg.status, msg.reason or msg.status)
            news = superseded_news(self._last_superseded, msg.superseded) if self._last_superseded is not None else None
            if news:
                self.log_event("warning", "superseded", news)
            self._last_superseded = msg.superseded
            if self._last_forged is not None and msg.forged > self._last_forged:
                self.log_event("warning", "forged", f"the edge refused {msg.forged - self._last_forged} commands in "
                               f"{msg.owner or 'the owner'!r}'s name that its session did not sign")
            self._last_forged = msg.forged

    def _on_force_level(self, sample: zenoh.Sample) -> None:
        msg = self._decode(ForceLevelState, sample)
        if msg is not None and self._from_the_edge(msg, keys.STATE_FORCE_LEVEL, str(sample.key_expr)):
            self.force_level, self.force_level_at = msg, time.monotonic()
            if not msg.stale:
                self.peak_force_level = max(self.peak_force_level, msg.level)

    def _on_force(self, sample: zenoh.Sample) -> None:
        msg = self._decode(ForceSample, sample)
        if msg is not None:
            self.force, self.force_at = msg, time.monotonic()
            self.force_history.append(float(np.linalg.norm(msg.force)))

    def _on_vital(self, sample: zenoh.Sample) -> None:
        msg = self._decode(SensorReading, sample)
        if msg is not None and msg.name and (msg.name in self.vitals or len(self.vitals) < MAX_VITALS):
            self.vitals[msg.name] = (msg, time.monotonic())

    def _on_servo(self, sample: zenoh.Sample) -> None:
        msg = self._decode(ServoState, sample)
        if msg is not None:
            self.servo, self.servo_at = msg, time.monotonic()

    def _on_torch(self, sample: zenoh.Sample) -> None:
        msg = self._decode(TorchState, sample)
        if msg is not None:
            self.torch, self.torch_at = msg, time.monotonic()

    def _on_markers(self, sample: zenoh.Sample) -> None:
        msg = self._decode(Markers, sample)
        if msg is not None:
            news = source_news("perception", self.markers.failure if self.markers is not None else "", msg.failure)
            if news:
                self.log_event("warning" if msg.failure else "info", "perception", news)
            self.markers, self.markers_at = msg, time.monotonic()

    def _on_edge_alive(self, sample: zenoh.Sample) -> None:
        self.edge_alive = sample.kind == zenoh.SampleKind.PUT
        if not self.edge_alive:
            self.log_event("stop", "edge_offline", "edge agent went offline (liveliness lost)")

    def _on_applied(self, sample: zenoh.Sample) -> None:
        now, mono = time.time_ns(), time.monotonic()
        msg = self._decode(AppliedCommand, sample)
        if msg is None or msg.operator != self.operator_id or \
                not self._from_the_edge(msg, keys.STATE_APPLIED, str(sample.key_expr)):
            return
        if self._proc_sender is not None:
            self._proc_sender.drain()  # the send record left the child before the command: take it now
        cmd = (msg.cmd_seq, msg.cmd_t)  # the very command this echo answers, whatever the grant
        with self._lock:
            sent = self._sent.pop(cmd, None)  # one echo per command: a repeat is not a second answer
            if sent is not None and msg.accepted and self._key:
                # The edge signed this with our key (checked above): it held us as its owner when our command
                # arrived, and an authentic command renews the edge's lease as a renewal does (Supervisor): while
                # we drive, a renewal that cannot get through loses nothing.
                self._renewed_at = max(self._renewed_at, sent)
            if sent is not None:
                self.echoes.append(Echo(msg.cmd_seq, msg.cmd_t, now, msg.accepted, msg.status, sent, mono))
                self.echo_count += 1
        if sent is not None:
            self.link.echoed(cmd, int(sent * 1e9), int(mono * 1e9))
            if self.echo_listener is not None:
                self.echo_listener(self.echoes[-1], msg)
        if not msg.accepted:
            self.last_refusal = msg
            # One log line per distinct refusal, not one per command at 60 Hz.
            if (msg.status, msg.reason) != self._last_refusal_key:
                self._last_refusal_key = (msg.status, msg.reason)
                self.log_event("refused", msg.status, msg.reason)
        else:
            self._last_refusal_key = None

    # ------------------------------------------------------------------ what stands between us and motion

    def _own_stop(self, reason: str) -> bool:
        """Whether the edge's reason for a stop (``stop from 'alice': <reason>``) is one this client sent lately."""
        recent = time.monotonic() - 10.0
        return any(t > recent and reason.startswith(f"{STOP_FROM}{self.operator_id!r}") and reason.endswith(f": {sent}")
                   for t, sent in self._own_stops)

    @property
    def halted_at(self) -> float:
        """Monotonic time the edge entered its latest halt that waits for a fresh press or a new grant."""
        return self._halted_at

    def safety_age(self, now: float | None = None) -> float:
        """s since the newest safety status arrived at monotonic ``now`` (default now); inf before the first."""
        return (time.monotonic() if now is None else now) - self.safety_at

    def safety_stale(self, now: float | None = None) -> bool:
        """The newest safety status is older than SAFETY_STALE_S: it no longer says what the edge's state is (the
        edge publishes one 20 times a second)."""
        return self.safety is not None and self.safety_age(now) > SAFETY_STALE_S

    def sending_deadman(self, now: float | None = None) -> bool:
        """Whether the command stream sends the deadman held: its last command said so and went out within
        SENT_LATELY_S. Not the input's deadman: without a grant the stream sends nothing, and under a new grant it
        sends the deadman released until a fresh press (CommandStream)."""
        now = time.monotonic() if now is None else now
        return self.last_sent_deadman and now - self.last_sent_at <= SENT_LATELY_S

    def next_step(self) -> recovery.NextStep:
        """What this operator must do before the robot moves again (:mod:`iorthand_operator.recovery`). A stale
        safety status (safety_stale) is none: an old one said "nothing stands between you and motion" while the
        link or the edge was down. (recovery.next_step gives an unreadable one its reason.)"""
        # Statuses that arrive and cannot be read leave the last one read to go stale too: the cause to say is the
        # console's age, not the link (an edge updated under a running console read "the link is down").
        unreadable = self._cannot_read_safety()
        if self.safety_stale() and not unreadable:
            return recovery.NextStep(recovery.Step.WAIT, f"no safety status from the edge for {self.safety_age():.1f} "
                                                         "s: the link or the edge is down")
        fresh = self._deadman and self._pressed_at > max(self._halted_at, self._press_from)
        old = self._deadman and self._pressed_at < self._press_from
        return recovery.next_step(self.operator_id, self.owner, self.safety, fresh, self.sender_down, old, unreadable)

    def recover(self) -> recovery.NextStep:
        """For a client whose intent is its command (a headless move, a script): take the step itself. It
        acquires control again, or presses the deadman afresh (the stream sends the release the edge waits for
        first). Returns the step that was needed, ``Step.NONE`` when nothing was."""
        step = self.next_step()
        if step.step is recovery.Step.ACQUIRE:
            try:
                self.acquire()
                self.log_event("control", "recovered", f"control taken again ({step.why})")
            except ControlRefused as exc:
                return recovery.NextStep(recovery.Step.WAIT, f"control refused: {exc}")
        elif step.step is recovery.Step.PRESS and self._deadman:
            with self._lock:
                self._pressed_at = time.monotonic()
                if self._proc_sender is not None:
                    self._proc_sender.write(pressed_at=self._pressed_at)
            self.log_event("control", "recovered", f"deadman pressed afresh ({step.why})")
        return step

    def driving(self, within: float = 0.1) -> bool:
        """The edge accepted a command of ours with the deadman held within the last ``within`` s (its limits may
        have clipped the twist, even to zero at a force or workspace limit: that is driving, not a halt)."""
        echo = self.echoes[-1] if self.echoes else None
        # On the monotonic clock: a wall clock stepped back by NTP made every echo look fresh for as long as the
        # step, and a headless motion's checks for a halt or a stop were blind meanwhile.
        return (echo is not None and echo.accepted and echo.status != Status.NO_DEADMAN
                and time.monotonic() - echo.echoed_mono <= within)

    def wait_for_echoes(self, timeout: float = 0.5) -> None:
        """Wait until every command sent so far has its echo (or ``timeout``): counts of sends and echoes taken
        after it agree, even for a command that had just left (a grant's release, sent by the stream itself)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._proc_sender is not None:
                self._proc_sender.drain()
            if self.echo_count >= self.sent_count:
                return
            time.sleep(0.005)

    def wait_for_state(self, timeout: float = 5.0) -> RobotState:
        deadline = time.monotonic() + timeout
        while self.robot_state is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no state from robot {self.keys.robot!r} within {timeout} s")
            time.sleep(0.01)
        return self.robot_state


def _json_list(text: str, what: str) -> list[dict[str, Any]]:
    try:
        data = json.loads(text) if text else []
    except json.JSONDecodeError as exc:
        raise ControlRefused(f"{what}: reply detail is not JSON ({exc})") from None
    if isinstance(data, dict) and isinstance(data.get(what), list):
        data = data[what]
    if not isinstance(data, list):
        raise ControlRefused(f"{what}: expected a JSON list, got {type(data).__name__}")
    return [d if isinstance(d, dict) else {"name": str(d)} for d in data]
