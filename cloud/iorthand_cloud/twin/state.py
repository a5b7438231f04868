"""The twin's memory: the latest state of every robot and the snapshot built from it. Pure (no Zenoh).

:meth:`TwinStore.ingest` takes ``(key, payload, receive time)`` as the subscriber queued it, decodes it with
the message class of its key (rejects are counted per robot and key, never acted on), keeps the newest
message per stream and derives safety events (refusals, stops, level changes, online/offline) by comparing
with the previous message. :meth:`TwinStore.snapshot` answers ``iorthand/_twin/<robot>/snapshot``.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass, field

from iorthand import keys
from iorthand.protocol import (
    AppliedCommand,
    DecodeError,
    ForceLevelState,
    ForceSample,
    ImageInfo,
    Markers,
    Message,
    RobotState,
    SafetyStatus,
    ServoState,
    Status,
    StreamInfo,
    TorchState,
    TwinSnapshot,
    VideoFrame,
    message_type_for,
    source_news,
    superseded_news,
)

LEVEL_NAMES = {0: "safe", 1: "caution", 2: "danger"}
MAX_EVENTS = 64


@dataclass
class Event:
    """A safety event for the text log: ``level`` is rerun's (INFO, WARN, ERROR)."""

    robot: str
    t: int  # ns since the epoch (source time when known)
    level: str
    text: str
    # True when ``t`` is this machine's clock (the twin's own news: online/offline, previews), not the edge's:
    # the viewer puts such events on the robot's timeline by its estimate of the edge's clock (viz.py).
    cloud_clock: bool = False


@dataclass
class _Stream:
    latest: Message | None = None
    recv_ns: int = 0
    recv_mono: float = 0.0
    count: int = 0
    rejected: int = 0
    last_reject: str = ""
    # The newest payload not decoded yet (state/robot at 125 Hz per robot: decoded only when drawn or asked
    # for — validation happens before any use, and a malformed one leaves the last valid state in place).
    pending: tuple[bytes, int, float] | None = None


@dataclass
class RobotTwin:
    robot: str
    index: int  # order of discovery: places robots without a configured base side by side
    streams: dict[str, _Stream] = field(default_factory=dict)
    online: bool = False
    seen_alive: bool = False
    online_changed_mono: float = 0.0
    offline_reason: str = "no liveliness token seen yet"
    events: deque[Event] = field(default_factory=lambda: deque(maxlen=MAX_EVENTS))
    q_drawn: list[float] = field(default_factory=lambda: [0.0] * 6)

    def stream(self, suffix: str) -> _Stream:
        s = self.streams.get(suffix)
        if s is None:
            s = self.streams[suffix] = _Stream()
        return s

    def latest(self, suffix: str) -> Message | None:
        s = self.streams.get(suffix)
        return s.latest if s else None


