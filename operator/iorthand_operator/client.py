"""The operator's library client: acquire control, stream twists at a fixed rate, watch the robot.

The sender runs in its own thread on an absolute schedule (``rate_hz``, default 60), independent of input
events: the reference system's irregular, event-driven publishing tripped safety stops. Each twist carries a
sequence number, its send time and the deadman flag. When the deadman is released the sender keeps sending
zero twists with ``deadman=False`` for ``release_tail`` seconds, then goes quiet. A liveliness token tells
the edge this operator is alive; the edge releases control when it disappears (a crash, a kill, Ctrl-C).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import zenoh

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    ControlReply,
    ControlRequest,
    DecodeError,
    RejectCounter,
    RobotState,
    SafetyStatus,
    Sequencer,
    StopCommand,
    TwistCommand,
)
from iorthand.transport import publisher, query

log = logging.getLogger("iorthand.operator")


class ControlRefused(RuntimeError):
    """The edge refused a control request; the message is the edge's reason."""


@dataclass
class Echo:
    """One command's round trip: sent by us, applied (or refused) by the edge, echoed back."""

    seq: int
    sent_ns: int
    echoed_ns: int
    accepted: bool
    status: str

    @property
    def rtt_ms(self) -> float:
        return (self.echoed_ns - self.sent_ns) / 1e6