class TwinStore:
    """Thread-safe store of :class:`RobotTwin` per robot id.

    Any participant that may publish robot state can name new robots, and each one costs memory here and in the
    viewer (its model, scene and workspace). So the store follows at most ``max_robots`` robots besides the
    ``configured`` ones, which are always followed: samples of robots beyond that are refused and counted
    (``refused_robots``, ``last_refused``), never stored. A deployment that lists its robots in the twin's
    configuration cannot have them crowded out.
    """

    def __init__(self, clock=time.monotonic, max_robots: int = 64, configured: Collection[str] = ()) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self.robots: dict[str, RobotTwin] = {}
        self.rejected = 0
        self.max_robots = max_robots
        self._configured = frozenset(configured)
        self._unconfigured = 0
        self.refused_robots = 0  # samples and events of robots beyond max_robots
        self.last_refused = ""

    def _robot(self, robot: str) -> tuple[RobotTwin | None, bool]:
        """The robot's twin and whether it is new; None when it would be one robot too many."""
        twin = self.robots.get(robot)
        if twin is not None:
            return twin, False
        configured = robot in self._configured
        if not configured and self._unconfigured >= self.max_robots:
            self.refused_robots += 1
            self.last_refused = robot
            return None, False
        self._unconfigured += not configured
        twin = self.robots[robot] = RobotTwin(robot, len(self.robots))
        return twin, True

    def get(self, robot: str) -> RobotTwin | None:
        with self._lock:
            return self.robots.get(robot)

    def ingest(self, key: str, payload: bytes, recv_ns: int) -> tuple[str, str, Message | None, list[Event], bool]:
        """Decode and store one sample. Returns (robot, suffix, message or None if rejected, new events,
        whether the robot is new)."""
        try:
            robot, suffix = keys.split_key(key)
            keys.check_robot_id(robot)
        except keys.KeyExprError:
            self.rejected += 1
            return "", "", None, [], False
        cls = message_type_for(key)
        msg: Message | None = None
        reason = ""
        if cls is None:
            reason = f"no message type for {suffix}"
        else:
            try:
                msg = cls.decode(payload)
            except DecodeError as exc:
                reason = str(exc)
        with self._lock:
            twin, new = self._robot(robot)
            if twin is None:
                return robot, suffix, None, [], False
            s = twin.stream(suffix)
            if msg is None:
                s.rejected += 1
                s.last_reject = reason
                self.rejected += 1
                return robot, suffix, None, [], new
            s.pending = None  # this one is newer than anything pending
            events = self._events(twin, suffix, s.latest, msg)
            s.latest, s.recv_ns, s.recv_mono = msg, recv_ns, self._clock()
            s.count += 1
            twin.events.extend(events)
            return robot, suffix, msg, events, new

    def ingest_lazy(self, key: str, payload: bytes, recv_ns: int) -> bool:
        """Keep a high-rate sample undecoded (it is decoded by :meth:`resolve` when needed). Returns False
        when the key is not a known robot's: the caller then ingests it normally."""
        try:
            robot, suffix = keys.split_key(key)
        except keys.KeyExprError:
            return False
        with self._lock:
            twin = self.robots.get(robot)
            if twin is None:
                return False
            s = twin.stream(suffix)
            s.pending = (payload, recv_ns, self._clock())
            s.count += 1
            return True

    def _resolve(self, twin: RobotTwin, suffix: str) -> None:
        """Decode a pending payload (caller holds the lock)."""
        s = twin.streams.get(suffix)
        if s is None or s.pending is None:
            return
        payload, recv_ns, recv_mono = s.pending
        s.pending = None
        cls = message_type_for(f"{keys.ROOT}/{twin.robot}/{suffix}")
        try:
            msg = cls.decode(payload) if cls is not None else None
        except DecodeError as exc:
            s.rejected += 1
            s.last_reject = str(exc)
            self.rejected += 1
            return
        if msg is None:
            return
        twin.events.extend(self._events(twin, suffix, s.latest, msg))
        s.latest, s.recv_ns, s.recv_mono = msg, recv_ns, recv_mono

    def set_online(self, robot: str, online: bool, reason: str = "") -> tuple[Event | None, bool]:
        """Liveliness of the robot's edge changed. Returns the event (if a change) and whether the robot is new."""
        if not keys.is_robot_id(robot):
            return None, False
        with self._lock:
            twin, new = self._robot(robot)
            if twin is None:
                return None, False
            if twin.online == online and (twin.seen_alive or not online):
                return None, new
            twin.online = online
            twin.online_changed_mono = self._clock()
            if online:
                twin.seen_alive = True
                twin.offline_reason = ""
                ev = Event(robot, time.time_ns(), "INFO", "edge online (liveliness token alive/edge)", cloud_clock=True)
            else:
                twin.offline_reason = reason or "edge liveliness token gone"
                ev = Event(robot, time.time_ns(), "ERROR", f"edge OFFLINE: {twin.offline_reason}", cloud_clock=True)
            twin.events.append(ev)
            return ev, new

    def add_event(self, robot: str, level: str, text: str) -> Event | None:
        """The event, kept in the robot's list; None for a robot beyond ``max_robots``."""
        with self._lock:
            twin, _ = self._robot(robot)
            if twin is None:
                return None
            ev = Event(robot, time.time_ns(), level, text, cloud_clock=True)
            twin.events.append(ev)
            return ev

    def set_q_drawn(self, robot: str, q: list[float]) -> None:
        with self._lock:
            twin = self.robots.get(robot)
            if twin is not None:
                twin.q_drawn = list(q)

    @staticmethod
    def _events(twin: RobotTwin, suffix: str, prev: Message | None, msg: Message) -> list[Event]:
        """Safety events worth a line in the log: changes only, so a 20 Hz status never floods it."""
        r, t = twin.robot, msg.t
        out: list[Event] = []
        if isinstance(msg, SafetyStatus):
            p = prev if isinstance(prev, SafetyStatus) else None
            if p is None or p.armed != msg.armed:
                out.append(Event(r, t, "INFO" if msg.armed else "WARN", "armed" if msg.armed else f"disarmed: {msg.reason}"))
            if p is None or p.owner != msg.owner:
                out.append(Event(r, t, "INFO", f"control held by {msg.owner!r}" if msg.owner else "no operator holds control"))
            halting = Status.halting(msg.status)
            if p is not None and (p.status, p.reason) != (msg.status, msg.reason) and msg.status not in (Status.OK, Status.IDLE):
                out.append(Event(r, t, "ERROR" if halting else "WARN", f"{msg.status}: {msg.reason}"))
            if p is not None and msg.stops > p.stops and not halting:  # a halting status has its line already
                out.append(Event(r, t, "WARN", f"stop #{msg.stops}: {msg.status} {msg.reason}".strip()))
            if p is not None and msg.forged > p.forged:
                out.append(Event(r, t, "ERROR", f"{msg.forged - p.forged} commands in {msg.owner or 'the owner'!r}'s "
                                 "name without its session's signature refused"))
            news = superseded_news(p.superseded, msg.superseded) if p is not None else None
            if news:
                out.append(Event(r, t, "WARN", news))
        elif isinstance(msg, ForceLevelState):
            p = prev if isinstance(prev, ForceLevelState) else None
            if p is None or (p.level, p.stale) != (msg.level, msg.stale):
                if msg.stale:
                    out.append(Event(r, t, "WARN", "force sensor stale"))
                else:
                    level = ("INFO", "WARN", "ERROR")[msg.level]
                    out.append(Event(r, t, level, f"force level {LEVEL_NAMES[msg.level]} ({msg.quantity} = {msg.value:.1f} N)"))
        elif isinstance(msg, AppliedCommand):
            p = prev if isinstance(prev, AppliedCommand) else None
            if not msg.accepted and (p is None or p.accepted or p.status != msg.status):
                out.append(Event(r, t, "WARN", f"command from {msg.operator!r} refused: {msg.status}: {msg.reason}"))
        elif isinstance(msg, RobotState):
            p = prev if isinstance(prev, RobotState) else None
            if msg.fault and (p is None or p.fault != msg.fault):
                out.append(Event(r, t, "ERROR", f"robot fault: {msg.fault}"))
        elif isinstance(msg, Markers | VideoFrame):
            what = "perception" if isinstance(msg, Markers) else f"{msg.source} video"
            news = source_news(what, prev.failure if isinstance(prev, type(msg)) else "", msg.failure)
            if news:
                out.append(Event(r, t, "WARN" if msg.failure else "INFO", news))
        return out

    def snapshot(self, robot: str, include_images: bool = False, state_timeout: float = 1.0) -> TwinSnapshot:
        now_mono = self._clock()
        now_ns = time.time_ns()
        with self._lock:
            twin = self.robots.get(robot)
            if twin is None:
                return TwinSnapshot(robot=robot, known=False, online=False, reason="the twin has not heard of this robot").stamp(0)
            self._resolve(twin, keys.STATE_ROBOT)
            snap = TwinSnapshot(robot=robot, known=True, online=twin.online, reason=twin.offline_reason)
            streams: list[StreamInfo] = []
            for suffix, s in sorted(twin.streams.items()):
                age = now_mono - s.recv_mono if s.latest is not None else -1.0
                latency = (s.recv_ns - s.latest.t) / 1e9 if s.latest is not None and s.latest.t else -1.0
                streams.append(StreamInfo(key=suffix, age=max(age, -1.0), latency=latency, count=s.count, rejected=s.rejected))
            snap.streams = streams[:32]
            rs = twin.streams.get(keys.STATE_ROBOT)
            if rs is not None and isinstance(rs.latest, RobotState):
                st = rs.latest
                snap.age = max(0.0, now_mono - rs.recv_mono)
                snap.robot_seq, snap.robot_t = st.seq, st.t
                snap.tcp_pose, snap.tcp_speed, snap.q = list(st.tcp_pose), list(st.tcp_speed), list(st.q)
                snap.mode, snap.fault = st.mode, st.fault
                if twin.online and snap.age > state_timeout:
                    snap.reason = f"no robot state for {snap.age:.1f} s"
            snap.q_drawn = list(twin.q_drawn)
            sf = twin.latest(keys.STATE_SAFETY)
            if isinstance(sf, SafetyStatus):
                snap.armed, snap.owner, snap.profile = sf.armed, sf.owner, sf.profile
                snap.safety_status, snap.safety_reason, snap.limits_hit = sf.status, sf.reason, list(sf.limits_hit)
            fs = twin.latest(keys.STATE_FORCE)
            if isinstance(fs, ForceSample):
                snap.force, snap.torque = list(fs.force), list(fs.torque)
            fl = twin.latest(keys.STATE_FORCE_LEVEL)
            if isinstance(fl, ForceLevelState):
                snap.force_value = fl.value
            snap.force_level, snap.force_stale = _newest_force_level(
                sf if isinstance(sf, SafetyStatus) else None, fl if isinstance(fl, ForceLevelState) else None,
                snap.force_level, snap.force_stale)
            sv = twin.latest(keys.STATE_SERVO)
            if isinstance(sv, ServoState):
                snap.servo_pan, snap.servo_tilt = sv.pan, sv.tilt
            tc = twin.latest(keys.STATE_TORCH)
            if isinstance(tc, TorchState):
                snap.torch_on = tc.on
            mk = twin.latest(keys.MARKERS)
            if isinstance(mk, Markers):
                snap.markers, snap.markers_t = list(mk.markers), mk.t
            for suffix in (keys.VIDEO_CAMERA, keys.VIDEO_ULTRASOUND):
                vs = twin.streams.get(suffix)
                if vs is not None and isinstance(vs.latest, VideoFrame):
                    f = vs.latest
                    snap.images.append(ImageInfo(
                        source=suffix.rsplit("/", 1)[-1], seq=f.seq, t=f.t, age=now_mono - vs.recv_mono,
                        width=f.width, height=f.height, encoding=f.encoding, data=f.data if include_images else b"",
                        failure=f.failure,
                    ))
            snap.events = [f"{e.level} {e.text}"[:200] for e in list(twin.events)[-16:]]
        return snap.stamp(0, now_ns)


def _newest_force_level(sf: SafetyStatus | None, fl: ForceLevelState | None, level: int,
                        stale: bool) -> tuple[int, bool]:
    """The force level and its staleness from the newer (by the edge's time ``t``) of the safety status and the
    force level state, both stamped by the same edge. An older one must never overwrite a newer one: a force
    level read a second ago said "safe, fresh" while the safety status of now says "stale". At the same time,
    the more alarming of the two (stale first, then the higher level)."""
    candidates = []
    if sf is not None:
        candidates.append((sf.t, sf.force_stale, sf.force_level))
    if fl is not None:
        candidates.append((fl.t, fl.stale, fl.level))
    if not candidates:
        return level, stale
    _, newest_stale, newest_level = max(candidates)  # by t, then stale (True > False), then level
    return newest_level, newest_stale


__all__ = ["Event", "RobotTwin", "TwinStore"]