class OperatorClient:
    def __init__(
        self,
        session: zenoh.Session,
        robot_id: str,
        operator_id: str,
        rate_hz: float = 60.0,
        release_tail: float = 0.3,
        query_timeout: float = 2.0,
    ) -> None:
        self.session = session
        self.keys = keys.RobotKeys(robot_id)
        self.operator_id = keys.check_operator_id(operator_id)
        self.rate_hz = rate_hz
        self.release_tail = release_tail
        self.query_timeout = query_timeout
        self.rejects = RejectCounter()
        self._lock = threading.Lock()
        self._twist = np.zeros(6)
        self._deadman = False
        self._released_at = 0.0
        self._seq = Sequencer()
        self._sent: OrderedDict[int, int] = OrderedDict()  # seq → send time (ns), bounded
        self.echoes: list[Echo] = []
        self.sent_count = 0
        self.last_sent_ns = 0
        self.send_times: list[float] = []  # monotonic send instants, for jitter figures
        self.robot_state: RobotState | None = None
        self.safety: SafetyStatus | None = None
        self.last_refusal: AppliedCommand | None = None
        self.owner = False
        self.lease = 0.0
        self.muted = False  # True: the sender skips its sends (models a dead link; tests and demo)
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._pub_twist = publisher(session, self.keys.key(keys.CMD_TWIST))
        self._pub_stop = publisher(session, self.keys.key(keys.CMD_STOP))
        self._token = session.liveliness().declare_token(self.keys.alive_operator(operator_id))
        self._subs = [
            session.declare_subscriber(self.keys.key(keys.STATE_ROBOT), self._on_robot),
            session.declare_subscriber(self.keys.key(keys.STATE_SAFETY), self._on_safety),
            session.declare_subscriber(self.keys.key(keys.STATE_APPLIED), self._on_applied),
        ]

    # ------------------------------------------------------------------ control

    def _control(self, suffix: str, profile: str = "") -> ControlReply:
        payload = ControlRequest(operator=self.operator_id, profile=profile).stamp(self._seq.next()).encode()
        replies = query(self.session, self.keys.key(suffix), payload, timeout=self.query_timeout)
        if not replies:
            raise ControlRefused(f"no answer from robot {self.keys.robot!r} on {suffix} (is its edge agent online?)")
        return ControlReply.decode(replies[0])

    def acquire(self, profile: str = "") -> ControlReply:
        reply = self._control(keys.CONTROL_ACQUIRE, profile)
        if not reply.ok:
            raise ControlRefused(reply.reason)
        self.owner, self.lease = True, reply.lease
        return reply

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

    def request_arm(self) -> ControlReply:
        return self._control(keys.CONTROL_ARM)

    def emergency_stop(self, reason: str = "operator e-stop") -> None:
        self.set_twist(np.zeros(3), np.zeros(3), deadman=False)
        self._pub_stop.put(StopCommand(operator=self.operator_id, reason=reason).stamp(self._seq.next()).encode())

    # ------------------------------------------------------------------ the command stream

    def set_twist(self, linear, angular, deadman: bool) -> None:  # noqa: ANN001 (array-likes)
        """What the sender sends from its next tick on (linear m/s, angular rad/s, base frame)."""
        with self._lock:
            if self._deadman and not deadman:
                self._released_at = time.monotonic()
            self._twist = np.concatenate([np.asarray(linear, float), np.asarray(angular, float)])
            self._deadman = bool(deadman)
            if not deadman:
                self._twist[:] = 0.0

    def start(self) -> None:
        """Start the fixed-rate sender and, while we own the robot, the lease renewal."""
        for name, fn in (("sender", self._sender), ("lease", self._renew_lease)):
            t = threading.Thread(target=fn, name=f"operator-{name}", daemon=True)
            t.start()
            self._threads.append(t)

    def _sender(self) -> None:
        period = 1.0 / self.rate_hz
        next_tick = time.monotonic()
        while not self._stop.is_set():
            with self._lock:
                twist, deadman = self._twist.copy(), self._deadman
                quiet = not deadman and time.monotonic() - self._released_at > self.release_tail
            if not quiet and not self.muted:
                self._send(twist, deadman)
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                # Sleep most of the way, then spin briefly: sleep alone overshoots by ~0.1–1 ms.
                if delay > 0.002:
                    self._stop.wait(delay - 0.0015)
                while time.monotonic() < next_tick:
                    pass
            else:
                next_tick = time.monotonic()  # overran: resume the schedule from now, never burst

    def _send(self, twist: np.ndarray, deadman: bool) -> None:
        cmd = TwistCommand(operator=self.operator_id, linear=twist[:3], angular=twist[3:], deadman=deadman)
        cmd.stamp(self._seq.next())
        payload = cmd.encode()
        with self._lock:
            self._sent[cmd.seq] = cmd.t
            while len(self._sent) > 4096:
                self._sent.popitem(last=False)
            self.sent_count += 1
            self.last_sent_ns = cmd.t
            self.send_times.append(time.monotonic())
        self._pub_twist.put(payload)

    def _renew_lease(self) -> None:
        while not self._stop.wait(max(0.2, self.lease / 3.0) if self.lease else 0.5):
            if self.owner:
                try:
                    self.acquire()
                except (ControlRefused, RuntimeError) as exc:
                    self.owner = False
                    log.warning("lost control: %s", exc)

    def close(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=1.0)
        try:
            self.release()
        finally:
            self._token.undeclare()
            for s in self._subs:
                s.undeclare()

    # ------------------------------------------------------------------ state (callbacks only store)

    def _decode(self, cls, sample: zenoh.Sample):  # noqa: ANN001, ANN202
        try:
            return cls.decode(sample.payload.to_bytes())
        except DecodeError as exc:
            self.rejects.add(str(sample.key_expr), str(exc))
            return None

    def _on_robot(self, sample: zenoh.Sample) -> None:
        msg = self._decode(RobotState, sample)
        if msg is not None:
            self.robot_state = msg

    def _on_safety(self, sample: zenoh.Sample) -> None:
        msg = self._decode(SafetyStatus, sample)
        if msg is not None:
            self.safety = msg

    def _on_applied(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        msg = self._decode(AppliedCommand, sample)
        if msg is None or msg.operator != self.operator_id:
            return
        with self._lock:
            sent = self._sent.get(msg.cmd_seq)
            if sent is not None:
                self.echoes.append(Echo(msg.cmd_seq, sent, now, msg.accepted, msg.status))
                if len(self.echoes) > 100_000:
                    del self.echoes[: len(self.echoes) - 100_000]
        if not msg.accepted:
            self.last_refusal = msg

    def wait_for_state(self, timeout: float = 5.0) -> RobotState:
        deadline = time.monotonic() + timeout
        while self.robot_state is None:
            if time.monotonic() > deadline:
                raise TimeoutError(f"no state from robot {self.keys.robot!r} within {timeout} s")
            time.sleep(0.01)
        return self.robot_state
